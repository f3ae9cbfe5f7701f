"""The one motion scorer: predicted body-model parameters against reference parameters, per clip, overall and
per group (M3T Tab. 1's DTW-JPE / DTW-PA-JPE per region and face DTW-VPE, SOKE's evaluation).

Any model that produces parameter sequences in the body model's layout is scored here (the SMLM,
back-translation baselines); models that produce points (the skeletal SGSA / PT) score posed pairs through
:func:`score_point_pairs`, the same means and groups: nothing below knows about tokens, vocabularies or text. Both sides of a pair are
posed with the same signer identity, so the error is the motion's alone. The points are the metric sets of
:mod:`m3t.body.metric_sets`, the metrics those of :mod:`m3t.metrics.motion`. With ``MotionMetricsConfig(mode=
"soke_exact")`` the body region is SOKE's (:func:`m3t.metrics.soke.soke_keypoints`: root, 12 measured points,
the further points of its Procrustes) and SOKE's zeroed joints are zeroed before posing; SMPL-FX only.

**Memory stays within a frame budget** (:data:`REFERENCE_FRAMES` by default), however many clips are scored:
:meth:`MotionScorer.reference` keeps a reference's parameters only, and its points are posed when it is first
scored and kept in a least-recently-used cache of at most ``frame_budget`` frames (a checkpoint selection scores
the same clips at every evaluation: those the cache holds are not posed again, the others are re-posed from
their parameters, the same computation, so the same numbers). :meth:`MotionScorer.score` poses and scores the
pairs a chunk at a time, each chunk holding at most ``frame_budget`` frames of predictions and references (a
pair longer than that is a chunk alone), and averages once over every clip. **No clip leaves a mean unseen**:
an empty prediction (0 frames, e.g. a model that stopped at its first step) is scored as what a viewer of the
avatar would see, one frame of the body model's rest pose, and counted in ``empty_rate`` (its row keeps
``frames == 0``).

Axis legend: T frames (T1 predicted, T2 reference), D modality dim, K points of a region, P identity dim.
"""
from __future__ import annotations

from collections import OrderedDict, defaultdict
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm.auto import tqdm

from m3t.body.metric_sets import joined_keypoints, metric_keypoints, metric_points
from m3t.body.protocol import BodyModel, as_tensors
from m3t.metrics.motion import (
    MotionMetricsConfig,
    _validated,
    evaluate_pairs,
    summarise,
)
from m3t.metrics.soke import soke_keypoints, zero_soke_joints

ParamSequence = Mapping[str, np.ndarray]
"""Modality name -> (T, D_m) per-frame parameters in the body model's layout."""

REFERENCE_FRAMES = 10_000
"""Default ``frame_budget`` of :class:`MotionScorer`: frames of posed points held at once, in the reference cache
and again in the chunk being scored. Anny's metric points are 3,572 a frame (3,518 of them face vertices), ~43 kB
in float32: ~0.43 GB of cached references, and a chunk at most ~1.3 GB while it is widened to float64 for the DTW
(200-frame clips: ~50 cached references, chunks of ~25 pairs)."""


@dataclass(frozen=True)
class MotionPair:
    """One clip to score. ``reference`` None: the reference stored by :meth:`MotionScorer.reference` is used."""

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

    @classmethod
    def of(cls, per_clip: Sequence[ClipScore]) -> MotionScores:
        """The means of scored clips (every scorer's one place for them): overall, per group, ``empty_rate``."""
        per_clip = list(per_clip)
        by_group: dict[str, list[dict[str, float]]] = defaultdict(list)
        for clip in per_clip:
            by_group[clip.group].append(clip.metrics)
        return cls(
            per_clip=per_clip,
            overall=summarise([c.metrics for c in per_clip]) if per_clip else {},
            groups={group: summarise(metrics) for group, metrics in by_group.items()},
            empty_rate=float(np.mean([c.frames == 0 for c in per_clip])) if per_clip else 0.0,
        )

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


@dataclass(frozen=True)
class _Reference:
    """A stored reference: what posing it takes, not its points (its parameters, or how to read them)."""

    params: dict[str, np.ndarray] | Callable[[], ParamSequence]  # (T2, D_m) float32 per modality, or a reader
    identity: np.ndarray  # (P,) float32
    frames: int  # T2


def budget_runs(sizes: Sequence[int], budget: int) -> Iterator[slice]:
    """Consecutive runs of items whose sizes (frames) sum to at most ``budget``; an item larger than the budget
    is a run of its own. How scoring keeps its memory flat, whatever the number of clips."""
    start, total = 0, 0
    for n, size in enumerate(sizes):
        if n > start and total + size > budget:
            yield slice(start, n)
            start, total = n, 0
        total += size
    if start < len(sizes):
        yield slice(start, len(sizes))


class MotionScorer:
    """Poses parameter sequences into the metric point sets of ``body`` and scores predictions against references.

    ``config.mode == "soke_exact"`` needs an SMPL-FX ``body`` (:class:`m3t.metrics.soke.SokeModeError` otherwise).
    ``frame_budget`` bounds the posed frames held at once (module docstring, :data:`REFERENCE_FRAMES`): the cache
    of reference points and each chunk :meth:`score` poses. One scorer serves one thread at a time.
    """

    def __init__(self, body: BodyModel, config: MotionMetricsConfig = MotionMetricsConfig(),
                 frame_budget: int = REFERENCE_FRAMES):
        if isinstance(frame_budget, bool) or not isinstance(frame_budget, (int, np.integer)) or frame_budget < 1:
            raise ValueError(f"frame_budget: expected a positive number of frames, got {frame_budget!r}")
        self.body, self.config, self.frame_budget = body, config, int(frame_budget)
        self.sets = soke_keypoints(body) if config.mode == "soke_exact" else metric_keypoints(body)
        self._joined = joined_keypoints(body, self.sets)  # built once: every sequence is posed in one forward
        self._references: dict[str, _Reference] = {}
        # clip id -> {region: (T2, K, 3)} in the posing dtype, least recently used first
        self._cache: OrderedDict[str, dict[str, np.ndarray]] = OrderedDict()
        self._cache_frames = 0

    @torch.no_grad()
    def _pose(self, params: ParamSequence, identity: np.ndarray) -> dict[str, np.ndarray]:
        """{region: (T, K, 3)} in the dtype the body model poses in (float32: half the memory of float64, and
        widened to float64 exactly wherever it is measured)."""
        ident = torch.as_tensor(np.asarray(identity), dtype=torch.float32)
        tensors = as_tensors(params)
        if self.config.mode == "soke_exact":
            tensors = zero_soke_joints(self.body.layout, tensors)
        return {k: v.numpy() for k, v in metric_points(self.body, tensors, ident, self.sets, self._joined).items()}

    def points(self, params: ParamSequence, identity: np.ndarray) -> dict[str, np.ndarray]:
        """(T, D_m) per modality and (P,) identity -> {region: (T, K, 3) float64 metres}."""
        return {k: v.astype(np.float64) for k, v in self._pose(params, identity).items()}

    def reference(self, clip_id: str, params: ParamSequence, identity: np.ndarray) -> None:
        """Store the reference of ``clip_id`` (replacing one stored before under that id), posed when scored.

        Its parameters are kept as float32 arrays (no copy of float32 input: leave them unchanged afterwards);
        parameters that do not fit the body model's layout raise ``ValueError`` naming the clip, here rather
        than at scoring.
        """
        stored, ident, frames = self._checked(clip_id, params, identity)
        self._drop(clip_id)
        self._references[clip_id] = _Reference(stored, ident, frames)

    def reference_on_demand(self, clip_id: str, frames: int, identity: np.ndarray,
                            read: Callable[[], ParamSequence]) -> None:
        """Store the reference of ``clip_id`` as :meth:`reference` does, but keep only how to ``read`` its
        ``frames`` frames of parameters (e.g. from its shard: :class:`m3t.shards.references.SplitReferences`):
        they are read each time the clip is posed and not held, and checked then (``ValueError`` naming the clip,
        also when they are not ``frames`` long)."""
        ident = self._checked_identity(clip_id, identity)
        self._drop(clip_id)
        self._references[clip_id] = _Reference(read, ident, int(frames))

    def _checked(self, clip_id: str, params: ParamSequence,
                 identity: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray, int]:
        """Parameters (float32; no copy of float32 input), identity and frames of a reference."""
        stored = {k: np.asarray(v, dtype=np.float32) for k, v in params.items()}
        try:
            frames = self.body.layout.check(stored)
        except ValueError as exc:
            raise ValueError(f"reference of clip {clip_id!r}: {exc}") from exc
        return stored, self._checked_identity(clip_id, identity), frames

    def _checked_identity(self, clip_id: str, identity: np.ndarray) -> np.ndarray:
        ident = np.asarray(identity, dtype=np.float32)
        if ident.size != self.body.layout.identity_dim:
            raise ValueError(f"reference of clip {clip_id!r}: identity of shape {ident.shape}, expected "
                             f"({self.body.layout.identity_dim},) for body model {self.body.name!r}")
        return ident

    @property
    def cached(self) -> tuple[str, ...]:
        """Clip ids whose reference points are held, least recently used first."""
        return tuple(self._cache)

    @property
    def cached_frames(self) -> int:
        """Frames of reference points held (never above ``frame_budget``)."""
        return self._cache_frames

    def _drop(self, clip_id: str) -> None:
        if clip_id in self._cache:
            del self._cache[clip_id]
            self._cache_frames -= self._references[clip_id].frames

    def _keep(self, clip_id: str, points: dict[str, np.ndarray], frames: int, needed: set[str]) -> None:
        """Cache ``points``, evicting the least recently used references first, but none of ``needed``: a score
        that evicted its own clips would pose every clip again at every evaluation once they outgrow the
        budget (a cyclic scan defeats plain LRU), where this keeps the first that fit."""
        room, evicted = self.frame_budget - self._cache_frames, []
        for cid in self._cache:
            if room >= frames:
                break
            if cid not in needed:
                evicted.append(cid)
                room += self._references[cid].frames
        if room < frames:  # longer than the budget, or only clips still needed would make room: used, not kept
            return
        for cid in evicted:
            self._drop(cid)
        self._cache[clip_id] = points
        self._cache_frames += frames

    def _reference_points(self, pair: MotionPair, needed: set[str]) -> dict[str, np.ndarray]:
        if pair.reference is not None:
            return self._pose(pair.reference, pair.identity)
        if pair.clip_id in self._cache:
            self._cache.move_to_end(pair.clip_id)
            return self._cache[pair.clip_id]
        stored = self._references[pair.clip_id]
        params = stored.params
        if callable(params):
            params, _, frames = self._checked(pair.clip_id, params(), stored.identity)
            if frames != stored.frames:
                raise ValueError(f"reference of clip {pair.clip_id!r}: {frames} frames read, {stored.frames} "
                                 "announced; its shard changed during the run (re-run the evaluation)")
        points = self._pose(params, stored.identity)
        self._keep(pair.clip_id, points, stored.frames, needed)
        return points

    def rest_pose(self) -> dict[str, np.ndarray]:
        """One frame of the body model's rest pose: how an empty prediction is scored."""
        return {k: v.detach().cpu().numpy() for k, v in self.body.rest_params(1).items()}

    def _chunks(self, pairs: Sequence[MotionPair]) -> Iterator[slice]:
        """Consecutive pairs whose frames (prediction, 1 for an empty one, plus reference) fit the budget."""
        return budget_runs([max(_frames(p.prediction), 1) + (_frames(p.reference) if p.reference is not None
                                                              else self._references[p.clip_id].frames)
                            for p in pairs], self.frame_budget)

    def _evaluate(self, posed: list[tuple[dict[str, np.ndarray], dict[str, np.ndarray]]],
                  pairs: Sequence[MotionPair], start: int) -> list[dict[str, float]]:
        """:func:`evaluate_pairs` of one chunk; a bad pair is named by its clip and its place in the whole call."""
        try:
            return evaluate_pairs(posed, config=self.config)
        except ValueError:
            for n, (pred, ref) in enumerate(posed):
                try:
                    _validated(pred, ref, start + n, self.config)
                except ValueError as exc:
                    raise ValueError(f"clip {pairs[n].clip_id!r}: {exc}") from exc
            raise

    def score(self, pairs: Sequence[MotionPair], progress: bool = False) -> MotionScores:
        """Score every pair (order kept in ``per_clip``); a bad pair raises ``ValueError`` naming it, a clip with
        neither a stored nor a given reference ``KeyError``, both before any later pair is posed."""
        pairs = list(pairs)
        unknown = [p.clip_id for p in pairs if p.reference is None and p.clip_id not in self._references]
        if unknown:
            raise KeyError(f"clip {unknown[0]!r}: no reference; store it with MotionScorer.reference(clip_id, "
                           "params, identity) or give the pair its reference params"
                           + (f" ({len(unknown)} clips lack one)" if len(unknown) > 1 else ""))
        needed = {p.clip_id for p in pairs if p.reference is None}
        rest = self.rest_pose() if any(_frames(p.prediction) == 0 for p in pairs) else {}
        metrics: list[dict[str, float]] = []
        with tqdm(total=len(pairs), desc="dtw", unit="pair", disable=not progress) as bar:
            for chunk in self._chunks(pairs):
                posed = [(self._pose(p.prediction if _frames(p.prediction) > 0 else rest, p.identity),
                          self._reference_points(p, needed)) for p in pairs[chunk]]
                metrics += self._evaluate(posed, pairs[chunk], chunk.start)
                bar.update(len(posed))
        return MotionScores.of([ClipScore(p.clip_id, p.group, _frames(p.prediction), m)
                                for p, m in zip(pairs, metrics)])


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
    return MotionScores.of([ClipScore(p.clip_id, p.group, p.frames, r) for p, r in zip(pairs, results)])


def score_on_worker(body_cfg, config: MotionMetricsConfig, frame_budget: int,
                    pairs: Sequence[MotionPair]) -> list[ClipScore]:
    """The per-clip scores of ``pairs`` (each with its ``reference`` parameters) on a worker process: its body
    model (``body_cfg``: :class:`m3t.body.config.BodyConfig`) and scorer are built once per process. A clip's
    figures are those a scorer in the run's own process gives: posing and the DTW depend only on the pair."""
    return _worker_scorer(body_cfg, config, frame_budget).score(pairs).per_clip


_WORKER_SCORERS: dict[tuple, MotionScorer] = {}


def _worker_scorer(body_cfg, config: MotionMetricsConfig, frame_budget: int) -> MotionScorer:
    key = (repr(body_cfg), repr(config), frame_budget)
    if key not in _WORKER_SCORERS:
        from m3t.body.factory import load_body_model

        _WORKER_SCORERS.clear()  # one scorer per worker process: a body model is large
        _WORKER_SCORERS[key] = MotionScorer(load_body_model(body_cfg), config, frame_budget)
    return _WORKER_SCORERS[key]
