"""Pose files as the motion definitions score them: a pose-format ``.pose`` file (MediaPipe Holistic, as
pose-format's ``load_holistic`` / ``video_to_pose`` writes it, and as :func:`m3t.render.posefile.export_pose`
writes the produced motion) -> the holistic point array of definition ``pose_eval`` and the 178-keypoint array
of definition ``slrtp``.

- **Holistic** (:func:`holistic_array`): pose-format's component order without world landmarks,
  ``POSE_LANDMARKS`` 33, ``FACE_LANDMARKS`` 478 (or 468, as the file has it), ``LEFT_HAND_LANDMARKS`` 21,
  ``RIGHT_HAND_LANDMARKS`` 21 (:data:`m3t.metrics.pose_eval.HOLISTIC_JOINTS`). Points are placed by component and
  point name, so a file with its components in another order, or with ``POSE_WORLD_LANDMARKS``, gives the same
  array. A point the file lacks, or stores with confidence 0 (pose-format's mask) or a non-finite value, is NaN.
  A file without ``FACE_LANDMARKS`` gets 478 NaN face points.
- **SLRTP** (:func:`slrtp_array`): the challenge's 178 keypoints (:data:`m3t.metrics.slrtp.SLRTP_JOINT_NAMES`):
  the 8 body joints from the POSE landmarks of the same side (``RShoulder`` = ``RIGHT_SHOULDER``, the signer's
  right, as MediaPipe names it), the right hand 8-28 from ``RIGHT_HAND_LANDMARKS`` and the left hand 29-49 from
  ``LEFT_HAND_LANDMARKS`` in MediaPipe's landmark order, and the 128 face slots from the face mesh points
  :data:`m3t.metrics.slrtp.SLRTP_FACE_MESH_INDICES` (NaN for an iris point of a 468-point face). The challenge's
  data are 3D uplifts; here the file's own coordinates are used (pose-format: x, y in pixels, z scaled like x), so
  the distances are in the file's units. Both sides of a pair go through the same mapping; the DTW-MJE and the
  frame distances do not depend on the face slots' order, which the challenge never published.

Axis legend: T frames, J joints (553 / 543 holistic, 178 SLRTP), D coordinates the file stores (2 or 3).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.corpora.listing import CorpusError
from m3t.corpora.posefile import PoseData, component_offsets, matched_points, read_pose
from m3t.metrics.pose_eval import FACE_MESH, FACE_REFINED, HAND_POINTS, POSE_POINTS
from m3t.metrics.slrtp import (
    SLRTP_BODY_JOINTS,
    SLRTP_FACE_MESH_INDICES,
    SLRTP_NUM_JOINTS,
)

HOLISTIC_COMPONENTS = ("POSE_LANDMARKS", "FACE_LANDMARKS", "LEFT_HAND_LANDMARKS", "RIGHT_HAND_LANDMARKS")
REQUIRED_COMPONENTS = ("POSE_LANDMARKS", "LEFT_HAND_LANDMARKS", "RIGHT_HAND_LANDMARKS")
# SLRTP body joint -> MediaPipe POSE landmark (``R`` / ``L``: the signer's right / left, as MediaPipe's RIGHT_ / LEFT_)
SLRTP_BODY_SOURCES = {name: ("RIGHT_" if name[0] == "R" else "LEFT_") + name[1:].upper()
                      for name in SLRTP_BODY_JOINTS}


class ScoreInputError(ValueError):
    """A prediction or reference that cannot be scored; the message names the file and what to do."""


@dataclass(frozen=True)
class PoseClip:
    """One ``.pose`` file in the holistic layout: ``points`` (T, J, D) float64, NaN where missing."""

    clip_id: str
    path: Path
    points: np.ndarray
    fps: float

    @property
    def face_points(self) -> int:
        return self.points.shape[1] - len(POSE_POINTS) - 2 * len(HAND_POINTS)


def _component_offsets(data: PoseData, source: str) -> dict[str, tuple[int, tuple[str, ...]]]:
    offsets = component_offsets(data)
    if offsets is None:
        raise ScoreInputError(f"{source}: the .pose data carry no point names; read the file with "
                              "m3t.corpora.posefile.read_pose")
    absent = [c for c in REQUIRED_COMPONENTS if c not in offsets]
    if absent:
        raise ScoreInputError(f"{source}: not a MediaPipe Holistic .pose file; it lacks {absent} (components: "
                              f"{[c for c, _ in data.components]}); score files written by pose-format's holistic "
                              "reader or by m3t produce")
    return offsets


def holistic_array(data: PoseData, source: str = "<pose>") -> np.ndarray:
    """(T, J, D) float64 holistic points of one person's ``.pose`` data (see the module doc), NaN where missing."""
    offsets = _component_offsets(data, source)
    face = len(offsets["FACE_LANDMARKS"][1]) if "FACE_LANDMARKS" in offsets else FACE_REFINED
    if face not in (FACE_REFINED, FACE_MESH):
        raise ScoreInputError(f"{source}: FACE_LANDMARKS has {face} points; the holistic layouts have "
                              f"{FACE_REFINED} (refined, with irises) or {FACE_MESH}")
    targets = {"POSE_LANDMARKS": POSE_POINTS, "FACE_LANDMARKS": tuple(str(i) for i in range(face)),
               "LEFT_HAND_LANDMARKS": HAND_POINTS, "RIGHT_HAND_LANDMARKS": HAND_POINTS}
    dims = int(data.dims)
    frames = data.points.shape[0]
    out = np.full((frames, sum(len(v) for v in targets.values()), dims), np.nan)
    valid = (data.confidence > 0) & np.isfinite(data.points[..., :dims]).all(-1)  # (T, N)
    first = 0
    for component in HOLISTIC_COMPONENTS:
        names = targets[component]
        src, dst = matched_points(offsets, component, names, first)
        if src:
            out[:, dst] = np.where(valid[:, src, None], data.points[:, src, :dims], np.nan)
        first += len(names)
    return out


def read_pose_clip(path: str | Path, clip_id: str) -> PoseClip:
    """Read one ``.pose`` file as a :class:`PoseClip`; :class:`ScoreInputError` naming the file when it cannot be."""
    path = Path(path)
    try:
        data = read_pose(path)
    except CorpusError as exc:
        raise ScoreInputError(str(exc)) from exc
    if data.points.shape[0] == 0:
        raise ScoreInputError(f"{path}: no frames")
    return PoseClip(clip_id, path, holistic_array(data, str(path)), float(data.fps))


def slrtp_array(holistic: np.ndarray) -> np.ndarray:
    """(T, 178, D) SLRTP keypoints of a (T, J, D) holistic array (553 or 543 joints), NaN where missing."""
    joints = holistic.shape[1]
    face = joints - len(POSE_POINTS) - 2 * len(HAND_POINTS)
    if face not in (FACE_REFINED, FACE_MESH):
        raise ScoreInputError(f"slrtp_array: {joints} joints is not a holistic layout (553 or 543)")
    body = [POSE_POINTS.index(SLRTP_BODY_SOURCES[name]) for name in SLRTP_BODY_JOINTS]
    left_hand = len(POSE_POINTS) + face
    right_hand = left_hand + len(HAND_POINTS)
    hands = list(range(right_hand, right_hand + len(HAND_POINTS))) + list(range(left_hand, right_hand))
    out = np.full((holistic.shape[0], SLRTP_NUM_JOINTS, holistic.shape[2]), np.nan)
    out[:, : len(body) + len(hands)] = holistic[:, body + hands]
    mesh = np.asarray(SLRTP_FACE_MESH_INDICES)
    inside = mesh < face
    face_slots = np.arange(len(body) + len(hands), SLRTP_NUM_JOINTS)
    out[:, face_slots[inside]] = holistic[:, len(POSE_POINTS) + mesh[inside]]
    return out
