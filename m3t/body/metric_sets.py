"""The keypoint sets that evaluation measures, defined once for every body model.

Following SOKE's evaluation (M3T Sec. 4, SGSA Tab. 1):
- ``body``: 12 upper-body points: neck, shoulders, elbows, wrists, ears, eyes, nose;
- ``left_hand`` / ``right_hand``: 21 points each in OpenPose hand order (wrist; thumb CMC, MCP, IP, tip;
  then MCP, PIP, DIP, tip of index, middle, ring, pinky), fingertips from vertices;
- ``face``: the vertices the face stream moves (for DTW-VPE).

Every point except the neck is taken from the body model's MediaPipe-Holistic correspondence (its pose
part for the 11 face and arm points, its hand parts for the hands: MediaPipe's hand order is OpenPose's),
so Anny and SMPL-FX share one definition. The neck, absent from MediaPipe, is the model's neck joint.
The face vertices are found through the protocol itself: those that move when the face stream changes.
The sets plug into ``body.keypoint_set`` / ``body.forward_keypoints``.

Axis legend: T frames, K keypoints.
"""
from __future__ import annotations

import numpy as np
import torch

from m3t.body.landmarks import HAND_LANDMARKS
from m3t.body.protocol import BodyModel, Correspondence, KeypointIndex, as_tensors

BODY_POINTS = ("neck", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
               "left_ear", "right_ear", "left_eye", "right_eye", "nose")
NECK_JOINT = {"anny": "neck01", "smplfx": "neck"}
HAND_POINTS = HAND_LANDMARKS  # all 21 MediaPipe hand landmarks, wrist first (OpenPose's order)
FACE_MOTION_THRESHOLD_M = 1e-5


def subset_correspondence(corr: Correspondence, names: list[str] | tuple[str, ...]) -> Correspondence:
    """The rows of ``corr`` for ``names``, in that order; a ``KeyError`` names the landmarks it lacks."""
    position = {n: i for i, n in enumerate(corr.names)}
    missing = [n for n in names if n not in position]
    if missing:
        raise KeyError(f"landmarks {missing} are not in the correspondence")
    rows = [position[n] for n in names]
    return Correspondence(tuple(names), corr.kind[rows].copy(), corr.index[rows].copy())


def _neck_index(body: BodyModel) -> int:
    name = NECK_JOINT.get(body.name)
    if name is None or name not in body.joint_names:
        candidates = [n for n in body.joint_names if n.lower().startswith("neck")]
        if not candidates:
            raise KeyError(f"body model {body.name!r} has no neck joint; add it to NECK_JOINT")
        name = candidates[0]
    return body.joint_names.index(name)


@torch.no_grad()
def face_vertices(body: BodyModel) -> np.ndarray:
    """Vertex indices moved by the face stream (rest vs. a mid-range face), sorted."""
    rest = body.rest_params(1)
    face = body.layout["face"]
    moved = {k: v.clone() for k, v in rest.items()}
    bump = rest["face"] + 0.5
    if face.bounds is not None:
        bump = bump.clamp(*face.bounds)
    moved["face"] = bump
    identity = body.default_identity()
    a = body.forward(rest, identity).vertices[0]
    b = body.forward(moved, identity).vertices[0]
    return np.flatnonzero((torch.linalg.norm(a - b, dim=-1) > FACE_MOTION_THRESHOLD_M).cpu().numpy())


def metric_keypoints(body: BodyModel, landmark_set: str = "mediapipe_holistic") -> dict[str, Correspondence]:
    """``{"body": 12 points, "left_hand": 21, "right_hand": 21, "face": face vertices}`` for ``body``."""
    corr = body.correspondence(landmark_set)
    pose = subset_correspondence(corr, [f"pose:{n}" for n in BODY_POINTS[1:]])
    body_set = Correspondence(BODY_POINTS, np.concatenate([[1], pose.kind]), np.concatenate([[_neck_index(body)], pose.index]))
    out = {"body": body_set}
    for side in ("left_hand", "right_hand"):
        hand = subset_correspondence(corr, [f"{side}:{n}" for n in HAND_POINTS])
        out[side] = Correspondence(HAND_POINTS, hand.kind, hand.index)
    for name, c in out.items():
        if not c.valid.all():
            lost = [n for n, ok in zip(c.names, c.valid) if not ok]
            raise ValueError(f"metric set {name!r} of body model {body.name!r} lacks points {lost}")
    verts = face_vertices(body)
    out["face"] = Correspondence(tuple(f"v{v}" for v in verts), np.zeros(len(verts), dtype=np.int64), verts.astype(np.int64))
    return out


def joined_keypoints(body: BodyModel, sets: dict[str, Correspondence]) -> tuple[KeypointIndex, dict[str, slice]]:
    """One keypoint set for all ``sets`` (their points one after the other) and each set's slice of it."""
    names, kinds, indices, slices, start = [], [], [], {}, 0
    for name, c in sets.items():
        names += [f"{name}:{n}" for n in c.names]
        kinds.append(np.asarray(c.kind))
        indices.append(np.asarray(c.index))
        slices[name] = slice(start, start + len(c.names))
        start += len(c.names)
    joined = Correspondence(tuple(names), np.concatenate(kinds), np.concatenate(indices))
    return body.keypoint_set(joined), slices


def metric_points(body: BodyModel, params: dict[str, torch.Tensor], identity: torch.Tensor,
                  sets: dict[str, Correspondence] | None = None,
                  joined: tuple[KeypointIndex, dict[str, slice]] | None = None) -> dict[str, torch.Tensor]:
    """(T, K, 3) positions of every metric set for a parameter sequence: one sparse forward over all the sets'
    points. ``joined``: :func:`joined_keypoints` of ``sets``, for callers that pose many sequences (building a
    keypoint set gathers the model's buffers: ~2 ms per set)."""
    if joined is None:
        joined = joined_keypoints(body, sets or metric_keypoints(body))
    keypoints, slices = joined
    points = body.forward_keypoints(params, identity, keypoints)
    return {name: points[:, sl] for name, sl in slices.items()}


def metric_joints(body: BodyModel) -> Correspondence:
    """Joint-only correspondence over the bones driven by rotation streams."""
    names = [label for m in body.layout.modalities if m.kind == "rotation6d" for label in m.labels]
    index = np.array([body.joint_names.index(n) for n in names], dtype=np.int64)
    return Correspondence(tuple(names), np.ones(len(names), dtype=np.int64), index)


def joints_for(body: BodyModel, params: dict[str, np.ndarray], identity: np.ndarray) -> torch.Tensor:
    """(T, J, 3) metric joints of a parameter sequence."""
    kp = body.keypoint_set(metric_joints(body))
    return body.forward_keypoints(as_tensors(params), torch.as_tensor(identity, dtype=torch.float32), kp)
