"""Real-corpus adapters on fixture trees in each documented layout, plus the packaged fingerspelling corpus."""
from __future__ import annotations

import collections
import csv
import dataclasses
import gzip
import json
import pickle
import sys
from pathlib import Path

import numpy as np
import pytest

import corpus_fixtures as fx
from m3t.corpora.base import (
    CORPORA, MEDIA_KINDS, SPLITS, CorpusError, Listing, Quarantined, hash_split, open_corpus,
)
from m3t.corpora.fingerspelling import FingerspellingCorpus, lexicon_root, spell
from m3t.corpora.fitted_pickles import SmplxSequenceError, load_smplx_sequence
from m3t.corpora.mead import read_flame_params
from m3t.corpora.posefile import read_pose, read_pose_info


def counts(listing: Listing) -> dict[str, int]:
    found = collections.Counter(c.split for c in listing.clips)
    return {s: found.get(s, 0) for s in SPLITS}


def check_listing(listing: Listing, fixture: fx.Fixture, root: Path | None = None) -> None:
    """Per-split counts, common clip fields, and exactly the expected quarantine records."""
    root = root or fixture.root
    if "all" in fixture.per_split:
        assert len(listing.clips) == fixture.per_split["all"]
    else:
        assert counts(listing) == {s: fixture.per_split.get(s, 0) for s in SPLITS}
    for clip in listing.clips:
        assert clip.split in SPLITS and clip.fps > 0 and clip.id
        assert clip.get("media_kind") in MEDIA_KINDS
        assert (root / clip.media).exists(), clip
    got = [(q.file, q.row, q.reason) for q in listing.quarantined]
    assert len(got) == len(fixture.bad), got
    for file, row, fragment in fixture.bad:
        assert any(f == file and r == row and fragment in reason for f, r, reason in got), (file, row, fragment, got)


# ----------------------------------------------------------------------------------------- PHOENIX-2014-T
@pytest.mark.parametrize("under_root", [False, True])
def test_phoenix14t(tmp_path, under_root):
    fixture = fx.build_phoenix14t(tmp_path, under_root)
    listing = open_corpus("phoenix14t", tmp_path).listing()
    check_listing(listing, fixture)
    clip = next(c for c in listing.clips if c.id == "train_clip1")
    assert (clip.text, clip.gloss, clip.signer, clip.language, clip.fps) == (
        "morgen regnet es", "REGEN MORGEN", "Signer01", "DGS", 25.0)
    assert clip.media == "features/fullFrame-210x260px/train/train_clip1/1" and clip.get("media_kind") == "frames"
    assert clip.label is None


def test_phoenix14t_wrong_header_and_missing_file(tmp_path):
    fx.build_phoenix14t(tmp_path)
    path = tmp_path / "annotations/manual/PHOENIX-2014-T.dev.corpus.csv"
    path.write_text(path.read_text().replace("speaker", "signer"), encoding="utf-8")
    with pytest.raises(CorpusError, match=r"PHOENIX-2014-T\.dev\.corpus\.csv line 1.*expected exactly "
                                          r"'name\|video\|start\|end\|speaker\|orth\|translation'"):
        open_corpus("phoenix14t", tmp_path).listing()
    path.unlink()
    with pytest.raises(CorpusError, match="PHOENIX-2014-T.dev.corpus.csv not found"):
        open_corpus("phoenix14t", tmp_path).listing()


# ----------------------------------------------------------------------------------------- How2Sign
def test_how2sign(tmp_path):
    fixture = fx.build_how2sign(tmp_path)
    listing = open_corpus("how2sign", tmp_path).listing()
    check_listing(listing, fixture)
    clip = next(c for c in listing.clips if c.id == "valvid1_1-5-rgb_front")
    assert clip.split == "dev" and clip.signer == "unknown" and clip.language == "ASL" and clip.fps == 24.0
    assert clip.text == "And now we stir sentence 1." and clip.gloss == ""
    assert (float(clip.get("start_s")), float(clip.get("end_s"))) == (2.5, 5.25)
    assert clip.media == "sentence_level/val/rgb_front/raw_videos/valvid1_1-5-rgb_front.mp4"
    assert {c.fps for c in open_corpus("how2sign", tmp_path, fps=30.0).clips()} == {30.0}


def test_how2sign_comma_header_is_refused(tmp_path):
    fx.build_how2sign(tmp_path)
    path = tmp_path / "how2sign_realigned_test.csv"
    path.write_text(path.read_text().replace("\t", ","), encoding="utf-8")
    with pytest.raises(CorpusError, match="how2sign_realigned_test.csv line 1"):
        open_corpus("how2sign", tmp_path).listing()


# ----------------------------------------------------------------------------------------- CSL-Daily
def test_csl_daily(tmp_path):
    fixture = fx.build_csl_daily(tmp_path)
    listing = open_corpus("csl_daily", tmp_path).listing()
    check_listing(listing, fixture)
    clip = next(c for c in listing.clips if c.id == "S000004_P0000_T00")
    assert (clip.split, clip.text, clip.gloss, clip.signer, clip.fps, clip.language) == (
        "dev", "你好吗", "你 好", "1", 30.0, "CSL")
    assert clip.get("chars") == "你好吗" and clip.get("media_kind") == "frames"


@pytest.mark.parametrize("payload, refused", [(None, "getcwd"), (np.zeros(3), "numpy")])
def test_csl_daily_refuses_non_data_pickles(tmp_path, payload, refused):
    fx.build_csl_daily(tmp_path)
    fx.write_hostile_pickle(tmp_path / "sentence_label/csl2020ct_v2.pkl", payload)
    with pytest.raises(CorpusError, match=rf"csl2020ct_v2.pkl: the pickle references \S*{refused}\S*, a non-data "
                                          r"class, and was refused"):
        open_corpus("csl_daily", tmp_path).listing()


# ----------------------------------------------------------------------------------------- NMFs-CSL
def test_nmfs_csl_without_subset_list(tmp_path):
    fixture = fx.build_nmfs_csl(tmp_path)
    corpus = open_corpus("nmfs_csl", tmp_path)
    listing = corpus.listing()
    check_listing(listing, fixture)
    by_id = {c.id: c for c in listing.clips}
    clip = by_id["P02__2_01"]
    assert (clip.label, clip.text, clip.gloss, clip.fps) == (2, "对不起", "对不起", 30.0)
    assert clip.media == "video/P02/2_01.mp4"
    assert by_id["video__P05__3_01"].media == "video/P05/3_01.mp4"
    assert {c.get("subset") for c in listing.clips} == {"unknown"}
    with pytest.raises(CorpusError, match="confusing_list"):
        corpus.subset(0)


def test_nmfs_csl_subsets_and_dev_split(tmp_path):
    fx.build_nmfs_csl(tmp_path)
    corpus = open_corpus("nmfs_csl", tmp_path, confusing_list="confusing.txt", dev_fraction=0.5)
    first = corpus.listing()
    assert first.clips == corpus.listing().clips  # the dev carve-out is deterministic
    subsets = {c.label: c.get("subset") for c in first.clips}
    assert subsets == {0: "confusing", 1: "normal", 2: "confusing", 3: "normal"}
    assert corpus.subset(2) == "confusing" and corpus.subset(3) == "normal"
    split = counts(first)
    assert split["train"] + split["dev"] == 5 and split["test"] == 3 and split["dev"] > 0
    assert all(c.get("source_split") == "train" for c in first.clips if c.split == "dev")
    with pytest.raises(ValueError, match="dev_fraction"):
        open_corpus("nmfs_csl", tmp_path, dev_fraction=1.0)


# ----------------------------------------------------------------------------------------- MEAD
def test_mead_listing_and_subject_splits(tmp_path):
    fixture = fx.build_mead(tmp_path)
    listing = open_corpus("mead", tmp_path).listing()
    check_listing(listing, fixture)
    by_subject = collections.defaultdict(set)
    for c in listing.clips:
        by_subject[c.signer].add(c.split)
        assert c.split == hash_split(c.signer, (0.8, 0.1, 0.1), salt="mead-subject")
    assert all(len(s) == 1 for s in by_subject.values())
    clip = next(c for c in listing.clips if c.id == "W009_happy_level_3_001")
    assert (clip.text, clip.language, clip.fps) == ("happy level_3", "none", 25.0)
    assert clip.get("media_kind") == "flame_params"
    named = open_corpus("mead", tmp_path, dev_subjects=["W009"], test_subjects=["M012"]).listing()
    assert {c.signer: c.split for c in named.clips} == {"M003": "train", "M005": "train", "W009": "dev",
                                                        "W011": "train", "M012": "test"}


def test_mead_read_flame_params(tmp_path, monkeypatch):
    fx.build_mead(tmp_path)
    params = read_flame_params(tmp_path / "M005/angry/level_1/001/shape_pose_cam.npz")
    assert {k: v.shape for k, v in params.items()} == {"exp": (4, 50), "jaw": (4, 3), "global_pose": (4, 3),
                                                        "shape": (4, 100), "cam": (4, 3)}
    bad = tmp_path / "bad.npz"
    np.savez(bad, **{k: v for k, v in fx.flame_arrays().items() if k != "jaw"})
    with pytest.raises(CorpusError, match=r"bad.npz lacks datasets \['jaw'\]"):
        read_flame_params(bad)
    monkeypatch.setitem(sys.modules, "h5py", None)  # import h5py now fails as if not installed
    with pytest.raises(ImportError, match="pip install h5py"):
        read_flame_params(tmp_path / "M003/neutral/level_1/002/shape_pose_cam.hdf5")


def test_mead_read_hdf5(tmp_path):
    h5py = pytest.importorskip("h5py")
    arrays = fx.flame_arrays(6)
    with h5py.File(tmp_path / "shape_pose_cam.hdf5", "w") as f:
        for k, v in arrays.items():
            f.create_dataset(k, data=v)
    params = read_flame_params(tmp_path / "shape_pose_cam.hdf5")
    for k, v in arrays.items():
        np.testing.assert_array_equal(params[k], v)


# ----------------------------------------------------------------------------------------- fitted pickles
def test_soke_smplx(tmp_path):
    fixture = fx.build_soke(tmp_path)
    listing = open_corpus("soke_smplx", tmp_path, annotation="annotation.csv", validate=True).listing()
    check_listing(listing, fixture)
    clip = next(c for c in listing.clips if c.id == "b1")
    assert (clip.split, clip.text, clip.gloss, clip.signer, clip.get("media_kind"), clip.get("frames")) == (
        "dev", "text of b1", "GLOSS B1", "s1", "smplx_params", "3")
    seq = load_smplx_sequence(tmp_path / "val/b1")
    with open(tmp_path / "val/b1/10.pkl", "rb") as fh:
        last = pickle.load(fh)
    assert seq["body_pose"].shape == (3, 63) and seq["expression"].shape == (3, 10) and "leye_pose" not in seq
    np.testing.assert_array_equal(seq["body_pose"][2], last["body_pose"])  # frame 10 after frame 2: numeric order
    unchecked = open_corpus("soke_smplx", tmp_path, annotation="annotation.csv").listing()
    assert counts(unchecked)["train"] == 4 and len(unchecked.quarantined) == 2
    with pytest.raises(SmplxSequenceError) as info:
        load_smplx_sequence(tmp_path / "train/bad_key")
    assert info.value.file.name == "1.pkl" and info.value.key == "left_hand_pose"


def test_slt_pickles(tmp_path):
    fixture = fx.build_slt(tmp_path)
    corpus = open_corpus("slt_pickle", tmp_path, language="DGS")
    listing = corpus.listing()
    check_listing(listing, fixture)
    clip = next(c for c in listing.clips if c.id == "dev__clip1")
    assert (clip.signer, clip.gloss, clip.text, clip.language, clip.get("media_kind")) == (
        "Signer01", "REGEN MORGEN", "es regnet", "DGS", "keypoints")
    assert corpus.sequence(clip).shape == (6, 12)
    (tmp_path / "extra.pkl.gz").write_bytes(b"")  # no split in the name: reported, not skipped
    assert Quarantined("extra.pkl.gz", None, None, "cannot tell the split from the file name (.train/.dev/.test)") \
        in open_corpus("slt_pickle", tmp_path).listing().quarantined


def test_slt_refuses_torch_and_unknown_classes(tmp_path):
    fx.build_slt(tmp_path)
    fx.write_torch_slt(tmp_path / "phoenix14t.pami0.dev")
    with pytest.raises(CorpusError, match=r"pami0.dev: the pickle references torch\S*.*tensor\.numpy\(\)"):
        open_corpus("slt_pickle", tmp_path).listing()
    with gzip.open(tmp_path / "phoenix14t.pami0.dev", "wb") as fh:
        pickle.dump([collections.OrderedDict(name="x")], fh)
    with pytest.raises(CorpusError, match="collections.OrderedDict, a non-data class"):
        open_corpus("slt_pickle", tmp_path).listing()


# ----------------------------------------------------------------------------------------- .pose files
@pytest.fixture(scope="module")
def lexicon_rows() -> list[dict]:
    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def test_posefile_index_collection(tmp_path, lexicon_rows):
    fixture = fx.build_pose_collection(tmp_path, lexicon_root(), lexicon_rows)
    listing = open_corpus("posefile", tmp_path, index="index.csv").listing()
    check_listing(listing, fixture)
    clip = next(c for c in listing.clips if c.id == "c1")
    info = read_pose_info(tmp_path / clip.media)
    assert (clip.label, clip.text, clip.language, clip.signer, clip.fps) == (1, "B", "ase", "s1", info.fps)
    data = read_pose(tmp_path / clip.media)
    assert data.points.shape == (info.frames, 586, 3) and data.confidence.shape == (info.frames, 586)
    assert data.points.dtype == np.float32 and sum(n for _, n in data.components) == 586
    with pytest.raises(CorpusError, match="truncated.pose: (unreadable or )?truncated"):
        read_pose(tmp_path / "poses/truncated.pose")


def test_posefile_walk_without_index(tmp_path, lexicon_rows):
    fx.build_pose_collection(tmp_path, lexicon_root(), lexicon_rows)
    listing = open_corpus("posefile", tmp_path, language="ase").listing()
    assert len(listing.clips) == 4 and [q.clip_id for q in listing.quarantined] == ["poses__truncated"]
    assert "truncated" in listing.quarantined[0].reason
    assert all(c.split == hash_split(c.id, (0.8, 0.1, 0.1), salt="posefile") for c in listing.clips)


# ----------------------------------------------------------------------------------------- fingerspelling
@pytest.fixture(scope="module")
def fingerspelling():
    corpus = FingerspellingCorpus()
    return corpus, corpus.listing()


def test_fingerspelling_letters_match_the_packaged_table(fingerspelling, lexicon_rows):
    corpus, listing = fingerspelling
    letters = [c for c in listing.clips if c.get("media_kind") == "pose"]
    languages = {r["signed_language"] for r in lexicon_rows}
    assert listing.quarantined == ()
    assert len(letters) == len(lexicon_rows) == 600 and len(languages) == 19  # found in spoken-to-signed 0.4.0
    per_language = collections.Counter(r["signed_language"] for r in lexicon_rows)
    for language, n in per_language.items():
        assert sorted(c.label for c in letters if c.language == language) == list(range(n))
    for row, clip in zip(lexicon_rows, letters, strict=True):
        assert (clip.media, clip.text, clip.language) == (row["path"], row["words"], row["signed_language"])
        assert (corpus.root / clip.media).is_file() and clip.fps > 0
    assert set(counts(listing)) == set(SPLITS) and min(counts(listing).values()) > 0


def test_fingerspelling_spelled_words(fingerspelling):
    corpus, listing = fingerspelling
    spelled = [c for c in listing.clips if c.get("media_kind") == "spelled"]
    assert len(spelled) == 19 * corpus.config.words_per_language
    assert [c.text for c in spelled] == [c.text for c in FingerspellingCorpus().listing().clips
                                         if c.get("media_kind") == "spelled"]
    fps_of = {c.media: c.fps for c in listing.clips if c.get("media_kind") == "pose"}
    mixed = [c for c in spelled if len({fps_of[p] for p in c.get("letter_paths").split("|")}) > 1]
    assert mixed, "the lexicon has languages whose letters differ in fps (gss, sgg)"
    for clip in spelled[:5] + mixed[:5]:
        data = corpus.spell(clip.text, clip.language)
        assert data.points.shape[0] == int(clip.get("frames")) and data.fps == clip.fps
        assert clip.gloss.split() == corpus.tokenize(clip.text, clip.language)
    assert corpus.tokenize("chschä", "asq") == ["C", "H", "SCH", "Ä"]
    a, b = corpus.spell("A", "ase"), corpus.spell("B", "ase")
    ab = spell("a b", "ase")
    np.testing.assert_array_equal(ab.points, np.concatenate([a.points, b.points]))
    with pytest.raises(CorpusError, match="cannot be fingerspelled in ase"):
        corpus.spell("A1", "ase")


def test_fingerspelling_index_table_adds_aliases():
    listing = open_corpus("fingerspelling", None, table="index.csv", words_per_language=0, languages=["fsl"]).listing()
    assert len(listing.clips) == 26 and {c.language for c in listing.clips} == {"fsl"}


# ----------------------------------------------------------------------------------------- registry
def test_registry(tmp_path):
    assert set(CORPORA) == {"synthetic", "phoenix14t", "how2sign", "csl_daily", "nmfs_csl", "mead", "soke_smplx",
                            "slt_pickle", "posefile", "fingerspelling"}
    with pytest.raises(ValueError, match="expected one of"):
        open_corpus("phoenix2014", tmp_path)
    with pytest.raises(ValueError, match="unknown options \\['frame_rate'\\]"):
        open_corpus("how2sign", tmp_path, frame_rate=25)
    record = {"id": "a", "corpus": "synthetic", "split": "train", "language": "ASL-SYN", "signer": "s", "text": "t",
              "gloss": "G", "media": "motion/a.npz", "fps": 25.0, "label": None, "extra": [["kind", "sentence"]]}
    (tmp_path / "clips.jsonl").write_text(json.dumps(record) + "\n", encoding="utf-8")
    (clip,) = open_corpus("synthetic", tmp_path).clips()
    assert clip.get("media_kind") == "synthetic" and clip.get("kind") == "sentence"
    assert dataclasses.replace(clip, extra=()).id == "a"
