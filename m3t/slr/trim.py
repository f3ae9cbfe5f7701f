"""Active-window trimming of isolated-sign clips (M3T Sec. 3.4, following SignRep, Wong et al. 2025).

Isolated-sign recordings start and end with the hands resting; those frames say nothing about the sign.
Per frame the two wrists are placed by the body model (sparse forward of its MediaPipe-Holistic
correspondence, so every body model is measured the same way) and compared with where they rest:

- *height*: how far a wrist is raised above its rest height along the body's up axis;
- *displacement*: how far a wrist is from its rest position.

A frame is active when either wrist is raised by more than ``height_threshold`` or displaced by more than
``displacement_threshold``. Both are in shoulder widths and the up axis is the trunk (mid-hips -> mid-shoulders),
all taken from the body model's rest pose under the clip's identity: scale- and orientation-free. Only the
first and last inactive frames go (everything between the first and the last active frame stays, plus
``margin``); a clip with no active frame is kept whole.

The kept window never has fewer than ``min_frames`` frames: a shorter one is widened around its centre within
the clip. A clip with fewer frames than that is refused with :class:`ClipTooShortError` naming it (the frozen
encoders need whole token windows; the probe needs more than a token or two). The kept frames are edge-padded
to a multiple of the tokenizers' downsampling later, as the tokenize stage does.

Axis legend: T frames, H = 2 wrists (left, right), K keypoints.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from m3t.body.metric_sets import subset_correspondence
from m3t.body.protocol import BodyModel, Correspondence, as_tensors
from m3t.slr.config import TrimConfig

LANDMARKS = "mediapipe_holistic"
WRISTS = ("pose:left_wrist", "pose:right_wrist")
TRUNK = ("pose:left_shoulder", "pose:right_shoulder", "pose:left_hip", "pose:right_hip")


class ClipTooShortError(ValueError):
    """A clip has fewer frames than the probe's minimum window (``slr.trim.min_frames``)."""


@dataclass(frozen=True)
class HandActivity:
    """height, displacement: (T, H) in shoulder widths; active: (T,) bool."""

    height: np.ndarray
    displacement: np.ndarray
    active: np.ndarray


@dataclass(frozen=True)
class ActiveWindow:
    """Frames ``[start, end)`` of a ``frames``-frame clip are kept; ``active_frames`` of them were active."""

    start: int
    end: int
    frames: int
    active_frames: int

    @property
    def kept(self) -> int:
        return self.end - self.start

    @property
    def trimmed_share(self) -> float:
        return 1.0 - self.kept / self.frames if self.frames else 0.0

    def to_dict(self) -> dict[str, int]:
        return {"start": self.start, "end": self.end, "frames": self.frames, "active_frames": self.active_frames}


def _trim_points(body: BodyModel) -> Correspondence:
    """The wrists and trunk points of ``body``'s MediaPipe-Holistic correspondence; a clear error without them."""
    full = body.correspondence(LANDMARKS)
    lost = [n for n in WRISTS + TRUNK if n not in full.names]
    corr = None if lost else subset_correspondence(full, WRISTS + TRUNK)
    lost += [] if corr is None else [n for n, ok in zip(corr.names, corr.valid) if not ok]
    if lost:
        raise ValueError(f"body model {body.name!r}: its {LANDMARKS} correspondence lacks {lost}, which "
                         "active-window trimming needs; set slr.trim.enabled: false to keep whole clips")
    return corr


class HandActivityProbe:
    """Per-frame wrist height and displacement of a clip relative to rest (one per body model)."""

    def __init__(self, body: BodyModel):
        self.body = body
        self.points = body.keypoint_set(_trim_points(body))

    @torch.no_grad()
    def activity(self, params: dict[str, np.ndarray], identity: np.ndarray, cfg: TrimConfig) -> HandActivity:
        """params: modality -> (T, D); identity: (P,)."""
        ident = torch.as_tensor(np.asarray(identity), dtype=torch.float32)
        rest = self.body.forward_keypoints(self.body.rest_params(1), ident, self.points)[0]  # (K, 3)
        l_sh, r_sh, l_hip, r_hip = rest[2], rest[3], rest[4], rest[5]
        shoulder_width = torch.linalg.norm(l_sh - r_sh).clamp_min(1e-6)
        up = (l_sh + r_sh - l_hip - r_hip) / 2
        up = up / torch.linalg.norm(up).clamp_min(1e-9)
        wrists = self.body.forward_keypoints(as_tensors(params), ident, self.points)[:, :2]  # (T, H, 3)
        if cfg.reference == "body_rest":
            rest_wrists = rest[:2]  # (H, 3)
        elif cfg.reference == "clip_rest":  # each wrist's lowest frame: where this signer's hand rests
            lowest = (wrists @ up).argmin(dim=0)  # (H,)
            rest_wrists = wrists[lowest, torch.arange(2, device=lowest.device)]
        else:
            raise ValueError(f"slr.trim.reference {cfg.reference!r} unknown; allowed: clip_rest, body_rest")
        offset = wrists - rest_wrists  # (T, H, 3)
        height = (offset @ up / shoulder_width).cpu().numpy()
        displacement = (torch.linalg.norm(offset, dim=-1) / shoulder_width).cpu().numpy()
        active = ((height > cfg.height_threshold) | (displacement > cfg.displacement_threshold)).any(axis=1)
        return HandActivity(height, displacement, active)


def active_window(active: np.ndarray, cfg: TrimConfig, clip_id: str = "?") -> ActiveWindow:
    """The kept frames of a clip from its per-frame activity (T,) bool (all of them when trimming is off)."""
    frames = len(active)
    if frames < cfg.min_frames:
        raise ClipTooShortError(f"clip {clip_id!r} has {frames} frames, fewer than slr.trim.min_frames="
                                f"{cfg.min_frames} that the probe needs; lower slr.trim.min_frames (not below "
                                "the tokenizers' downsampling) or leave the clip out (slr_train.bad_clips: skip)")
    hits = np.flatnonzero(active)
    if not cfg.enabled or hits.size == 0:
        return ActiveWindow(0, frames, frames, int(hits.size))
    start, end = max(0, int(hits[0]) - cfg.margin), min(frames, int(hits[-1]) + 1 + cfg.margin)
    if end - start < cfg.min_frames:  # widen around the centre, within the clip
        start = max(0, min(frames - cfg.min_frames, (start + end - cfg.min_frames) // 2))
        end = start + cfg.min_frames
    return ActiveWindow(start, end, frames, int(hits.size))


def trim_params(params: dict[str, np.ndarray], window: ActiveWindow) -> dict[str, np.ndarray]:
    """The kept frames of every modality: (T, D) -> (end - start, D)."""
    return {k: np.asarray(v)[window.start: window.end] for k, v in params.items()}


class Trimmer:
    """Clip params -> (kept params, window) under one :class:`TrimConfig` and body model."""

    def __init__(self, body: BodyModel | None, cfg: TrimConfig):
        if cfg.enabled and body is None:
            raise ValueError("active-window trimming needs the body model; pass it or set slr.trim.enabled: false")
        self.cfg = cfg
        self.probe = HandActivityProbe(body) if cfg.enabled else None

    def __call__(self, params: dict[str, np.ndarray], identity: np.ndarray,
                 clip_id: str = "?") -> tuple[dict[str, np.ndarray], ActiveWindow]:
        frames = next((len(v) for v in params.values()), 0)
        if self.probe is None or frames < self.cfg.min_frames:  # too short: active_window names the clip
            active = np.zeros(frames, dtype=bool)
        else:
            active = self.probe.activity(params, identity, self.cfg).active
        window = active_window(active, self.cfg, clip_id)
        return trim_params(params, window), window
