"""Builders of tiny corpus trees in each real corpus's documented layout, with known good and bad rows.

Every builder writes under ``root`` and returns a :class:`Fixture`: the clip count expected per split and the
quarantine records expected as (file, row, fragment of the reason). Frames are 2x2 PNG / JPG images, videos a
few bytes (listing never decodes media).
"""
from __future__ import annotations

import gzip
import os
import pickle
import shutil
import struct
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np


@dataclass
class Fixture:
    root: Path
    per_split: dict[str, int]
    bad: list[tuple[str, int | None, str]] = field(default_factory=list)  # (file, row, reason fragment)
    extra: dict = field(default_factory=dict)


class _Python2Pickler(pickle._Pickler):
    """Writes ``str`` and ``bytes`` as Python 2 wrote its 8-bit ``str`` (the SHORT_BINSTRING / BINSTRING opcodes of
    ``pickletools``' table), text encoded with ``text_encoding``."""

    dispatch = dict(pickle._Pickler.dispatch)

    def __init__(self, fh, text_encoding: str):
        super().__init__(fh, protocol=2)
        self.text_encoding = text_encoding

    def save_py2_str(self, obj):
        data = obj.encode(self.text_encoding) if isinstance(obj, str) else bytes(obj)
        if len(data) < 256:
            self.write(pickle.SHORT_BINSTRING + bytes([len(data)]) + data)
        else:
            self.write(pickle.BINSTRING + struct.pack("<i", len(data)) + data)
        self.memoize(obj)

    dispatch[str] = save_py2_str
    dispatch[bytes] = save_py2_str


def write_python2_pickle(path: Path, obj: object, text_encoding: str) -> None:
    """A protocol-2 pickle as Python 2 wrote it: its strings and array buffers are 8-bit strings (FLAME 2020's
    ``generic_model.pkl`` holds latin-1 text; CSL-Daily's annotation pickles UTF-8 glosses). Python 3 reads such
    strings with the ``encoding`` given to the unpickler."""
    with open(path, "wb") as fh:
        _Python2Pickler(fh, text_encoding).dump(obj)


def write_frames(folder: Path, n: int = 2, suffix: str = ".png") -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        assert cv2.imwrite(str(folder / f"{i:06d}{suffix}"), np.full((2, 2, 3), 40 * i, np.uint8))


def write_video(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x00\x00\x00\x18ftypmp42")  # a few bytes: listing only checks existence


# ----------------------------------------------------------------------------------------- PHOENIX-2014-T
PHOENIX_HEADER = "name|video|start|end|speaker|orth|translation"
PHOENIX_FILE = "annotations/manual/PHOENIX-2014-T.{split}.corpus.csv"
# The row of the dummy PHOENIX-2014-T.train.corpus.csv that sign-language-processing/datasets ships (see
# build_phoenix14t); its frames are features/fullFrame-210x260px/train/<name>/images0001.png, no "1/" folder.
PHOENIX_REAL_ROW = ("25October_2010_Monday_tagesschau-17|25October_2010_Monday_tagesschau-17/1/*.png|-1|-1|Signer01|"
                    "REGEN SCHNEE REGION VERSCHWINDEN NORD REGEN KOENNEN REGION STERN KOENNEN SEHEN|regen und schnee "
                    "lassen an den alpen in der nacht nach im norden und nordosten fallen hier und da schauer sonst "
                    "ist das klar")


def write_phoenix_frames(folder: Path, n: int = 2) -> None:
    """``images0001.png`` ... as in the release's frame folders."""
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        assert cv2.imwrite(str(folder / f"images{i + 1:04d}.png"), np.full((2, 2, 3), 40 * i, np.uint8))


def build_phoenix14t(root: Path, under_root: bool = False, legacy_1_folder: bool = False) -> Fixture:
    """A PHOENIX-2014-T release tree with good rows (train 3, dev 2, test 1) and bad train rows.

    Layout source: the dummy data of the ``sign-language-datasets`` package (sign-language-processing/datasets,
    ``sign_language_datasets/datasets/rwth_phoenix2014_t/dummy_data/annotations/PHOENIX-2014-T-release-v3/
    PHOENIX-2014-T/``): ``annotations/manual/PHOENIX-2014-T.{train,dev,test}.corpus.csv`` and
    ``features/fullFrame-210x260px/{train,dev,test}/25October_2010_Monday_tagesschau-17/images0001.png``; its reader
    ``rwth_phoenix2014_t.py`` takes ``features/fullFrame-210x260px/<split>/`` + the ``video`` column without its
    ``1/*.png`` tail. The first train row is that file's row verbatim (:data:`PHOENIX_REAL_ROW`).

    ``under_root``: the CSVs directly under the root. ``legacy_1_folder``: images in ``<name>/1/`` as in
    PHOENIX-2014's ``multisigner`` tree (same CSV rows). Bad train rows: 6 columns, empty translation, missing
    frame folder, empty frame folder, a video column naming no folder, and a second name for the real row's video.
    """
    ann = root if under_root else root / "annotations" / "manual"
    ann.mkdir(parents=True, exist_ok=True)
    frames = root / "features" / "fullFrame-210x260px"
    sub = "1" if legacy_1_folder else ""
    good = {"train": 3, "dev": 2, "test": 1}
    bad = []
    real_name = PHOENIX_REAL_ROW.split("|")[0]
    for split, n in good.items():
        lines = [PHOENIX_HEADER]
        for i in range(n):
            if split == "train" and i == 0:
                write_phoenix_frames(frames / split / real_name / sub)
                lines.append(PHOENIX_REAL_ROW)
                continue
            name = f"0{i + 1}December_2011_Thursday_{split}-{100 + i}"
            write_phoenix_frames(frames / split / name / sub)
            lines.append(f"{name}|{name}/1/*.png|-1|-1|Signer0{i}|REGEN MORGEN|morgen regnet es")
        if split == "train":
            file = PHOENIX_FILE.format(split=split).split("/")[-1] if under_root else PHOENIX_FILE.format(split=split)
            lines.append("train_bad_cols|x/1/*.png|-1|Signer01|WETTER|das wetter")  # 6 columns
            bad.append((file, len(lines), "malformed row"))
            write_phoenix_frames(frames / "train" / "train_empty_text" / sub)
            lines.append("train_empty_text|train_empty_text/1/*.png|-1|-1|Signer01|WETTER|")
            bad.append((file, len(lines), "empty translation"))
            lines.append("train_no_frames|train_no_frames/1/*.png|-1|-1|Signer01|WETTER|das wetter")
            bad.append((file, len(lines), "missing media"))
            (frames / "train" / "train_empty_dir" / sub).mkdir(parents=True)
            lines.append("train_empty_dir|train_empty_dir/1/*.png|-1|-1|Signer01|WETTER|das wetter")
            bad.append((file, len(lines), "empty frame folder"))
            lines.append("train_no_folder|*.png|-1|-1|Signer01|WETTER|das wetter")
            bad.append((file, len(lines), "names no frame folder"))
            lines.append(f"train_same_video|{real_name}/1/*.png|-1|-1|Signer01|WETTER|das wetter")
            bad.append((file, len(lines), f"duplicate media: features/fullFrame-210x260px/train/{real_name}"))
        (ann / f"PHOENIX-2014-T.{split}.corpus.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return Fixture(root, good, bad, {"real_name": real_name})


# ----------------------------------------------------------------------------------------- How2Sign
H2S_HEADER = "\t".join(["VIDEO_ID", "VIDEO_NAME", "SENTENCE_ID", "SENTENCE_NAME", "START_REALIGNED",
                        "END_REALIGNED", "SENTENCE"])
# A row of how2sign_realigned_train.csv as quoted in how2sign/how2sign-data issue 9 (its times run past the
# 140 s video: the realigned times are full-video seconds, kept as they are).
H2S_REAL_ROW = ("10om04b2LIw\t10om04b2LIw-8-rgb_front\t10om04b2LIw_26\t10om04b2LIw_26-8-rgb_front\t137.95\t141.01\t"
                "And that ought to do it.")
H2S_LAYOUTS = {  # layout -> (CSV folder, clip folder), {split} = train / val / test
    "script": ("sentence_level/{split}/text/en/raw_text/re_aligned", "sentence_level/{split}/rgb_front/raw_videos"),
    "archives": ("", "{split}_rgb_front_clips/raw_videos"),
}


def build_how2sign(root: Path, layout: str = "script") -> Fixture:
    """A How2Sign tree with good rows (train 3, val 2, test 2) and bad train rows.

    Layout sources: ``layout="script"`` is what the official ``download_how2sign.sh`` (how2sign/how2sign.github.io)
    builds: ``unzip <split>_rgb_front_clips.zip -d How2Sign/sentence_level/<split>/rgb_front`` (the archive holds
    ``raw_videos/``, as the sign-language-datasets reader ``how2sign.py`` expects) and the realigned CSVs moved to
    ``sentence_level/<split>/text/en/raw_text/re_aligned/``. ``layout="archives"``: the website's archives unpacked
    by hand next to the CSVs, ``<split>_rgb_front_clips/raw_videos/<SENTENCE_NAME>.mp4``. The first train row is
    :data:`H2S_REAL_ROW`. Bad train rows: end = start, a non-number time, no clip file, empty sentence, 8 columns
    (a tab inside the sentence), and a SENTENCE_NAME listed twice.
    """
    csv_dir, clip_dir = H2S_LAYOUTS[layout]
    good = {"train": 3, "val": 2, "test": 2}
    bad = []
    for split, n in good.items():
        clips = root / clip_dir.format(split=split)
        folder = root / csv_dir.format(split=split)
        folder.mkdir(parents=True, exist_ok=True)
        file = (folder / f"how2sign_realigned_{split}.csv").relative_to(root).as_posix()
        lines = [H2S_HEADER]
        for i in range(n):
            if split == "train" and i == 0:
                write_video(clips / f"{H2S_REAL_ROW.split(chr(9))[3]}.mp4")
                lines.append(H2S_REAL_ROW)
                continue
            video = f"-{split}Vid{i}xY"
            name = f"{video}_{i}-5-rgb_front"
            write_video(clips / f"{name}.mp4")
            lines.append(f"{video}\t{video}-5-rgb_front\t{video}_{i}\t{name}\t{1.5 + i}\t{4.25 + i}\t"
                         f"And now we stir sentence {i}.")
        if split == "train":
            write_video(clips / "bad_order.mp4")
            lines.append("v\tv-rgb\tv_0\tbad_order\t5.0\t5.0\tEnd equals start.")
            bad.append((file, len(lines), "bad times"))
            lines.append("v\tv-rgb\tv_1\tbad_number\tabc\t5.0\tNot a number.")
            bad.append((file, len(lines), "bad times"))
            lines.append("v\tv-rgb\tv_2\tno_video\t1.0\t2.0\tThe video is missing.")
            bad.append((file, len(lines), "missing media"))
            write_video(clips / "no_text.mp4")
            lines.append("v\tv-rgb\tv_3\tno_text\t1.0\t2.0\t")
            bad.append((file, len(lines), "empty SENTENCE"))
            lines.append("v\tv-rgb\tv_4\ttabbed\t1.0\t2.0\tA tab\tinside.")
            bad.append((file, len(lines), "8 tab-separated columns"))
            lines.append(H2S_REAL_ROW.replace("137.95", "138.00"))
            bad.append((file, len(lines), "duplicate clip id"))
        (folder / f"how2sign_realigned_{split}.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return Fixture(root, {"train": 3, "dev": 2, "test": 2}, bad, {"clip_dir": clip_dir})


# ----------------------------------------------------------------------------------------- CSL-Daily
class _CallsGetcwd:
    """Pickles as a call of os.getcwd: a stand-in for a hostile pickle (harmless even if it ran)."""

    def __reduce__(self):
        return (os.getcwd, ())


# An "info" entry of CSL-Daily's csl2020ct_v2.pkl as printed by a peer notebook exploring the file; the same keys
# are read by hsuzjx/SLRT (slr/datasets/preprocess/CSLDailyPreprocessor.py: label_gloss, label_word, label_char,
# label_postag, signer). Its name is the pickle half of the release's one mismatched pair (see build_csl_daily).
CSL_REAL_INFO = {"name": "S000007_P0003_T00", "length": 55, "label_gloss": ["他", "谁"],
                 "label_char": ["他", "是", "谁", "？"], "label_word": ["他", "是", "谁", "？"],
                 "label_postag": ["r", "v", "v", "w"], "signer": 3, "time": 0}
CSL_FRAME_DIRS = {"sentence": "sentence/frames_512x512", "archive": "sentence_frames-512x512/frames_512x512"}


def build_csl_daily(root: Path, frames_layout: str = "sentence") -> Fixture:
    """A CSL-Daily tree with good clips (train 4, dev 1, test 1) and each known bad input.

    Layout source: hsuzjx/SLRT ``slr/datasets/Datasets/VideoDatasets/CSLDailyDataset.py`` reads
    ``sentence_label/split_1.txt`` (``|``-separated, header ``name|split``), ``sentence_label/csl2020ct_v2.pkl``
    (``info`` list + ``gloss_map`` / ``char_map`` / ``word_map`` / ``postag_map``) and ``<frames>/<name>/*.jpg``
    with frames in ``sentence_frames-512x512/frames_512x512`` (``frames_layout="archive"``); other loaders use
    ``sentence/frames_512x512`` (the default here). The same file renames split row ``S000005_P0004_T00`` to the
    pickle's ``S000007_P0003_T00``: the release's one mismatched pair, reproduced here with
    :data:`CSL_REAL_INFO` (both halves must be reported, not guessed).
    """
    labels = root / "sentence_label"
    labels.mkdir(parents=True)
    frames = root / CSL_FRAME_DIRS[frames_layout]
    info, split_rows = [], ["name|split"]
    splits = ["train", "train", "train", "train", "dev", "test"]
    for i, split in enumerate(splits):
        name = f"S{i:06d}_P0000_T00"
        write_frames(frames / name, suffix=".jpg")
        info.append({"name": name, "length": 2, "label_gloss": ["你", "好"], "label_char": ["你", "好", "吗"],
                     "label_word": ["你好", "吗"], "label_postag": ["v", "y"], "signer": i % 3, "time": 0})
        split_rows.append(f"{name}|{split}")
    pkl, split_file = "sentence_label/csl2020ct_v2.pkl", "sentence_label/split_1.txt"
    bad = []
    write_frames(frames / CSL_REAL_INFO["name"], suffix=".jpg")
    info.append(dict(CSL_REAL_INFO))  # the pickle half of the mismatched pair
    bad.append((pkl, len(info) - 1, "not in the split file"))
    split_rows.append("S000005_P0004_T00|train")  # the split-file half
    bad.append((split_file, len(split_rows), "not in the annotation pickle"))
    info.append({"name": "S100001_P0000_T00", "length": 2, "label_char": ["a"], "label_word": ["a"], "signer": 0})
    split_rows.append("S100001_P0000_T00|train")
    bad.append((pkl, len(info) - 1, "lacks keys ['label_gloss']"))
    info.append({"name": "S100002_P0000_T00", "length": 2, "label_gloss": ["A"], "label_char": ["a"],
                 "label_word": ["a"], "signer": 1})
    split_rows.append("S100002_P0000_T00|train")
    bad.append((pkl, len(info) - 1, "missing media"))
    (frames / "S100004_P0000_T00").mkdir()
    info.append({"name": "S100004_P0000_T00", "length": 0, "label_gloss": ["A"], "label_char": ["a"],
                 "label_word": ["a"], "signer": 1})
    split_rows.append("S100004_P0000_T00|dev")
    bad.append((pkl, len(info) - 1, "empty frame folder"))
    info.append({"name": "S100005_P0000_T00", "length": 2, "label_gloss": ["A"], "label_char": [],
                 "label_word": [], "signer": 1})
    split_rows.append("S100005_P0000_T00|test")
    bad.append((pkl, len(info) - 1, "label_word is empty"))
    info.append(dict(info[0]))  # a name twice in the pickle
    bad.append((pkl, len(info) - 1, "duplicate clip id"))
    split_rows.append("S000001_P0000_T00|dev")  # a name twice in the split file
    bad.append((split_file, len(split_rows), "name listed twice"))
    split_rows.append("S100003_P0000_T00|dev")  # no pickle entry
    bad.append((split_file, len(split_rows), "not in the annotation pickle"))
    split_rows.append("S000000_P0000_T00|holdout")
    bad.append((split_file, len(split_rows), "split 'holdout' unknown"))
    with open(root / pkl, "wb") as fh:
        pickle.dump({"info": info, "gloss_map": ["你", "好"], "char_map": [], "word_map": [], "postag_map": []}, fh)
    (root / split_file).write_text("\n".join(split_rows) + "\n", encoding="utf-8")
    return Fixture(root, {"train": 4, "dev": 1, "test": 1}, bad)


def write_hostile_pickle(path: Path, payload: object = None) -> None:
    with open(path, "wb") as fh:
        pickle.dump({"info": [payload if payload is not None else _CallsGetcwd()]}, fh)


# ----------------------------------------------------------------------------------------- NMFs-CSL
def build_nmfs_csl(root: Path) -> Fixture:
    """An NMFs-CSL tree: dictionary, train / test lists, videos under ``video/``; train 5, test 4 good clips.

    The distributed list files could not be checked against a public copy; the list rows follow the two shapes
    that sakura2233565548/MASA (by the dataset authors' group) reads in ``feeder/single_dataset/NMFs_CSL.py``:
    train rows ``<class>/<file> <label>`` and test rows ``<class>/<file>`` whose label is the numeric class folder.
    Bad train rows: an unknown class, a path without class, a missing video, a non-numeric class folder.
    """
    root.mkdir(parents=True, exist_ok=True)
    (root / "dictionary.txt").write_text("0\t谢谢\n1 你好\n2\t对不起\n3 再见\n", encoding="utf-8")
    train = [("P01/0_01.mp4", 0), ("P01/1_01.mp4", 1), ("P02/2_01.mp4", 2), ("P02/3_01.mp4", 3), ("P03/0_02.mp4", 0)]
    test = [("P04/1_01.mp4", 1), ("P04/2_01.mp4", 2), ("video/P05/3_01.mp4", 3)]
    for rel, _ in train + test:
        write_video(root / ("" if rel.startswith("video/") else "video") / rel)
    write_video(root / "video" / "2" / "P06_2_01.mp4")
    train_lines = [f"{p} {c}" for p, c in train] + ["P09/9_01.mp4 9", "only_a_path.mp4", "P09/missing.mp4 1",
                                                    "P09/no_class.mp4"]
    (root / "train.txt").write_text("\n".join(train_lines) + "\n", encoding="utf-8")
    test_lines = [f"{p} {c}" for p, c in test] + ["2/P06_2_01.mp4"]
    (root / "test.txt").write_text("\n".join(test_lines) + "\n", encoding="utf-8")
    (root / "confusing.txt").write_text("0\n2\n", encoding="utf-8")
    bad = [("train.txt", 6, "class 9 is not in"), ("train.txt", 7, "malformed row"), ("train.txt", 8, "missing media"),
           ("train.txt", 9, "malformed row")]
    return Fixture(root, {"train": 5, "dev": 0, "test": 4}, bad)


# ----------------------------------------------------------------------------------------- MEAD
def flame_arrays(frames: int = 4, rng: np.random.Generator | None = None, exp: int = 50, shape: int = 100,
                 batch_axis: bool = False) -> dict[str, np.ndarray]:
    """FLAME parameters of one clip. ``batch_axis``: EMOTE's (1, T, D) storage (inferno ``_save_hdf5_dict``)."""
    rng = rng or np.random.default_rng(0)
    dims = {"exp": exp, "jaw": 3, "global_pose": 3, "shape": shape, "cam": 3}
    out = {k: (0.3 * rng.normal(size=(frames, d))).astype(np.float32) for k, d in dims.items()}
    return {k: v[None] for k, v in out.items()} if batch_axis else out


def write_hdf5(path: Path, arrays: dict[str, np.ndarray]) -> None:
    import h5py

    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            f.create_dataset(key, data=value)


def build_mead(root: Path) -> Fixture:
    """A tree without the view level and with EMOCA-style (T, D) arrays in ``.npz`` files (see
    :func:`build_mead_release` for the released layout)."""
    count = 0
    for subject in ("M003", "M005", "W009", "W011", "M012"):
        for emotion, level in (("angry", "level_1"), ("happy", "level_3")):
            folder = root / subject / emotion / level / "001"
            folder.mkdir(parents=True)
            np.savez(folder / "shape_pose_cam.npz", **flame_arrays())
            count += 1
    (root / "M003" / "neutral" / "level_1" / "002").mkdir(parents=True)
    (root / "M003" / "neutral" / "level_1" / "002" / "shape_pose_cam.hdf5").write_bytes(b"\x89HDF\r\n\x1a\n")
    count += 1
    (root / "stray").mkdir()
    np.savez(root / "stray" / "shape_pose_cam.npz", **flame_arrays())
    return Fixture(root, {"all": count}, [("stray/shape_pose_cam.npz", None, "unexpected location")])


def build_mead_release(root: Path) -> Fixture:
    """EMOTE's EMICA-MEAD release (``reconstruction_v1.zip`` -> ``reconstructions/EMICA-MEAD_flame2020``):
    ``<subject>/<view>/<emotion>/<level>/<clip>/shape_pose_cam.hdf5`` beside ``appearance.hdf5``, one dataset per
    key with a leading batch axis: ``exp`` (1, T, 100), ``jaw`` (1, T, 3), ``global_pose`` (1, T, 3), ``shape``
    (1, T, 300), ``cam`` (1, T, 3); ``appearance.hdf5``: ``light`` (1, T, 27), ``tex`` (1, T, 50). Sources:
    radekd91/inferno ``inferno/datasets/FaceVideoDataModule.py`` (the path and the kept keys),
    ``inferno/datasets/IO.py`` (``_save_hdf5_dict``, "a leading batch dimension of size 1"), and the readers of
    the released files, which index ``f[k][0]`` and document those shapes (e.g. ``M003/front/angry/level_1/001``).

    Besides three good clips: a ``left_30`` view (not listed by default), a clip whose every frame is NaN and a
    clip with one NaN frame (both listed; the import quarantines the first and holds the second's NaN frame).
    """
    rng = np.random.default_rng(1)
    clips = {"M003/front/angry/level_1/001": 5, "M003/front/happy/level_3/002": 4, "W009/front/sad/level_2/001": 6,
             "M003/left_30/angry/level_1/001": 5, "W011/front/fear/level_1/003": 4, "W011/front/fear/level_1/004": 4}
    for rel, frames in clips.items():
        arrays = flame_arrays(frames, rng, exp=100, shape=300, batch_axis=True)
        arrays["jaw"][..., 0] = np.abs(arrays["jaw"][..., 0])  # the jaw opens about x
        if rel.endswith("003"):
            arrays = {k: np.full_like(v, np.nan) for k, v in arrays.items()}
        if rel.endswith("004"):
            arrays["exp"][0, 1] = np.nan
        write_hdf5(root / rel / "shape_pose_cam.hdf5", arrays)
        write_hdf5(root / rel / "appearance.hdf5", {"light": rng.normal(size=(1, frames, 27)).astype(np.float32),
                                                   "tex": rng.normal(size=(1, frames, 50)).astype(np.float32)})
    bad = [("M003/left_30/angry/level_1/001/shape_pose_cam.hdf5", None, "view 'left_30' not in corpora.mead.views")]
    return Fixture(root, {"all": 5}, bad, {"frames": clips})


# ----------------------------------------------------------------------------------------- SOKE SMPL-X
SOKE_KEYS = {"smplx_root_pose": 3, "smplx_body_pose": 63, "smplx_lhand_pose": 45, "smplx_rhand_pose": 45,
             "smplx_jaw_pose": 3, "smplx_shape": 10, "smplx_expr": 10}
SOKE_FRAME_NAMES = {"how2sign": "{clip}_{n}_3D.pkl", "phoenix": "images{n:04d}.pkl", "csl": "{n:06d}.pkl"}


def smplx_frame(rng: np.random.Generator, expression: int = 10, names: str = "soke") -> dict[str, np.ndarray]:
    """One frame pickle of SOKE's release: SMPLer-X keys and widths as 2000ZRL/SOKE
    ``mGPT/data/humanml/load_data.py`` reads them (root 3, body 63, hands 45 + 45, jaw 3, shape 10, expr 10;
    179 values, 1-D float arrays). ``names="smplx"``: the smplx package's names (``global_orient``, ...,
    ``transl``) of other exports. Axis-angles are below pi (one rotation, one vector)."""
    if names == "smplx":
        dims = {"global_orient": 3, "body_pose": 63, "left_hand_pose": 45, "right_hand_pose": 45, "jaw_pose": 3,
                "expression": expression, "betas": 10, "transl": 3}
    else:
        dims = SOKE_KEYS | {"smplx_expr": expression}
    return {k: (0.3 * rng.normal(size=(d,))).astype(np.float32) for k, d in dims.items()}


def _write_frames_pkl(folder: Path, frames: list[dict], numbers: list[int], pattern: str = "{n}.pkl") -> None:
    folder.mkdir(parents=True)
    for n, frame in zip(numbers, frames, strict=True):
        with open(folder / pattern.format(n=n, clip=folder.name), "wb") as fh:
            pickle.dump(frame, fh)


def build_soke(root: Path, layout: str = "how2sign") -> Fixture:
    """SOKE's SMPL-X release as its loaders read it (2000ZRL/SOKE ``mGPT/data/humanml/load_data.py``):
    ``how2sign``: ``<split>/poses/<clip>/<clip>_<n>_3D.pkl`` (split train / val / test, clip ids like
    ``-fZc293MpJk_0-1-rgb_front``); ``phoenix``: ``<split>/<clip>/images<n>.pkl``; ``csl``:
    ``poses/<clip>/<n>.pkl`` without split folders (the split comes from the annotation's ``split`` column).
    Frames 1, 2 and 10 of each good clip (10 sorts before 2 as text); bad clips: a missing key, an uneven
    expression width, an empty folder, a clip without an annotation row."""
    rng = np.random.default_rng(0)
    pattern = SOKE_FRAME_NAMES[layout]
    folder = {"how2sign": lambda split, clip: root / split / "poses" / clip,
              "phoenix": lambda split, clip: root / split / clip,
              "csl": lambda split, clip: root / "poses" / clip}[layout]
    shown = {"how2sign": "train/poses", "phoenix": "train", "csl": "poses"}[layout]
    notes = ["id,text,gloss,signer" + (",split" if layout == "csl" else "")]

    def note(clip: str, split: str, text: str, gloss: str = "", signer: str = "") -> None:
        notes.append(f"{clip},{text},{gloss},{signer}" + (f",{split}" if layout == "csl" else ""))

    for split, names in (("train", ["-fZc293MpJk_0-1-rgb_front", "-fZc293MpJk_2-1-rgb_front"]),
                         ("val", ["b1_0-8-rgb_front"]), ("test", ["c1_3-5-rgb_front"])):
        for name in names:
            _write_frames_pkl(folder(split, name), [smplx_frame(rng) for _ in range(3)], [1, 2, 10], pattern)
            note(name, split, f"text of {name}", f"GLOSS {name[:2].upper()}", f"s{name[1]}")
    broken = [smplx_frame(rng) for _ in range(3)]
    del broken[1]["smplx_lhand_pose"]
    _write_frames_pkl(folder("train", "bad_key"), broken, [0, 1, 2], pattern)
    note("bad_key", "train", "broken")
    uneven = [smplx_frame(rng, 10), smplx_frame(rng, 10), smplx_frame(rng, 50)]
    _write_frames_pkl(folder("train", "bad_shape"), uneven, [0, 1, 2], pattern)
    note("bad_shape", "train", "broken")
    folder("train", "empty").mkdir(parents=True)
    note("empty", "train", "nothing")
    _write_frames_pkl(folder("test", "no_note"), [smplx_frame(rng)], [0], pattern)
    (root / "annotation.csv").write_text("\n".join(notes) + "\n", encoding="utf-8")
    no_note = {"how2sign": "test/poses", "phoenix": "test", "csl": "poses"}[layout]
    bad = [(f"{shown}/bad_key/" + pattern.format(n=1, clip="bad_key"), None, "'smplx_lhand_pose' missing"),
           (f"{shown}/bad_shape/" + pattern.format(n=2, clip="bad_shape"), None, "'smplx_expr' has 50 values"),
           (f"{shown}/empty", None, "missing media"), (f"{no_note}/no_note", None, "no row in the annotation")]
    return Fixture(root, {"train": 2, "dev": 1, "test": 1}, bad)


# ----------------------------------------------------------------------------------------- slt pickles
def slt_entries(split: str, n: int, rng: np.random.Generator, dims: int = 12) -> list[dict]:
    """Records of neccam/slt's gzip pickles (``signjoey/dataset.py`` reads ``name``, ``signer``, ``gloss``, ``text``,
    ``sign``; its Phoenix files hold (T, 1024) features, ``configs/sign.yaml`` ``feature_size: 1024``)."""
    return [{"name": f"{split}/clip{i}", "signer": f"Signer0{i}", "gloss": "REGEN MORGEN", "text": "es regnet",
             "sign": rng.normal(size=(5 + i, dims)).astype(np.float32)} for i in range(n)]


def build_slt(root: Path) -> Fixture:
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    files = {"train": "phoenix14t.pami0.train", "dev": "phoenix14t.pami0.dev", "test": "phoenix14t.pami0.test.pkl.gz"}
    for split, n in (("train", 3), ("dev", 2), ("test", 2)):
        entries = slt_entries(split, n, rng)
        if split == "train":
            flat = np.zeros(7, np.float32)  # 1-D: not a (T, D) sequence
            entries.append({"name": "train/flat", "signer": "x", "gloss": "", "text": "", "sign": flat})
            entries.append({"name": "train/nosign", "signer": "x", "gloss": "", "text": ""})
        with gzip.open(root / files[split], "wb") as fh:
            pickle.dump(entries, fh)
    bad = [(files["train"], 3, "expected a non-empty (T, D) float array"), (files["train"], 4, "lacks keys ['sign']")]
    return Fixture(root, {"train": 3, "dev": 2, "test": 2}, bad, {"files": files})


def build_slt_import(root: Path) -> Fixture:
    """slt pickles for the import: a real-shaped Phoenix-2014T record (name ``train/<folder>``, signer, gloss,
    text, (T, 1024) ``sign``), two more good ones, and records the import must refuse: every frame NaN, another
    width, the names ``..`` and ``a\\b`` (unsafe ids). One good record has a NaN frame (held, reported)."""
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(2)
    train = [{"name": "train/11August_2010_Wednesday_tagesschau-2", "signer": "Signer08", "gloss": "DRUCK TIEF KOMMEN",
              "text": "tiefer luftdruck bestimmt in den nächsten tagen unser wetter",
              "sign": rng.normal(size=(6, 1024)).astype(np.float32)}]
    train += slt_entries("train", 2, rng, dims=1024)
    train[2]["sign"][3, 7] = np.nan
    train.append({**slt_entries("train", 1, rng, 1024)[0], "name": "train/all_nan"})
    train[-1]["sign"][:] = np.nan
    train.append({**slt_entries("train", 1, rng, 12)[0], "name": "train/narrow"})
    train.append({**slt_entries("train", 1, rng, 1024)[0], "name": ".."})
    train.append({**slt_entries("train", 1, rng, 1024)[0], "name": "a\\b"})
    dev = slt_entries("dev", 1, rng, dims=1024)
    for name, entries in (("phoenix14t.pami0.train", train), ("phoenix14t.pami0.dev", dev)):
        with gzip.open(root / name, "wb") as fh:
            pickle.dump(entries, fh)
    return Fixture(root, {"train": 3, "dev": 1, "test": 0},
                   [("train__all_nan", None, "frames holds NaN or inf"), ("train__narrow", None, "sign has 12 values"),
                    ("..", None, "unsafe clip id"), ("a\\b", None, "unsafe clip id")])


def write_torch_slt(path: Path) -> None:
    import torch

    with gzip.open(path, "wb") as fh:
        pickle.dump([{"name": "train/x", "signer": "s", "gloss": "", "text": "", "sign": torch.zeros(3, 4)}], fh)


# ----------------------------------------------------------------------------------------- .pose files
def build_pose_collection(root: Path, lexicon: Path, rows: list[dict]) -> Fixture:
    """Copy a few real lexicon ``.pose`` files (``rows`` of its data.csv) into an index-CSV collection.

    The files are real pose-format files of the spoken-to-signed wheel; the index is this project's own format.
    Bad index rows: a truncated file, a missing file, an unknown split, too few columns, a non-integer label, an
    empty id, a repeated id and a file that is not a ``.pose`` at all.
    """
    root.mkdir(parents=True, exist_ok=True)
    lines = ["id,path,split,text,language,signer,label"]
    for i, row in enumerate(rows[:4]):
        rel = f"poses/{row['signed_language']}_{i}.pose"
        (root / "poses").mkdir(exist_ok=True)
        shutil.copyfile(lexicon / row["path"], root / rel)
        split = ["train", "train", "dev", "test"][i]
        lines.append(f"c{i},{rel},{split},{row['words']},{row['signed_language']},s{i},{i}")
    data = (lexicon / rows[0]["path"]).read_bytes()
    (root / "poses" / "truncated.pose").write_bytes(data[: len(data) // 2])
    lines.append("cut,poses/truncated.pose,train,A,ase,s0,0")
    lines.append("gone,poses/none.pose,train,A,ase,s0,0")
    lines.append("odd,poses/ase_0.pose,holdout,A,ase,s0,0")
    lines.append("short,poses/ase_0.pose,train")
    lines.append("badlabel,poses/ase_0.pose,train,A,ase,s0,first")
    lines.append(",poses/ase_0.pose,train,A,ase,s0,0")
    lines.append("c0,poses/ase_0.pose,train,A,ase,s0,0")
    (root / "poses" / "junk.pose").write_bytes(b"id,path\nnot a pose file\n")
    lines.append("junk,poses/junk.pose,train,A,ase,s0,0")
    bad = [("index.csv", 6, "truncated"), ("index.csv", 7, "missing media"), ("index.csv", 8, "split 'holdout'"),
           ("index.csv", 9, "malformed row"), ("index.csv", 10, "label 'first' is not an integer"),
           ("index.csv", 11, "empty id or path"), ("index.csv", 12, "duplicate clip id"),
           ("index.csv", 13, "not a .pose file")]
    (root / "index.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return Fixture(root, {"train": 2, "dev": 1, "test": 1}, bad)
