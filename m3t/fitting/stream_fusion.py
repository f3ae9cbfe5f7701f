"""Per-modality, per-frame fusion of candidate 3D tracker streams into one body-model initialisation.

1. every candidate :class:`TrackerStream` (values in the body's modality layout, a confidence per frame)
   is tried in priority order (hands: WiLoR, then NLF's hands); the first one whose confidence reaches
   ``min_confidence`` gives the frame;
2. frames that no stream covers are filled: gaps of at most ``max_gap`` frames between two covered
   frames are interpolated (rotations joint by joint along the geodesic, scalars linearly), longer gaps
   and the clip ends hold the nearest covered value, and a modality no stream covers at all stays at the
   rest pose; :attr:`FusedInit.source` flags every frame (stream index, or ``INTERPOLATED`` / ``HELD`` / ``REST``).

The streams of the paper's trackers are made by :mod:`m3t.fitting.tracker_streams`.

Axis legend: T frames, D modality dim, n joints of a stream.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import roma
import torch

from m3t.body.protocol import ModalityLayout
from m3t.fitting.config import FusionConfig
from m3t.trackers.tracker_files import rotmat_to_6d

INTERPOLATED, HELD, REST = -1, -2, -3


@dataclass(frozen=True)
class TrackerStream:
    """One tracker's estimate of one modality: values (T, D) in the layout, confidence (T,), 0 = missing."""

    source: str
    values: np.ndarray
    confidence: np.ndarray


@dataclass(frozen=True)
class FusedInit:
    init: dict[str, np.ndarray]  # modality -> (T, D) float32, usable as Track.init
    source: dict[str, np.ndarray]  # modality -> (T,) int: stream index, INTERPOLATED, HELD or REST
    stream_names: dict[str, tuple[str, ...]]  # modality -> "<tracker>[:<part>]" per stream, priority order
    identity: np.ndarray | None  # (P,) or None when no tracker gave one
    identity_sources: tuple[str, ...] = ()  # trackers that gave the identity
    outside: dict[str, int] = field(default_factory=dict)  # tracker -> estimates at frames outside the clip


def _interpolate(a: np.ndarray, b: np.ndarray, w: float, rotation: bool) -> np.ndarray:
    if not rotation:
        return (1 - w) * a + w * b
    ra = roma.special_gramschmidt(torch.as_tensor(a, dtype=torch.float64).reshape(-1, 2, 3).transpose(-1, -2))
    rb = roma.special_gramschmidt(torch.as_tensor(b, dtype=torch.float64).reshape(-1, 2, 3).transpose(-1, -2))
    rw = roma.rotmat_slerp(ra, rb, torch.tensor([w], dtype=torch.float64))[0]  # (n, 3, 3)
    return rot_to_flat6d(rw.numpy())


def rot_to_flat6d(rot: np.ndarray) -> np.ndarray:
    """(..., n, 3, 3) -> (..., n * 6) in the project's 6D layout."""
    six = rotmat_to_6d(rot)
    return six.reshape(*six.shape[:-2], -1)


def fuse_modality(streams: list[TrackerStream], rest: np.ndarray, rotation: bool, cfg: FusionConfig) -> tuple[np.ndarray, np.ndarray]:
    """(T, D) values and (T,) source flags of one modality (see the module docstring)."""
    T = streams[0].values.shape[0] if streams else 0
    out = np.tile(rest, (T, 1)).astype(np.float64)
    source = np.full(T, REST, dtype=np.int64)
    for k in reversed(range(len(streams))):  # the highest priority written last
        s = streams[k]
        ok = (s.confidence >= cfg.min_confidence) & np.isfinite(s.values).all(1)
        out[ok] = s.values[ok]
        source[ok] = k
    covered = np.flatnonzero(source >= 0)
    if covered.size == 0:
        return out.astype(np.float32), source
    for t in np.flatnonzero(source < 0):
        after = covered[covered > t]
        before = covered[covered < t]
        if before.size and after.size and after[0] - before[-1] - 1 <= cfg.max_gap:
            a, b = before[-1], after[0]
            out[t] = _interpolate(out[a], out[b], (t - a) / (b - a), rotation)
            source[t] = INTERPOLATED
        else:
            near = before[-1] if (before.size and (not after.size or t - before[-1] <= after[0] - t)) else after[0]
            out[t] = out[near]
            source[t] = HELD
    return out.astype(np.float32), source


def fuse(layout: ModalityLayout, streams: dict[str, list[TrackerStream]], rest: dict[str, np.ndarray], num_frames: int,
         cfg: FusionConfig = FusionConfig(), identity: np.ndarray | None = None) -> FusedInit:
    """Fuse candidate streams per modality; ``rest``: modality -> (D,) rest parameters."""
    init, source, names = {}, {}, {}
    for m in layout.modalities:
        cands = streams.get(m.name, [])
        for s in cands:
            if s.values.shape != (num_frames, m.dim) or s.confidence.shape != (num_frames,):
                raise ValueError(f"stream {s.source!r} for {m.name!r} has shape {s.values.shape} / "
                                 f"{s.confidence.shape}; expected ({num_frames}, {m.dim}) / ({num_frames},)")
        if cands:
            init[m.name], source[m.name] = fuse_modality(cands, rest[m.name], m.kind == "rotation6d", cfg)
        else:
            init[m.name] = np.tile(rest[m.name], (num_frames, 1)).astype(np.float32)
            source[m.name] = np.full(num_frames, REST, dtype=np.int64)
        names[m.name] = tuple(s.source for s in cands)
    return FusedInit(init, source, names, identity)
