"""SOKE's already-fitted SMPL-X corpora (media kind ``smplx_params``): per-frame pickles read with the allow-list
unpickler (numpy arrays only), as released on SOKE's project page and read by its loaders
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
"""
from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.corpora.annotation_files import csv_rows, load_data_pickle, read_lines
from m3t.corpora.base import CorpusAdapter
from m3t.corpora.clip import Clip
from m3t.corpora.listing import (
    Collector,
    CorpusError,
    Listing,
    media_path_problem,
    with_kind,
)
from m3t.corpora.splits import SPLIT_DIRS

SMPLX_DIMS = {"global_orient": 3, "body_pose": 63, "left_hand_pose": 45, "right_hand_pose": 45, "jaw_pose": 3,
              "expression": None, "betas": None}  # None: any width, the same in every frame
SMPLX_OPTIONAL = {"leye_pose": 3, "reye_pose": 3, "transl": 3}
SOKE_NAMES = {"smplx_root_pose": "global_orient", "smplx_body_pose": "body_pose", "smplx_lhand_pose": "left_hand_pose",
              "smplx_rhand_pose": "right_hand_pose", "smplx_jaw_pose": "jaw_pose", "smplx_expr": "expression",
              "smplx_shape": "betas"}  # SOKE / SMPLer-X frame keys -> the smplx package's names
FRAME_NAMES = (re.compile(r"(\d+)"), re.compile(r"images(\d+)"), re.compile(r".+_(\d+)_3D"))  # <n>, Phoenix, How2Sign
POSES_DIR = "poses"  # SOKE's How2Sign (<split>/poses/<clip>) and CSL-Daily (poses/<clip>) folder


class SmplxSequenceError(CorpusError):
    """A SOKE clip whose frames cannot be stacked; ``file`` is the frame pickle and ``key`` the parameter."""

    def __init__(self, message: str, file: Path, key: str | None):
        super().__init__(message)
        self.file, self.key = file, key


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
        return [], (f"frame pickle {min(bad)} has no frame number (expected <n>.pkl, images<n>.pkl or "
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
    return stack_smplx_frames((file, load_data_pickle(file, allow_numpy=True)) for file in files)


def stack_smplx_frames(records: Iterable[tuple[Path, object]]) -> dict[str, np.ndarray]:
    """(T, D) float32 arrays per SMPL-X key from T frame records ``(file, frame dict)`` in time order: SOKE's or
    the smplx package's key names, one frame's values per key ((D,) or (1, D)). The checks and messages of
    :func:`load_smplx_sequence`, which reads one record per frame pickle; at least one record."""
    rows: dict[str, list[np.ndarray]] = {}
    optional: set[str] = set()
    soke = False
    first: Path | None = None
    for i, (file, raw) in enumerate(records):
        if not isinstance(raw, dict):
            raise SmplxSequenceError(f"{file}: expected a dict of SMPL-X arrays, found {type(raw).__name__}",
                                     file, None)
        frame = _smplx_named(raw, file)
        if i == 0:
            optional = {k for k in SMPLX_OPTIONAL if k in frame}
            soke = frame is not raw
            first = file
        shown = {v: k for k, v in SOKE_NAMES.items()} if soke else {}  # errors name keys as the files do
        for key in (*SMPLX_DIMS, *sorted(optional)):
            if key not in frame:
                raise SmplxSequenceError(f"{file}: key {key!r} missing (present in {first.name})"
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
            raise SmplxSequenceError(f"{file}: key {key!r} present but absent in {first.name}", file, key)
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
        expected = "at least id,text (optional gloss,signer,language,split)"
        header, records = csv_rows(lines, path, expected, out)
        if not {"id", "text"} <= set(header):
            raise CorpusError(f"{path} line 1: columns {list(header)}; expected {expected}")
        rows: dict[str, dict[str, str]] = {}
        for row, record in records:
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
