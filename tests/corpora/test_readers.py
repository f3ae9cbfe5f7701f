"""Real-corpus adapters on fixture trees in each documented layout, plus the packaged fingerspelling corpus."""
from __future__ import annotations

import collections
import csv
import dataclasses
import gzip
import json
import pickle
import sys
from pathlib import Path, PurePosixPath

import corpus_fixtures as fx
import numpy as np
import pytest

from m3t.corpora.base import CORPORA, open_corpus
from m3t.corpora.csl_daily import INFO_KEYS, CslDailyConfig, CslDailyCorpus, _record
from m3t.corpora.fingerspelling import FingerspellingCorpus, lexicon_root, spell
from m3t.corpora.how2sign import How2SignConfig, How2SignCorpus
from m3t.corpora.listing import (
    MEDIA_KINDS,
    Collector,
    CorpusError,
    Listing,
    Quarantined,
    media_path_problem,
)
from m3t.corpora.mead import MeadCorpus, read_flame_params
from m3t.corpora.nmfs_csl import NmfsCslConfig, NmfsCslCorpus
from m3t.corpora.phoenix14t import Phoenix14TCorpus
from m3t.corpora.posefile import read_pose, read_pose_info
from m3t.corpora.soke_smplx import SmplxSequenceError, frame_number, load_smplx_sequence
from m3t.corpora.splits import SPLITS, hash_split, hash_unit


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
    real = fixture.extra["real_name"]
    clip = next(c for c in listing.clips if c.id == real)
    assert (clip.split, clip.signer, clip.language, clip.fps, clip.gloss.split()[:2]) == (
        "train", "Signer01", "DGS", 25.0, ["REGEN", "SCHNEE"])
    assert clip.text.startswith("regen und schnee lassen an den alpen")
    # the release tree: <split>/<name>/images0001.png, no "1/" folder although the video column says <name>/1/*.png
    assert clip.media == f"features/fullFrame-210x260px/train/{real}" and clip.get("media_kind") == "frames"
    assert clip.label is None and clip.get("frame_glob") == "*.png"
    assert {c.media.split("/")[2] for c in listing.clips} == {"train", "dev", "test"}  # the split folder, always
    same = next(q for q in listing.quarantined if q.clip_id == "train_same_video")  # listed under the first name
    file = ("" if under_root else "annotations/manual/") + "PHOENIX-2014-T.train.corpus.csv"
    assert f"is already the media of clip {real} ({file} row 2)" in same.reason


def test_phoenix2014_style_1_folder(tmp_path):
    """PHOENIX-2014's multisigner tree keeps the images in <split>/<name>/1/: the same rows list there too."""
    fixture = fx.build_phoenix14t(tmp_path, legacy_1_folder=True)
    listing = open_corpus("phoenix14t", tmp_path).listing()
    check_listing(listing, fixture)
    assert all(c.media.endswith("/1") for c in listing.clips)
    assert next(c for c in listing.clips if c.id == fixture.extra["real_name"]).media == (
        f"features/fullFrame-210x260px/train/{fixture.extra['real_name']}/1")


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
@pytest.mark.parametrize("layout", ["script", "archives"])
def test_how2sign(tmp_path, layout):
    fixture = fx.build_how2sign(tmp_path, layout)
    listing = open_corpus("how2sign", tmp_path).listing()
    check_listing(listing, fixture)
    real = next(c for c in listing.clips if c.id == "10om04b2LIw_26-8-rgb_front")
    assert (real.split, real.text, real.get("video_name")) == ("train", "And that ought to do it.",
                                                              "10om04b2LIw-8-rgb_front")
    assert (float(real.get("start_s")), float(real.get("end_s"))) == (137.95, 141.01)
    clip = next(c for c in listing.clips if c.id == "-valVid1xY_1-5-rgb_front")
    assert clip.split == "dev" and clip.signer == "unknown" and clip.language == "ASL" and clip.fps == 24.0
    assert clip.text == "And now we stir sentence 1." and clip.gloss == ""
    assert clip.media == fixture.extra["clip_dir"].format(split="val") + "/-valVid1xY_1-5-rgb_front.mp4"
    assert {c.fps for c in open_corpus("how2sign", tmp_path, fps=30.0).clips()} == {30.0}


def test_how2sign_without_clip_folder_names_the_places(tmp_path):
    fixture = fx.build_how2sign(tmp_path, "archives")
    for f in (tmp_path / "test_rgb_front_clips/raw_videos").iterdir():
        f.unlink()
    (tmp_path / "test_rgb_front_clips/raw_videos").rmdir()
    with pytest.raises(CorpusError, match=r"no How2Sign clip folder for split test \(looked in .*"
                                          r"sentence_level/test/rgb_front/raw_videos, .*test_rgb_front_clips"):
        open_corpus("how2sign", fixture.root).listing()


def test_how2sign_comma_header_is_refused(tmp_path):
    fx.build_how2sign(tmp_path, "archives")
    path = tmp_path / "how2sign_realigned_test.csv"
    path.write_text(path.read_text().replace("\t", ","), encoding="utf-8")
    with pytest.raises(CorpusError, match="how2sign_realigned_test.csv line 1"):
        open_corpus("how2sign", tmp_path).listing()


# ----------------------------------------------------------------------------------------- CSL-Daily
@pytest.mark.parametrize("frames_layout", ["sentence", "archive"])
def test_csl_daily(tmp_path, frames_layout):
    fixture = fx.build_csl_daily(tmp_path, frames_layout)
    listing = open_corpus("csl_daily", tmp_path).listing()
    check_listing(listing, fixture)
    clip = next(c for c in listing.clips if c.id == "S000004_P0000_T00")
    assert (clip.split, clip.text, clip.gloss, clip.signer, clip.fps, clip.language) == (
        "dev", "你好吗", "你 好", "1", 30.0, "CSL")
    assert clip.get("chars") == "你好吗" and clip.get("media_kind") == "frames"
    assert clip.media == f"{fx.CSL_FRAME_DIRS[frames_layout]}/S000004_P0000_T00"


def test_csl_daily_without_frames_names_the_places(tmp_path):
    fx.build_csl_daily(tmp_path)
    (tmp_path / "sentence").rename(tmp_path / "elsewhere")
    with pytest.raises(CorpusError, match=r"no CSL-Daily frame folder \(looked in .*sentence/frames_512x512, "
                                          r".*sentence_frames-512x512/frames_512x512\)"):
        open_corpus("csl_daily", tmp_path).listing()
    assert len(open_corpus("csl_daily", tmp_path, frames_dir="elsewhere/frames_512x512").clips()) == 6


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
    assert (by_id["2__P06_2_01"].label, by_id["2__P06_2_01"].split) == (2, "test")  # class = its numeric folder
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
    assert split["train"] + split["dev"] == 5 and split["test"] == 4 and split["dev"] > 0
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
    assert clip.get("media_kind") == "flame_params" and clip.get("view") is None
    named = open_corpus("mead", tmp_path, dev_subjects=["W009"], test_subjects=["M012"]).listing()
    assert {c.signer: c.split for c in named.clips} == {"M003": "train", "M005": "train", "W009": "dev",
                                                        "W011": "train", "M012": "test"}


def test_mead_release_layout_with_views(tmp_path):
    """EMOTE's tree has a view level: listed (front only by default), the view kept in extra and the id."""
    fixture = fx.build_mead_release(tmp_path)
    listing = open_corpus("mead", tmp_path).listing()
    check_listing(listing, fixture)
    clip = next(c for c in listing.clips if c.id == "M003_front_angry_level_1_001")
    assert (clip.signer, clip.text, clip.get("view"), clip.get("emotion"), clip.get("level"), clip.get("clip"),
            clip.media) == ("M003", "angry level_1", "front", "angry", "level_1", "001",
                            "M003/front/angry/level_1/001/shape_pose_cam.hdf5")
    both = open_corpus("mead", tmp_path, views=["front", "left_30"]).listing()
    assert len(both.clips) == 6 and not both.quarantined
    assert "M003_left_30_angry_level_1_001" in {c.id for c in both.clips}
    with pytest.raises(ValueError, match=r"corpora\.mead\.views: \['side'\]"):
        open_corpus("mead", tmp_path, views=["side"])


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
    """(T, D) and EMOTE's (1, T, D) datasets read to the same (T, D) arrays; other shapes named in the error."""
    import h5py  # a main dependency: a missing install fails here instead of skipping

    arrays = fx.flame_arrays(6, exp=100, shape=300)
    fx.write_hdf5(tmp_path / "flat" / "shape_pose_cam.hdf5", arrays)
    fx.write_hdf5(tmp_path / "batch" / "shape_pose_cam.hdf5", {k: v[None] for k, v in arrays.items()})
    for folder in ("flat", "batch"):
        params = read_flame_params(tmp_path / folder / "shape_pose_cam.hdf5")
        assert params.keys() == arrays.keys()
        for k, v in arrays.items():
            np.testing.assert_array_equal(params[k], v)
    with h5py.File(tmp_path / "batch" / "shape_pose_cam.hdf5", "a") as f:
        del f["jaw"]
        f.create_dataset("jaw", data=np.zeros((2, 6, 3), np.float32))  # two clips in one file
    with pytest.raises(CorpusError, match=r"dataset 'jaw' has shape \(2, 6, 3\); expected \(T, D\) or EMOTE's "
                                          r"\(1, T, D\)"):
        read_flame_params(tmp_path / "batch" / "shape_pose_cam.hdf5")
    short = {**arrays, "cam": arrays["cam"][:4]}
    fx.write_hdf5(tmp_path / "short" / "shape_pose_cam.hdf5", short)
    with pytest.raises(CorpusError, match="dataset 'cam' has 4 frames, 'exp' has 6"):
        read_flame_params(tmp_path / "short" / "shape_pose_cam.hdf5")


# ----------------------------------------------------------------------------------------- fitted pickles
@pytest.mark.parametrize("layout", ["how2sign", "phoenix", "csl"])
def test_soke_smplx(tmp_path, layout):
    fixture = fx.build_soke(tmp_path, layout)
    listing = open_corpus("soke_smplx", tmp_path, annotation="annotation.csv", validate=True).listing()
    check_listing(listing, fixture)
    clip = next(c for c in listing.clips if c.id == "b1_0-8-rgb_front")
    assert (clip.split, clip.text, clip.gloss, clip.signer, clip.get("media_kind"), clip.get("frames")) == (
        "dev", "text of b1_0-8-rgb_front", "GLOSS B1", "s1", "smplx_params", "3")
    folder = tmp_path / clip.media
    seq = load_smplx_sequence(folder)
    last_file = folder / fx.SOKE_FRAME_NAMES[layout].format(n=10, clip=folder.name)
    with open(last_file, "rb") as fh:
        last = pickle.load(fh)
    assert {k: v.shape for k, v in seq.items()} == {"global_orient": (3, 3), "body_pose": (3, 63),
                                                    "left_hand_pose": (3, 45), "right_hand_pose": (3, 45),
                                                    "jaw_pose": (3, 3), "betas": (3, 10), "expression": (3, 10)}
    np.testing.assert_array_equal(seq["body_pose"][2], last["smplx_body_pose"])  # frame 10 after 2: numeric order
    np.testing.assert_array_equal(seq["left_hand_pose"][2], last["smplx_lhand_pose"])
    unchecked = open_corpus("soke_smplx", tmp_path, annotation="annotation.csv").listing()
    assert counts(unchecked)["train"] == 4 and len(unchecked.quarantined) == 2
    bad_key = next(c for c in unchecked.clips if c.id == "bad_key")
    with pytest.raises(SmplxSequenceError) as info:
        load_smplx_sequence(tmp_path / bad_key.media)
    assert frame_number(info.value.file.stem) == 1 and info.value.key == "smplx_lhand_pose"


def test_soke_smplx_names_and_layout_errors(tmp_path):
    """Exports with the smplx package's key names stack the same way; a CSL-style tree without a split column
    and a root without clips say what to do."""
    rng = np.random.default_rng(0)
    frames = [fx.smplx_frame(rng, names="smplx") for _ in range(2)]
    fx._write_frames_pkl(tmp_path / "plain" / "train" / "x1", frames, [0, 1])
    seq = load_smplx_sequence(tmp_path / "plain" / "train" / "x1")
    np.testing.assert_array_equal(seq["transl"], np.stack([f["transl"] for f in frames]))
    assert open_corpus("soke_smplx", tmp_path / "plain").listing().clips[0].split == "train"
    mixed = {**fx.smplx_frame(rng), "body_pose": np.zeros(63, np.float32)}
    fx._write_frames_pkl(tmp_path / "mixed", [mixed], [0])
    with pytest.raises(SmplxSequenceError, match="holds both 'smplx_body_pose' and 'body_pose'"):
        load_smplx_sequence(tmp_path / "mixed")
    fx._write_frames_pkl(tmp_path / "csl" / "poses" / "c1", [fx.smplx_frame(rng)], [0])
    with pytest.raises(CorpusError, match="annotation to a CSV with a split column"):
        open_corpus("soke_smplx", tmp_path / "csl").listing()
    (tmp_path / "none").mkdir()
    with pytest.raises(CorpusError, match="none of the split folders"):
        open_corpus("soke_smplx", tmp_path / "none").listing()
    assert [frame_number(n) for n in ("12", "images0012", "a_1-b_12_3D", "frame_x")] == [12, 12, 12, None]


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
    assert len(listing.clips) == 4
    assert {q.clip_id: q.reason.split(":")[0] for q in listing.quarantined} == {
        "poses__truncated": "poses/truncated.pose", "poses__junk": "poses/junk.pose"}
    assert all("truncated" in q.reason for q in listing.quarantined)
    assert all(c.split == hash_split(c.id, (0.8, 0.1, 0.1), salt="posefile") for c in listing.clips)


# ----------------------------------------------------------------------------------------- unsafe media paths
@pytest.mark.parametrize("media, fragment", [
    ("", "empty path"), ("/etc/passwd", "is absolute"), ("C:\\corpus\\a.mp4", "is absolute"),
    ("\\\\server\\share\\a.mp4", "is absolute"), ("video/../../a.mp4", "'..' component"),
    ("video\\..\\..\\a.mp4", "'..' component"), ("video/link/a.mp4", "resolves outside the corpus root"),
    ("video/a\x00.mp4", "cannot be resolved"), ("video/inner/a.mp4", None), ("--7E2sU6zP4_10-5-rgb_front.mp4", None),
])
def test_media_path_problem(tmp_path, media, fragment):
    root = tmp_path / "corpus"
    (root / "video" / "inner").mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    (root / "video" / "link").symlink_to(tmp_path / "elsewhere")
    problem = media_path_problem(root, media)
    assert problem is None if fragment is None else (problem.startswith("unsafe media path:") and fragment in problem)


def test_media_path_problem_follows_a_symlinked_root(tmp_path):
    (tmp_path / "real" / "video").mkdir(parents=True)
    (tmp_path / "root").symlink_to(tmp_path / "real")  # e.g. data/raw/phoenix14t -> a big disk
    assert media_path_problem(tmp_path / "root", "video/a.mp4") is None


def outside_rows(tmp_path: Path, depth: int, name: str) -> tuple[Path, str, str]:
    """A target beside the corpus root ``tmp_path / "corpus"`` and two annotation values reaching it from a folder
    ``depth`` levels below the root: one through ``..``, one absolute."""
    target = tmp_path / "outside" / name
    return target, "../" * (depth + 1) + f"outside/{name}", str(target)


def recording(monkeypatch, module, name: str) -> list[Path]:
    """Replace ``module.name`` (a media check or reader) by a wrapper that records the paths it is given."""
    seen: list[Path] = []
    real = getattr(module, name)

    def wrapper(path, *args, **kwargs):
        seen.append(Path(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(module, name, wrapper)
    return seen


def assert_refused(listing: Listing, ids: set[str], seen: list[Path], root: Path) -> None:
    refused = {q.clip_id: q.reason for q in listing.quarantined if q.clip_id in ids}
    assert set(refused) == ids and all(r.startswith("unsafe media path:") for r in refused.values()), refused
    assert not ids & {c.id for c in listing.clips}
    assert seen and all(p.resolve().is_relative_to(root.resolve()) for p in seen), seen  # nothing outside touched


def test_how2sign_sentence_names_leaving_the_root_are_quarantined(tmp_path, monkeypatch):
    import m3t.corpora.how2sign as how2sign

    root = tmp_path / "corpus"
    fx.build_how2sign(root, "archives")
    target, up, absolute = outside_rows(tmp_path, 2, "clip")  # clips: <root>/test_rgb_front_clips/raw_videos
    fx.write_video(target.with_suffix(".mp4"))
    path = root / "how2sign_realigned_test.csv"
    path.write_text(path.read_text() + f"v\tv-rgb\tv_8\t{up}\t1.0\t2.0\tUp.\nv\tv-rgb\tv_9\t{absolute}\t1.0\t2.0\tAbs.\n",
                    encoding="utf-8")
    seen = recording(monkeypatch, how2sign, "media_file")
    listing = open_corpus("how2sign", root).listing()
    assert_refused(listing, {up, absolute}, seen, root)
    assert counts(listing)["test"] == 2


def test_csl_daily_names_leaving_the_root_are_quarantined(tmp_path, monkeypatch):
    import m3t.corpora.csl_daily as csl_daily

    root = tmp_path / "corpus"
    fx.build_csl_daily(root)
    target, up, absolute = outside_rows(tmp_path, 2, "S900000_P0000_T00")  # frames: <root>/sentence/frames_512x512
    fx.write_frames(target, suffix=".jpg")
    pkl, split_file = root / "sentence_label/csl2020ct_v2.pkl", root / "sentence_label/split_1.txt"
    with open(pkl, "rb") as fh:
        data = pickle.load(fh)
    for name in (up, absolute):
        data["info"].append(dict(fx.CSL_REAL_INFO, name=name))
    with open(pkl, "wb") as fh:
        pickle.dump(data, fh)
    split_file.write_text(split_file.read_text() + f"{up}|train\n{absolute}|train\n", encoding="utf-8")
    checked: list[Path] = []
    real_check = csl_daily.media_folder

    def media_folder(*args):
        inner = real_check(*args)
        return lambda path: checked.append(path) or inner(path)

    monkeypatch.setattr(csl_daily, "media_folder", media_folder)
    listing = open_corpus("csl_daily", root).listing()
    assert_refused(listing, {up, absolute}, checked, root)
    assert counts(listing)["train"] == 4


def test_posefile_index_paths_leaving_the_root_are_never_read(tmp_path, monkeypatch, lexicon_rows):
    import m3t.corpora.posefile as posefile

    root = tmp_path / "corpus"
    fx.build_pose_collection(root, lexicon_root(), lexicon_rows)
    target, up, absolute = outside_rows(tmp_path, 0, "secret.pose")
    target.parent.mkdir()
    target.write_bytes((root / "poses/ase_0.pose").read_bytes())  # a valid .pose: listing it would mean reading it
    (root / "poses/link.pose").symlink_to(target)
    index = root / "index.csv"
    index.write_text(index.read_text() + f"up,{up},train,A,ase,s0,0\nabs,{absolute},train,A,ase,s0,0\n"
                     "passwd,/etc/passwd,train,A,ase,s0,0\nlink,poses/link.pose,train,A,ase,s0,0\n", encoding="utf-8")
    seen = recording(monkeypatch, posefile, "read_pose_info")
    listing = open_corpus("posefile", root, index="index.csv").listing()
    assert_refused(listing, {"up", "abs", "passwd", "link"}, seen, root)
    assert "resolves outside the corpus root" in next(q.reason for q in listing.quarantined if q.clip_id == "link")
    walked = open_corpus("posefile", root).listing()  # without an index: the walk finds the link, and refuses it
    assert "unsafe media path" in next(q.reason for q in walked.quarantined if q.clip_id == "poses__link")


def test_phoenix_and_nmfs_paths_leaving_the_root_are_quarantined(tmp_path):
    root = tmp_path / "phoenix"
    fx.build_phoenix14t(root)
    target, up, absolute = outside_rows(tmp_path, 3, "clip/1/*.png")  # features/fullFrame-210x260px/<split>/
    fx.write_phoenix_frames(target.parent)
    path = root / "annotations/manual/PHOENIX-2014-T.test.corpus.csv"
    path.write_text(path.read_text() + f"up|{up}|-1|-1|S|G|t\nabs|{absolute}|-1|-1|S|G|t\n", encoding="utf-8")
    assert_refused(open_corpus("phoenix14t", root).listing(), {"up", "abs"}, [root], root)
    root = tmp_path / "nmfs"
    fx.build_nmfs_csl(root)
    target, up, absolute = outside_rows(tmp_path, 1, "x.mp4")  # video/
    fx.write_video(target)
    path = root / "test.txt"
    path.write_text(path.read_text() + f"{up} 1\n{absolute} 1\n", encoding="utf-8")
    listing = open_corpus("nmfs_csl", root).listing()
    ids = {q.clip_id for q in listing.quarantined if q.file == "test.txt"}
    assert_refused(listing, ids, [root], root)
    assert len(ids) == 2 and counts(listing)["test"] == 4


# ----------------------------------------------------------------------------------------- text and track files
def test_non_utf8_row_names_its_line_and_byte(tmp_path):
    fx.build_phoenix14t(tmp_path)
    path = tmp_path / "annotations/manual/PHOENIX-2014-T.dev.corpus.csv"
    lines = path.read_bytes().split(b"\n")
    lines[2] = lines[2].replace(b"morgen regnet es", "morgen regnet es über".encode("latin-1"))
    path.write_bytes(b"\n".join(lines))
    offset = len(lines[0]) + 1 + len(lines[1]) + 1 + lines[2].index(b"\xfc")
    with pytest.raises(CorpusError, match=rf"PHOENIX-2014-T\.dev\.corpus\.csv line 3 \(byte {offset}\): not UTF-8"):
        open_corpus("phoenix14t", tmp_path).listing()
    path.write_bytes(b"\xef\xbb\xbf" + b"\n".join(lines))  # a BOM shifts the byte offset, not the line
    with pytest.raises(CorpusError, match=rf"line 3 \(byte {offset + 3}\)"):
        open_corpus("phoenix14t", tmp_path).listing()


def test_rows_end_at_newlines_only(tmp_path):
    """A U+2028 / U+0085 inside a sentence (and CRLF line ends) neither splits a row nor shifts row numbers."""
    fixture = fx.build_phoenix14t(tmp_path)
    path = tmp_path / "annotations/manual/PHOENIX-2014-T.train.corpus.csv"
    text = path.read_text(encoding="utf-8").replace("morgen regnet es", "morgen\u2028regnet\x85es")
    path.write_bytes(text.replace("\n", "\r\n").encode("utf-8"))
    listing = open_corpus("phoenix14t", tmp_path).listing()
    check_listing(listing, fixture)
    assert any(c.text == "morgen\u2028regnet\x85es" for c in listing.clips)


@pytest.mark.parametrize("fps", [0.0, -25.0, float("nan"), float("inf")])
def test_track_files_refuse_unusable_fps(tmp_path, fps):
    from m3t.trackers.track import Track, TrackError, load_track, save_track

    k = 543
    track = Track(np.zeros((3, k, 2), np.float32), np.ones((3, k), np.float32), "mediapipe_holistic", (8, 8), 25.0,
                  np.full(4, np.nan, np.float32), "test")
    path = save_track(track, tmp_path / "ok.npz")
    assert load_track(path).fps == 25.0
    with pytest.raises(TrackError, match=r"bad\.npz: fps .* is not a positive finite number"):
        save_track(dataclasses.replace(track, fps=fps), tmp_path / "bad.npz")
    assert not (tmp_path / "bad.npz").exists()
    with np.load(path) as data:
        fields = {name: data[name] for name in data.files}
    np.savez(tmp_path / "bad.npz", **{**fields, "fps": np.array(fps)})
    with pytest.raises(TrackError, match=r"track file .*bad\.npz: fps .* is not a positive finite number"):
        load_track(tmp_path / "bad.npz")


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


def test_resampling_a_letter_clip_keeps_its_duration_and_its_straight_line():
    """A 30 fps letter clip spelled into a 25 fps word: 1.2 s stay 1.2 s (36 -> 30 frames), a point moving at
    constant speed stays on its line, a masked neighbour takes the nearest frame; the same fps is a no-op."""
    from m3t.corpora.fingerspelling import resample
    from m3t.corpora.posefile import PoseData

    t = np.arange(36, dtype=np.float32) / 30.0
    points = np.zeros((36, 2, 3), np.float32)
    points[:, 0, 0] = 100.0 * t  # x = 100 px per second
    points[:, 1, 1] = np.arange(36)  # y = the frame index
    confidence = np.ones((36, 2), np.float32)
    confidence[7, 1] = 0.0  # point 1 masked at frame 7
    clip = PoseData(points, confidence, 30.0, (("POSE", 2),), 640, 480)
    out = resample(clip, 25.0)
    assert out.points.shape == (30, 2, 3) and out.fps == 25.0
    assert np.allclose(out.points[:, 0, 0], 100.0 * np.arange(30) / 25.0, atol=1e-4)
    # output frame 6 sits at source position 7.2: next to the masked frame 7, so it takes the nearest frame (7)
    # for point 1; point 0, seen on both sides, is interpolated
    assert out.points[6, 1, 1] == 7.0 and out.confidence[6, 1] == 0.0
    assert resample(clip, 30.0) is clip


def test_fingerspelling_splits_are_pinned(fingerspelling):
    """The split of a clip is a salted hash of its id: a changed salt or rule would move clips between train and
    test and silently invalidate every model trained before (the counts and first test ids as of this test)."""
    _, listing = fingerspelling
    counts = collections.Counter((c.get("media_kind"), c.split) for c in listing.clips)
    assert counts == {("pose", "train"): 487, ("pose", "dev"): 53, ("pose", "test"): 60,
                      ("spelled", "train"): 306, ("spelled", "dev"): 41, ("spelled", "test"): 33}
    assert sorted(c.id for c in listing.clips if c.split == "test")[:3] == [
        "ase-fs-stsc0f68923fe12ab1862f2174adfb0182a", "ase-fs-stsd4266153e5392060923bfa7668849cb6", "ase-spelled-015"]


@pytest.mark.parametrize("fps", [0.0, -25.0])
def test_mead_refuses_a_frame_rate_that_is_not_positive(fps):
    from m3t.corpora.mead import MeadConfig

    with pytest.raises(ValueError, match=f"corpora.mead.fps must be > 0, got {fps}"):
        MeadConfig(fps=fps)


# ----------------------------------------------------------------------------------------- NMFs-CSL
def test_confusing_list_rows_are_numbered_from_line_one(tmp_path):
    fx.build_nmfs_csl(tmp_path)
    (tmp_path / "confusing.txt").write_text("0\nzwei\n\n9\n2\n", encoding="utf-8")
    corpus = NmfsCslCorpus(tmp_path, NmfsCslConfig(confusing_list="confusing.txt"))
    bad = {(q.file, q.row): q.reason for q in corpus.listing().quarantined if q.file == "confusing.txt"}
    assert bad == {("confusing.txt", 2): "'zwei' is not a class index",
                   ("confusing.txt", 4): "class 9 is not in dictionary.txt"}
    with pytest.raises(CorpusError, match=r"confusing.txt line 2: 'zwei' is not a class index"):
        corpus.subset(0)
    (tmp_path / "confusing.txt").write_text("0\n2\n", encoding="utf-8")
    assert (corpus.subset(0), corpus.subset(1), corpus.subset(2)) == ("confusing", "normal", "confusing")


# ----------------------------------------------------------------------------------------- CSL-Daily pickle
def test_csl_daily_pickle_without_info_list_is_refused_naming_what_it_holds(tmp_path):
    """The annotation pickle must be the release's dict with an ``info`` list (see ``build_csl_daily``)."""
    fx.build_csl_daily(tmp_path)
    corpus = CslDailyCorpus(tmp_path)
    path = tmp_path / "sentence_label" / "csl2020ct_v2.pkl"
    info = corpus.read_info()
    assert info[0]["name"] == "S000000_P0000_T00" and fx.CSL_REAL_INFO in info and len(info) == 12
    for payload, found in (({"gloss_map": ["你"], "char_map": []}, "['char_map', 'gloss_map']"),
                           ({"info": "S000007_P0003_T00"}, "['info']"), ([fx.CSL_REAL_INFO], "list")):
        with open(path, "wb") as fh:
            pickle.dump(payload, fh)
        with pytest.raises(CorpusError) as err:
            corpus.read_info()
        assert str(err.value).startswith(f"{path}: expected a dict with an 'info' list of clip records, "
                                         f"found {found}. Point the corpus root at the CSL-Daily folder")


# ----------------------------------------------------------------------------------------- MEAD, NMFs-CSL, PHOENIX
def test_flame_files_are_read_by_suffix_and_a_missing_one_is_named(tmp_path):
    """EMOTE's release stores (1, T, D) datasets (``fx.flame_arrays(batch_axis=True)``); ``.h5`` is the same format
    as ``.hdf5``."""
    arrays = fx.flame_arrays(4, exp=100, shape=300, batch_axis=True)
    for name in ("shape_pose_cam.hdf5", "shape_pose_cam.h5"):
        fx.write_hdf5(tmp_path / name, arrays)
        params = read_flame_params(tmp_path / name)
        assert {k: v.shape for k, v in params.items()} == {"exp": (4, 100), "jaw": (4, 3), "global_pose": (4, 3),
                                                          "shape": (4, 300), "cam": (4, 3)}
        np.testing.assert_array_equal(params["jaw"], arrays["jaw"][0])
    (tmp_path / "shape_pose_cam.mat").write_bytes(b"MATLAB 5.0")
    with pytest.raises(CorpusError, match="unsupported FLAME parameter file; expected shape_pose_cam.npz or .hdf5"):
        read_flame_params(tmp_path / "shape_pose_cam.mat")
    missing = tmp_path / "M003" / "front" / "angry" / "level_1" / "001" / "shape_pose_cam.hdf5"
    with pytest.raises(CorpusError) as err:
        read_flame_params(missing)
    assert str(err.value) == f"FLAME parameter file {missing} not found"


def test_nmfs_list_blank_lines_are_skipped_and_rows_keep_their_line_numbers(tmp_path):
    fx.build_nmfs_csl(tmp_path)
    lines = (tmp_path / "train.txt").read_text(encoding="utf-8").splitlines()
    (tmp_path / "train.txt").write_text("\n".join(lines[:2] + ["", "  "] + lines[2:]) + "\n", encoding="utf-8")
    listing = NmfsCslCorpus(tmp_path).listing()
    train = [c for c in listing.clips if c.split == "train"]
    assert [c.id for c in train] == ["P01__0_01", "P01__1_01", "P02__2_01", "P02__3_01", "P03__0_02"]
    assert all(c.signer == "unknown" and c.language == "CSL" for c in listing.clips)
    assert [(q.file, q.row, q.clip_id) for q in listing.quarantined] == [
        ("train.txt", 8, "P09__9_01"), ("train.txt", 9, None), ("train.txt", 10, "P09__missing"),
        ("train.txt", 11, None)]


def test_phoenix_rows_without_name_or_frame_folder_are_quarantined_with_every_field(tmp_path):
    """Rows in the release's ``|``-separated layout (see ``fx.build_phoenix14t``) with the name or the video
    column's folder left out."""
    fixture = fx.build_phoenix14t(tmp_path)
    path = tmp_path / fx.PHOENIX_FILE.format(split="train")
    lines = path.read_text(encoding="utf-8").splitlines()
    lines.append("|26October_2010_Tuesday_tagesschau-1/1/*.png|-1|-1|Signer05|REGEN|es regnet")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    quarantined = Phoenix14TCorpus(tmp_path).listing().quarantined
    file = fx.PHOENIX_FILE.format(split="train")
    (no_folder_row,) = [row for f, row, reason in fixture.bad if "names no frame folder" in reason]
    assert Quarantined(file, no_folder_row, "train_no_folder",
                       "video column '*.png' names no frame folder; expected '<name>/1/*.png'") in quarantined
    assert quarantined[-1] == Quarantined(file, len(lines), None, "empty name")


# ----------------------------------------------------------------------------------------- split rows and errors
def test_csl_daily_split_rows_without_name_or_split_are_quarantined_and_clips_carry_the_corpus_name(tmp_path):
    """Rows of ``sentence_label/split_1.txt`` (``name|split``, see ``build_csl_daily``) with one half empty."""
    fx.build_csl_daily(tmp_path)
    split_file = tmp_path / "sentence_label" / "split_1.txt"
    lines = split_file.read_text(encoding="utf-8").splitlines()
    split_file.write_text("\n".join(lines + ["|train", "S100009_P0000_T00|", "a|b|test"]) + "\n", encoding="utf-8")
    corpus = CslDailyCorpus(tmp_path)
    out = Collector(tmp_path)
    splits = corpus.read_splits(out)
    assert "" not in splits and "S100009_P0000_T00" not in splits and splits["S000004_P0000_T00"] == ("dev", 6)
    n = len(lines)
    assert out.listing().quarantined[-3:] == (
        Quarantined("sentence_label/split_1.txt", n + 1, None,
                    "malformed row: expected '<name>|<split>', found '|train'"),
        Quarantined("sentence_label/split_1.txt", n + 2, "S100009_P0000_T00",
                    "split '' unknown; expected one of train, dev, test"),
        Quarantined("sentence_label/split_1.txt", n + 3, None,
                    "malformed row: expected '<name>|<split>', found 'a|b|test'"))
    listing = corpus.listing()
    assert {c.corpus for c in listing.clips} == {"csl_daily"} and len(listing.clips) == 6


def test_how2sign_clip_folder_option_is_formatted_per_split(tmp_path):
    from m3t.corpora.how2sign import How2SignConfig, How2SignCorpus

    corpus = How2SignCorpus(tmp_path, How2SignConfig(clips_dir="videos/{split}/clips"))
    assert corpus.clips_dir("val") == PurePosixPath("videos/val/clips")
    assert corpus.clips_dir("train") == PurePosixPath("videos/train/clips")


def test_nmfs_dictionary_glosses_may_hold_spaces(tmp_path):
    (tmp_path / "dictionary.txt").write_text("0\t打 电话\n1 thank you very much\n", encoding="utf-8")
    assert NmfsCslCorpus(tmp_path).read_dictionary() == {0: "打 电话", 1: "thank you very much"}


@pytest.mark.parametrize("config, option, bad, good", [(How2SignConfig, "how2sign", (0.0, -24.0), 30.0),
                                                      (CslDailyConfig, "csl_daily", (0, -30.0), 25.0)])
def test_video_corpora_refuse_a_non_positive_frame_rate_naming_the_option(config, option, bad, good):
    for fps in bad:
        with pytest.raises(ValueError) as err:
            config(fps=fps)
        assert str(err.value) == f"corpora.{option}.fps must be > 0, got {fps}"
    assert config(fps=good).fps == good


def test_csl_daily_info_entry_that_is_not_a_dict_names_its_type_and_the_keys_expected():
    assert _record(["S000000_P0000_T00", 120]) == ("info entry is a list, expected a dict with keys name, length, "
                                                    "label_gloss, label_char, label_word, signer")
    assert _record("S000000_P0000_T00").startswith("info entry is a str, expected a dict with keys name, length,")
    entry = {"name": "S000000_P0000_T00", "length": 120, "label_gloss": ["你", "好"], "label_char": ["你", "好"],
             "label_word": ["你好"], "signer": 0}
    assert _record(entry) is entry and set(entry) == set(INFO_KEYS)
    assert _record({k: v for k, v in entry.items() if k != "signer"}) == "info entry lacks keys ['signer']"
    assert _record({**entry, "name": ""}) == "name '' is not a non-empty string"
    assert _record({**entry, "name": 7}) == "name 7 is not a non-empty string"
    assert _record({**entry, "label_char": "你好"}) == "label_char is not a list of strings"
    assert _record({**entry, "label_gloss": ["你", 2]}) == "label_gloss is not a list of strings"
    assert _record({**entry, "label_word": []}) == "label_word is empty (no sentence text)"


def test_nmfs_dictionary_bad_lines_are_quarantined_with_the_file_and_line(tmp_path):
    (tmp_path / "dictionary.txt").write_text("0\t谢谢\n\nx\t你好\n0 再见\n2\n3\tthank you\n", encoding="utf-8")
    out = Collector(tmp_path)
    assert NmfsCslCorpus(tmp_path).read_dictionary(out) == {0: "谢谢", 3: "thank you"}
    assert out.listing().quarantined == (
        Quarantined("dictionary.txt", 3, None, "malformed class line 'x\\t你好': expected '<index><tab or space><gloss>'"),
        Quarantined("dictionary.txt", 4, None, "class 0 defined twice"),
        Quarantined("dictionary.txt", 5, None, "malformed class line '2': expected '<index><tab or space><gloss>'"))
    with pytest.raises(CorpusError) as err:
        NmfsCslCorpus(tmp_path).read_dictionary()
    assert str(err.value).startswith(f"{tmp_path / 'dictionary.txt'} line 3: malformed class line")


def test_nmfs_dev_clips_are_drawn_from_train_by_the_documented_hash(tmp_path):
    """``dev_fraction`` moves the train clips with ``hash_unit(id, salt="nmfs_csl-dev") < dev_fraction`` (module
    docstring): the dev set is part of the data version and is pinned here."""
    fx.build_nmfs_csl(tmp_path)
    clips = NmfsCslCorpus(tmp_path, NmfsCslConfig(dev_fraction=0.5)).listing().clips
    moved = {c.id for c in clips if c.split == "dev"}
    assert moved == {c.id for c in clips if c.get("source_split") == "train"
                     and hash_unit(c.id, salt="nmfs_csl-dev") < 0.5}
    assert sorted(moved) == ["P02__2_01", "P02__3_01", "P03__0_02"]
    assert all(c.split == "test" for c in clips if c.get("source_split") == "test")
    assert {c.split for c in NmfsCslCorpus(tmp_path).listing().clips} == {"train", "test"}


def test_phoenix_clips_record_the_rows_start_and_end(tmp_path):
    fx.build_phoenix14t(tmp_path)
    path = tmp_path / fx.PHOENIX_FILE.format(split="dev")
    lines = path.read_text(encoding="utf-8").splitlines()
    name = lines[1].split("|")[0]
    lines[1] = f"{name}|{name}/1/*.png|12|87|Signer00|REGEN MORGEN|morgen regnet es"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    clips = {c.id: c for c in Phoenix14TCorpus(tmp_path).listing().clips}
    assert (clips[name].get("start"), clips[name].get("end"), clips[name].get("frame_glob")) == ("12", "87", "*.png")
    assert clips[name].get("annotation") == f"{fx.PHOENIX_FILE.format(split='dev')}:2"
    other = clips[lines[2].split("|")[0]]
    assert (other.get("start"), other.get("end")) == ("-1", "-1")


# ----------------------------------------------------------------------------------------- more reader details
def test_csl_daily_info_entry_that_is_not_a_dict_is_quarantined_and_clips_keep_their_length(tmp_path):
    """An ``info`` list (see ``build_csl_daily``) with a bare name string among the release's dict records."""
    fx.build_csl_daily(tmp_path)
    path = tmp_path / "sentence_label" / "csl2020ct_v2.pkl"
    with open(path, "rb") as fh:
        data = pickle.load(fh)
    data["info"][0]["length"] = 117
    data["info"].insert(1, "S000001_P0000_T00")
    with open(path, "wb") as fh:
        pickle.dump(data, fh)
    listing = CslDailyCorpus(tmp_path).listing()
    assert Quarantined("sentence_label/csl2020ct_v2.pkl", 1, None,
                       "info entry is a str, expected a dict with keys name, length, label_gloss, label_char, "
                       "label_word, signer") in listing.quarantined
    lacking = next(i for i, e in enumerate(data["info"]) if isinstance(e, dict) and e["name"] == "S100001_P0000_T00")
    assert Quarantined("sentence_label/csl2020ct_v2.pkl", lacking, "S100001_P0000_T00",
                       "info entry lacks keys ['label_gloss']") in listing.quarantined
    assert [q.file for q in listing.quarantined if q.clip_id == "S100001_P0000_T00"] == [
        "sentence_label/csl2020ct_v2.pkl"]  # its split row is not reported a second time
    clips = {c.id: c for c in listing.clips}
    assert dict(clips["S000000_P0000_T00"].extra) == {"media_kind": "frames", "chars": "你好吗", "length": "117"}
    assert dict(clips["S000002_P0000_T00"].extra)["length"] == "2"


def _how2sign_train_csv(root: Path) -> Path:
    (path,) = root.rglob("how2sign_realigned_train.csv")
    return path


def test_how2sign_row_without_sentence_name_is_quarantined_and_a_bad_header_gets_the_hint(tmp_path):
    """The realigned CSVs of ``build_how2sign`` (the official download script's layout) with a row whose
    SENTENCE_NAME is blank, then with a comma-separated header."""
    fx.build_how2sign(tmp_path)
    path = _how2sign_train_csv(tmp_path)
    text = path.read_text(encoding="utf-8")
    lines = text.splitlines()
    path.write_text(text + "v\tv-rgb\tv_9\t \t1.0\t2.0\tNo name.\n", encoding="utf-8")
    listing = How2SignCorpus(tmp_path).listing()
    rel = path.relative_to(tmp_path).as_posix()
    assert Quarantined(rel, len(lines) + 1, None, "empty SENTENCE_NAME") in listing.quarantined
    path.write_text(text.replace("\t", ",", 6), encoding="utf-8")
    with pytest.raises(CorpusError) as err:
        How2SignCorpus(tmp_path).listing()
    message = str(err.value)
    assert message.startswith(f"{path} line 1: header is ")
    assert message.endswith("Is this a How2Sign realigned CSV (tab-separated)? Point the corpus root at the How2Sign "
                            "folder, or set option annotations_dir to the folder holding "
                            "how2sign_realigned_<split>.csv and clips_dir to the sentence clip folders.")


def test_phoenix_row_without_name_leaves_the_rows_after_it_listed(tmp_path):
    """PHOENIX-2014-T's test ``corpus.csv`` (see ``build_phoenix14t``) with a nameless row before its one row."""
    fx.build_phoenix14t(tmp_path)
    (path,) = tmp_path.rglob("PHOENIX-2014-T.test.corpus.csv")
    before = {c.id for c in Phoenix14TCorpus(tmp_path).listing().clips if c.split == "test"}
    header, *rows = path.read_text(encoding="utf-8").splitlines()
    path.write_text("\n".join([header, "|x/1/*.png|-1|-1|Signer01|REGEN|es regnet"] + rows) + "\n", encoding="utf-8")
    listing = Phoenix14TCorpus(tmp_path).listing()
    assert len(before) == 1 and {c.id for c in listing.clips if c.split == "test"} == before
    assert Quarantined(path.relative_to(tmp_path).as_posix(), 2, None, "empty name") in listing.quarantined


def test_mead_errors_name_the_root_or_the_file_and_what_was_expected(tmp_path):
    not_a_folder = tmp_path / "mead.txt"
    not_a_folder.write_text("x", encoding="utf-8")
    with pytest.raises(CorpusError) as err:
        MeadCorpus(not_a_folder).listing()
    assert str(err.value) == (f"MEAD root {not_a_folder} is not a folder; point it at the folder of subject folders "
                              f"(EMOTE's release: .../reconstructions/EMICA-MEAD_flame2020)")
    corrupt = tmp_path / "shape_pose_cam.npz"
    corrupt.write_bytes(b"PK\x03\x04 not really a zip archive")
    with pytest.raises(CorpusError) as err:
        read_flame_params(corrupt)
    assert str(err.value).startswith(f"{corrupt}: not a readable .npz (")
    assert str(err.value).endswith("); re-export the clip")
    np.savez(corrupt, exp=np.zeros((2, 50), np.float32), jaw=np.zeros((2, 3), np.float32))
    with pytest.raises(CorpusError) as err:
        read_flame_params(corrupt)
    assert str(err.value) == (f"{corrupt} lacks datasets ['global_pose', 'shape', 'cam']; expected exp, jaw, "
                              f"global_pose, shape, cam (EMOTE's export)")
