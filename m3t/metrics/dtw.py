"""Dynamic time warping as SOKE evaluates it (mGPT/metrics/dtw.py), batched, plus the DTW-JPE cost matrix.

The recursion is the classic one, ``D[i, j] = c(i, j) + min(D[i-1, j], D[i, j-1], D[i-1, j-1])`` with
``D[0, 0] = c(0, 0)``; the result is the raw accumulated cost ``D[T1-1, T2-1]`` (not divided by anything)
and the optimal warping path, backtracked from the end. Ties prefer the diagonal step, then ``i-1``, then
``j-1``, so the path is deterministic. ``cost_pathnorm`` divides the raw cost by the path length.

Many pairs run together: their cost matrices are zero-padded to one (B, T1, T2) array (a cell only depends on
cells above and to its left, so padding below/right of a pair never reaches it). The first row and column
are cumulative sums; the interior is swept by anti-diagonals, each a strided view of the flattened array,
three numpy ops per diagonal for the whole batch, accumulated in place, so the result is bit-identical to
the scalar recursion. The backtrack is vectorised over the batch too.

Axis legend: B pairs, T1 prediction frames, T2 ground-truth frames, K points, L path length.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from m3t.metrics.procrustes import check_sequence_pair

CHUNK_ELEMENTS = 1 << 21  # (K x T1 x T2) distances held at once by jpe_distance_matrix


@dataclass(frozen=True)
class DTWResult:
    """Raw accumulated cost, the optimal warping path (L, 2) of (i, j) frame indices, and its length L."""

    cost_raw: float
    path: np.ndarray
    path_length: int

    @property
    def cost_pathnorm(self) -> float:
        """Raw cost divided by the path length (a mean cost per aligned frame pair)."""
        return self.cost_raw / self.path_length


def _as_cost(cost: np.ndarray | torch.Tensor, index: int) -> np.ndarray:
    if isinstance(cost, torch.Tensor):
        cost = cost.detach().cpu().numpy()
    cost = np.asarray(cost, dtype=np.float64)
    if cost.ndim != 2 or cost.shape[0] == 0 or cost.shape[1] == 0:
        raise ValueError(f"DTW cost matrix {index} has shape {cost.shape}; expected a non-empty (T1, T2) matrix")
    if not np.isfinite(cost).all():
        raise ValueError(f"DTW cost matrix {index} ({cost.shape}) holds non-finite values; check the input sequences")
    return cost


def accumulate(costs: np.ndarray) -> np.ndarray:
    """Accumulated-cost tables of a zero-padded batch, batch axis last so each cell's B values are contiguous.

    Parameters
    ----------
    costs : (T1, T2, B) float64 cost matrices; overwritten in place with the tables D (no copy is made).

    Returns
    -------
    (T1, T2, B) ``D``, the same array.
    """
    t1, t2, b = costs.shape
    np.cumsum(costs[0], axis=0, out=costs[0])
    np.cumsum(costs[:, 0], axis=0, out=costs[:, 0])
    flat = costs.reshape(t1 * t2, b)
    buffer = np.empty((min(t1, t2), b))
    stride = t2 - 1  # cell (i, d - i) of anti-diagonal d sits at flat row i * (T2 - 1) + d
    for d in range(2, t1 + t2 - 1):
        lo, hi = max(1, d - t2 + 1), min(d - 1, t1 - 1)
        if lo > hi:
            continue
        start, n = lo * stride + d, hi - lo + 1
        stop = start + (n - 1) * stride + 1
        out = buffer[:n]
        np.minimum(flat[start - t2:stop - t2:stride], flat[start - 1:stop - 1:stride], out=out)  # up, left
        np.minimum(out, flat[start - t2 - 1:stop - t2 - 1:stride], out=out)  # diagonal
        flat[start:stop:stride] += out
    return costs


def backtrack(tables: np.ndarray, lengths: np.ndarray) -> list[np.ndarray]:
    """Optimal paths of accumulated tables (T1, T2, B) from (T1_b - 1, T2_b - 1) back to (0, 0).

    Ties prefer the diagonal, then ``i - 1``, then ``j - 1``. ``lengths`` is (B, 2) int (T1_b, T2_b).
    Returns B arrays (L_b, 2) int64, from (0, 0) to the end.
    """
    t1, t2, b = tables.shape
    flat = tables.reshape(-1)
    lane = np.arange(b)
    i, j = lengths[:, 0].astype(np.int64) - 1, lengths[:, 1].astype(np.int64) - 1
    steps = np.empty((t1 + t2 - 1, 2, b), dtype=np.int64)
    size = np.zeros(b, dtype=np.int64)
    active = (i > 0) | (j > 0)
    k = 0
    while active.any():
        steps[k, 0], steps[k, 1] = i, j
        size += active
        im, jm = np.maximum(i - 1, 0), np.maximum(j - 1, 0)
        diag = flat[(im * t2 + jm) * b + lane]
        up, left = flat[(im * t2 + j) * b + lane], flat[(i * t2 + jm) * b + lane]
        take_diag = (diag <= np.minimum(up, left)) & (i > 0) & (j > 0)
        take_up = ~take_diag & (((up <= left) & (i > 0)) | (j == 0))
        i = np.where(active & (take_diag | take_up), i - 1, i)
        j = np.where(active & ~take_up, j - 1, j)
        active &= (i > 0) | (j > 0)
        k += 1
    steps[k] = 0  # every path ends at (0, 0)
    size += 1
    return [steps[size[n] - 1::-1, :, n].copy() for n in range(b)]


def dtw_batch(costs: Sequence[np.ndarray | torch.Tensor]) -> list[DTWResult]:
    """DTW of many cost matrices at once (each (T1_b, T2_b), sizes may differ).

    Pairs are zero-padded to the largest T1 and T2 of the batch, so group pairs of similar size for speed.
    """
    if len(costs) == 0:
        return []
    mats = [_as_cost(c, n) for n, c in enumerate(costs)]
    lengths = np.array([m.shape for m in mats], dtype=np.int64)  # (B, 2)
    tables = np.zeros((*lengths.max(0), len(mats)))
    for n, m in enumerate(mats):
        tables[:m.shape[0], :m.shape[1], n] = m
    return dtw_padded(tables, lengths)


def dtw_padded(tables: np.ndarray, lengths: np.ndarray) -> list[DTWResult]:
    """DTW of a zero-padded batch already laid out as (T1, T2, B) finite costs, consumed in place.

    ``lengths`` (B, 2) gives each pair's (T1_b, T2_b); ``dtw_batch`` is the checked entry point.
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    accumulate(tables)
    paths = backtrack(tables, lengths)
    raw = tables[lengths[:, 0] - 1, lengths[:, 1] - 1, np.arange(len(lengths))]
    return [DTWResult(float(c), p, len(p)) for c, p in zip(raw, paths)]


def dtw(cost: np.ndarray | torch.Tensor) -> DTWResult:
    """DTW of one (T1, T2) cost matrix: raw accumulated cost, optimal path (L, 2) and its length."""
    return dtw_batch([cost])[0]


def jpe_distance_matrix(pred: torch.Tensor, gt: torch.Tensor, chunk_elements: int = CHUNK_ELEMENTS,
                        measure: slice | None = None) -> torch.Tensor:
    """SOKE's ``dist_jpe`` for every frame pair: root-relative mean point distance.

    Parameters
    ----------
    pred : (T1, K, 3) predicted points; gt : (T2, K, 3) ground-truth points. Point 0 of each frame is the
        region's root (the neck for the body, the wrist for a hand; SOKE's pelvis in ``soke_exact`` mode); both
        are translated to put it at the origin.
    chunk_elements : points are processed in chunks of about this many (K x T1 x T2) distances.
    measure : the points whose distances are averaged; None: all K, the root included (its distance is 0).
        SOKE's body measures 12 points after the pelvis (``l2_dist_align``'s ``wanted``).

    Returns
    -------
    (T1, T2) tensor in pred's dtype and units.
    """
    t1, _, t2 = check_sequence_pair(pred, gt)
    picked = slice(None) if measure is None else measure
    x = (pred[:, picked] - pred[:, :1]).transpose(0, 1)  # (K', T1, 3)
    y = (gt[:, picked] - gt[:, :1]).transpose(0, 1)  # (K', T2, 3)
    k = x.shape[0]
    if k == 0:
        raise ValueError(f"measure {measure} selects none of the {pred.shape[1]} points")
    total = torch.zeros(t1, t2, dtype=pred.dtype, device=pred.device)
    step = max(1, chunk_elements // (t1 * t2))
    for start in range(0, k, step):
        # Direct differences (not the |x|^2 + |y|^2 - 2xy expansion): identical frames give exactly 0.
        dist = torch.cdist(x[start:start + step], y[start:start + step], compute_mode="donot_use_mm_for_euclid_dist")
        total += dist.sum(0)
    return total / k
