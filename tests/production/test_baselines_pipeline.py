"""evaluate-baselines on the tiny pipeline (:mod:`tiny_pipeline`): the baselines are scored like the SMLM (the same
clips, scorer and judge), ``m3t score`` reproduces their figures from the motion shards the stage writes, and
their MLflow runs are rows of the production tables.

The tiny corpus has sentence clips only (texts ``sentence 0`` .. ``sentence 2``, gloss ``G``): every test text
occurs in the training split (retrieval: exact matches), and there is no isolated sign (lexicon: no entry, no
motion, every gloss counted missing).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from m3t.experiment import fetch_runs
from m3t.production.baselines import evaluate_and_log, motion_dir
from m3t.production.config import BaselinesConfig
from m3t.scoring.score import score
from m3t.sgsa.config import SGSAEvaluateConfig
from m3t.shards.io import read_shard
from m3t.smlm.table import production_table


@pytest.fixture(scope="module")
def evaluated(tiny_workspace):
    p = tiny_workspace.params
    # the tiny workspace trains no skeleton judge: the skeleton path is scored without back-translation
    summary = evaluate_and_log(BaselinesConfig(), p.data, p.body, p.smlm_generate, p.sgsa,
                               SGSAEvaluateConfig(backtranslate=False), p.experiment, p.backtranslation)
    return tiny_workspace, summary


def test_the_baselines_are_scored_on_the_smlms_clips_and_m3t_score_reproduces_them(evaluated, body):
    workspace, summary = evaluated
    data, bt = workspace.params.data, workspace.params.backtranslation
    test = Path(data.shards_root) / "synthetic" / "test.parquet"
    assert json.loads((data.metrics("baselines") / "metrics.json").read_text()) == pytest.approx(summary)
    smlm = json.loads((data.metrics("smlm") / "metrics.json").read_text())
    assert summary["retrieval/clips_scored"] == smlm["clips_scored"] == len(read_shard(test).clips)
    produced = pd.read_csv(data.metrics("baselines") / "produced.csv")
    retrieval = produced[(produced.system == "retrieval") & (produced.path == "body_model")]
    assert set(retrieval.match) == {"exact"} and summary["retrieval/exact_rate"] == 1.0
    train = {c.clip.id: c for c in read_shard(Path(data.shards_root) / "synthetic" / "train.parquet").clips}
    shard = {c.clip.id: c for c in read_shard(motion_dir(data) / "retrieval.parquet").clips}
    for row in retrieval.itertuples():  # the training clip's motion, unchanged
        assert train[row.source].clip.text == shard[row.clip_id].clip.text
        for name, values in train[row.source].params.items():
            np.testing.assert_array_equal(shard[row.clip_id].params[name], values)
    report = score(motion_dir(data) / "retrieval.parquet", test, ["m3t", "slt"], body=body,
                   judge=data.backtranslation_dir, beam_size=bt.beam_size, length_penalty=bt.length_penalty)
    dtw = [k for k in report.metrics if k.startswith("m3t_dtw_")]
    assert len(dtw) >= 5
    for key in dtw:  # the same scorer on the same parameters, both in this process
        assert report.metrics[key] == pytest.approx(summary[f"retrieval/{key.removeprefix('m3t_')}"], rel=1e-9), key
    judged = [k for k in report.metrics if k.startswith("slt/")]
    assert judged
    for key in judged:
        assert report.metrics[key] == pytest.approx(summary[f"retrieval/bt/{key}"], abs=1e-9), key


def test_a_lexicon_without_entries_gives_no_motion_and_counts_every_gloss(evaluated):
    _, summary = evaluated
    assert summary["lexicon/no_motion_rate"] == 1.0 and summary["lexicon/missing_rate"] == 1.0
    assert summary["lexicon/empty_rate"] == 1.0  # scored as the rest pose, as an empty generation is
    assert np.isfinite(summary["lexicon/dtw_jpe_body_m"]) and summary["lexicon/dtw_jpe_body_m"] > 0
    produced = pd.read_csv(evaluated[0].params.data.metrics("baselines") / "produced.csv")
    lexicon = produced[produced.system == "lexicon"]
    assert set(lexicon.missing_words) == {"G"} and set(lexicon.frames) == {0}
    assert read_shard(motion_dir(evaluated[0].params.data) / "lexicon.parquet").clips == ()  # no empty clip stored


def test_the_skeleton_path_scores_evaluate_sgsas_samples(evaluated):
    workspace, summary = evaluated
    per_clip = pd.read_csv(workspace.params.data.metrics("baselines") / "per_clip.csv")
    skeleton = per_clip[per_clip.path == "skeleton"]
    for split in ("dev", "test"):
        assert summary[f"retrieval/skeleton/{split}/clips"] == len(skeleton[(skeleton.system == "retrieval")
                                                                            & (skeleton.split == split)]) > 0
        assert f"retrieval/skeleton/{split}/dtw_jpe_mean_m" in summary
    assert not any("/skeleton/" in k and "/bt/" in k for k in summary)  # no skeleton judge asked for


def test_each_baseline_is_a_run_and_a_row_of_the_production_table(evaluated):
    workspace, summary = evaluated
    experiment = workspace.params.experiment
    runs = fetch_runs(experiment, stage="evaluate-baselines")
    assert sorted(r.tags["variant"] for r in runs) == ["lexicon", "retrieval"]
    assert all(r.tags["baseline"] == r.tags["variant"] for r in runs)
    table = production_table(fetch_runs(experiment, stage="evaluate-smlm"), baselines=runs)
    lines = table.splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    line = next(x for x in lines if x.startswith("| baseline: retrieval |"))
    cells = dict(zip(header, (c.strip() for c in line.strip("|").split("|"))))
    assert cells["synthetic/ASL-SYN JPE body"] == f"{summary['retrieval/synthetic/ASL-SYN/dtw_jpe_body_m']:.3f}"
