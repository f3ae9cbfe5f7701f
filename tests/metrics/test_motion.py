"""DTW-JPE / DTW-PA-JPE against a brute-force reference (plain loops, numpy SVD per frame pair, full DP table).

Also, written to pin behaviours that mutation testing found unchecked: shape checks naming both shapes, the
quaternion solver's SVD fallback (collinear sets at any scale, never for generic ones, lines onto themselves
exactly), codebook statistics of an empty token set, the native kernels' float64 inputs and integer paths, and
SOKE's body keypoint layout (iBUG landmark names, the SMPL-X vertex check).
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from m3t.body.similarity import rotation_from_covariance, similarity_align
from m3t.metrics.dtw import dtw, dtw_batch, jpe_distance_matrix
from m3t.metrics.motion import (
    MotionMetricsConfig,
    evaluate_pairs,
    sequence_metrics,
    summarise,
)
from m3t.metrics.procrustes import pa_distance_matrix

# ---------------------------------------------------------------- brute-force reference (SOKE's definitions)


def ref_align(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Classic compute_similarity_transform: x (K, 3) aligned onto y (K, 3)."""
    mu1, mu2 = x.mean(0), y.mean(0)
    x1, x2 = (x - mu1).T, (y - mu2).T
    k = x1 @ x2.T
    u, _, vh = np.linalg.svd(k)
    v = vh.T
    z = np.eye(3)
    z[-1, -1] = np.sign(np.linalg.det(u @ v.T))
    r = v @ z @ u.T
    scale = np.trace(r @ k) / (x1 ** 2).sum()
    return (scale * r @ x.T).T + (mu2 - scale * r @ mu1)


def ref_jpe(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.linalg.norm((x - x[0]) - (y - y[0]), axis=-1).mean())


def ref_pa(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.linalg.norm(ref_align(x, y) - y, axis=-1).mean())


def ref_dtw(cost: np.ndarray) -> tuple[float, list[tuple[int, int]]]:
    t1, t2 = cost.shape
    d = np.full((t1, t2), np.inf)
    for i in range(t1):
        for j in range(t2):
            if i == 0 and j == 0:
                d[i, j] = cost[0, 0]
                continue
            up, left = d[i - 1, j] if i else np.inf, d[i, j - 1] if j else np.inf
            best = min(up, left, d[i - 1, j - 1] if i and j else np.inf)
            d[i, j] = cost[i, j] + best
    i, j = t1 - 1, t2 - 1
    path = [(i, j)]
    while (i, j) != (0, 0):
        if i == 0:
            j -= 1
        elif j == 0:
            i -= 1
        elif d[i - 1, j - 1] <= min(d[i - 1, j], d[i, j - 1]):
            i, j = i - 1, j - 1
        elif d[i - 1, j] <= d[i, j - 1]:
            i -= 1
        else:
            j -= 1
        path.append((i, j))
    return float(d[-1, -1]), path[::-1]


def ref_sequence(pred: np.ndarray, gt: np.ndarray, dist) -> tuple[float, list[tuple[int, int]]]:
    return ref_dtw(np.array([[dist(p, g) for g in gt] for p in pred]))


# ---------------------------------------------------------------- helpers


def motion(rng: np.random.Generator, frames: int, points: int) -> np.ndarray:
    """(T, K, 3) a random rest shape (~10 cm) that drifts and wobbles smoothly, in metres."""
    rest = rng.normal(scale=0.1, size=(points, 3))
    drift = np.cumsum(rng.normal(scale=0.01, size=(frames, points, 3)), axis=0)
    return rest + drift


def regions(rng: np.random.Generator, frames: int) -> dict[str, np.ndarray]:
    return {"body": motion(rng, frames, 12), "left_hand": motion(rng, frames, 21),
            "right_hand": motion(rng, frames, 21)}


def similarity_copy(x: np.ndarray, rng: np.random.Generator, per_frame: bool = True) -> np.ndarray:
    """(T, K, 3) every frame rotated, scaled and translated (independently per frame if per_frame)."""
    n = len(x) if per_frame else 1
    rot = Rotation.random(n, random_state=int(rng.integers(1 << 30))).as_matrix()
    scale = rng.uniform(0.5, 2.0, size=(n, 1, 1))
    shift = rng.normal(size=(n, 1, 3))
    return scale * np.einsum("tab,tkb->tka", rot, x) + shift


T = torch.as_tensor
LENGTHS = [(1, 1), (1, 6), (5, 1), (7, 7), (9, 4), (6, 13)]

# ---------------------------------------------------------------- DTW


@pytest.mark.parametrize("integer_costs", [False, True])
def test_dtw_matches_reference_cost_and_path(integer_costs):
    rng = np.random.default_rng(0)
    costs = [rng.integers(0, 3, size=s).astype(float) if integer_costs else rng.random(s) for s in LENGTHS]
    for cost, res in zip(costs, dtw_batch(costs)):  # integer costs: many ties, exercises the tie rule
        raw, path = ref_dtw(cost)
        assert res.cost_raw == pytest.approx(raw, abs=1e-12)
        assert [tuple(p) for p in res.path] == path


@pytest.mark.parametrize("shape", LENGTHS)
def test_path_is_monotone_unit_steps_from_start_to_end(shape):
    res = dtw(np.random.default_rng(1).random(shape))
    assert tuple(res.path[0]) == (0, 0) and tuple(res.path[-1]) == (shape[0] - 1, shape[1] - 1)
    steps = {tuple(s) for s in np.diff(res.path, axis=0)}
    assert steps <= {(1, 0), (0, 1), (1, 1)}
    assert res.path_length == len(res.path) >= max(shape)
    assert res.cost_pathnorm == pytest.approx(res.cost_raw / res.path_length)


def test_dtw_rejects_bad_costs():
    with pytest.raises(ValueError, match="non-empty"):
        dtw(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        dtw(np.array([[0.0, np.nan]]))


# ---------------------------------------------------------------- cost matrices and Procrustes


@pytest.mark.parametrize("method", ["quaternion", "svd"])
@pytest.mark.parametrize("points", [3, 12, 21])
def test_distance_matrices_match_reference(method, points):
    rng = np.random.default_rng(points)
    pred, gt = motion(rng, 7, points), motion(rng, 5, points)
    jpe = jpe_distance_matrix(T(pred), T(gt)).numpy()
    pa = pa_distance_matrix(T(pred), T(gt), method, chunk_pairs=8).numpy()  # several chunks
    np.testing.assert_allclose(jpe, [[ref_jpe(p, g) for g in gt] for p in pred], atol=1e-10, rtol=0)
    np.testing.assert_allclose(pa, [[ref_pa(p, g) for g in gt] for p in pred], atol=1e-10, rtol=0)


def test_quaternion_solver_matches_svd_including_degenerate_points():
    rng = np.random.default_rng(3)
    x, y = T(rng.normal(size=(500, 12, 3))), T(rng.normal(size=(500, 12, 3)))
    line = T(np.linspace(0, 1, 12)[:, None] * np.array([1.0, 2.0, 3.0]))
    x[0] = line  # collinear source: the eigenvector is not unique -> SVD fallback
    x[1] = line + 1e-9 * T(rng.normal(size=(12, 3)))
    fast, slow = similarity_align(x, y, "quaternion"), similarity_align(x, y, "svd")
    assert float((fast - slow).abs().max()) < 1e-9
    np.testing.assert_allclose(fast[5].numpy(), ref_align(x[5].numpy(), y[5].numpy()), atol=1e-10)
    rotation, _ = rotation_from_covariance(x.transpose(1, 2) @ y, x.square().sum((1, 2)), y.square().sum((1, 2)))
    assert torch.allclose(torch.linalg.det(rotation), torch.ones(500, dtype=torch.float64))


def test_quaternion_solver_matches_svd_in_float32_on_collinear_points():
    rng = np.random.default_rng(5)
    direction = rng.normal(size=(400, 1, 3))
    x = np.linspace(0, 1, 10)[None, :, None] * direction + 1e-4 * rng.normal(size=(400, 10, 3))  # nearly collinear
    y = rng.normal(size=(400, 10, 3))
    fast = similarity_align(torch.tensor(x, dtype=torch.float32), torch.tensor(y, dtype=torch.float32), "quaternion")
    slow = similarity_align(torch.tensor(x, dtype=torch.float32), torch.tensor(y, dtype=torch.float32), "svd")
    assert fast.dtype == torch.float32
    assert float((fast - slow).abs().max()) < 1e-4  # float32 thresholds let wrong roots through: errors up to ~2


def test_procrustes_of_a_similarity_copy_is_zero():
    rng = np.random.default_rng(4)
    x = motion(rng, 6, 21)
    moved = similarity_copy(x, rng)
    np.testing.assert_allclose(similarity_align(T(moved), T(x)).numpy(), x, atol=1e-9)
    assert float(pa_distance_matrix(T(moved), T(x)).diagonal().abs().max()) < 1e-9


def test_collapsed_frame_gets_scale_zero_not_nan():
    rng = np.random.default_rng(5)
    gt = motion(rng, 2, 12)
    pred = np.repeat(np.full((1, 1, 3), 0.3), 12, axis=1)  # every point at one spot
    pa = pa_distance_matrix(T(pred), T(gt)).numpy()
    expected = [np.linalg.norm(g - g.mean(0), axis=-1).mean() for g in gt]
    np.testing.assert_allclose(pa[0], expected, atol=1e-12)


def test_unknown_method_is_rejected():
    with pytest.raises(ValueError, match="unknown Procrustes method"):
        pa_distance_matrix(torch.zeros(2, 3, 3, dtype=torch.float64), torch.ones(2, 3, 3, dtype=torch.float64), "eig")


# ---------------------------------------------------------------- sequence metrics


@pytest.mark.parametrize("t1,t2", [(1, 1), (1, 8), (9, 1), (12, 7), (6, 15)])
def test_sequence_metrics_match_reference(t1, t2):
    rng = np.random.default_rng(t1 * 100 + t2)
    pred, gt = regions(rng, t1), regions(rng, t2)
    out = sequence_metrics(pred, gt)
    for region in pred:
        for stem, dist in ((f"dtw_jpe_{region}", ref_jpe), (f"dtw_pa_jpe_{region}", ref_pa)):
            raw, path = ref_sequence(pred[region], gt[region], dist)
            assert out[f"{stem}_m"] == pytest.approx(raw, abs=1e-6, rel=0)
            assert out[f"{stem}_pathnorm_m"] == pytest.approx(raw / len(path), abs=1e-6, rel=0)
    for stem in ("dtw_jpe", "dtw_pa_jpe"):
        for suffix in ("_m", "_pathnorm_m"):
            left, right = out[f"{stem}_left_hand{suffix}"], out[f"{stem}_right_hand{suffix}"]
            assert out[f"{stem}_hand{suffix}"] == pytest.approx((left + right) / 2)


def test_face_is_named_vpe_and_procrustes_regions_are_configurable():
    rng = np.random.default_rng(6)
    pred, gt = {"face": motion(rng, 4, 30)}, {"face": motion(rng, 5, 30)}
    assert set(sequence_metrics(pred, gt)) == {"dtw_vpe_face_m", "dtw_vpe_face_pathnorm_m"}
    out = sequence_metrics(pred, gt, MotionMetricsConfig(procrustes_regions=("face",)))
    assert out["dtw_pa_vpe_face_m"] == pytest.approx(ref_sequence(pred["face"], gt["face"], ref_pa)[0], abs=1e-6)


def test_dtw_of_a_sequence_with_itself_is_zero():
    seq = regions(np.random.default_rng(7), 20)
    out = sequence_metrics(seq, seq)
    assert all(abs(v) < 1e-9 for v in out.values()), out


def test_jpe_is_symmetric_pa_is_invariant_to_similarity_of_the_prediction():
    rng = np.random.default_rng(8)
    a, b = regions(rng, 11), regions(rng, 8)
    ab, ba = sequence_metrics(a, b), sequence_metrics(b, a)
    for name in ab:
        if name.startswith("dtw_jpe"):
            assert ab[name] == pytest.approx(ba[name], abs=1e-12)
    # PA aligns pred onto gt, so swapping sides is not symmetric; what holds: any per-frame similarity of the
    # prediction and any per-frame rigid motion of the ground truth leave it unchanged.
    moved_pred = {k: similarity_copy(v, rng) for k, v in a.items()}
    rigid_gt = {}
    for k, v in b.items():
        rot = Rotation.random(len(v), random_state=1).as_matrix()
        rigid_gt[k] = np.einsum("tab,tkb->tka", rot, v) + rng.normal(size=(len(v), 1, 3))
    out = sequence_metrics(moved_pred, rigid_gt)
    for name in ab:
        if name.startswith("dtw_pa"):
            assert out[name] == pytest.approx(ab[name], abs=1e-9)


def test_evaluate_pairs_batches_but_keeps_order_and_values():
    rng = np.random.default_rng(9)
    pairs = [(regions(rng, t1), regions(rng, t2)) for t1, t2 in [(9, 3), (2, 2), (14, 11), (1, 5), (6, 6)]]
    batched = evaluate_pairs(pairs, config=MotionMetricsConfig(batch_pairs=2))
    for (pred, gt), got in zip(pairs, batched):
        alone = sequence_metrics(pred, gt)
        assert got.keys() == alone.keys()
        assert all(got[k] == pytest.approx(alone[k], abs=1e-12) for k in got)
    summary = summarise(batched)
    assert summary["dtw_jpe_body_m"] == pytest.approx(np.mean([m["dtw_jpe_body_m"] for m in batched]))


def test_torch_inputs_are_accepted():
    rng = np.random.default_rng(10)
    pred, gt = regions(rng, 4), regions(rng, 5)
    as_torch = sequence_metrics({k: torch.as_tensor(v, dtype=torch.float32) for k, v in pred.items()}, gt)
    assert as_torch["dtw_jpe_body_m"] == pytest.approx(sequence_metrics(pred, gt)["dtw_jpe_body_m"], abs=1e-6)


@pytest.mark.parametrize("bad,message", [
    ({"body": np.zeros((0, 12, 3))}, "empty sequence"),
    ({"body": np.zeros((4, 11, 3))}, "different point counts"),
    ({"body": np.zeros((4, 12))}, r"expected \(T, K, 3\)"),
    ({"body": np.full((4, 12, 3), np.inf)}, "non-finite"),
    ({"hand": np.zeros((4, 12, 3))}, "regions differ"),
    ({}, "regions differ"),
])
def test_bad_inputs_raise_naming_region_and_shape(bad, message):
    good = {"body": np.zeros((4, 12, 3))}
    with pytest.raises(ValueError, match=message):
        sequence_metrics(bad, good)


def test_summarise_rejects_empty_and_mismatched():
    with pytest.raises(ValueError, match="no per-pair"):
        summarise([])
    with pytest.raises(ValueError, match="pair 1"):
        summarise([{"a": 1.0}, {"b": 1.0}])


def test_zero_weights_drop_points_and_negative_or_all_zero_weights_are_refused():
    """Umeyama's weighted problem: a point of weight 0 must not move the fit (the same transform as without the
    point), a negative weight or an all-zero set is refused."""
    from m3t.body.similarity import similarity_transform

    gen = torch.Generator().manual_seed(3)
    source = torch.randn(6, 3, generator=gen, dtype=torch.float64)
    rotation = torch.as_tensor(Rotation.from_euler("xyz", [0.3, -0.2, 0.5]).as_matrix())
    target = 1.7 * source @ rotation.T + torch.tensor([0.1, -0.4, 0.2], dtype=torch.float64)
    target[5] += 3.0  # an outlier: weight 0 must ignore it
    weights = torch.tensor([1.0, 2.0, 1.0, 0.5, 1.0, 0.0], dtype=torch.float64)
    full = similarity_transform(source, target, weights=weights)
    dropped = similarity_transform(source[:5], target[:5], weights=weights[:5])
    for field in ("rotation", "scale", "translation"):
        assert torch.allclose(getattr(full, field), getattr(dropped, field), atol=1e-9)
    assert torch.allclose(full.rotation, rotation, atol=1e-9) and float(full.scale) == pytest.approx(1.7)
    for bad in (torch.tensor([1.0, 1, 1, 1, 1, -0.1], dtype=torch.float64), torch.zeros(6, dtype=torch.float64)):
        with pytest.raises(ValueError, match="non-negative with a positive sum"):
            similarity_transform(source, target, weights=bad)


# ---------------------------------------------------------------- input checks, degenerate frames, fast path


def test_pa_distance_matrix_names_both_shapes_when_they_do_not_pair():
    for pred, gt in (((4, 5, 3), (6, 4, 3)), ((4, 5, 2), (6, 5, 2)), ((5, 3), (6, 5, 3))):
        with pytest.raises(ValueError) as err:
            pa_distance_matrix(torch.zeros(pred, dtype=torch.float64), torch.zeros(gt, dtype=torch.float64))
        assert str(err.value) == f"pred {pred} and gt {gt} must be (T1, K, 3) and (T2, K, 3)"


def test_batched_pa_distance_matrices_refuse_pairs_that_do_not_match():
    from m3t.metrics.procrustes import pa_distance_matrices

    z = torch.zeros
    for pred, gt in (((2, 4, 5, 3), (3, 6, 5, 3)), ((2, 4, 5, 3), (2, 6, 4, 3)), ((2, 4, 5, 2), (2, 6, 5, 2)),
                     ((4, 5, 3), (6, 5, 3))):
        with pytest.raises(ValueError) as err:
            pa_distance_matrices(z(pred, dtype=torch.float64), z(gt, dtype=torch.float64))
        assert str(err.value) == f"pred {pred} and gt {gt} must be (B, T1, K, 3) and (B, T2, K, 3)"
    rng = np.random.default_rng(11)
    pred, gt = np.stack([motion(rng, 3, 6) for _ in range(2)]), np.stack([motion(rng, 4, 6) for _ in range(2)])
    both = pa_distance_matrices(T(pred), T(gt)).numpy()
    for b in range(2):
        np.testing.assert_allclose(both[b], [[ref_pa(p, g) for g in gt[b]] for p in pred[b]], atol=1e-10, rtol=0)


@pytest.mark.parametrize("size", [1.0, 0.01, 1000.0])
def test_quaternion_solver_falls_back_on_collinear_points_at_any_scale(size):
    """Body parts are centimetres to metres (or millimetres, in other units): a collinear (finger-like) set of small
    extent is ill-conditioned as much as a long one, and must be re-solved like it."""
    rng = np.random.default_rng(12)
    direction = rng.normal(size=(300, 1, 3))
    x = size * np.linspace(-0.5, 0.5, 8)[None, :, None] * direction + size * rng.normal(size=(300, 1, 3))
    y = size * rng.normal(size=(300, 8, 3))
    y[:100] = x[:100]  # onto itself: a double top root
    fast, slow = similarity_align(T(x), T(y), "quaternion"), similarity_align(T(x), T(y), "svd")
    np.testing.assert_allclose(fast.numpy(), slow.numpy(), atol=1e-6 * size, rtol=0)
    np.testing.assert_allclose(fast[:100].numpy(), x[:100], atol=1e-6 * size, rtol=0)
    np.testing.assert_allclose(fast[150].numpy(), ref_align(x[150], y[150]), atol=1e-6 * size, rtol=0)


def test_quaternion_solver_solves_well_conditioned_frames_without_the_svd(monkeypatch):
    """The SVD is the slow fallback (5x or worse on CPU): generic point sets never reach it, in metres or in
    millimetres; collinear ones do."""
    from m3t.body import similarity

    solved = []
    svd = similarity._rotation_svd

    def counting(cov):
        solved.append(cov.shape[:-2].numel())
        return svd(cov)

    monkeypatch.setattr(similarity, "_rotation_svd", counting)
    rng = np.random.default_rng(13)
    pred, gt = motion(rng, 9, 12), motion(rng, 7, 12)
    pa = pa_distance_matrix(T(pred), T(gt)).numpy()
    moved = similarity_copy(pred, rng)
    np.testing.assert_allclose(pa_distance_matrix(T(moved), T(pred)).numpy().diagonal(), 0.0, atol=1e-9)
    np.testing.assert_allclose(pa_distance_matrix(T(1000 * pred), T(1000 * gt)).numpy(), 1000 * pa, atol=1e-7, rtol=0)
    assert solved == []
    np.testing.assert_allclose(pa, [[ref_pa(p, g) for g in gt] for p in pred], atol=1e-10, rtol=0)
    line = np.linspace(0, 1, 12)[:, None] * np.array([0.1, 0.2, 0.3])
    pa_distance_matrix(T(np.stack([line, pred[0]])), T(np.stack([line, gt[0]])))
    assert sum(solved) >= 1  # the line onto itself


# ---------------------------------------------------------------- codebook statistics


def test_codebook_stats_of_no_tokens_are_all_zero_and_of_uniform_use_are_the_codebook_size():
    from m3t.metrics.codebook import codebook_stats, token_counts

    assert codebook_stats(np.zeros(8, dtype=np.int64)) == {"utilisation_pct": 0.0, "count_sd": 0.0,
                                                           "perplexity": 0.0, "perplexity_per_code": 0.0,
                                                           "tokens": 0.0, "tokens_per_code": 0.0}
    stats = codebook_stats(token_counts([np.array([0, 1, 1, 3]), np.array([[3, 3], [1, 0]])], 4))
    assert stats["utilisation_pct"] == 75.0 and stats["tokens"] == 8.0
    assert stats["count_sd"] == pytest.approx(np.std([2, 3, 0, 3]))
    probs = np.array([2, 3, 3]) / 8
    assert stats["perplexity"] == pytest.approx(np.exp(-(probs * np.log(probs)).sum()))
    assert stats["perplexity_per_code"] == pytest.approx(stats["perplexity"] / 4) and stats["tokens_per_code"] == 2.0
    # a skewed histogram: every code used (100 %), but perplexity / K tells it from a uniform one
    skewed = codebook_stats(np.array([97, 1, 1, 1]))
    assert skewed["utilisation_pct"] == 100.0 and skewed["perplexity_per_code"] < 0.35
    assert codebook_stats(np.full(4, 25))["perplexity_per_code"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match=r"token index out of range \[0, 4\): \[0, 4\]"):
        token_counts([np.array([0, 4])], 4)


# ---------------------------------------------------------------- native kernels: inputs and paths


def test_kernels_read_float32_points_as_float64():
    """float32 input (tensors from a model) is widened before any arithmetic, so the costs equal those of the
    same values given as float64 (root-relative differences of far-apart float32 points are not float32-exact)."""
    from m3t.metrics import kernels

    rng = np.random.default_rng(14)
    pred = (motion(rng, 5, 6) + np.array([100.0, -50.0, 3.0])).astype(np.float32)
    pred[:, 0] = np.array([0.001, 250.0, -0.3], dtype=np.float32)  # the root far from the other points
    gt = motion(rng, 4, 6)
    wide = pred.astype(np.float64)
    np.testing.assert_array_equal(kernels.jpe_cost_matrix(pred, gt), kernels.jpe_cost_matrix(wide, gt))
    np.testing.assert_array_equal(kernels.pa_cost_matrix(pred, gt), kernels.pa_cost_matrix(wide, gt))
    jobs = [kernels.CostJob(pred, gt, False), kernels.CostJob(wide, gt, False)]
    narrow, double = kernels.dtw_jobs(jobs, threads=1)
    assert narrow.cost_raw == double.cost_raw


def test_kernel_dtw_paths_are_integer_indices_into_the_cost_matrix():
    from m3t.metrics import kernels

    rng = np.random.default_rng(15)
    costs = [rng.random((5, 3)), rng.random((1, 4)), rng.random((6, 6))]
    for cost, res in zip(costs, kernels.dtw_costs(costs, threads=1), strict=True):
        assert res.path.dtype == np.int64 and res.path.shape == (res.path_length, 2)
        assert cost[res.path[:, 0], res.path[:, 1]].sum() == pytest.approx(res.cost_raw, abs=1e-12)
        assert tuple(res.path[0]) == (0, 0) and tuple(res.path[-1]) == (cost.shape[0] - 1, cost.shape[1] - 1)


# ---------------------------------------------------------------- SOKE's keypoint layout


def test_soke_keypoints_name_the_face_landmarks_by_their_ibug_numbers(fx):
    from m3t.metrics.soke import soke_keypoints

    body = soke_keypoints(fx)["body"]
    landmarks = [n for n in body.names if n.startswith("ibug_")]
    assert landmarks == [f"ibug_{k}" for k in range(18, 69)]  # iBUG 18-68: 51 static landmarks
    assert body.names[-51:] == tuple(landmarks)
    np.testing.assert_array_equal(body.index[-51:], fx.data.landmark_vertices)
    assert (body.kind[-51:] == 0).all() and body.kind.dtype == np.int64 and body.index.dtype == np.int64


def test_soke_keypoints_refuse_a_model_without_smplx_vertex_ids(fx):
    """A SMPL-FX built from a smaller SMPL-X mesh than v1.1's lacks the vertices SOKE's points sit on (here its
    landmark correspondence still resolves, so the check of SOKE's own vertex points is the one that speaks)."""
    import copy
    import dataclasses

    from m3t.metrics.soke import SokeModeError, soke_keypoints

    small = copy.copy(fx)
    small.data = dataclasses.replace(fx.data, num_smplx_vertices=9929)
    small.correspondence = fx.correspondence
    with pytest.raises(SokeModeError) as err:
        soke_keypoints(small)
    assert str(err.value) == ("SMPL-X vertex points ['reye'] lie beyond the model's 9929 SMPL-X "
                              "vertices; build SMPL-FX from SMPLX_NEUTRAL.npz of the SMPL-X v1.1 download")


def test_collinear_frames_align_onto_themselves_exactly_in_both_solvers():
    """A line onto itself has a double top root; Newton could stall just below it with a tiny quartic residual and
    the right eigenvector, and the scale then came out up to 2e-5 off (torch) or the PA cost ~1e-7 (kernel).
    The eigenvector's Rayleigh quotient exposes the stall, and such frames go to the fallback solver."""
    from m3t.metrics import kernels

    rng = np.random.default_rng(16)
    for points in (8, 21):
        line = (np.linspace(-0.5, 0.5, points)[None, :, None] * rng.normal(size=(120, 1, 3))
                + rng.normal(size=(120, 1, 3)))
        np.testing.assert_allclose(similarity_align(T(line), T(line)).numpy(), line, atol=1e-12, rtol=0)
        np.testing.assert_allclose(pa_distance_matrix(T(line), T(line)).numpy().diagonal(), 0.0, atol=1e-12)
        np.testing.assert_allclose(kernels.pa_cost_matrix(line, line).diagonal(), 0.0, atol=1e-12)
        # ... and the cost between different lines is the SVD's
        np.testing.assert_allclose(kernels.pa_cost_matrix(line[:6], line[6:12]),
                                   [[ref_pa(p, g) for g in line[6:12]] for p in line[:6]], atol=1e-9, rtol=0)


def test_a_bad_side_of_a_pair_is_named_with_its_pair_region_and_shape():
    good = {"body": np.zeros((4, 12, 3))}
    wrong = {"body": np.zeros((4, 12, 2))}
    message = r"^pair 1, region 'body', prediction: shape \(4, 12, 2\), expected \(T, K, 3\) points in metres$"
    with pytest.raises(ValueError, match=message):
        evaluate_pairs([(good, good), (wrong, good)])
    with pytest.raises(ValueError, match=r"^pair 0, region 'body', ground truth: shape \(4, 12, 2\), expected"):
        evaluate_pairs([(good, wrong)])
    with pytest.raises(ValueError, match=r"^pair 0, region 'body', prediction: empty sequence of shape \(0, 12, 3\)"):
        evaluate_pairs([({"body": np.zeros((0, 12, 3))}, good)])


def test_cost_kernels_name_the_job_and_both_shapes_of_a_malformed_pair():
    from m3t.metrics import kernels

    pred, gt = np.zeros((3, 5, 3)), np.zeros((4, 6, 3))
    message = r"^job 1: pred \(3, 5, 3\) and gt \(4, 6, 3\) must be non-empty \(T1, K, 3\) and \(T2, K, 3\)$"
    with pytest.raises(ValueError, match=message):
        kernels.dtw_jobs([kernels.CostJob(gt, gt, False), kernels.CostJob(pred, gt, True)], threads=1)
    with pytest.raises(ValueError, match=r"^job 0: pred \(0, 5, 3\) and gt \(4, 5, 3\) must be non-empty"):
        kernels.pa_cost_matrix(np.zeros((0, 5, 3)), np.zeros((4, 5, 3)))


def test_slt_scores_chinese_by_character_and_every_other_language_by_word():
    from m3t.metrics.text import slt_unit

    assert [slt_unit(lang) for lang in ("zh", "CSL", "CSL-SYN")] == ["char"] * 3
    assert [slt_unit(lang) for lang in ("de", "en", "DGS")] == ["word"] * 3


def test_bleu_on_jieba_words_counts_each_word_as_one_token():
    """A jieba word such as ``C++`` is one token: 5 of 6 words match, every higher order loses one n-gram."""
    from m3t.metrics.text import bleu4

    hyp, ref = "C++ 明天 北方 下雨 南方 晴朗", "C 明天 北方 下雨 南方 晴朗"
    assert bleu4([hyp], [ref], method="zh") == pytest.approx(100 * (5 / 6 * 4 / 5 * 3 / 4 * 2 / 3) ** 0.25)
    assert bleu4([ref], [ref], method="zh") == pytest.approx(100.0)


def _accumulated(c: np.ndarray) -> np.ndarray:
    """The DTW table of ``c`` by the textbook recursion, one cell at a time, with an infinite border: cell
    (i + 1, j + 1) is the cheapest cost of aligning frames 0..i with 0..j."""
    t1, t2 = c.shape
    acc = np.full((t1 + 1, t2 + 1), np.inf)
    acc[0, 0] = 0.0
    for i in range(t1):
        for j in range(t2):
            acc[i + 1, j + 1] = c[i, j] + min(acc[i, j], acc[i, j + 1], acc[i + 1, j])
    return acc


def test_every_path_is_a_monotone_walk_whose_costs_add_up_to_the_optimal_cost():
    """With continuous random costs (no ties) the optimal warping path is unique: every batched path must start at
    (0, 0), end at (T1 - 1, T2 - 1), move by one of the three DTW steps, and its costs must add up to the DP's
    optimum; two-row and two-column matrices included (their first row or column is where a step up or left is
    last possible), and signed costs (any finite matrix is accepted; with distances a step along the first row or
    column is never cheaper than the diagonal, with signed costs it can be)."""
    rng = np.random.default_rng(3)
    shapes = [(2, 5), (5, 2), (2, 2), (3, 7), (7, 3), (6, 6), (1, 4), (4, 1)]
    costs = [rng.uniform(low, 1.0, size=s) for s in shapes for low in (0.1, -1.0) for _ in range(6)]
    for c, result in zip(costs, dtw_batch(costs)):
        t1, t2 = c.shape
        acc = _accumulated(c)
        path = result.path
        assert path[0].tolist() == [0, 0] and path[-1].tolist() == [t1 - 1, t2 - 1], c.shape
        assert {tuple(s) for s in np.diff(path, axis=0).tolist()} <= {(1, 1), (1, 0), (0, 1)}, c.shape
        assert result.path_length == len(path)
        assert result.cost_raw == pytest.approx(acc[-1, -1], rel=1e-12)
        assert c[path[:, 0], path[:, 1]].sum() == pytest.approx(acc[-1, -1], rel=1e-12), (c.shape, path.tolist())




def test_tied_steps_prefer_the_diagonal_then_the_previous_row_then_the_previous_column():
    """Integer costs tie often; the documented rule (diagonal, then i - 1, then j - 1) decides every tie, checked
    against a plain walk back through the accumulated table."""
    rng = np.random.default_rng(5)
    costs = [rng.integers(0, 3, size=(int(rng.integers(1, 7)), int(rng.integers(1, 7)))).astype(float)
             for _ in range(60)]
    for c, result in zip(costs, dtw_batch(costs)):
        t1, t2 = c.shape
        acc = _accumulated(c)
        i, j, walk = t1 - 1, t2 - 1, [(t1 - 1, t2 - 1)]
        while (i, j) != (0, 0):
            diag, up, left = acc[i, j], acc[i, j + 1], acc[i + 1, j]  # cells (i-1, j-1), (i-1, j), (i, j-1)
            if diag <= min(up, left):
                i, j = i - 1, j - 1
            elif up <= left:
                i -= 1
            else:
                j -= 1
            walk.append((i, j))
        assert [tuple(s) for s in result.path.tolist()] == walk[::-1], c.tolist()


@pytest.mark.parametrize("settings, message", [
    ({"mode": "soke"}, ("motion metric mode 'soke' unknown; use 'm3t' (neck-rooted body, this project's tables) or "
                        "'soke_exact' (SOKE's pelvis-rooted body, needs SMPL-FX)")),
    ({"backend": "cupy"}, ("motion metric backend 'cupy' unknown; use 'numba' (fused CPU kernels) or 'torch' (cost "
                           "matrices on any torch device)")),
    ({"device": "cuda:1"}, "motion metric device 'cuda:1' needs backend 'torch'; the numba kernels run on the CPU"),
])
def test_motion_metric_settings_name_the_bad_value_and_the_choices(settings, message):
    from m3t.metrics.motion import MotionMetricsConfig

    with pytest.raises(ValueError) as err:
        MotionMetricsConfig(**settings)
    assert str(err.value) == message
    for mode in ("m3t", "soke_exact"):  # every documented choice is accepted; any torch device with backend torch
        MotionMetricsConfig(mode=mode, backend="torch", device="cuda:1")
        MotionMetricsConfig(mode=mode, backend="numba", device="cpu")


def test_torch_backend_workers_compute_cost_matrices_on_that_many_threads_with_the_same_results(monkeypatch):
    import threading

    from m3t.metrics import motion

    rng = np.random.default_rng(4)
    pairs = [(regions(rng, t1), regions(rng, t2)) for t1, t2 in [(5, 7), (6, 4), (3, 3)]]
    reference = motion.evaluate_pairs(pairs, config=motion.MotionMetricsConfig(root_precision="float64"))  # numba
    threads: list[str] = []
    lock = threading.Lock()

    def recorded(fn):
        def wrapper(*args, **kwargs):
            with lock:
                threads.append(threading.current_thread().name)
            return fn(*args, **kwargs)
        return wrapper

    monkeypatch.setattr(motion, "jpe_distance_matrix", recorded(motion.jpe_distance_matrix))
    monkeypatch.setattr(motion, "pa_distance_matrix", recorded(motion.pa_distance_matrix))
    main = threading.current_thread().name
    for workers in (1, 2, 3):
        threads.clear()
        got = motion.evaluate_pairs(pairs, config=motion.MotionMetricsConfig(backend="torch", workers=workers))
        assert len(threads) == 3 * 2 * 3, "one JPE and one PA matrix per region and pair"
        if workers == 1:
            assert set(threads) == {main}
        else:
            assert main not in threads and 1 <= len(set(threads)) <= workers
        for want, have in zip(reference, got):
            assert have.keys() == want.keys()
            assert all(have[k] == pytest.approx(want[k], abs=1e-9) for k in want)


def test_summarise_names_the_metrics_in_which_a_pair_differs_from_the_first():
    assert summarise([{"a": 1.0, "b": 2.0}, {"a": 3.0, "b": 4.0}]) == {"a": 2.0, "b": 3.0}
    with pytest.raises(ValueError) as info:
        summarise([{"a": 1.0, "b": 2.0}, {"a": 1.0, "b": 2.0}, {"a": 1.0, "c": 3.0}])
    assert str(info.value) == ("pair 2 reports ['b', 'c'] unlike pair 0; evaluate all pairs with the same regions "
                               "and config")
    with pytest.raises(ValueError, match="^no per-pair metrics to summarise; evaluate at least one pair$"):
        summarise([])


def test_regions_may_be_given_as_lists_of_per_frame_tensors_or_arrays():
    """A region is anything that reads as (T, K, 3) floats: one array, one tensor, or a list of per-frame (K, 3)
    tensors or arrays; all give the same metrics."""
    rng = np.random.default_rng(4)
    pred, gt = regions(rng, 6), regions(rng, 5)
    reference = evaluate_pairs([(pred, gt)])[0]
    as_frames = {k: [torch.as_tensor(frame) for frame in v] for k, v in pred.items()}
    as_arrays = {k: list(v) for k, v in gt.items()}
    assert evaluate_pairs([(as_frames, as_arrays)])[0] == pytest.approx(reference, rel=1e-12)


def test_available_cores_counts_the_cores_this_process_may_run_on(monkeypatch):
    from m3t.metrics import kernels

    monkeypatch.setattr(kernels.os, "cpu_count", lambda: 8)
    monkeypatch.setattr(kernels.os, "sched_getaffinity", lambda pid: {0, 3}, raising=False)
    assert kernels.available_cores() == 2  # pinned to two of the eight (taskset, a cluster's cgroup)
    monkeypatch.delattr(kernels.os, "sched_getaffinity")  # systems without affinity masks (macOS, Windows)
    assert kernels.available_cores() == 8
    monkeypatch.setattr(kernels.os, "cpu_count", lambda: None)  # undeterminable
    assert kernels.available_cores() == 1


def test_native_dtw_of_float32_or_integer_cost_matrices_accumulates_in_float64():
    pytest.importorskip("numba")
    from m3t.metrics import kernels

    rng = np.random.default_rng(8)
    cost = rng.uniform(0.0, 1.0, size=(40, 30)) + 1e4  # large: float32 sums would drift by whole units
    exact = kernels.dtw_costs([cost])[0]
    single = kernels.dtw_costs([cost.astype(np.float32)])[0]
    assert single.cost_raw == dtw_batch([cost.astype(np.float32)])[0].cost_raw
    assert single.cost_raw == pytest.approx(exact.cost_raw, abs=0.1) and isinstance(single.cost_raw, float)
    whole = kernels.dtw_costs([np.arange(12).reshape(3, 4)])[0]
    assert isinstance(whole.cost_raw, float) and whole.cost_raw == dtw_batch([np.arange(12).reshape(3, 4)])[0].cost_raw


def test_quaternion_solve_converges_to_the_top_eigenvalue_of_horns_matrix_to_rounding_level():
    """tr(R S) of the optimal rotation is the largest eigenvalue of Horn's matrix; Newton's quadratic convergence
    puts it there to a few ulps on well-conditioned sets (a wrong derivative converges too, but only to ~1e-13)."""
    from m3t.body import similarity

    torch.manual_seed(0)
    x = torch.randn(2000, 10, 3, dtype=torch.float64)
    y = x @ torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64))[0] + 0.01 * torch.randn_like(x)
    x, y = x - x.mean(1, keepdim=True), y - y.mean(1, keepdim=True)
    cov = torch.einsum("nki,nkj->ijn", x, y).contiguous()  # component-first (3, 3, N)
    upper = torch.minimum((x.square().sum((1, 2)) * y.square().sum((1, 2))).sqrt(),
                          (3.0 * cov.square().sum((0, 1))).sqrt()).contiguous()
    horn = torch.stack([torch.stack(row, 0) for row in similarity._horn_matrix(cov)], 0).permute(2, 0, 1)
    top = torch.linalg.eigvalsh(horn)[:, -1]
    rotation, trace, ill = similarity._rotation_quaternion(cov, upper)
    assert not bool(ill.any())
    assert float(((trace - top).abs() / top.abs()).max()) < 1e-14
    assert torch.allclose(torch.einsum("ijn,jin->n", rotation, cov), trace, rtol=1e-12, atol=0)
