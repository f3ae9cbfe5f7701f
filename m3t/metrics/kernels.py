"""Native DTW kernels (numba): the DTW-JPE and DTW-PA-JPE cost matrices, the DP and the backtrack, fused per pair.

The same definitions as the torch/numpy path, in float64 (:mod:`m3t.metrics.dtw`, :mod:`m3t.metrics.procrustes`),
except, by default, the square root of each point distance (``root_precision``):

- JPE cost: root-relative mean point distance (``jpe_distance_matrix``);
- PA cost: similarity Procrustes of every prediction frame onto every ground-truth frame (Umeyama, unweighted),
  solved by the same QCP as ``m3t.body.similarity._rotation_quaternion`` (Horn's quaternion matrix, Newton on its
  characteristic quartic from the same upper bound, eigenvector from the adjugate, reflection impossible by
  construction); frame pairs the QCP flags ill-conditioned or off the largest root are re-solved by Jacobi's
  eigenvalue method on Horn's matrix (no LAPACK, so no scipy at run time), the role ``torch.linalg.svd`` plays
  there; then the mean point distance after alignment (``pa_distance_matrix``);
- DP: ``D[i, j] = c(i, j) + min(D[i-1, j], D[i, j-1], D[i-1, j-1])``, first row and column cumulative sums, swept
  four rows at a time as a wavefront (bit-identical to ``dtw.accumulate``: each cell sees the same three
  neighbours and one addition);
  the backtrack prefers the diagonal, then ``i - 1``, then ``j - 1`` (``dtw.backtrack``'s rule).

Why fused: a pair's cost row ``i`` is computed straight into row ``i`` of its table and accumulated there, so no
(T1, T2) cost matrix is materialised beside the table, and the per-frame-pair work (covariance, QCP, residuals)
runs as loops over the ground-truth frames ``j`` with structure-of-arrays temporaries that the compiler
vectorises. Jobs (one pair, region and metric each) run in parallel on a thread pool, longest first, each
a compiled call that releases the GIL. A shared queue rather than numba's ``prange``: its OpenMP layer splits
the jobs evenly by count up front, and on a shared machine the thread whose core is taken holds up the batch
(measured up to 2x slower on the benchmark's 2 shared cores).

Why a float32 root: DTW-JPE is bound by its square roots (3.2 M per 250-frame pair of body + hands), and a
vector instruction takes twice as many float32 roots at the same throughput; the squares, sums, means and the
DP stay float64, so a cost moves by less than 1.5 x 2^-24 relative (9e-9 m on a 0.1 m cost; lengths within
float32's range, 1e-19 to 1e19 m), far below any digit a table reports. ``root_precision="float64"`` gives
the torch path's arithmetic to ~1e-15.

Compiled functions are cached on disk (``cache=True``: compiled once per machine); where no cache directory is
writable (a read-only install and home, no ``NUMBA_CACHE_DIR``) they compile once per process instead.

Why one file above the project's ~350 lines: numba's disk cache checks only the source file of the function it
compiled, and a fused job (``_point_job``) carries its callees (cost rows, QCP, DP sweep, backtrack) compiled
into it. With the callees in another file, an edit there would leave the cached job running the old code
(numba's documented limit: "cache invalidation fails to recognize changes in functions defined in a different
file"); in one file any edit recompiles them all. The constants imported from :mod:`m3t.body.similarity` are
frozen into the cache the same way: clear the cache (``__pycache__/kernels*.nb*``) after changing them.

Axis legend: T1 prediction frames, T2 ground-truth frames, K points of a region, L path length, B jobs.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from m3t.body.similarity import (
    EIGENPAIR_RESIDUAL,
    ILL_CONDITIONED,
    NEWTON_MAX_ITERATIONS,
    NEWTON_RESIDUAL,
    NEWTON_TOLERANCE,
)
from m3t.metrics.dtw import DTWResult, _as_cost
from m3t.runtime import jit

JACOBI_SWEEPS = 30  # cyclic sweeps of the 4x4 fallback; converges quadratically, ~6 suffice
PA_WORK = 6.0  # a PA cell costs ~6 JPE cells of as many points (250 x 250 x 21: 4.7 vs 0.84 ms): job order
JPE, PA = 0, 1  # job kinds
ROOT_PRECISIONS = ("float32", "float64")  # of the square root of each point distance (see dtw_jobs)


# ---------------------------------------------------------------- DP and backtrack


@jit()
def _sweep_row(table, i):
    """Accumulate row ``i`` of a (T1, T2) table in place (rows above already accumulated)."""
    t2 = table.shape[1]
    if i == 0:
        for j in range(1, t2):
            table[0, j] += table[0, j - 1]
        return
    table[i, 0] += table[i - 1, 0]
    prev, row = table[i - 1], table[i]
    for j in range(1, t2):  # min without branches: on real costs the argmin is unpredictable
        row[j] += min(min(prev[j], prev[j - 1]), row[j - 1])


@jit()
def _sweep_block(table, i0):
    """Accumulate rows ``i0`` .. ``i0 + 3`` in place (``i0 >= 1``, the rows above accumulated), as four
    :func:`_sweep_row` calls would, bit for bit: each cell sees the same three neighbours and one addition. A
    row's cells form a chain (cell j waits for cell j - 1), so the four rows advance as a wavefront, row r at
    column s - r, and the four independent chains overlap in the pipeline."""
    t2 = table.shape[1]
    for r in range(4):
        table[i0 + r, 0] += table[i0 + r - 1, 0]
    for s in range(1, t2 + 3):
        for r in range(4):  # unrolled by the compiler; the bounds only bite in the first and last 3 steps
            j = s - r
            if 1 <= j < t2:
                up, row = table[i0 + r - 1], table[i0 + r]
                row[j] += min(min(up[j], up[j - 1]), row[j - 1])


@jit()
def _sweep_pending(table, i, done):
    """Accumulate the rows ``done`` .. ``i`` once row ``i`` is written: in blocks of four as they fill up, and
    the rest at the last row. Returns the rows accumulated so far."""
    if done == 0:
        _sweep_row(table, 0)
        done = 1
    if i - done + 1 == 4:
        _sweep_block(table, done)
        done += 4
    if i == table.shape[0] - 1:
        while done <= i:
            _sweep_row(table, done)
            done += 1
    return done


@jit()
def _backtrack(table, path):
    """Optimal path of an accumulated (T1, T2) table into ``path`` (>= T1 + T2 - 1, 2), from (0, 0); returns L."""
    t1, t2 = table.shape
    i, j, n = t1 - 1, t2 - 1, 0
    reverse = np.empty((t1 + t2 - 1, 2), dtype=np.int64)
    reverse[0, 0], reverse[0, 1] = i, j
    while i > 0 or j > 0:
        if i == 0:
            j -= 1
        elif j == 0:
            i -= 1
        else:
            diag, up, left = table[i - 1, j - 1], table[i - 1, j], table[i, j - 1]
            if diag <= min(up, left):
                i -= 1
                j -= 1
            elif up <= left:
                i -= 1
            else:
                j -= 1
        n += 1
        reverse[n, 0], reverse[n, 1] = i, j
    for m in range(n + 1):
        path[m, 0], path[m, 1] = reverse[n - m, 0], reverse[n - m, 1]
    return n + 1


# ---------------------------------------------------------------- cost rows


@jit()
def _jpe_prepare(pred, gt, m0, m1):
    """Root-relative measured points: pred (T1, K', 3) and gt as (K', 3, T2) so rows run over contiguous j."""
    t1, t2, kk = pred.shape[0], gt.shape[0], m1 - m0
    x = np.empty((t1, kk, 3))
    for i in range(t1):
        for p in range(kk):
            for a in range(3):
                x[i, p, a] = pred[i, m0 + p, a] - pred[i, 0, a]
    y = np.empty((kk, 3, t2))
    for j in range(t2):
        for p in range(kk):
            for a in range(3):
                y[p, a, j] = gt[j, m0 + p, a] - gt[j, 0, a]
    return x, y


@jit()
def _length(d0, d1, d2, single):
    """|(d0, d1, d2)|: the squares and their sum in float64, the root in float64 or, with ``single``, in float32
    (relative error < 1.5 x 2^-24, and twice as many roots per vector instruction: the JPE cost is root-bound)."""
    squared = d0 * d0 + d1 * d1 + d2 * d2
    return np.float64(np.sqrt(np.float32(squared))) if single else np.sqrt(squared)


@jit()
def _jpe_row(x, y, i, out, single):
    """Row ``i`` of the JPE cost matrix into ``out`` (T2,): mean over K' of |x[i, k] - y[k, :, j]|."""
    kk, t2 = y.shape[0], y.shape[2]
    out[:] = 0.0
    k = 0
    while k + 2 <= kk:  # two points per pass: half the loads and stores of ``out``
        x0, x1, x2 = x[i, k, 0], x[i, k, 1], x[i, k, 2]
        u0, u1, u2 = x[i, k + 1, 0], x[i, k + 1, 1], x[i, k + 1, 2]
        y0, y1, y2 = y[k, 0], y[k, 1], y[k, 2]
        v0, v1, v2 = y[k + 1, 0], y[k + 1, 1], y[k + 1, 2]
        for j in range(t2):
            out[j] += (_length(x0 - y0[j], x1 - y1[j], x2 - y2[j], single)
                       + _length(u0 - v0[j], u1 - v1[j], u2 - v2[j], single))
        k += 2
    if k < kk:
        x0, x1, x2 = x[i, k, 0], x[i, k, 1], x[i, k, 2]
        y0, y1, y2 = y[k, 0], y[k, 1], y[k, 2]
        for j in range(t2):
            out[j] += _length(x0 - y0[j], x1 - y1[j], x2 - y2[j], single)
    for j in range(t2):
        out[j] = out[j] / kk


@jit()
def _centred(points):
    """(T, K, 3) points centred per frame, and each frame's sum of squares (T,) (points, then axes)."""
    t, k, _ = points.shape
    out = np.empty((t, k, 3))
    for i in range(t):
        for a in range(3):
            mean = 0.0
            for p in range(k):
                mean += points[i, p, a]
            mean /= k
            for p in range(k):
                out[i, p, a] = points[i, p, a] - mean
    var = np.zeros(t)
    for i in range(t):
        for p in range(k):
            for a in range(3):
                var[i] += out[i, p, a] * out[i, p, a]
    return out, var


@jit()
def _pa_prepare(pred, gt):
    """Centred points: pred (T1, K, 3), gt (K, 3, T2), and their sums of squares (T1,), (T2,)."""
    xs, var_s = _centred(pred)
    centred_gt, var_t = _centred(gt)
    ys = np.ascontiguousarray(centred_gt.transpose(1, 2, 0))
    return xs, ys, var_s, var_t


@jit()
def _top_eigen_jacobi(n):
    """Largest eigenvalue and its unit eigenvector of a symmetric 4x4 matrix, by cyclic Jacobi rotations."""
    a = n.copy()
    v = np.eye(4)
    scale = 0.0
    for p in range(4):
        for q in range(4):
            scale += a[p, q] * a[p, q]
    for _ in range(JACOBI_SWEEPS):
        off = 0.0
        for p in range(3):
            for q in range(p + 1, 4):
                off += a[p, q] * a[p, q]
        if off <= 1e-32 * scale:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                if a[p, q] == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
                t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0)) if abs(theta) < 1e150 else 0.5 / abs(theta)
                if theta < 0.0:
                    t = -t
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for r in range(4):  # A <- A G, then G^T A, V <- V G
                    arp, arq = a[r, p], a[r, q]
                    a[r, p], a[r, q] = c * arp - s * arq, s * arp + c * arq
                for r in range(4):
                    apr, aqr = a[p, r], a[q, r]
                    a[p, r], a[q, r] = c * apr - s * aqr, s * apr + c * aqr
                for r in range(4):
                    vrp, vrq = v[r, p], v[r, q]
                    v[r, p], v[r, q] = c * vrp - s * vrq, s * vrp + c * vrq
    top = 0
    for r in range(1, 4):
        if a[r, r] > a[top, top]:
            top = r
    return a[top, top], v[:, top].copy()


@jit()
def _store_rotation(srot, j, w, x, y, z, scale):
    """Column ``j`` of (9, T2) ``srot`` = scale x the rotation of the unit quaternion (w, x, y, z), row-major."""
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    wx, wy, wz, xy, xz, yz = w * x, w * y, w * z, x * y, x * z, y * z
    srot[0, j], srot[1, j], srot[2, j] = (ww + xx - yy - zz) * scale, 2 * (xy - wz) * scale, 2 * (xz + wy) * scale
    srot[3, j], srot[4, j], srot[5, j] = 2 * (xy + wz) * scale, (ww - xx + yy - zz) * scale, 2 * (yz - wx) * scale
    srot[6, j], srot[7, j], srot[8, j] = 2 * (xz - wy) * scale, 2 * (yz + wx) * scale, (ww - xx - yy + zz) * scale


@jit()
def _pa_row(xs, ys, var_s, var_t, i, m0, m1, work, out, single):
    """Row ``i`` of the PA cost matrix into ``out`` (T2,).

    ``work`` is (25, T2) scratch: rows 0-8 covariance, 9-17 scaled rotation, 18-24 QCP state.
    """
    k, t2 = xs.shape[1], ys.shape[2]
    cov = work[0:9]
    srot = work[9:18]
    lam, upper, q0, q1, q2, tol = work[18], work[19], work[20], work[21], work[22], work[23]
    cov[:] = 0.0
    for b in range(3):  # S[a, b] = sum_k x_a y_b, vectorised over j, four points per pass over the rows
        r0, r1, r2 = cov[b], cov[3 + b], cov[6 + b]
        p = 0
        while p + 4 <= k:
            y0, y1, y2, y3 = ys[p, b], ys[p + 1, b], ys[p + 2, b], ys[p + 3, b]
            x00, x01, x02 = xs[i, p, 0], xs[i, p, 1], xs[i, p, 2]
            x10, x11, x12 = xs[i, p + 1, 0], xs[i, p + 1, 1], xs[i, p + 1, 2]
            x20, x21, x22 = xs[i, p + 2, 0], xs[i, p + 2, 1], xs[i, p + 2, 2]
            x30, x31, x32 = xs[i, p + 3, 0], xs[i, p + 3, 1], xs[i, p + 3, 2]
            for j in range(t2):
                v0, v1, v2, v3 = y0[j], y1[j], y2[j], y3[j]
                r0[j] += x00 * v0 + x10 * v1 + x20 * v2 + x30 * v3
                r1[j] += x01 * v0 + x11 * v1 + x21 * v2 + x31 * v3
                r2[j] += x02 * v0 + x12 * v1 + x22 * v2 + x32 * v3
            p += 4
        for q in range(p, k):
            y0 = ys[q, b]
            x00, x01, x02 = xs[i, q, 0], xs[i, q, 1], xs[i, q, 2]
            for j in range(t2):
                v0 = y0[j]
                r0[j] += x00 * v0
                r1[j] += x01 * v0
                r2[j] += x02 * v0
    vs = var_s[i]
    for j in range(t2):
        s00, s01, s02 = cov[0, j], cov[1, j], cov[2, j]
        s10, s11, s12 = cov[3, j], cov[4, j], cov[5, j]
        s20, s21, s22 = cov[6, j], cov[7, j], cov[8, j]
        frob = (s00 * s00 + s01 * s01 + s02 * s02 + s10 * s10 + s11 * s11 + s12 * s12
                + s20 * s20 + s21 * s21 + s22 * s22)
        n00, n11 = s00 + s11 + s22, s00 - s11 - s22
        n22, n33 = s11 - s00 - s22, s22 - s00 - s11
        n01, n02, n03 = s12 - s21, s20 - s02, s01 - s10
        n12, n13, n23 = s01 + s10, s20 + s02, s12 + s21
        m01, m02, m03 = n00 * n11 - n01 * n01, n00 * n12 - n01 * n02, n00 * n13 - n01 * n03
        m12, m13, m23 = n01 * n12 - n11 * n02, n01 * n13 - n11 * n03, n02 * n13 - n12 * n03
        c01, c02, c03 = n02 * n13 - n03 * n12, n02 * n23 - n03 * n22, n02 * n33 - n03 * n23
        c12, c13, c23 = n12 * n23 - n13 * n22, n12 * n33 - n13 * n23, n22 * n33 - n23 * n23
        q0[j] = m01 * c23 - m02 * c13 + m03 * c12 + m12 * c03 - m13 * c02 + m23 * c01  # det N
        q1[j] = -8.0 * (s00 * (s11 * s22 - s12 * s21) - s01 * (s10 * s22 - s12 * s20) + s02 * (s10 * s21 - s11 * s20))
        q2[j] = -2.0 * frob
        bound = min(np.sqrt(vs * var_t[j]), np.sqrt(3.0 * frob))
        upper[j] = bound
        lam[j] = bound
        tol[j] = NEWTON_TOLERANCE * bound
    for it in range(NEWTON_MAX_ITERATIONS):  # as procrustes: every j steps until the whole row has converged
        busy = False
        for j in range(t2):
            lj = lam[j]
            l2 = lj * lj
            f = (l2 + q2[j]) * l2 + q1[j] * lj + q0[j]
            df = (4.0 * l2 + 2.0 * q2[j]) * lj + q1[j]
            step = f / df if df > 0.0 else 0.0
            lam[j] = lj - step
            busy = busy | (abs(step) > tol[j])
        if it % 2 == 1 and not busy:
            break
    ill_any = False
    ill = work[24]
    for j in range(t2):
        s00, s01, s02 = cov[0, j], cov[1, j], cov[2, j]
        s10, s11, s12 = cov[3, j], cov[4, j], cov[5, j]
        s20, s21, s22 = cov[6, j], cov[7, j], cov[8, j]
        lj = lam[j]
        a00, a11 = s00 + s11 + s22 - lj, s00 - s11 - s22 - lj
        a22, a33 = s11 - s00 - s22 - lj, s22 - s00 - s11 - lj
        a01, a02, a03 = s12 - s21, s20 - s02, s01 - s10
        a12, a13, a23 = s01 + s10, s20 + s02, s12 + s21
        # 2x2 minors of rows (0, 1) and (2, 3), then the adjugate of the symmetric N - lambda I
        m01, m02, m03 = a00 * a11 - a01 * a01, a00 * a12 - a01 * a02, a00 * a13 - a01 * a03
        m12, m13, m23 = a01 * a12 - a11 * a02, a01 * a13 - a11 * a03, a02 * a13 - a12 * a03
        c02, c03 = a02 * a23 - a03 * a22, a02 * a33 - a03 * a23
        c12, c13, c23 = a12 * a23 - a13 * a22, a12 * a33 - a13 * a23, a22 * a33 - a23 * a23
        d0 = a11 * c23 - a12 * c13 + a13 * c12
        d1 = a00 * c23 - a02 * c03 + a03 * c02
        d2 = a03 * m13 - a13 * m03 + a33 * m01
        d3 = a02 * m12 - a12 * m02 + a22 * m01
        o01 = -a01 * c23 + a02 * c13 - a03 * c12
        o02 = a13 * m23 - a23 * m13 + a33 * m12
        o03 = -a12 * m23 + a22 * m13 - a23 * m12
        o12 = -a03 * m23 + a23 * m03 - a33 * m02
        o13 = a02 * m23 - a22 * m03 + a23 * m02
        o23 = -a02 * m13 + a12 * m03 - a23 * m01
        # its largest-diagonal column is the most accurate top eigenvector
        w, x, y, z, top = d0, o01, o02, o03, abs(d0)
        if abs(d1) > top:
            w, x, y, z, top = o01, d1, o12, o13, abs(d1)
        if abs(d2) > top:
            w, x, y, z, top = o02, o12, d2, o23, abs(d2)
        if abs(d3) > top:
            w, x, y, z, top = o03, o13, o23, d3, abs(d3)
        bound = upper[j]
        # as procrustes: a tiny eigenvalue gap, or lambda no root / below a Rayleigh quotient (a diagonal of N)
        l2 = lj * lj
        missed = abs((l2 + q2[j]) * l2 + q1[j] * lj + q0[j]) > NEWTON_RESIDUAL * 0.25 * q2[j] * q2[j]
        lower = max(max(a00, a11), max(a22, a33)) + lj
        missed = missed | (lj < lower - tol[j])
        # ... or lambda off the eigenvector's Rayleigh quotient, q^T (N - lambda I) q != 0 (as procrustes)
        squared = w * w + x * x + y * y + z * z
        quadratic = (a00 * w * w + a11 * x * x + a22 * y * y + a33 * z * z
                     + 2.0 * (a01 * w * x + a02 * w * y + a03 * w * z + a12 * x * y + a13 * x * z + a23 * y * z))
        missed = missed | (abs(quadratic) > EIGENPAIR_RESIDUAL * bound * squared)
        bad = (top <= ILL_CONDITIONED * bound * bound * bound or missed) and bound > 0.0
        ill[j] = 1.0 if bad else 0.0
        ill_any = ill_any | bad
        norm = np.sqrt(w * w + x * x + y * y + z * z)
        inv = 1.0 / norm if norm != 0.0 else 1.0
        w = w * inv if norm != 0.0 else 1.0  # a zero covariance: every rotation is optimal, take the identity
        x, y, z = x * inv, y * inv, z * inv
        _store_rotation(srot, j, w, x, y, z, lj / vs if vs > 0.0 else 0.0)
    if ill_any:
        horn = np.empty((4, 4))
        for j in range(t2):
            if ill[j] == 0.0:
                continue
            s00, s01, s02 = cov[0, j], cov[1, j], cov[2, j]
            s10, s11, s12 = cov[3, j], cov[4, j], cov[5, j]
            s20, s21, s22 = cov[6, j], cov[7, j], cov[8, j]
            horn[0, 0], horn[1, 1] = s00 + s11 + s22, s00 - s11 - s22
            horn[2, 2], horn[3, 3] = s11 - s00 - s22, s22 - s00 - s11
            horn[0, 1] = horn[1, 0] = s12 - s21
            horn[0, 2] = horn[2, 0] = s20 - s02
            horn[0, 3] = horn[3, 0] = s01 - s10
            horn[1, 2] = horn[2, 1] = s01 + s10
            horn[1, 3] = horn[3, 1] = s20 + s02
            horn[2, 3] = horn[3, 2] = s12 + s21
            trace, q = _top_eigen_jacobi(horn)
            _store_rotation(srot, j, q[0], q[1], q[2], q[3], trace / vs if vs > 0.0 else 0.0)
    out[:] = 0.0
    for p in range(m0, m1):  # |s R x - y| per measured point (centroids already coincide)
        x0, x1, x2 = xs[i, p, 0], xs[i, p, 1], xs[i, p, 2]
        y0, y1, y2 = ys[p, 0], ys[p, 1], ys[p, 2]
        for j in range(t2):
            r0 = srot[0, j] * x0 + srot[1, j] * x1 + srot[2, j] * x2 - y0[j]
            r1 = srot[3, j] * x0 + srot[4, j] * x1 + srot[5, j] * x2 - y1[j]
            r2 = srot[6, j] * x0 + srot[7, j] * x1 + srot[8, j] * x2 - y2[j]
            out[j] += _length(r0, r1, r2, single)
    for j in range(t2):
        out[j] = out[j] / (m1 - m0)


# ---------------------------------------------------------------- one job, without the GIL


@jit(nogil=True)
def _point_job(pred, gt, kind, m0, m1, single, accumulate, path):
    """(T1, T2) cost matrix of one job (point lengths rooted in float32 with ``single``); with ``accumulate``
    swept in place into the DP table as its rows are written (:func:`_sweep_pending`) and backtracked into
    ``path`` (>= T1 + T2 - 1, 2). Returns the table and the path length L (0 without)."""
    t1, t2 = pred.shape[0], gt.shape[0]
    table = np.empty((t1, t2))
    done = 0  # rows accumulated
    if kind == JPE:
        x, y = _jpe_prepare(pred, gt, m0, m1)
        for i in range(t1):
            _jpe_row(x, y, i, table[i], single)
            if accumulate:
                done = _sweep_pending(table, i, done)
    else:
        xs, ys, var_s, var_t = _pa_prepare(pred, gt)
        work = np.empty((25, t2))
        for i in range(t1):
            _pa_row(xs, ys, var_s, var_t, i, m0, m1, work, table[i], single)
            if accumulate:
                done = _sweep_pending(table, i, done)
    return table, _backtrack(table, path) if accumulate else 0


@jit(nogil=True)
def _cost_job(cost, path):
    """DP + backtrack of a given (T1, T2) cost matrix (left unchanged): raw cost and path length."""
    table = cost.copy()
    done = 0
    for i in range(table.shape[0]):
        done = _sweep_pending(table, i, done)
    return table[-1, -1], _backtrack(table, path)


# ---------------------------------------------------------------- Python entry points


@dataclass(frozen=True)
class CostJob:
    """One DTW of point sequences: pred (T1, K, 3), gt (T2, K, 3) float64, the PA cost or the JPE cost, and the
    points the distances average over (None: all K; the PA alignment always fits all K)."""

    pred: np.ndarray
    gt: np.ndarray
    procrustes: bool
    measure: slice | None = None


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _in_parallel(run: Callable[[int], DTWResult], work: Sequence[float], threads: int | None) -> list[DTWResult]:
    """``run(b)`` for every job b on ``threads`` threads (None: every available core), longest job first.

    The kernels release the GIL, so threads run them concurrently; a shared queue (not a fixed split) keeps
    every core busy when jobs differ in cost (PA ~10x JPE) or a core is lent to another process meanwhile.
    """
    order = [int(b) for b in np.argsort(-np.asarray(work, dtype=np.float64), kind="stable")]
    threads = min(threads or available_cores(), len(order))
    if threads <= 1:
        done = [run(b) for b in order]
    else:
        with ThreadPoolExecutor(threads) as pool:
            done = list(pool.map(run, order))
    out: list[DTWResult] = [None] * len(order)  # type: ignore[list-item]
    for b, result in zip(order, done):
        out[b] = result
    return out


def _measured_range(measure: slice | None, k: int, index: int) -> tuple[int, int]:
    if measure is None:
        return 0, k
    start, stop, step = measure.indices(k)
    if step != 1 or stop <= start:
        raise ValueError(f"job {index}: measure {measure} must select a non-empty contiguous range of the {k} points")
    return start, stop


def _checked_points(job: CostJob, index: int) -> tuple[np.ndarray, np.ndarray]:
    pred, gt = (np.ascontiguousarray(job.pred, dtype=np.float64), np.ascontiguousarray(job.gt, dtype=np.float64))
    if pred.ndim != 3 or gt.ndim != 3 or pred.shape[1:] != gt.shape[1:] or pred.shape[-1] != 3 \
            or 0 in pred.shape or 0 in gt.shape:
        raise ValueError(f"job {index}: pred {pred.shape} and gt {gt.shape} must be non-empty (T1, K, 3) and "
                         "(T2, K, 3)")
    return pred, gt


def _single(root_precision: str) -> bool:
    if root_precision not in ROOT_PRECISIONS:
        raise ValueError(f"root precision {root_precision!r} unknown; use one of {ROOT_PRECISIONS}")
    return root_precision == "float32"


def _result(raw: float, path: np.ndarray, length: int) -> DTWResult:
    return DTWResult(float(raw), path[:length].copy(), int(length))


def dtw_jobs(jobs: Sequence[CostJob], threads: int | None = None,
             root_precision: str = "float32") -> list[DTWResult]:
    """DTW (raw cost, path, path length) of many point-sequence pairs, cost matrices computed in the kernel.

    ``threads``: jobs run concurrently on this many threads (None: every available core). ``root_precision``:
    the square root of each point distance in float32 (the default: ~1.9x faster DTW-JPE, costs within 9e-8
    relative) or float64 (the torch path's arithmetic, to ~1e-15); squares and sums are float64 either way.
    """
    single = _single(root_precision)
    checked = [_checked_points(job, n) for n, job in enumerate(jobs)]
    ranges = [_measured_range(job.measure, pred.shape[1], n) for n, (job, (pred, _)) in enumerate(zip(jobs, checked))]

    def run(b: int) -> DTWResult:
        (pred, gt), (m0, m1) = checked[b], ranges[b]
        path = np.empty((len(pred) + len(gt) - 1, 2), dtype=np.int64)
        table, length = _point_job(pred, gt, PA if jobs[b].procrustes else JPE, m0, m1, single, True, path)
        return _result(table[-1, -1], path, length)

    work = [len(p) * len(g) * (PA_WORK * p.shape[1] if job.procrustes else r[1] - r[0])
            for job, (p, g), r in zip(jobs, checked, ranges)]
    return _in_parallel(run, work, threads)


def dtw_costs(costs: Sequence[np.ndarray], threads: int | None = None) -> list[DTWResult]:
    """DTW of given (T1_b, T2_b) cost matrices (sizes may differ), like ``dtw.dtw_batch`` without padding."""
    mats = [_as_cost(c, n) for n, c in enumerate(costs)]

    def run(b: int) -> DTWResult:
        path = np.empty((sum(mats[b].shape) - 1, 2), dtype=np.int64)
        raw, length = _cost_job(mats[b], path)
        return _result(raw, path, length)

    return _in_parallel(run, [m.size for m in mats], threads)


def jpe_cost_matrix(pred: np.ndarray, gt: np.ndarray, measure: slice | None = None,
                    root_precision: str = "float32") -> np.ndarray:
    """(T1, T2) DTW-JPE cost matrix of pred (T1, K, 3) and gt (T2, K, 3), as ``dtw.jpe_distance_matrix``."""
    pred, gt = _checked_points(CostJob(pred, gt, False, measure), 0)
    m0, m1 = _measured_range(measure, pred.shape[1], 0)
    return _point_job(pred, gt, JPE, m0, m1, _single(root_precision), False, np.empty((0, 2), dtype=np.int64))[0]


def pa_cost_matrix(pred: np.ndarray, gt: np.ndarray, measure: slice | None = None,
                   root_precision: str = "float32") -> np.ndarray:
    """(T1, T2) DTW-PA-JPE cost matrix of pred (T1, K, 3) and gt (T2, K, 3), as ``procrustes.pa_distance_matrix``."""
    pred, gt = _checked_points(CostJob(pred, gt, True, measure), 0)
    m0, m1 = _measured_range(measure, pred.shape[1], 0)
    return _point_job(pred, gt, PA, m0, m1, _single(root_precision), False, np.empty((0, 2), dtype=np.int64))[0]
