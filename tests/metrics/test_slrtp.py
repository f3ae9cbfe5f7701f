"""Definition "slrtp" (the SLRTP 2025 sign-production challenge's evaluation): text metrics against hand-counted
n-grams, LCS and edits; FastDTW against paths recorded from the fastdtw 0.3.4 package and against exact DTW; the
pose metrics on small arrays worked by hand; the frame-rate rule, missing joints, empty sequences and the errors.

Floats are compared with a relative tolerance of 1e-12: the expected values are exact fractions, and the code sums
float64 terms in an order numpy may change between builds (pairwise, SIMD), so only the last bits may differ."""
from __future__ import annotations

import importlib
import math

import numpy as np
import pytest

from m3t.metrics.slrtp import (
    SLRTP_FACE,
    SLRTP_FACE_MESH_INDICES,
    SLRTP_JOINT_NAMES,
    SLRTP_LEFT_HAND,
    SLRTP_LEFT_WRIST,
    SLRTP_NUM_JOINTS,
    SLRTP_RIGHT_HAND,
    SLRTP_RIGHT_WRIST,
    slrtp_eval_rate,
    slrtp_fastdtw,
    slrtp_pair_statistics,
    slrtp_pose_corpus_metrics,
    slrtp_pose_metrics,
    slrtp_text_metrics,
    slrtp_wer,
    slrtp_wer_words,
)

REL = 1e-12
NO_HALVING = {"pred_fps": 12.5, "ref_fps": 12.5}  # a rate other than 25: frames are taken as given


# ---- text -----------------------------------------------------------------------------------------------------
def test_identical_text_is_perfect():
    sents = ["am tag regnet es im norden", "morgen scheint die sonne"]
    out = slrtp_text_metrics(sents, sents)
    for k in ("slrtp_bleu1", "slrtp_bleu2", "slrtp_bleu3", "slrtp_bleu4", "slrtp_chrf", "slrtp_rouge_l"):
        assert out[k] == pytest.approx(100.0, rel=REL), k
    assert out["slrtp_wer"] == 0.0


def test_bleu_hand_counted_corpus_statistics():
    # unigrams: a b c d | x y -> 3 + 1 of 6 match; bigrams: ab bc cd | xy -> 2 of 4; trigrams: abc bcd -> 1 of 2;
    # the one 4-gram abcd does not match -> BLEU-4 = 0 (no smoothing). 6 hypothesis and 6 reference words: BP = 1.
    out = slrtp_text_metrics(["a b c d", "x y"], ["a b c e", "x z"])
    assert out["slrtp_bleu1"] == pytest.approx(100 * 4 / 6, rel=REL)
    assert out["slrtp_bleu2"] == pytest.approx(100 * (4 / 6 * 2 / 4) ** (1 / 2), rel=REL)
    assert out["slrtp_bleu3"] == pytest.approx(100 * (4 / 6 * 2 / 4 * 1 / 2) ** (1 / 3), rel=REL)
    assert out["slrtp_bleu4"] == 0.0


def test_bleu_brevity_penalty_and_an_order_the_hypotheses_never_reach():
    # 2 hypothesis words for 4 reference words: BP = exp(1 - 4/2); all unigrams and the bigram match; there is no
    # hypothesis trigram at all, and the challenge's sacreBLEU 1.4 then scores BLEU-3 and BLEU-4 as 0.
    out = slrtp_text_metrics(["a b"], ["a b c d"])
    assert out["slrtp_bleu1"] == pytest.approx(100 * math.exp(-1), rel=REL)
    assert out["slrtp_bleu2"] == pytest.approx(100 * math.exp(-1), rel=REL)
    assert out["slrtp_bleu3"] == out["slrtp_bleu4"] == 0.0


def test_bleu_is_case_sensitive_but_wer_lower_cases():
    # "Regen" != "regen" for BLEU (1 of 2 unigrams, no bigram); WER's normalisation lower-cases both sides first
    out = slrtp_text_metrics(["Regen morgen"], ["regen morgen"])
    assert out["slrtp_bleu1"] == pytest.approx(50.0, rel=REL)
    assert out["slrtp_bleu2"] == 0.0
    assert out["slrtp_wer"] == 0.0


def test_chrf_hand_computed():
    # "ab" vs "abc", beta 2: 1-grams P = 2/2, R = 2/3; 2-grams P = 1/1, R = 1/2; the hypothesis has no 3..6-grams,
    # so 2 effective orders: P = 1, R = (2/3 + 1/2) / 2 = 7/12; F = 5 P R / (4 P + R) = (35/12) / (55/12) = 7/11
    assert slrtp_text_metrics(["ab"], ["abc"])["slrtp_chrf"] == pytest.approx(100 * 7 / 11, rel=REL)
    # whitespace is removed before counting characters
    assert slrtp_text_metrics(["a b"], ["ab"])["slrtp_chrf"] == pytest.approx(100.0, rel=REL)


def test_rouge_l_beta_1_2_and_single_space_tokens():
    beta2 = 1.2 ** 2

    def f(p, r):
        return (1 + beta2) * p * r / (r + beta2 * p)

    # "a b c d" vs "a c e": LCS "a c" = 2 -> P = 2/4, R = 2/3
    assert slrtp_text_metrics(["a b c d"], ["a c e"])["slrtp_rouge_l"] == pytest.approx(100 * f(2 / 4, 2 / 3), rel=REL)
    # a doubled space is an empty token: "a  b" is [a, "", b], LCS with [a, b] is 2 -> P = 2/3, R = 1
    assert slrtp_text_metrics(["a  b"], ["a b"])["slrtp_rouge_l"] == pytest.approx(100 * f(2 / 3, 1), rel=REL)
    # mean over sentences: 1 and 0
    assert slrtp_text_metrics(["x y", "q"], ["x y", "z"])["slrtp_rouge_l"] == pytest.approx(50.0, rel=REL)


def test_wer_normalisation():
    # contractions before lower-casing ("Won't" only meets "n't"), whitespace runs collapsed, punctuation deleted
    # without a space ("über-cool" -> "übercool")
    assert slrtp_wer_words("  Won't  STOP, it's  über-cool!  ") == ["wo", "not", "stop", "it", "is", "übercool"]
    assert slrtp_wer_words("...") == []


def test_wer_is_a_corpus_ratio():
    # pair 1: 1 substitution of 1 word; pair 2: 0 edits of 3 words -> 1 / 4 (a mean of sentence WERs would be 50)
    assert slrtp_wer(["nord", "es regnet heute"], ["süd", "Es regnet, heute!"]) == pytest.approx(25.0, rel=REL)
    # one insertion over 3 reference words
    assert slrtp_wer(["es regnet heute morgen"], ["es regnet morgen"]) == pytest.approx(100 / 3, rel=REL)
    # three words for one: 1 substitution + 2 insertions -> 300
    assert slrtp_wer(["b c d"], ["a"]) == pytest.approx(300.0, rel=REL)


def test_empty_hypothesis():
    out = slrtp_text_metrics([""], ["es regnet morgen"])
    assert out["slrtp_wer"] == pytest.approx(100.0, rel=REL)  # three deletions of three words
    assert out["slrtp_bleu1"] == out["slrtp_bleu4"] == 0.0  # no hypothesis word: BP = 0
    assert out["slrtp_chrf"] == 0.0
    assert out["slrtp_rouge_l"] == 0.0


def test_text_errors_name_the_problem():
    with pytest.raises(ValueError, match="2 hypotheses but 1 references"):
        slrtp_text_metrics(["a", "b"], ["a"])
    with pytest.raises(ValueError, match="no hypotheses"):
        slrtp_text_metrics([], [])
    with pytest.raises(ValueError, match=r"pair 1: reference '\?!' has no word left"):
        slrtp_text_metrics(["a", "b"], ["a", "?!"])


# ---- FastDTW --------------------------------------------------------------------------------------------------
def _series(values) -> np.ndarray:
    return np.asarray(values, dtype=np.float64).reshape(-1, 1, 1)  # (T, 1 joint, 1 coordinate)


# Recorded from fastdtw 0.3.4 (radius 1, Euclidean distance): the compiled module (_fastdtw.pyx) and the pure-Python
# fallback (fastdtw.py). Integer values, so every distance and tie is exact on any host.
X8 = [3, 2, 0, 1, 2, 3, 1, 2]
Y8 = [1, 2, 2, 2, 0, 3, 3, 3]
PATH_COMPILED = [(0, 0), (1, 0), (2, 0), (3, 0), (4, 1), (4, 2), (4, 3), (4, 4), (5, 5), (6, 6), (7, 7)]
PATH_PYTHON = [(0, 0), (1, 1), (1, 2), (1, 3), (2, 4), (3, 4), (4, 5), (5, 5), (5, 6), (5, 7), (6, 7), (7, 7)]


@pytest.mark.parametrize(("variant", "expected"), [("compiled", PATH_COMPILED), ("python", PATH_PYTHON)])
def test_fastdtw_matches_recorded_package_paths(variant, expected):
    path = slrtp_fastdtw(_series(X8), _series(Y8), variant=variant)
    assert [tuple(p) for p in path.tolist()] == expected


@pytest.mark.parametrize(("variant", "expected"), [("compiled", [(0, 0), (1, 0), (2, 1)]),
                                                    ("python", [(0, 0), (1, 1), (2, 1)])])
def test_fastdtw_tie_breaking_by_hand(variant, expected):
    # x = 0 1 2, y = 0 2: y is shorter than radius + 2, so full DTW. D(1,0) = 1, D(1,1) = 1 + D(0,0) = 1,
    # D(2,1) = 0 + min(up D(1,1) = 1, left D(2,0) = 3, diagonal D(1,0) = 1): a tie the compiled module gives to
    # the diagonal and the Python fallback to (i-1, j)
    assert [tuple(p) for p in slrtp_fastdtw(_series([0, 1, 2]), _series([0, 2]), variant=variant).tolist()] == expected


def _exact_dtw_cost(x: np.ndarray, y: np.ndarray) -> float:
    d = np.sqrt(((x.reshape(len(x), 1, -1) - y.reshape(1, len(y), -1)) ** 2).sum(-1))
    acc = np.full((len(x) + 1, len(y) + 1), np.inf)
    acc[0, 0] = 0.0
    for i in range(1, len(x) + 1):
        for j in range(1, len(y) + 1):
            acc[i, j] = d[i - 1, j - 1] + min(acc[i - 1, j], acc[i, j - 1], acc[i - 1, j - 1])
    return float(acc[-1, -1])


@pytest.mark.parametrize("variant", ["compiled", "python"])
def test_fastdtw_path_is_valid_and_never_beats_exact_dtw(variant):
    rng = np.random.default_rng(7)
    for _ in range(20):
        x, y = rng.normal(size=(rng.integers(1, 30), 4, 3)), rng.normal(size=(rng.integers(1, 30), 4, 3))
        path = slrtp_fastdtw(x, y, variant=variant)
        assert tuple(path[0]) == (0, 0) and tuple(path[-1]) == (len(x) - 1, len(y) - 1)
        assert {tuple(s) for s in np.diff(path, axis=0).tolist()} <= {(1, 0), (0, 1), (1, 1)}
        cost = float(np.sqrt(((x[path[:, 0]] - y[path[:, 1]]) ** 2).reshape(len(path), -1).sum(-1)).sum())
        assert cost >= _exact_dtw_cost(x, y) * (1 - REL)


def test_fastdtw_matches_the_fastdtw_package():
    fastdtw = pytest.importorskip("fastdtw")  # test-only cross-check, never a dependency
    try:
        importlib.import_module("fastdtw._fastdtw")
        variant = "compiled"
    except ImportError:
        variant = "python"
    rng = np.random.default_rng(11)
    for k in range(40):
        shape = (rng.integers(1, 50), 3, 2), (rng.integers(1, 50), 3, 2)
        x, y = ((rng.integers(0, 3, size=s) if k % 2 else rng.normal(size=s).cumsum(0)).astype(float) for s in shape)
        _, expected = fastdtw.fastdtw(x.reshape(len(x), -1), y.reshape(len(y), -1), radius=1,
                                      dist=lambda a, b: np.sqrt(np.sum((a - b) ** 2)))
        assert [tuple(p) for p in slrtp_fastdtw(x, y, variant=variant).tolist()] == list(expected)


# ---- pose metrics ---------------------------------------------------------------------------------------------
def _moving(values, joints: int = 6) -> np.ndarray:
    """(T, joints, 3) poses: every joint at (v, 0, 0) in the frame of value v."""
    poses = np.zeros((len(values), joints, 3))
    poses[:, :, 0] = np.asarray(values, dtype=np.float64)[:, None]
    return poses


def test_identical_sequences():
    ref = _moving(np.arange(9.0) ** 1.5)
    ref[:, SLRTP_RIGHT_WRIST, 1] = np.sin(np.arange(9.0))
    out = slrtp_pose_metrics(ref, ref.copy())
    assert out == {"slrtp_dtw_mje": 0.0, "slrtp_wrist_path_ratio": 1.0, "slrtp_duration_ratio": 1.0}


def test_dtw_mje_one_joint_offset():
    # joint 0 is 0.3 off in every frame; frames 1 apart along x make the diagonal the only cheap path:
    # errors 0.3 on 1 of 6 joints -> 0.05
    ref = _moving(np.arange(7.0))
    pred = ref.copy()
    pred[:, 0, 2] += 0.3
    assert slrtp_pose_metrics(pred, ref, **NO_HALVING)["slrtp_dtw_mje"] == pytest.approx(0.3 / 6, rel=REL)


@pytest.mark.parametrize("variant", ["compiled", "python"])
def test_dtw_mje_different_lengths_and_pooling(variant):
    # pred 0 1 2 vs ref 0 2 (hand-worked in test_fastdtw_tie_breaking_by_hand): either path has joint errors
    # 0, 1, 0 on all 6 joints -> 1/3. Pooled with an identical 5-frame pair (30 terms of error 0):
    # 6 / (18 + 30) = 1/8, not the mean of the pairs' values (1/6)
    short = slrtp_pose_metrics(_moving([0, 1, 2]), _moving([0, 2]), variant=variant, **NO_HALVING)
    assert short["slrtp_dtw_mje"] == pytest.approx(1 / 3, rel=REL)
    assert short["slrtp_duration_ratio"] == pytest.approx(1.5, rel=REL)
    same = _moving(np.arange(5.0))
    corpus = slrtp_pose_corpus_metrics([_moving([0, 1, 2]), same], [_moving([0, 2]), same], variant=variant,
                                       **NO_HALVING)
    assert corpus["slrtp_dtw_mje"] == pytest.approx(1 / 8, rel=REL)
    assert corpus["slrtp_pairs"] == corpus["slrtp_dtw_mje_pairs"] == 2.0


def test_wrist_path_ratio_is_a_ratio_of_means():
    # pair 1: right wrist 0 -> 1 (path 1) against 0 -> 2 (path 2); pair 2: 0 -> 3 (3) against 0 -> 1 (1);
    # left wrists the same. Ratio of means (1 + 3) / (2 + 1) = 4/3; a mean of ratios would be (1/2 + 3) / 2.
    def pose(end):
        x = np.zeros((2, SLRTP_NUM_JOINTS, 3))
        x[1, [SLRTP_RIGHT_WRIST, SLRTP_LEFT_WRIST], 1] = end
        return x

    one = slrtp_pose_metrics(pose(1.0), pose(2.0), **NO_HALVING)
    assert one["slrtp_wrist_path_ratio"] == pytest.approx(0.5, rel=REL)
    out = slrtp_pose_corpus_metrics([pose(1.0), pose(3.0)], [pose(2.0), pose(1.0)], **NO_HALVING)
    assert out["slrtp_wrist_path_ratio"] == pytest.approx(4 / 3, rel=REL)


def test_wrist_path_uses_the_body_wrists_and_averages_left_and_right():
    # right wrist (joint 2) path 1 vs 2 -> 1/2; left wrist (joint 5) 6 vs 3 -> 2; the hand roots (8, 29) move a lot
    # in the prediction only and count for nothing. (1/2 + 2) / 2 = 1.25
    pred, ref = np.zeros((3, SLRTP_NUM_JOINTS, 3)), np.zeros((3, SLRTP_NUM_JOINTS, 3))
    pred[:, SLRTP_RIGHT_WRIST, 0] = [0, 1, 1]
    ref[:, SLRTP_RIGHT_WRIST, 0] = [0, 1, 2]
    pred[:, SLRTP_LEFT_WRIST, 2] = [0, 3, 0]
    ref[:, SLRTP_LEFT_WRIST, 2] = [0, 0, 3]
    pred[:, [8, 29], 0] = [[0, 0], [50, 50], [0, 0]]
    assert slrtp_pose_metrics(pred, ref, **NO_HALVING)["slrtp_wrist_path_ratio"] == pytest.approx(1.25, rel=REL)


def test_still_reference_wrists_give_inf_or_nan():
    still = np.zeros((3, 6, 3))
    assert math.isnan(slrtp_pose_metrics(still, still, **NO_HALVING)["slrtp_wrist_path_ratio"])
    assert slrtp_pose_metrics(_moving([0, 1, 2]), still, **NO_HALVING)["slrtp_wrist_path_ratio"] == math.inf


def test_frame_rate_rule():
    # 25 fps: every second frame (7 -> 4, 8 -> 4); any other rate: as given
    assert len(slrtp_eval_rate(np.zeros((7, 6, 3)), 25)) == 4
    assert len(slrtp_eval_rate(np.zeros((7, 6, 3)), 12)) == 7
    assert slrtp_pose_metrics(_moving(range(7)), _moving(range(8)))["slrtp_duration_ratio"] == 1.0
    assert slrtp_pose_metrics(_moving(range(4)), _moving(range(8)), pred_fps=12)["slrtp_duration_ratio"] == 1.0
    # mean of per-pair ratios: 2/4 and 4/4 -> 0.75
    out = slrtp_pose_corpus_metrics([_moving(range(2)), _moving(range(4))], [_moving(range(8))] * 2, pred_fps=12)
    assert out["slrtp_duration_ratio"] == pytest.approx(0.75, rel=REL)


def test_missing_joint_by_nan_or_mask():
    ref = _moving(np.arange(5.0))
    pred = ref.copy()
    pred[2, 3] = [40.0, 40.0, 40.0]  # a wild joint: it is all the error there is
    assert slrtp_pose_metrics(pred, ref, **NO_HALVING)["slrtp_dtw_mje"] > 1.0
    mask = np.ones((5, 6), dtype=bool)
    mask[2, 3] = False
    assert slrtp_pose_metrics(pred, ref, pred_mask=mask, **NO_HALVING)["slrtp_dtw_mje"] == 0.0
    pred[2, 3] = np.nan
    stats = slrtp_pair_statistics(pred, ref, **NO_HALVING)
    assert (stats.dtw_error_sum, stats.dtw_error_terms) == (0.0, 5 * 6 - 1)


def test_missing_wrist_frame_is_bridged():
    # the right wrist at x = 0, 5, 1; missing in frame 1, its path joins frames 0 and 2: 1 (not 5 + 4)
    pred = np.zeros((3, 6, 3))
    pred[:, SLRTP_RIGHT_WRIST, 0] = [0, 5, 1]
    pred[1, SLRTP_RIGHT_WRIST] = np.nan
    assert slrtp_pair_statistics(pred, pred, **NO_HALVING).pred_right_wrist_path == 1.0


def test_empty_prediction_is_scored_as_the_challenge_does():
    out = slrtp_pose_metrics(np.zeros((0, 6, 3)), _moving([0, 1, 2]), **NO_HALVING)
    assert math.isnan(out["slrtp_dtw_mje"])
    assert out["slrtp_wrist_path_ratio"] == 0.0 and out["slrtp_duration_ratio"] == 0.0
    corpus = slrtp_pose_corpus_metrics([np.zeros((0, 6, 3)), _moving([0, 1])], [_moving([0, 1, 2]), _moving([0, 1])],
                                       **NO_HALVING)
    assert corpus["slrtp_dtw_mje"] == 0.0  # the empty pair is skipped, the other scores 0
    assert (corpus["slrtp_pairs"], corpus["slrtp_dtw_mje_pairs"]) == (2.0, 1.0)


def test_pose_errors_name_the_problem():
    ok = _moving([0, 1, 2])
    with pytest.raises(ValueError, match="prediction has 178 joints x 3 coordinates, reference 177 x 3"):
        slrtp_pose_metrics(np.zeros((3, 178, 3)), np.zeros((3, 177, 3)))
    with pytest.raises(ValueError, match="pair 1: the reference has no frame"):
        slrtp_pose_corpus_metrics([ok, ok], [ok, np.zeros((0, 6, 3))])
    with pytest.raises(ValueError, match="4 joints, but the wrists are joints 2 and 5"):
        slrtp_pose_metrics(np.zeros((3, 4, 3)), np.zeros((3, 4, 3)))
    with pytest.raises(ValueError, match=r"expected \(T, J, D\)"):
        slrtp_pose_metrics(np.zeros((3, 6)), np.zeros((3, 6)))
    with pytest.raises(ValueError, match="infinite"):
        slrtp_pose_metrics(np.full((3, 6, 3), np.inf), ok)
    with pytest.raises(ValueError, match=r"prediction mask is bool \(3, 5\); expected bool \(3, 6\)"):
        slrtp_pose_metrics(ok, ok, pred_mask=np.ones((3, 5), dtype=bool), **NO_HALVING)
    with pytest.raises(ValueError, match="2 predicted sequences but 1 references"):
        slrtp_pose_corpus_metrics([ok, ok], [ok])
    with pytest.raises(ValueError, match="no pose pairs"):
        slrtp_pose_corpus_metrics([], [])
    with pytest.raises(ValueError, match="fps: expected a positive frame rate"):
        slrtp_pose_metrics(ok, ok, pred_fps=0)
    with pytest.raises(ValueError, match="variant 'cython' unknown"):
        slrtp_fastdtw(ok, ok, variant="cython")
    with pytest.raises(ValueError, match="radius: expected an integer >= 1, got 0"):
        slrtp_fastdtw(ok, ok, radius=0)


def test_layout_tables():
    assert SLRTP_NUM_JOINTS == len(SLRTP_JOINT_NAMES) == 178
    assert (SLRTP_JOINT_NAMES[SLRTP_RIGHT_WRIST], SLRTP_JOINT_NAMES[SLRTP_LEFT_WRIST]) == ("RWrist", "LWrist")
    assert (SLRTP_RIGHT_WRIST, SLRTP_LEFT_WRIST) == (2, 5)
    assert SLRTP_JOINT_NAMES[SLRTP_RIGHT_HAND][0] == "RHWrist" and SLRTP_JOINT_NAMES[SLRTP_RIGHT_HAND][-1] == "RPinky4FingerTip"
    assert SLRTP_JOINT_NAMES[SLRTP_LEFT_HAND][0] == "LHWrist" and len(SLRTP_JOINT_NAMES[SLRTP_LEFT_HAND]) == 21
    assert SLRTP_JOINT_NAMES[SLRTP_FACE] == tuple(f"face{k}" for k in range(128))
    assert len(set(SLRTP_FACE_MESH_INDICES)) == 128 and list(SLRTP_FACE_MESH_INDICES) == sorted(SLRTP_FACE_MESH_INDICES)
    assert 0 <= min(SLRTP_FACE_MESH_INDICES) and max(SLRTP_FACE_MESH_INDICES) < 478
