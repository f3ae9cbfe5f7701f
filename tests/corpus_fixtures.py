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


def write_frames(folder: Path, n: int = 2, suffix: str = ".png") -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        assert cv2.imwrite(str(folder / f"{i:06d}{suffix}"), np.full((2, 2, 3), 40 * i, np.uint8))


def write_video(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x00\x00\x00\x18ftypmp42")  # a few bytes: listing only checks existence


# ----------------------------------------------------------------------------------------- PHOENIX-2014-T
PHOENIX_HEADER = "name|video|start|end|speaker|orth|translation"


def build_phoenix14t(root: Path, under_root: bool = False) -> Fixture:
    ann = root if under_root else root / "annotations" / "manual"
    ann.mkdir(parents=True, exist_ok=True)
    frames = root / "features" / "fullFrame-210x260px"
    good = {"train": 3, "dev": 2, "test": 1}
    bad = []
    for split, n in good.items():
        lines = [PHOENIX_HEADER]
        for i in range(n):
            name = f"{split}_clip{i}"
            write_frames(frames / split / name / "1")
            lines.append(f"{name}|{split}/{name}/1/*.png|-1|-1|Signer0{i}|REGEN MORGEN|morgen regnet es")
        if split == "train":
            file = ("" if under_root else "annotations/manual/") + "PHOENIX-2014-T.train.corpus.csv"
            lines.append("train_bad_cols|train/x/1/*.png|-1|Signer01|WETTER|das wetter")  # 6 columns
            bad.append((file, len(lines), "malformed row"))
            write_frames(frames / "train" / "train_empty_text" / "1")
            lines.append("train_empty_text|train/train_empty_text/1/*.png|-1|-1|Signer01|WETTER|")
            bad.append((file, len(lines), "empty translation"))
            lines.append("train_no_frames|train/train_no_frames/1/*.png|-1|-1|Signer01|WETTER|das wetter")
            bad.append((file, len(lines), "missing media"))
            (frames / "train" / "train_empty_dir" / "1").mkdir(parents=True)
            lines.append("train_empty_dir|train/train_empty_dir/1/*.png|-1|-1|Signer01|WETTER|das wetter")
            bad.append((file, len(lines), "empty frame folder"))
        (ann / f"PHOENIX-2014-T.{split}.corpus.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return Fixture(root, good, bad)


# ----------------------------------------------------------------------------------------- How2Sign
H2S_HEADER = "\t".join(["VIDEO_ID", "VIDEO_NAME", "SENTENCE_ID", "SENTENCE_NAME", "START_REALIGNED",
                        "END_REALIGNED", "SENTENCE"])


def build_how2sign(root: Path) -> Fixture:
    good = {"train": 3, "val": 2, "test": 2}
    bad = []
    for split, n in good.items():
        clips = root / "sentence_level" / split / "rgb_front" / "raw_videos"
        lines = [H2S_HEADER]
        for i in range(n):
            name = f"{split}vid{i}_{i}-5-rgb_front"
            write_video(clips / f"{name}.mp4")
            lines.append(f"{split}vid{i}\t{split}vid{i}-5-rgb_front\t{split}vid{i}_{i}\t{name}\t{1.5 + i}\t{4.25 + i}\t"
                         f"And now we stir sentence {i}.")
        if split == "train":
            file = "how2sign_realigned_train.csv"
            write_video(clips / "bad_order.mp4")
            lines.append("v\tv-rgb\tv_0\tbad_order\t5.0\t5.0\tEnd equals start.")
            bad.append((file, len(lines), "bad times"))
            lines.append("v\tv-rgb\tv_1\tbad_number\tabc\t5.0\tNot a number.")
            bad.append((file, len(lines), "bad times"))
            lines.append("v\tv-rgb\tv_2\tno_video\t1.0\t2.0\tThe video is missing.")
            bad.append((file, len(lines), "missing media"))
        (root / f"how2sign_realigned_{split}.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return Fixture(root, {"train": 3, "dev": 2, "test": 2}, bad)


# ----------------------------------------------------------------------------------------- CSL-Daily
class _CallsGetcwd:
    """Pickles as a call of os.getcwd: a stand-in for a hostile pickle (harmless even if it ran)."""

    def __reduce__(self):
        return (os.getcwd, ())


def build_csl_daily(root: Path) -> Fixture:
    labels = root / "sentence_label"
    labels.mkdir(parents=True)
    info, split_rows = [], ["name|split"]
    splits = ["train", "train", "train", "train", "dev", "test"]
    for i, split in enumerate(splits):
        name = f"S{i:06d}_P0000_T00"
        write_frames(root / "sentence" / "frames_512x512" / name, suffix=".jpg")
        info.append({"name": name, "length": 2, "label_gloss": ["你", "好"], "label_char": ["你", "好", "吗"],
                     "label_word": ["你好", "吗"], "signer": i % 3})
        split_rows.append(f"{name}|{split}")
    pkl, split_file = "sentence_label/csl2020ct_v2.pkl", "sentence_label/split_1.txt"
    bad = []
    info.append({"name": "S100000_P0000_T00", "length": 2, "label_gloss": ["A"], "label_char": ["a"],
                 "label_word": ["a"], "signer": 0})  # no split row
    write_frames(root / "sentence" / "frames_512x512" / "S100000_P0000_T00", suffix=".jpg")
    bad.append((pkl, len(info) - 1, "not in the split file"))
    info.append({"name": "S100001_P0000_T00", "length": 2, "label_char": ["a"], "label_word": ["a"], "signer": 0})
    split_rows.append("S100001_P0000_T00|train")
    bad.append((pkl, len(info) - 1, "lacks keys ['label_gloss']"))
    info.append({"name": "S100002_P0000_T00", "length": 2, "label_gloss": ["A"], "label_char": ["a"],
                 "label_word": ["a"], "signer": 1})
    split_rows.append("S100002_P0000_T00|train")
    bad.append((pkl, len(info) - 1, "missing media"))
    split_rows.append("S100003_P0000_T00|dev")  # no pickle entry
    bad.append((split_file, len(split_rows), "not in the annotation pickle"))
    split_rows.append("S000000_P0000_T00|holdout")
    bad.append((split_file, len(split_rows), "split 'holdout' unknown"))
    with open(root / pkl, "wb") as fh:
        pickle.dump({"info": info, "gloss_map": ["你", "好"], "char_map": [], "word_map": []}, fh)
    (root / split_file).write_text("\n".join(split_rows) + "\n", encoding="utf-8")
    return Fixture(root, {"train": 4, "dev": 1, "test": 1}, bad)


def write_hostile_pickle(path: Path, payload: object = None) -> None:
    with open(path, "wb") as fh:
        pickle.dump({"info": [payload if payload is not None else _CallsGetcwd()]}, fh)


# ----------------------------------------------------------------------------------------- NMFs-CSL
def build_nmfs_csl(root: Path) -> Fixture:
    root.mkdir(parents=True, exist_ok=True)
    (root / "dictionary.txt").write_text("0\t谢谢\n1 你好\n2\t对不起\n3 再见\n", encoding="utf-8")
    train = [("P01/0_01.mp4", 0), ("P01/1_01.mp4", 1), ("P02/2_01.mp4", 2), ("P02/3_01.mp4", 3), ("P03/0_02.mp4", 0)]
    test = [("P04/1_01.mp4", 1), ("P04/2_01.mp4", 2), ("video/P05/3_01.mp4", 3)]
    for rel, _ in train + test:
        write_video(root / ("" if rel.startswith("video/") else "video") / rel)
    train_lines = [f"{p} {c}" for p, c in train] + ["P09/9_01.mp4 9", "only_a_path.mp4", "P09/missing.mp4 1"]
    (root / "train.txt").write_text("\n".join(train_lines) + "\n", encoding="utf-8")
    (root / "test.txt").write_text("\n".join(f"{p} {c}" for p, c in test) + "\n", encoding="utf-8")
    (root / "confusing.txt").write_text("0\n2\n", encoding="utf-8")
    bad = [("train.txt", 6, "class 9 is not in"), ("train.txt", 7, "malformed row"), ("train.txt", 8, "missing media")]
    return Fixture(root, {"train": 5, "dev": 0, "test": 3}, bad)


# ----------------------------------------------------------------------------------------- MEAD
def flame_arrays(frames: int = 4, rng: np.random.Generator | None = None) -> dict[str, np.ndarray]:
    rng = rng or np.random.default_rng(0)
    dims = {"exp": 50, "jaw": 3, "global_pose": 3, "shape": 100, "cam": 3}
    return {k: rng.normal(size=(frames, d)).astype(np.float32) for k, d in dims.items()}


def build_mead(root: Path) -> Fixture:
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


# ----------------------------------------------------------------------------------------- SOKE SMPL-X
def smplx_frame(rng: np.random.Generator, expression: int = 10) -> dict[str, np.ndarray]:
    dims = {"global_orient": 3, "body_pose": 63, "left_hand_pose": 45, "right_hand_pose": 45, "jaw_pose": 3,
            "expression": expression, "betas": 10, "transl": 3}
    return {k: rng.normal(size=(d,)).astype(np.float32) for k, d in dims.items()}


def _write_frames_pkl(folder: Path, frames: list[dict], numbers: list[int]) -> None:
    folder.mkdir(parents=True)
    for n, frame in zip(numbers, frames, strict=True):
        with open(folder / f"{n}.pkl", "wb") as fh:
            pickle.dump(frame, fh)


def build_soke(root: Path) -> Fixture:
    rng = np.random.default_rng(0)
    notes = ["id,text,gloss,signer"]
    for split, names in (("train", ["a1", "a2"]), ("val", ["b1"]), ("test", ["c1"])):
        for name in names:
            _write_frames_pkl(root / split / name, [smplx_frame(rng) for _ in range(3)], [1, 2, 10])
            notes.append(f"{name},text of {name},GLOSS {name.upper()},s{name[-1]}")
    broken = [smplx_frame(rng) for _ in range(3)]
    del broken[1]["left_hand_pose"]
    _write_frames_pkl(root / "train" / "bad_key", broken, [0, 1, 2])
    notes.append("bad_key,broken,,")
    uneven = [smplx_frame(rng, 10), smplx_frame(rng, 10), smplx_frame(rng, 50)]
    _write_frames_pkl(root / "train" / "bad_shape", uneven, [0, 1, 2])
    notes.append("bad_shape,broken,,")
    (root / "train" / "empty").mkdir()
    notes.append("empty,nothing,,")
    _write_frames_pkl(root / "test" / "no_note", [smplx_frame(rng)], [0])
    (root / "annotation.csv").write_text("\n".join(notes) + "\n", encoding="utf-8")
    bad = [("train/bad_key/1.pkl", None, "'left_hand_pose' missing"),
           ("train/bad_shape/2.pkl", None, "'expression' has 50 values"),
           ("train/empty", None, "missing media"), ("test/no_note", None, "no row in the annotation")]
    return Fixture(root, {"train": 2, "dev": 1, "test": 1}, bad)


# ----------------------------------------------------------------------------------------- slt pickles
def slt_entries(split: str, n: int, rng: np.random.Generator) -> list[dict]:
    return [{"name": f"{split}/clip{i}", "signer": f"Signer0{i}", "gloss": "REGEN MORGEN", "text": "es regnet",
             "sign": rng.normal(size=(5 + i, 12)).astype(np.float32)} for i in range(n)]


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


def write_torch_slt(path: Path) -> None:
    import torch

    with gzip.open(path, "wb") as fh:
        pickle.dump([{"name": "train/x", "signer": "s", "gloss": "", "text": "", "sign": torch.zeros(3, 4)}], fh)


# ----------------------------------------------------------------------------------------- .pose files
def build_pose_collection(root: Path, lexicon: Path, rows: list[dict]) -> Fixture:
    """Copy a few real lexicon ``.pose`` files (``rows`` of its data.csv) into an index-CSV collection."""
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
    bad = [("index.csv", 6, "truncated"), ("index.csv", 7, "missing media"), ("index.csv", 8, "split 'holdout'"),
           ("index.csv", 9, "malformed row")]
    (root / "index.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return Fixture(root, {"train": 2, "dev": 1, "test": 1}, bad)
