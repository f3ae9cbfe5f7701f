"""``m3t score`` on the tiny pipeline's own outputs (:mod:`tiny_pipeline`): the figures of its metrics files,
from the fitted test shard, generate-smlm's token shard and the back-translation judge it trained.

Kept apart from tests/scoring/test_score.py because the workspace takes minutes to build: the mutation run's
test selection holds the fast file only.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from cli.main import main as cli_main
from m3t.scoring.poses import ScoreInputError
from m3t.scoring.score import score
from m3t.shards.io import read_shard


def test_ground_truth_back_translation_as_the_pipeline_scores_it(tiny_workspace, body, tmp_path, capsys):
    """The tiny pipeline's evaluate-backtranslation scores the test split's fitted motion with its judge: the same
    shard scored against itself with that judge gives the figures of its metrics file."""
    data = tiny_workspace.params.data
    test = Path(data.shards_root) / "synthetic" / "test.parquet"
    stored = json.loads((data.metrics("backtranslation") / "metrics.json").read_text())
    bt = tiny_workspace.params.backtranslation
    report = score(test, test, ["m3t", "slt", "soke"], body=body, judge=data.backtranslation_dir,
                   beam_size=bt.beam_size, length_penalty=bt.length_penalty)
    slt = {k: v for k, v in report.metrics.items() if report.definition_of[k] == "slt"}
    assert slt and all(k.startswith("slt/") for k in slt)
    for key, value in slt.items():
        assert value == pytest.approx(stored[key], rel=1e-12, abs=1e-12), key
    assert report.metrics["m3t_dtw_jpe_body_m"] == pytest.approx(0.0, abs=1e-9)
    assert {r["clip"] for r in report.sentences} == {c.clip.id for c in read_shard(test).clips}
    assert report.clips_scored["slt"] == report.clips_scored["soke"] == len(report.sentences)
    # the command finds the workspace's judge itself
    assert cli_main(["--params", str(tiny_workspace.params_file), "score", str(test), str(test),
                     "--definitions", "slt", "--out", str(tmp_path)]) == 0
    assert "slt/" in capsys.readouterr().out
    assert (tmp_path / "sentences.csv").read_text().startswith("clip,language,hypothesis,reference\n")


def test_generated_motion_as_evaluate_smlm_scores_it(tiny_workspace, body):
    """generate-smlm's token shard, decoded by the workspace's tokenizers, against the test split: the motion
    metrics and the judge's back-translation scores of evaluate-smlm's metrics file (``dtw_*``, ``bt/slt/...``)."""
    data = tiny_workspace.params.data
    test = Path(data.shards_root) / "synthetic" / "test.parquet"
    stored = json.loads((data.metrics("smlm") / "metrics.json").read_text())
    bt = tiny_workspace.params.backtranslation
    report = score(data.generated / "generated.parquet", test, ["m3t", "slt"], body=body,
                   judge=data.backtranslation_dir, beam_size=bt.beam_size, length_penalty=bt.length_penalty,
                   tokenizers_dir=data.tokenizers_dir)
    motion = {k.removeprefix("m3t_"): v for k, v in report.metrics.items() if report.definition_of[k] == "m3t"}
    dtw = [k for k in motion if k.startswith("dtw_")]
    assert len(dtw) >= 5 and motion["empty_rate"] == pytest.approx(stored["empty_rate"], abs=0)
    for key in dtw:
        # the same scorer on the same decoded parameters; the decoder runs in another process than the stage's
        # (torch's float reductions may order differently between thread counts): a relative tolerance
        assert motion[key] == pytest.approx(stored[key], rel=1e-5), key
    judged = {k: v for k, v in report.metrics.items() if report.definition_of[k] == "slt"}
    assert judged and all(f"bt/{k}" in stored for k in judged)
    for key, value in judged.items():
        assert value == pytest.approx(stored[f"bt/{key}"], abs=1e-9), key


def test_token_shard_needs_its_tokenizers(tiny_workspace, body, tmp_path):
    data = tiny_workspace.params.data
    test = Path(data.shards_root) / "synthetic" / "test.parquet"
    with pytest.raises(ScoreInputError, match=r"generated\.parquet: a token shard; decoding its prediction needs the "
                                              r"tokenizers that wrote it \(models/tokenizers; not found: None\)"):
        score(data.generated / "generated.parquet", test, ["m3t"], body=body)
    with pytest.raises(ScoreInputError, match=r"the reference must be a parameter shard"):
        score(test, data.generated / "generated.parquet", ["m3t"], body=body, tokenizers_dir=data.tokenizers_dir)
