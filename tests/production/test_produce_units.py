"""``m3t produce``'s retrieval path and ``m3t translate``'s input handling without trained checkpoints: over
fitted shards of smooth synthetic motion (:func:`tiny_pipeline.write_shards`: train clips c0-c3 of 18, 25, 32
and 39 frames, texts ``"sentence <seed % 3>"``, language ASL-SYN, 25 fps)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from builders import tiny_params

from m3t.production.produce import ProductionError, produce, slug
from m3t.production.translate import _parameters, input_kind


@pytest.fixture(scope="module")
def shards(body, tmp_path_factory):
    from tiny_pipeline import write_shards

    return write_shards(tmp_path_factory.mktemp("produce_shards") / "synthetic", body)


@pytest.fixture(scope="module")
def params(shards, tmp_path_factory):
    from dataclasses import replace

    p = tiny_params(tmp_path_factory.mktemp("produce"))
    return replace(p, data=replace(p.data, shards_root=str(shards.parent),
                                   models_dir=str(tmp_path_factory.mktemp("no_models"))))


def test_slug():
    assert slug("The weather, is NICE!") == "the_weather_is_nice"
    assert slug("a " * 40) == "a_a_a_a_a_a_a_a_a_a_a_a_a_a_a_a_a_a_a_a"
    assert slug("?!") == "produced"


def test_retrieval_writes_pose_parameters_and_summary(params, body, tmp_path, shards):
    from pose_format import Pose

    from m3t.shards.io import read_shard

    result = produce("sentence 2 tomorrow", "ASL-SYN", params, "retrieval", tmp_path, video=False, body=body)
    train = {c.clip.id: c for c in read_shard(shards / "train.parquet").clips}
    assert result.details["retrieved_clip"] == "c2" and result.details["match"] == "chrf"  # c2: "sentence 2"
    assert result.unhandled_words == ("tomorrow",) and result.fps == 25.0
    for name, values in train["c2"].params.items():
        np.testing.assert_array_equal(result.params[name], values)
    np.testing.assert_array_equal(result.identity, train["c2"].identity)
    pose = Pose.read((tmp_path / "sentence_2_tomorrow.pose").read_bytes())
    assert pose.body.data.shape[0] == train["c2"].num_frames == result.frames and pose.body.fps == 25.0
    stored = np.load(tmp_path / "sentence_2_tomorrow.npz")
    assert sorted(stored.files) == sorted([*body.layout.dims, "identity", "fps"])
    summary = json.loads((tmp_path / "sentence_2_tomorrow.json").read_text())
    assert summary == {"system": "retrieval", "text": "sentence 2 tomorrow", "language": "ASL-SYN",
                       "frames": result.frames, "fps": 25.0, "unhandled_words": ["tomorrow"],
                       "retrieved_clip": "c2", "retrieved_text": "sentence 2", "match": "chrf",
                       "chrf": result.details["chrf"], "words": 3,
                       "files": {"pose": "sentence_2_tomorrow.pose", "params": "sentence_2_tomorrow.npz",
                                 "summary": "sentence_2_tomorrow.json"}}
    assert not (tmp_path / "sentence_2_tomorrow.mp4").exists()


def test_produce_refusals(params, body, tmp_path):
    with pytest.raises(ProductionError, match=r"no training clip with text in sign language 'DGS-SYN'; the training "
                                              r"shards hold \['ASL-SYN'\]"):
        produce("sentence 1", "DGS-SYN", params, "retrieval", body=body)
    with pytest.raises(ProductionError, match=r"^empty text: give a sentence to produce$"):
        produce("  ", "ASL-SYN", params, "retrieval", body=body)
    with pytest.raises(ProductionError, match=r"SMLM checkpoint .*smlm\.pt not found; run `dvc repro train-smlm`"):
        produce("sentence 1", "ASL-SYN", params, "smlm", body=body)
    from dataclasses import replace

    nowhere = replace(params, data=replace(params.data, shards_root=str(tmp_path / "none")))
    with pytest.raises(ProductionError, match=r"shard .*train\.parquet not found; run the fit-corpus stage"):
        produce("sentence 1", "ASL-SYN", nowhere, "retrieval", body=body)
    # the tiny shards hold no isolated sign: the lexicon has no entry; checkpoints of PT / SGSA are missing
    with pytest.raises(ProductionError, match=r"hold no isolated sign with a gloss: the lexicon baseline has no entry"):
        produce("sentence 1", "ASL-SYN", params, "lexicon", body=body)
    with pytest.raises(ProductionError, match=r"sgsa\.pt not found; run `dvc repro train-sgsa`"):
        produce("sentence 1", "ASL-SYN", params, "sgsa", body=body)
    with pytest.raises(ProductionError, match=r"a lexicon folder is the lexicon system's input; --system is 'smlm'"):
        produce("sentence 1", "ASL-SYN", params, "smlm", body=body, lexicon_dir=tmp_path)


def test_lexicon_from_a_pose_folder_writes_a_holistic_pose(params, body, tmp_path):
    """spoken-to-signed's shipped fingerspelling lexicon as the user's folder: a word spelled from its letters."""
    from pose_format import Pose

    from m3t.corpora.fingerspelling import lexicon_root

    result = produce("Hi!", "ase", params, "lexicon", out=tmp_path, body=body, lexicon_dir=lexicon_root())
    assert result.details["signs"] == "h i" and result.details["fingerspelled"] == "hi"
    pose = Pose.read((tmp_path / "hi.pose").read_bytes())
    assert pose.body.data.shape[0] == result.frames > 0 and pose.body.fps == 25.0
    assert [c.name for c in pose.header.components][:4] == ["POSE_LANDMARKS", "FACE_LANDMARKS",
                                                            "LEFT_HAND_LANDMARKS", "RIGHT_HAND_LANDMARKS"]
    summary = json.loads((tmp_path / "hi.json").read_text())
    assert summary["system"] == "lexicon" and set(summary["files"]) == {"pose", "points", "summary"}
    with pytest.raises(ProductionError, match=r"no entry of signed language 'xyz'"):
        produce("hi", "xyz", params, "lexicon", body=body, lexicon_dir=lexicon_root())


def test_translate_reads_parameter_files(body, tmp_path):
    dims = dict(body.layout.dims)
    arrays = {m: np.full((5, d), 0.5, np.float32) for m, d in dims.items()}
    np.savez(tmp_path / "ok.npz", **arrays)
    params, identity = _parameters(tmp_path / "ok.npz", body)
    assert {m: v.shape for m, v in params.items()} == {m: (5, d) for m, d in dims.items()}
    np.testing.assert_array_equal(identity, body.default_identity().numpy())
    np.savez(tmp_path / "id.npz", **arrays, identity=np.ones(len(identity), np.float32))
    assert _parameters(tmp_path / "id.npz", body)[1].sum() == len(identity)
    first = next(iter(dims))
    np.savez(tmp_path / "ragged.npz", **{**arrays, first: np.zeros((4, dims[first]), np.float32)})
    with pytest.raises(ProductionError, match=r"ragged\.npz: parameters .*; expected \(T > 0, D\) per modality "
                                              r"with one T"):
        _parameters(tmp_path / "ragged.npz", body)
    np.savez(tmp_path / "empty.npz", **{m: np.zeros((0, d), np.float32) for m, d in dims.items()})
    with pytest.raises(ProductionError, match=r"empty\.npz: parameters"):
        _parameters(tmp_path / "empty.npz", body)


def test_translate_input_kinds(tmp_path):
    for name, kind in (("a.MP4", "video"), ("a.webm", "video"), ("a.pose", "pose"), ("a.npz", "parameters")):
        (tmp_path / name).write_bytes(b"")
        assert input_kind(tmp_path / name) == kind
    (tmp_path / "noext").write_bytes(b"")
    with pytest.raises(ProductionError, match=r"noext: cannot translate a suffix-less file"):
        input_kind(tmp_path / "noext")
