"""``m3t produce`` on the tiny pipeline's checkpoints and shards (:mod:`tiny_pipeline`): the produced sentence
reads back through pose-format with the frame count and rate of what was produced, the parameters file holds the
motion, and missing checkpoints name the stage to run."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cli.main import main as cli_main
from m3t.production.produce import ProductionError, produce
from m3t.shards.io import read_split


def _read_pose(path: Path):
    from pose_format import Pose

    return Pose.read(path.read_bytes())


def test_smlm_produces_a_sentence(tiny_workspace, body, tmp_path):
    params = tiny_workspace.params
    text = "sentence 1"
    result = produce(text, "ASL-SYN", params, "smlm", tmp_path, body=body)
    downsample = 2 ** params.tokenizer.down_stages  # frames per motion token
    assert result.frames == result.details["steps"] * downsample > 0 and result.fps == 25.0
    pose = _read_pose(tmp_path / "sentence_1.pose")
    assert pose.body.data.shape[0] == result.frames and pose.body.fps == 25.0
    assert [c.name for c in pose.header.components][:4] == ["POSE_LANDMARKS", "FACE_LANDMARKS",
                                                            "LEFT_HAND_LANDMARKS", "RIGHT_HAND_LANDMARKS"]
    stored = np.load(tmp_path / "sentence_1.npz")
    for name, values in result.params.items():
        np.testing.assert_array_equal(stored[name], values)
    assert float(stored["fps"]) == 25.0 and stored["identity"].shape == result.identity.shape
    summary = json.loads((tmp_path / "sentence_1.json").read_text())
    assert summary["system"] == "smlm" and summary["frames"] == result.frames
    assert (tmp_path / "sentence_1.mp4").stat().st_size > 0
    with pytest.raises(ProductionError, match=r"unknown language 'XSL'; this vocabulary knows"):
        produce(text, "XSL", params, "smlm", body=body)


def test_retrieval_returns_the_training_motion(tiny_workspace, body, tmp_path, capsys):
    params = tiny_workspace.params
    train = read_split(params.data.shards_dirs, "train")
    first = min((c for c in train if c.clip.text == "sentence 1"), key=lambda c: c.clip.id)
    result = produce("Sentence 1!", "ASL-SYN", params, "retrieval", tmp_path, name="s1", video=False, body=body)
    assert result.details["retrieved_clip"] == first.clip.id and result.details["match"] == "exact"
    for name, values in first.params.items():
        np.testing.assert_array_equal(result.params[name], values)
    assert _read_pose(tmp_path / "s1.pose").body.data.shape[0] == first.num_frames
    assert not (tmp_path / "s1.mp4").exists()
    assert cli_main(["--params", str(tiny_workspace.params_file), "produce", "sentence 1 tomorrow", "--language",
                     "ASL-SYN", "--system", "retrieval", "--out", str(tmp_path / "cli"), "--no-video"]) == 0
    printed = capsys.readouterr().out
    assert "match: chrf" in printed and "words not handled (1): tomorrow" in printed
    assert (tmp_path / "cli" / "sentence_1_tomorrow.pose").exists()


def test_missing_checkpoint_names_the_stage(tiny_workspace, tmp_path, body):
    from dataclasses import replace

    params = tiny_workspace.params
    empty = replace(params, data=replace(params.data, models_dir=str(tmp_path / "none")))
    with pytest.raises(ProductionError, match=r"SMLM checkpoint .*smlm\.pt not found; run `dvc repro train-smlm` "
                                              r"first"):
        produce("sentence 1", "ASL-SYN", empty, "smlm", body=body)
    with pytest.raises(ProductionError, match=r"system 'copy' cannot produce from text here; choose one of smlm, "
                                              r"retrieval, lexicon, pt, sgsa$"):
        produce("sentence 1", "ASL-SYN", params, "copy", body=body)
    with pytest.raises(ProductionError, match=r"sgsa\.pt not found; run `dvc repro train-sgsa`"):  # none trained
        produce("sentence 1", "ASL-SYN", params, "sgsa", body=body)
