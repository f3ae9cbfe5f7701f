"""The numba DTW kernels against the torch/numpy path they replace: same costs, same paths, same metrics.

The references are :func:`m3t.metrics.dtw.jpe_distance_matrix`, :func:`m3t.metrics.procrustes.pa_distance_matrix`
and the numpy anti-diagonal sweep :func:`m3t.metrics.dtw.dtw_batch` (itself checked against brute force in
``tests/metrics/test_motion.py``). Motions are smooth random walks around a rest shape, in metres, with the region
sizes of ``m3t.body.metric_sets`` (body 12 points, hands 21).
"""
from __future__ import annotations

import sys

import numba
import numpy as np
import pytest
import torch

import m3t.metrics
from m3t.metrics import kernels
from m3t.metrics.dtw import accumulate, dtw_batch, jpe_distance_matrix
from m3t.metrics.motion import MotionMetricsConfig, _batched_pa, _validated, evaluate_pairs
from m3t.metrics.procrustes import pa_distance_matrices, pa_distance_matrix
from m3t.runtime import jit

LENGTHS = [(1, 1), (1, 6), (5, 1), (7, 7), (9, 4), (6, 13), (31, 24)]
ROOT_BOUND = 1.5 * 2.0 ** -24  # relative error of a float32 square root of a float64 square
T = torch.as_tensor


def motion(rng: np.random.Generator, frames: int, points: int) -> np.ndarray:
    """(T, K, 3) a rest shape (~10 cm) drifting smoothly, in metres."""
    return rng.normal(scale=0.1, size=(points, 3)) + np.cumsum(rng.normal(scale=0.01, size=(frames, points, 3)), 0)


def regions(rng: np.random.Generator, frames: int, body_points: int = 12) -> dict[str, np.ndarray]:
    return {"body": motion(rng, frames, body_points), "left_hand": motion(rng, frames, 21),
            "right_hand": motion(rng, frames, 21)}


def collinear(rng: np.random.Generator, frames: int, points: int) -> np.ndarray:
    """(T, K, 3) points on one line per frame: Horn's top eigenvalue is double, the QCP's fallback case."""
    direction = rng.normal(size=(frames, 1, 3))
    return rng.normal(size=(frames, points, 1)) * direction + rng.normal(size=(frames, 1, 3))


# ---------------------------------------------------------------- DP and backtrack


@pytest.mark.parametrize("integer_costs", [False, True])
def test_dp_and_backtrack_are_bit_identical_to_the_numpy_sweep(integer_costs):
    rng = np.random.default_rng(0)
    # integer costs: many exact ties, which exercise the tie rule (diagonal, then i-1, then j-1)
    costs = [rng.integers(0, 3, size=s).astype(float) if integer_costs else rng.random(s) for s in LENGTHS]
    costs.append(np.zeros((4, 6)))  # every step ties
    for ours, ref in zip(kernels.dtw_costs(costs), dtw_batch(costs), strict=True):
        assert ours.cost_raw == ref.cost_raw
        np.testing.assert_array_equal(ours.path, ref.path)
        assert ours.path_length == ref.path_length == len(ours.path)


@pytest.mark.parametrize("shape", [(1, 7), (4, 1), (5, 1), (6, 2), (9, 3), (8, 4), (13, 5), (250, 250), (251, 17)])
def test_blocked_sweep_gives_the_numpy_table_bit_for_bit(shape):
    """Rows accumulated four at a time as a wavefront, and one at a time for the rest: the whole table, every
    cell, equals the numpy anti-diagonal sweep; integer costs make ties everywhere."""
    rng = np.random.default_rng(shape[0] * 1000 + shape[1])
    for cost in (rng.random(shape), rng.integers(0, 3, size=shape).astype(float)):
        table, done = cost.copy(), 0
        for i in range(shape[0]):
            done = kernels._sweep_pending(table, i, done)
        assert done == shape[0]
        np.testing.assert_array_equal(table, accumulate(cost[..., None].copy())[..., 0])


def test_dtw_costs_rejects_bad_matrices_naming_them():
    with pytest.raises(ValueError, match="matrix 1 .* non-finite"):
        kernels.dtw_costs([np.ones((2, 2)), np.array([[np.nan]])])
    assert kernels.dtw_costs([]) == [] and kernels.dtw_jobs([]) == []


# ---------------------------------------------------------------- cost matrices


@pytest.mark.parametrize("points,measure", [(12, None), (21, None), (1, None), (20, slice(1, 13))])
@pytest.mark.parametrize("t1,t2", [(1, 1), (1, 9), (8, 1), (17, 11)])
def test_cost_matrices_match_torch(points, measure, t1, t2):
    rng = np.random.default_rng(t1 * 100 + t2 + points)
    pred, gt = motion(rng, t1, points), motion(rng, t2, points)
    jpe = jpe_distance_matrix(T(pred), T(gt), measure=measure).numpy()
    pa = pa_distance_matrix(T(pred), T(gt), measure=measure).numpy()
    np.testing.assert_allclose(kernels.jpe_cost_matrix(pred, gt, measure, "float64"), jpe, rtol=0, atol=1e-12)
    np.testing.assert_allclose(kernels.pa_cost_matrix(pred, gt, measure, "float64"), pa, rtol=0, atol=1e-12)
    # the default float32 root: within its bound of 1.5 x 2^-24 relative
    np.testing.assert_allclose(kernels.jpe_cost_matrix(pred, gt, measure), jpe, rtol=ROOT_BOUND, atol=0)
    np.testing.assert_allclose(kernels.pa_cost_matrix(pred, gt, measure), pa, rtol=ROOT_BOUND, atol=1e-12)


def test_the_float32_root_is_used_by_default_and_the_precision_is_checked():
    rng = np.random.default_rng(11)
    pred, gt = motion(rng, 30, 21), motion(rng, 40, 21)
    single, double = kernels.jpe_cost_matrix(pred, gt), kernels.jpe_cost_matrix(pred, gt, root_precision="float64")
    squares = np.square((pred - pred[:, :1])[:, None] - (gt - gt[:, :1])[None]).sum(-1)  # (T1, T2, K)
    rooted32 = np.sqrt(squares.astype(np.float32)).astype(np.float64).mean(-1)  # the root point counts as 0
    assert np.abs(single - double).max() > 0  # the float32 root rounds differently somewhere
    np.testing.assert_allclose(single, rooted32, rtol=1e-12)  # and is exactly that rounding, length by length
    assert np.abs(single / double - 1).max() < ROOT_BOUND
    pa_single = kernels.pa_cost_matrix(pred, gt)
    assert np.abs(pa_single - kernels.pa_cost_matrix(pred, gt, root_precision="float64")).max() > 0
    for bad in ("float16", "half"):
        with pytest.raises(ValueError, match=f"root precision '{bad}' unknown"):
            kernels.dtw_jobs([kernels.CostJob(pred, gt, False)], root_precision=bad)
    with pytest.raises(ValueError, match="root_precision 'double' unknown"):
        MotionMetricsConfig(root_precision="double")  # type: ignore[arg-type]
    assert MotionMetricsConfig().root == "float32" and MotionMetricsConfig(mode="soke_exact").root == "float64"
    assert MotionMetricsConfig(mode="soke_exact", root_precision="float32").root == "float32"
    assert MotionMetricsConfig(root_precision="float64").root == "float64"


def reference_pa(x: np.ndarray, y: np.ndarray) -> float:
    """Classic compute_similarity_transform by numpy SVD (x (K, 3) onto y (K, 3)), then the mean point distance."""
    xc, yc = x - x.mean(0), y - y.mean(0)
    u, _, vh = np.linalg.svd(xc.T @ yc)
    z = np.diag([1.0, 1.0, np.sign(np.linalg.det(vh.T @ u.T)) or 1.0])
    rot = vh.T @ z @ u.T
    var = (xc ** 2).sum()
    scale = np.trace(rot @ xc.T @ yc) / var if var > 0 else 0.0
    return float(np.linalg.norm(scale * xc @ rot.T - yc, axis=-1).mean())


def test_pa_cost_matches_on_degenerate_frames():
    """Collinear frames (a double top eigenvalue: the ill-conditioned fallback), frames whose points coincide
    (scale 0), planar frames. The kernel matches a per-frame-pair numpy SVD to 1e-8 and the torch solver to 1e-6:
    on rank-1 covariances just above the fallback threshold the QCP eigenvector is slightly off, ~1e-10 in our
    kernel and up to ~2e-7 in torch's, which stops Newton on a whole chunk at once."""
    rng = np.random.default_rng(3)
    pred, gt = collinear(rng, 9, 21), motion(rng, 7, 21)
    pred[2] = 0.3  # every point at one place: no rotation is defined, the scale is 0
    gt[4, :, 2] = 0.0  # planar
    line_gt = collinear(rng, 5, 21)
    for p, g in ((pred, gt), (gt, pred), (pred, line_gt), (pred, pred)):
        ours = kernels.pa_cost_matrix(p, g, root_precision="float64")
        reference = np.array([[reference_pa(x, y) for y in g] for x in p])
        np.testing.assert_allclose(ours, reference, rtol=0, atol=1e-8)
        np.testing.assert_allclose(ours, pa_distance_matrix(T(p), T(g)).numpy(), rtol=0, atol=1e-6)
    assert np.abs(np.diag(ours)).max() < 1e-8  # a line aligned onto itself (was 0.23-0.34 before the fix)


def test_torch_qcp_aligns_collinear_frames_onto_themselves():
    """A double top root of Horn's quartic: Newton used to jump below it and stall (up to 1.06 m here, scale
    2/3); now such frames fall back to the SVD (QCP's eigenvector near a double root stays ~1e-8 off)."""
    line = collinear(np.random.default_rng(3), 9, 21)
    costs = pa_distance_matrix(T(line), T(line)).numpy()
    assert np.abs(np.diag(costs)).max() < 1e-7
    np.testing.assert_allclose(costs, [[reference_pa(x, y) for y in line] for x in line], rtol=0, atol=1e-7)


def test_pa_cost_of_a_similarity_copy_is_zero():
    rng = np.random.default_rng(4)
    gt = motion(rng, 6, 21)
    angle = 0.7
    rot = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    pred = 1.7 * gt @ rot.T + np.array([0.1, -2.0, 0.5])
    assert np.abs(np.diag(kernels.pa_cost_matrix(pred, gt))).max() < 1e-12


# ---------------------------------------------------------------- fused jobs


def test_fused_jobs_match_torch_costs_and_numpy_paths():
    rng = np.random.default_rng(5)
    jobs = []
    for n, (t1, t2) in enumerate(LENGTHS):
        pred, gt = motion(rng, t1, 12 + n), motion(rng, t2, 12 + n)
        jobs += [kernels.CostJob(pred, gt, False), kernels.CostJob(pred, gt, True),
                 kernels.CostJob(pred, gt, n % 2 == 0, slice(1, 6))]
    same = motion(rng, 15, 21)
    jobs += [kernels.CostJob(same, same, False), kernels.CostJob(same, same, True)]
    references = dtw_batch([(pa_distance_matrix if job.procrustes else jpe_distance_matrix)(
        T(job.pred), T(job.gt), measure=job.measure) for job in jobs])
    results = kernels.dtw_jobs(jobs, root_precision="float64")
    for ours, single, ref in zip(results, kernels.dtw_jobs(jobs), references, strict=True):
        assert ours.cost_raw == pytest.approx(ref.cost_raw, abs=1e-10)
        np.testing.assert_array_equal(ours.path, ref.path)
        assert single.cost_raw == pytest.approx(ref.cost_raw, rel=ROOT_BOUND, abs=1e-12)
        np.testing.assert_array_equal(single.path, ref.path)
    jpe_self, pa_self = results[-2:]
    assert jpe_self.cost_raw == 0.0 and pa_self.cost_raw < 1e-10  # a sequence against itself
    np.testing.assert_array_equal(jpe_self.path, np.stack([np.arange(15)] * 2, 1))


def test_jobs_reject_mismatched_points_and_empty_measures():
    rng = np.random.default_rng(6)
    with pytest.raises(ValueError, match="job 1: pred"):
        kernels.dtw_jobs([kernels.CostJob(motion(rng, 3, 4), motion(rng, 2, 4), True),
                          kernels.CostJob(motion(rng, 3, 4), motion(rng, 2, 5), True)])
    with pytest.raises(ValueError, match="job 0: measure"):
        kernels.dtw_jobs([kernels.CostJob(motion(rng, 3, 4), motion(rng, 2, 4), False, slice(3, 3))])


# ---------------------------------------------------------------- evaluate_pairs


@pytest.mark.parametrize("mode", ["m3t", "soke_exact"])
def test_evaluate_pairs_gives_the_same_metrics_with_both_backends(mode):
    rng = np.random.default_rng(7)
    body = 12 if mode == "m3t" else 20  # soke_exact: root, 12 measured points, further fitted points
    pairs = [(regions(rng, t1, body), regions(rng, t2, body)) for t1, t2 in ((1, 5), (23, 19), (12, 30), (8, 8))]
    numba_metrics = evaluate_pairs(pairs, config=MotionMetricsConfig(mode=mode, batch_pairs=3,
                                                                     root_precision="float64"))
    single_metrics = evaluate_pairs(pairs, config=MotionMetricsConfig(mode=mode, batch_pairs=3))
    torch_metrics = evaluate_pairs(pairs, config=MotionMetricsConfig(mode=mode, backend="torch", workers=2))
    for ours, single, ref in zip(numba_metrics, single_metrics, torch_metrics, strict=True):
        assert ours.keys() == ref.keys() == single.keys() and "dtw_pa_jpe_body_pathnorm_m" in ours
        for name in ref:
            assert ours[name] == pytest.approx(ref[name], abs=1e-10), name
            assert single[name] == pytest.approx(ref[name], rel=ROOT_BOUND, abs=1e-12), name


def test_batched_pa_on_padded_pairs_matches_one_pair_at_a_time():
    """The GPU branch of the torch backend (one zero-padded call per region), run here on the CPU."""
    rng = np.random.default_rng(8)
    pairs = [(regions(rng, t1), regions(rng, t2)) for t1, t2 in ((3, 9), (11, 4), (1, 1))]
    config = MotionMetricsConfig(backend="torch")
    checked = [_validated(p, g, n, config) for n, (p, g) in enumerate(pairs)]
    jobs = [(n, region, pa) for n in range(len(pairs)) for region in ("body", "left_hand") for pa in (False, True)]
    batched = _batched_pa(checked, jobs, config)
    assert sorted(batched) == [b for b, (_, _, pa) in enumerate(jobs) if pa]
    for b, cost in batched.items():
        n, region, _ = jobs[b]
        ref = pa_distance_matrix(*checked[n][region])
        assert cost.shape == ref.shape
        torch.testing.assert_close(cost, ref, rtol=0, atol=1e-12)
    pred, gt = (T(np.stack([motion(rng, 6, 5) for _ in range(2)])) for _ in range(2))
    small_chunks = pa_distance_matrices(pred, gt, chunk_pairs=7, residual_elements=40, measure=slice(1, 3))
    torch.testing.assert_close(small_chunks[1], pa_distance_matrix(pred[1], gt[1], measure=slice(1, 3)))


def test_backend_and_device_are_checked():
    with pytest.raises(ValueError, match="backend 'jax' unknown"):
        MotionMetricsConfig(backend="jax")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="needs backend 'torch'"):
        MotionMetricsConfig(device="cuda")
    assert MotionMetricsConfig(backend="torch", device="cuda").device == "cuda"  # built without a GPU


def test_without_numba_the_numba_backend_names_the_package_and_torch_still_scores(monkeypatch):
    rng = np.random.default_rng(9)
    pairs = [(regions(rng, 6), regions(rng, 5))]
    expected = evaluate_pairs(pairs, config=MotionMetricsConfig(root_precision="float64"))
    monkeypatch.delitem(sys.modules, "m3t.metrics.kernels")  # forget the imported module, so it is imported again
    monkeypatch.delattr(m3t.metrics, "kernels")
    monkeypatch.setitem(sys.modules, "numba", None)  # import numba now fails as if it were not installed
    with pytest.raises(ImportError, match="pip install numba"):
        evaluate_pairs(pairs)
    fallback = evaluate_pairs(pairs, config=MotionMetricsConfig(backend="torch"))[0]  # numpy sweep
    assert fallback == pytest.approx(expected[0], abs=1e-10)


def test_kernels_compile_uncached_where_no_cache_directory_is_writable(monkeypatch):
    """A read-only install and home: numba finds no cache locator and raises at decoration; ``_jit`` then
    compiles without a cache (simulated: permissions do not stop root, who runs CI containers). ``jit`` is the
    one decorator of the DTW kernels and the mesh rasteriser."""
    def unwritable(self):
        raise PermissionError(13, "Permission denied", self.get_cache_path())

    monkeypatch.setattr(numba.core.caching._CacheLocator, "ensure_cache_path", unwritable)
    monkeypatch.setattr(numba.config, "CACHE_DIR", "")

    def add_one(x):
        return x + 1

    with pytest.raises(RuntimeError, match="no locator available"):
        numba.njit(cache=True)(add_one)
    assert jit()(add_one)(41) == 42
