"""The readers of already-fitted corpora (:mod:`m3t.corpora.soke_smplx`, :mod:`m3t.corpora.slt_pickle`): SMPL-X
export folders, SOKE's annotations and frames (both namings, the keys a renamed frame keeps), neccam/slt's records;
what their errors name and what they quarantine. Written to pin behaviours that mutation testing found unchecked.
"""
from __future__ import annotations

import gzip
import pickle
from pathlib import Path

import corpus_fixtures as fx
import numpy as np
import pytest

from m3t.corpora.clip import Clip
from m3t.corpora.listing import Collector, CorpusError, Quarantined
from m3t.corpora.slt_pickle import SltPickleCorpus
from m3t.corpora.soke_smplx import (
    SmplxSequenceError,
    SokeSmplxConfig,
    SokeSmplxCorpus,
    load_smplx_sequence,
)


# ----------------------------------------------------------------------------------------- SOKE SMPL-X fits
def test_missing_smplx_clip_folder_error_names_the_folder(tmp_path):
    folder = tmp_path / "train" / "poses" / "-fZc293MpJk_0-1-rgb_front"
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(folder)
    assert str(folder) in str(err.value) and "not found" in str(err.value)
    assert err.value.file == folder and err.value.key is None


def test_frame_mixing_both_namings_is_refused_naming_the_file_and_key(tmp_path):
    """A frame holding SOKE's ``smplx_root_pose`` and the smplx package's ``global_orient`` is ambiguous."""
    folder = tmp_path / "clip"
    folder.mkdir()
    frame = fx.smplx_frame(np.random.default_rng(0))
    frame["global_orient"] = frame["smplx_root_pose"].copy()
    with open(folder / "0.pkl", "wb") as fh:
        pickle.dump(frame, fh)
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(folder)
    message = str(err.value)
    assert str(folder / "0.pkl") in message and "'smplx_root_pose'" in message and "'global_orient'" in message
    assert err.value.file == folder / "0.pkl" and err.value.key == "smplx_root_pose"


def test_soke_clips_without_annotation_have_empty_text_and_gloss(tmp_path):
    fx.build_soke(tmp_path, "phoenix")
    listing = SokeSmplxCorpus(tmp_path, SokeSmplxConfig()).listing()
    assert len(listing.clips) == 7  # every clip folder with frames, the broken ones too (validate is off)
    assert all(c.text == "" and c.gloss == "" for c in listing.clips)
    assert all(c.signer == "unknown" and c.language == "unknown" for c in listing.clips)


def test_soke_annotation_without_gloss_column_gives_empty_gloss(tmp_path):
    fx.build_soke(tmp_path, "phoenix")
    (tmp_path / "notes.csv").write_text("id,text\nb1_0-8-rgb_front,guten morgen\n", encoding="utf-8")
    listing = SokeSmplxCorpus(tmp_path, SokeSmplxConfig(annotation="notes.csv")).listing()
    (clip,) = listing.clips
    assert (clip.id, clip.split, clip.text, clip.gloss) == ("b1_0-8-rgb_front", "dev", "guten morgen", "")
    assert clip.get("frames") == "3"


# ----------------------------------------------------------------------------------------- SMPL-X fits, slt pickles
def _write_frames(folder: Path, frames: list[dict]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for n, frame in enumerate(frames):
        with open(folder / f"{n}.pkl", "wb") as fh:
            pickle.dump(frame, fh)


def test_smplx_export_names_are_read_in_both_array_shapes_and_checked_per_key(tmp_path):
    """Exports with the smplx package's names (``fx.smplx_frame(names="smplx")``) store (D,) or (1, D) arrays;
    both stack to (T, D). A wrong or missing key is named as the file names it."""
    rng = np.random.default_rng(4)
    frames = [fx.smplx_frame(rng, names="smplx") for _ in range(3)]
    frames[1] = {k: v[None] for k, v in frames[1].items()}  # (1, D), as some exporters write
    _write_frames(tmp_path / "clip", frames)
    seq = load_smplx_sequence(tmp_path / "clip")
    assert {k: v.shape for k, v in seq.items()} == {
        "global_orient": (3, 3), "body_pose": (3, 63), "left_hand_pose": (3, 45), "right_hand_pose": (3, 45),
        "jaw_pose": (3, 3), "expression": (3, 10), "betas": (3, 10), "transl": (3, 3)}
    np.testing.assert_array_equal(seq["body_pose"][1], frames[1]["body_pose"][0])

    missing = [dict(f) for f in frames]
    del missing[2]["body_pose"]
    _write_frames(tmp_path / "missing", missing)
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(tmp_path / "missing")
    assert str(err.value) == f"{tmp_path / 'missing' / '2.pkl'}: SMPL-X key 'body_pose' missing"
    assert (err.value.file, err.value.key) == (tmp_path / "missing" / "2.pkl", "body_pose")

    for key, width, names in (("global_orient", 4, "smplx"), ("smplx_root_pose", 4, "soke"),
                              ("right_hand_pose", 48, "smplx"), ("transl", 2, "smplx")):
        frame = fx.smplx_frame(rng, names=names)
        frame[key] = np.zeros(width, np.float32)
        _write_frames(tmp_path / key, [frame])
        with pytest.raises(SmplxSequenceError) as err:
            load_smplx_sequence(tmp_path / key)
        expected = {"transl": 3, "right_hand_pose": 45}.get(key, 3)
        assert str(err.value) == f"{tmp_path / key / '0.pkl'}: key {key!r} has {width} values; expected {expected}"
        assert (err.value.file, err.value.key) == (tmp_path / key / "0.pkl", key)

    without_transl = {k: v for k, v in fx.smplx_frame(rng, names="smplx").items() if k != "transl"}
    for name, pair, expected in (("late", [without_transl, frames[0]], "present but absent in 0.pkl"),
                                 ("dropped", [frames[0], without_transl], "missing (present in 0.pkl)")):
        _write_frames(tmp_path / name, pair)  # an optional key is kept only when every frame has it
        with pytest.raises(SmplxSequenceError) as err:
            load_smplx_sequence(tmp_path / name)
        assert str(err.value) == f"{tmp_path / name / '1.pkl'}: key 'transl' {expected}"
        assert (err.value.file, err.value.key) == (tmp_path / name / "1.pkl", "transl")


def test_soke_empty_clip_folder_and_repeated_annotation_id_are_quarantined_with_every_field(tmp_path):
    fx.build_soke(tmp_path, "phoenix")  # SOKE's Phoenix layout, see corpus_fixtures.build_soke
    (tmp_path / "notes.csv").write_text("id,text,gloss,signer\nb1_0-8-rgb_front,guten morgen,,\n"
                                        "c1_3-5-rgb_front,es regnet,REGEN,s3\nb1_0-8-rgb_front,noch einmal,,\n",
                                        encoding="utf-8")
    listing = SokeSmplxCorpus(tmp_path, SokeSmplxConfig(annotation="notes.csv")).listing()
    assert {c.id: (c.split, c.text, c.gloss, c.signer) for c in listing.clips} == {
        "b1_0-8-rgb_front": ("dev", "guten morgen", "", "unknown"),
        "c1_3-5-rgb_front": ("test", "es regnet", "REGEN", "s3")}
    assert listing.quarantined[0] == Quarantined("notes.csv", 4, "b1_0-8-rgb_front", "id listed twice")
    assert Quarantined("train/empty", None, "empty", "missing media (no <frame>.pkl files)") in listing.quarantined


def test_soke_clip_folder_linking_out_of_the_root_is_refused_before_it_is_read(tmp_path):
    root, outside = tmp_path / "soke", tmp_path / "elsewhere" / "clip"
    fx.build_soke(root, "phoenix")
    outside.mkdir(parents=True)  # holds no frame pickles: only the link is wrong
    (root / "train" / "escape").symlink_to(outside, target_is_directory=True)
    listing = SokeSmplxCorpus(root).listing()
    (q,) = [q for q in listing.quarantined if q.clip_id == "escape"]
    assert q.file == "train/escape" and q.row is None
    assert q.reason.startswith("unsafe media path: 'train/escape' resolves outside the corpus root")
    assert q.reason.endswith("point the root at a folder that holds it: train/escape")
    assert "escape" not in {c.id for c in listing.clips}


def test_slt_records_that_are_not_named_dicts_are_quarantined_and_clips_record_their_shape(tmp_path):
    """Records of neccam/slt's gzip pickles (``fx.slt_entries``), with the kinds of broken record one meets."""
    rng = np.random.default_rng(0)
    entries = fx.slt_entries("train", 2, rng, dims=12)
    entries += [["train/listed", "s", "", "", np.zeros((2, 3), np.float32)],
                {**fx.slt_entries("train", 1, rng)[0], "name": ""},
                {**fx.slt_entries("train", 1, rng)[0], "name": 17},
                {**fx.slt_entries("train", 1, rng)[0], "name": "train/ints", "sign": np.zeros((3, 4), np.int64)},
                {**fx.slt_entries("train", 1, rng)[0], "name": "train/none", "sign": np.zeros((0, 4), np.float32)},
                {**fx.slt_entries("train", 1, rng)[0], "name": "train/nested", "sign": [[0.5, 0.5]]}]
    with gzip.open(tmp_path / "phoenix14t.pami0.train", "wb") as fh:
        pickle.dump(entries, fh)
    listing = SltPickleCorpus(tmp_path).listing()
    assert [(c.id, c.split, c.signer, c.media) for c in listing.clips] == [
        ("train__clip0", "train", "Signer00", "phoenix14t.pami0.train"),
        ("train__clip1", "train", "Signer01", "phoenix14t.pami0.train")]
    assert [dict(c.extra) for c in listing.clips] == [
        {"media_kind": "keypoints", "index": str(i), "frames": str(5 + i), "dims": "12", "name": f"train/clip{i}"}
        for i in range(2)]
    file = "phoenix14t.pami0.train"
    q = listing.quarantined
    assert (q[0], *q[2:]) == (
        Quarantined(file, 2, None, "entry is a list, expected a dict with keys name, signer, gloss, text, sign"),
        Quarantined(file, 4, None, "name is not a non-empty string"),
        Quarantined(file, 5, "train/ints", "sign is (3, 4); expected a non-empty (T, D) float array"),
        Quarantined(file, 6, "train/none", "sign is (0, 4); expected a non-empty (T, D) float array"),
        Quarantined(file, 7, "train/nested", "sign is list; expected a non-empty (T, D) float array"))
    assert len(q) == 6 and q[1] == Quarantined(file, 3, None, "name is not a non-empty string")  # "" is no id


def test_smplx_clip_folders_without_usable_frames_are_refused_naming_the_folder(tmp_path):
    empty = tmp_path / "train" / "empty_clip"
    empty.mkdir(parents=True)
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(empty)
    assert (str(err.value), err.value.file, err.value.key) == (
        f"{empty}: missing media (no <frame>.pkl files)", empty, None)
    (empty / "frame.pkl").write_bytes(b"")
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(str(empty))
    assert str(err.value).startswith(f"{empty}: frame pickle frame.pkl has no frame number (expected <n>.pkl")
    assert (err.value.file, err.value.key) == (empty, None)


def test_soke_annotation_errors_name_the_file_and_malformed_rows_are_quarantined(tmp_path):
    fx.build_soke(tmp_path, "phoenix")
    corpus = SokeSmplxCorpus(tmp_path, SokeSmplxConfig(annotation="notes.csv"))
    with pytest.raises(CorpusError) as err:
        corpus.read_annotation(Collector(tmp_path))
    assert str(err.value) == (f"{tmp_path / 'notes.csv'} not found. Set corpora.soke_smplx.annotation to a CSV with "
                              f"columns id,text[,gloss,signer,language,split].")
    (tmp_path / "notes.csv").write_text("id,text\n,no id\nb1,hello,extra\nb1,ok\nb1,again\n", encoding="utf-8")
    out = Collector(tmp_path)
    rows = corpus.read_annotation(out)
    assert rows == {"b1": {"id": "b1", "text": "ok", "row": "4"}}
    assert out.listing().quarantined == (
        Quarantined("notes.csv", 2, None, "malformed row: empty id or extra columns"),
        Quarantined("notes.csv", 3, "b1", "malformed row: empty id or extra columns"),
        Quarantined("notes.csv", 5, "b1", "id listed twice"))
    assert SokeSmplxCorpus(tmp_path, SokeSmplxConfig()).read_annotation(out) is None


def test_an_slt_clip_whose_record_moved_is_refused_naming_the_file_and_clip(tmp_path):
    built = fx.build_slt(tmp_path)
    corpus = SltPickleCorpus(tmp_path)
    clip = next(c for c in corpus.listing().clips if c.split == "dev")
    assert corpus.sequence(clip).dtype == np.float32
    for extra in ((("index", "99"),), (("index", clip.get("index")), ("name", "dev/other"))):
        moved = Clip(clip.id, clip.corpus, clip.split, clip.language, clip.signer, clip.text, clip.gloss, clip.media,
                     clip.fps, extra=extra)
        with pytest.raises(CorpusError) as err:
            corpus.sequence(moved)
        index = moved.get("index")
        assert str(err.value) == (f"{tmp_path / built.extra['files']['dev']}: record {index} is no longer clip "
                                  f"{clip.id}; list the corpus again")


def test_soke_frames_keep_their_other_keys_and_may_not_mix_both_namings(tmp_path):
    """SOKE's keys are renamed to the smplx package's; the frame's other keys (a translation, eye poses that some
    exports add) keep their names and are stacked like in any export. A frame holding a parameter under both
    names is refused naming the file and the SOKE key."""
    rng = np.random.default_rng(5)
    frames = [fx.smplx_frame(rng) | {"transl": np.full(3, n, np.float32), "leye_pose": np.zeros(3, np.float32),
                                      "reye_pose": np.ones(3, np.float32)} for n in range(2)]
    _write_frames(tmp_path / "clip", frames)
    seq = load_smplx_sequence(tmp_path / "clip")
    assert {k: v.shape for k, v in seq.items()} == {
        "global_orient": (2, 3), "body_pose": (2, 63), "left_hand_pose": (2, 45), "right_hand_pose": (2, 45),
        "jaw_pose": (2, 3), "expression": (2, 10), "betas": (2, 10), "transl": (2, 3), "leye_pose": (2, 3),
        "reye_pose": (2, 3)}
    np.testing.assert_array_equal(seq["transl"], [[0, 0, 0], [1, 1, 1]])
    np.testing.assert_array_equal(seq["reye_pose"], np.ones((2, 3)))
    np.testing.assert_array_equal(seq["global_orient"][1], frames[1]["smplx_root_pose"])

    mixed = fx.smplx_frame(rng) | {"global_orient": np.zeros(3, np.float32)}
    _write_frames(tmp_path / "mixed", [mixed])
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(tmp_path / "mixed")
    file = tmp_path / "mixed" / "0.pkl"
    assert str(err.value) == f"{file}: holds both 'smplx_root_pose' and 'global_orient'; keep one naming"
    assert (err.value.file, err.value.key) == (file, "smplx_root_pose")


def test_soke_annotation_language_and_signer_override_the_defaults(tmp_path):
    fx.build_soke(tmp_path, "phoenix")
    (tmp_path / "notes.csv").write_text("id,text,signer,language\nb1_0-8-rgb_front,guten morgen,Signer05,DGS\n"
                                        "c1_3-5-rgb_front,regen,,\n", encoding="utf-8")
    clips = SokeSmplxCorpus(tmp_path, SokeSmplxConfig(annotation="notes.csv", language="GSL")).listing().clips
    assert [(c.id, c.language, c.signer, c.corpus) for c in clips] == [
        ("b1_0-8-rgb_front", "DGS", "Signer05", "soke_smplx"), ("c1_3-5-rgb_front", "GSL", "unknown", "soke_smplx")]


def test_soke_csl_layout_row_with_an_unknown_split_is_quarantined_at_its_annotation_row(tmp_path):
    """SOKE's CSL-Daily layout (``poses/<clip>/<n>.pkl``, split from the annotation's ``split`` column, see
    ``build_soke``) with one row's split misspelt."""
    fx.build_soke(tmp_path, "csl")
    notes = tmp_path / "annotation.csv"
    lines = notes.read_text(encoding="utf-8").splitlines()
    row = next(i for i, line in enumerate(lines, start=1) if line.startswith("b1_0-8-rgb_front,"))
    lines[row - 1] = lines[row - 1].rsplit(",", 1)[0] + ",foo"
    notes.write_text("\n".join(lines) + "\n", encoding="utf-8")
    listing = SokeSmplxCorpus(tmp_path, SokeSmplxConfig(annotation="annotation.csv")).listing()
    assert Quarantined("annotation.csv", row, "b1_0-8-rgb_front",
                       "split 'foo'; expected one of train, dev, val, test") in listing.quarantined
    assert "b1_0-8-rgb_front" not in {c.id for c in listing.clips}
    assert {c.id: c.split for c in listing.clips}["c1_3-5-rgb_front"] == "test"
