"""Already-fitted corpora in community pickle formats, read with the allow-list unpickler (numpy arrays only).

SOKE's SMPL-X fits (media kind ``smplx_params``), as released on SOKE's project page and read by its loaders
(2000ZRL/SOKE, ``mGPT/data/humanml/load_data.py``: ``load_h2s_sample``, ``load_csl_sample``,
``load_phoenix_sample``)::

    <root>/<split>/poses/<clip_id>/<clip_id>_<n>_3D.pkl   How2Sign (split train / val / test)
    <root>/<split>/<clip_id>/images<n>.pkl                 Phoenix-2014T (its names are <split>/<clip_id>)
    <root>/poses/<clip_id>/<n>.pkl                         CSL-Daily: no split folders; the split comes from
                                                           the annotation's ``split`` column
    <root>/<split>/<clip_id>/<n>.pkl                       any other per-frame export
    <root>/<annotation>.csv                                optional: id,text[,gloss,signer,language,split]

One dict per frame. SOKE's files (SMPLer-X output) name the arrays ``smplx_root_pose`` (3,), ``smplx_body_pose``
(63,), ``smplx_lhand_pose`` (45,), ``smplx_rhand_pose`` (45,), ``smplx_jaw_pose`` (3,), ``smplx_shape`` (10,),
``smplx_expr`` (10,); exports written with the smplx package's names (``global_orient``, ``body_pose``,
``left_hand_pose``, ``right_hand_pose``, ``jaw_pose``, ``betas``, ``expression``; optional ``leye_pose``,
``reye_pose``, ``transl``) are read too. :func:`load_smplx_sequence` stacks the frames in the numeric order of
``<n>`` and returns the smplx names. Hand poses are as the fitter wrote them: SMPLer-X / SOKE build SMPL-X with
the smplx default ``flat_hand_mean=False`` (poses relative to the mean hand), which the ``flat_hand_mean``
option records for the import (:mod:`m3t.fitting.imports`). The split folder ``val`` is ``dev``.

slt-style gzip pickles (media kind ``keypoints``): ``<name>.{train,dev,test}`` or ``<name>.<split>.pkl.gz``, each a
gzip-compressed pickle of a list of ``{name, signer, gloss, text, sign}`` with ``sign`` a (T, D) float array. The
originals hold torch tensors; those are refused (convert to numpy once), never unpickled. What ``sign`` holds
is not documented by the format (CNN features in neccam/slt's Phoenix files, keypoints in some conversions):
fit-corpus stores it as it is, never as joints.
"""
from __future__ import annotations

import csv
import io
import re
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.corpora.base import (
    Collector,
    CorpusAdapter,
    CorpusError,
    Listing,
    load_data_pickle,
    media_path_problem,
    read_lines,
    with_kind,
)
from m3t.corpora.clip import Clip

SPLIT_DIRS = {"train": "train", "dev": "dev", "val": "dev", "test": "test"}
SMPLX_DIMS = {"global_orient": 3, "body_pose": 63, "left_hand_pose": 45, "right_hand_pose": 45, "jaw_pose": 3,
              "expression": None, "betas": None}  # None: any width, the same in every frame
SMPLX_OPTIONAL = {"leye_pose": 3, "reye_pose": 3, "transl": 3}
SOKE_NAMES = {"smplx_root_pose": "global_orient", "smplx_body_pose": "body_pose", "smplx_lhand_pose": "left_hand_pose",
              "smplx_rhand_pose": "right_hand_pose", "smplx_jaw_pose": "jaw_pose", "smplx_expr": "expression",
              "smplx_shape": "betas"}  # SOKE / SMPLer-X frame keys -> the smplx package's names
FRAME_NAMES = (re.compile(r"(\d+)"), re.compile(r"images(\d+)"), re.compile(r".+_(\d+)_3D"))  # <n>, Phoenix, How2Sign
POSES_DIR = "poses"  # SOKE's How2Sign (<split>/poses/<clip>) and CSL-Daily (poses/<clip>) folder
SLT_KEYS = ("name", "signer", "gloss", "text", "sign")


class SmplxSequenceError(CorpusError):
    """A SOKE clip whose frames cannot be stacked; ``file`` is the frame pickle and ``key`` the parameter."""

    def __init__(self, message: str, file: Path, key: str | None):
        super().__init__(message)
        self.file, self.key = file, key


# ----------------------------------------------------------------------------------------- SOKE
@dataclass(frozen=True)
class SokeSmplxConfig:
    """Options (params.yaml ``corpora.soke_smplx``)."""

    annotation: str = ""  # CSV relative to the root; empty = no text (clips listed with empty text)
    fps: float = 25.0  # of the source videos the fits were made from
    language: str = "unknown"
    validate: bool = False  # load every clip while listing and quarantine those that do not stack
    flat_hand_mean: bool = False  # False: hand poses are relative to SMPL-X's mean hand (SMPLer-X / SOKE)

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ValueError(f"corpora.soke_smplx.fps must be > 0, got {self.fps}")


def frame_number(name: str) -> int | None:
    """The frame number of a frame pickle's stem (``12``, ``images0012``, ``<clip>_12_3D``), None if it has none."""
    for pattern in FRAME_NAMES:
        match = pattern.fullmatch(name)
        if match:
            return int(match.group(1))
    return None


def _frame_files(folder: Path) -> tuple[list[Path], str | None]:
    """Frame pickles in numeric order, or the problem (a name without a frame number, no frames)."""
    frames = [p for p in folder.iterdir() if p.suffix == ".pkl"]
    bad = [p.name for p in frames if frame_number(p.stem) is None]
    if bad:
        return [], (f"frame pickle {sorted(bad)[0]} has no frame number (expected <n>.pkl, images<n>.pkl or "
                    f"<clip>_<n>_3D.pkl)")
    if not frames:
        return [], "missing media (no <frame>.pkl files)"
    return sorted(frames, key=lambda p: frame_number(p.stem)), None


def _smplx_named(frame: dict, file: Path) -> dict:
    """A frame dict with SOKE's keys renamed to the smplx package's (a frame mixing both is refused)."""
    if not any(k in frame for k in SOKE_NAMES):
        return frame
    both = sorted(k for k, name in SOKE_NAMES.items() if k in frame and name in frame)
    if both:
        raise SmplxSequenceError(f"{file}: holds both {both[0]!r} and {SOKE_NAMES[both[0]]!r}; keep one naming",
                                 file, both[0])
    return {SOKE_NAMES.get(k, k): v for k, v in frame.items()}


def load_smplx_sequence(path: str | Path) -> dict[str, np.ndarray]:
    """Stack a SOKE clip folder's frame pickles into (T, D) float32 arrays per SMPL-X key (T frames).

    Keys are the smplx package's names (:data:`SMPLX_DIMS`, plus the :data:`SMPLX_OPTIONAL` ones the first frame
    has). Raises :class:`SmplxSequenceError` naming the frame file and key (as the file names it) for a missing
    key or an inconsistent shape.
    """
    folder = Path(path)
    if not folder.is_dir():
        raise SmplxSequenceError(f"SMPL-X clip folder {folder} not found", folder, None)
    files, problem = _frame_files(folder)
    if problem:
        raise SmplxSequenceError(f"{folder}: {problem}", folder, None)
    rows: dict[str, list[np.ndarray]] = {}
    optional: set[str] = set()
    soke = False
    for i, file in enumerate(files):
        raw = load_data_pickle(file, allow_numpy=True)
        if not isinstance(raw, dict):
            raise SmplxSequenceError(f"{file}: expected a dict of SMPL-X arrays, found {type(raw).__name__}",
                                     file, None)
        frame = _smplx_named(raw, file)
        if i == 0:
            optional = {k for k in SMPLX_OPTIONAL if k in frame}
            soke = frame is not raw
        shown = {v: k for k, v in SOKE_NAMES.items()} if soke else {}  # errors name keys as the files do
        for key in (*SMPLX_DIMS, *sorted(optional)):
            if key not in frame:
                raise SmplxSequenceError(f"{file}: key {key!r} missing (present in {files[0].name})"
                                         if key in optional else f"{file}: SMPL-X key {shown.get(key, key)!r} missing",
                                         file, shown.get(key, key))
            value = np.asarray(frame[key], dtype=np.float32).reshape(-1)  # (1, D) and (D,) both occur
            want = SMPLX_DIMS.get(key) or SMPLX_OPTIONAL.get(key)
            width = want if want is not None else (rows[key][0].shape[0] if key in rows else value.shape[0])
            if value.shape[0] != width or value.shape[0] == 0:
                raise SmplxSequenceError(f"{file}: key {shown.get(key, key)!r} has {value.shape[0]} values; "
                                         f"expected {width}", file, shown.get(key, key))
            rows.setdefault(key, []).append(value)
        extra = set(SMPLX_OPTIONAL) & set(frame) - optional
        if extra:
            key = min(extra)
            raise SmplxSequenceError(f"{file}: key {key!r} present but absent in {files[0].name}", file, key)
    return {k: np.stack(v) for k, v in rows.items()}  # (T, D)


class SokeSmplxCorpus(CorpusAdapter):
    """Lists SOKE-style per-frame SMPL-X fits, one clip per folder."""

    name = "soke_smplx"
    config_type = SokeSmplxConfig
    imported_kind = "smplx_params"  # fit-corpus imports these clips (m3t.fitting.imports), never tracks them

    def read_annotation(self, out: Collector) -> dict[str, dict[str, str]] | None:
        cfg = self.config
        if not cfg.annotation:
            return None
        path = self.root / cfg.annotation
        unsafe = media_path_problem(self.root, cfg.annotation)
        if unsafe is not None:
            raise CorpusError(f"corpora.soke_smplx.annotation: {unsafe}")
        lines = read_lines(path, "Set corpora.soke_smplx.annotation to a CSV with columns "
                                 "id,text[,gloss,signer,language,split].")
        reader = csv.DictReader(io.StringIO("\n".join(lines)))
        if not {"id", "text"} <= set(reader.fieldnames or ()):
            raise CorpusError(f"{path} line 1: columns {reader.fieldnames}; expected at least id,text "
                              f"(optional gloss,signer,language,split)")
        rows: dict[str, dict[str, str]] = {}
        for row, record in enumerate(reader, start=2):
            clip_id = (record.get("id") or "").strip()
            if not clip_id or None in record:
                out.quarantine(path, row, clip_id or None, "malformed row: empty id or extra columns")
            elif clip_id in rows:
                out.quarantine(path, row, clip_id, "id listed twice")
            else:
                rows[clip_id] = {k: (v or "").strip() for k, v in record.items()} | {"row": str(row)}
        return rows

    def clip_folders(self, notes: dict[str, dict[str, str]] | None) -> list[tuple[str | None, Path]]:
        """(split folder name or None, clip folder) of every clip folder, in listing order."""
        split_dirs = [self.root / d for d in SPLIT_DIRS if (self.root / d).is_dir()]
        if split_dirs:
            bases = [(d.name, d / POSES_DIR if (d / POSES_DIR).is_dir() else d) for d in split_dirs]
        elif (self.root / POSES_DIR).is_dir():
            if notes is None or not any(n.get("split") for n in notes.values()):
                raise CorpusError(f"{self.root}/{POSES_DIR} holds clips without split folders (SOKE's CSL-Daily "
                                  f"layout); set corpora.soke_smplx.annotation to a CSV with a split column "
                                  f"(train/dev/test, from SOKE's csl_clean.<split> lists)")
            bases = [(None, self.root / POSES_DIR)]
        else:
            raise CorpusError(f"{self.root} has none of the split folders {', '.join(SPLIT_DIRS)} and no "
                              f"{POSES_DIR}/ folder; point the root at the folder holding "
                              f"<split>/<clip_id>/<frame>.pkl (or <split>/{POSES_DIR}/<clip_id>/...)")
        return [(split, folder) for split, base in bases for folder in sorted(p for p in base.iterdir() if p.is_dir())]

    def listing(self) -> Listing:
        cfg = self.config
        out = Collector(self.root)
        notes = self.read_annotation(out)
        for split_name, folder in self.clip_folders(notes):
            unsafe = out.media_problem(out.rel(folder))  # a symlinked clip folder may lead out of the root
            if unsafe is not None:
                out.quarantine(folder, None, folder.name, f"{unsafe}: {out.rel(folder)}")
                continue
            files, problem = _frame_files(folder)
            if problem:
                out.quarantine(folder, None, folder.name, problem)
                continue
            note = {} if notes is None else notes.get(folder.name)
            if note is None:
                out.quarantine(folder, None, folder.name, f"no row in the annotation {cfg.annotation}")
                continue
            split = SPLIT_DIRS.get(split_name or note.get("split", ""))
            if split is None:
                out.quarantine(self.root / cfg.annotation, int(note["row"]), folder.name,
                               f"split {note.get('split', '')!r}; expected one of {', '.join(SPLIT_DIRS)}")
                continue
            if cfg.validate:
                try:
                    load_smplx_sequence(folder)
                except CorpusError as exc:
                    file = getattr(exc, "file", folder)
                    out.quarantine(file, None, folder.name, str(exc).removeprefix(f"{file}: "))
                    continue
            clip = Clip(id=folder.name, corpus=self.name, split=split,
                        language=note.get("language") or cfg.language, signer=note.get("signer") or "unknown",
                        text=note.get("text", ""), gloss=note.get("gloss", ""),
                        media=out.rel(folder), fps=cfg.fps,
                        extra=with_kind("smplx_params", frames=len(files)))
            out.add(clip, folder, None)
        return out.listing()

    def source(self, clip: Clip) -> dict[str, np.ndarray]:
        """A listed clip's stacked SMPL-X arrays (:func:`load_smplx_sequence`), for the import."""
        return load_smplx_sequence(self.root / clip.media)


# ----------------------------------------------------------------------------------------- slt
@dataclass(frozen=True)
class SltPickleConfig:
    """Options (params.yaml ``corpora.slt_pickle``); ``files`` relative to the root, empty = discover."""

    files: tuple[str, ...] = ()
    fps: float = 25.0
    language: str = "unknown"

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ValueError(f"corpora.slt_pickle.fps must be > 0, got {self.fps}")


def split_of_file(path: Path) -> str | None:
    """Split named by ``x.train`` / ``x.dev`` / ``x.test`` / ``x.<split>.pkl.gz`` / ``<split>.pkl.gz``."""
    name = path.name.removesuffix(".pkl.gz")
    return SPLIT_DIRS.get(name.rsplit(".", 1)[-1])


def read_slt_pickle(path: str | Path) -> list:
    """The list of records of one slt-style gzip pickle (numpy arrays allowed, torch tensors refused)."""
    path = Path(path)
    data = load_data_pickle(path, allow_numpy=True, compressed=True)
    if not isinstance(data, list):
        raise CorpusError(f"{path}: expected a list of {{{', '.join(SLT_KEYS)}}} records, found {type(data).__name__}")
    return data


def _slt_problem(entry: object) -> str | None:
    if not isinstance(entry, dict):
        return f"entry is a {type(entry).__name__}, expected a dict with keys {', '.join(SLT_KEYS)}"
    missing = [k for k in SLT_KEYS if k not in entry]
    if missing:
        return f"entry lacks keys {missing}"
    if not isinstance(entry["name"], str) or not entry["name"]:
        return "name is not a non-empty string"
    sign = entry["sign"]
    if not isinstance(sign, np.ndarray) or sign.ndim != 2 or sign.shape[0] == 0 or sign.dtype.kind != "f":
        shape = getattr(sign, "shape", type(sign).__name__)
        return f"sign is {shape}; expected a non-empty (T, D) float array"
    return None


class SltPickleCorpus(CorpusAdapter):
    """Lists the records of slt-style gzip pickles; media = the pickle file, the record index in extra."""

    name = "slt_pickle"
    config_type = SltPickleConfig
    imported_kind = "keypoints"  # fit-corpus imports these clips (m3t.fitting.imports), never tracks them

    def __init__(self, root: str | Path, config: SltPickleConfig | None = None):
        super().__init__(root, config)
        self._lock = threading.Lock()
        self._held: tuple[Path, list] | None = None  # the last file read: every clip of a file is in it

    def entries(self, path: Path) -> list:
        """The records of one file; the last file read is kept (one unpickling per file, not per clip)."""
        with self._lock:
            if self._held is None or self._held[0] != path:
                self._held = (path, read_slt_pickle(path))
            return self._held[1]

    def files(self) -> list[Path]:
        if self.config.files:
            return [self.root / f for f in self.config.files]
        found = sorted(p for p in self.root.glob("*")  # a .pkl.gz without a split is listed, then quarantined
                       if p.is_file() and (split_of_file(p) is not None or p.name.endswith(".pkl.gz")))
        if not found:
            raise CorpusError(f"{self.root} holds no <name>.train/.dev/.test or <name>.<split>.pkl.gz files; "
                              f"point the root at them or set corpora.slt_pickle.files")
        return found

    def listing(self) -> Listing:
        cfg = self.config
        out = Collector(self.root)
        for path in self.files():
            unsafe = out.media_problem(out.rel(path))  # a params value or a symbolic link may lead out of the root
            if unsafe is not None:
                out.quarantine(path, None, None, unsafe)
                continue
            split = split_of_file(path)
            if split is None:
                out.quarantine(path, None, None, "cannot tell the split from the file name (.train/.dev/.test)")
                continue
            for index, entry in enumerate(read_slt_pickle(path)):
                problem = _slt_problem(entry)
                if problem:
                    name = entry.get("name") if isinstance(entry, dict) else None
                    out.quarantine(path, index, name if isinstance(name, str) and name else None, problem)
                    continue
                clip = Clip(id=entry["name"].replace("/", "__"), corpus=self.name, split=split, language=cfg.language,
                            signer=str(entry["signer"]), text=str(entry["text"]), gloss=str(entry["gloss"]),
                            media=out.rel(path), fps=cfg.fps,
                            extra=with_kind("keypoints", index=index, frames=entry["sign"].shape[0],
                                            dims=entry["sign"].shape[1], name=entry["name"]))
                out.add(clip, path, index)
        return out.listing()

    def sequence(self, clip: Clip) -> np.ndarray:
        """The (T, D) float32 ``sign`` array of a listed clip (its whole pickle file is read once and kept)."""
        entries = self.entries(self.root / clip.media)
        index = int(clip.get("index", "-1"))
        if not 0 <= index < len(entries) or _slt_problem(entries[index]) or entries[index]["name"] != clip.get("name"):
            raise CorpusError(f"{self.root / clip.media}: record {index} is no longer clip {clip.id}; "
                              f"list the corpus again")
        return entries[index]["sign"].astype(np.float32)

    def source(self, clip: Clip) -> dict[str, np.ndarray]:
        """``{"sign": (T, D)}`` of a listed clip, for the import."""
        return {"sign": self.sequence(clip)}
