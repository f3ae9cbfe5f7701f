"""The track format: what every tracker writes and fitting reads (one ``.npz`` per clip).

Fields
------
keypoints : (T, K, 2) float32, pixels (origin top-left); NaN where the tracker found nothing
confidence : (T, K) float32 in [0, 1]; 0 where missing
landmark_set : str, e.g. ``"mediapipe_holistic"`` (K = 33 pose + 21 left hand + 21 right hand + 468 face)
image_size : (2,) int, (width, height)
fps : float, finite and > 0 (files with any other value are refused on save and on load)
intrinsics : (4,) float32 (fx, fy, cx, cy) when the camera is calibrated, else NaN
tracker : str, the tracker that wrote it
init__<modality> : (T, D_m) float32, optional per-frame body-model parameters from 3D trackers (the paper's
    NLF / WiLoR / Pixel3DMM estimates; simulated: ground truth plus tracker-like noise); the fitting
    initialisation that ``L_reg`` pulls toward. Absent -> fitting starts from the rest pose.
extra__<name> : (T, ...) float32, optional per-frame side data kept with the track but not fitted to; may hold
    NaN. ``pose_world``: (T, 33, 3) MediaPipe pose world landmarks (metres, hip-centred; a ``.pose`` file's
    ``POSE_WORLD_LANDMARKS`` in its own units); ``depth``: (T, K) a ``.pose`` file's z per landmark.
"""
from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.atomic import atomic_path
from m3t.declared import open_npz

MEDIAPIPE_HOLISTIC_PARTS = {"pose": 33, "left_hand": 21, "right_hand": 21, "face": 468}


def landmark_slices(landmark_set: str) -> dict[str, slice]:
    """Part name -> slice into the K axis."""
    if landmark_set != "mediapipe_holistic":
        raise ValueError(f"unknown landmark set {landmark_set!r}; known: mediapipe_holistic")
    out, start = {}, 0
    for part, n in MEDIAPIPE_HOLISTIC_PARTS.items():
        out[part] = slice(start, start + n)
        start += n
    return out


class TrackError(ValueError):
    """A track file that cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class Track:
    keypoints: np.ndarray
    confidence: np.ndarray
    landmark_set: str
    image_size: tuple[int, int]
    fps: float
    intrinsics: np.ndarray
    tracker: str
    init: dict[str, np.ndarray] | None = None
    extras: dict[str, np.ndarray] | None = None

    @property
    def num_frames(self) -> int:
        return self.keypoints.shape[0]


def _fps_problem(fps: object) -> str | None:
    """Why ``fps`` is not a usable frame rate (a finite number > 0), or ``None``."""
    value = np.asarray(fps)
    if value.size != 1 or value.dtype.kind not in "iuf":
        return f"fps {value.tolist()!r} is not a single number"
    rate = float(value.reshape(()))
    return None if np.isfinite(rate) and rate > 0 else f"fps {rate} is not a positive finite number"


def save_track(track: Track, path: str | Path) -> Path:
    """Write atomically (temp file + rename) so a killed run never leaves a half-written track."""
    path = Path(path)
    problem = _fps_problem(track.fps)
    if problem is not None:  # a track is timed by its fps: refuse to write one nothing downstream can use
        raise TrackError(f"track for {path}: {problem}; the tracker must report the clip's frame rate")
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(
            tmp,
            keypoints=track.keypoints.astype(np.float32),
            confidence=track.confidence.astype(np.float32),
            landmark_set=np.array(track.landmark_set),
            image_size=np.asarray(track.image_size, dtype=np.int64),
            fps=np.array(float(np.asarray(track.fps).reshape(())), dtype=np.float64),  # a 1-element array: its value
            intrinsics=np.asarray(track.intrinsics, dtype=np.float32),
            tracker=np.array(track.tracker),
            **{f"init__{k}": np.asarray(v, dtype=np.float32) for k, v in (track.init or {}).items()},
            **{f"extra__{k}": np.asarray(v, dtype=np.float32) for k, v in (track.extras or {}).items()},
        )
    return path


def load_track(path: str | Path) -> Track:
    """Read and validate a track file; NaN keypoints get zero confidence."""
    path = Path(path)
    if not path.exists():
        raise TrackError(f"track file {path} does not exist; run the tracking step for this clip first")
    try:
        with open_npz(path) as data:
            fields = {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise TrackError(f"track file {path} is unreadable ({exc}); delete it and re-run tracking") from exc
    required = ("keypoints", "confidence", "landmark_set", "image_size", "fps")
    missing = [k for k in required if k not in fields]
    if missing:
        raise TrackError(f"track file {path} lacks fields {missing}; expected {list(required)}")
    kp, conf = fields["keypoints"].astype(np.float32), fields["confidence"].astype(np.float32)
    if kp.ndim != 3 or kp.shape[-1] != 2 or conf.shape != kp.shape[:2]:
        raise TrackError(f"track file {path}: keypoints {kp.shape} / confidence {conf.shape} are not (T, K, 2) / (T, K)")
    if kp.shape[0] == 0:
        raise TrackError(f"track file {path} has no frames")
    problem = _fps_problem(fields["fps"])
    if problem is not None:
        raise TrackError(f"track file {path}: {problem}; delete it and re-run tracking (for a frame folder, set "
                         "the corpus' fps option)")
    landmark_set = str(fields["landmark_set"])
    expected = sum(MEDIAPIPE_HOLISTIC_PARTS.values()) if landmark_set == "mediapipe_holistic" else kp.shape[1]
    if kp.shape[1] != expected:
        raise TrackError(f"track file {path}: {kp.shape[1]} landmarks, {landmark_set} has {expected}")
    bad = ~np.isfinite(kp).all(-1)
    conf = np.where(bad, 0.0, np.clip(np.nan_to_num(conf, nan=0.0), 0.0, 1.0)).astype(np.float32)
    kp = np.where(bad[..., None], np.nan, kp).astype(np.float32)
    intr = fields.get("intrinsics", np.full(4, np.nan, dtype=np.float32))
    init = {k.removeprefix("init__"): v.astype(np.float32) for k, v in fields.items() if k.startswith("init__")}
    for name, value in init.items():
        if value.ndim != 2 or value.shape[0] != kp.shape[0] or not np.isfinite(value).all():
            raise TrackError(f"track file {path}: initialisation {name!r} has shape {value.shape} or non-finite "
                             f"values; expected ({kp.shape[0]}, D) finite")
    extras = {k.removeprefix("extra__"): v.astype(np.float32) for k, v in fields.items() if k.startswith("extra__")}
    for name, value in extras.items():
        if value.ndim < 1 or value.shape[0] != kp.shape[0]:
            raise TrackError(f"track file {path}: extra {name!r} has shape {value.shape}; expected "
                             f"({kp.shape[0]}, ...), one entry per frame; delete the file and re-run tracking")
    fps = float(np.asarray(fields["fps"]).reshape(()))  # one value (_fps_problem), stored 0-d or as [value]
    return Track(kp, conf, landmark_set, tuple(int(v) for v in fields["image_size"]), fps,
                 np.asarray(intr, dtype=np.float32), str(fields.get("tracker", "unknown")), init or None,
                 extras or None)
