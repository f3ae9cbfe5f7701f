"""Calibration of the synthetic corpus's generator, once per corpus with the body model.

Finds the flexion axis of every finger bone (the direction that moves the fingertip toward the palm) and, by
inverse kinematics, arm postures that put the dominant hand at each sign location (neutral space, chin,
forehead, cheek, chest, shoulder) and both hands at rest.

Rotations of the generator are rotation vectors applied on top of the template pose:
``R = exp(rotvec) @ R_rest`` (world-aligned axes, Anny's ``local-ref`` parameterisation); :func:`to_params`
turns them into the body model's 6D parameters. Axis legend: T frames, n bones of a stream, N targets.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import roma
import torch

from m3t.body.protocol import BodyModel, Correspondence
from m3t.body.rotations import matrix_to_6d, sixd_to_matrix

ARM = ("clavicle", "upperarm01", "lowerarm01", "wrist")


def stream_rest(body: BodyModel) -> dict[str, torch.Tensor]:
    """Rest rotations (n, 3, 3) of every rotation stream of the body model."""
    return {k: sixd_to_matrix(v[0].reshape(-1, 6)) for k, v in body.rest_params(1).items()
            if body.layout[k].kind == "rotation6d"}


def to_params(rotvecs: dict[str, torch.Tensor], face: torch.Tensor, rest: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rotation vectors (T, n, 3) on top of the rest rotations -> 6D params (T, n*6), plus the face."""
    out = {k: matrix_to_6d(roma.rotvec_to_rotmat(v) @ rest[k]).reshape(v.shape[0], -1) for k, v in rotvecs.items()}
    out["face"] = face
    return out


def _joint(body: BodyModel, name: str) -> int:
    return body.joint_names.index(name)


@dataclass(frozen=True)
class Calibration:
    finger_axes: np.ndarray  # (15, 3) right-hand flexion axes
    locations: dict[str, np.ndarray]  # location -> (4, 3) right-arm rotvecs
    rest_arm: np.ndarray  # (4, 3) right-arm rotvecs of the resting posture


@torch.no_grad()
def _finger_axes(body: BodyModel, rest: dict[str, torch.Tensor]) -> np.ndarray:
    joints = body.forward(body.rest_params(1), body.default_identity()).joints[0]
    p = lambda n: joints[_joint(body, n)]  # noqa: E731
    toward_thumb = p("finger2-1.R") - p("finger5-1.R")
    axes = []
    for f in range(1, 6):
        direction = p(f"finger{f}-3.R") - p(f"finger{f}-1.R")
        direction = direction / direction.norm()
        palm = torch.linalg.cross(toward_thumb, direction)  # right hand: palm side = thumb x fingers
        palm = palm / palm.norm()
        axis = torch.linalg.cross(direction, palm)
        axes += [axis / axis.norm()] * 3
    axes = torch.stack(axes)
    # The sign of the axis depends on frame conventions: keep the one that curls the fingertip toward the palm.
    probe = {k: torch.zeros(1, len(body.layout[k].labels), 3) for k in rest}
    probe["right_hand"] = 1.2 * axes[None]
    face = torch.zeros(1, body.layout["face"].dim)
    curled = body.forward(to_params(probe, face, rest), body.default_identity()).joints[0]
    tip_before = p("finger3-3.R") - p("wrist.R")
    tip_after = curled[_joint(body, "finger3-3.R")] - curled[_joint(body, "wrist.R")]
    if float(torch.dot(tip_after - tip_before, palm)) < 0:
        axes = -axes
    return axes.numpy()


def _targets(body: BodyModel) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """3D targets of the right hand's middle knuckle per location (body faces -y, z up), and the rest target."""
    with torch.no_grad():
        out = body.forward(body.rest_params(1), body.default_identity())
    j = lambda n: out.joints[0, _joint(body, n)].numpy()  # noqa: E731
    head, neck = j("head"), j("neck01")
    shoulders = (j("upperarm01.L") + j("upperarm01.R")) / 2
    fwd, right, up = np.array([0, -1.0, 0]), np.array([-1.0, 0, 0]), np.array([0, 0, 1.0])
    chest = shoulders - 0.15 * up + 0.14 * fwd
    face_front = head + 0.13 * fwd
    targets = {
        "neutral": chest + 0.25 * fwd + 0.1 * right - 0.05 * up,
        "neutral_high": chest + 0.25 * fwd + 0.12 * right + 0.12 * up,
        "chest": chest + 0.06 * fwd,
        "chin": (neck + head) / 2 + 0.14 * fwd,
        "forehead": face_front + 0.12 * up + 0.04 * fwd,
        "cheek": face_front + 0.07 * right - 0.02 * up,
        "shoulder": j("upperarm01.L") + 0.1 * fwd + 0.02 * up,
    }
    rest_target = chest - 0.3 * up + 0.12 * fwd + 0.12 * right
    return targets, rest_target


def _arm_ik(body: BodyModel, rest: dict[str, torch.Tensor], targets: np.ndarray, steps: int = 250) -> np.ndarray:
    """Right-arm rotvecs (N, 4, 3) placing the middle knuckle at each target (N, 3); elbow kept low."""
    n = targets.shape[0]
    arm_idx = [body.layout["body"].labels.index(f"{b}.R") for b in ARM]
    # Only two joints matter: a joint-only sparse forward keeps the IK cheap.
    points = body.keypoint_set(Correspondence(("knuckle", "elbow"), np.ones(2, dtype=np.int64),
                                              np.array([_joint(body, "finger3-1.R"), _joint(body, "lowerarm01.R")])))
    rot = torch.zeros(n, 4, 3, requires_grad=True)
    goal = torch.as_tensor(targets, dtype=torch.float32)
    opt = torch.optim.Adam([rot], lr=0.05)
    zeros = {k: torch.zeros(n, len(body.layout[k].labels), 3) for k in rest}
    face = torch.zeros(n, body.layout["face"].dim)
    for _ in range(steps):
        opt.zero_grad()
        body_rv = zeros["body"].clone()
        body_rv[:, arm_idx] = rot
        joints = body.forward_keypoints(to_params({**zeros, "body": body_rv}, face, rest), body.default_identity(), points)
        loss = ((joints[:, 0] - goal) ** 2).sum(-1).mean() * 100
        loss = loss + 0.002 * (rot ** 2).sum((-1, -2)).mean() + 0.5 * torch.relu(joints[:, 1, 1] - 0.05).mean()
        loss.backward()
        opt.step()
    return rot.detach().numpy()


def calibrate(body: BodyModel) -> Calibration:
    rest = stream_rest(body)
    targets, rest_target = _targets(body)
    names = list(targets)
    solved = _arm_ik(body, rest, np.stack([targets[k] for k in names] + [rest_target]))
    return Calibration(_finger_axes(body, rest), {k: solved[i] for i, k in enumerate(names)}, solved[-1])
