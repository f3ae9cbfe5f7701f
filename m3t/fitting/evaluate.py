"""Errors of a fit against ground truth (synthetic corpus): joints in mm and per-modality parameter errors.

Joint error uses the heads of every bone a rotation stream drives (upper body, wrists, all finger
joints). A monocular fit only observes the body relative to its camera (a rotation of the camera and a
counter-rotation of the spine give the same image), so ``joint_mm`` compares joints in each one's camera
frame after removing the per-frame centroid (translation alignment only): it still contains the depth
ambiguity of a single view. ``pa_joint_mm`` aligns each frame by a similarity Procrustes (the usual
PA-MPJPE) and measures articulation only; it needs no camera, so the tracker initialisation gets it too.
Axis legend: T frames, J joints, D modality dim.
"""
from __future__ import annotations

import numpy as np
import roma
import torch

from m3t.body.protocol import BodyModel, Correspondence
from m3t.body.rotations import sixd_to_matrix


def metric_joints(body: BodyModel) -> Correspondence:
    """Joint-only correspondence over the bones driven by rotation streams."""
    names = [label for m in body.layout.modalities if m.kind == "rotation6d" for label in m.labels]
    index = np.array([body.joint_names.index(n) for n in names], dtype=np.int64)
    return Correspondence(tuple(names), np.ones(len(names), dtype=np.int64), index)


def as_tensors(params: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """numpy (T, D) per modality -> float32 tensors."""
    return {k: torch.as_tensor(np.asarray(v), dtype=torch.float32) for k, v in params.items()}


def procrustes_error_mm(pred: torch.Tensor, truth: torch.Tensor) -> float:
    """Mean joint error (mm) after per-frame similarity alignment of pred (T, J, 3) onto truth (T, J, 3)."""
    rot, trans, scale = roma.rigid_points_registration(pred, truth, compute_scaling=True)
    aligned = scale[:, None, None] * (pred @ rot.transpose(-1, -2)) + trans[:, None]
    return float(torch.linalg.norm(aligned - truth, dim=-1).mean() * 1000.0)


def joints_for(body: BodyModel, params: dict[str, np.ndarray], identity: np.ndarray) -> torch.Tensor:
    """(T, J, 3) metric joints of a parameter sequence."""
    kp = body.keypoint_set(metric_joints(body))
    return body.forward_keypoints(as_tensors(params), torch.as_tensor(identity, dtype=torch.float32), kp)


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
