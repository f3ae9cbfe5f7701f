"""MEAD as face-only data: FLAME parameters extracted per clip (EMOTE's layout), listed without h5py.

Layout::

    <root>/<subject>/<emotion>/<level>/<clip>/shape_pose_cam.hdf5   (or shape_pose_cam.npz, same arrays)

Each file holds ``exp`` (T, 50 or 100), ``jaw`` (T, 3) axis-angle, ``global_pose`` (T, 3), ``shape``
(T, 100 or 300) and ``cam`` (T, 3) at 25 fps. Listing only walks for the file names; :func:`read_flame_params`
reads one (``.npz`` with numpy, ``.hdf5`` with h5py imported on demand). signer = subject, text =
``"<emotion> <level>"``, language ``"none"``. Splits are by subject: the ``dev_subjects`` / ``test_subjects``
options when given, otherwise a deterministic 80/10/10 hash of the subject name.
"""
from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from m3t.corpora.base import (
    Collector,
    CorpusAdapter,
    CorpusError,
    Listing,
    check_fractions,
    hash_split,
    with_kind,
)
from m3t.corpora.clip import Clip

FILE_STEM = "shape_pose_cam"
FLAME_KEYS = ("exp", "jaw", "global_pose", "shape", "cam")
FIXED_DIMS = {"jaw": 3, "global_pose": 3, "cam": 3}


@dataclass(frozen=True)
class MeadConfig:
    """Options (params.yaml ``corpora.mead``)."""

    fps: float = 25.0
    dev_subjects: tuple[str, ...] = ()
    test_subjects: tuple[str, ...] = ()
    split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)  # used when no subjects are named

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ValueError(f"corpora.mead.fps must be > 0, got {self.fps}")
        check_fractions(self.split_fractions, "corpora.mead.split_fractions")
        both = set(self.dev_subjects) & set(self.test_subjects)
        if both:
            raise ValueError(f"corpora.mead: subjects {sorted(both)} are in both dev_subjects and test_subjects")


class MeadCorpus(CorpusAdapter):
    """Lists MEAD FLAME-parameter clips (media kind ``flame_params``)."""

    name = "mead"
    config_type = MeadConfig

    def split_of(self, subject: str) -> str:
        cfg = self.config
        if cfg.dev_subjects or cfg.test_subjects:
            return "test" if subject in cfg.test_subjects else "dev" if subject in cfg.dev_subjects else "train"
        return hash_split(subject, cfg.split_fractions, salt="mead-subject")

    def listing(self) -> Listing:
        if not self.root.is_dir():
            raise CorpusError(f"MEAD root {self.root} is not a folder; point it at the folder of subject folders")
        out = Collector(self.root)
        found: dict[PurePosixPath, list[str]] = {}
        for folder, dirs, files in os.walk(self.root):
            dirs.sort()
            names = [f for f in files if f in (f"{FILE_STEM}.npz", f"{FILE_STEM}.hdf5")]
            if names:
                found[PurePosixPath(Path(folder).relative_to(self.root).as_posix())] = sorted(names)
        for rel, names in sorted(found.items()):
            media = rel / (f"{FILE_STEM}.npz" if f"{FILE_STEM}.npz" in names else f"{FILE_STEM}.hdf5")  # npz: no h5py
            if len(rel.parts) != 4:
                out.quarantine(self.root / media, None, None,
                               "unexpected location: expected <subject>/<emotion>/<level>/<clip>/" + media.name)
                continue
            subject, emotion, level, clip_name = rel.parts
            clip = Clip(id=f"{subject}_{emotion}_{level}_{clip_name}", corpus=self.name, split=self.split_of(subject),
                        language="none", signer=subject, text=f"{emotion} {level}", gloss="", media=media.as_posix(),
                        fps=self.config.fps,
                        extra=with_kind("flame_params", emotion=emotion, level=level, clip=clip_name))
            out.add(clip, self.root / media, None)
        return out.listing()


def read_flame_params(path: str | Path) -> dict[str, np.ndarray]:
    """FLAME parameters of one clip as float32 arrays keyed by :data:`FLAME_KEYS`.

    Shapes: ``exp`` (T, E), ``jaw`` (T, 3), ``global_pose`` (T, 3), ``shape`` (T, S), ``cam`` (T, 3); T frames.
    ``.npz`` is read with numpy (no pickles); ``.hdf5`` needs h5py, imported only here.
    """
    path = Path(path)
    if not path.is_file():
        raise CorpusError(f"FLAME parameter file {path} not found")
    raw: dict[str, np.ndarray] = {}
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                raw = {k: np.asarray(data[k]) for k in FLAME_KEYS if k in data.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            raise CorpusError(f"{path}: not a readable .npz ({exc}); re-export the clip") from exc
    elif path.suffix in (".hdf5", ".h5"):
        try:
            import h5py
        except ImportError as exc:
            raise ImportError(f"reading {path} needs h5py: pip install h5py (or convert the clip to "
                              f"{FILE_STEM}.npz with the same arrays, which needs only numpy)") from exc
        try:
            with h5py.File(path, "r") as data:
                raw = {k: np.asarray(data[k]) for k in FLAME_KEYS if k in data}
        except OSError as exc:
            raise CorpusError(f"{path}: not a readable HDF5 file ({exc}); re-extract the clip") from exc
    else:
        raise CorpusError(f"{path}: unsupported FLAME parameter file; expected {FILE_STEM}.npz or .hdf5")
    return _checked(raw, path)


def _checked(raw: dict[str, np.ndarray], path: Path) -> dict[str, np.ndarray]:
    missing = [k for k in FLAME_KEYS if k not in raw]
    if missing:
        raise CorpusError(f"{path} lacks datasets {missing}; expected {', '.join(FLAME_KEYS)} (EMOTE's export)")
    out = {}
    frames = raw["exp"].shape[0] if raw["exp"].ndim == 2 else -1
    for key in FLAME_KEYS:
        value = raw[key].astype(np.float32)
        if value.ndim != 2 or value.shape[0] != frames:
            raise CorpusError(f"{path}: dataset {key!r} has shape {value.shape}; expected (T, D) with the T of 'exp'"
                              f" ({frames})")
        if key in FIXED_DIMS and value.shape[1] != FIXED_DIMS[key]:
            raise CorpusError(f"{path}: dataset {key!r} has {value.shape[1]} columns; expected {FIXED_DIMS[key]}")
        out[key] = value
    return out
