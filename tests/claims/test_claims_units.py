"""Judging one claim (:func:`m3t.claims.verdicts.judge`, :func:`~m3t.claims.verdicts.seed_halves`) and its table
cells (:mod:`m3t.claims.report`) on hand-made samples whose means, spreads and verdicts are worked out by hand.
Written to pin behaviours that mutation testing found unchecked."""
from __future__ import annotations

import numpy as np
import pytest

from m3t.claims.collectors import Sample
from m3t.claims.definitions import Claim
from m3t.claims.report import interval_cell, means_cell, stability_line
from m3t.claims.verdicts import judge, seed_halves, stability


def claim(**options) -> Claim:
    return Claim("k", "src", "B beats A", "1 -> 2", "metric (unit)", "A", "B", collect=lambda records: None, **options)


def rng() -> np.random.Generator:
    return np.random.default_rng(0)


# per seed (rows) and clip (columns): A's seed means 12 and 14, B's 1 and 2; seed-averaged, B - A is -10.5 on clip
# 0 and -12.5 on clip 1. Any resample of seeds and clips lies in [1 - 15, 2 - 11] = [-14, -9]
A = np.array([[11.0, 13.0], [13.0, 15.0]])
B = np.array([[1.0, 1.0], [2.0, 2.0]])


def test_a_row_holds_the_means_the_seeds_spread_the_difference_and_its_verdict():
    row = judge(claim(), Sample(A, B, ["0", "1"], ["ra0", "ra1"], ["rb0", "rb1"]), 2, rng())
    assert (row["mean_a"], row["mean_b"]) == pytest.approx((13.0, 1.5))
    assert (row["std_a"], row["std_b"]) == pytest.approx((1.0, 0.5))  # population std of the seeds' means
    assert row["value"] == pytest.approx(-11.5) and row["compared"] == "B - A"
    low, high = row["interval95"]
    assert -14.0 <= low <= -11.5 <= high <= -9.0
    assert row["verdict"] == "reproduced" and row["note"] == "" and row["band"] is None
    assert (row["units"], row["unit"], row["seeds"]) == (2, "clip", ["0", "1"])
    assert (row["runs_a"], row["runs_b"]) == (["ra0", "ra1"], ["rb0", "rb1"])
    higher = judge(claim(lower_is_better=False), Sample(A, B, ["0", "1"], [], []), 2, rng())
    assert higher["verdict"] == "not reproduced"
    few = judge(claim(), Sample(A, B, ["0", "1"], [], []), 3, rng())
    assert few["verdict"] == "inconclusive" and few["note"] == "2 seed(s) < 3: the verdict needs the seeds' spread"


def test_a_band_claim_reads_b_alone_or_the_difference():
    alone = judge(claim(within=(1.5, 1.0), of="b"), Sample(A, B, ["0", "1"], [], []), 2, rng())
    assert alone["compared"] == "B" and alone["value"] == pytest.approx(1.5) and alone["band"] == [1.5, 1.0]
    assert alone["verdict"] == "reproduced"  # B's interval lies within [1, 2] (its values are 1 and 2)
    assert 1.0 <= alone["interval95"][0] <= alone["interval95"][1] <= 2.0
    outside = judge(claim(within=(10.0, 1.0), of="b"), Sample(A, B, ["0", "1"], [], []), 2, rng())
    assert outside["verdict"] == "not reproduced"
    diff = judge(claim(within=(-11.5, 3.0)), Sample(A, B, ["0", "1"], [], []), 2, rng())  # [-14.5, -8.5]
    assert diff["compared"] == "B - A" and diff["value"] == pytest.approx(-11.5) and diff["verdict"] == "reproduced"
    assert judge(claim(within=(0.0, 1.0)), Sample(A, B, ["0", "1"], [], []), 2, rng())["verdict"] == "not reproduced"


def test_per_run_statistics_resample_the_seeds_and_report_their_spread():
    a, b = np.array([[10.0, 12.0, 14.0]]), np.array([[20.0, 20.0, 23.0]])  # unit "seed": (1, R)
    row = judge(claim(lower_is_better=False), Sample(a, b, ["0", "1", "2"], [], [], unit="seed"), 3, rng())
    assert row["units"] == 3 and row["unit"] == "seed"
    assert row["std_a"] == pytest.approx(np.sqrt(8 / 3)) and row["std_b"] == pytest.approx(np.sqrt(2.0))
    assert row["value"] == pytest.approx(9.0) and row["verdict"] == "reproduced"


def test_seed_halves_split_first_half_and_rest_along_the_seed_axis():
    four = np.array([[1.0, 1.0], [1.0, 1.0], [3.0, 3.0], [3.0, 3.0]])
    # the first two seeds: B below A (reproduced); the last two: B above A (not reproduced)
    halves = seed_halves(claim(), Sample(four, np.full((4, 2), 2.0), ["0", "1", "2", "3"], [], []), rng())
    assert halves == {"seeds": [["0", "1"], ["2", "3"]], "verdicts": ["not reproduced", "reproduced"]}
    three = seed_halves(claim(), Sample(np.zeros((3, 2)), np.ones((3, 2)), ["0", "1", "2"], [], []), rng())
    assert three["seeds"] == [["0"], ["1", "2"]]  # an odd count: the rest has one more
    per_run = Sample(np.array([[1.0, 1.0, 3.0, 3.0]]), np.full((1, 4), 2.0), ["0", "1", "2", "3"], [], [], "seed")
    assert seed_halves(claim(), per_run, rng())["verdicts"] == ["not reproduced", "reproduced"]
    assert seed_halves(claim(), Sample(A[:1], B[:1], ["0"], [], []), rng()) is None


def test_stability_counts_the_rows_whose_halves_disagree():
    rows = [{"key": "x", "claim": "X", "halves": {"seeds": [["0"], ["1"]], "verdicts": ["reproduced", "inconclusive"]}},
            {"key": "y", "claim": "Y", "halves": {"seeds": [["0"], ["1"]], "verdicts": ["reproduced", "reproduced"]}},
            {"key": "z", "claim": "Z", "halves": None}, {"key": "n", "claim": "N"}]
    summary = stability(rows)
    assert (summary["compared"], summary["flipped"], summary["share_flipped"]) == (2, 1, 0.5)
    assert summary["flips"] == [{"key": "x", "claim": "X", "verdicts": ["reproduced", "inconclusive"],
                                 "seeds": [["0"], ["1"]]}]
    assert stability_line(summary) == ("Stability: judged again on two disjoint halves of their seeds (first half, "
                                       "rest), 1 of 2 claims flip their verdict (50 %): X (reproduced / inconclusive).")
    steady = stability(rows[1:])
    assert steady["share_flipped"] == 0.0 and stability_line(steady).endswith("flip their verdict (0 %).")
    assert stability([])["share_flipped"] is None


def test_the_table_cells_by_hand():
    row = {"a": "VQ", "b": "FSQ", "mean_a": 1.0, "std_a": 0.25, "mean_b": 2.0, "std_b": 0.5, "value": 1.0,
           "interval95": [0.5, 1.5], "band": [1.0, 0.75]}
    assert means_cell(row, str, lambda v: f"{v:.2f}") == "VQ 1.0 +- 0.25 -> FSQ 2.0 +- 0.50"
    assert interval_cell(row, str) == "1.0 [0.5, 1.5] (band 1 +- 0.75)"
    assert interval_cell({**row, "band": None}, str) == "1.0 [0.5, 1.5]"


def test_write_claims_judges_with_the_seeds_it_is_given(tmp_path, monkeypatch):
    import json

    from m3t.claims import report

    seen = []
    monkeypatch.setattr(report, "claims_table", lambda records, min_seeds: seen.append(min_seeds) or [])
    assert report.write_claims([], tmp_path, min_seeds=5) == [] and seen == [5]
    assert json.loads((tmp_path / "claims.json").read_text())["min_seeds"] == 5
    assert "Verdicts need >= 5 seeds." in (tmp_path / "claims.md").read_text()


# ------------------------------------------------------------------------------------ reading runs (collectors)
def _record(run_id, stage, tags=None, params=None, metrics=None, artifact_dir=None, status="FINISHED", start=0):
    from m3t.experiment import RunRecord

    return RunRecord(run_id, stage, start, status, params or {}, metrics or {}, artifact_dir, tags or {})


def _csv(folder, name, text):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(text, encoding="utf-8")
    return folder


def test_rows_values_and_alignment_of_per_clip_files(tmp_path):
    """A run's CSV artifact as rows (a missing one names the run, its stage and the file); the values of one
    column on the rows matching every ``where`` (empty cells skipped); A and B aligned on every clip either side
    scored, NaN where a side has none."""
    from m3t.claims.collectors import MissingRuns, _aligned, _rows, _values

    folder = _csv(tmp_path / "r1", "per_clip.csv", 'clip_id,system,x\nc2,pt,1.5\nc1,pt,\nc1,sgsa,"2"\nc3,pt,4\n')
    rows = _rows(_record("r1", "evaluate-sgsa", artifact_dir=folder), "per_clip.csv")
    assert rows[0] == {"clip_id": "c2", "system": "pt", "x": "1.5"} and len(rows) == 4
    for record in (_record("r2", "evaluate-sgsa", artifact_dir=folder), _record("r2", "evaluate-sgsa")):
        with pytest.raises(MissingRuns) as err:
            _rows(record, "other.csv")
        assert str(err.value) == "run r2 (evaluate-sgsa) has no artifact other.csv; rerun that stage"
    assert _values(rows, "x", system="pt") == {"c2": 1.5, "c3": 4.0}
    assert _values(rows, "x") == {"c2": 1.5, "c1": 2.0, "c3": 4.0}
    assert _values(rows, "missing") == {} and _values(rows, "x", system="pt", clip_id="c3") == {"c3": 4.0}
    a, b = _aligned([({"c2": 1.0, "c1": 2.0}, {"c1": 5.0}), ({"c3": 3.0}, {})])
    assert a.shape == b.shape == (2, 3) and a.dtype == np.float64
    np.testing.assert_array_equal(a, [[2.0, 1.0, np.nan], [np.nan, np.nan, 3.0]])
    np.testing.assert_array_equal(b, [[5.0, np.nan, np.nan], [np.nan] * 3])
    empty_a, empty_b = _aligned([({}, {})])
    assert empty_a.shape == empty_b.shape == (1, 0)


def test_a_stage_compares_only_finished_runs_of_one_data_version():
    from m3t.claims.collectors import MissingRuns, _seed, _smlm_variant, _stage

    runs = [_record("n0", "s", {"data_version": "v2"}), _record("f", "s", {"data_version": "v2"}, status="FAILED"),
            _record("n1", "s", {"data_version": "v1"}), _record("n2", "s"), _record("x", "t", {"data_version": "v2"}),
            _record("n3", "s", {"data_version": "v2"})]
    assert [r.run_id for r in _stage(runs, "s")] == ["n0", "n3"]  # the newest tagged run's version
    assert [r.run_id for r in _stage(runs, "s", "v1")] == ["n1"]
    assert _stage(runs, "s", "v9") == []
    with pytest.raises(MissingRuns) as err:
        _stage(runs, "u")
    assert str(err.value) == "no u run: run `dvc repro u`"
    with pytest.raises(MissingRuns) as err:
        _stage([_record("old", "u")], "u")
    assert str(err.value) == ("no u run carries a data_version tag (runs of earlier code): run `dvc repro u`")
    assert _seed(_record("a", "s", {"seed": "3"})) == "3" and _seed(_record("a", "s")) == "?"
    assert _smlm_variant(_record("a", "s", {"translation_objective": "False", "translation_steps": "added"})) == "off"
    assert _smlm_variant(_record("a", "s", {"translation_objective": "True", "translation_steps": "added"})) == "added"
    assert _smlm_variant(_record("a", "s")) == "shared"


def test_collectors_say_which_command_makes_the_missing_runs(tmp_path):
    from m3t.claims.collectors import (
        MissingRuns,
        ground_truth_ceiling,
        sgsa_adjacency,
        sgsa_systems,
        slr_face,
        smlm_objective,
        tokenizer_runs,
    )

    def message(collect, records):
        with pytest.raises(MissingRuns) as err:
            collect(records)
        return str(err.value)

    v = {"data_version": "v"}
    off = _record("o", "evaluate-smlm", {**v, "translation_objective": "False", "seed": "0"})
    assert message(smlm_objective("f", "c"), [off]) == (
        "needs evaluate-smlm runs with and without the translation objective (shared translation steps) for one "
        "seed: `dvc exp run -S smlm_train.translation_objective=false` and `dvc exp run` (or `m3t study`)")
    assert message(smlm_objective("f", "c", "added"), [off]) == (
        "needs evaluate-smlm runs with and without the translation objective (added translation steps) for one "
        "seed: `dvc exp run -S smlm_train.translation_objective=false` and `dvc exp run -S "
        "smlm_train.translation_steps=added` (or `m3t study`)")
    dev_truth = _record("g", "evaluate-backtranslation", {**v, "source": "ground-truth", "split": "dev"})
    assert message(ground_truth_ceiling, [off, dev_truth]) == (
        "needs evaluate-smlm and evaluate-backtranslation (ground truth, test) runs: `dvc repro`")
    assert message(slr_face("test", "hit", "full", "no_face"), [_record("s", "evaluate-slr", v)]) == (
        "needs evaluate-slr runs: `dvc repro evaluate-slr`")
    folder = _csv(tmp_path / "slr", "predictions.csv", "clip_id,variant,subset,other\nc,full,test,1\n")
    slr = _record("s1", "evaluate-slr", v, {"slr_train.seed": "0"}, artifact_dir=folder)
    assert message(slr_face("test", "hit", "full", "no_face"), [slr]) == (
        "run s1 predictions.csv has no 'hit' column; rerun evaluate-slr")
    gt_lengths = _record("g", "evaluate-sgsa", {**v, "counter": "ground-truth"})
    assert message(sgsa_systems("pt", "sgsa", "f", "c"), [gt_lengths]) == (
        "every evaluate-sgsa run used ground-truth lengths; the claims judge the models' own counters: rerun with "
        "sgsa_evaluate.counter: predicted")
    inf_only = _record("i", "evaluate-sgsa", v, {"sgsa.decoder_layers": "2", "sgsa.temporal_adjacency": "0"})
    assert message(sgsa_adjacency("f", "c"), [inf_only]) == (
        "needs evaluate-sgsa runs at N = inf and a finite N with the same layers and seed: `m3t sgsa-sweep 2`")
    tok = _record("t", "train-tokenizers", {**v, "quantizer": "vq", "batch_size": "8", "seed": "0"}, metrics={"m": 1})
    assert message(tokenizer_runs("m", ("vq", "8"), ("fsq", "8")), [tok]) == (
        "needs train-tokenizers runs of vq batch 8 and fsq batch 8 with the same seed: `m3t ablate-tokenizers`")


def test_tokenizer_runs_pair_one_value_per_seed_at_the_newest_runs_width():
    from m3t.claims.collectors import tokenizer_runs

    v = {"data_version": "v"}

    def tok(run_id, quantizer, seed, value, width="32", metrics=None):
        tags = {**v, "quantizer": quantizer, "batch_size": "8", "seed": seed, "width": width}
        return _record(run_id, "train-tokenizers", tags, metrics={"m": value} if metrics is None else metrics)

    records = [tok("a1", "vq", "1", 3.0), tok("b1", "fsq", "1", 4.0), tok("a0", "vq", "0", 1.0),
               tok("b0", "fsq", "0", 2.0), tok("b2", "fsq", "2", 9.0), tok("a2", "vq", "2", 9.0, metrics={}),
               tok("w", "vq", "0", 7.0, width="64")]
    sample = tokenizer_runs("m", ("vq", "8"), ("fsq", "8"))(records)
    assert sample.seeds == ["0", "1"] and sample.unit == "seed"  # seed 2: vq has no value of the metric
    np.testing.assert_array_equal(sample.a, [[1.0, 3.0]])
    np.testing.assert_array_equal(sample.b, [[2.0, 4.0]])
    assert (sample.runs_a, sample.runs_b) == (["a0", "a1"], ["b0", "b1"])


def test_sgsa_adjacency_pairs_infinite_and_finite_n_runs_of_the_same_layers_by_seed(tmp_path):
    from m3t.claims.collectors import sgsa_adjacency

    v = {"data_version": "v"}

    def run(run_id, layers, n, seed, value):
        folder = _csv(tmp_path / run_id, "per_clip.csv",
                      f"clip_id,system,split,x\nc,sgsa,test,{value}\nc,pt,test,99\nd,sgsa,dev,99\n")
        return _record(run_id, "evaluate-sgsa", {**v, "seed": seed},
                       {"sgsa.decoder_layers": layers, "sgsa.temporal_adjacency": n}, artifact_dir=folder)

    records = [run("f1", "2", "4", "1", 5.0), run("i1", "2", "0", "1", 6.0), run("f0", "2", "4", "0", 3.0),
               run("i0", "2", "0", "0", 4.0), run("f9", "2", "4", "9", 0.0), run("z", "0", "0", "0", 7.0)]
    sample = sgsa_adjacency("per_clip.csv", "x")(records)
    assert sample.seeds == ["0", "1"]  # seed 9 has no N = inf run
    assert (sample.runs_a, sample.runs_b) == (["i0", "i1"], ["f0", "f1"])
    np.testing.assert_array_equal(sample.a, [[4.0], [6.0]])
    np.testing.assert_array_equal(sample.b, [[3.0], [5.0]])


# -------------------------------------------------------------------------------------- the table and files
def test_claims_table_rows_of_judged_and_missing_claims():
    """A judged row has exactly the documented keys (plus its seed halves); a claim whose runs are missing is a
    "not run" row with what to run; each claim's generator depends on the seed and its key only."""
    from m3t.claims.collectors import MissingRuns
    from m3t.claims.definitions import Claim
    from m3t.claims.verdicts import claims_table

    def missing(records):
        raise MissingRuns("run `x`")

    judged = Claim("k", "src", "B beats A", "1 -> 2", "metric (unit)", "A", "B",
                   collect=lambda records: Sample(A, B, ["0", "1"], ["ra0", "ra1"], ["rb0", "rb1"]))
    absent = Claim("m", "s2", "C", "p", "met", "X", "Y", collect=missing)
    rows = claims_table([], 2, (absent, judged))
    assert rows[0] == {"key": "m", "source": "s2", "claim": "C", "paper": "p", "metric": "met", "a": "X", "b": "Y",
                       "seeds": [], "verdict": "not run", "note": "run `x`"}
    assert list(rows[1]) == ["key", "source", "claim", "paper", "metric", "a", "b", "seeds", "units", "unit",
                             "mean_a", "std_a", "mean_b", "std_b", "compared", "value", "interval95", "band", "verdict",
                             "note", "runs_a", "runs_b", "halves"]
    assert (rows[1]["key"], rows[1]["source"], rows[1]["claim"], rows[1]["paper"], rows[1]["metric"]) == (
        "k", "src", "B beats A", "1 -> 2", "metric (unit)")
    assert rows[1]["halves"]["seeds"] == [["0"], ["1"]] and rows[1]["verdict"] == "reproduced"
    again = claims_table([], 2, (judged,))
    assert again[0]["interval95"] == rows[1]["interval95"]  # independent of the other claims judged
    spread = np.random.default_rng(5).normal(size=(2, 5, 7))  # enough values for intervals to differ by draw
    varied = Claim("v", "s", "c", "p", "m", "A", "B", collect=lambda records: Sample(spread[0], spread[1],
                                                                                   list("01234"), [], []))
    by_seed = [claims_table([], 2, (varied,), seed=s)[0]["interval95"] for s in (0, 0, 1)]
    assert by_seed[0] == by_seed[1] != by_seed[2]
    assert claims_table([], 3, (judged,))[0]["verdict"] == "inconclusive"


def test_claims_markdown_by_hand():
    from m3t.claims.report import claims_markdown

    judged = {"claim": "B beats A", "source": "src", "paper": "1 -> 2", "metric": "m", "a": "A", "b": "B",
              "mean_a": 13.0, "std_a": 1.0, "mean_b": 1.5, "std_b": 0.5, "compared": "B - A", "value": -11.5,
              "interval95": [-14.0, -9.0], "band": None, "verdict": "reproduced", "note": "", "seeds": ["0", "1"],
              "runs_a": ["runA0123456", "shared0000"], "runs_b": ["shared0000x"], "key": "k",
              "halves": {"seeds": [["0"], ["1"]], "verdicts": ["reproduced", "inconclusive"]}}
    noted = {**judged, "claim": "Noted", "verdict": "inconclusive", "note": "1 seed(s) < 3", "halves": None,
             "band": [0.0, 2.5], "value": 123.456}
    missing = {"claim": "Missing", "source": "s", "paper": "p", "metric": "x", "verdict": "not run",
               "note": "run `y`", "seeds": [], "key": "n"}
    text = claims_markdown([judged, noted, missing], 4)
    lines = text.split("\n")
    assert lines[0] == (
        "Claims of M3T and SGSA on this platform's runs. Ours: A -> B as mean +- std over seeds; the 95 % interval "
        "is a hierarchical bootstrap over training seeds and test clips (over seeds for codebook statistics), so it "
        "includes how much a retrained model moves. Verdicts need >= 4 seeds. Metric definitions in the metric "
        "column.")
    assert lines[1] == ""
    assert lines[2] == ("| claim | source | paper | metric | ours: A -> B | compared [95 % interval] | verdict "
                        "| seeds | runs |")
    # three significant digits, whole from 100 up; run ids cut to 8 characters, each once, sorted
    assert lines[4] == ("| B beats A | src | 1 -> 2 | m | A 13 +- 1 -> B 1.5 +- 0.5 | B - A -11.5 [-14, -9] "
                        "| reproduced | 2 | runA0123, shared00 |")
    assert lines[5] == ("| Noted | src | 1 -> 2 | m | A 13 +- 1 -> B 1.5 +- 0.5 | B - A 123 [-14, -9] "
                        "(band 0 +- 2.5) | inconclusive (1 seed(s) < 3) | 2 | runA0123, shared00 |")
    assert lines[6] == "| Missing | s | p | x | - | - | not run: run `y` | 0 | - |"
    assert lines[7:] == ["", ("Stability: judged again on two disjoint halves of their seeds (first half, rest), 1 "
                              "of 1 claims flip their verdict (100 %): B beats A (reproduced / inconclusive)."), ""]
    assert claims_markdown([missing], 3).endswith(
        "\n\nStability: no claim has 2 seeds yet, so none could be judged again on two disjoint seed halves.\n")


def test_write_claims_files_hold_the_definitions_rows_and_stability(tmp_path, monkeypatch):
    import json

    from m3t.claims import report

    rows = [{"key": "n", "claim": "C", "source": "s", "paper": "p", "metric": "m", "verdict": "not run",
             "note": "run it", "seeds": []}]
    monkeypatch.setattr(report, "claims_table", lambda records, min_seeds: rows)
    assert report.write_claims([], tmp_path) is rows
    written = json.loads((tmp_path / "claims.json").read_text())
    assert written == {"min_seeds": 3, "motion_definition": "SOKE DTW (raw cost over aligned frames, m)",
                       "text_definition": "SL-T (ROUGE-L beta 1.2, per sentence; Chinese per character)",
                       "claims": rows, "stability": {"compared": 0, "flipped": 0, "share_flipped": None, "flips": []}}
    assert (tmp_path / "claims.md").read_text() == report.claims_markdown(rows, 3)


# ------------------------------------------------------------------------------------------- the claims
def test_the_tokenizer_claims_of_m3t_tab3_per_group_and_vq_baseline():
    """Nine claims per body group: FSQ's utilisation and PA-VPE against each VQ baseline, and FSQ's utilisation
    falling with the batch, with the paper's figures and the metric each reads."""
    from m3t.claims.definitions import CLAIMS

    baselines = (("", "VQ (EMA + reset)"), ("-vq-ema", "VQ (EMA, no reset)"), ("-vq-plain", "VQ-VAE (plain)"))
    figures = {"body": ("67.3 -> 96.4 %", "20.67 -> 16.11", "96.4 -> 84.1 %"),
               "hand": ("72.5 -> 98.1 %", "5.61 -> 4.94", "98.1 -> 86.9 %"),
               "face": ("78.8 -> 99.0 %", "1.35 -> 1.18", "99.0 -> 89.3 %")}
    expected = []
    for group, (use, vpe, batch) in figures.items():
        expected += [(f"tokenizer-utilisation-{group}{s}", "M3T Tab. 3",
                      f"FSQ uses more of its codebook than {label} ({group})", f"VQ -> FSQ {use}",
                      "test-split codebook utilisation (%)", label, "FSQ", False, None, "b-a")
                     for s, label in baselines]
        expected += [(f"tokenizer-pa-vpe-{group}{s}", "M3T Tab. 3",
                      f"FSQ reconstructs with lower PA-VPE than {label} ({group})", f"VQ -> FSQ {vpe}",
                      "test PA-VPE (mm, per-frame Procrustes)", label, "FSQ", True, None, "b-a")
                     for s, label in baselines]
        expected.append((f"tokenizer-batch-{group}", "M3T Tab. 3",
                         f"FSQ utilisation falls as the batch grows 16 -> 128 ({group})", f"batch 16 -> 128 {batch}",
                         "test-split codebook utilisation (%)", "FSQ batch 128", "FSQ batch 16", False, None, "b-a"))
    got = [(c.key, c.source, c.statement, c.paper, c.metric, c.a, c.b, c.lower_is_better, c.within, c.of)
           for c in CLAIMS]
    assert got[:21] == expected


def test_the_production_recognition_and_sgsa_claims_as_the_papers_state_them():
    """Every other claim's key, source, statement, paper figure, metric (in its named definition), variants and
    direction, in the order claims.md lists them."""
    from m3t.claims.definitions import CLAIMS, MOTION_DEFINITION, TEXT_DEFINITION

    assert MOTION_DEFINITION == "SOKE DTW (raw cost over aligned frames, m)"
    assert TEXT_DEFINITION == "SL-T (ROUGE-L beta 1.2, per sentence; Chinese per character)"
    got = [(c.key, c.source, c.statement, c.paper, c.metric, c.a, c.b, c.lower_is_better, c.within, c.of)
           for c in CLAIMS[21:]]
    assert got == [
        ("smlm-objective-dtw-body", "M3T Tab. 1",
         "the auxiliary translation objective lowers body DTW-JPE",
         "How2Sign 5.02 -> 4.86, CSL-Daily 4.77 -> 4.63, Phoenix14T 4.17 -> 4.02",
         "body DTW-JPE, SOKE DTW (raw cost over aligned frames, m)",
         "production only", "production + translation", True, None, "b-a"),
        ("smlm-objective-dtw-hand", "M3T Tab. 1",
         "the auxiliary translation objective lowers hand DTW-JPE",
         "How2Sign 8.94 -> 9.44 (higher), CSL-Daily 9.94 -> 9.28, Phoenix14T 9.14 -> 8.55",
         "hand DTW-JPE, SOKE DTW (raw cost over aligned frames, m)",
         "production only", "production + translation", True, None, "b-a"),
        ("smlm-objective-bt", "M3T Tab. 2",
         "the auxiliary translation objective raises back-translation",
         "ROUGE-L How2Sign 12.32 -> 13.15, CSL-Daily 17.27 -> 20.23, Phoenix14T 31.14 -> 32.12",
         "back-translation ROUGE-L, SL-T (ROUGE-L beta 1.2, per sentence; Chinese per character)",
         "production only", "production + translation", False, None, "b-a"),
        ("smlm-objective-dtw-body-equal-updates", "M3T Tab. 1",
         "the auxiliary translation objective lowers body DTW-JPE (at equal production updates)",
         ("How2Sign 5.02 -> 4.86, CSL-Daily 4.77 -> 4.63, Phoenix14T 4.17 -> 4.02 (the paper's budget "
          "is not given)"),
         "body DTW-JPE, SOKE DTW (raw cost over aligned frames, m)",
         "production only", "production + translation (added steps)", True, None, "b-a"),
        ("smlm-objective-dtw-hand-equal-updates", "M3T Tab. 1",
         "the auxiliary translation objective lowers hand DTW-JPE (at equal production updates)",
         "How2Sign 8.94 -> 9.44 (higher), CSL-Daily 9.94 -> 9.28, Phoenix14T 9.14 -> 8.55",
         "hand DTW-JPE, SOKE DTW (raw cost over aligned frames, m)",
         "production only", "production + translation (added steps)", True, None, "b-a"),
        ("smlm-objective-bt-equal-updates", "M3T Tab. 2",
         "the auxiliary translation objective raises back-translation (at equal production updates)",
         "ROUGE-L How2Sign 12.32 -> 13.15, CSL-Daily 17.27 -> 20.23, Phoenix14T 31.14 -> 32.12",
         "back-translation ROUGE-L, SL-T (ROUGE-L beta 1.2, per sentence; Chinese per character)",
         "production only", "production + translation (added steps)", False, None, "b-a"),
        ("bt-ground-truth-ceiling", "M3T Tab. 2",
         "back-translation of the ground truth is the upper bound",
         "ROUGE-L GT 18.68 / 27.14 / 35.83 vs M3T 13.15 / 20.23 / 32.12",
         "back-translation ROUGE-L, SL-T (ROUGE-L beta 1.2, per sentence; Chinese per character)",
         "generated (with objective)", "ground truth", False, None, "b-a"),
        ("slr-face-confusing", "M3T Tab. 4 / Sec. 4.3",
         "the face stream carries the confusing pairs",
         "confusing Top-1 58.3 % with face (no face-less run reported)",
         "pair accuracy on confusing signs (%): the target beats its manual twin",
         "without face", "with face", False, None, "b-a"),
        ("slr-face-chance", "M3T Sec. 4.3",
         "without the face, confusing pairs fall to about chance",
         "'face tokens are the sole source of discriminative information' (no figure)",
         "pair accuracy on confusing signs without face (%), within 10 points of chance (50 %)",
         "with face", "without face", True, (50.0, 10.0), "b"),
        ("slr-face-normal", "M3T Sec. 4.3",
         "normal signs stay recognised without the face",
         "'adding face tokens provides no discriminative advantage' on normal signs (no figure)",
         "Top-1 on normal signs (%), without - with face within 10 points",
         "with face", "without face", True, (0.0, 10.0), "b-a"),
        ("sgsa-vs-pt-bt", "SGSA Tab. 1",
         "SGSA beats Progressive Transformers (back-translation)",
         "test BLEU-4 13.64 -> 14.27, ROUGE 36.59 -> 37.79 (L = 0 with 4 SA layers -> L = 5)",
         ("back-translation ROUGE-L of the skeleton judge, SL-T (ROUGE-L beta 1.2, per sentence; "
          "Chinese per character)"),
         "PT", "SGSA", False, None, "b-a"),
        ("sgsa-vs-pt-dtw", "SGSA Tab. 1 (our metric)",
         "SGSA beats Progressive Transformers (motion)",
         "not reported (back-translation only)",
         "body DTW-JPE, SOKE DTW (raw cost over aligned frames, m), skeleton judge's split",
         "PT", "SGSA", True, None, "b-a"),
        ("sgsa-adjacency", "SGSA Tab. 2",
         "temporal adjacency N = 1 beats N = inf",
         "test BLEU-4 14.27 -> 14.33, ROUGE 37.79 -> 37.96 (dev BLEU-4 14.72 -> 15.15)",
         ("back-translation ROUGE-L of the skeleton judge, SL-T (ROUGE-L beta 1.2, per sentence; "
          "Chinese per character)"),
         "SGSA N = inf", "SGSA N = 1", False, None, "b-a"),
        ("smlm-vs-sgsa", "across papers",
         "M3T's SMLM beats SGSA on the same split",
         "not compared in either paper",
         "body DTW-JPE, SOKE DTW (raw cost over aligned frames, m)",
         "SGSA", "SMLM", True, None, "b-a"),
        ("smlm-vs-pt", "across papers",
         "M3T's SMLM beats Progressive Transformers on the same split",
         "M3T Tab. 1: PT 14.74 vs M3T 4.86 body DTW-JPE (How2Sign)",
         "body DTW-JPE, SOKE DTW (raw cost over aligned frames, m)",
         "PT", "SMLM", True, None, "b-a"),
        ("smlm-vs-retrieval", "baselines",
         "M3T's SMLM beats the retrieval baseline (motion)",
         "not compared in either paper (SLRTP 2025: a copy baseline beat the learned systems)",
         "body DTW-JPE, SOKE DTW (raw cost over aligned frames, m)",
         "retrieval", "SMLM", True, None, "b-a"),
        ("smlm-vs-lexicon", "baselines",
         "M3T's SMLM beats the lexicon baseline (motion)",
         "not compared in either paper (Spoken2Sign, spoken-to-signed: stitched dictionary signs)",
         "body DTW-JPE, SOKE DTW (raw cost over aligned frames, m)",
         "lexicon (annotated glosses)", "SMLM", True, None, "b-a"),
        ("sgsa-vs-retrieval", "baselines",
         "SGSA beats the retrieval baseline (motion)",
         "not compared in the paper",
         "body DTW-JPE, SOKE DTW (raw cost over aligned frames, m), skeleton judge's split",
         "retrieval", "SGSA", True, None, "b-a"),
    ]


def test_slr_face_and_the_ground_truth_ceiling_read_their_runs_by_seed(tmp_path):
    """evaluate-slr predictions of two probe variants on one subset, as %, one run per seed (the seed param of
    the B variant's section or the plain one); the ground-truth ceiling pairs each seed's generated motion with
    the one ground-truth test run of the same data version."""
    from m3t.claims.collectors import ground_truth_ceiling, slr_face

    v = {"data_version": "v"}
    text = ("clip_id,variant,subset,correct_pair\nc1,full,confusing,1\nc1,no_face,confusing,0\n"
            "c2,full,confusing,0\nc2,no_face,normal,1\n")
    runs = [_record("s1", "evaluate-slr", v, {"full.slr_train.seed": "1"}, artifact_dir=_csv(tmp_path / "s1",
                                                                                            "predictions.csv", text)),
            _record("s0", "evaluate-slr", v, {"slr_train.seed": "0"}, artifact_dir=_csv(tmp_path / "s0",
                                                                                       "predictions.csv", text))]
    sample = slr_face("confusing", "correct_pair", "no_face", "full")(runs)
    assert sample.seeds == ["0", "1"] and sample.runs_a == sample.runs_b == ["s0", "s1"]
    np.testing.assert_array_equal(sample.a, [[0.0, np.nan]] * 2)
    np.testing.assert_array_equal(sample.b, [[100.0, 0.0]] * 2)

    def generated(run_id, seed, value):
        return _record(run_id, "evaluate-smlm", {**v, "seed": seed}, artifact_dir=_csv(
            tmp_path / run_id, "backtranslation.csv", f"clip_id,rouge_l\nc1,{value}\n"))

    truth = _record("gt", "evaluate-backtranslation", {**v, "source": "ground-truth", "split": "test"},
                    artifact_dir=_csv(tmp_path / "gt", "per_clip.csv", "clip_id,rouge_l\nc1,50\nc2,40\n"))
    ceiling = ground_truth_ceiling([generated("g1", "1", 20.0), truth, generated("g0", "0", 10.0)])
    assert ceiling.seeds == ["0", "1"] and ceiling.runs_a == ["g0", "g1"] and ceiling.runs_b == ["gt", "gt"]
    np.testing.assert_array_equal(ceiling.a, [[10.0, np.nan], [20.0, np.nan]])
    np.testing.assert_array_equal(ceiling.b, [[50.0, 40.0]] * 2)
