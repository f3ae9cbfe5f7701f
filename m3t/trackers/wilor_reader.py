"""Reader of WiLoR's hand estimates (M3T App. 0.C's hand tracker).

Format (field names checked against WiLoR / HaMeR ``demo.py`` and the model's forward): one file per clip
(``.npz`` or a torch-saved dict), one row per detected hand: ``frame_index`` (N,) int; ``is_right`` (N,) 0/1
(WiLoR's ``batch['right']``); ``global_orient`` (N, 1, 3, 3) and ``hand_pose`` (N, 15, 3, 3) rotation matrices
and ``betas`` (N, 10), i.e. the model's ``out['pred_mano_params']`` (also accepted nested under that key);
optional ``confidence`` (N,) detector score. Rotations are MANO's, relative to the flat hand (``MANOLayer`` with
rotation matrices adds no hand mean). WiLoR runs left hands as flipped right hands: their parameters are mirrored
back here (``R -> M R M``, M = diag(-1, 1, 1)), giving left-hand MANO / SMPL-X rotations. Several hands of one
side in a frame: the most confident is kept.

Axis legend: N detections.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.trackers.tracker_files import (
    TrackerFileError,
    load_tracker_file,
    tracker_array,
)

REFLECT_X = np.diag([-1.0, 1.0, 1.0])


@dataclass(frozen=True)
class HandEstimates:
    """One side's hands over frames (only frames where the hand was found)."""

    frame: np.ndarray  # (N,) int
    hand_pose: np.ndarray  # (N, 15, 3, 3) MANO rotations of this side
    global_orient: np.ndarray  # (N, 3, 3) camera-frame wrist orientation of this side
    betas: np.ndarray  # (N, 10)
    confidence: np.ndarray  # (N,)


def _mirror_matrices(rot: np.ndarray) -> np.ndarray:
    return REFLECT_X @ rot @ REFLECT_X


def read_wilor(path: str | Path) -> dict[str, HandEstimates]:
    """``{"left": ..., "right": ...}`` from a WiLoR output file (format in the module docstring)."""
    path = Path(path)
    data = load_tracker_file(path)
    if isinstance(data.get("pred_mano_params"), dict):
        data = {**data, **data["pred_mano_params"]}
    go = tracker_array(data, "global_orient", path, (3, 3)).reshape(-1, 3, 3)
    hp = tracker_array(data, "hand_pose", path, (3, 3)).reshape(go.shape[0], 15, 3, 3)
    betas = tracker_array(data, "betas", path).reshape(go.shape[0], -1)
    frame = tracker_array(data, "frame_index", path).astype(np.int64).reshape(-1)
    right = tracker_array(data, "is_right", path).reshape(-1) > 0.5
    conf = tracker_array(data, "confidence", path).reshape(-1) if "confidence" in data else np.ones(go.shape[0])
    if not (len(frame) == len(right) == len(conf) == go.shape[0]):
        raise TrackerFileError(f"{path}: fields disagree on the number of detections")
    out = {}
    for side, mask in (("right", right), ("left", ~right)):
        rows = np.flatnonzero(mask)
        best: dict[int, int] = {}
        for r in rows:  # the most confident detection per frame
            if frame[r] not in best or conf[r] > conf[best[frame[r]]]:
                best[int(frame[r])] = int(r)
        keep = np.array([best[f] for f in sorted(best)], dtype=np.int64)
        h, g = hp[keep], go[keep]
        if side == "left":  # WiLoR ran these as flipped right hands
            h, g = _mirror_matrices(h), _mirror_matrices(g)
        out[side] = HandEstimates(frame[keep], h, g, betas[keep], conf[keep])
    return out
