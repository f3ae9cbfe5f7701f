"""The one motion scorer (a body model and parameter sequences, nothing else), the per-language text
aggregation, and the one Procrustes behind every PA error."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import roma
import torch
from builders import smooth_motion

from m3t.body.similarity import similarity_align, similarity_transform
from m3t.fitting import evaluate as fitting_evaluate
from m3t.metrics.motion import evaluate_pairs, summarise
from m3t.metrics.procrustes import procrustes_error_mm
from m3t.metrics.scorer import MotionPair, MotionScorer
from m3t.metrics.text import translation_metrics, translation_metrics_by_language
from m3t.metrics.vertices import vertex_errors_mm


def motion(body, frames: int, seed: int) -> dict[str, np.ndarray]:
    """(frames, D_m) per modality: the rest pose under slow random rotations, a moving face."""
    return {k: v.numpy() for k, v in smooth_motion(body, frames, seed, amplitude=0.3).items()}


@pytest.fixture(scope="module")
def scorer(body):
    return MotionScorer(body)


@pytest.fixture(scope="module")
def clips(body):
    """(clip id, group, prediction, reference): two groups, differing lengths, one empty prediction."""
    return [("a", "toy/DGS", motion(body, 7, 1), motion(body, 9, 2)),
            ("b", "toy/DGS", {}, motion(body, 5, 3)),
            ("c", "toy/CSL", motion(body, 6, 4), motion(body, 4, 5)),
            ("d", "toy/CSL", motion(body, 5, 6), motion(body, 8, 7))]


# ---------------------------------------------------------------- motion scorer


def test_scorer_needs_no_tokenizer_vocabulary_or_fitting():
    code = ("import sys, m3t.metrics.scorer; "
            "print(sorted(m for m in sys.modules if m.startswith(('m3t.tokenizers', 'm3t.smlm', 'm3t.fitting'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "[]"


def test_summary_is_evaluate_pairs_and_summarise_on_the_metric_points(body, scorer, clips):
    ident = body.default_identity().numpy()
    for cid, _, _, ref in clips:
        scorer.reference(cid, ref, ident)
    scores = scorer.score([MotionPair(cid, group, pred, ident) for cid, group, pred, _ in clips])

    # the empty prediction of "b" is scored as one frame of the rest pose: every clip is in the means
    rest = {k: v.numpy() for k, v in body.rest_params(1).items()}
    shown = [pred or rest for _, _, pred, _ in clips]
    expected = evaluate_pairs([(scorer.points(s, ident), scorer.points(ref, ident))
                               for s, (_, _, _, ref) in zip(shown, clips)])
    assert [c.clip_id for c in scores.per_clip] == ["a", "b", "c", "d"]
    assert [c.frames for c in scores.per_clip] == [7, 0, 6, 5]
    assert [c.metrics for c in scores.per_clip] == expected
    assert scores.per_clip[1].metrics["dtw_jpe_body_m"] > 0
    assert scores.overall == summarise(expected)
    assert scores.empty_rate == 0.25
    summary = scores.summary
    assert summary["empty_rate"] == 0.25
    assert {k: v for k, v in summary.items() if k.startswith("toy/DGS/")} == {
        f"toy/DGS/{k}": v for k, v in summarise(expected[:2]).items()}
    assert {k: v for k, v in summary.items() if k.startswith("toy/CSL/")} == {
        f"toy/CSL/{k}": v for k, v in summarise(expected[2:]).items()}
    assert {"dtw_jpe_body_m", "dtw_pa_jpe_hand_m", "dtw_vpe_face_m"} <= set(summary)


def test_stored_and_given_references_score_alike_and_a_missing_one_names_the_fix(body, scorer, clips):
    ident = body.default_identity().numpy()
    cid, group, pred, ref = clips[0]
    scorer.reference(cid, ref, ident)
    stored = scorer.score([MotionPair(cid, group, pred, ident)])
    given = scorer.score([MotionPair("unstored", group, pred, ident, reference=ref)])
    assert stored.per_clip[0].metrics == given.per_clip[0].metrics
    with pytest.raises(KeyError, match="MotionScorer.reference"):
        scorer.score([MotionPair("unstored", group, pred, ident)])


def test_a_prediction_equal_to_its_reference_scores_zero(body, scorer, clips):
    ident = body.default_identity().numpy()
    ref = clips[0][3]
    metrics = scorer.score([MotionPair("x", "toy/DGS", ref, ident, reference=ref)]).per_clip[0].metrics
    assert max(metrics.values()) < 1e-6


def test_an_empty_prediction_scores_as_the_rest_pose(body, scorer, clips):
    ident, ref = body.default_identity().numpy(), clips[1][3]
    rest = {k: v.numpy() for k, v in body.rest_params(1).items()}
    empty = scorer.score([MotionPair("b", "toy/DGS", {}, ident, reference=ref)])
    still = scorer.score([MotionPair("b", "toy/DGS", rest, ident, reference=ref)])
    assert empty.overall == still.overall and empty.empty_rate == 1.0 and still.empty_rate == 0.0
    assert scorer.score([]).overall == {}


# ---------------------------------------------------------------- text, per language


def test_translation_metrics_per_language_and_their_mean():
    hyps = ["the cat sat on the mat", "今天天气很好", "a dog runs fast", "我们明天见"]
    refs = ["a cat sat on the mat", "今天天气不错", "the dog runs fast", "我们明天见"]
    languages = ["ASL", "CSL", "ASL", "CSL"]
    out = translation_metrics_by_language(hyps, refs, languages)
    asl = translation_metrics(hyps[0::2], refs[0::2], "ASL")
    csl = translation_metrics(hyps[1::2], refs[1::2], "CSL")  # jieba words, not 13a tokens
    assert out == {"translation/ASL/bleu4": asl["bleu4"], "translation/ASL/rouge_l": asl["rouge_l"],
                   "translation/CSL/bleu4": csl["bleu4"], "translation/CSL/rouge_l": csl["rouge_l"],
                   "translation_bleu4": (asl["bleu4"] + csl["bleu4"]) / 2}
    with pytest.raises(ValueError, match="one language per hypothesis"):
        translation_metrics_by_language(hyps, refs, languages[:3])


# ---------------------------------------------------------------- one Procrustes


def test_fitting_and_vertex_pa_errors_are_the_one_procrustes():
    rng = np.random.default_rng(0)
    pred = torch.as_tensor(rng.normal(size=(6, 20, 3)))
    truth = 0.7 * pred + 0.05 * torch.as_tensor(rng.normal(size=(6, 20, 3))) + 0.3
    one = procrustes_error_mm(pred, truth)
    assert fitting_evaluate.procrustes_error_mm(pred, truth) == one
    assert vertex_errors_mm(pred, truth)["pa_vpe_mm"] == one
    # the former fitting implementation (roma's Kabsch-Umeyama with scale, proper rotations)
    rot, trans, scale = roma.rigid_points_registration(pred, truth, compute_scaling=True)
    former = scale[:, None, None] * (pred @ rot.transpose(-1, -2)) + trans[:, None]
    assert one == pytest.approx(float(torch.linalg.norm(former - truth, dim=-1).mean() * 1000.0), rel=1e-12)
    assert procrustes_error_mm(pred.float(), truth.float()) == pytest.approx(one, rel=1e-6)  # solved in float64


@pytest.mark.parametrize("method", ["quaternion", "svd"])
@pytest.mark.parametrize("weighted", [False, True])
def test_similarity_transform_recovers_closed_form_cases_without_reflecting(method, weighted):
    """An exact similarity (scale 1.4, 0.7 rad about z, a shift) is recovered whatever the weights; a planar set
    onto its mirror image (x -> -x) gets the proper rotation that matches it exactly, a half turn about y."""
    rng = np.random.default_rng(1)
    src = rng.normal(size=(12, 3))
    weights = torch.as_tensor(rng.uniform(0.1, 3.0, size=12)) if weighted else None
    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    shift = np.array([0.3, -0.2, 0.5])
    fit = similarity_transform(torch.as_tensor(src), torch.as_tensor(1.4 * src @ rot.T + shift), method, weights)
    np.testing.assert_allclose(fit.rotation.numpy(), rot, atol=1e-12)
    assert float(fit.scale) == pytest.approx(1.4, rel=1e-12)
    np.testing.assert_allclose(fit.translation.numpy(), shift, atol=1e-12)

    planar = src * [1.0, 1.0, 0.0]
    fit = similarity_transform(torch.as_tensor(planar), torch.as_tensor(planar * [-1.0, 1.0, 1.0]), method, weights)
    np.testing.assert_allclose(fit.rotation.numpy(), np.diag([-1.0, 1.0, -1.0]), atol=1e-12)
    assert float(fit.scale) == pytest.approx(1.0, rel=1e-12)
    np.testing.assert_allclose(fit.translation.numpy(), 0.0, atol=1e-12)


def test_uniform_weights_are_the_unweighted_problem_and_bad_weights_name_the_fix():
    rng = np.random.default_rng(2)
    x, y = torch.as_tensor(rng.normal(size=(4, 9, 3))), torch.as_tensor(rng.normal(size=(4, 9, 3)))
    plain, uniform = similarity_transform(x, y), similarity_transform(x, y, weights=torch.full((4, 9), 2.0))
    torch.testing.assert_close(uniform.rotation, plain.rotation)
    torch.testing.assert_close(uniform.scale, plain.scale)
    torch.testing.assert_close(similarity_align(x, y), plain.apply(x))
    with pytest.raises(ValueError, match="one per point"):
        similarity_transform(x, y, weights=torch.ones(4, 8))
    with pytest.raises(ValueError, match="non-negative"):
        similarity_transform(x, y, weights=torch.zeros(4, 9))


def test_region_keypoints_pose_exactly_the_regions_vertices_from_a_well_formed_correspondence(body):
    from m3t.metrics.vertices import region_keypoints, region_vertices

    class Recording:
        """The body model, recording the correspondences it is handed."""

        def __init__(self, inner):
            self.inner, self.seen = inner, []

        def keypoint_set(self, corr):
            self.seen.append(corr)
            return self.inner.keypoint_set(corr)

    region = np.array([12, 3000, 7, 9000])
    recording = Recording(body)
    keypoints = region_keypoints(recording, region.tolist())
    (corr,) = recording.seen
    assert len(corr.names) == len(corr.kind) == len(corr.index) == 4
    assert len(set(corr.names)) == 4 and all(isinstance(n, str) for n in corr.names)
    assert corr.valid.all() and (corr.kind == 0).all() and np.array_equal(corr.index, region)
    params = body.rest_params(3)
    params["body"] = params["body"] + 0.1 * torch.randn(3, params["body"].shape[1], generator=torch.Generator().manual_seed(0))
    identity = body.default_identity()
    dense = body.forward(params, identity).vertices[:, region]
    got = region_vertices(body, params, identity, keypoints, chunk=2)  # chunks of frames give the same result
    assert got.shape == (3, 4, 3)
    assert torch.allclose(got, dense, atol=1e-5)
