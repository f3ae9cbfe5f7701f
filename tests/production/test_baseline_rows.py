"""The baselines in every production table and in the claims: evaluate-baselines' MLflow runs (one per system,
tag ``variant`` = the system; body-model metrics under evaluate-smlm's names, skeleton ones under evaluate-sgsa's
``<system>/<split>/...``) and its ``per_clip.csv`` (``system``, ``path``, ``split``, ``clip_id``, metrics), on
hand-made run records."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from m3t.backtranslation.table import backtranslation_table
from m3t.claims.definitions import CLAIMS
from m3t.claims.verdicts import claims_table
from m3t.experiment import RunRecord
from m3t.sgsa.table import adjacency_table, cross_table, layers_table
from m3t.smlm.table import baseline_rows, production_table

CLIPS = [f"asl-syn-{i:04d}" for i in range(8)]


def baseline(run_id: str, system: str, value: float, start: int = 0, status: str = "FINISHED",
             folder: Path | None = None, version: str = "v1") -> RunRecord:
    metrics = {"synthetic/ASL-SYN/dtw_pa_jpe_body_m": value, "synthetic/ASL-SYN/dtw_pa_jpe_hand_m": value + 0.1,
               "synthetic/ASL-SYN/dtw_jpe_body_m": value + 0.2, "synthetic/ASL-SYN/dtw_jpe_hand_m": value + 0.3,
               "bt/slt/ASL-SYN/bleu4": 10 * value, "bt/slt/ASL-SYN/rouge_l": 20 * value}
    for split in ("dev", "test"):  # the skeleton path's figures, evaluate-sgsa's names (with their own groups)
        metrics[f"{system}/{split}/bt/slt/ASL-SYN/bleu4"] = 10 * value
        metrics[f"{system}/{split}/dtw_jpe_mean_m"] = value / 1000
        metrics[f"{system}/{split}/dtw_jpe_body_m"] = metrics[f"{system}/{split}/synthetic/ASL-SYN/dtw_jpe_body_m"] = 9.0
    return RunRecord(run_id, "evaluate-baselines", start, status, {}, metrics, folder,
                     {"variant": system, "baseline": system, "data_version": version})


def smlm(run_id: str, value: float) -> RunRecord:
    metrics = {f"synthetic/ASL-SYN/{k}": value for k in ("dtw_pa_jpe_body_m", "dtw_pa_jpe_hand_m", "dtw_jpe_body_m",
                                                          "dtw_jpe_hand_m")}
    metrics.update({"translation_bleu4": 5.0, "bt/slt/ASL-SYN/bleu4": 1.0, "bt/slt/ASL-SYN/rouge_l": 2.0})
    return RunRecord(run_id, "evaluate-smlm", 0, "FINISHED", {}, metrics, None,
                     {"variant": "production + translation"})


BASELINES = [baseline("lex-new", "lexicon", 2.0, start=5), baseline("ret-failed", "retrieval", 9.0, 9, "FAILED"),
             baseline("ret-new", "retrieval", 1.0, start=4), baseline("ret-old", "retrieval", 7.0, start=1)]


def test_baseline_rows_are_the_newest_finished_run_of_each_system_retrieval_first():
    rows = baseline_rows(sorted(BASELINES, key=lambda r: -r.start_time))
    assert [(name, r.run_id) for name, r in rows] == [("retrieval", "ret-new"), ("lexicon", "lex-new")]


def test_m3t_tables_show_the_baselines_below_the_models():
    tab1 = production_table([smlm("s", 3.0)], baselines=BASELINES).splitlines()
    assert tab1[2:] == ["| production + translation | 3.000 | 3.000 | 3.000 | 3.000 | 5.00 |",
                        "| baseline: retrieval | 1.000 | 1.100 | 1.200 | 1.300 | - |",
                        "| baseline: lexicon | 2.000 | 2.100 | 2.200 | 2.300 | - |"]
    assert production_table([smlm("s", 3.0)]).count("baseline") == 0  # no baseline run: no row
    tab2 = backtranslation_table([], [smlm("s", 3.0)], BASELINES).splitlines()
    assert tab2[4:] == ["| SMLM, production + translation | 2.00 | 1.00 |",
                        "| baseline: retrieval | 20.00 | 10.00 |",
                        "| baseline: lexicon | 40.00 | 20.00 |"]


def sgsa_record(run_id: str, value: float) -> RunRecord:
    metrics = {}
    for system in ("pt", "sgsa", "smlm", "ground_truth"):
        for split in ("dev", "test"):
            metrics[f"{system}/{split}/bt/slt/ASL-SYN/bleu4"] = value
            metrics[f"{system}/{split}/dtw_jpe_mean_m"] = value / 1000
    return RunRecord(run_id, "evaluate-sgsa", 0, "FINISHED", {"sgsa.decoder_layers": "2",
                                                               "sgsa.temporal_adjacency": "0"}, metrics, None,
                     {"seed": "0", "counter": "predicted"})


def row(table: str, first: str) -> list[str]:
    line = next(x for x in table.splitlines() if x.startswith(f"| {first} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_sgsa_tables_show_the_baselines_scored_on_the_skeleton():
    records = [sgsa_record("a", 30.0)]
    retrieval = "Retrieval baseline (nearest training text's motion)"
    lexicon = "Lexicon baseline (stored sign per gloss, stitched)"
    for table in (layers_table(records, BASELINES), adjacency_table(records, baselines=BASELINES),
                  cross_table(records, BASELINES)):
        # BLEU-4 dev, ..., DTW-JPE dev (mm), ..., seeds: one run
        assert row(table, retrieval)[1] == "10.00" and row(table, retrieval)[6] == "1.00"
        assert row(table, lexicon)[1] == "20.00" and row(table, retrieval)[-1] == "1"
    cross = [line.split("|")[1].strip() for line in cross_table(records, BASELINES).splitlines()
             if line.startswith("| ")][1:]
    assert cross == ["Progressive Transformers", "Skeletal Graph Self-Attention (L=2, N=inf)",
                     "M3T SMLM (posed into the skeleton)", retrieval, lexicon,
                     "Ground-truth motion (judge upper bound)"]
    assert retrieval not in cross_table(records)


def _per_clip(folder: Path, rows: list[dict]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "per_clip.csv", "w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return folder


def test_baseline_claims_pair_the_one_baseline_run_with_each_seeds_model(tmp_path):
    """A: the baseline's clips on the model's path (body-model rows for the SMLM, skeleton test rows for SGSA),
    the same run for every seed; B: the model per seed; runs on other data are never paired."""
    rows = []
    for path, split, value in (("body_model", "test", 2.0), ("skeleton", "test", 5.0), ("skeleton", "dev", 99.0)):
        rows += [{"system": "retrieval", "path": path, "split": split, "clip_id": c, "dtw_jpe_body_m": value + 0.01 * i}
                 for i, c in enumerate(CLIPS)]
    base = baseline("ret", "retrieval", 1.0, start=50, folder=_per_clip(tmp_path / "ret", rows))
    other = baseline("ret-other", "retrieval", 1.0, start=60, folder=base.artifact_dir, version="v2")
    smlm_runs, sgsa_runs = [], []
    for seed in range(3):
        folder = _per_clip(tmp_path / f"smlm{seed}", [{"clip_id": c, "group": "g", "dtw_jpe_body_m": 1.0 + 0.01 * i}
                                                      for i, c in enumerate(CLIPS)])
        smlm_runs.append(RunRecord(f"smlm{seed}", "evaluate-smlm", seed, "FINISHED", {}, {}, folder,
                                   {"seed": str(seed), "data_version": "v1", "translation_objective": "True"}))
        folder = _per_clip(tmp_path / f"sgsa{seed}", [{"clip_id": c, "system": "sgsa", "split": "test",
                                                       "dtw_jpe_body_m": 4.0 + 0.01 * i} for i, c in enumerate(CLIPS)])
        sgsa_runs.append(RunRecord(f"sgsa{seed}", "evaluate-sgsa", seed, "FINISHED",
                                   {"sgsa.decoder_layers": "2", "sgsa.temporal_adjacency": "1"}, {}, folder,
                                   {"seed": str(seed), "data_version": "v1", "variant": "sgsa L=2 N=1"}))
    records = sorted([base, other, *smlm_runs, *sgsa_runs], key=lambda r: -r.start_time)
    claims = {c.key: c for c in CLAIMS}
    smlm_row = claims_table(records, claims=(claims["smlm-vs-retrieval"],))[0]
    assert smlm_row["runs_a"] == ["ret"] * 3 and smlm_row["runs_b"] == ["smlm0", "smlm1", "smlm2"]
    assert smlm_row["mean_a"] == pytest.approx(2.035) and smlm_row["mean_b"] == pytest.approx(1.035)
    assert smlm_row["verdict"] == "reproduced"
    sgsa_row = claims_table(records, claims=(claims["sgsa-vs-retrieval"],))[0]
    assert sgsa_row["mean_a"] == pytest.approx(5.035) and sgsa_row["mean_b"] == pytest.approx(4.035)
    sample = claims["sgsa-vs-retrieval"].collect(records)
    np.testing.assert_allclose(sample.a[0], [5.0 + 0.01 * i for i in range(len(CLIPS))])  # test split rows only
    with pytest.raises(LookupError, match=r"needs an evaluate-baselines run of 'lexicon' on the same data: "
                                          r"`dvc repro evaluate-baselines`"):
        claims["smlm-vs-lexicon"].collect(records)


def test_the_results_page_says_which_baselines_beat_the_smlm():
    from dashboards.docs_pages import _baseline_verdict

    smlm = {"dtw_jpe_mean_m": 1.5}
    both = _baseline_verdict(smlm, {"retrieval/dtw_jpe_mean_m": 1.2, "lexicon/dtw_jpe_mean_m": 1.4})
    assert both.startswith("**The retrieval and the lexicon baselines beat the SMLM on DTW-JPE** (mean of body and "
                           "hands: SMLM 1.5 m, retrieval 1.2 m, lexicon 1.4 m)")
    one = _baseline_verdict(smlm, {"retrieval/dtw_jpe_mean_m": 1.2, "lexicon/dtw_jpe_mean_m": 1.6})
    assert one.startswith("**The retrieval baseline beats the SMLM on DTW-JPE** (mean of body and hands: SMLM 1.5 m, "
                          "retrieval 1.2 m)")
    assert _baseline_verdict(smlm, {"retrieval/dtw_jpe_mean_m": 1.5}) == (
        "The SMLM is closer to the reference motion (DTW-JPE, mean of body and hands) than both baselines.\n")
    assert _baseline_verdict({}, {"retrieval/dtw_jpe_mean_m": 1.2}) == ""
