"""Reader of NLF's body estimates (M3T App. 0.C's body tracker).

Format (field names checked against NLF ``detect_smpl_batched``): one file per clip (``.npz`` or torch-saved
dict) for the signer, with SMPL-X parameters of ``detect_smpl_batched(..., model_name='smplx')``: ``pose``
(T, 165) axis-angle of the 55 SMPL-X joints (global orient, 21 body, jaw, two eyes, 15 + 15 finger joints),
``betas`` (T, 10), ``trans`` (T, 3); optional ``frame_index`` (T,) and ``confidence`` (T,) (the detection score,
``boxes[..., 4]``). The per-frame lists that ``detect_smpl_batched`` returns (``pose[t]`` of shape (people, 165))
are accepted too: the first (most confident) person is taken; frames without a person are missing. NaN rows are
missing frames.

Axis legend: T frames of the file, N frames with an estimate.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import roma
import torch

from m3t.trackers.tracker_files import load_tracker_file, tracker_array


def axis_angle_to_matrix(aa: np.ndarray) -> np.ndarray:
    return roma.rotvec_to_rotmat(torch.as_tensor(aa, dtype=torch.float64)).numpy()


@dataclass(frozen=True)
class BodyEstimates:
    frame: np.ndarray  # (N,) int
    rotations: np.ndarray  # (N, 55, 3, 3) SMPL-X joint rotations (global orient first)
    betas: np.ndarray  # (N, 10)
    translation: np.ndarray  # (N, 3)
    confidence: np.ndarray  # (N,)


def read_nlf(path: str | Path) -> BodyEstimates:
    """NLF SMPL-X estimates of one signer (format in the module docstring)."""
    path = Path(path)
    data = load_tracker_file(path)
    if isinstance(data.get("pose"), (list, tuple)):  # per-frame lists straight from detect_smpl_batched
        frames, pose, betas, trans, conf = [], [], [], [], []
        for t, p in enumerate(data["pose"]):
            p = np.asarray(p.detach().cpu() if torch.is_tensor(p) else p, dtype=np.float64).reshape(-1, 165)
            if p.shape[0] == 0:
                continue
            frames.append(t)
            pose.append(p[0])
            betas.append(np.asarray(data["betas"][t], dtype=np.float64).reshape(-1, 10)[0])
            trans.append(np.asarray(data["trans"][t], dtype=np.float64).reshape(-1, 3)[0])
            boxes = data.get("boxes")
            conf.append(float(np.asarray(boxes[t]).reshape(-1, 5)[0, 4]) if boxes is not None else 1.0)
        pose_a, betas_a, trans_a = np.array(pose).reshape(-1, 165), np.array(betas).reshape(-1, 10), np.array(trans).reshape(-1, 3)
        frame_a, conf_a = np.array(frames, dtype=np.int64), np.array(conf)
    else:
        pose_a = tracker_array(data, "pose", path, (165,)).reshape(-1, 165)
        betas_a = tracker_array(data, "betas", path).reshape(pose_a.shape[0], -1)[:, :10]
        trans_a = tracker_array(data, "trans", path, (3,)).reshape(-1, 3)
        frame_a = (tracker_array(data, "frame_index", path).astype(np.int64).reshape(-1) if "frame_index" in data
                   else np.arange(pose_a.shape[0]))
        conf_a = tracker_array(data, "confidence", path).reshape(-1) if "confidence" in data else np.ones(pose_a.shape[0])
        found = np.isfinite(pose_a).all(1) & np.isfinite(betas_a).all(1)
        pose_a, betas_a, trans_a, frame_a, conf_a = (a[found] for a in (pose_a, betas_a, trans_a, frame_a, conf_a))
    rot = axis_angle_to_matrix(pose_a.reshape(-1, 55, 3)) if len(pose_a) else np.zeros((0, 55, 3, 3))
    return BodyEstimates(frame_a, rot, betas_a, trans_a, conf_a)
