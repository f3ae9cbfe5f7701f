"""PA errors: the per-frame similarity-Procrustes error of matching frames, and the per-frame-pair PA distance.

The transforms come from the one solver, :mod:`m3t.body.similarity` (``"quaternion"`` or ``"svd"``).
``procrustes_error_mm`` is the PA error of matching frames (PA-MPJPE of fitting, PA-VPE of the tokenizers), in
float64 whatever the input dtype.

``pa_distance_matrix`` is SOKE's ``dist_pa`` for every (prediction frame, ground-truth frame) pair, the cost
matrix of DTW-PA-JPE: the cross-covariances of all pairs come from one matrix product, the transforms from
the solver, the aligned residuals from batched matrix products, in row chunks that bound memory.
``pa_distance_matrices`` does B sequence pairs in the same ops (a GPU wants few, large launches). The CPU
default of DTW-PA-JPE is the fused kernel of :mod:`m3t.metrics.kernels`, checked against these.

Axis legend: B sequence pairs, K points, T1 prediction frames, T2 ground-truth frames.
"""
from __future__ import annotations

import torch

from m3t.body.similarity import rotation_component_first, similarity_align

# Frame pairs per chunk: ~64 KB per elementwise temporary stays in cache and below malloc's mmap threshold
# (fresh mmap'd temporaries page-fault on every op and were measured 2x slower at 62,500 pairs).
CHUNK_PAIRS = 8192
RESIDUAL_ELEMENTS = 1 << 18  # (rows x T2 x 3 x K) residual entries at once: about 2 MB, cache-resident


def procrustes_error_mm(pred: torch.Tensor, truth: torch.Tensor, method: str = "quaternion") -> float:
    """Mean point distance in mm after aligning every frame of pred (T, K, 3) onto truth (T, K, 3), metres.

    The usual PA-MPJPE / PA-VPE: one similarity transform per frame. Solved in float64 whatever the input
    dtype, so float32 joints lose nothing to the 3x3 solve.
    """
    pred, truth = pred.double(), truth.double()
    return float(torch.linalg.norm(similarity_align(pred, truth, method) - truth, dim=-1).mean() * 1000.0)


def check_sequence_pair(pred: torch.Tensor, gt: torch.Tensor) -> tuple[int, int, int]:
    """(T1, K, T2) of a (T1, K, 3) prediction and a (T2, K, 3) reference; ValueError on other shapes."""
    if pred.ndim != 3 or gt.ndim != 3 or pred.shape[1:] != gt.shape[1:] or pred.shape[-1] != 3:
        raise ValueError(f"pred {tuple(pred.shape)} and gt {tuple(gt.shape)} must be (T1, K, 3) and (T2, K, 3)")
    return pred.shape[0], pred.shape[1], gt.shape[0]


def pa_distance_matrix(pred: torch.Tensor, gt: torch.Tensor, method: str = "quaternion",
                       chunk_pairs: int = CHUNK_PAIRS, measure: slice | None = None) -> torch.Tensor:
    """SOKE's ``dist_pa`` for every frame pair: mean point distance after aligning pred[i] onto gt[j].

    Parameters
    ----------
    pred : (T1, K, 3) predicted points; gt : (T2, K, 3) ground-truth points (same units, K >= 1).
    method : Procrustes solver, see ``rotation_from_covariance``.
    chunk_pairs : rows of pred are processed in chunks of about this many frame pairs (bounds memory).
    measure : the points whose distances are averaged after the alignment, which is always fitted on all K
        (SOKE's dormant PA: ``rigid_align`` on every joint, then the subset); None: all K.

    Returns
    -------
    (T1, T2) tensor in pred's dtype and units.
    """
    check_sequence_pair(pred, gt)
    return pa_distance_matrices(pred[None], gt[None], method, chunk_pairs, measure)[0]


def pa_distance_matrices(pred: torch.Tensor, gt: torch.Tensor, method: str = "quaternion",
                         chunk_pairs: int = CHUNK_PAIRS, measure: slice | None = None,
                         residual_elements: int = RESIDUAL_ELEMENTS) -> torch.Tensor:
    """``pa_distance_matrix`` of B sequence pairs at once, for devices where one launch per pair is too many.

    Parameters
    ----------
    pred : (B, T1, K, 3); gt : (B, T2, K, 3). Pairs of other lengths may be zero-padded up to T1 and T2: a
        zero frame has scale 0 and identity rotation, so its costs are finite (and meaningless; crop them).
    chunk_pairs : (B x rows x T2) frame pairs solved at once; the CPU default keeps temporaries in cache, a GPU
        wants millions.
    residual_elements : (B x rows x T2 x 3 x K) aligned residual entries held at once.

    Returns
    -------
    (B, T1, T2) tensor in pred's dtype and units.
    """
    if pred.ndim != 4 or gt.ndim != 4 or pred.shape[0] != gt.shape[0] or pred.shape[2:] != gt.shape[2:] \
            or pred.shape[-1] != 3:
        raise ValueError(f"pred {tuple(pred.shape)} and gt {tuple(gt.shape)} must be (B, T1, K, 3) and (B, T2, K, 3)")
    b, t1, k, _ = pred.shape
    t2 = gt.shape[1]
    xs = (pred - pred.mean(2, keepdim=True)).transpose(2, 3)  # (B, T1, 3, K)
    yt = (gt - gt.mean(2, keepdim=True)).transpose(2, 3).contiguous()  # (B, T2, 3, K)
    var_s, var_t = xs.square().sum((2, 3)), yt.square().sum((2, 3))  # (B, T1), (B, T2)
    # All cross-covariances in one product: (B, 3*T1, K) @ (B, K, 3*T2) -> S[a, b, n, i, j] = sum_k x_iak y_jbk.
    cov = xs.permute(0, 2, 1, 3).reshape(b, 3 * t1, k) @ yt.permute(0, 3, 2, 1).reshape(b, k, 3 * t2)
    cov = cov.reshape(b, 3, t1, 3, t2).permute(1, 3, 0, 2, 4).contiguous()  # (3, 3, B, T1, T2)
    if measure is not None:  # residuals of the measured points only, in the full set's centred frame
        xs, yt = xs[..., measure], yt[..., measure].contiguous()  # (B, T1, 3, K'), (B, T2, 3, K')
        k = yt.shape[-1]
        if k == 0:
            raise ValueError(f"measure {measure} selects none of the {pred.shape[2]} points")
    rows = max(1, chunk_pairs // (b * t2))
    sub_rows = max(1, residual_elements // (b * t2 * 3 * k))
    neg_target = (-yt).reshape(b, 1, t2 * 3, k)
    out = torch.empty(b, t1, t2, dtype=pred.dtype, device=pred.device)
    for start in range(0, t1, rows):
        sl = slice(start, min(start + rows, t1))
        rotation, trace = rotation_component_first(cov[:, :, :, sl], var_s[:, sl, None], var_t[:, None, :], method)
        vs = var_s[:, sl, None]
        scale = torch.where(vs > 0, trace / torch.where(vs > 0, vs, torch.ones_like(vs)), torch.zeros_like(trace))
        s_rot = (rotation * scale).permute(2, 3, 4, 0, 1).reshape(b, -1, t2 * 3, 3)  # (B, c, T2*3, 3)
        for sub in range(0, s_rot.shape[1], sub_rows):
            part = s_rot[:, sub:sub + sub_rows]
            c = part.shape[1]
            # s R x - y for every (i, j, point); centroids already coincide. baddbmm fuses the subtraction.
            residual = torch.baddbmm(neg_target.expand(b, c, -1, -1).reshape(b * c, t2 * 3, k),
                                     part.reshape(b * c, t2 * 3, 3),
                                     xs[:, start + sub:start + sub + c].reshape(b * c, 3, k))
            residual = residual.reshape(b, c, t2, 3, k).square_()
            out[:, start + sub:start + sub + c] = residual.sum(3).sqrt_().mean(-1)
    return out
