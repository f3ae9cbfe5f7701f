"""Errors of a fit against ground truth (synthetic corpus): joints in mm and per-modality parameter errors.

Joint error uses the heads of every bone a rotation stream drives (upper body, wrists, all finger
joints). A monocular fit only observes the body relative to its camera (a rotation of the camera and a
counter-rotation of the spine give the same image), so ``joint_mm`` compares joints in each one's camera
frame after removing the per-frame centroid (translation alignment only): it still contains the depth
ambiguity of a single view. ``pa_joint_mm`` aligns each frame by a similarity Procrustes (the usual
PA-MPJPE, :func:`m3t.metrics.procrustes.procrustes_error_mm`) and measures articulation only; it needs no
camera, so the tracker initialisation gets it too.
Axis legend: T frames, J joints, D modality dim.
"""
from __future__ import annotations

import numpy as np
import torch

from m3t.body.metric_sets import joints_for, metric_joints  # noqa: F401 - joints_for: also used by the engine
from m3t.body.protocol import BodyModel
from m3t.body.rotations import sixd_to_matrix
from m3t.metrics.procrustes import procrustes_error_mm


def _camera_frame(joints: torch.Tensor, camera: dict) -> torch.Tensor:
    """(T, J, 3) world joints -> camera frame, centred per frame."""
    rot = torch.as_tensor(camera["rotation"], dtype=joints.dtype)
    cam = joints @ rot.T + torch.as_tensor(camera["translation"], dtype=joints.dtype)
    return cam - cam.mean(dim=1, keepdim=True)


@torch.no_grad()
def ground_truth_errors(
    body: BodyModel,
    fitted: dict[str, np.ndarray],
    fitted_identity: np.ndarray,
    fitted_camera: dict,
    truth: dict[str, np.ndarray],
    truth_identity: np.ndarray,
    truth_camera: dict,
) -> dict[str, float]:
    """``joint_mm`` (mean per-joint 3D error), ``<rotation stream>_deg`` (mean geodesic angle) and
    ``<scalar stream>_abs`` (mean absolute error)."""
    fit_j = joints_for(body, fitted, fitted_identity)
    true_j = joints_for(body, truth, truth_identity)
    fit_c, true_c = _camera_frame(fit_j, fitted_camera), _camera_frame(true_j, truth_camera)
    out = {"joint_mm": float(torch.linalg.norm(fit_c - true_c, dim=-1).mean() * 1000.0),
           "pa_joint_mm": procrustes_error_mm(fit_j, true_j)}
    for m in body.layout.modalities:
        a, b = torch.as_tensor(fitted[m.name]), torch.as_tensor(truth[m.name])
        if m.kind == "rotation6d":
            ra = sixd_to_matrix(a.reshape(*a.shape[:-1], -1, 6))
            rb = sixd_to_matrix(b.reshape(*b.shape[:-1], -1, 6))
            cos = ((ra.transpose(-1, -2) @ rb).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
            out[f"{m.name}_deg"] = float(torch.rad2deg(torch.arccos(cos.clamp(-1, 1))).mean())
        else:
            out[f"{m.name}_abs"] = float((a - b).abs().mean())
    return out
