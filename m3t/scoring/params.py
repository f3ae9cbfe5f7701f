"""Body-model parameters scored as the SMLM's evaluation scores them: two Parquet shards of this project
(:mod:`m3t.shards`, e.g. a fitted test split and a system's output written as a shard; a token shard such as
generate-smlm's ``generated.parquet`` is decoded by the tokenizers that wrote it) -> definitions ``m3t``
(DTW-JPE / DTW-PA-JPE per region and the face's DTW-VPE on the workspace's body model, this project's tables)
and ``soke_exact`` (SOKE's pelvis-rooted body and zeroed joints; SMPL-FX only), through the one scorer
:class:`m3t.metrics.scorer.MotionScorer`.

Both sides of a pair are posed with the **reference's** identity (the scorer's rule: the error is the motion's
alone). Keys carry the definition: ``m3t_dtw_jpe_body_m`` is the pipeline's ``dtw_jpe_body_m`` under mode
``m3t``. A clip is refused with its reason when its two sides differ in body model, when the shards' layouts
differ from the body model's, or when it has no frames on the reference side.

With a judge (the back-translation checkpoints), every sentence clip's prediction is back-translated and scored
against the reference's text under the text definitions (``slt``, ``soke``, ``slrtp``), keys
``<definition>/<language>/<metric>`` as evaluate-smlm writes them under ``bt/``; isolated signs and clips
without text are left out with that reason, as the pipeline leaves them out. A released SignSparK_BT model
directory as the judge (:mod:`m3t.backtranslation.signspark`) back-translates the clips of its one language from
their 240-d SMPL-X input, under the same definitions and keys.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.body.protocol import BodyModel
from m3t.corpora.clip import Clip
from m3t.metrics.definitions import TEXT_DEFINITIONS, text_metrics
from m3t.metrics.motion import MotionMetricsConfig
from m3t.metrics.scorer import MotionPair, MotionScorer
from m3t.metrics.soke import SokeModeError
from m3t.scoring.poses import ScoreInputError
from m3t.scoring.report import ScoreReport, check_definitions, pairing
from m3t.shards.io import parquet_file, read_shard
from m3t.shards.schema import ShardFormatError
from m3t.shards.tokens import read_token_shard

TOKEN_VERSION_KEY = b"m3t.token_schema_version"

MOTION_DEFINITIONS = ("m3t", "soke_exact")
PARAMETER_DEFINITIONS = (*MOTION_DEFINITIONS, *TEXT_DEFINITIONS)  # text: the judge's back-translations


@dataclass(frozen=True)
class Side:
    """One side's clips: clip id -> (corpus record, {modality: (T, D) parameters}, body model name)."""

    path: Path
    modalities: dict[str, int]
    clips: dict[str, tuple[Clip, dict[str, np.ndarray], str]]
    identities: dict[str, np.ndarray]


def is_token_shard(path: Path) -> bool:
    """Whether ``path`` is a token shard (what tokenize and generate-smlm write), by its Parquet metadata."""
    try:
        return TOKEN_VERSION_KEY in (parquet_file(path).schema_arrow.metadata or {})
    except (ShardFormatError, OSError):
        return False


def read_side(path: Path, side: str, body: BodyModel, tokenizers_dir: Path | None = None) -> Side:
    """A parameter shard as it is, or a token shard decoded by the tokenizers of ``tokenizers_dir`` (an empty
    generation, no token, is a 0-frame prediction: scored as the rest pose, as evaluate-smlm scores it)."""
    if is_token_shard(path):
        return _decoded(path, side, body, tokenizers_dir)
    try:
        shard = read_shard(path)
    except (ShardFormatError, OSError) as exc:
        raise ScoreInputError(f"{side} shard {exc}") from exc
    return Side(path, dict(shard.layout.dims), {c.clip.id: (c.clip, c.params, c.body_model) for c in shard.clips},
                {c.clip.id: c.identity for c in shard.clips})


def _decoded(path: Path, side: str, body: BodyModel, tokenizers_dir: Path | None) -> Side:
    from m3t.tokenizers.evaluate import decode_streams
    from m3t.tokenizers.tokenize import load_tokenizers

    if tokenizers_dir is None or not Path(tokenizers_dir).is_dir():
        raise ScoreInputError(f"{path}: a token shard; decoding its {side} needs the tokenizers that wrote it "
                              f"(models/tokenizers; not found: {tokenizers_dir})")
    try:
        shard = read_token_shard(path)
    except ShardFormatError as exc:
        raise ScoreInputError(f"{side} token shard {exc}") from exc
    tokenizers, info = load_tokenizers(tokenizers_dir)
    if shard.info.tokenizers != info.tokenizers:
        raise ScoreInputError(f"{path}: written with tokenizers {shard.info.tokenizers}, {tokenizers_dir} holds "
                              f"{info.tokenizers}; decode with the tokenizers that wrote it")
    empty = {name: np.zeros((0, dim), np.float32) for name, dim in body.layout.dims.items()}
    clips = {c.clip.id: (c.clip, decode_streams(tokenizers, c.tokens) if c.num_tokens else dict(empty), body.name)
             for c in shard.clips}
    return Side(path, dict(body.layout.dims), clips, {})


def _check_layout(side: Side, body: BodyModel, name: str) -> None:
    if side.modalities != dict(body.layout.dims):
        raise ScoreInputError(f"{side.path}: {name} parameters have modalities {side.modalities}, the workspace's "
                              f"body model {body.name!r} has {dict(body.layout.dims)}; set body.model in params.yaml "
                              "to the model the shard was fitted with")


def score_parameter_shards(pred: Path, ref: Path, body: BodyModel, definitions: Sequence[str] | None = None,
                           progress: Callable[[Iterable], Iterable] | None = None,
                           judge: Path | None = None, beam_size: int = 1, length_penalty: float = 1.0,
                           tokenizers_dir: Path | None = None, judge_language: str | None = None) -> ScoreReport:
    """Score the clips of shard ``pred`` against those of shard ``ref`` on ``body`` (see the module doc); a token
    shard on either side is decoded by the tokenizers of ``tokenizers_dir``. With a
    ``judge`` folder (back-translation checkpoints, ``models/backtranslation``), the predictions are also
    back-translated (``beam_size``, ``length_penalty``: the decoding of params.yaml ``backtranslation``) and the
    sentences scored against the reference shard's texts under the text definitions. A SignSparK_BT model
    directory as ``judge`` back-translates with that released model (its own decoding; ``judge_language``: the
    sign language of its clips when its dataset does not say it, :mod:`m3t.backtranslation.signspark`)."""
    if definitions is None:  # every definition that applies: soke_exact needs SMPL-FX, text ones a judge
        definitions = [d for d in PARAMETER_DEFINITIONS if (d != "soke_exact" or body.name == "smplfx")
                       and (d in MOTION_DEFINITIONS or judge is not None)]
    chosen = check_definitions(definitions, PARAMETER_DEFINITIONS, "parameter")
    report = ScoreReport("parameters", str(pred), str(ref))
    predicted = read_side(pred, "prediction", body, tokenizers_dir)
    references = read_side(ref, "reference", body, tokenizers_dir)
    if not references.identities:
        raise ScoreInputError(f"{ref}: the reference must be a parameter shard (fitted motion with the signer's "
                              "identity), not a token shard")
    for side, name in ((predicted, "prediction"), (references, "reference")):
        _check_layout(side, body, name)
    ids = pairing(predicted.clips, references.clips, report, "clip")
    pairs = []
    for clip in (progress or (lambda x: x))(ids):
        (_, p_params, p_body), (r_clip, r_params, r_body) = predicted.clips[clip], references.clips[clip]
        if p_body != r_body or r_body != body.name:
            report.unscored.append({"clip": clip, "definition": "all", "reason": (
                f"prediction fitted with {p_body!r}, reference with {r_body!r}, workspace body model "
                f"{body.name!r}; both sides must be parameters of the workspace's body model")})
            continue
        if not len(next(iter(r_params.values()), ())):
            report.unscored.append({"clip": clip, "definition": "all", "reason": "the reference has no frames"})
            continue
        group = f"{r_clip.corpus}/{r_clip.language}"
        pairs.append(MotionPair(clip, group, p_params, references.identities[clip], r_params))
    if not pairs:
        raise ScoreInputError(f"no clip could be scored ({len(report.unscored)} refused; "
                              + "; ".join(f"{u['clip']}: {u['reason']}" for u in report.unscored[:3]) + ")")
    score_motion_pairs(report, pairs, body, [d for d in chosen if d in MOTION_DEFINITIONS])
    text = [d for d in chosen if d in TEXT_DEFINITIONS]
    if text:
        if judge is None:
            raise ScoreInputError(f"definitions {text} score back-translated sentences and need a judge: the "
                                  "folder of back-translation checkpoints (`dvc repro train-backtranslation` writes "
                                  "models/backtranslation)")
        _backtranslated(report, pairs, {c: v[0] for c, v in references.clips.items()}, judge, text, beam_size,
                        length_penalty, body, judge_language)
    report.notes.append(f"body model: {body.name}; both sides posed with the reference's identity; metres")
    return report


def score_motion_pairs(report: ScoreReport, pairs: Sequence[MotionPair], body: BodyModel,
                       definitions: Sequence[str]) -> None:
    """Score ``pairs`` under each motion definition of ``definitions`` (``m3t``, ``soke_exact``) with
    :class:`MotionScorer` into ``report``: keys ``<definition>_<metric>``, the clip count, every clip's values."""
    for name in definitions:
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


def _backtranslated(report: ScoreReport, pairs: Sequence[MotionPair], clips: dict, judge: Path,
                    definitions: Sequence[str], beam_size: int, length_penalty: float, body: BodyModel,
                    judge_language: str | None = None) -> None:
    """Back-translate each pair's prediction with the judge of its clip's language (this project's judges, or a
    SignSparK_BT model directory, recognised by its config); score the sentences per language against the
    reference texts (as the judge's text rule writes them). Keys ``<definition>/<language>/<metric>``, as the
    back-translation stages write them."""
    from m3t.backtranslation.signspark import is_signspark_judge

    if is_signspark_judge(judge):
        rows = _signspark_rows(report, pairs, clips, judge, body, judge_language)
    else:
        rows = _m3t_rows(report, pairs, clips, judge, beam_size, length_penalty)
    for language in dict.fromkeys(r["language"] for r in rows):
        mine = [r for r in rows if r["language"] == language]
        for name in definitions:
            values = text_metrics([r["hypothesis"] for r in mine], [r["reference"] for r in mine], language, [name])
            for key, value in values.items():  # "slt_bleu4" -> "slt/<language>/bleu4", the pipeline's key
                named = f"{name}/{language}/{key.removeprefix(name + '_')}"
                report.metrics[named] = value
                report.definition_of[named] = name
            report.clips_scored[name] = report.clips_scored.get(name, 0) + len(mine)
    report.sentences += [{"clip": r["clip_id"], "language": r["language"], "hypothesis": r["hypothesis"],
                          "reference": r["reference"]} for r in rows]


def _judged(report: ScoreReport, pairs: Sequence[MotionPair], clips: dict, languages: set[str],
            judges: str) -> list[MotionPair]:
    """The pairs a judge of ``languages`` back-translates; the others go to the report's unscored list with their
    reason (isolated signs and clips without text, as the pipeline skips them)."""
    from m3t.backtranslation.data import skip_reason

    kept = []
    for pair in pairs:
        clip = clips[pair.clip_id]
        if clip.language not in languages:
            reason = f"no judge for language {clip.language!r} in {judges}"
        elif skip_reason(clip, 1) is not None:
            reason = f"not back-translated: {skip_reason(clip, 1)}"
        else:
            kept.append(pair)
            continue
        report.unscored.append({"clip": pair.clip_id, "definition": "back-translation", "reason": reason})
    return kept


def _m3t_rows(report: ScoreReport, pairs: Sequence[MotionPair], clips: dict, judge: Path, beam_size: int,
              length_penalty: float) -> list[dict]:
    """Back-translations by this project's judges (``<language>.pt`` of ``judge``)."""
    from m3t.backtranslation.pipeline import backtranslate, load_models

    try:
        languages = set(load_models(judge))
    except FileNotFoundError as exc:
        raise ScoreInputError(f"{exc} (a SignSparK_BT model directory holds config.yaml, best.ckpt, txt.vocab and "
                              "gls.vocab)") from exc
    kept = _judged(report, pairs, clips, languages, f"{judge} (judges: {sorted(languages)})")
    if not kept:
        return []
    inputs = {p.clip_id: (clips[p.clip_id].language, p.prediction) for p in kept}
    return backtranslate(judge, inputs, {p.clip_id: clips[p.clip_id].text for p in kept}, beam_size,
                         length_penalty).per_clip


def _signspark_rows(report: ScoreReport, pairs: Sequence[MotionPair], clips: dict, judge: Path, body: BodyModel,
                    language: str | None) -> list[dict]:
    """Back-translations by a released SignSparK_BT model: its 240-d SMPL-X input from the predictions, its own
    decoding and reference text rule. A body model without the SMPL-X joints leaves every clip unscored with
    :func:`~m3t.backtranslation.smplx240.smplx240_index`'s reason."""
    from m3t.backtranslation.signspark import (
        SignSparkCheckpointError,
        load_signspark,
        translate,
    )
    from m3t.backtranslation.smplx240 import smplx240_index, to_smplx240

    try:
        loaded = load_signspark(judge, language)
    except (FileNotFoundError, SignSparkCheckpointError) as exc:
        raise ScoreInputError(str(exc)) from exc
    kept = _judged(report, pairs, clips, {loaded.language}, f"{judge} (the SignSparK_BT judge of "
                   f"{loaded.language!r}, trained on {loaded.dataset})")
    try:
        smplx240_index(body.layout, body.name)
    except ValueError as exc:
        report.unscored += [{"clip": p.clip_id, "definition": "back-translation", "reason": str(exc)} for p in kept]
        return []
    if not kept:
        return []
    dec = loaded.decoding
    report.notes.append(f"judge: SignSparK_BT {loaded.checkpoint} ({loaded.language}, {loaded.dataset}); its own "
                        f"decoding (beam {dec.beam_size}, alpha {dec.alpha:g}, at most {dec.max_output_length} "
                        "tokens; params.yaml's beam_size and length_penalty not used) and reference text rule")
    hypotheses = translate(loaded, [to_smplx240(p.prediction, body.layout, body.name) for p in kept])
    return [{"clip_id": p.clip_id, "language": loaded.language, "hypothesis": h,
             "reference": loaded.text.reference(clips[p.clip_id].text)} for p, h in zip(kept, hypotheses)]
