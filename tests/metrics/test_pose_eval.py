"""Definition "pose_eval" (pose-evaluation's DTW distances) on small fixed arrays, checked against values worked
out by hand, a brute-force DTW over every warping path and pose-format's own processors.

Floats are compared with ``rel=1e-9, abs=1e-12``: the module and the references add the same float64 terms in
different orders (numpy's pairwise / SIMD sums differ between builds), which moves the last bits only.
"""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from m3t.metrics.pose_eval import (
    SELECTIONS,
    VARIANTS,
    PoseEvalVariant,
    holistic_index,
    keypoint_selection,
    normalize_by_shoulders,
    pose_eval_corpus,
    pose_eval_distance,
    signing_span,
)

TOL = {"rel": 1e-9, "abs": 1e-12}
J = 553  # POSE 0-32, FACE 33-510, LEFT_HAND 511-531, RIGHT_HAND 532-552
R_SHOULDER, L_SHOULDER, L_ELBOW, R_ELBOW, L_WRIST, R_WRIST = 12, 11, 13, 14, 15, 16
LEFT_HAND_WRIST = 511


def brute_dtw(a: np.ndarray, b: np.ndarray) -> float:
    """sqrt of the least sum of squared distances over every monotone path from (0, 0) to the end, by recursion."""
    def best(i: int, j: int) -> float:
        here = float(((a[i] - b[j]) ** 2).sum())
        if i == 0 and j == 0:
            return here
        steps = [(i - 1, j - 1), (i - 1, j), (i, j - 1)]
        return here + min(best(p, q) for p, q in steps if p >= 0 and q >= 0)
    return math.sqrt(best(len(a) - 1, len(b) - 1))


def resting(frames: int, seed: int = 0) -> np.ndarray:
    """(T, 553, 3) random holistic pose with both POSE wrists below the elbows, so trimming keeps every frame."""
    x = np.random.default_rng(seed).normal(size=(frames, J, 3))
    x[:, [L_WRIST, R_WRIST], 1] = x[:, [L_ELBOW, R_ELBOW], 1] + 1.0
    return x


def one_frame(wrist: tuple[float, float, float]) -> np.ndarray:
    """(1, 553, 3) zeros (no wrist raised, so no trimming) with the shoulders at x = 0 and 2 and the left hand's
    wrist at ``wrist``."""
    x = np.zeros((1, J, 3))
    x[0, L_SHOULDER] = (2.0, 0.0, 0.0)
    x[0, LEFT_HAND_WRIST] = wrist
    return x


# --- the DTW and its aggregation ---------------------------------------------------------------------------------

def test_dtw_by_hand_per_keypoint_mean():
    # joint 0 moves along x: pred 0, 1, 2 against ref 0, 2. Squared costs [[0, 4], [1, 1], [4, 0]]; accumulated
    # S = [[0, 4], [1, 1], [5, 1]] (S[2,1] = 0 + min(S[1,0]=1, S[1,1]=1, S[2,0]=5)), so the distance is sqrt(1) = 1.
    # Joint 1 is the same in both (0 cost); the definition averages keypoints: (1 + 0) / 2.
    pred = np.zeros((3, 2, 3))
    ref = np.zeros((2, 2, 3))
    pred[:, 0, 0] = [0.0, 1.0, 2.0]
    ref[:, 0, 0] = [0.0, 2.0]
    assert pose_eval_distance(pred, ref, "pose_eval_dtw") == pytest.approx(0.5, **TOL)
    assert pose_eval_distance(pred[:, :1], ref[:, :1], "pose_eval_dtw") == pytest.approx(1.0, **TOL)


def test_dtw_is_the_root_of_the_summed_squares_not_a_sum_of_distances():
    # two pred frames at the origin, one ref frame at (3, 4, 0): both pred frames align to it, squared Euclidean
    # 25 + 25 inside, the root outside: sqrt(50) ~ 7.07 (a sum of Euclidean distances would give 10).
    pred, ref = np.zeros((2, 1, 3)), np.array([[[3.0, 4.0, 0.0]]])
    assert pose_eval_distance(pred, ref, "pose_eval_dtw") == pytest.approx(math.sqrt(50), **TOL)


@pytest.mark.parametrize("seed", range(6))
def test_dtw_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    t1, t2, d = rng.integers(1, 5), rng.integers(1, 5), rng.integers(1, 4)
    pred, ref = rng.normal(size=(t1, 3, d)), rng.normal(size=(t2, 3, d))
    expected = np.mean([brute_dtw(pred[:, k], ref[:, k]) for k in range(3)])
    assert pose_eval_distance(pred, ref, "pose_eval_dtw") == pytest.approx(expected, **TOL)
    assert pose_eval_distance(ref, pred, "pose_eval_dtw") == pytest.approx(expected, **TOL)  # DTW is symmetric


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_identical_poses_give_zero(variant):
    x = resting(6)
    mask = np.zeros((6, J), dtype=bool)
    mask[2, [5, 520, 540]] = True  # the same points missing on both sides fill alike
    assert pose_eval_distance(x, x.copy(), variant, mask, mask.copy()) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_different_lengths_are_warped_not_padded(variant):
    x = resting(5, seed=1)
    stretched = np.repeat(x, 2, axis=0)  # every frame twice: DTW aligns it to the original at no cost
    assert pose_eval_distance(stretched, x, variant) == pytest.approx(0.0, abs=1e-12)
    other = resting(7, seed=2)
    assert pose_eval_distance(x, other, variant) == pytest.approx(pose_eval_distance(other, x, variant), **TOL)
    assert pose_eval_distance(x, other, variant) > 0


def test_non_finite_distance_falls_back_to_the_default_with_a_warning():
    variant = PoseEvalVariant("pose_eval_test", None, trim=False, normalize=False, fill_value=0.0,
                              default_distance=7.0)
    pred, ref = np.full((1, 1, 2), 1e200), np.full((1, 1, 2), -1e200)  # (2e200)^2 overflows to inf
    with pytest.warns(RuntimeWarning, match="default distance 7.0"):
        assert pose_eval_distance(pred, ref, variant) == 7.0


# --- missing values ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("variant", "expected"), [
    # dtwp fills with 10: |(10, 10, 10) - (1, 2, 3)| = sqrt(81 + 64 + 49); the other 41 hand points agree.
    ("pose_eval_dtwp", math.sqrt(194) / 42),
    # no fill step: the peer reads pose-format's zeros under the mask: |(1, 2, 3)| = sqrt(14).
    ("pose_eval_dtw_hands", math.sqrt(14) / 42),
    # nDTWp normalises first (centre (1, 0, 0), width 2: the reference wrist (1, 2, 3) becomes (0, 1, 1.5)), then
    # fills with 1: |(1, 1, 1) - (0, 1, 1.5)| = sqrt(1 + 0 + 0.25).
    ("pose_eval_ndtwp", math.sqrt(1.25) / 42),
    ("pose_eval_dtw", math.sqrt(14) / J),
])
def test_a_masked_hand_point_is_filled_the_peer_way(variant, expected):
    ref = one_frame((1.0, 2.0, 3.0))
    pred = ref.copy()
    mask = np.zeros((1, J), dtype=bool)
    mask[0, LEFT_HAND_WRIST] = True
    assert pose_eval_distance(pred, ref, variant, mask_pred=mask) == pytest.approx(expected, **TOL)
    pred[0, LEFT_HAND_WRIST] = np.nan  # NaN counts as missing, like a mask
    assert pose_eval_distance(pred, ref, variant) == pytest.approx(expected, **TOL)


def test_per_coordinate_masks_fill_single_coordinates():
    ref = one_frame((1.0, 2.0, 3.0))
    mask = np.zeros((1, J, 3), dtype=bool)
    mask[0, LEFT_HAND_WRIST, 0] = True  # only x: (10, 2, 3) against (1, 2, 3)
    assert pose_eval_distance(ref, ref, "pose_eval_dtwp", mask_pred=mask) == pytest.approx(9 / 42, **TOL)
    mask[0, LEFT_HAND_WRIST] = True  # every coordinate equals a (T, J) mask
    full = mask.any(-1)
    assert pose_eval_distance(ref, ref, "pose_eval_dtwp", mask_pred=mask) == pytest.approx(
        pose_eval_distance(ref, ref, "pose_eval_dtwp", mask_pred=full), **TOL)


def test_points_outside_the_selection_do_not_count():
    x = resting(4, seed=3)
    mask = np.zeros((4, J), dtype=bool)
    mask[:, 40:60] = True  # face points: not hands
    for variant in ("pose_eval_dtwp", "pose_eval_ndtwp", "pose_eval_dtw_hands"):
        assert pose_eval_distance(x, x, variant, mask_pred=mask) == pytest.approx(0.0, abs=1e-12)
    assert pose_eval_distance(x, x, "pose_eval_dtw", mask_pred=mask) > 0


# --- trimming and normalisation ----------------------------------------------------------------------------------

def signing(frames: int = 30) -> np.ndarray:
    x = resting(frames, seed=4)
    x[10:13, L_WRIST, 1] = x[10:13, L_ELBOW, 1] - 1.0  # left wrist above its elbow in frames 10, 11, 12
    return x


def test_signing_span_by_hand():
    x = signing()
    missing = np.zeros(x.shape, dtype=bool)
    # raised 10..12, widened by 5 frames: [10 - 5, 12 + 1 + 5) = [5, 18)
    assert signing_span(x, missing) == (5, 18)
    missing[:8, L_WRIST] = True  # the left wrist only appears at frame 8: the span cannot start earlier
    assert signing_span(x, missing) == (8, 18)
    missing[:, L_ELBOW] = True  # no elbow, no comparison: nothing raised, nothing trimmed
    assert signing_span(x, missing) == (0, 30)


def test_trimming_removes_rest_frames_for_dtwp_only():
    x = signing()
    core = x[5:18]  # its own span is [max(0, 5 - 5), min(13, 8 + 5)) = everything
    assert pose_eval_distance(x, core, "pose_eval_dtwp") == pytest.approx(0.0, abs=1e-12)
    assert pose_eval_distance(x, core, "pose_eval_dtw_hands") > 0  # the random rest-frame hands still count


def test_normalize_by_shoulders_by_hand():
    x = np.zeros((3, J, 3))
    x[0, R_SHOULDER], x[0, L_SHOULDER] = (0, 0, 0), (2, 0, 0)  # midpoint (1, 0, 0), width 2
    x[1, R_SHOULDER], x[1, L_SHOULDER] = (2, 0, 0), (6, 0, 0)  # midpoint (4, 0, 0), width 4
    x[2, L_SHOULDER] = (100, 100, 100)  # right shoulder missing in frame 2: the frame is left out
    x[0, 100] = (5.5, 3.0, 0.0)
    missing = np.zeros(x.shape, dtype=bool)
    missing[2, R_SHOULDER] = True
    out = normalize_by_shoulders(x, missing)
    # centre (2.5, 0, 0), mean width 3: (5.5 - 2.5, 3, 0) / 3
    assert out[0, 100] == pytest.approx([1.0, 1.0, 0.0], **TOL)


def test_normalised_variants_ignore_position_and_scale():
    x, y = resting(5, seed=5), resting(6, seed=6)
    moved = 3.0 * x + np.array([10.0, -4.0, 2.0])
    for variant in ("pose_eval_ndtwp", "pose_eval_ndtw_mje"):
        assert pose_eval_distance(moved, y, variant) == pytest.approx(pose_eval_distance(x, y, variant), **TOL)
    assert pose_eval_distance(moved, y, "pose_eval_dtwp") != pytest.approx(pose_eval_distance(x, y, "pose_eval_dtwp"))


# --- keypoint selections -----------------------------------------------------------------------------------------

def test_selection_sizes_and_named_points():
    assert {k: len(v) for k, v in SELECTIONS.items()} == {
        "hands": 42, "no_legs": 543, "reduce_holistic": 178, "upper_body": 176, "youtube_asl": 85}
    assert len(keypoint_selection("youtube_asl", 543)) == 83  # no refined iris points in a 468-point face
    assert holistic_index("POSE_LANDMARKS", "LEFT_SHOULDER") == 11
    assert holistic_index("FACE_LANDMARKS", 61) == 33 + 61
    assert holistic_index("LEFT_HAND_LANDMARKS", "WRIST") == 511
    assert holistic_index("RIGHT_HAND_LANDMARKS", "PINKY_TIP") == 552
    assert holistic_index("RIGHT_HAND_LANDMARKS", "WRIST", joints=543) == 33 + 468 + 21
    assert SELECTIONS["hands"].tolist() == list(range(511, 553))
    assert not set(range(23, 33)) & set(SELECTIONS["no_legs"].tolist())  # hips, knees, ankles, heels, feet
    assert [i for i in SELECTIONS["upper_body"] if i < 33] == [11, 12, 13, 14, 15, 16]
    assert [i for i in SELECTIONS["reduce_holistic"] if i < 33] == [11, 12, 13, 14, 15, 16, 23, 24]
    assert {33 + 468, 33 + 473, 11, 12, 13, 14, 23, 24} <= set(SELECTIONS["youtube_asl"].tolist())


def holistic_pose(face_points: int = 478):
    """A pose-format Pose in the holistic layout whose x coordinate is each point's index."""
    pytest.importorskip("pose_format")
    try:
        from pose_format.utils.holistic import holistic_components
        components = [copy.deepcopy(c) for c in holistic_components() if c.name != "POSE_WORLD_LANDMARKS"]
    except ImportError as err:  # pose-format's holistic header needs mediapipe on some installs
        pytest.skip(f"pose-format's holistic header is unavailable: {err}")
    from pose_format import Pose
    from pose_format.numpy import NumPyPoseBody
    from pose_format.pose_header import PoseHeader, PoseHeaderDimensions

    for c in components:
        if c.name == "FACE_LANDMARKS":
            c.points = [str(i) for i in range(face_points)]
    header = PoseHeader(0.2, PoseHeaderDimensions(width=1, height=1, depth=1), components)
    n = header.total_points()
    data = np.zeros((2, 1, n, 3))
    data[..., 0] = np.arange(n)
    return Pose(header, NumPyPoseBody(fps=25, data=np.ma.masked_array(data), confidence=np.ones((2, 1, n))))


def test_selections_match_pose_formats_processors():
    pose = holistic_pose()
    from pose_format.utils.generic import pose_hide_legs, reduce_holistic

    def kept(p):
        return sorted(int(v) for v in np.asarray(p.body.data[0, 0, :, 0]))

    assert kept(pose) == list(range(J))
    assert kept(pose.get_components(["LEFT_HAND_LANDMARKS", "RIGHT_HAND_LANDMARKS"])) == SELECTIONS["hands"].tolist()
    assert kept(pose_hide_legs(pose.copy(), remove=True)) == SELECTIONS["no_legs"].tolist()
    assert kept(reduce_holistic(pose.copy())) == SELECTIONS["reduce_holistic"].tolist()
    assert kept(reduce_holistic(pose_hide_legs(pose.copy(), remove=True))) == SELECTIONS["upper_body"].tolist()


def test_shoulder_normalisation_matches_pose_format():
    pose = holistic_pose()
    rng = np.random.default_rng(7)
    data = rng.normal(size=(4, 1, J, 3))
    confidence = np.ones((4, 1, J))
    confidence[1, 0, R_SHOULDER] = 0  # pose-format masks points of zero confidence
    mask = np.repeat((confidence == 0)[..., None], 3, axis=-1)
    pose.body.data, pose.body.confidence = np.ma.masked_array(data, mask=mask), confidence
    expected = np.asarray(pose.normalize().body.data[:, 0])
    ours = normalize_by_shoulders(data[:, 0], mask[:, 0])
    assert ours[~mask[:, 0]] == pytest.approx(expected[~mask[:, 0]], **TOL)


# --- errors ------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("pred", "ref", "variant", "message"), [
    (np.zeros((3, 42, 3)), np.zeros((3, 42, 3)), "pose_eval_dtwp", r"pose_eval_dtwp: 42 joints .* expected 553"),
    (np.zeros((0, J, 3)), np.zeros((3, J, 3)), "pose_eval_dtwp", r"pred is empty"),
    (np.zeros((3, 2, 3)), np.zeros((0, 2, 3)), "pose_eval_dtw", r"ref is empty"),
    (np.zeros((3, 6)), np.zeros((3, 6)), "pose_eval_dtw", r"pred has shape \(3, 6\); expected \(T, J, D\)"),
    (np.zeros((3, 4, 3)), np.zeros((3, 5, 3)), "pose_eval_dtw", r"pred has 4 joints .* ref has 5"),
    (np.zeros((3, 4, 3)), np.zeros((3, 4, 3)), "pose_eval_dtw_feet", r"unknown variant 'pose_eval_dtw_feet'"),
    (np.full((3, J, 3), np.nan), np.zeros((3, J, 3)), "pose_eval_ndtwp", r"pred has no frame with both .* shoulders"),
    (np.zeros((3, J, 3)), np.zeros((3, J, 3)), "pose_eval_ndtwp", r"pred's shoulders coincide"),
    (np.zeros((3, J, 1)), np.zeros((3, J, 1)), "pose_eval_dtwp", r"trimming compares image y"),
])
def test_errors_name_what_is_wrong(pred, ref, variant, message):
    with pytest.raises(ValueError, match=message):
        pose_eval_distance(pred, ref, variant)


def test_mask_and_lookup_errors():
    with pytest.raises(ValueError, match=r"mask of pred has shape \(2, 3\); expected \(3, 4\)"):
        pose_eval_distance(np.zeros((3, 4, 2)), np.zeros((3, 4, 2)), "pose_eval_dtw", mask_pred=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="unknown keypoint selection 'feet'"):
        keypoint_selection("feet")
    with pytest.raises(ValueError, match="POSE_LANDMARKS has no point 'TAIL'"):
        holistic_index("POSE_LANDMARKS", "TAIL")
    with pytest.raises(ValueError, match="600 joints is not the pose-format holistic layout"):
        keypoint_selection("hands", 600)


# --- corpus ------------------------------------------------------------------------------------------------------

def test_corpus_mean_by_hand():
    pred = np.zeros((3, 1, 3))
    pred[:, 0, 0] = [0.0, 1.0, 2.0]
    ref = np.zeros((2, 1, 3))
    ref[:, 0, 0] = [0.0, 2.0]  # distance 1 (first test)
    same = np.ones((2, 1, 3))  # distance 0
    scores = pose_eval_corpus([pred, same], [ref, same], variants=["pose_eval_dtw"])
    assert scores == {"pose_eval_dtw": pytest.approx(0.5, **TOL)}
    x, y = resting(3, seed=8), resting(4, seed=9)
    both = pose_eval_corpus([x, y], [y, x])
    assert set(both) == set(VARIANTS)
    assert both["pose_eval_dtwp"] == pytest.approx(pose_eval_distance(x, y), **TOL)  # symmetric pairs


def test_corpus_errors():
    with pytest.raises(ValueError, match="2 predictions but 1 references"):
        pose_eval_corpus([np.zeros((1, 1, 2))] * 2, [np.zeros((1, 1, 2))])
    with pytest.raises(ValueError, match="no pairs"):
        pose_eval_corpus([], [])
