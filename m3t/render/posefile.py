"""Export body-model motion as a ``.pose`` file (pose-format), so generated signing opens in the tools the
community already uses (pose-format viewers, spoken-to-signed, sign-language segmentation / recognition).

The points are the body model's MediaPipe-Holistic correspondence in 3D, in metres and in the body model's
own frame (Anny: z up; SMPL-FX: y up), one component per holistic part; points the model has no
correspondence for get confidence 0.

Axis legend: T frames, K points.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import torch

from m3t.body.protocol import BodyModel, as_tensors

COMPONENTS = {"pose": "POSE_LANDMARKS", "face": "FACE_LANDMARKS", "left_hand": "LEFT_HAND_LANDMARKS",
              "right_hand": "RIGHT_HAND_LANDMARKS"}


@torch.no_grad()
def holistic_points(body: BodyModel, params: dict[str, np.ndarray], identity: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """(T, K, 3) holistic points in metres, (K,) validity and the K point names (``part:name``)."""
    corr = body.correspondence("mediapipe_holistic")
    ident = torch.as_tensor(np.asarray(identity), dtype=torch.float32)
    points = body.forward_keypoints(as_tensors(params), ident, body.keypoint_set(corr)).numpy()
    return points, corr.valid, tuple(corr.names)


def export_pose(path: str | Path, body: BodyModel, params: dict[str, np.ndarray], identity: np.ndarray,
                fps: float) -> Path:
    """Write ``params`` as a ``.pose`` file (atomically), metres in the body model's frame."""
    from pose_format import Pose
    from pose_format.numpy.pose_body import NumPyPoseBody
    from pose_format.pose_header import (
        PoseHeader,
        PoseHeaderComponent,
        PoseHeaderDimensions,
    )

    points, valid, names = holistic_points(body, params, identity)
    parts = [n.split(":", 1)[0] for n in names]
    order, components = [], []
    for part, component in COMPONENTS.items():
        idx = [i for i, p in enumerate(parts) if p == part]
        order += idx
        components.append(PoseHeaderComponent(component, [names[i].split(":", 1)[1] for i in idx], [], [], "XYZC"))
    data = points[:, order][:, None]  # (T, 1 person, K, 3)
    conf = np.broadcast_to(valid[order].astype(np.float32), data.shape[:-1]).copy()
    header = PoseHeader(0.1, PoseHeaderDimensions(1000, 1000, 1000), components)
    pose = Pose(header, NumPyPoseBody(fps=float(fps), data=data.astype(np.float32), confidence=conf))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            pose.write(fh)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
