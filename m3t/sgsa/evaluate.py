"""Producing and scoring skeleton sequences (SGSA Sec. 5 "Evaluation"; the DTW errors of M3T Tab. 1).

Generation is counter decoding (:meth:`m3t.sgsa.model.SGSAProduction.generate`): by default the model's own
counter decides the length; ``counter="ground_truth"`` gives it the true length (only for parity with published
PT numbers, which were produced so). A produced sequence is denormalised with the reference clip's scale (the
signer's mean shoulder width, as the body-model scorer poses both sides with the signer's identity) and scored
against the reference skeleton by SOKE's DTW-JPE / DTW-PA-JPE per region (``body`` neck-rooted, each hand
wrist-rooted: :func:`m3t.metrics.scorer.score_point_pairs`). Checkpoints are selected on
``dtw_jpe_mean_x_length_m``: ``dtw_jpe_mean_m`` (the mean of body and hand DTW-JPE, SOKE's raw accumulated cost)
times the clips' mean length penalty max(U / U_ref, U_ref / U). The raw cost alone rewards a sequence that stops
after one frame: its path has only the reference's length, each step a distance to one mean-ish pose, while every
extra frame of a sequence that runs long adds to it.

Counter decoding's length statistics per split: ``mean_frames``, ``length_ratio`` (mean of U / U_ref, kept for
continuity; a mean of ratios hides bimodal failures), ``length_ratio_median``, ``length_within_25`` (share of clips
with 0.75 <= U / U_ref <= 1.25) and ``stopped_rate`` (share ended by their own counter before ``max_frames``).

Axis legend: B batch, U frames, S skeleton width with counter, J joints.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from m3t.body.skeleton import SkeletonGraph
from m3t.body.skeleton_points import denormalise, regions
from m3t.metrics.scorer import MotionScores, PointPair, score_point_pairs
from m3t.sgsa.data import Sample, collate, text_batch
from m3t.sgsa.model import SGSAProduction
from m3t.vocabulary import Vocabulary

MEAN_DTW = "dtw_jpe_mean_m"  # the mean of body and hand DTW-JPE (SOKE's raw cost), as for the SMLM
SELECTION_METRIC = "dtw_jpe_mean_x_length_m"


def length_penalty(frames: int, reference_frames: int) -> float:
    """max(U / U_ref, U_ref / U) >= 1: how many times too long or too short a produced sequence is."""
    if frames < 1 or reference_frames < 1:
        return float("inf")
    return max(frames / reference_frames, reference_frames / frames)


@torch.no_grad()
def generate(model: SGSAProduction, samples: Sequence[Sample], text_vocab: Vocabulary, max_frames: int,
             counter: str = "predicted", batch_size: int = 16) -> dict[str, np.ndarray]:
    """clip id -> (U, S) produced normalised frames, counter last (U >= 1)."""
    if counter not in ("predicted", "ground_truth"):
        raise ValueError(f"counter {counter!r} unknown; allowed: predicted, ground_truth")
    model.eval()
    device = next(model.parameters()).device
    pad = text_vocab.stoi["<pad>"]
    out = {}
    for i in range(0, len(samples), batch_size):
        chunk = samples[i: i + batch_size]
        ids, mask = text_batch(chunk, pad)
        lengths = None
        if counter == "ground_truth":
            lengths = torch.tensor([min(len(s.clip.coords), max_frames) for s in chunk], device=device)
        produced = model.generate(ids.to(device), mask.to(device), max_frames, lengths)
        for sample, frames in zip(chunk, produced):
            out[sample.clip_id] = frames.detach().cpu().numpy().astype(np.float32)
    return out


def produced_points(frames: np.ndarray, graph: SkeletonGraph, scale: float) -> np.ndarray:
    """(U, S) normalised frames with counter -> (U, J, 3) metres."""
    return denormalise(frames[:, :-1], graph, scale)


@dataclass
class ProductionReport:
    summary: dict[str, float]
    scores: MotionScores
    per_clip: list[dict] = field(default_factory=list)


def score_production(samples: Sequence[Sample], produced: dict[str, np.ndarray], graph: SkeletonGraph,
                     max_frames: int, progress: bool = False) -> ProductionReport:
    """DTW metrics of every sample's produced skeleton against its reference, overall and per group, with the
    length statistics of counter decoding and the selection figure (module docstring)."""
    lost = [s.clip_id for s in samples if s.clip_id not in produced]
    if lost:
        raise KeyError(f"no produced skeleton for clips {lost[:5]} (of {len(lost)}); rerun the generation")
    pairs = [PointPair(s.clip_id, s.group, len(produced[s.clip_id]),
                       regions(produced_points(produced[s.clip_id], graph, s.clip.scale), graph),
                       regions(s.clip.points, graph)) for s in samples]
    scores = score_point_pairs(pairs, progress)
    rows = []
    for s, c in zip(samples, scores.per_clip):
        rows.append({"clip_id": s.clip_id, "group": s.group, "frames": c.frames,
                     "reference_frames": len(s.clip.points), **c.metrics})
    summary = dict(scores.overall)
    if scores.overall:
        ratios = np.array([r["frames"] / r["reference_frames"] for r in rows])
        summary[MEAN_DTW] = 0.5 * (scores.overall["dtw_jpe_body_m"] + scores.overall["dtw_jpe_hand_m"])
        summary["length_penalty"] = float(np.mean([length_penalty(r["frames"], r["reference_frames"]) for r in rows]))
        summary[SELECTION_METRIC] = summary[MEAN_DTW] * summary["length_penalty"]
        summary["mean_frames"] = float(np.mean([r["frames"] for r in rows]))
        summary["length_ratio"] = float(ratios.mean())
        summary["length_ratio_median"] = float(np.median(ratios))
        summary["length_within_25"] = float(np.mean((ratios >= 0.75) & (ratios <= 1.25)))
        summary["stopped_rate"] = float(np.mean([r["frames"] < max_frames for r in rows]))
    else:
        summary[MEAN_DTW] = summary[SELECTION_METRIC] = float("inf")
    summary.update(scores.group_summary)
    return ProductionReport(summary, scores, rows)


@torch.no_grad()
def teacher_forced_loss(model: SGSAProduction, samples: Sequence[Sample], text_vocab: Vocabulary,
                        batch_size: int = 16) -> float:
    """Mean squared error per real frame coordinate with the ground-truth previous frames as input."""
    model.eval()
    device = next(model.parameters()).device
    total, count = 0.0, 0
    for i in range(0, len(samples), batch_size):
        batch = collate(samples[i: i + batch_size], text_vocab).to(device)
        pred = model(batch.text_ids, batch.text_mask, batch.frames_in, batch.frame_mask).frames
        err = F.mse_loss(pred, batch.target, reduction="none").sum(-1)[batch.frame_mask]
        total, count = total + float(err.sum()), count + int(err.numel()) * batch.target.shape[-1]
    return total / max(count, 1)


class ProductionEvaluator:
    """Dev-split selection during training: generate ``samples`` with the predicted counter and score them."""

    def __init__(self, samples: Sequence[Sample], graph: SkeletonGraph, text_vocab: Vocabulary, max_frames: int,
                 batch_size: int = 16):
        self.samples, self.graph, self.text_vocab = list(samples), graph, text_vocab
        self.max_frames, self.batch_size = max_frames, batch_size

    def __call__(self, model: SGSAProduction) -> dict[str, float]:
        produced = generate(model, self.samples, self.text_vocab, self.max_frames, "predicted", self.batch_size)
        report = score_production(self.samples, produced, self.graph, self.max_frames)
        summary = {k: v for k, v in report.summary.items() if "/" not in k}
        summary["loss"] = teacher_forced_loss(model, self.samples, self.text_vocab, self.batch_size)
        return summary
