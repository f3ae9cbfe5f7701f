"""The real 2D tracker: MediaPipe Holistic (legacy ``solutions`` API, 0.10.14) over a clip's frames -> Track.

Offline by construction: the wheel ships the holistic graph with the pose landmark model of
``model_complexity=1`` only (``pose_landmark_full.tflite``); complexities 0 and 2 download their model on
first use and fail without internet, so other values are refused with a clear message. Install with
``bash .ci/install-tracking`` (mediapipe without jax and without its second, non-headless OpenCV build).

Output per frame, in the ``mediapipe_holistic`` layout of :mod:`m3t.trackers.track` (33 pose, 21 left hand,
21 right hand, 468 face): MediaPipe's normalised x, y times the frame width, height -> pixels. Confidence:
the pose landmark's visibility (times its presence where the model sets one; 0.10.14 does not); 1 for the
points of a detected hand or face, whose models give no per-point score. A hand or face not found in a
frame -> NaN keypoints with confidence 0. ``refine_face_landmarks`` adds 10 iris points that the layout
does not hold: they are dropped. The pose world landmarks (metres, origin between the hips) are returned
beside the track (:class:`HolisticOutput`), as the track format has no field for them.

Axis legend: T frames, K = 543 landmarks.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.trackers.config import MediaPipeConfig
from m3t.trackers.media import open_media
from m3t.trackers.track import MEDIAPIPE_HOLISTIC_PARTS, Track, landmark_slices

INSTALL_HINT = "run `bash .ci/install-tracking` (mediapipe 0.10.14 without jax and without a second OpenCV build)"
NUM_LANDMARKS = sum(MEDIAPIPE_HOLISTIC_PARTS.values())
LANDMARK_SET = "mediapipe_holistic"
TRACKER_NAME = "mediapipe_holistic"


@dataclass(frozen=True)
class TrackingTiming:
    """Per-frame wall-clock seconds of decoding and of MediaPipe inference (plus conversion), (T,) each."""

    decode_s: np.ndarray
    inference_s: np.ndarray

    def summary(self) -> dict[str, float]:
        decode, inference = float(self.decode_s.sum()), float(self.inference_s.sum())
        total = decode + inference
        frames = len(self.decode_s)
        return {"frames": float(frames), "decode_s": decode, "inference_s": inference,
                "decode_share": decode / total if total else float("nan"),
                "inference_share": inference / total if total else float("nan"),
                "frames_per_s": frames / total if total else float("nan")}


@dataclass(frozen=True)
class HolisticOutput:
    track: Track
    pose_world: np.ndarray  # (T, 33, 3) float32, metres, MediaPipe's hip-centred frame; NaN where no pose
    timing: TrackingTiming
    frames_reported: int | None  # what the container announced (compare with track.num_frames for truncation)


def import_mediapipe():
    """Import mediapipe, or explain how to install it; refuses a protobuf it cannot run with."""
    try:
        import google.protobuf
        import mediapipe
    except ImportError as exc:
        raise ImportError(f"MediaPipe tracking needs the `mediapipe` package: {INSTALL_HINT}") from exc
    if int(google.protobuf.__version__.split(".")[0]) >= 5:
        raise ImportError(f"mediapipe {mediapipe.__version__} fails at run time with protobuf "
                          f"{google.protobuf.__version__} (needs 4.25.x): {INSTALL_HINT}")
    return mediapipe


def _holistic(mp, cfg: MediaPipeConfig, static_image_mode: bool):
    model = {0: "pose_landmark_lite.tflite", 1: "pose_landmark_full.tflite", 2: "pose_landmark_heavy.tflite"}
    if cfg.model_complexity not in model:
        raise ValueError(f"MediaPipeConfig.model_complexity={cfg.model_complexity}; allowed: 0, 1, 2 (offline: 1)")
    shipped = Path(mp.__file__).parent / "modules" / "pose_landmark" / model[cfg.model_complexity]
    if not shipped.is_file():
        raise ValueError(f"MediaPipeConfig.model_complexity={cfg.model_complexity} needs {shipped.name}, which "
                         "MediaPipe downloads on first use (no internet here); use model_complexity=1")
    return mp.solutions.holistic.Holistic(
        static_image_mode=static_image_mode, model_complexity=cfg.model_complexity,
        smooth_landmarks=cfg.smooth_landmarks, refine_face_landmarks=cfg.refine_face_landmarks,
        min_detection_confidence=cfg.min_detection_confidence, min_tracking_confidence=cfg.min_tracking_confidence)


def _fill(landmarks, part: slice, keypoints: np.ndarray, confidence: np.ndarray, width: int, height: int,
          scored: bool) -> None:
    if landmarks is None:
        return
    points = landmarks.landmark[: part.stop - part.start]
    xy = np.array([(p.x, p.y) for p in points], dtype=np.float32) * np.array([width, height], dtype=np.float32)
    keypoints[part] = xy
    if scored:
        conf = np.array([p.visibility * (p.presence if p.HasField("presence") else 1.0) for p in points])
        confidence[part] = np.clip(conf, 0.0, 1.0)
    else:
        confidence[part] = 1.0


@dataclass(frozen=True)
class FrameLandmarks:
    keypoints: np.ndarray  # (K, 2) float32 pixels, NaN where missing
    confidence: np.ndarray  # (K,) float32, 0 where missing
    pose_world: np.ndarray  # (33, 3) float32 metres, NaN without a pose


def results_to_arrays(results, width: int, height: int) -> FrameLandmarks:
    """One frame's Holistic results (a ``process`` output) -> arrays in the track's layout."""
    keypoints = np.full((NUM_LANDMARKS, 2), np.nan, dtype=np.float32)
    confidence = np.zeros(NUM_LANDMARKS, dtype=np.float32)
    parts = landmark_slices(LANDMARK_SET)
    _fill(results.pose_landmarks, parts["pose"], keypoints, confidence, width, height, scored=True)
    _fill(results.left_hand_landmarks, parts["left_hand"], keypoints, confidence, width, height, scored=False)
    _fill(results.right_hand_landmarks, parts["right_hand"], keypoints, confidence, width, height, scored=False)
    _fill(results.face_landmarks, parts["face"], keypoints, confidence, width, height, scored=False)
    world = np.full((MEDIAPIPE_HOLISTIC_PARTS["pose"], 3), np.nan, dtype=np.float32)
    if results.pose_world_landmarks is not None:
        world[:] = [(p.x, p.y, p.z) for p in results.pose_world_landmarks.landmark]
    return FrameLandmarks(keypoints, confidence, world)


def _process(holistic, rgb: np.ndarray):
    view = rgb.view()
    view.flags.writeable = False  # lets MediaPipe wrap the buffer, not copy it; the caller's array stays writeable
    with warnings.catch_warnings():
        # 0.10.14 calls protobuf's deprecated SymbolDatabase.GetPrototype on every result.
        warnings.filterwarnings("ignore", message=r"SymbolDatabase\.GetPrototype", category=UserWarning)
        return holistic.process(view)


def _check_rgb(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {rgb.shape} {rgb.dtype}")
    return np.ascontiguousarray(rgb)


def track_image(rgb: np.ndarray, cfg: MediaPipeConfig = MediaPipeConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Holistic on one (H, W, 3) uint8 RGB image (static-image mode) -> keypoints (K, 2) px, confidence (K,)."""
    mp = import_mediapipe()
    rgb = _check_rgb(rgb)
    with _holistic(mp, cfg, static_image_mode=True) as holistic:
        frame = results_to_arrays(_process(holistic, rgb), rgb.shape[1], rgb.shape[0])
    return frame.keypoints, frame.confidence


def run_holistic(path: str | Path, cfg: MediaPipeConfig = MediaPipeConfig(), fps: float | None = None,
                 progress: bool = False) -> HolisticOutput:
    """Track a video file or frame folder (see :func:`m3t.trackers.media.open_media`); one Holistic graph per
    clip, so the landmarks of one frame seed the search in the next.

    Raises :class:`m3t.trackers.media.MediaError` for undecodable media (the caller quarantines the clip).
    """
    mp = import_mediapipe()
    stream = open_media(path, fps)
    info = stream.info
    frames = stream.frames
    if progress:
        from tqdm import tqdm

        frames = iter(tqdm(frames, total=info.num_frames, desc=f"holistic {info.path.name}", unit="frame"))
    keypoints, confidence, world, decode_s, inference_s = [], [], [], [], []
    try:
        with _holistic(mp, cfg, static_image_mode=cfg.static_image_mode) as holistic:
            while True:
                start = time.perf_counter()
                rgb = next(frames, None)
                decoded = time.perf_counter()
                if rgb is None:
                    break
                frame = results_to_arrays(_process(holistic, rgb), info.width, info.height)
                keypoints.append(frame.keypoints)
                confidence.append(frame.confidence)
                world.append(frame.pose_world)
                decode_s.append(decoded - start)
                inference_s.append(time.perf_counter() - decoded)
    finally:
        stream.frames.close()  # releases the video decoder now, also when a frame fails
    track = Track(np.stack(keypoints), np.stack(confidence), LANDMARK_SET, (info.width, info.height), info.fps,
                  np.full(4, np.nan, dtype=np.float32), TRACKER_NAME)
    return HolisticOutput(track, np.stack(world), TrackingTiming(np.array(decode_s), np.array(inference_s)),
                          info.num_frames)


def track_media(path: str | Path, cfg: MediaPipeConfig = MediaPipeConfig(), fps: float | None = None,
                progress: bool = False) -> Track:
    """Track a video file or frame folder -> :class:`Track` (intrinsics NaN: the camera is unknown)."""
    return run_holistic(path, cfg, fps=fps, progress=progress).track
