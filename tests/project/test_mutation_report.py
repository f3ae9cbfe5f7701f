"""The arithmetic of the mutation report (``benchmarks/mutation.py``): what counts as detected, what is left out of
the rate, and the interval of a sampled rate. The mutmut run itself is the benchmark command, not a test."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import mutation  # noqa: E402


def rows(module: str, **counts: int) -> list[dict]:
    return [{"name": f"m3t.{module}.f__mutmut_{status}{i}", "module": module, "status": status.replace("_", " ")}
            for status, n in counts.items() for i in range(n)]


def test_timeouts_and_crashes_count_as_detected_and_unchecked_mutants_stay_out_of_the_rate():
    result = mutation.summary(rows("metrics", killed=5, timeout=2, segfault=1, survived=1, no_tests=1, not_checked=5)
                              + rows("body", killed=1, survived=3))
    metrics, body, total = result["modules"]["metrics"], result["modules"]["body"], result["total"]
    assert (metrics["mutants"], metrics["checked"], metrics["not_checked"]) == (15, 10, 5)
    assert metrics["detection_pct"] == 80.0  # (5 killed + 2 timeout + 1 crashed) / 10 checked
    assert (metrics["killed"], metrics["timeout"], metrics["crashed"]) == (5, 2, 1)
    assert metrics["detection_of_tested_pct"] == pytest.approx(88.9)  # the untested mutant left out: 8 / 9
    assert body["detection_pct"] == 25.0 and body["no_tests"] == 0
    assert total["detection_pct"] == pytest.approx(64.3)  # 9 / 14
    assert total["survived"] == 4 and total["other"] == 0


def test_wilson_interval_brackets_the_rate_and_narrows_with_the_sample():
    low, high = mutation.wilson(90, 100)
    assert low < 90.0 < high and (low, high) == (82.6, 94.5)
    wide, narrow = mutation.wilson(9, 10), mutation.wilson(900, 1000)
    assert wide[1] - wide[0] > narrow[1] - narrow[0]
    assert mutation.wilson(0, 0) is None
    assert mutation.wilson(10, 10)[1] == 100.0


def test_mutants_targeted_by_new_tests_are_left_out_of_a_second_rate():
    targeted = rows("fitting", killed=3, survived=1)  # one function: its survivor got a test
    rest = rows("corpora", killed=2, survived=2)
    result = mutation.summary(targeted + rest, targeted={"m3t.fitting.f__mutmut_survived0", "m3t.elsewhere__mutmut_1"})
    assert result["targeted"] == 4 and result["untargeted"]["mutants"] == 4
    assert result["untargeted"]["detection_pct"] == 50.0 and result["total"]["detection_pct"] == 62.5
    assert "untargeted" not in mutation.summary(targeted + rest)


def test_the_sample_is_stable_when_code_changes_add_mutants():
    population = [f"m3t.metrics.f__mutmut_{i}" for i in range(500)]
    sample = mutation.draw(population, 50, seed=0)
    assert len(sample) == 50 == len(set(sample)) and sample == sorted(sample) and set(sample) <= set(population)
    assert set(mutation.draw(population, 20, seed=0)) <= set(sample)  # a smaller sample is a subset
    assert mutation.draw(list(reversed(population)), 50, seed=0) == sample  # the order of the listing is irrelevant
    assert set(mutation.draw(population, 50, seed=1)) != set(sample)
    grown = population + [f"m3t.body.g__mutmut_{i}" for i in range(5)]  # a code change planted 5 more
    assert len(set(mutation.draw(grown, 50, seed=0)) - set(sample)) <= 5
    shrunk = population[10:]  # ... or removed 10
    assert len(set(sample) - set(mutation.draw(shrunk, 50, seed=0))) <= 10


def test_the_score_leaves_out_only_the_survivors_justified_as_equivalent():
    justified = {"m3t.metrics.f__mutmut_survived0": "equivalent: numpy infers that dtype anyway",
                 "m3t.metrics.f__mutmut_survived1": "unreachable: every caller checks it first",
                 "m3t.metrics.f__mutmut_survived2": "wording: a plot title",
                 "m3t.metrics.f__mutmut_killed0": "equivalent: listed, but a test kills it"}
    same = mutation.equivalents(justified)
    assert same == {"m3t.metrics.f__mutmut_survived0", "m3t.metrics.f__mutmut_survived1",
                    "m3t.metrics.f__mutmut_killed0"}
    result = mutation.summary(rows("metrics", killed=7, survived=4, no_tests=1), equivalent=same)
    total = result["total"]
    assert total["detection_pct"] == pytest.approx(58.3)  # 7 / 12: every survivor counts against the rate
    assert total["equivalent"] == 2  # the killed one is not a survivor; the reworded title stays undetected
    assert total["score_pct"] == 70.0 and total["score_ci95"] == mutation.wilson(7, 10)  # 7 / (12 - 2)
    assert mutation.summary(rows("metrics", killed=3))["total"]["equivalent"] == 0


def test_modules_are_packages_top_level_modules_by_name_and_the_dashboard():
    assert mutation.module_of(Path("mutants/m3t/fitting/corpus.py")) == "fitting"
    assert mutation.module_of(Path("m3t/experiment.py")) == "experiment"
    assert mutation.module_of(mutation.ROOT / "mutants" / "m3t" / "sgsa" / "model.py") == "sgsa"
    assert mutation.module_of(Path("mutants/dashboards/sections/runs.py")) == "dashboards"


def test_a_run_over_some_modules_keeps_the_earlier_figures_of_the_others(tmp_path):
    core = {"modules": {"body": {}, "fitting": {}}, "total": {}, "commit": "aaa", "sample": 800}
    out = tmp_path / "mutation.json"
    out.write_text(json.dumps({"detail": core}))
    new = {"modules": {"sgsa": {}, "slr": {}}}
    assert mutation.earlier_runs(new, out) == [core]  # other modules: kept, as measured then
    assert mutation.earlier_runs({"modules": {"body": {}}}, out) == []  # remeasured: the earlier run goes
    out.write_text(json.dumps({"detail": {**new, "commit": "bbb", "earlier": [core]}}))
    kept = mutation.earlier_runs({"modules": {"sgsa": {}}}, out)  # a rerun of the new modules keeps the core run
    assert kept == [core]
    assert mutation.earlier_runs(new, tmp_path / "none.json") == []
    assert mutation.drawn_from({"modules_drawn": ["sgsa", "slr"], "excluded": 300}) == (
        ", drawn from sgsa, slr only; leaving out the 300 mutants of earlier draws (a fresh draw)")
    assert mutation.drawn_from({}) == ""
