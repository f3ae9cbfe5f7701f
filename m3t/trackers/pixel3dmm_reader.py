"""Reader of Pixel3DMM's face estimates (M3T App. 0.C's face tracker).

Format (field names checked against Pixel3DMM ``tracking/tracker.py::save_checkpoint``): a folder of
``{frame:05d}.frame`` files, each ``torch.save`` of a dict: ``flame``: ``exp`` (1, 100), ``shape`` (1, 300),
``eyes`` (1, 12) (two 6D), ``eyelids`` (1, 2), ``jaw`` (1, 6), ``neck`` (1, 6), ``R`` (1, 6) head rotation,
``t`` (1, 3) (plus ``R_rotation_matrix``); ``camera``: ``R_base_0``, ``t_base_0``, ``fl``, ``pp``; ``img_size``;
``frame_id``; ``global_step``. All rotations are 6D in PyTorch3D's layout (the first two *rows* of the matrix);
they are converted here to this project's layout (first two columns, :mod:`m3t.body.rotations`).

Axis legend: N frames with an estimate.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import roma
import torch

from m3t.trackers.tracker_files import (
    TrackerFileError,
    load_tracker_file,
    tracker_array,
)


def pytorch3d_6d_to_matrix(sixd: np.ndarray) -> np.ndarray:
    """PyTorch3D 6D (first two rows, Gram-Schmidt on rows) -> rotation matrices (..., 3, 3)."""
    rows = torch.as_tensor(sixd, dtype=torch.float64).reshape(*np.shape(sixd)[:-1], 2, 3)
    return roma.special_gramschmidt(rows.transpose(-1, -2)).transpose(-1, -2).numpy()


@dataclass(frozen=True)
class FaceEstimates:
    frame: np.ndarray  # (N,) int
    expression: np.ndarray  # (N, 100)
    eyelids: np.ndarray  # (N, 2)
    jaw: np.ndarray  # (N, 3, 3)
    neck: np.ndarray  # (N, 3, 3)
    head_rotation: np.ndarray  # (N, 3, 3) FLAME's R
    head_translation: np.ndarray  # (N, 3)
    shape: np.ndarray  # (300,) FLAME shape (the tracker's per-clip identity; median over frames)


def frames_folder(folder: Path) -> Path:
    """Pixel3DMM's per-clip output folder -> its ``checkpoint`` subfolder, unless the frames lie directly in it."""
    sub = folder / "checkpoint"
    if folder.is_dir() and sub.is_dir() and not any(folder.glob("*.frame")):
        return sub
    return folder


def read_pixel3dmm(folder: str | Path) -> FaceEstimates:
    """Every ``*.frame`` file of a Pixel3DMM ``checkpoint`` folder, or of the clip's output folder holding it
    (format in the module docstring)."""
    folder = frames_folder(Path(folder))
    files = sorted(folder.glob("*.frame")) if folder.is_dir() else [folder]
    if not files or not files[0].exists():
        raise TrackerFileError(f"{folder}: no Pixel3DMM '*.frame' files (expected <output>/checkpoint/00000.frame ...)")
    rows: dict[str, list] = {k: [] for k in ("frame", "exp", "eyelids", "jaw", "neck", "R", "t", "shape")}
    for f in files:
        data = load_tracker_file(f)
        flame = data.get("flame")
        if not isinstance(flame, dict):
            raise TrackerFileError(f"{f}: field 'flame' missing or not a dict; found {sorted(data)}")
        rows["frame"].append(int(np.asarray(data.get("frame_id", f.stem)).reshape(-1)[0]))
        rows["exp"].append(tracker_array(flame, "exp", f).reshape(-1)[:100])
        rows["eyelids"].append(tracker_array(flame, "eyelids", f, (2,)).reshape(2))
        for key in ("jaw", "neck", "R"):
            rows[key].append(tracker_array(flame, key, f, (6,)).reshape(6) if key in flame else np.array([1.0, 0, 0, 0, 1, 0]))
        rows["t"].append(tracker_array(flame, "t", f, (3,)).reshape(3) if "t" in flame else np.zeros(3))
        rows["shape"].append(tracker_array(flame, "shape", f).reshape(-1))
    exp = np.stack(rows["exp"])
    if exp.shape[1] < 100:
        exp = np.pad(exp, ((0, 0), (0, 100 - exp.shape[1])))
    order = np.argsort(rows["frame"])
    return FaceEstimates(
        frame=np.asarray(rows["frame"], dtype=np.int64)[order],
        expression=exp[order],
        eyelids=np.stack(rows["eyelids"])[order],
        jaw=pytorch3d_6d_to_matrix(np.stack(rows["jaw"]))[order],
        neck=pytorch3d_6d_to_matrix(np.stack(rows["neck"]))[order],
        head_rotation=pytorch3d_6d_to_matrix(np.stack(rows["R"]))[order],
        head_translation=np.stack(rows["t"])[order],
        shape=np.median(np.stack(rows["shape"]), axis=0),
    )
