"""The one motion scorer: predicted body-model parameters against reference parameters, per clip, overall and
per group (M3T Tab. 1's DTW-JPE / DTW-PA-JPE per region and face DTW-VPE, SOKE's evaluation).

Any model that produces parameter sequences in the body model's layout is scored here (the SMLM,
back-translation baselines); models that produce points (the skeletal SGSA / PT) score posed pairs through
:func:`score_point_pairs`, the same means and groups: nothing below knows about tokens, vocabularies or text. Both sides of a pair are
posed with the same signer identity, so the error is the motion's alone. The points are the metric sets of
:mod:`m3t.body.metric_sets`, the metrics those of :mod:`m3t.metrics.motion`. With ``MotionMetricsConfig(mode=
"soke_exact")`` the body region is SOKE's (:func:`m3t.metrics.soke.soke_keypoints`: root, 12 measured points,
the further points of its Procrustes) and SOKE's zeroed joints are zeroed before posing; SMPL-FX only.

A reference is posed once: :meth:`MotionScorer.reference` stores its points under the clip id, and every
later :meth:`MotionScorer.score` of that clip reuses them (a checkpoint selection scores the same clips at
every evaluation). **No clip leaves a mean unseen**: an empty prediction (0 frames, e.g. a model that stopped
at its first step) is scored as what a viewer of the avatar would see, one frame of the body model's rest
pose, and counted in ``empty_rate`` (its row keeps ``frames == 0``).

Axis legend: T frames (T1 predicted, T2 reference), D modality dim, K points of a region, P identity dim.
"""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from m3t.body.metric_sets import joined_keypoints, metric_keypoints, metric_points
from m3t.body.protocol import BodyModel, as_tensors
from m3t.metrics.motion import MotionMetricsConfig, evaluate_pairs, summarise
from m3t.metrics.soke import soke_keypoints, zero_soke_joints

ParamSequence = Mapping[str, np.ndarray]
"""Modality name -> (T, D_m) per-frame parameters in the body model's layout."""


@dataclass(frozen=True)
class MotionPair:
    """One clip to score. ``reference`` None: the points stored by :meth:`MotionScorer.reference` are used."""

    clip_id: str
    group: str  # e.g. ``<corpus>/<language>``; summaries are also given per group
    prediction: ParamSequence  # (T1, D_m) per modality; empty mapping or T1 = 0: an empty prediction
    identity: np.ndarray  # (P,) signer identity, posing both sides
    reference: ParamSequence | None = None  # (T2, D_m) per modality


@dataclass(frozen=True)
class ClipScore:
    """``metrics``: the ``dtw_*`` entries of :func:`m3t.metrics.motion.evaluate_pairs` (of the rest pose for an
    empty prediction, ``frames == 0``)."""

    clip_id: str
    group: str
    frames: int  # T1, predicted frames
    metrics: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class MotionScores:
    """Per-clip scores and their means over every clip, overall and per group."""

    per_clip: list[ClipScore]
    overall: dict[str, float]  # metric -> mean; {} for no clips
    groups: dict[str, dict[str, float]]  # group -> metric -> mean, groups in first-seen order
    empty_rate: float  # fraction of clips with an empty prediction (0.0 for no clips)

    @property
    def group_summary(self) -> dict[str, float]:
        """``"<group>/<metric>"`` -> mean."""
        return {f"{group}/{k}": v for group, means in self.groups.items() for k, v in means.items()}

    @property
    def summary(self) -> dict[str, float]:
        """Overall means, ``empty_rate``, then the ``"<group>/<metric>"`` means."""
        return {**self.overall, "empty_rate": self.empty_rate, **self.group_summary}


def _frames(params: ParamSequence) -> int:
    return int(np.asarray(next(iter(params.values()))).shape[0]) if params else 0


class MotionScorer:
    """Poses parameter sequences into the metric point sets of ``body`` and scores predictions against references.

    ``config.mode == "soke_exact"`` needs an SMPL-FX ``body`` (:class:`m3t.metrics.soke.SokeModeError` otherwise).
    """

    def __init__(self, body: BodyModel, config: MotionMetricsConfig = MotionMetricsConfig()):
        self.body, self.config = body, config
        self.sets = soke_keypoints(body) if config.mode == "soke_exact" else metric_keypoints(body)
        self._joined = joined_keypoints(body, self.sets)  # built once: every sequence is posed in one forward
        self._references: dict[str, dict[str, np.ndarray]] = {}

    @torch.no_grad()
    def points(self, params: ParamSequence, identity: np.ndarray) -> dict[str, np.ndarray]:
        """(T, D_m) per modality and (P,) identity -> {region: (T, K, 3) float64 metres}."""
        ident = torch.as_tensor(np.asarray(identity), dtype=torch.float32)
        tensors = as_tensors(params)
        if self.config.mode == "soke_exact":
            tensors = zero_soke_joints(self.body.layout, tensors)
        return {k: v.numpy().astype(np.float64)
                for k, v in metric_points(self.body, tensors, ident, self.sets, self._joined).items()}

    def reference(self, clip_id: str, params: ParamSequence, identity: np.ndarray) -> None:
        """Pose and store the reference of ``clip_id`` (replacing one stored before under that id)."""
        self._references[clip_id] = self.points(params, identity)

    def _reference_points(self, pair: MotionPair) -> dict[str, np.ndarray]:
        if pair.reference is not None:
            return self.points(pair.reference, pair.identity)
        if pair.clip_id not in self._references:
            raise KeyError(f"clip {pair.clip_id!r}: no reference; store it with MotionScorer.reference(clip_id, "
                           "params, identity) or give the pair its reference params")
        return self._references[pair.clip_id]

    def rest_pose(self) -> dict[str, np.ndarray]:
        """One frame of the body model's rest pose: how an empty prediction is scored."""
        return {k: v.detach().cpu().numpy() for k, v in self.body.rest_params(1).items()}

    def score(self, pairs: Sequence[MotionPair], progress: bool = False) -> MotionScores:
        """Score every pair (order kept in ``per_clip``); a bad pair raises ``ValueError`` naming it."""
        shown = [p.prediction if _frames(p.prediction) > 0 else self.rest_pose() for p in pairs]
        return score_point_pairs([PointPair(p.clip_id, p.group, _frames(p.prediction), self.points(s, p.identity),
                                            self._reference_points(p)) for p, s in zip(pairs, shown)],
                                 progress, self.config)


@dataclass(frozen=True)
class PointPair:
    """One clip already posed: {region: (T, K, 3) metres} on both sides. ``frames`` is what the model produced
    (0 for an empty prediction shown as something else, e.g. the rest pose), counted in ``empty_rate``."""

    clip_id: str
    group: str
    frames: int
    prediction: Mapping[str, np.ndarray]
    reference: Mapping[str, np.ndarray]


def score_point_pairs(pairs: Sequence[PointPair], progress: bool = False,
                      config: MotionMetricsConfig = MotionMetricsConfig()) -> MotionScores:
    """The scores of posed pairs (skeleton models score here directly; :class:`MotionScorer` poses first)."""
    results = evaluate_pairs([(p.prediction, p.reference) for p in pairs], progress, config)
    per_clip = [ClipScore(p.clip_id, p.group, p.frames, r) for p, r in zip(pairs, results)]
    by_group: dict[str, list[dict[str, float]]] = defaultdict(list)
    for clip in per_clip:
        by_group[clip.group].append(clip.metrics)
    return MotionScores(
        per_clip=per_clip,
        overall=summarise([c.metrics for c in per_clip]) if per_clip else {},
        groups={group: summarise(metrics) for group, metrics in by_group.items()},
        empty_rate=float(np.mean([c.frames == 0 for c in per_clip])) if per_clip else 0.0,
    )
