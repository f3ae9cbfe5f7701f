"""Pose-sequence distances of pose-evaluation (Jiang et al., "Meaningful Pose-Based Sign Language Evaluation",
WMT 2025): definition ``"pose_eval"``, re-implemented over numpy (the peer installs from git only).

Peer: ``sign-language-processing/pose-evaluation``. A metric there is a ``DistanceMetric``
(``pose_evaluation/metrics/distance_metric.py``): a list of pose preprocessors run on each pose of a pair, then
a distance measure on the two ``pose.body.data`` arrays. Every variant here uses its DTW measure,
``DTWDTAIImplementationDistanceMeasure`` (``pose_evaluation/metrics/dtw_metric.py``, ``use_fast=True``):

- one DTW **per keypoint trajectory** (each keypoint warps on its own path), the keypoint's (T, D) track of
  person 0 against the other pose's; dtaidistance's ``dtw_ndim.distance_fast`` with its defaults (no window,
  no ``psi`` relaxation, no penalty, ``max_dist`` / pruning off): ``C[i, j] = ||a_i - b_j||^2`` (squared
  Euclidean over all D coordinates), ``S[i, j] = C[i, j] + min(S[i-1, j-1], S[i-1, j], S[i, j-1])`` from
  ``S[0, 0] = C[0, 0]``, distance ``sqrt(S[T1-1, T2-1])``. The same recursion runs here
  (:func:`m3t.metrics.dtw.accumulate`, batched over keypoints) instead of adding dtaidistance;
- the keypoint distances are averaged (``aggregation_strategy="mean"``); a non-finite mean is replaced by the
  measure's ``default_distance`` with a ``RuntimeWarning`` (the peer's fallback). The sequences are never
  padded (``create_metrics.py`` only zero-pads for non-DTW measures).

Missing values. pose-format masks a point whose confidence is 0; here a point is missing where ``mask`` is True
(a (T, J) mask covers every coordinate, a (T, J, D) mask single coordinates) or a coordinate is NaN / inf
(the peer's ``pose_mask_invalid_values``). ``FillMaskedOrInvalidValuesPoseProcessor(v)`` replaces every missing
coordinate with the constant ``v`` after normalisation and selection. A pipeline without that step hands the
measure ``np.asarray`` of the masked array, i.e. the data under the mask, which pose-format stores as 0 and
numpy's masked arithmetic leaves untouched through ``normalize``: those variants fill with 0.

Preprocessing steps, in the peer's order (trim, normalise, select, fill):

- **trim** (``TrimMeaninglessFramesPoseProcessor`` -> spoken-to-signed ``trim_pose(pose, start, end)`` of
  ``gloss_to_pose/concatenate.py``; :func:`signing_span`): per side, the frames where the POSE wrist is above
  the elbow (image y smaller; frames where either is missing do not count), widened by 5 frames each way but not
  past the first / last frame where that wrist is present; the union over both sides, the whole clip when
  neither wrist is ever raised. spoken-to-signed is an unpinned git dependency of the peer and its
  ``trim_pose`` changed over time: an older revision cut on hand-component visibility instead, and the newest
  drops the ``start`` / ``end`` arguments the peer passes. This elbow rule is the one whose output matches the
  peer notebook's trimmed lengths (63 and 45 frames) and its DTWp value;
- **normalise** (``NormalizePosesProcessor`` -> pose-format ``Pose.normalize``; :func:`normalize_by_shoulders`):
  subtract the mean over frames of the shoulder midpoint, divide by the mean shoulder distance (D-dimensional
  Euclidean), both over the frames where both POSE shoulders are present;
- **select** keypoints (:data:`SELECTIONS`, index tables into the holistic layout below).

Variants (:data:`VARIANTS`; names carry the definition name):

- ``pose_eval_dtw``: DTW over every given point, no preprocessing (``DistanceMetric`` with
  ``pose_preprocessors=[]``): missing points are 0;
- ``pose_eval_dtw_hands``: ``GetHandsOnlyHolisticPoseProcessor`` only: the 42 hand points, missing are 0;
- ``pose_eval_ndtw_mje``: the normalised DTW-MJE of ``pose_evaluation/examples/example_metric_construction.py``
  ("n-dtai-DTW-MJE", ``get_standard_pose_processors(reduce_holistic_to_face_and_upper_body=True,
  zero_pad_shorter=False)``): trim, normalise, legs removed and ``reduce_holistic`` (selection
  ``"upper_body"``), missing are 0 (after normalising), default distance 0;
- ``pose_eval_dtwp``: DTWp, the README's metric and one of the paper's two best (``create_metrics.py``
  ``construct_metric`` name ``startendtrimmed_unnormalized_hands_defaultdist0.0_nointerp_dtw_fillmasked10.0``):
  trim, hands, missing filled with 10.0, default distance 0. **The default.**
- ``pose_eval_ndtwp``: nDTWp, the paper's other best (``untrimmed_normalizedbyshoulders_hands_defaultdist1.0_
  nointerp_dtw_fillmasked1.0``): normalise, hands, missing filled with 1.0, default distance 1.0.

With the peer's test files (``colin-1-HOUSE.pose`` against ``colin-HOUSE-needs-trim.pose``) this code gives
DTWp 1991.93 after trimming to 63 and 45 frames, and nDTWp 4.15845, the values its example notebook prints.

Layout: pose-format's MediaPipe-Holistic components in header order, ``POSE_LANDMARKS`` 33, ``FACE_LANDMARKS``
478 (refined; 468 also accepted), ``LEFT_HAND_LANDMARKS`` 21, ``RIGHT_HAND_LANDMARKS`` 21, without world
landmarks (the peer's ``RemoveWorldLandmarksProcessor`` drops them). ``pose_eval_dtw`` takes any J.

Axis legend: T frames (T1 prediction, T2 reference), J joints, K selected keypoints, D coordinates (x, y[, z]).
"""
from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from m3t.body.landmarks import HAND_LANDMARKS, POSE_LANDMARKS
from m3t.metrics.dtw import accumulate

DEFINITION = "pose_eval"
POSE_POINTS = tuple(name.upper() for name in POSE_LANDMARKS)  # pose-format's point names
HAND_POINTS = tuple(name.upper() for name in HAND_LANDMARKS)
FACE_REFINED, FACE_MESH = 478, 468
HOLISTIC_JOINTS = 33 + FACE_REFINED + 2 * 21  # 553
CHUNK_ELEMENTS = 1 << 22  # (T1 x T2 x keypoints) DTW cells held at once
TRIM_MARGIN = 5  # frames kept on each side of the raised-wrist span (spoken-to-signed)

# MediaPipe FACEMESH_CONTOURS points, as pose-format's ``reduce_holistic`` (pose_format/utils/generic.py) keeps.
FACE_CONTOURS = (
    0, 7, 10, 13, 14, 17, 21, 33, 37, 39, 40, 46, 52, 53, 54, 55, 58, 61, 63, 65, 66, 67, 70, 78, 80, 81, 82, 84,
    87, 88, 91, 93, 95, 103, 105, 107, 109, 127, 132, 133, 136, 144, 145, 146, 148, 149, 150, 152, 153, 154, 155,
    157, 158, 159, 160, 161, 162, 163, 172, 173, 176, 178, 181, 185, 191, 234, 246, 249, 251, 263, 267, 269, 270,
    276, 282, 283, 284, 285, 288, 291, 293, 295, 296, 297, 300, 308, 310, 311, 312, 314, 317, 318, 321, 323, 324,
    332, 334, 336, 338, 356, 361, 362, 365, 373, 374, 375, 377, 378, 379, 380, 381, 382, 384, 385, 386, 387, 388,
    389, 390, 397, 398, 400, 402, 405, 409, 415, 454, 466,
)
# YouTube-ASL's 37 face points (Uthus et al. 2023), the peer's get_youtube_asl_mediapipe_keypoints
# (pose_evaluation/utils/pose_utils.py); the iris centres 468 and 473 only exist in the refined face.
YOUTUBE_ASL_FACE = (0, 4, 13, 14, 17, 33, 37, 39, 46, 52, 55, 61, 64, 81, 82, 93, 133, 151, 152, 159, 172, 178,
                    181, 263, 269, 276, 282, 285, 291, 294, 311, 323, 362, 386, 397)
YOUTUBE_ASL_IRIS = (468, 473)
YOUTUBE_ASL_POSE = ("LEFT_SHOULDER", "RIGHT_SHOULDER", "LEFT_ELBOW", "RIGHT_ELBOW", "LEFT_HIP", "RIGHT_HIP")
# pose-format's pose_hide_legs (0.15): hips, knees, ankles, heels, foot indices.
LEG_POINTS = tuple(f"{side}_{part}" for side in ("LEFT", "RIGHT") for part in ("KNEE", "ANKLE", "HEEL",
                                                                                "FOOT_INDEX", "HIP"))
SELECTION_NAMES = ("hands", "no_legs", "reduce_holistic", "upper_body", "youtube_asl")
# reduce_holistic drops POSE points naming any of these (face, finger and foot points of the body model).
REDUCE_DROPPED = ("EAR", "NOSE", "MOUTH", "EYE", "THUMB", "PINKY", "INDEX", "KNEE", "ANKLE", "HEEL", "FOOT_INDEX")


def _face_points(joints: int, what: str) -> int:
    face = joints - 33 - 42
    if face not in (FACE_REFINED, FACE_MESH):
        raise ValueError(f"{what}: {joints} joints is not the pose-format holistic layout; expected "
                         f"{HOLISTIC_JOINTS} (POSE_LANDMARKS 33, FACE_LANDMARKS 478, LEFT_HAND_LANDMARKS 21, "
                         f"RIGHT_HAND_LANDMARKS 21) or {HOLISTIC_JOINTS - 10} (468 face points)")
    return face


def holistic_index(component: str, point: str | int, joints: int = HOLISTIC_JOINTS) -> int:
    """Index of ``point`` of ``component`` (e.g. ``"POSE_LANDMARKS", "LEFT_SHOULDER"``, ``"FACE_LANDMARKS", 61``)
    on the joint axis of the pose-format holistic layout with ``joints`` points (553 or 543)."""
    face = _face_points(joints, "holistic_index")
    sizes = {"POSE_LANDMARKS": (0, POSE_POINTS), "FACE_LANDMARKS": (33, tuple(str(i) for i in range(face))),
             "LEFT_HAND_LANDMARKS": (33 + face, HAND_POINTS), "RIGHT_HAND_LANDMARKS": (54 + face, HAND_POINTS)}
    if component not in sizes:
        raise ValueError(f"{DEFINITION}: unknown component {component!r}; expected one of {list(sizes)}")
    start, points = sizes[component]
    if str(point) not in points:
        raise ValueError(f"{DEFINITION}: {component} has no point {point!r} ({len(points)} points)")
    return start + points.index(str(point))


def keypoint_selection(name: str, joints: int = HOLISTIC_JOINTS) -> np.ndarray:
    """Sorted joint indices of selection ``name`` in the holistic layout with ``joints`` points (553 or 543).

    ``"hands"``: ``GetHandsOnlyHolisticPoseProcessor`` (42). ``"no_legs"``: ``removelegsandworld`` of
    ``construct_metric``, all but :data:`LEG_POINTS` (543 of 553). ``"reduce_holistic"``: pose-format's
    ``reduce_holistic`` (``ReduceHolisticPoseProcessor``): shoulders, elbows, wrists, hips, the 128 face contour
    points and both hands (178). ``"upper_body"``: legs removed, then ``reduce_holistic``, as in the standard
    processors (176). ``"youtube_asl"``: ``GetYoutubeASLKeypointsPoseProcessor``, 6 pose + 37 face (35 without
    the refined iris) + 42 hand points (85).
    """
    face = _face_points(joints, "keypoint_selection")
    pose = {p: holistic_index("POSE_LANDMARKS", p, joints) for p in POSE_POINTS}
    hands = list(range(33 + face, joints))
    contours = [33 + i for i in FACE_CONTOURS]
    reduced_pose = [i for p, i in pose.items() if not any(word in p for word in REDUCE_DROPPED)]
    if name == "hands":
        out = hands
    elif name == "no_legs":
        out = [i for i in range(joints) if i not in {pose[p] for p in LEG_POINTS}]
    elif name == "reduce_holistic":
        out = reduced_pose + contours + hands
    elif name == "upper_body":
        out = [i for i in reduced_pose if POSE_POINTS[i] not in LEG_POINTS] + contours + hands
    elif name == "youtube_asl":
        iris = YOUTUBE_ASL_IRIS if face == FACE_REFINED else ()
        out = [pose[p] for p in YOUTUBE_ASL_POSE] + [33 + i for i in YOUTUBE_ASL_FACE + iris] + hands
    else:
        raise ValueError(f"{DEFINITION}: unknown keypoint selection {name!r}; expected one of {SELECTION_NAMES}")
    return np.array(sorted(out), dtype=np.int64)


SELECTIONS = {name: keypoint_selection(name) for name in SELECTION_NAMES}  # for the 553-joint layout


@dataclass(frozen=True)
class PoseEvalVariant:
    """One metric of the definition: preprocessing switches, selection (``None``: every joint) and fills."""

    name: str
    selection: str | None
    trim: bool
    normalize: bool
    fill_value: float
    default_distance: float


VARIANTS = {v.name: v for v in (
    PoseEvalVariant("pose_eval_dtw", None, trim=False, normalize=False, fill_value=0.0, default_distance=0.0),
    PoseEvalVariant("pose_eval_dtw_hands", "hands", trim=False, normalize=False, fill_value=0.0,
                    default_distance=0.0),
    PoseEvalVariant("pose_eval_ndtw_mje", "upper_body", trim=True, normalize=True, fill_value=0.0,
                    default_distance=0.0),
    PoseEvalVariant("pose_eval_dtwp", "hands", trim=True, normalize=False, fill_value=10.0, default_distance=0.0),
    PoseEvalVariant("pose_eval_ndtwp", "hands", trim=False, normalize=True, fill_value=1.0, default_distance=1.0),
)}
DEFAULT_VARIANT = "pose_eval_dtwp"


def _checked(x: np.ndarray, mask: np.ndarray | None, label: str) -> tuple[np.ndarray, np.ndarray]:
    """(T, J, D) float64 copy and its (T, J, D) missing mask (given mask or non-finite)."""
    x = np.array(x, dtype=np.float64)
    if x.ndim != 3:
        raise ValueError(f"{DEFINITION}: {label} has shape {x.shape}; expected (T, J, D) frames x joints x coords")
    if x.shape[0] == 0 or x.shape[1] == 0 or x.shape[2] == 0:
        raise ValueError(f"{DEFINITION}: {label} is empty (shape {x.shape}); a distance needs at least one frame, "
                         "joint and coordinate per sequence")
    missing = ~np.isfinite(x)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape == x.shape[:2]:
            mask = mask[..., None]
        elif mask.shape != x.shape:
            raise ValueError(f"{DEFINITION}: mask of {label} has shape {mask.shape}; expected {x.shape[:2]} "
                             f"(T, J) or {x.shape} (T, J, D), True where a value is missing")
        missing |= mask
    return x, missing


def signing_span(x: np.ndarray, missing: np.ndarray) -> tuple[int, int]:
    """[start, stop) frames kept by the peer's trimming of a (T, J, D) holistic pose (see the module doc)."""
    starts, stops = [], []
    for side in ("LEFT", "RIGHT"):
        wrist, elbow = (holistic_index("POSE_LANDMARKS", f"{side}_{p}", x.shape[1]) for p in ("WRIST", "ELBOW"))
        seen = np.flatnonzero(~missing[:, wrist].any(-1))
        both = ~missing[:, wrist].any(-1) & ~missing[:, elbow].any(-1)
        raised = np.flatnonzero(both & (x[:, wrist, 1] < x[:, elbow, 1]))  # image y grows downwards
        if raised.size:
            starts.append(max(seen[0], raised[0] - TRIM_MARGIN))
            stops.append(min(seen[-1] + 1, raised[-1] + 1 + TRIM_MARGIN))
    return (int(min(starts)), int(max(stops))) if starts else (0, len(x))


def normalize_by_shoulders(x: np.ndarray, missing: np.ndarray, label: str = "pose") -> np.ndarray:
    """pose-format's ``Pose.normalize`` of a (T, J, D) holistic pose: shoulder-midpoint mean to the origin, mean
    shoulder width to 1, over frames with both shoulders present. Returns a new (T, J, D) array."""
    right, left = (holistic_index("POSE_LANDMARKS", f"{s}_SHOULDER", x.shape[1]) for s in ("RIGHT", "LEFT"))
    both = ~missing[:, right].any(-1) & ~missing[:, left].any(-1)  # (T,)
    if not both.any():
        raise ValueError(f"{DEFINITION}: {label} has no frame with both POSE_LANDMARKS shoulders present; "
                         "shoulder normalisation needs them (use a variant without normalisation)")
    p1, p2 = x[both, right], x[both, left]  # (T', D)
    width = float(np.sqrt(((p1 - p2) ** 2).sum(-1)).mean())
    if not width > 0:
        raise ValueError(f"{DEFINITION}: {label}'s shoulders coincide (mean width {width}); cannot normalise")
    return (x - ((p1 + p2) / 2).mean(0)) / width


def preprocess(x: np.ndarray, variant: str | PoseEvalVariant = DEFAULT_VARIANT, mask: np.ndarray | None = None,
               label: str = "pose") -> np.ndarray:
    """(T, J, D) pose -> the (T', K, D) filled keypoint trajectories ``variant``'s DTW compares."""
    v = _variant(variant)
    x, missing = _checked(x, mask, label)
    if v.selection is not None or v.trim or v.normalize:
        try:
            _face_points(x.shape[1], v.name)
        except ValueError as err:
            raise ValueError(f"{err}; {label} has shape {x.shape}") from None
    if v.trim:
        if x.shape[2] < 2:
            raise ValueError(f"{v.name}: trimming compares image y; {label} has {x.shape[2]} coordinate(s)")
        start, stop = signing_span(x, missing)
        x, missing = x[start:stop], missing[start:stop]
    if v.normalize:
        x = normalize_by_shoulders(x, missing, label)
    if v.selection is not None:
        keep = keypoint_selection(v.selection, x.shape[1])
        x, missing = x[:, keep], missing[:, keep]
    return np.where(missing, v.fill_value, x)


def trajectory_distances(pred: np.ndarray, ref: np.ndarray, chunk_elements: int = CHUNK_ELEMENTS) -> np.ndarray:
    """(K,) dtaidistance ``dtw_ndim`` distances of each keypoint's (T1, D) track in ``pred`` (T1, K, D) against
    its (T2, D) track in ``ref`` (T2, K, D): sqrt of the least accumulated squared Euclidean cost."""
    t1, t2, k = len(pred), len(ref), pred.shape[1]
    step = max(1, chunk_elements // (t1 * t2))
    out = np.empty(k)
    with np.errstate(over="ignore", invalid="ignore"):  # huge inputs overflow to inf: the default distance
        for lo in range(0, k, step):
            a, b = pred[:, lo:lo + step], ref[:, lo:lo + step]
            costs = np.ascontiguousarray(((a[:, None] - b[None]) ** 2).sum(-1))  # (T1, T2, k')
            out[lo:lo + step] = np.sqrt(accumulate(costs)[-1, -1])
    return out


def pose_eval_distance(pred: np.ndarray, ref: np.ndarray, variant: str | PoseEvalVariant = DEFAULT_VARIANT,
                       mask_pred: np.ndarray | None = None, mask_ref: np.ndarray | None = None) -> float:
    """Distance of one (T1, J, D) prediction to its (T2, J, D) reference under ``variant`` (lower is better).

    Masks are (T, J) or (T, J, D), True where a value is missing; NaN / inf count as missing too.
    """
    v = _variant(variant)
    pred, ref = np.asarray(pred), np.asarray(ref)
    if pred.ndim == ref.ndim == 3 and pred.shape[1:] != ref.shape[1:]:
        raise ValueError(f"{v.name}: pred has {pred.shape[1]} joints x {pred.shape[2]} coords but ref has "
                         f"{ref.shape[1]} x {ref.shape[2]}; both must use the same layout")
    a, b = preprocess(pred, v, mask_pred, "pred"), preprocess(ref, v, mask_ref, "ref")
    distance = float(trajectory_distances(a, b).mean())
    if not math.isfinite(distance):
        warnings.warn(f"{v.name}: non-finite distance for pred {pred.shape} / ref {ref.shape}; using the "
                      f"default distance {v.default_distance}", RuntimeWarning, stacklevel=2)
        distance = v.default_distance
    return distance


def pose_eval_corpus(preds: Sequence[np.ndarray], refs: Sequence[np.ndarray],
                     variants: Sequence[str | PoseEvalVariant] = tuple(VARIANTS),
                     masks_pred: Sequence[np.ndarray | None] | None = None,
                     masks_ref: Sequence[np.ndarray | None] | None = None) -> dict[str, float]:
    """Mean distance over pairs for each variant, keyed by variant name (``{"pose_eval_dtwp": ...}``)."""
    if len(preds) != len(refs):
        raise ValueError(f"{DEFINITION}: {len(preds)} predictions but {len(refs)} references; give one per pair")
    if len(preds) == 0:
        raise ValueError(f"{DEFINITION}: no pairs to score")
    masks_pred = [None] * len(preds) if masks_pred is None else masks_pred
    masks_ref = [None] * len(refs) if masks_ref is None else masks_ref
    if len(masks_pred) != len(preds) or len(masks_ref) != len(refs):
        raise ValueError(f"{DEFINITION}: {len(masks_pred)} / {len(masks_ref)} masks for {len(preds)} pairs")
    out = {}
    for variant in variants:
        v = _variant(variant)
        out[v.name] = float(np.mean([pose_eval_distance(p, r, v, mp, mr)
                                     for p, r, mp, mr in zip(preds, refs, masks_pred, masks_ref)]))
    return out


def _variant(variant: str | PoseEvalVariant) -> PoseEvalVariant:
    if isinstance(variant, PoseEvalVariant):
        return variant
    if variant not in VARIANTS:
        raise ValueError(f"{DEFINITION}: unknown variant {variant!r}; expected one of {list(VARIANTS)}")
    return VARIANTS[variant]
