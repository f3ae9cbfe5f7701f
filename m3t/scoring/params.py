"""Body-model parameters scored as the SMLM's evaluation scores them: two Parquet shards of this project
(:mod:`m3t.shards`, e.g. a fitted test split and a system's output written as a shard) -> definitions ``m3t``
(DTW-JPE / DTW-PA-JPE per region and the face's DTW-VPE on the workspace's body model, this project's tables)
and ``soke_exact`` (SOKE's pelvis-rooted body and zeroed joints; SMPL-FX only), through the one scorer
:class:`m3t.metrics.scorer.MotionScorer`.

Both sides of a pair are posed with the **reference's** identity (the scorer's rule: the error is the motion's
alone). Keys carry the definition: ``m3t_dtw_jpe_body_m`` is the pipeline's ``dtw_jpe_body_m`` under mode
``m3t``. A clip is refused with its reason when its two sides differ in body model, when the shards' layouts
differ from the body model's, or when it has no frames on the reference side.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from m3t.body.protocol import BodyModel
from m3t.metrics.motion import MotionMetricsConfig
from m3t.metrics.scorer import MotionPair, MotionScorer
from m3t.metrics.soke import SokeModeError
from m3t.scoring.poses import ScoreInputError
from m3t.scoring.report import ScoreReport, check_definitions, pairing
from m3t.shards.io import read_shard
from m3t.shards.schema import ShardFormatError

PARAMETER_DEFINITIONS = ("m3t", "soke_exact")


def _read(path: Path, side: str):
    try:
        return read_shard(path)
    except (ShardFormatError, OSError) as exc:
        raise ScoreInputError(f"{side} shard {exc}") from exc


def _check_layout(shard, body: BodyModel, side: str) -> None:
    if dict(shard.layout.dims) != dict(body.layout.dims):
        raise ScoreInputError(f"{shard.path}: {side} parameters have modalities {dict(shard.layout.dims)}, the "
                              f"workspace's body model {body.name!r} has {dict(body.layout.dims)}; set body.model in "
                              "params.yaml to the model the shard was fitted with")


def score_parameter_shards(pred: Path, ref: Path, body: BodyModel, definitions: Sequence[str] | None = None,
                           progress: Callable[[Iterable], Iterable] | None = None) -> ScoreReport:
    """Score the clips of shard ``pred`` against those of shard ``ref`` on ``body`` (see the module doc)."""
    if definitions is None:  # every definition that applies: soke_exact needs SMPL-FX
        definitions = [d for d in PARAMETER_DEFINITIONS if d != "soke_exact" or body.name == "smplfx"]
    chosen = check_definitions(definitions, PARAMETER_DEFINITIONS, "parameter")
    report = ScoreReport("parameters", str(pred), str(ref))
    predicted, references = _read(pred, "prediction"), _read(ref, "reference")
    for shard, side in ((predicted, "prediction"), (references, "reference")):
        _check_layout(shard, body, side)
    p_clips = {c.clip.id: c for c in predicted.clips}
    r_clips = {c.clip.id: c for c in references.clips}
    ids = pairing(p_clips, r_clips, report, "clip")
    pairs = []
    for clip in (progress or (lambda x: x))(ids):
        p, r = p_clips[clip], r_clips[clip]
        if p.body_model != r.body_model or r.body_model != body.name:
            report.unscored.append({"clip": clip, "definition": "all", "reason": (
                f"prediction fitted with {p.body_model!r}, reference with {r.body_model!r}, workspace body "
                f"model {body.name!r}; both sides must be parameters of the workspace's body model")})
            continue
        if r.num_frames == 0:
            report.unscored.append({"clip": clip, "definition": "all", "reason": "the reference has no frames"})
            continue
        group = f"{r.clip.corpus}/{r.clip.language}"
        pairs.append(MotionPair(clip, group, p.params, r.identity, r.params))
    if not pairs:
        raise ScoreInputError(f"no clip could be scored ({len(report.unscored)} refused; "
                              + "; ".join(f"{u['clip']}: {u['reason']}" for u in report.unscored[:3]) + ")")
    for name in chosen:
        try:
            scorer = MotionScorer(body, MotionMetricsConfig(mode=name))
        except SokeModeError as exc:
            raise ScoreInputError(str(exc)) from exc
        scores = scorer.score(pairs)
        for key, value in {**scores.overall, "empty_rate": scores.empty_rate}.items():
            report.metrics[f"{name}_{key}"] = value
            report.definition_of[f"{name}_{key}"] = name
        report.clips_scored[name] = len(pairs)
        for row in scores.per_clip:
            report.per_clip += [{"clip": row.clip_id, "definition": name, "metric": f"{name}_{k}", "value": v}
                                for k, v in row.metrics.items()]
    report.notes.append(f"body model: {body.name}; both sides posed with the reference's identity; metres")
    return report
