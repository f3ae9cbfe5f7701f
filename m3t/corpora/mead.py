"""MEAD as face-only data: FLAME parameters extracted per clip (EMOTE's EMICA-MEAD release), listed without h5py.

Layout (``root`` = the folder of subject folders, e.g. ``mead_25fps/processed/reconstructions/EMICA-MEAD_flame2020``
of EMOTE's ``reconstruction_v1.zip``)::

    <root>/<subject>/<view>/<emotion>/<level>/<clip>/shape_pose_cam.hdf5   the release (view: front, ...)
    <root>/<subject>/<emotion>/<level>/<clip>/shape_pose_cam.hdf5          a tree without the view level
    (either may hold shape_pose_cam.npz instead: the same arrays, read with numpy only)

Source of the layout: inferno (radekd91/inferno, the EMOTE code), ``inferno/datasets/FaceVideoDataModule.py``
writes ``<method>/<subject>/<view>/<emotion>/<level>/<clip>/shape_pose_cam.hdf5`` through
``inferno/datasets/IO.py:_save_hdf5_dict``, one dataset per key with a leading batch axis of 1
("we saved the data with a leading batch dimension of size 1"); ``inferno/datasets/MEADDataModule.py`` reads
only the ``front`` view by default; ``inferno_apps/TalkingHead/data_processing/download_processed_mead.sh``
downloads the release. Each file holds ``exp`` (1, T, 100), ``jaw`` (1, T, 3) axis-angle, ``global_pose``
(1, T, 3), ``shape`` (1, T, 300) and ``cam`` (1, T, 3) at 25 fps; EMOCA-style exports hold (T, 50) / (T, 100)
arrays without the batch axis. Both are accepted; an optional ``eyelids`` (T, 2) dataset (trackers that fit
FLAME's eyelid blendshapes) is kept when present.

Listing only walks for the file names; :func:`read_flame_params` reads one (``.npz`` with numpy, ``.hdf5`` with
h5py imported on demand). Only the ``views`` option's views are listed (default ``front``, the release's only
view); a clip of another view is quarantined with that reason. signer = subject, text = ``"<emotion> <level>"``,
language ``"none"``. Splits are by subject: the ``dev_subjects`` / ``test_subjects`` options when given,
otherwise a deterministic 80/10/10 hash of the subject name.
"""
from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from m3t.corpora.base import CorpusAdapter
from m3t.corpora.clip import Clip
from m3t.corpora.listing import Collector, CorpusError, Listing, with_kind
from m3t.corpora.splits import check_fractions, hash_split
from m3t.declared import DeclaredSizeError, check_hdf5_dataset, open_npz

FILE_STEM = "shape_pose_cam"
FLAME_KEYS = ("exp", "jaw", "global_pose", "shape", "cam")
OPTIONAL_KEYS = ("eyelids",)
FIXED_DIMS = {"jaw": 3, "global_pose": 3, "cam": 3, "eyelids": 2}
MEAD_VIEWS = ("front", "down", "top", "left_30", "left_60", "right_30", "right_60")  # MEAD's seven cameras
RELEASE_VIEW = "front"


@dataclass(frozen=True)
class MeadConfig:
    """Options (params.yaml ``corpora.mead``)."""

    fps: float = 25.0
    views: tuple[str, ...] = (RELEASE_VIEW,)  # views listed from a <subject>/<view>/... tree
    dev_subjects: tuple[str, ...] = ()
    test_subjects: tuple[str, ...] = ()
    split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)  # used when no subjects are named

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ValueError(f"corpora.mead.fps must be > 0, got {self.fps}")
        unknown = sorted(set(self.views) - set(MEAD_VIEWS))
        if unknown or not self.views:
            raise ValueError(f"corpora.mead.views: {unknown or 'empty'}; expected some of {', '.join(MEAD_VIEWS)}")
        check_fractions(self.split_fractions, "corpora.mead.split_fractions")
        both = set(self.dev_subjects) & set(self.test_subjects)
        if both:
            raise ValueError(f"corpora.mead: subjects {sorted(both)} are in both dev_subjects and test_subjects")


class MeadCorpus(CorpusAdapter):
    """Lists MEAD FLAME-parameter clips (media kind ``flame_params``)."""

    name = "mead"
    config_type = MeadConfig
    imported_kind = "flame_params"  # fit-corpus imports these clips (m3t.fitting.imports), never tracks them

    def split_of(self, subject: str) -> str:
        cfg = self.config
        if cfg.dev_subjects or cfg.test_subjects:
            return "test" if subject in cfg.test_subjects else "dev" if subject in cfg.dev_subjects else "train"
        return hash_split(subject, cfg.split_fractions, salt="mead-subject")

    def listing(self) -> Listing:
        if not self.root.is_dir():
            raise CorpusError(f"MEAD root {self.root} is not a folder; point it at the folder of subject folders "
                              f"(EMOTE's release: .../reconstructions/EMICA-MEAD_flame2020)")
        out = Collector(self.root)
        found: dict[PurePosixPath, list[str]] = {}
        for folder, dirs, files in os.walk(self.root):
            dirs.sort()
            names = [f for f in files if f in (f"{FILE_STEM}.npz", f"{FILE_STEM}.hdf5")]
            if names:
                found[PurePosixPath(Path(folder).relative_to(self.root).as_posix())] = sorted(names)
        for rel, names in sorted(found.items()):
            media = rel / (f"{FILE_STEM}.npz" if f"{FILE_STEM}.npz" in names else f"{FILE_STEM}.hdf5")  # npz: no h5py
            parts = rel.parts
            if len(parts) == 5 and parts[1] in MEAD_VIEWS:
                subject, view, emotion, level, clip_name = parts
                if view not in self.config.views:
                    out.quarantine(self.root / media, None, None,
                                   f"view {view!r} not in corpora.mead.views ({', '.join(self.config.views)})")
                    continue
                clip_id = f"{subject}_{view}_{emotion}_{level}_{clip_name}"
            elif len(parts) == 4:
                (subject, emotion, level, clip_name), view = parts, None
                clip_id = f"{subject}_{emotion}_{level}_{clip_name}"
            else:
                out.quarantine(self.root / media, None, None,
                               f"unexpected location: expected <subject>/<view>/<emotion>/<level>/<clip>/{media.name} "
                               f"(view one of {', '.join(MEAD_VIEWS)}) or <subject>/<emotion>/<level>/<clip>/"
                               f"{media.name}")
                continue
            clip = Clip(id=clip_id, corpus=self.name, split=self.split_of(subject),
                        language="none", signer=subject, text=f"{emotion} {level}", gloss="", media=media.as_posix(),
                        fps=self.config.fps,
                        extra=with_kind("flame_params", view=view, emotion=emotion, level=level, clip=clip_name))
            out.add(clip, self.root / media, None)
        return out.listing()

    def source(self, clip: Clip) -> dict[str, np.ndarray]:
        """A listed clip's FLAME parameters (:func:`read_flame_params`), for the import."""
        return read_flame_params(self.root / clip.media)


def read_flame_params(path: str | Path) -> dict[str, np.ndarray]:
    """FLAME parameters of one clip as float32 (T, D) arrays keyed by :data:`FLAME_KEYS` (+ ``eyelids`` if present).

    Shapes: ``exp`` (T, E), ``jaw`` (T, 3), ``global_pose`` (T, 3), ``shape`` (T, S), ``cam`` (T, 3), ``eyelids``
    (T, 2); T frames. Each dataset may be stored as (T, D) or with EMOTE's leading batch axis, (1, T, D).
    ``.npz`` is read with numpy (no pickles); ``.hdf5`` needs h5py, imported only here.
    """
    path = Path(path)
    if not path.is_file():
        raise CorpusError(f"FLAME parameter file {path} not found")
    keys = FLAME_KEYS + OPTIONAL_KEYS
    raw: dict[str, np.ndarray] = {}
    if path.suffix == ".npz":
        try:
            with open_npz(path) as data:
                raw = {k: np.asarray(data[k]) for k in keys if k in data.files}
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
                raw = {k: _hdf5_array(data[k], k, path) for k in keys if k in data}
        except (OSError, DeclaredSizeError) as exc:
            raise CorpusError(f"{path}: not a readable HDF5 file ({exc}); re-extract the clip") from exc
    else:
        raise CorpusError(f"{path}: unsupported FLAME parameter file; expected {FILE_STEM}.npz or .hdf5")
    return _checked(raw, path)


def _hdf5_array(node, key: str, path: Path) -> np.ndarray:
    """A dataset of numbers, its declared size checked against its storage before it is read."""
    import h5py

    if not isinstance(node, h5py.Dataset) or node.dtype.kind not in "fiub":
        kind = f"a dataset of {node.dtype}" if isinstance(node, h5py.Dataset) else type(node).__name__
        raise CorpusError(f"{path}: {key!r} is {kind}, not a dataset of numbers; re-extract the clip")
    check_hdf5_dataset(node, str(path))
    return np.asarray(node[()])


def _frames_first(value: np.ndarray, key: str, path: Path) -> np.ndarray:
    """(T, D) or EMOTE's (1, T, D) -> (T, D); anything else is refused naming the dataset."""
    if value.ndim == 3 and value.shape[0] == 1:
        return value[0]
    if value.ndim == 2:
        return value
    raise CorpusError(f"{path}: dataset {key!r} has shape {value.shape}; expected (T, D) or EMOTE's (1, T, D) "
                      f"(one clip per file)")


def _checked(raw: dict[str, np.ndarray], path: Path) -> dict[str, np.ndarray]:
    missing = [k for k in FLAME_KEYS if k not in raw]
    if missing:
        raise CorpusError(f"{path} lacks datasets {missing}; expected {', '.join(FLAME_KEYS)} (EMOTE's export)")
    for key, value in raw.items():
        if value.dtype.kind not in "fiu":  # strings, objects: astype would fail without naming the file
            raise CorpusError(f"{path}: dataset {key!r} holds {value.dtype} values; expected numbers (float32)")
    out = {k: _frames_first(raw[k], k, path).astype(np.float32) for k in FLAME_KEYS + OPTIONAL_KEYS if k in raw}
    frames = out["exp"].shape[0]
    for key, value in out.items():
        if value.shape[0] != frames:
            raise CorpusError(f"{path}: dataset {key!r} has {value.shape[0]} frames, 'exp' has {frames}; every "
                              f"dataset needs one row per frame")
        if key in FIXED_DIMS and value.shape[1] != FIXED_DIMS[key]:
            raise CorpusError(f"{path}: dataset {key!r} has {value.shape[1]} columns; expected {FIXED_DIMS[key]}")
    return out
