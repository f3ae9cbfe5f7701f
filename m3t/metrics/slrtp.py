"""Definition "slrtp": the evaluation of the SLRTP 2025 sign-production challenge (CVPR 2025), text and poses.

The challenge's code is ``walsharry/SLRTP-Sign-Production-Evaluation`` (read at commit ``bf4129e``), re-implemented
here (not pasted). Its ``main.py`` back-translates the produced poses with an SL-T model
(``back_translation/back_translate.py``; not part of this module, which scores the sentences such a model wrote),
then calls ``metrics.py``: ``bleu``, ``chrf``, ``rouge`` and ``wer`` on the text, ``pose_dtw_mje``,
``pose_distance`` and ``pose_length`` on the poses. Keys carry the definition name.

**Text** (:func:`slrtp_text_metrics`; one reference per hypothesis; corpus level unless said; 0-100):

- ``slrtp_bleu1..4``: ``metrics.bleu``, i.e. ``raw_corpus_bleu`` of the sacreBLEU 1.4.2 vendored in
  ``external_metrics/sacrebleu.py``: whitespace tokens (``tokenize="none"``), text as given (no lower-casing:
  PHOENIX-2014T's references and the model's vocabulary are lower-case already), ``floor`` smoothing with value 0
  (none), cumulative BLEU-n of one 4-gram computation (an order no hypothesis reaches scores 0). That is the
  arithmetic of definition "slt" (:func:`m3t.metrics.text.slt_bleu_from_statistics`, reused) without its
  lower-casing;
- ``slrtp_chrf``: ``metrics.chrf``, sacreBLEU 2's ``CHRF()`` with its defaults (character 6-grams, no word
  n-grams, beta 2, case-sensitive, whitespace removed), statistics summed over the corpus. The peer pins
  sacrebleu 2.4.0; the installed sacrebleu 2.x computes it here;
- ``slrtp_rouge_l``: ``metrics.rouge`` over ``external_metrics/rouge.py`` ``calc_score`` (MS-COCO ROUGE-L):
  tokens are ``text.split(" ")`` (so ``""`` is one empty token and a doubled space makes an empty token), the
  F-measure ``(1 + b^2) P R / (R + b^2 P)`` of the LCS with ``b = 1.2``, 0 when P or R is 0, mean over sentences;
- ``slrtp_wer``: ``metrics.wer``, jiwer 3.1.0 ``wer(references, hypotheses, ...)`` with, on both sides,
  ``ExpandCommonEnglishContractions, ToLowerCase, RemoveMultipleSpaces, Strip, RemovePunctuation,
  ReduceToListOfListOfWords`` (:func:`slrtp_wer_words`). WER = all word-level Levenshtein edits / all reference
  words (a corpus ratio, not a mean of sentence WERs; it can pass 100). A reference left with no word is an error,
  as in jiwer; an empty hypothesis is all deletions.

**Poses** (:func:`slrtp_pose_metrics` per pair, :func:`slrtp_pose_corpus_metrics` as the challenge aggregates;
arrays (T, J, D): T frames, J joints, D coordinates; results in the units of the coordinates):

- rate (:func:`slrtp_eval_rate`): ``main.py`` keeps every second frame of the predictions when ``--fps`` is 25
  (any other value: as given) and of the references always (released at 25 fps), so everything below, the
  back-translation included, runs at 12.5 fps. ``pred_fps`` and ``ref_fps`` (both 25 by default) apply the rule;
- ``slrtp_dtw_mje`` (``pose_dtw_mje``): FastDTW (fastdtw 0.3.4 ``fastdtw(pred, ref, dist=...)``, radius 1)
  between frames flattened to J*D vectors, frame distance the Euclidean norm of the whole difference; along the
  path, the Euclidean error of each joint, averaged over every path step and joint of every pair pooled
  (``torch.cat`` then ``mean``: a longer path weighs more). All J joints, no normalisation or alignment. A pair
  with an empty sequence is skipped (the peer's ``continue``); ``slrtp_dtw_mje_pairs`` counts the pairs scored;
- ``slrtp_wrist_path_ratio`` (``pose_distance``, the README's "Total Distance"): a wrist's path length is the sum
  of its Euclidean steps between consecutive frames; per wrist, the mean over predictions divided by the mean
  over references (a ratio of means), then the mean of the left and right ratios; 1 is ideal. The wrists are the
  body's ``LWrist`` and ``RWrist`` (joints 5 and 2), not the hand roots 29 and 8. A zero reference path gives
  ``inf`` (``nan`` when the prediction's is zero too), as the peer's tensor division does;
- ``slrtp_duration_ratio`` (``pose_length``, "Average Duration"): the mean over pairs of prediction frames /
  reference frames, counted after the rate step.

**FastDTW** (:func:`slrtp_fastdtw`), Salvador & Chan 2007 as fastdtw 0.3.4 runs it, implemented here (no
dependency): when either series has fewer than ``radius + 2`` frames, full DTW; else both are halved (means of
frame pairs, an odd last frame dropped), solved recursively, and the coarse path, widened by ``radius`` cells in
every direction and doubled, is the window of a DTW at full resolution. The package has two bodies that differ
in details; ``variant`` picks one:

- ``"compiled"`` (default): ``fastdtw/_fastdtw.pyx``, what ``pip install fastdtw`` builds on the Python 3.8 the
  README installs. A step comes from ``(i-1, j)`` only when strictly cheaper than both others, else from
  ``(i, j-1)`` when strictly cheaper than the diagonal, else from the diagonal (ties go to the diagonal); a
  diagonal step into ``(i, j)`` also needs ``(i-1, j)`` in the window (its bound check), and fine rows past the
  coarse path's end take the bounds of its last row;
- ``"python"``: ``fastdtw/fastdtw.py``, the fallback installed when the extension does not compile (on Python
  >= 3.11 the shipped C++ does not): ties prefer ``(i-1, j)``, then ``(i, j-1)``; any diagonal inside the window
  counts; rows past the coarse end are bounded by the path cells within ``radius``.

Both were checked path for path against fastdtw 0.3.4's two bodies; on real-valued poses, where exact ties do
not occur, they rarely differ.

**Missing joints** (an extension: the challenge has none, its 3D uplift fills every joint; with nothing missing
all results equal the peer's): a joint is missing where ``mask`` is False or a coordinate is NaN. It adds nothing
to a frame distance (as if both frames had it at the same place); halving averages the present values of a pair;
DTW-MJE averages over the (step, joint) terms present on both sides (NaN for a pair with none); a wrist's path
joins the frames where it is present. Sums are in float64 (the peer's MJE is float32 torch).

**Layout**: 178 keypoints (README "Skeleton Format", ``skeleton_def.py`` ``RELEASE_JOINTS``, the same table as
``walsharry/SLRTP_Skeleton_Keypoint_information`` ``keypoint_def.py``): 8 body joints (:data:`SLRTP_BODY_JOINTS`),
the right hand 8-28 and the left hand 29-49 (21 MediaPipe hand landmarks each), and 128 face points 50-177 from
MediaPipe's 478-point face mesh (:data:`SLRTP_FACE_MESH_INDICES`, ``make_128_face_from_478.py``
``face_478_to_128``), uplifted to 3D (Ivashechkin et al. 2023). The face slots' order comes from an ``order_128``
mapping that file never defines, so face slot k is not known to be mesh point ``SLRTP_FACE_MESH_INDICES[k]``.
"""
from __future__ import annotations

import math
import re
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from sacrebleu.metrics import CHRF

from m3t.metrics.text import (
    _check,
    bleu_statistics,
    rouge_l_sentence,
    slt_bleu_from_statistics,
)

SLRTP_DEFINITION = "slrtp"
SLRTP_ROUGE_BETA = 1.2
SLRTP_RELEASE_FPS = 25  # the rate the challenge data are released at; halved before scoring
SLRTP_FASTDTW_RADIUS = 1
SLRTP_FASTDTW_VARIANTS = ("compiled", "python")

SLRTP_BODY_JOINTS = ("RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "RHip", "LHip")
_HAND = ("HWrist", "Thumb1CMC", "Thumb2Knuckles", "Thumb3IP", "Thumb4FingerTip") + tuple(
    f"{finger}{k}{part}" for finger in ("Index", "Middle", "Ring", "Pinky")
    for k, part in ((1, "Knuckles"), (2, "PIP"), (3, "DIP"), (4, "FingerTip")))
SLRTP_JOINT_NAMES = (SLRTP_BODY_JOINTS + tuple("R" + n for n in _HAND) + tuple("L" + n for n in _HAND)
                     + tuple(f"face{k}" for k in range(128)))
SLRTP_NUM_JOINTS = len(SLRTP_JOINT_NAMES)  # 178
SLRTP_RIGHT_WRIST = SLRTP_JOINT_NAMES.index("RWrist")  # 2
SLRTP_LEFT_WRIST = SLRTP_JOINT_NAMES.index("LWrist")  # 5
SLRTP_RIGHT_HAND = slice(8, 29)
SLRTP_LEFT_HAND = slice(29, 50)
SLRTP_FACE = slice(50, 178)
SLRTP_FACE_MESH_INDICES = (
    0, 7, 10, 13, 14, 17, 21, 33, 37, 39, 40, 46, 52, 53, 54, 55, 58, 61, 63, 65, 66, 67, 70, 78, 80, 81, 82, 84, 87,
    88, 91, 93, 95, 103, 105, 107, 109, 127, 132, 133, 136, 144, 145, 146, 148, 149, 150, 152, 153, 154, 155, 157, 158,
    159, 160, 161, 162, 163, 172, 173, 176, 178, 181, 185, 191, 234, 246, 249, 251, 263, 267, 269, 270, 276, 282, 283,
    284, 285, 288, 291, 293, 295, 296, 297, 300, 308, 310, 311, 312, 314, 317, 318, 321, 323, 324, 332, 334, 336, 338,
    356, 361, 362, 365, 373, 374, 375, 377, 378, 379, 380, 381, 382, 384, 385, 386, 387, 388, 389, 390, 397, 398, 400,
    402, 405, 409, 415, 454, 466)

# jiwer's ExpandCommonEnglishContractions, literal replacements applied in this order (before lower-casing)
_CONTRACTIONS = (("won't", "will not"), ("can't", "can not"), ("let's", "let us"), ("n't", " not"), ("'re", " are"),
                 ("'s", " is"), ("'d", " would"), ("'ll", " will"), ("'t", " not"), ("'ve", " have"), ("'m", " am"))
_MULTIPLE_SPACES = re.compile(r"\s\s+")


# ---- text -----------------------------------------------------------------------------------------------------
def slrtp_wer_words(text: str) -> list[str]:
    """The words WER compares: English contractions expanded, lower-cased, runs of whitespace made one space,
    stripped, every Unicode punctuation character (category P*) deleted, split on single spaces, empties dropped."""
    for contraction, expansion in _CONTRACTIONS:
        text = text.replace(contraction, expansion)
    text = _MULTIPLE_SPACES.sub(" ", text.lower()).strip()
    text = "".join(c for c in text if not unicodedata.category(c).startswith("P"))
    return [w for w in text.split(" ") if w]


def _edit_distance(a: Sequence[str], b: Sequence[str]) -> int:
    """Levenshtein distance (unit substitution, insertion, deletion) of two word lists, one DP row kept."""
    row = list(range(len(b) + 1))
    for i, x in enumerate(a, start=1):
        diag, row[0] = row[0], i
        for j, y in enumerate(b, start=1):
            diag, row[j] = row[j], min(row[j] + 1, row[j - 1] + 1, diag + (x != y))
    return row[-1]


def slrtp_wer(hyps: Sequence[str], refs: Sequence[str]) -> float:
    """Corpus WER (0-100, may exceed 100): word edits over reference words, words of :func:`slrtp_wer_words`."""
    _check(hyps, refs)
    edits = words = 0
    for n, (hyp, ref) in enumerate(zip(hyps, refs)):
        ref_words = slrtp_wer_words(ref)
        if not ref_words:
            raise ValueError(f"pair {n}: reference {ref!r} has no word left after WER normalisation; WER needs at "
                             "least one reference word per pair")
        edits += _edit_distance(ref_words, slrtp_wer_words(hyp))
        words += len(ref_words)
    return 100.0 * edits / words


def slrtp_text_metrics(hyps: Sequence[str], refs: Sequence[str]) -> dict[str, float]:
    """``slrtp_bleu1..4``, ``slrtp_chrf``, ``slrtp_rouge_l`` and ``slrtp_wer`` (0-100) of back-translated
    hypotheses against one reference each, as the challenge scores them (module docstring)."""
    _check(hyps, refs)
    stats = bleu_statistics([h.split() for h in hyps], [r.split() for r in refs])
    out = {f"slrtp_{k}": v for k, v in slt_bleu_from_statistics(stats).items()}
    out["slrtp_chrf"] = float(CHRF().corpus_score(list(hyps), [list(refs)]).score)
    rouge = [rouge_l_sentence(h.split(" "), r.split(" "), SLRTP_ROUGE_BETA) for h, r in zip(hyps, refs)]
    out["slrtp_rouge_l"] = 100.0 * sum(rouge) / len(rouge)
    out["slrtp_wer"] = slrtp_wer(hyps, refs)
    return out


# ---- FastDTW --------------------------------------------------------------------------------------------------
def _halve(x: np.ndarray, present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Means of frame pairs (0, 1), (2, 3), ... of (T, J, D) values with a (T, J) presence mask; an odd last frame
    is dropped. A joint present in one frame of a pair keeps that value; in neither, it stays missing."""
    m = len(x) - len(x) % 2
    a, b, pa, pb = x[0:m:2], x[1:m:2], present[0:m:2, :, None], present[1:m:2, :, None]
    both = pa & pb
    out = np.where(both, (a + b) / 2, np.where(pa, a, np.where(pb, b, 0.0)))  # (T // 2, J, D)
    return out, present[0:m:2] | present[1:m:2]


def _row_distances(x, px, y, py, i: int, lo: int, hi: int) -> np.ndarray:
    """Euclidean distances (hi - lo + 1,) from frame i of x to frames lo..hi of y, over joints present in both."""
    diff = np.where((px[i] & py[lo:hi + 1])[..., None], x[i] - y[lo:hi + 1], 0.0)  # (n, J, D)
    return np.sqrt(np.square(diff.reshape(len(diff), -1)).sum(axis=1))


def _window(path: np.ndarray, n_x: int, n_y: int, radius: int, compiled: bool) -> tuple[list[int], list[int]]:
    """Per-row column bounds [low, high] at full resolution of a coarse path widened by ``radius`` and doubled."""
    max_x, max_y = int(path[-1, 0]), int(path[-1, 1])
    low1, high1 = np.full(max_x + 1, max_y), np.zeros(max_x + 1, dtype=int)
    np.minimum.at(low1, path[:, 0], path[:, 1])
    np.maximum.at(high1, path[:, 0], path[:, 1])
    lows, highs = [], []
    for i in range(n_x):
        c = i // 2
        c_low = min(c, max_x) if compiled else c  # the compiled body repeats the last coarse row's bounds
        lows.append(2 * max(0, int(low1[max(0, c_low - radius)]) - radius))
        highs.append(min(n_y - 1, 2 * (int(high1[min(max_x, c + radius)]) + radius) + 1))
    return lows, highs


def _band_dtw(x, px, y, py, lows: Sequence[int], highs: Sequence[int], compiled: bool) -> np.ndarray:
    """DTW restricted to rows i in [lows[i], highs[i]]; the warping path (L, 2) from (0, 0) to the last cell."""
    inf = math.inf
    costs, steps = [], []  # per row: accumulated costs and back-steps (0: from (i-1, j), 1: (i, j-1), 2: diagonal)
    for i, (lo, hi) in enumerate(zip(lows, highs)):
        dist = _row_distances(x, px, y, py, i, lo, hi).tolist()
        row, step = [0.0] * (hi - lo + 1), [0] * (hi - lo + 1)
        plo, phi, prev = (lows[i - 1], highs[i - 1], costs[-1]) if i else (0, -1, [])
        for k, j in enumerate(range(lo, hi + 1)):
            up = prev[j - plo] if plo <= j <= phi else inf
            left = row[k - 1] if k else inf
            if i == 0 and j == 0:
                diag = 0.0
            elif plo + 1 <= j <= (phi if compiled else phi + 1):
                diag = prev[j - 1 - plo]
            else:
                diag = inf
            if compiled:
                best, s = (up, 0) if up < left and up < diag else (left, 1) if left < diag else (diag, 2)
            else:
                best, s = (up, 0) if up <= left and up <= diag else (left, 1) if left <= diag else (diag, 2)
            row[k], step[k] = best + dist[k], s
        costs.append(row)
        steps.append(step)
    i, j = len(lows) - 1, highs[-1]
    if j != len(y) - 1 or not math.isfinite(costs[-1][-1]):
        raise RuntimeError(f"FastDTW window does not reach frame pair ({len(x) - 1}, {len(y) - 1}); this is a bug")
    path = []
    while True:
        path.append((i, j))
        if i == 0 and j == 0:
            break
        s = steps[i][j - lows[i]]
        i, j = (i - 1, j) if s == 0 else (i, j - 1) if s == 1 else (i - 1, j - 1)
    return np.asarray(path[::-1], dtype=np.int64)


def _fastdtw(x, px, y, py, radius: int, compiled: bool) -> np.ndarray:
    if len(x) < radius + 2 or len(y) < radius + 2:
        return _band_dtw(x, px, y, py, [0] * len(x), [len(y) - 1] * len(x), compiled)
    coarse = _fastdtw(*_halve(x, px), *_halve(y, py), radius, compiled)
    lows, highs = _window(coarse, len(x), len(y), radius, compiled)
    return _band_dtw(x, px, y, py, lows, highs, compiled)


def slrtp_fastdtw(pred: np.ndarray, ref: np.ndarray, pred_mask: np.ndarray | None = None,
                  ref_mask: np.ndarray | None = None, radius: int = SLRTP_FASTDTW_RADIUS,
                  variant: str = "compiled") -> np.ndarray:
    """FastDTW warping path (L, 2) of (pred frame, ref frame) indices between (T1, J, D) and (T2, J, D) poses,
    Euclidean frame distance over the joints present in both (module docstring). Both need at least one frame."""
    if variant not in SLRTP_FASTDTW_VARIANTS:
        raise ValueError(f"FastDTW variant {variant!r} unknown; use one of {SLRTP_FASTDTW_VARIANTS}")
    if isinstance(radius, bool) or not isinstance(radius, int) or radius < 1:
        raise ValueError(f"FastDTW radius: expected an integer >= 1, got {radius!r}")
    x, px = _poses(pred, pred_mask, "prediction")
    y, py = _poses(ref, ref_mask, "reference")
    _check_pair(x, y, "FastDTW")
    if not len(x) or not len(y):
        raise ValueError(f"FastDTW needs frames on both sides; got {len(x)} prediction and {len(y)} reference frames")
    return _fastdtw(x, px, y, py, radius, variant == "compiled")


# ---- pose metrics ---------------------------------------------------------------------------------------------
def _poses(poses, mask, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(T, J, D) float64 values with missing joints zeroed, and the (T, J) presence mask."""
    x = np.asarray(poses, dtype=np.float64)
    if x.ndim != 3:
        raise ValueError(f"{what} poses have shape {x.shape}; expected (T, J, D) frames x joints x coordinates")
    if np.isinf(x).any():
        raise ValueError(f"{what} poses hold infinite values; mark a missing joint with NaN or the mask instead")
    present = ~np.isnan(x).any(axis=-1)  # (T, J)
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != x.shape[:2] or mask.dtype != np.bool_:
            raise ValueError(f"{what} mask is {mask.dtype} {mask.shape}; expected bool {x.shape[:2]} (True = present)")
        present &= mask
    return np.where(present[..., None], x, 0.0), present


def _check_pair(x: np.ndarray, y: np.ndarray, where: str) -> None:
    if x.shape[1:] != y.shape[1:]:
        raise ValueError(f"{where}: prediction has {x.shape[1]} joints x {x.shape[2]} coordinates, reference "
                         f"{y.shape[1]} x {y.shape[2]}; both must use the same skeleton")


def slrtp_eval_rate(poses: np.ndarray, fps: float = SLRTP_RELEASE_FPS) -> np.ndarray:
    """Frames at the challenge's evaluation rate: every second frame when ``fps`` is 25, else as given (``main.py``
    takes any other rate to be the 12.5 fps it evaluates at)."""
    if not fps > 0:
        raise ValueError(f"fps: expected a positive frame rate, got {fps!r}")
    return poses[::2] if fps == SLRTP_RELEASE_FPS else poses


def _path_length(x: np.ndarray, present: np.ndarray, joint: int) -> float:
    points = x[present[:, joint], joint]  # (T', D): the frames where the joint is present
    return float(np.linalg.norm(np.diff(points, axis=0), axis=-1).sum())


@dataclass(frozen=True)
class SLRTPPairStatistics:
    """One (prediction, reference) pair at the evaluation rate, what :func:`slrtp_metrics_from_statistics` pools:
    the summed joint errors along the FastDTW path and how many (step, joint) terms they hold (0: pair skipped),
    the wrists' path lengths on both sides, and the frame counts."""

    dtw_error_sum: float
    dtw_error_terms: int
    pred_left_wrist_path: float
    pred_right_wrist_path: float
    ref_left_wrist_path: float
    ref_right_wrist_path: float
    pred_frames: int
    ref_frames: int


def slrtp_pair_statistics(pred: np.ndarray, ref: np.ndarray, pred_mask: np.ndarray | None = None,
                          ref_mask: np.ndarray | None = None, pred_fps: float = SLRTP_RELEASE_FPS,
                          ref_fps: float = SLRTP_RELEASE_FPS, variant: str = "compiled",
                          where: str = "pair") -> SLRTPPairStatistics:
    """Statistics of one pair of (T, J, D) pose sequences given at ``pred_fps`` / ``ref_fps`` with optional
    (T, J) presence masks; ``where`` names the pair in errors. An empty prediction is scored as the challenge does
    (skipped by DTW-MJE, path 0, duration 0); an empty reference is an error."""
    x, px = _poses(slrtp_eval_rate(pred, pred_fps), None if pred_mask is None else
                   slrtp_eval_rate(pred_mask, pred_fps), f"{where}: prediction")
    y, py = _poses(slrtp_eval_rate(ref, ref_fps), None if ref_mask is None else
                   slrtp_eval_rate(ref_mask, ref_fps), f"{where}: reference")
    _check_pair(x, y, where)
    if not len(y):
        raise ValueError(f"{where}: the reference has no frame; every reference needs at least one")
    if x.shape[1] <= max(SLRTP_LEFT_WRIST, SLRTP_RIGHT_WRIST):
        raise ValueError(f"{where}: {x.shape[1]} joints, but the wrists are joints {SLRTP_RIGHT_WRIST} and "
                         f"{SLRTP_LEFT_WRIST} of the {SLRTP_NUM_JOINTS}-keypoint SLRTP layout")
    err_sum, terms = 0.0, 0
    if len(x):
        path = slrtp_fastdtw(x, y, px, py, variant=variant)
        both = px[path[:, 0]] & py[path[:, 1]]  # (L, J)
        errors = np.linalg.norm(x[path[:, 0]] - y[path[:, 1]], axis=-1)  # (L, J)
        err_sum, terms = float(errors[both].sum()), int(both.sum())
    return SLRTPPairStatistics(err_sum, terms, _path_length(x, px, SLRTP_LEFT_WRIST),
                               _path_length(x, px, SLRTP_RIGHT_WRIST), _path_length(y, py, SLRTP_LEFT_WRIST),
                               _path_length(y, py, SLRTP_RIGHT_WRIST), len(x), len(y))


def _ratio(a: float, b: float) -> float:
    if b > 0:
        return a / b
    return math.nan if a == 0 else math.inf


def slrtp_metrics_from_statistics(stats: Sequence[SLRTPPairStatistics]) -> dict[str, float]:
    """``slrtp_dtw_mje`` (pooled over all path terms), ``slrtp_wrist_path_ratio`` (ratio of mean path lengths,
    averaged over the two wrists), ``slrtp_duration_ratio`` (mean frame ratio), ``slrtp_pairs`` and
    ``slrtp_dtw_mje_pairs`` (pairs DTW-MJE scored)."""
    if not stats:
        raise ValueError("no pose pairs to score; give at least one (prediction, reference) pair")
    terms = sum(s.dtw_error_terms for s in stats)
    left = _ratio(sum(s.pred_left_wrist_path for s in stats), sum(s.ref_left_wrist_path for s in stats))
    right = _ratio(sum(s.pred_right_wrist_path for s in stats), sum(s.ref_right_wrist_path for s in stats))
    return {
        "slrtp_dtw_mje": sum(s.dtw_error_sum for s in stats) / terms if terms else math.nan,
        "slrtp_wrist_path_ratio": (left + right) / 2,
        "slrtp_duration_ratio": float(np.mean([s.pred_frames / s.ref_frames for s in stats])),
        "slrtp_pairs": float(len(stats)),
        "slrtp_dtw_mje_pairs": float(sum(s.dtw_error_terms > 0 for s in stats)),
    }


def slrtp_pose_metrics(pred: np.ndarray, ref: np.ndarray, pred_mask: np.ndarray | None = None,
                       ref_mask: np.ndarray | None = None, pred_fps: float = SLRTP_RELEASE_FPS,
                       ref_fps: float = SLRTP_RELEASE_FPS, variant: str = "compiled") -> dict[str, float]:
    """``slrtp_dtw_mje``, ``slrtp_wrist_path_ratio`` and ``slrtp_duration_ratio`` of one pair of (T, J, D) pose
    sequences (arguments as :func:`slrtp_pair_statistics`; DTW-MJE is NaN for an empty prediction)."""
    stats = slrtp_pair_statistics(pred, ref, pred_mask, ref_mask, pred_fps, ref_fps, variant)
    out = slrtp_metrics_from_statistics([stats])
    return {k: out[k] for k in ("slrtp_dtw_mje", "slrtp_wrist_path_ratio", "slrtp_duration_ratio")}


def slrtp_pose_corpus_metrics(preds: Sequence[np.ndarray], refs: Sequence[np.ndarray],
                              pred_masks: Sequence[np.ndarray | None] | None = None,
                              ref_masks: Sequence[np.ndarray | None] | None = None,
                              pred_fps: float = SLRTP_RELEASE_FPS, ref_fps: float = SLRTP_RELEASE_FPS,
                              variant: str = "compiled") -> dict[str, float]:
    """The challenge's pose scores of paired prediction and reference sequences (same order), aggregated as
    ``main.py`` does (:func:`slrtp_metrics_from_statistics`)."""
    if len(preds) != len(refs):
        raise ValueError(f"{len(preds)} predicted sequences but {len(refs)} references; give one prediction per "
                         "reference, in the same order")
    pred_masks = [None] * len(preds) if pred_masks is None else pred_masks
    ref_masks = [None] * len(refs) if ref_masks is None else ref_masks
    if len(pred_masks) != len(preds) or len(ref_masks) != len(refs):
        raise ValueError(f"{len(pred_masks)} prediction masks and {len(ref_masks)} reference masks for {len(preds)} "
                         "pairs; give one mask (or None) per sequence")
    stats = [slrtp_pair_statistics(p, r, pm, rm, pred_fps, ref_fps, variant, where=f"pair {n}")
             for n, (p, r, pm, rm) in enumerate(zip(preds, refs, pred_masks, ref_masks))]
    return slrtp_metrics_from_statistics(stats)
