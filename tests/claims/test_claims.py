"""The claims table (m3t.claims) on MLflow run records built here: the artifacts have the columns the evaluate
stages write (``per_clip.csv`` of evaluate-smlm: clip_id, group, ..., dtw_jpe_body_m, ...; ``predictions.csv``
of evaluate-slr: variant, clip_id, ..., subset, ..., correct_top1, correct_top5, correct_pair), one row per clip.
"""
from __future__ import annotations

import csv
import dataclasses
import json
import zlib
from pathlib import Path

import numpy as np
import pytest

from m3t.claims.definitions import CLAIMS
from m3t.claims.report import claims_markdown, stability_line, write_claims
from m3t.claims.verdicts import claims_table, judge, stability
from m3t.experiment import RunRecord

CLIPS = [f"asl-syn-{i:04d}" for i in range(12)]


def _write(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def smlm_run(tmp: Path, run_id: str, objective: bool, seed: int, body: np.ndarray, version: str = "v1",
             start: int = 0, steps: str | None = None) -> RunRecord:
    folder = tmp / run_id
    _write(folder / "per_clip.csv", [{"clip_id": c, "group": "synthetic/ASL-SYN", "steps": 9, "stopped": 1.0,
                                      "dtw_jpe_body_m": float(v), "dtw_jpe_hand_m": float(v) / 2}
                                     for c, v in zip(CLIPS, body)])
    _write(folder / "backtranslation.csv", [{"clip_id": c, "language": "ASL-SYN", "frames": 40, "reference": "i read",
                                            "hypothesis": "i read", "bleu4": 0.0, "rouge_l": 30.0 + float(v)}
                                           for c, v in zip(CLIPS[:4], body)])
    return RunRecord(run_id, "evaluate-smlm", start, "FINISHED", {"smlm_train.seed": str(seed)}, {}, folder,
                     {"translation_objective": str(objective), "seed": str(seed), "data_version": version,
                      **({} if steps is None else {"translation_steps": steps})})


def smlm_runs(tmp: Path, seeds: int, gain: float, version: str = "v1") -> list[RunRecord]:
    g = np.random.default_rng(0)
    out = []
    for s in range(seeds):
        base = 3.0 + g.random(len(CLIPS))
        out.append(smlm_run(tmp, f"po{s}{version}", False, s, base, version, start=10 * s))
        out.append(smlm_run(tmp, f"pt{s}{version}", True, s, base - gain + 0.01 * g.standard_normal(len(CLIPS)),
                            version, start=10 * s + 1))
    return sorted(out, key=lambda r: -r.start_time)  # newest first, as fetch_runs gives them


def only(key: str):
    return tuple(c for c in CLAIMS if c.key == key)


def test_three_seeds_with_a_clear_gain_reproduce_and_one_seed_is_inconclusive(tmp_path):
    rows = claims_table(smlm_runs(tmp_path, 3, gain=0.5), claims=only("smlm-objective-dtw-body"))
    row = rows[0]
    assert row["verdict"] == "reproduced" and row["seeds"] == ["0", "1", "2"] and row["units"] == len(CLIPS)
    assert row["value"] == pytest.approx(-0.5, abs=0.02) and row["interval95"][1] < 0
    assert sorted(row["runs_a"]) == ["po0v1", "po1v1", "po2v1"] and sorted(row["runs_b"]) == ["pt0v1", "pt1v1", "pt2v1"]
    worse = claims_table(smlm_runs(tmp_path / "w", 3, gain=-0.5), claims=only("smlm-objective-dtw-body"))[0]
    assert worse["verdict"] == "not reproduced"
    one = claims_table(smlm_runs(tmp_path / "one", 1, gain=0.5), claims=only("smlm-objective-dtw-body"))[0]
    assert one["verdict"] == "inconclusive" and "1 seed(s) < 3" in one["note"]
    assert claims_table(smlm_runs(tmp_path / "one", 1, gain=0.5), min_seeds=1,
                        claims=only("smlm-objective-dtw-body"))[0]["verdict"] == "reproduced"


def test_a_verdict_that_one_half_of_the_seeds_gives_and_the_other_does_not_is_reported_as_a_flip(tmp_path):
    # seeds 0-1: the objective helps by 0.5 on every clip; seeds 2-3: it does nothing. Pooled, the gain is real
    # on average; judged on each half, the first says reproduced and the second inconclusive: a flip
    g = np.random.default_rng(1)
    records = []
    for s in range(4):
        base = 3.0 + g.random(len(CLIPS))
        gain = 0.5 if s < 2 else 0.0
        records.append(smlm_run(tmp_path, f"po{s}", False, s, base, "v1", start=10 * s))
        records.append(smlm_run(tmp_path, f"pt{s}", True, s, base - gain + 0.01 * g.standard_normal(len(CLIPS)), "v1",
                                start=10 * s + 1))
    records.sort(key=lambda r: -r.start_time)
    row = claims_table(records, claims=only("smlm-objective-dtw-body"))[0]
    assert row["halves"]["seeds"] == [["0", "1"], ["2", "3"]]
    assert row["halves"]["verdicts"] == ["reproduced", "inconclusive"]
    summary = stability([row])
    assert summary["compared"] == 1 and summary["flipped"] == 1 and summary["share_flipped"] == 1.0
    assert "1 of 1 claims flip" in stability_line(summary) and "reproduced / inconclusive" in stability_line(summary)
    steady = claims_table(smlm_runs(tmp_path / "steady", 4, gain=0.5), claims=only("smlm-objective-dtw-body"))[0]
    assert steady["halves"]["verdicts"] == ["reproduced", "reproduced"] and stability([steady])["flipped"] == 0
    # the halves are drawn after the row's own interval: judging them leaves the interval as it was
    alone = judge(only("smlm-objective-dtw-body")[0],
                  only("smlm-objective-dtw-body")[0].collect(records), 3,
                  np.random.default_rng([0, zlib.crc32(b"smlm-objective-dtw-body")]))
    assert alone["interval95"] == row["interval95"]
    one = claims_table(smlm_runs(tmp_path / "one", 1, gain=0.5), claims=only("smlm-objective-dtw-body"))[0]
    assert one["halves"] is None and "no claim has 2 seeds" in stability_line(stability([one]))


def test_runs_on_other_shards_are_never_paired(tmp_path):
    # the newest runs are on data v2 (production only missing there); v1 runs of both variants must not be used
    old = smlm_runs(tmp_path, 3, gain=0.5, version="v1")
    new = [dataclasses.replace(r, start_time=r.start_time + 1000)
           for r in smlm_runs(tmp_path, 3, gain=0.5, version="v2") if r.tags["translation_objective"] == "True"]
    records = sorted(old + new, key=lambda r: -r.start_time)
    row = claims_table(records, claims=only("smlm-objective-dtw-body"))[0]
    assert row["verdict"] == "not run" and "with and without the translation objective" in row["note"]
    untagged = [dataclasses.replace(r, tags={k: v for k, v in r.tags.items() if k != "data_version"}) for r in old]
    row = claims_table(untagged, claims=only("smlm-objective-dtw-body"))[0]
    assert row["verdict"] == "not run" and "data_version" in row["note"]


def test_ground_truth_ceiling_pairs_each_seed_with_the_one_ground_truth_run(tmp_path):
    records = smlm_runs(tmp_path, 3, gain=0.5)
    gt = tmp_path / "gt"
    _write(gt / "per_clip.csv", [{"clip_id": c, "language": "ASL-SYN", "frames": 40, "reference": "i read",
                                  "hypothesis": "i read", "bleu4": 0.0, "rouge_l": 80.0} for c in CLIPS[:4]])
    records.append(RunRecord("gt", "evaluate-backtranslation", 0, "FINISHED", {}, {}, gt,
                             {"source": "ground-truth", "split": "test", "data_version": "v1"}))
    row = claims_table(records, claims=only("bt-ground-truth-ceiling"))[0]
    assert row["verdict"] == "reproduced" and row["units"] == 4 and row["runs_b"] == ["gt"] * 3
    assert row["mean_b"] == pytest.approx(80.0)


def test_recognition_claims_read_pair_hits_and_the_chance_band(tmp_path):
    def slr(seed: int, face_less_pair: list[int]) -> RunRecord:
        folder = tmp_path / f"slr{seed}"
        rows = []
        for i, hit in enumerate(face_less_pair):
            for variant, pair_hit in (("full", 1), ("no_face", hit)):
                rows.append({"variant": variant, "clip_id": f"iso-c{i}", "label": i, "gloss": "X",
                             "subset": "confusing",
                             "pair": f"p{i // 2}", "predicted_label": i, "predicted_gloss": "X", "top5_labels": "",
                             "correct_top1": pair_hit, "correct_top5": 1, "correct_pair": pair_hit, "frames": 40,
                             "kept_start": 0, "kept_end": 40})
        for i in range(6):
            for variant in ("full", "no_face"):
                rows.append({"variant": variant, "clip_id": f"iso-n{i}", "label": 20 + i, "gloss": "Y",
                             "subset": "normal", "pair": "", "predicted_label": 20 + i, "predicted_gloss": "Y",
                             "top5_labels": "", "correct_top1": 1, "correct_top5": 1, "correct_pair": "",
                             "frames": 40, "kept_start": 0, "kept_end": 40})
        _write(folder / "predictions.csv", rows)
        return RunRecord(f"slr{seed}", "evaluate-slr", seed, "FINISHED",
                         {"full.slr_train.seed": str(seed), "no_face.slr_train.seed": str(seed)}, {}, folder,
                         {"data_version": "v1"})

    half = [1, 0] * 100  # the face-less probe picks the right twin half the time: chance
    records = [slr(s, half) for s in range(3)]
    rows = {r["key"]: r for r in claims_table(records, claims=only("slr-face-confusing") + only("slr-face-chance")
                                              + only("slr-face-normal"))}
    assert rows["slr-face-chance"]["value"] == pytest.approx(50.0)
    assert rows["slr-face-chance"]["verdict"] == "reproduced"  # 200 clips: the interval stays inside 50 +- 10
    few = {r["key"]: r for r in claims_table([slr(s, [1, 0] * 10) for s in range(3)], claims=only("slr-face-chance"))}
    assert few["slr-face-chance"]["verdict"] == "inconclusive"  # 20 clips: +-20 points, wider than the band
    assert rows["slr-face-confusing"]["verdict"] == "reproduced"  # with face 100 %, without 50 %
    assert rows["slr-face-normal"]["verdict"] == "reproduced" and rows["slr-face-normal"]["value"] == 0.0
    always = [slr(s, [1] * 40) for s in range(3)]  # the face-less probe still separates every pair
    rows = {r["key"]: r for r in claims_table(always, claims=only("slr-face-chance"))}
    assert rows["slr-face-chance"]["verdict"] == "not reproduced"


def test_write_claims_lists_every_claim_with_run_ids_or_what_to_run(tmp_path):
    records = smlm_runs(tmp_path, 3, gain=0.5)
    rows = write_claims(records, tmp_path / "out")
    saved = json.loads((tmp_path / "out" / "claims.json").read_text())
    assert [r["key"] for r in saved["claims"]] == [c.key for c in CLAIMS] == [r["key"] for r in rows]
    assert saved["min_seeds"] == 3 and "SOKE" in saved["motion_definition"]
    table = (tmp_path / "out" / "claims.md").read_text()
    assert "po0v1"[:8] in table and "| reproduced |" in table
    assert "not run: no train-tokenizers run: run `dvc repro train-tokenizers`" in table
    assert table == claims_markdown(rows, 3)


def test_codebook_claims_pair_runs_by_seed_at_one_width(tmp_path):
    def run(run_id: str, quantizer: str, batch: int, seed: int, use: float, width: int = 128, start: int = 0):
        return RunRecord(run_id, "train-tokenizers", start, "FINISHED", {}, {"body/utilisation_pct": use}, tmp_path,
                         {"quantizer": quantizer, "batch_size": str(batch), "seed": str(seed), "width": str(width),
                          "data_version": "v1"})

    records = [run(f"f{s}", "fsq", 16, s, 60.0 + s, start=10 + s) for s in range(3)]
    records += [run(f"v{s}", "vq", 16, s, 40.0 + 2 * s, start=s) for s in range(3)]
    records += [run("wide", "vq", 16, 0, 99.0, width=1024, start=-1)]  # another width: never paired
    records.sort(key=lambda r: -r.start_time)
    row = claims_table(records, claims=only("tokenizer-utilisation-body"))[0]
    assert row["unit"] == "seed" and row["units"] == 3 and row["seeds"] == ["0", "1", "2"]
    assert row["mean_a"] == pytest.approx(42.0) and row["mean_b"] == pytest.approx(61.0)
    assert row["verdict"] == "reproduced" and "wide" not in row["runs_a"]
    assert row["std_a"] == pytest.approx(float(np.std([40.0, 42.0, 44.0])))


def test_a_claims_interval_does_not_depend_on_the_other_claims_judged(tmp_path):
    # one generator per claim, seeded from its key: judged alone, after another claim or in reverse order, the
    # interval is the same (a shared generator gave each claim the draws its predecessors left)
    records = smlm_runs(tmp_path, 3, gain=0.1)
    keys = ("smlm-objective-dtw-body", "smlm-objective-dtw-hand")
    alone = claims_table(records, claims=only(keys[1]))[0]
    both = {r["key"]: r for r in claims_table(records, claims=only(keys[0]) + only(keys[1]))}
    reverse = {r["key"]: r for r in claims_table(records, claims=only(keys[1]) + only(keys[0]))}
    assert alone["interval95"] == both[keys[1]]["interval95"] == reverse[keys[1]]["interval95"]
    assert both[keys[0]]["interval95"] == reverse[keys[0]]["interval95"]
    other_seed = claims_table(records, claims=only(keys[1]), seed=1)[0]
    assert other_seed["interval95"] != alone["interval95"]  # the draws do come from the seed


def test_the_objective_at_equal_production_updates_pairs_added_steps_runs_with_production_only(tmp_path):
    """translation_steps added (the objective's steps on top of production's) is its own variant: it answers the
    equal-updates claim, never the equal-epochs one; runs without the tag (older code) count as shared."""
    runs = smlm_runs(tmp_path, 3, gain=0.5)  # shared (untagged) runs with a clear gain
    g = np.random.default_rng(1)
    added = [smlm_run(tmp_path, f"pa{s}", True, s, 3.0 + g.random(len(CLIPS)) + 1.0, steps="added", start=100 + s)
             for s in range(3)]  # added steps: worse than production only
    records = sorted(runs + added, key=lambda r: -r.start_time)
    shared = claims_table(records, claims=only("smlm-objective-dtw-body"))[0]
    assert shared["verdict"] == "reproduced" and sorted(shared["runs_b"]) == ["pt0v1", "pt1v1", "pt2v1"]
    equal = claims_table(records, claims=only("smlm-objective-dtw-body-equal-updates"))[0]
    assert sorted(equal["runs_a"]) == ["po0v1", "po1v1", "po2v1"] and sorted(equal["runs_b"]) == ["pa0", "pa1", "pa2"]
    assert equal["verdict"] == "not reproduced" and equal["b"] == "production + translation (added steps)"
    missing = claims_table(runs, claims=only("smlm-objective-bt-equal-updates"))[0]
    assert missing["verdict"] == "not run" and "translation_steps=added" in missing["note"]


def sgsa_run(tmp: Path, run_id: str, adjacency: int, seed: int, start: int, systems: dict[str, float],
             counter: str = "predicted") -> RunRecord:
    """An evaluate-sgsa run: ``per_clip.csv`` with one row per (system, clip) of the test split, as
    m3t.sgsa.pipeline writes it (clip_id, system, split, ..., dtw_jpe_body_m)."""
    folder = tmp / run_id
    _write(folder / "per_clip.csv", [{"clip_id": c, "system": system, "split": "test", "frames": 40,
                                      "dtw_jpe_body_m": value + 0.01 * i}
                                     for system, value in systems.items() for i, c in enumerate(CLIPS)])
    _write(folder / "backtranslation.csv", [{"clip_id": c, "system": system, "split": "test", "language": "ASL-SYN",
                                             "rouge_l": 100.0 - 10.0 * value + i}
                                            for system, value in systems.items() for i, c in enumerate(CLIPS[:4])])
    return RunRecord(run_id, "evaluate-sgsa", start, "FINISHED",
                     {"sgsa.decoder_layers": "2", "sgsa.temporal_adjacency": str(adjacency)}, {}, folder,
                     {"variant": f"sgsa L=2 N={adjacency or 'inf'}", "seed": str(seed), "counter": counter,
                      "data_version": "v1"})


def test_sgsa_system_claims_read_the_finite_adjacency_runs_of_the_models_own_counters_in_any_order(tmp_path):
    """The study's N = inf runs may finish after the N = 1 ones (DVC restores what it ran before), and runs with
    ground-truth lengths may be the newest: the PT-vs-SGSA claim still pairs the N = 1 runs' own-counter scores."""
    finite = [sgsa_run(tmp_path, f"n1-{s}", 1, s, 10 + s, {"pt": 3.0, "sgsa": 2.0, "smlm": 1.0}) for s in range(3)]
    inf = [sgsa_run(tmp_path, f"ninf-{s}", 0, s, 20 + s, {"sgsa": 2.5, "smlm": 1.0}) for s in range(3)]
    truth = [sgsa_run(tmp_path, f"gt-{s}", 1, s, 30 + s, {"pt": 1.0, "sgsa": 9.0}, "ground_truth") for s in range(3)]
    records = sorted(finite + inf + truth, key=lambda r: -r.start_time)
    row = claims_table(records, claims=only("sgsa-vs-pt-dtw"))[0]
    assert row["verdict"] == "reproduced" and sorted(row["runs_a"]) == [r.run_id for r in finite]
    assert row["mean_a"] == pytest.approx(3.055) and row["mean_b"] == pytest.approx(2.055)
    adjacency = claims_table(records, claims=only("sgsa-adjacency"))[0]  # ROUGE-L: N = inf 75 against N = 1 80
    assert sorted(adjacency["runs_a"]) == [r.run_id for r in inf] and sorted(adjacency["runs_b"]) == [
        r.run_id for r in finite]
    assert (adjacency["mean_a"], adjacency["mean_b"]) == (pytest.approx(76.5), pytest.approx(81.5))
    with pytest.raises(Exception, match="ground-truth lengths"):
        only("sgsa-vs-pt-dtw")[0].collect(truth)
