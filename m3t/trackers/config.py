"""Configs of the trackers (params.yaml ``tracker``: the simulated one; ``mediapipe``: real 2D tracking)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SimulatedTrackerConfig:
    seed: int = 0
    noise_px_pose: float = 2.0
    noise_px_hand: float = 1.5
    noise_px_face: float = 0.8
    hand_dropout_prob: float = 0.3  # chance per clip and hand of one missing span
    hand_dropout_max_frac: float = 0.3  # longest missing span, as a fraction of the clip
    occlusion_prob: float = 0.02  # chance per frame that a random 10% of points are occluded
    intrinsics_known: bool = True  # write the camera intrinsics into the track (a calibrated camera)
    init_noise_deg_body: float = 6.0  # per-frame rotation noise of the 3D initialisation, body joints
    init_noise_deg_hand: float = 10.0  # ... finger joints (hand estimators are less precise)
    init_noise_scalar: float = 0.08  # std of the noise on scalar streams (face)


@dataclass(frozen=True)
class MediaPipeConfig:
    model_complexity: int = 1  # the only pose model shipped in the wheel: 0 and 2 need a download (offline: fail)
    min_detection_confidence: float = 0.5
    min_tracking_confidence: float = 0.5
    refine_face_landmarks: bool = False  # iris points; the track keeps the 468 mesh points either way
    static_image_mode: bool = False  # False: track across frames (faster, steadier); True: detect every frame
    smooth_landmarks: bool = True  # MediaPipe's own temporal filter of the pose landmarks (video mode only)
