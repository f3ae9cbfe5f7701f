"""Vertex errors of one parameter stream: which vertices a stream moves, and PA-VPE over them.

A stream's vertex region is found from the body model itself, so it holds for any model behind the
protocol: the vertices that move by more than ``threshold_m`` when that stream alone is perturbed away
from the rest pose (random joint rotations for rotation streams, random values within bounds for scalar
streams). PA-VPE is the mean per-vertex distance over the region after a per-frame similarity Procrustes
alignment, in millimetres (the tokenizer ablation's reconstruction measure, M3T Tab. 3).

Axis legend: T frames, V vertices, D stream dim, P identity dim.
"""
from __future__ import annotations

import numpy as np
import roma
import torch

from m3t.body.protocol import BodyModel, Correspondence
from m3t.body.rotations import matrix_to_6d
from m3t.metrics.procrustes import procrustes_error_mm


@torch.no_grad()
def stream_vertex_region(body: BodyModel, modality: str, samples: int = 8, angle_deg: float = 30.0,
                         threshold_m: float = 1e-3, seed: int = 0, max_vertices: int = 2000) -> np.ndarray:
    """(R,) int64 indices of the vertices that ``modality`` moves; a region larger than ``max_vertices`` is
    thinned to that many evenly spaced indices (an unbiased estimate of the mean error at a fraction of the cost)."""
    spec = body.layout[modality]
    gen = torch.Generator().manual_seed(seed)
    params = body.rest_params(samples)
    if spec.kind == "rotation6d":
        axis = torch.randn(samples, len(spec.labels), 3, generator=gen)
        axis = axis / axis.norm(dim=-1, keepdim=True)
        angle = torch.rand(samples, len(spec.labels), 1, generator=gen) * np.deg2rad(angle_deg)
        params[modality] = matrix_to_6d(roma.rotvec_to_rotmat(axis * angle)).reshape(samples, -1)
    else:
        low, high = spec.bounds if spec.bounds is not None else (-1.0, 1.0)
        params[modality] = low + (high - low) * torch.rand(samples, spec.dim, generator=gen)
    identity = body.default_identity()
    rest = body.forward(body.rest_params(1), identity).vertices[0]  # (V, 3)
    moved = body.forward(params, identity).vertices  # (S, V, 3)
    displacement = (moved - rest).norm(dim=-1).amax(dim=0)  # (V,)
    region = torch.nonzero(displacement > threshold_m).flatten().numpy()
    if region.size < 3:
        raise ValueError(f"modality {modality!r} moves fewer than 3 vertices of {body.name}; cannot measure PA-VPE")
    if region.size > max_vertices:
        region = region[np.linspace(0, region.size - 1, max_vertices).round().astype(np.int64)]
    return region


def region_keypoints(body: BodyModel, region: np.ndarray) -> object:
    """The body model's sparse-forward set for the vertices of ``region`` (only they are skinned)."""
    region = np.asarray(region, dtype=np.int64)
    corr = Correspondence(tuple(f"v{i}" for i in region), np.zeros(len(region), dtype=np.int64), region)
    return body.keypoint_set(corr)


@torch.no_grad()
def region_vertices(body: BodyModel, params: dict[str, torch.Tensor], identity: torch.Tensor, keypoints: object,
                    chunk: int = 512) -> torch.Tensor:
    """(T, R, 3) positions of a region's vertices (sparse forward, in chunks of frames); identity (P,) or (T, P)."""
    frames = next(iter(params.values())).shape[0]
    if identity.ndim == 1:
        identity = identity.expand(frames, -1)
    return torch.cat([body.forward_keypoints({k: v[s: s + chunk] for k, v in params.items()}, identity[s: s + chunk],
                                             keypoints) for s in range(0, frames, chunk)])


def vertex_errors_mm(pred: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    """VPE (no alignment) and PA-VPE (per-frame similarity Procrustes) in mm of (T, R, 3) vertex sets."""
    return {"vpe_mm": float((pred - truth).norm(dim=-1).mean() * 1000.0), "pa_vpe_mm": procrustes_error_mm(pred, truth)}
