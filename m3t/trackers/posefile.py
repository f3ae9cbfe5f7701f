"""``.pose`` files (pose-format) with MediaPipe-Holistic components as tracks.

A holistic ``.pose`` file holds, per frame and person, the components ``POSE_LANDMARKS`` (33),
``LEFT_HAND_LANDMARKS`` / ``RIGHT_HAND_LANDMARKS`` (21 each), ``FACE_LANDMARKS`` (468, or 478 with the
refined iris points, or a subset in "reduced holistic" files) and often ``POSE_WORLD_LANDMARKS`` (33), each
point as x, y, z plus a confidence. x and y are pixels of the header's width x height (pose-format
multiplies MediaPipe's normalised output by the video size); z is MediaPipe's relative depth in the same
scale. Collections may have normalised the coordinates: the fingerspelling lexicon shipped in
``spoken-to-signed`` is centred on the shoulders and scaled to a 500 x 500 canvas (shoulders ~200 px
apart, centre (250, 250), z ~250), which is still a valid image for fitting with an unknown camera.

Components and points are matched by name, so reordered or reduced files map correctly; face points past
the 468 mesh points (iris) are dropped. Points with zero confidence (pose-format's masked points) become NaN
with confidence 0. Decoding is :func:`m3t.corpora.posefile.read_pose` (the project's one ``.pose`` reader);
this module only maps its :class:`~m3t.corpora.posefile.PoseData` onto the track layout.

Axis legend: T frames, K = 543 landmarks of the ``mediapipe_holistic`` layout.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.body.landmarks import HAND_LANDMARKS, POSE_LANDMARKS
from m3t.corpora.listing import CorpusError
from m3t.corpora.posefile import (
    PoseData,
    component_offsets,
    matched_points,
    pose_data,
    read_pose,
)
from m3t.trackers.track import MEDIAPIPE_HOLISTIC_PARTS, Track, landmark_slices

# MediaPipe's landmark names (its PoseLandmark / HandLandmark enums, in index order) as pose-format writes them:
# the body layer's lists, upper-case.
POSE_POINTS = tuple(name.upper() for name in POSE_LANDMARKS)
HAND_POINTS = tuple(name.upper() for name in HAND_LANDMARKS)
FACE_POINTS = tuple(str(i) for i in range(MEDIAPIPE_HOLISTIC_PARTS["face"]))
COMPONENTS = {  # track part -> (.pose component, point names in the track's order)
    "pose": ("POSE_LANDMARKS", POSE_POINTS),
    "left_hand": ("LEFT_HAND_LANDMARKS", HAND_POINTS),
    "right_hand": ("RIGHT_HAND_LANDMARKS", HAND_POINTS),
    "face": ("FACE_LANDMARKS", FACE_POINTS),
}
WORLD_COMPONENT = "POSE_WORLD_LANDMARKS"
TRACKER_NAME = "posefile"


class PoseFileError(ValueError):
    """A ``.pose`` file that cannot be turned into a track; the message names the file and the fix."""


@dataclass(frozen=True)
class PoseFileTrack:
    track: Track
    points3d: np.ndarray  # (T, K, 3) float32: the file's x, y, z in its own units; NaN where missing or no z
    pose_world: np.ndarray | None  # (T, 33, 3) float32 POSE_WORLD_LANDMARKS as stored (see module doc); NaN missing


def _offsets(data: PoseData, source: str) -> dict[str, tuple[int, tuple[str, ...]]]:
    """Component name -> (index of its first point on the file's point axis, its point names)."""
    offsets = component_offsets(data)
    if offsets is None:
        raise PoseFileError(f".pose data of {source} carries no point names; read it with "
                            "m3t.corpora.posefile.read_pose / pose_data")
    if COMPONENTS["pose"][0] not in offsets:
        raise PoseFileError(f".pose file {source} is not MediaPipe Holistic: components "
                            f"{[c for c, _ in data.components]}, expected {[c for c, _ in COMPONENTS.values()]}")
    return offsets


def posedata_to_track(pose: PoseData, source: str = "<pose>") -> PoseFileTrack:
    """One person's holistic ``.pose`` data -> track in the ``mediapipe_holistic`` layout (the one conversion:
    single files and spelled words, i.e. concatenated letter files, both come here).

    Parameters
    ----------
    pose : PoseData; points (T, N, 3), confidence (T, N) over the file's N points
    source : the file name (or word), for error messages

    The track keeps the file's z as extra ``depth`` (T, K) when the file has one, and ``POSE_WORLD_LANDMARKS``
    as extra ``pose_world`` (T, 33, 3).
    """
    data, conf = pose.points, pose.confidence  # (T, N, 3), (T, N)
    if data.ndim != 3 or data.shape[0] == 0:
        raise PoseFileError(f".pose file {source} has no frames (data shape {data.shape})")
    offsets = _offsets(pose, source)
    parts = landmark_slices("mediapipe_holistic")
    src, dst = [], []
    for part, (component, names) in COMPONENTS.items():
        a, b = matched_points(offsets, component, names, parts[part].start)
        src, dst = src + a, dst + b
    if not src:
        raise PoseFileError(f".pose file {source}: no point of its holistic components has a MediaPipe landmark "
                            f"name (e.g. {POSE_POINTS[0]!r}); it was not written by pose-format's holistic reader")
    missing = ~(conf > 0) | ~np.isfinite(data).all(-1)  # (T, N)

    T, K = data.shape[0], sum(MEDIAPIPE_HOLISTIC_PARTS.values())
    points3d = np.full((T, K, 3), np.nan, dtype=np.float32)
    points3d[:, dst, : pose.dims] = data[:, src, : pose.dims]
    confidence = np.zeros((T, K), dtype=np.float32)
    confidence[:, dst] = np.clip(conf[:, src], 0.0, 1.0)
    gone = np.ones((T, K), dtype=bool)
    gone[:, dst] = missing[:, src]
    points3d[gone] = np.nan
    confidence[gone] = 0.0

    width, height = pose.width, pose.height
    if width <= 0 or height <= 0:  # no video size recorded: the smallest image holding every point
        seen = points3d[..., :2][~gone]
        width, height = (int(np.ceil(v)) + 1 for v in (seen.max(0) if len(seen) else (1, 1)))

    pose_world = None
    world_src, world_dst = matched_points(offsets, WORLD_COMPONENT, POSE_POINTS, 0)
    if world_src and pose.dims >= 3:
        pose_world = np.full((T, len(POSE_POINTS), 3), np.nan, dtype=np.float32)
        pose_world[:, world_dst] = np.where(missing[:, world_src, None], np.nan, data[:, world_src, :3])
    extras = {}
    if pose.dims >= 3:
        extras["depth"] = points3d[..., 2].copy()
    if pose_world is not None:
        extras["pose_world"] = pose_world
    track = Track(points3d[..., :2].copy(), confidence, "mediapipe_holistic", (width, height), float(pose.fps),
                  np.full(4, np.nan, dtype=np.float32), TRACKER_NAME, extras=extras or None)
    return PoseFileTrack(track, points3d, pose_world)


def pose_to_track(pose, person: int = 0, source: str = "<pose>") -> PoseFileTrack:
    """A decoded ``pose_format.Pose`` with holistic components -> track (via :class:`PoseData`)."""
    try:
        data = pose_data(pose, source, person)
    except CorpusError as exc:
        raise PoseFileError(f".pose file {exc}") from exc
    return posedata_to_track(data, source)


def load_pose_track(path: str | Path, person: int = 0) -> PoseFileTrack:
    """Read a holistic ``.pose`` file -> :class:`PoseFileTrack` (fps and image size from its header)."""
    path = Path(path)
    if not path.is_file():
        raise PoseFileError(f".pose file {path} does not exist; check the corpus' pose root")
    try:
        data = read_pose(path, person)
    except CorpusError as exc:
        raise PoseFileError(f".pose file {exc}; quarantine the clip") from exc
    return posedata_to_track(data, str(path))
