"""The ``soke_exact`` motion metric mode against an independent re-implementation of SOKE's released arithmetic.

The reference functions below are written from SOKE's published evaluation (repository 2000ZRL/SOKE):
``mGPT/metrics/dtw.py`` (``dtw`` with ``w=inf, s=1, warp=1``: a full (T1 + 1, T2 + 1) table with an infinite
first row and column, ``D[i, j] += min(diagonal, up, left)``, the raw ``D[-1, -1]``; ``l2_dist_align``:
``x - x[align_idx] + y[align_idx]``, or ``rigid_align(x, y)`` when ``align_idx`` is None, then the ``wanted``
rows, mean point distance) and ``mGPT/utils/human_models.py`` (``rigid_transform_3D``: SVD of the covariance
divided by n, reflection fixed by negating the last singular value and the last row of V, scale =
sum(s) / var(A)). ``mGPT/metrics/t2m.py`` calls them per clip as ``dtw(joints_rst, joints_ref,
partial(l2_dist_align, wanted=joint_part2idx['upper_body'], align_idx=0))`` on SMPL-X's 144 output joints
(``upper_body`` = indices 12, 16, 17, 18, 19, 20, 21, 59, 58, 57, 56, 55) and with ``align_idx=0`` on the 21
regressed points of each hand. Plain numpy loops, nothing shared with the code under test.

Parameters are random SMPL-FX sequences of the synthetic stand-in model (``fx``, :mod:`smplfx_fixtures`).
"""
from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch

from m3t.body.metric_sets import BODY_POINTS
from m3t.body.protocol import Modality, ModalityLayout
from m3t.body.rotations import identity_6d
from m3t.body.similarity import similarity_transform
from m3t.body.smplfx_build import SMPLX_JOINTS
from m3t.metrics.motion import MotionMetricsConfig, evaluate_pairs
from m3t.metrics.procrustes import pa_distance_matrix
from m3t.metrics.scorer import MotionPair, MotionScorer
from m3t.metrics.soke import SMPLX_VERTEX_JOINTS, SOKE_ZEROED_JOINTS, SokeModeError, zero_soke_joints

SOKE = MotionMetricsConfig(mode="soke_exact")
SOKE_UPPER_BODY = [12, 16, 17, 18, 19, 20, 21, 59, 58, 57, 56, 55]  # joint_idx[joint_part['upper_body']]
# smplx's VertexJointSelector appends vertex_ids['smplx'] nose, reye, leye, rear, lear as output joints 55-59.
SMPLX_FACE_POINTS = [("nose", 9120), ("reye", 9929), ("leye", 9448), ("rear", 616), ("lear", 6)]


# ---------------------------------------------------------------- SOKE's arithmetic, re-implemented in numpy


def soke_rigid_align(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 3) a aligned onto (N, 3) b by SOKE's rigid_transform_3D / rigid_align."""
    n = a.shape[0]
    ca, cb = a.mean(0), b.mean(0)
    h = (a - ca).T @ (b - cb) / n
    u, s, v = np.linalg.svd(h)
    r = v.T @ u.T
    if np.linalg.det(r) < 0:
        s[-1], v[2] = -s[-1], -v[2]
        r = v.T @ u.T
    c = s.sum() / np.var(a, axis=0).sum()
    t = cb - c * r @ ca
    return (c * r @ a.T).T + t


def soke_l2_dist_align(x: np.ndarray, y: np.ndarray, wanted=None, align_idx=None) -> float:
    x = soke_rigid_align(x, y) if align_idx is None else x - x[align_idx:align_idx + 1] + y[align_idx:align_idx + 1]
    if wanted is not None:
        x, y = x[wanted], y[wanted]
    return float(np.mean(np.sqrt(((x - y) ** 2).sum(axis=1))))


def soke_dtw(x: np.ndarray, y: np.ndarray, dist) -> float:
    r, c = len(x), len(y)
    d0 = np.zeros((r + 1, c + 1))
    d0[0, 1:] = np.inf
    d0[1:, 0] = np.inf
    d1 = d0[1:, 1:]  # a view: the cost matrix is accumulated in place
    for i in range(r):
        for j in range(c):
            d1[i, j] = dist(x[i], y[j])
    for i in range(r):
        for j in range(c):
            d1[i, j] += min(d0[i, j], d0[min(i + 1, r), j], d0[i, min(j + 1, c)])
    return float(d1[-1, -1])


# ---------------------------------------------------------------- helpers


def random_params(body, frames: int, seed: int) -> dict[str, np.ndarray]:
    """Rest pose plus Gaussian 6D noise (orthonormalised by the model) and random expression values."""
    rng = np.random.default_rng(seed)
    rest = {k: v.numpy().astype(np.float64) for k, v in body.rest_params(frames).items()}
    out = {}
    for m in body.layout.modalities:
        out[m.name] = rest[m.name] + rng.normal(0.0, 0.3 if m.kind == "rotation6d" else 0.5, rest[m.name].shape)
    out["face"][:, 102:] = rest["face"][:, 102:] + rng.normal(0.0, 0.1, (frames, 6))  # a plausible jaw
    return out


@pytest.fixture(scope="module")
def soke_scorer(fx):
    return MotionScorer(fx, SOKE)


@pytest.fixture(scope="module")
def pairs(fx):
    """Two (prediction, reference) clips of different lengths on the default identity."""
    return [(random_params(fx, 6, 1), random_params(fx, 8, 2)), (random_params(fx, 5, 3), random_params(fx, 4, 4))]


def spine_bend(points: np.ndarray, degrees: float) -> np.ndarray:
    """(T, K, 3) SOKE body points with everything but the root (point 0) turned about the root, a little more
    every frame, about the protocol frame's x axis: a forward bend of the spine."""
    out = points.copy()
    for t in range(len(points)):
        a = np.radians(degrees) * (t + 1) / len(points)
        rot = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
        out[t, 1:] = (points[t, 1:] - points[t, :1]) @ rot.T + points[t, :1]
    return out


# ---------------------------------------------------------------- tests


def test_soke_body_layout_is_soke_upper_body_after_a_fixed_root(fx, soke_scorer):
    """Points 1-12 are SOKE's ``upper_body`` rows of SMPL-X's output joints; point 0 (SMPL-FX's root, standing
    for the pelvis) never moves, like SOKE's pelvis with the lower body and global orient zeroed."""
    assert list(SMPLX_VERTEX_JOINTS[:5]) == SMPLX_FACE_POINTS
    output_joints = list(SMPLX_JOINTS) + [name for name, _ in SMPLX_FACE_POINTS]  # the first 60 of the 144
    vertex_of = dict(SMPLX_FACE_POINTS)
    body = soke_scorer.sets["body"]
    assert body.names[1:13] == BODY_POINTS
    for k, soke_row in enumerate(SOKE_UPPER_BODY, start=1):
        name = output_joints[soke_row]
        if name in vertex_of:
            assert (body.kind[k], body.index[k]) == (0, vertex_of[name]), (k, name)
        else:
            assert (body.kind[k], fx.joint_names[body.index[k]]) == (1, name), (k, name)
    # SOKE's 12 zeroed joints: SMPL-FX keeps only spine3, its fixed root, rigidly tied to where the pelvis was.
    assert body.names[0] == "spine3" and set(fx.joint_names) & set(SOKE_ZEROED_JOINTS) == {"spine3"}
    # The rest of the Procrustes set: the other 36 joints, smplx's 16 other vertex points, 51 landmarks; the
    # measured points are members of SOKE's set, not repeated in it.
    assert len(fx.joint_names) == 44 and len(body.names) == 1 + 12 + 36 + 16 + 51
    first = set(zip(body.kind[:13].tolist(), body.index[:13].tolist()))
    assert not first & set(zip(body.kind[13:-51].tolist(), body.index[13:-51].tolist()))
    points = soke_scorer.points(random_params(fx, 4, 9), fx.default_identity().numpy())["body"]
    assert points.shape == (4, 116, 3)
    np.testing.assert_array_equal(points[:, 0], 0.0)


def test_soke_exact_matches_an_independent_reimplementation_of_soke(fx, soke_scorer, pairs):
    ident = fx.default_identity().numpy()
    scores = soke_scorer.score([MotionPair(f"c{n}", "toy/DGS", p, ident, r) for n, (p, r) in enumerate(pairs)])
    for (pred, ref), clip in zip(pairs, scores.per_clip):
        x, y = soke_scorer.points(pred, ident), soke_scorer.points(ref, ident)
        jpe = soke_dtw(x["body"], y["body"], partial(soke_l2_dist_align, wanted=list(range(1, 13)), align_idx=0))
        pa = soke_dtw(x["body"], y["body"], partial(soke_l2_dist_align, wanted=list(range(1, 13))))
        assert clip.metrics["DTW_MPJPE_PA_body"] == clip.metrics["dtw_jpe_body_m"]
        assert clip.metrics["dtw_jpe_body_m"] == pytest.approx(jpe, rel=0, abs=1e-9)
        assert clip.metrics["dtw_pa_jpe_body_m"] == pytest.approx(pa, rel=0, abs=1e-9)
        for region, soke in (("left_hand", "lhand"), ("right_hand", "rhand")):
            jpe = soke_dtw(x[region], y[region], partial(soke_l2_dist_align, align_idx=0))
            pa = soke_dtw(x[region], y[region], soke_l2_dist_align)
            assert clip.metrics[f"DTW_MPJPE_PA_{soke}"] == pytest.approx(jpe, rel=0, abs=1e-9)
            assert clip.metrics[f"dtw_jpe_{region}_m"] == clip.metrics[f"DTW_MPJPE_PA_{soke}"]
            assert clip.metrics[f"dtw_pa_jpe_{region}_m"] == pytest.approx(pa, rel=0, abs=1e-9)
        assert clip.metrics["dtw_jpe_body_m"] > 0.01 and clip.metrics["dtw_pa_jpe_body_m"] > 0.01
    assert "toy/DGS/DTW_MPJPE_PA_body" in scores.summary


def test_modes_agree_while_the_spine_is_fixed_and_differ_once_it_moves(fx, soke_scorer, pairs):
    """On SMPL-FX the spine cannot move, so neck-rooted (m3t) and pelvis-rooted (SOKE) DTW-JPE agree; the body
    PA differs (12 points vs. all). A spine bend, which Anny or raw SMPL-X can make, separates the two JPEs.
    Both modes root in float64 here (``soke_exact``'s default), so the comparison is of the rooting alone."""
    ident = fx.default_identity().numpy()
    (pred, ref) = pairs[0]
    double = MotionMetricsConfig(root_precision="float64")
    ours = MotionScorer(fx, double).score([MotionPair("c", "g", pred, ident, ref)]).per_clip[0].metrics
    soke = soke_scorer.score([MotionPair("c", "g", pred, ident, ref)]).per_clip[0].metrics
    for name in ("dtw_jpe_body_m", "dtw_jpe_left_hand_m", "dtw_jpe_right_hand_m", "dtw_pa_jpe_left_hand_m"):
        assert soke[name] == pytest.approx(ours[name], rel=0, abs=1e-12), name
    assert abs(soke["dtw_pa_jpe_body_m"] - ours["dtw_pa_jpe_body_m"]) > 1e-3

    x, y = soke_scorer.points(pred, ident)["body"], soke_scorer.points(ref, ident)["body"]
    jpe_only = MotionMetricsConfig(procrustes_regions=(), root_precision="float64")
    for degrees, agree in ((0.0, True), (20.0, False)):
        bent = spine_bend(x, degrees)
        m3t = evaluate_pairs([({"body": bent[:, 1:13]}, {"body": y[:, 1:13]})], config=jpe_only)[0]["dtw_jpe_body_m"]
        exact = evaluate_pairs([({"body": bent}, {"body": y})],
                               config=MotionMetricsConfig(procrustes_regions=(), mode="soke_exact"))[0]
        reference = soke_dtw(bent, y, partial(soke_l2_dist_align, wanted=list(range(1, 13)), align_idx=0))
        assert exact["dtw_jpe_body_m"] == pytest.approx(reference, rel=0, abs=1e-9)
        assert (abs(m3t - exact["dtw_jpe_body_m"]) < 1e-12) is agree, (degrees, m3t, exact["dtw_jpe_body_m"])


def test_anny_is_refused_naming_smplfx_and_its_files(body):
    with pytest.raises(SokeModeError, match=r"body\.model: smplfx.*'anny'.*licensed SMPL-X and FLAME.*smplx_path"):
        MotionScorer(body, SOKE)


def test_smlm_evaluation_scores_in_the_configured_mode(fx):
    from m3t.smlm.evaluate import SMLMEvaluator

    assert SMLMEvaluator(fx, {}, None, [], {}).scorer.config.mode == "m3t"
    evaluator = SMLMEvaluator(fx, {}, None, [], {}, motion=SOKE)
    assert evaluator.scorer.config.mode == "soke_exact" and len(evaluator.scorer.sets["body"].names) == 116


def test_soke_mode_refuses_points_without_its_body_layout_and_unknown_modes():
    rng = np.random.default_rng(0)
    twelve = {"body": rng.normal(size=(3, 12, 3))}
    assert "dtw_jpe_body_m" in evaluate_pairs([(twelve, twelve)])[0]  # the m3t layout, fine in mode m3t
    with pytest.raises(ValueError, match=r"pair 0, region 'body': 12 points.*'soke_exact'.*at least 13.*root first"):
        evaluate_pairs([(twelve, twelve)], config=SOKE)
    with pytest.raises(ValueError, match="mode 'soke' unknown; use 'm3t'"):
        MotionMetricsConfig(mode="soke")  # type: ignore[arg-type]


def test_zero_soke_joints_zeroes_the_listed_joints_and_nothing_else(fx):
    layout = ModalityLayout((Modality("body", "rotation6d", ("spine3", "neck", "left_hip")),), ())
    params = {"body": torch.randn(4, 18, dtype=torch.float64)}
    out = zero_soke_joints(layout, params)["body"].reshape(4, 3, 6)
    torch.testing.assert_close(out[:, [0, 2]], identity_6d(4, 2, dtype=torch.float64))
    torch.testing.assert_close(out[:, 1], params["body"].reshape(4, 3, 6)[:, 1])
    assert not torch.equal(params["body"].reshape(4, 3, 6)[:, 0], out[:, 0])  # a copy; the input is kept
    fx_params = {k: torch.as_tensor(v) for k, v in random_params(fx, 2, 5).items()}
    assert all(torch.equal(a, fx_params[k]) for k, a in zero_soke_joints(fx.layout, fx_params).items())


def test_pa_fits_on_all_points_and_measures_the_subset():
    """``measure``: one similarity per frame pair fitted on every point, distances of the chosen points only."""
    rng = np.random.default_rng(3)
    pred, gt = torch.as_tensor(rng.normal(size=(3, 9, 3))), torch.as_tensor(rng.normal(size=(4, 9, 3)))
    got = pa_distance_matrix(pred, gt, measure=slice(1, 5))
    for i in range(3):
        for j in range(4):
            aligned = similarity_transform(pred[i], gt[j]).apply(pred[i])
            want = torch.linalg.norm(aligned[1:5] - gt[j, 1:5], dim=-1).mean()
            assert float(got[i, j]) == pytest.approx(float(want), abs=1e-12)
    assert not torch.allclose(got, pa_distance_matrix(pred[:, 1:5], gt[:, 1:5]))
