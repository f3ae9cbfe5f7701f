"""Simulated tracker for the synthetic corpus: ground-truth motion -> 2D MediaPipe-Holistic track.

The ground-truth parameters go through the body model's sparse keypoint forward (using the stored
landmark correspondence), are projected with the clip's camera and corrupted the way a real 2D tracker
is: per-part pixel noise that grows as confidence drops, per-point confidence, whole-hand dropouts over
spans of frames (MediaPipe loses hands often) and random occlusions. Landmarks without a correspondence
and points that leave the image get NaN with zero confidence. Like the paper's 3D trackers (NLF for the
body, WiLoR for hands, Pixel3DMM for the face) it also gives a per-frame parameter estimate: ground truth
with independent per-frame rotation noise on every joint and noise on the face, which fitting refines. The output is an ordinary
:class:`m3t.trackers.track.Track`, so fitting has one code path for simulated and real tracks.

Axis legend: T frames, K landmarks.
"""
from __future__ import annotations

import zlib

import numpy as np
import roma
import torch

from m3t.body.protocol import BodyModel, ModalityLayout, Params
from m3t.body.rotations import matrix_to_6d, sixd_to_matrix
from m3t.camera import Camera, camera_tensors, project
from m3t.trackers.config import SimulatedTrackerConfig
from m3t.trackers.track import Track, landmark_slices


def clip_rng(seed: int, clip_id: str) -> np.random.Generator:
    """Independent, order-free random stream per clip (so parallel runs give identical tracks)."""
    return np.random.default_rng([seed, zlib.crc32(clip_id.encode())])


def noisy_initialisation(params: Params, layout: ModalityLayout, cfg: SimulatedTrackerConfig,
                         rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Ground truth + per-frame, per-joint noise, as a 3D tracker's estimate: (T, D) per modality."""
    out = {}
    for m in layout.modalities:
        value = params[m.name]
        if m.kind == "rotation6d":
            deg = cfg.init_noise_deg_hand if "hand" in m.name else cfg.init_noise_deg_body
            rot = sixd_to_matrix(value.reshape(value.shape[0], -1, 6))  # (T, n, 3, 3)
            noise = torch.as_tensor(rng.normal(0.0, np.deg2rad(deg), size=(*rot.shape[:2], 3)), dtype=rot.dtype)
            out[m.name] = matrix_to_6d(roma.rotvec_to_rotmat(noise) @ rot).reshape(value.shape).numpy()
        else:
            noisy = value.numpy() + rng.normal(0.0, cfg.init_noise_scalar, size=value.shape)
            out[m.name] = np.clip(noisy, *m.bounds) if m.bounds is not None else noisy
        out[m.name] = out[m.name].astype(np.float32)
    return out


@torch.no_grad()
def simulate_track(
    clip_id: str,
    params: Params,
    identity: torch.Tensor,
    camera: Camera,
    fps: float,
    body: BodyModel,
    cfg: SimulatedTrackerConfig,
    landmark_set: str = "mediapipe_holistic",
) -> Track:
    correspondence = body.correspondence(landmark_set)
    points = body.forward_keypoints(params, identity, body.keypoint_set(correspondence))  # (T, K, 3)
    rotation, translation, intrinsics = camera_tensors(camera)
    uv = project(points, rotation, translation, intrinsics).numpy()  # (T, K, 2)
    T, K, _ = uv.shape
    rng = clip_rng(cfg.seed, clip_id)

    confidence = np.clip(0.97 - np.abs(rng.normal(0.0, 0.08, size=(T, K))), 0.3, 1.0)
    sigma = np.zeros(K)
    parts = landmark_slices(landmark_set)
    for part, noise in (("pose", cfg.noise_px_pose), ("left_hand", cfg.noise_px_hand),
                        ("right_hand", cfg.noise_px_hand), ("face", cfg.noise_px_face)):
        sigma[parts[part]] = noise
    # Less confident detections are noisier, as with real detectors' heatmap peaks.
    uv = uv + rng.normal(size=uv.shape) * (sigma[None, :, None] / confidence[..., None])

    missing = np.zeros((T, K), dtype=bool)
    missing[:, ~correspondence.valid] = True
    for hand in ("left_hand", "right_hand"):
        if rng.random() < cfg.hand_dropout_prob:
            length = max(1, int(rng.uniform(0.05, cfg.hand_dropout_max_frac) * T))
            start = int(rng.integers(0, max(1, T - length + 1)))
            missing[start:start + length, parts[hand]] = True
    occluded = rng.random(T) < cfg.occlusion_prob
    missing[occluded] |= rng.random((int(occluded.sum()), K)) < 0.1
    outside = (uv[..., 0] < 0) | (uv[..., 0] >= camera.width) | (uv[..., 1] < 0) | (uv[..., 1] >= camera.height)
    missing |= outside

    uv[missing] = np.nan
    confidence[missing] = 0.0
    intr = intrinsics.numpy() if cfg.intrinsics_known else np.full(4, np.nan, dtype=np.float32)
    init = noisy_initialisation(params, body.layout, cfg, rng)
    return Track(uv.astype(np.float32), confidence.astype(np.float32), landmark_set,
                 (camera.width, camera.height), float(fps), intr.astype(np.float32), "simulated", init)
