"""Similarity Procrustes (scale + proper rotation + translation), batched: the project's one solver, used by the
correspondence builder (``tools/build_correspondence.py``) and by every PA error (:mod:`m3t.metrics.procrustes`),
so it sits in the body layer, the lowest that needs it.

``similarity_transform`` solves the classic ``compute_similarity_transform`` (Umeyama): the rotation that
maximises ``tr(R S)`` over proper rotations (the reflection fix), ``scale = tr(R S) / |source - mean|^2`` and
the translation that maps centroids. Two solvers give the same answer:

- ``"quaternion"`` (default): Horn's 4x4 quaternion matrix, its largest eigenvalue by Newton's method on the
  characteristic quartic from an upper bound (Theobald's QCP; the quartic is convex and increasing right of
  its largest root, so the iteration decreases monotonically onto it) and the eigenvector from the adjugate
  of ``N - lambda I``. Every step is elementwise, so a million 3x3 problems cost a few hundred vector ops;
  LAPACK's batched ``torch.linalg.svd`` loops over matrices one by one and is 5x slower or worse on CPU
  (``benchmarks/bench_dtw.py`` measures both; results agree to ~1e-13). Ill-conditioned problems (nearly
  collinear points, whose eigenvector is not unique) are re-solved by SVD, where every optimal rotation
  aligns alike; so are those where Newton did not end on the largest root: at a double root (collinear
  points onto the same line) f and f' vanish together, one rounding-sized step can jump far below, and the
  iteration then stalls where f' <= 0 (the rotation of a line onto itself came out with scale 2/3). A stall
  just below the root leaves f tiny (~ the squared distance) and the eigenvector right, so lambda is also
  checked against the eigenvector's Rayleigh quotient (such stalls put a line onto itself up to 2e-5 off).
- ``"svd"``: the textbook SVD with ``Z = diag(1, 1, sign det(U V^T))``.

Optional point ``weights`` give Umeyama's weighted problem (weighted centroids, covariance and scale
denominator); without them every point counts alike.

Axis legend: K points, ``...`` any batch axes.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

NEWTON_MAX_ITERATIONS = 60
NEWTON_TOLERANCE = 1e-12  # relative to the starting bound
ILL_CONDITIONED = 1e-8  # top adjugate diagonal below this x bound^3: eigenvalue gap too small -> SVD
NEWTON_RESIDUAL = 1e-8  # |f(lambda)| above this x |S|_F^4 after Newton: not a root -> SVD (rounding is ~1e-15)
# |q^T (N - lambda I) q| above this x bound x |q|^2: lambda is not the eigenvalue of the eigenvector q -> SVD. Near a
# double top root f ~ (lambda - root)^2, so f's test lets Newton's stalls of up to ~1e-4 x bound through; this one
# sees the gap itself (a converged lambda is good to ~NEWTON_TOLERANCE: 10x below this).
EIGENPAIR_RESIDUAL = 1e-11


@dataclass(frozen=True)
class SimilarityTransform:
    """``aligned = scale * source @ rotation.T + translation``.

    rotation (..., 3, 3), scale (...), translation (..., 3).
    """

    rotation: torch.Tensor
    scale: torch.Tensor
    translation: torch.Tensor

    def apply(self, points: torch.Tensor) -> torch.Tensor:
        """(..., K, 3) points -> (..., K, 3) transformed points."""
        return self.scale[..., None, None] * points @ self.rotation.transpose(-1, -2) + self.translation[..., None, :]


def _det3(m: torch.Tensor) -> torch.Tensor:
    """(3, 3, ...) component-first matrices -> (...) determinants by cofactors (elementwise, no LAPACK)."""
    return (m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]) - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
            + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]))


def _rotation_svd(cov: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 3, 3) covariance S = sum_k x_k y_k^T -> proper rotation R (..., 3, 3) maximising tr(R S), and tr(R S)."""
    u, sigma, vh = torch.linalg.svd(cov)
    sign = torch.sign(torch.linalg.det(vh.transpose(-1, -2) @ u.transpose(-1, -2)))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)  # rank-deficient: either sign is optimal
    z = torch.ones_like(sigma)
    z[..., 2] = sign
    rotation = vh.transpose(-1, -2) @ (z[..., :, None] * u.transpose(-1, -2))
    return rotation, (sigma * z).sum(-1)


def _horn_matrix(s: torch.Tensor) -> list[list[torch.Tensor]]:
    """(3, 3, ...) covariance -> Horn's symmetric, traceless quaternion matrix as 4 x 4 nested lists of (...)."""
    n00, n11 = s[0, 0] + s[1, 1] + s[2, 2], s[0, 0] - s[1, 1] - s[2, 2]
    n22, n33 = s[1, 1] - s[0, 0] - s[2, 2], s[2, 2] - s[0, 0] - s[1, 1]
    n01, n02, n03 = s[1, 2] - s[2, 1], s[2, 0] - s[0, 2], s[0, 1] - s[1, 0]
    n12, n13, n23 = s[0, 1] + s[1, 0], s[2, 0] + s[0, 2], s[1, 2] + s[2, 1]
    return [[n00, n01, n02, n03], [n01, n11, n12, n13], [n02, n12, n22, n23], [n03, n13, n23, n33]]


def _minors(a: list[list[torch.Tensor]]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """2x2 minors of rows (0, 1) (``s``) and rows (2, 3) (``c``) of a 4 x 4 matrix, shared by det and adjugate."""
    def m(r: int, c0: int, c1: int) -> torch.Tensor:
        return a[r][c0] * a[r + 1][c1] - a[r + 1][c0] * a[r][c1]

    cols = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    return [m(0, i, j) for i, j in cols], [m(2, i, j) for i, j in reversed(cols)]


def _det4(s: list[torch.Tensor], c: list[torch.Tensor]) -> torch.Tensor:
    """Laplace expansion of a 4 x 4 determinant over its complementary 2x2 minors."""
    return s[0] * c[0] - s[1] * c[1] + s[2] * c[2] + s[3] * c[3] - s[4] * c[4] + s[5] * c[5]


def _adjugate_symmetric(a: list[list[torch.Tensor]], s: list[torch.Tensor],
                        c: list[torch.Tensor]) -> list[list[torch.Tensor]]:
    """Adjugate (4 x 4 nested lists) of a symmetric 4 x 4 matrix from its 2x2 minors (as ``_minors`` orders them)."""
    c5, c4, c3, c2, c1, _ = c  # the last minor (columns 0, 1) only enters the determinant
    s0, s1, s2, s3, s4, s5 = s
    d0 = a[1][1] * c5 - a[1][2] * c4 + a[1][3] * c3
    d1 = a[0][0] * c5 - a[0][2] * c2 + a[0][3] * c1
    d2 = a[3][0] * s4 - a[3][1] * s2 + a[3][3] * s0
    d3 = a[2][0] * s3 - a[2][1] * s1 + a[2][2] * s0
    o01 = -a[0][1] * c5 + a[0][2] * c4 - a[0][3] * c3
    o02 = a[3][1] * s5 - a[3][2] * s4 + a[3][3] * s3
    o03 = -a[2][1] * s5 + a[2][2] * s4 - a[2][3] * s3
    o12 = -a[3][0] * s5 + a[3][2] * s2 - a[3][3] * s1
    o13 = a[2][0] * s5 - a[2][2] * s2 + a[2][3] * s1
    o23 = -a[2][0] * s4 + a[2][1] * s2 - a[2][3] * s0
    return [[d0, o01, o02, o03], [o01, d1, o12, o13], [o02, o12, d2, o23], [o03, o13, o23, d3]]


def _rotation_quaternion(cov: torch.Tensor, upper: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(3, 3, ...) component-first covariance -> rotation (3, 3, ...), tr(R S) (...), ill-conditioned mask (...).

    Component-first layout keeps every elementwise op on contiguous memory (3-4x faster than strided views).
    """
    horn = _horn_matrix(cov)
    # det(lambda I - N) = l^4 + c2 l^2 + c1 l + c0 with c2 = -2|S|^2, c1 = -8 det S, c0 = det N (N is traceless).
    q2 = -2.0 * cov.square().sum((0, 1))
    q1 = -8.0 * _det3(cov)
    q0 = _det4(*_minors(horn))
    lam = upper.clone()
    two_q2 = 2.0 * q2
    tolerance = NEWTON_TOLERANCE * upper
    for it in range(NEWTON_MAX_ITERATIONS):
        lam2 = lam * lam
        f = (lam2 + q2) * lam2 + q1 * lam + q0
        df = (4.0 * lam2 + two_q2) * lam + q1
        step = torch.where(df > 0, f / df, torch.zeros_like(f))
        lam -= step
        # Quadratic convergence: once a step is ~1e-12 of the root the next would be ~1e-24, below rounding.
        if it % 2 == 1 and not bool((step.abs() > tolerance).any()):
            break
    shifted = [[v - lam if r == c else v for c, v in enumerate(row)] for r, row in enumerate(horn)]
    # adj(N - lambda I) = mu q q^T for the top eigenvector q: its largest-diagonal column is the most accurate q.
    adjugate = _adjugate_symmetric(shifted, *_minors(shifted))
    q, top = adjugate[0], adjugate[0][0].abs()
    for col in range(1, 4):
        diagonal = adjugate[col][col].abs()
        better = diagonal > top
        q = [torch.where(better, new, old) for new, old in zip(adjugate[col], q)]
        top = torch.maximum(top, diagonal)
    ill = top <= ILL_CONDITIONED * upper * upper * upper
    # Not on the largest root: f(lambda) is no root, or lambda is below a Rayleigh quotient (a diagonal of N).
    lam2 = lam * lam
    ill |= ((lam2 + q2) * lam2 + q1 * lam + q0).abs() > NEWTON_RESIDUAL * 0.25 * q2 * q2
    lower = torch.maximum(torch.maximum(horn[0][0], horn[1][1]), torch.maximum(horn[2][2], horn[3][3]))
    ill |= lam < lower - tolerance
    # ... or lambda is not q's Rayleigh quotient (a stall just below a double root: q is right, lambda is not).
    # Evaluated as the quadratic form, not as f(lambda) q_k (equal in exact arithmetic): f's cancellation hides
    # stalls below ~1e-8.
    squared = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
    off = (shifted[0][1] * q[1] + shifted[0][2] * q[2] + shifted[0][3] * q[3]) * q[0] \
        + (shifted[1][2] * q[2] + shifted[1][3] * q[3]) * q[1] + shifted[2][3] * q[2] * q[3]
    quadratic = (shifted[0][0] * q[0] * q[0] + shifted[1][1] * q[1] * q[1] + shifted[2][2] * q[2] * q[2]
                 + shifted[3][3] * q[3] * q[3] + 2.0 * off)
    ill |= quadratic.abs() > EIGENPAIR_RESIDUAL * upper * squared
    norm = squared.sqrt()
    zero = norm == 0  # a zero covariance: every rotation is optimal, take the identity
    inv = 1.0 / torch.where(zero, torch.ones_like(norm), norm)
    w, x, y, z = (torch.where(zero, torch.ones_like(norm), q[0] * inv), q[1] * inv, q[2] * inv, q[3] * inv)
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    wx, wy, wz, xy, xz, yz = w * x, w * y, w * z, x * y, x * z, y * z
    rotation = cov.new_empty(cov.shape)
    rotation[0, 0], rotation[0, 1], rotation[0, 2] = ww + xx - yy - zz, 2 * (xy - wz), 2 * (xz + wy)
    rotation[1, 0], rotation[1, 1], rotation[1, 2] = 2 * (xy + wz), ww - xx + yy - zz, 2 * (yz - wx)
    rotation[2, 0], rotation[2, 1], rotation[2, 2] = 2 * (xz - wy), 2 * (yz + wx), ww - xx - yy + zz
    return rotation, lam, ill


def rotation_component_first(cov: torch.Tensor, source_sq: torch.Tensor, target_sq: torch.Tensor,
                              method: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Like ``rotation_from_covariance`` for a component-first (3, 3, ...) covariance (the layout batched callers
    build directly), in its own dtype; returns a (3, 3, ...) rotation and tr(R S) (...)."""
    if method == "svd":
        rotation, trace = _rotation_svd(cov.movedim((0, 1), (-2, -1)))
        return rotation.movedim((-2, -1), (0, 1)), trace
    if method != "quaternion":
        raise ValueError(f"unknown Procrustes method {method!r}; use 'quaternion' or 'svd'")
    # tr(R S) <= sum of singular values <= min(sqrt(|x|^2 |y|^2), sqrt(3) |S|_F): Newton starts above the root.
    upper = torch.minimum((source_sq * target_sq).sqrt(), (3.0 * cov.square().sum((0, 1))).sqrt())
    upper = upper.expand(cov.shape[2:]).contiguous()
    rotation, trace, ill = _rotation_quaternion(cov, upper)
    ill &= upper > 0
    if bool(ill.any()):
        fixed, trace[ill] = _rotation_svd(cov[:, :, ill].movedim((0, 1), (-2, -1)))
        rotation[:, :, ill] = fixed.movedim((-2, -1), (0, 1))
    return rotation, trace


def rotation_from_covariance(cov: torch.Tensor, source_sq: torch.Tensor, target_sq: torch.Tensor,
                             method: str = "quaternion") -> tuple[torch.Tensor, torch.Tensor]:
    """Optimal proper rotation for a centred covariance.

    Parameters
    ----------
    cov : (..., 3, 3) ``S = sum_k x_k y_k^T`` of centred source points x and target points y.
    source_sq, target_sq : (...) ``sum_k |x_k|^2`` and ``sum_k |y_k|^2`` (an upper bound on tr(R S) from them).
    method : ``"quaternion"`` (elementwise QCP, SVD fallback when ill-conditioned) or ``"svd"``.

    Returns
    -------
    rotation (..., 3, 3) with ``y ~ R x``, and ``tr(R S)`` (...), the numerator of the optimal scale, in
    ``cov``'s dtype. The quaternion solve runs in float64 for lower-precision input: its conditioning thresholds
    are set against float64 rounding, and in float32 near-degenerate (nearly collinear) sets passed them with a
    wrong root, aligned points off by up to 1.9 units (the 3x3 solve is a small part of the cost).
    """
    if method == "quaternion" and cov.dtype != torch.float64:
        rotation, trace = rotation_from_covariance(cov.double(), source_sq.double(), target_sq.double(), method)
        return rotation.to(cov.dtype), trace.to(cov.dtype)
    rotation, trace = rotation_component_first(cov.movedim((-2, -1), (0, 1)).contiguous(), source_sq, target_sq,
                                               method)
    return rotation.movedim((0, 1), (-2, -1)), trace


def _point_weights(weights: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
    """(..., K) weights normalised to sum 1 per leading index; ValueError naming the fix otherwise."""
    weights = torch.as_tensor(weights, dtype=source.dtype, device=source.device)
    if weights.shape != source.shape[:-1]:
        raise ValueError(f"weights {tuple(weights.shape)} must be (..., K) = {tuple(source.shape[:-1])}, one per point")
    if bool((weights < 0).any()) or not bool((weights.sum(-1) > 0).all()):
        raise ValueError("weights must be non-negative with a positive sum per point set; drop all-zero sets")
    return weights / weights.sum(-1, keepdim=True)


def similarity_transform(source: torch.Tensor, target: torch.Tensor, method: str = "quaternion",
                         weights: torch.Tensor | None = None) -> SimilarityTransform:
    """Similarity transform aligning source (..., K, 3) onto target (..., K, 3) in (weighted) least squares.

    ``weights`` (..., K): per-point weights of Umeyama's weighted problem; None weighs every point alike.
    A source whose points all coincide gets scale 0 (it is mapped onto the target's centroid).
    """
    if source.shape != target.shape or source.shape[-1] != 3:
        raise ValueError(f"source {tuple(source.shape)} and target {tuple(target.shape)} must both be (..., K, 3)")
    if weights is None:
        mu_s, mu_t = source.mean(-2), target.mean(-2)
        xs, yt = source - mu_s[..., None, :], target - mu_t[..., None, :]
        var_s, var_t = xs.square().sum((-1, -2)), yt.square().sum((-1, -2))
        cov = xs.transpose(-1, -2) @ yt
    else:
        w = _point_weights(weights, source)[..., None]  # (..., K, 1)
        mu_s, mu_t = (w * source).sum(-2), (w * target).sum(-2)
        xs, yt = source - mu_s[..., None, :], target - mu_t[..., None, :]
        var_s, var_t = (w * xs.square()).sum((-1, -2)), (w * yt.square()).sum((-1, -2))
        cov = (w * xs).transpose(-1, -2) @ yt
    rotation, trace = rotation_from_covariance(cov, var_s, var_t, method)
    scale = torch.where(var_s > 0, trace / var_s.clamp_min(torch.finfo(source.dtype).tiny), torch.zeros_like(trace))
    translation = mu_t - scale[..., None] * (mu_s[..., None, :] @ rotation.transpose(-1, -2))[..., 0, :]
    return SimilarityTransform(rotation, scale, translation)


def similarity_align(source: torch.Tensor, target: torch.Tensor, method: str = "quaternion") -> torch.Tensor:
    """(..., K, 3) source aligned onto (..., K, 3) target by similarity Procrustes (per leading index)."""
    return similarity_transform(source, target, method).apply(source)
