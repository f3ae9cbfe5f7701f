"""The skeletal production runs behind the train-sgsa and evaluate-sgsa stages, over the fitted shards of
``data.train_corpora`` seen as skeletons (:mod:`m3t.shards.skeletons`, graph ``sgsa.skeleton``).

- :func:`train_and_log`: every system of ``sgsa_train.systems`` (``pt``: Progressive Transformers, ``sgsa``: the
  configured SGSA model) on the train split, selected on the dev split's DTW-JPE; writes
  ``<models>/sgsa/<system>.pt``, ``metrics.json`` and ``skipped.jsonl``.
- :func:`evaluate_and_log`: SGSA Tab. 1-3 and the cross-paper comparison. For each split of
  ``sgsa_evaluate.splits`` and each trained system: generation (predicted counter by default), DTW-JPE /
  DTW-PA-JPE per region against the reference skeletons, and the back-translation of the sentence clips by the
  frozen **skeleton judge** (``<models>/backtranslation-skeleton``, SL-T definition) with BLEU-1..4 / ROUGE-L.
  The same judges score the ground truth (the upper bound) and, on the split generate-smlm produced, the M3T
  SMLM's motion posed into the same skeleton (``smlm``): one table, one corpus, one split, one judge.
  Writes ``<metrics>/sgsa/metrics.json`` (``<system>/<split>/<metric>``), ``per_clip.csv``,
  ``backtranslation.csv``, ``pose/<system>/<clip>.pose`` (every clip each trained system produced, a skeleton
  ``.pose``: :func:`m3t.render.posefile.export_skeleton_pose`), side-by-side skeleton videos
  ``videos/<clip>.mp4`` (reference / PT / SGSA / SMLM) and an attention-map picture.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from m3t.atomic import copy_file, write_json, write_jsonl, write_text
from m3t.backtranslation.config import BackTranslationConfig
from m3t.backtranslation.pipeline import PER_CLIP_COLUMNS, backtranslate
from m3t.body.factory import BodyConfig, load_body_model
from m3t.body.protocol import BodyModel
from m3t.body.skeleton import SkeletonGraph, graph_for
from m3t.body.skeleton_points import regions
from m3t.experiment import ExperimentConfig, section_params, start_run
from m3t.metrics.scorer import PointPair, score_point_pairs
from m3t.metrics.text import SLT_DEFINITION
from m3t.reporting import csv_text, frame_csv
from m3t.shards.folders import DataConfig
from m3t.shards.io import production_data_version, read_production_split
from m3t.shards.skeletons import SKELETON_STREAM, graph_points, skeleton_clips
from m3t.sgsa.checkpoint import STAGE, LoadedSGSA, load_sgsa
from m3t.sgsa.config import SGSAConfig, SGSAEvaluateConfig, SGSATrainConfig
from m3t.sgsa.data import Sample, collate, make_samples, vocabularies
from m3t.sgsa.evaluate import MEAN_DTW, generate, produced_points, score_production
from m3t.sgsa.train import run_key, train_sgsa
from m3t.training_jobs import run_jobs, worker_split
from m3t.vocabulary import Vocabulary

SMLM_SYSTEM = "smlm"  # the M3T SMLM's generated motion, posed into the same skeleton
REFERENCE = "ground_truth"  # the fitted motion itself: the judges' upper bound


def checkpoint_name(system: str) -> str:
    return f"{system}.pt"


# ------------------------------------------------------------------------------------------ train
def _train_system(model_cfg: SGSAConfig, cfg: SGSATrainConfig, graph: SkeletonGraph, text_vocab: Vocabulary,
                  gloss_vocab: Vocabulary | None, train: list[Sample], dev: list[Sample], version: str, out: Path,
                  progress: bool, system: str, on_epoch: Callable[[dict[str, float], int], None] | None
                  ) -> dict[str, float]:
    """Train one system into ``out/<system>.pt`` (here or in a worker process); its numbers for metrics.json."""
    system_cfg = model_cfg.for_system(system)
    key = run_key(system_cfg, cfg, graph, text_vocab, gloss_vocab, version)
    best, last = Path(cfg.cache_dir) / f"{key}.best.pt", Path(cfg.cache_dir) / f"{key}.last.pt"
    result = train_sgsa(system_cfg, cfg, graph, text_vocab, gloss_vocab, train, dev, version, best, last,
                        progress=progress, on_epoch=on_epoch)
    copy_file(best, out / checkpoint_name(system))
    parameters = sum(p.numel() for p in result.model.parameters() if p.requires_grad)
    return {f"{system}/parameters": float(parameters), f"{system}/best_epoch": float(result.best.get("epoch", 0)),
            **{f"{system}/best_{k}": float(v) for k, v in result.best.items() if k.startswith(("val_", "train_"))}}


def run_train(model_cfg: SGSAConfig, cfg: SGSATrainConfig, body: BodyModel, data: DataConfig, on_epoch=None,
              progress: bool = True) -> dict[str, float]:
    """Train every system of ``cfg.systems``; ``on_epoch(system, record, epoch)`` sees each epoch's record."""
    graph = graph_for(model_cfg.skeleton, model_cfg.face_points)
    train_clips = skeleton_clips(body, read_production_split(data, "train"), graph, progress, "skeletons: train")
    dev_clips = skeleton_clips(body, read_production_split(data, "dev"), graph, progress, "skeletons: dev")
    if not train_clips:
        raise ValueError(f"the train split of {list(data.train_corpora)} has no clip with frames")
    text_vocab, gloss_vocab = vocabularies(train_clips, model_cfg)
    train = make_samples(train_clips, text_vocab, gloss_vocab, model_cfg, training=True)
    dev = make_samples(dev_clips, text_vocab, gloss_vocab, model_cfg, training=False)
    version = production_data_version(data)
    out = data.sgsa_dir
    report: dict[str, float] = {"train_clips": float(len(train.samples)), "dev_clips": float(len(dev.samples)),
                                "skipped_clips": float(len(train.skipped) + len(dev.skipped)),
                                "cut_frames": float(train.cut_frames), "skeleton_width": float(graph.width + 1),
                                "text_vocabulary_size": float(len(text_vocab)),
                                "gloss_vocabulary_size": float(0 if gloss_vocab is None else len(gloss_vocab))}
    processes, threads = worker_split(cfg.workers, len(cfg.systems), cfg.device)
    run = partial(_train_system, model_cfg, cfg, graph, text_vocab, gloss_vocab, train.samples, dev.samples, version,
                  out, progress)
    for numbers in run_jobs(run, list(cfg.systems), list(cfg.systems), processes, threads, on_epoch, "system",
                            "sgsa_train.workers"):
        report.update(numbers)
    for stale in out.glob("*.pt"):
        if stale.name not in {checkpoint_name(s) for s in cfg.systems}:
            stale.unlink()
    write_json(out / "metrics.json", report)
    write_jsonl(out / "skipped.jsonl", train.skipped + dev.skipped)
    return report


def train_and_log(model_cfg: SGSAConfig, cfg: SGSATrainConfig, body_cfg: BodyConfig, data: DataConfig,
                  experiment: ExperimentConfig, progress: bool = True) -> dict[str, float]:
    """:func:`run_train` inside an MLflow run (params, per-epoch curves per system, the written files)."""
    body = load_body_model(body_cfg)
    tags = {"systems": ",".join(cfg.systems), "skeleton": model_cfg.skeleton, "body_model": body_cfg.model,
            "seed": str(cfg.seed)}
    with start_run(experiment, STAGE, tags=tags, variant=model_cfg.variant) as run:
        run.log_params(section_params(sgsa=model_cfg, sgsa_train=cfg, data=data))
        report = run_train(model_cfg, cfg, body, data, progress=progress,
                           on_epoch=lambda system, record, epoch: run.log_metrics(
                               {f"{system}/{k}": v for k, v in record.items()}, step=epoch))
        run.log_metrics(report)
        for name in ("metrics.json", "skipped.jsonl"):
            run.log_artifact(data.sgsa_dir / name)
    return report


# --------------------------------------------------------------------------------------- evaluate
def load_systems(data: DataConfig, device: str = "cpu") -> dict[str, LoadedSGSA]:
    files = sorted(data.sgsa_dir.glob("*.pt")) if data.sgsa_dir.is_dir() else []
    if not files:
        raise FileNotFoundError(f"no SGSA / PT checkpoint in {data.sgsa_dir}; run `dvc repro {STAGE}` "
                                "(python -m m3t.stages.train_sgsa) first")
    return {path.stem: load_sgsa(path, device) for path in files}


def _smlm_params(data: DataConfig, split: str, body: BodyModel) -> dict[str, dict[str, np.ndarray]] | None:
    """clip id -> the SMLM's generated parameters (frozen tokenizers' decoding; the rest pose for an empty
    generation), when generate-smlm produced ``split``; None otherwise."""
    from m3t.shards.tokens import read_token_shard
    from m3t.tokenizers.evaluate import decode_streams
    from m3t.tokenizers.tokenize import load_tokenizers

    path = data.generated / "generated.parquet"
    if not path.exists():
        return None
    shard = read_token_shard(path)
    if not shard.clips or shard.clips[0].clip.split != split:
        return None
    tokenizers, _ = load_tokenizers(data.tokenizers_dir)
    rest = {k: v.detach().cpu().numpy() for k, v in body.rest_params(1).items()}
    return {c.clip.id: decode_streams(tokenizers, dict(c.tokens)) if c.num_tokens else rest for c in shard.clips}


def _judge(judge_dir: Path, rows: dict[str, tuple[str, np.ndarray]], texts: dict[str, str],
           judge: BackTranslationConfig):
    """Back-translate {clip id: (language, (T, C) normalised coordinates)} with the skeleton judge."""
    clips = {cid: (language, {SKELETON_STREAM: coords}) for cid, (language, coords) in rows.items()}
    return backtranslate(judge_dir, clips, texts, judge.beam_size, judge.length_penalty)


@dataclass
class Posed:
    """A parameter system scored on the skeleton: ``<system>/<split>/<metric>`` figures, per-clip rows, the
    judge's rows and the posed points {clip id: (U, J, 3) metres}."""

    summary: dict[str, float]
    per_clip: list[dict]
    backtranslation: list[dict]
    points: dict[str, np.ndarray]


def score_posed(system: str, split: str, params: dict[str, dict[str, np.ndarray]], samples: list[Sample],
                graph: SkeletonGraph, body: BodyModel, judge_dir: Path,
                judge: BackTranslationConfig | None) -> Posed:
    """Body-model parameters of any system (``{clip id: {modality: (T, D_m)}}``, e.g. the SMLM's generations or a
    baseline's) posed into ``graph`` with each reference signer's identity and scored against the reference
    skeletons like the skeletal systems (DTW-JPE / DTW-PA-JPE per region), the samples of ``params`` only; with
    ``judge``, its sentence clips back-translated by the skeleton judge (SL-T definition)."""
    from m3t.body.skeleton_points import normalise

    by_id = {s.clip_id: s for s in samples}
    scored = [s for s in samples if s.clip_id in params]
    points = {s.clip_id: graph_points(body, params[s.clip_id], s.clip.fitted.identity, graph) for s in scored}
    scores = score_point_pairs([PointPair(s.clip_id, s.group, len(points[s.clip_id]),
                                          regions(points[s.clip_id], graph), regions(s.clip.points, graph))
                                for s in scored])
    summary = {f"{system}/{split}/{k}": v for k, v in scores.summary.items()}
    summary[f"{system}/{split}/{MEAN_DTW}"] = 0.5 * (scores.overall["dtw_jpe_body_m"] + scores.overall["dtw_jpe_hand_m"])
    summary[f"{system}/{split}/clips"] = float(len(scored))
    per_clip = [{"system": system, "split": split, "clip_id": c.clip_id, "group": c.group, "frames": c.frames,
                 "reference_frames": len(by_id[c.clip_id].clip.points), **c.metrics} for c in scores.per_clip]
    rows: list[dict] = []
    sentences = [s for s in scored if s.sentence]
    if judge is not None and sentences:
        judged = _judge(judge_dir, {s.clip_id: (s.language, normalise(points[s.clip_id], graph)[0])
                                    for s in sentences},
                        {s.clip_id: s.clip.fitted.clip.text for s in sentences}, judge)
        summary.update({f"{system}/{split}/bt/{k}": v for k, v in judged.summary.items()})
        rows = [{"system": system, "split": split, **r} for r in judged.per_clip]
    return Posed(summary, per_clip, rows, points)


def run_evaluate(model_cfg: SGSAConfig, cfg: SGSAEvaluateConfig, body: BodyModel, data: DataConfig,
                 judge: BackTranslationConfig | None = None, progress: bool = True) -> dict[str, float]:
    """Score every trained system (and the SMLM and the ground truth) on ``cfg.splits``; see the module docstring."""
    from m3t.render.posefile import export_skeleton_pose
    from m3t.render.skeleton_video import render_attention_map, render_skeleton_video
    from m3t.runtime import choose_device

    judge = judge or BackTranslationConfig()
    device = str(choose_device(cfg.device))
    systems = load_systems(data, device)
    if len({s.graph for s in systems.values()}) != 1:
        raise ValueError(f"the checkpoints of {data.sgsa_dir} use different skeleton graphs; retrain them together")
    first = next(iter(systems.values()))
    graph: SkeletonGraph = first.graph
    summary: dict[str, float] = {}
    per_clip: list[dict] = []
    bt_rows: list[dict] = []
    skipped: list[dict] = []
    out = data.metrics("sgsa")
    videos: dict[str, dict[str, np.ndarray]] = {}
    shown: list[Sample] = []
    for split in cfg.splits:
        clips = skeleton_clips(body, read_production_split(data, split), graph, progress, f"skeletons: {split}")
        sets = make_samples(clips, first.text_vocab, first.gloss_vocab, model_cfg, training=False)
        samples = sets.samples
        skipped.extend(sets.skipped)
        summary[f"{split}/clips"] = float(len(samples))
        summary[f"{split}/cut_text"] = float(sets.cut_text)
        sentences = [s for s in samples if s.sentence]
        texts = {s.clip_id: s.clip.fitted.clip.text for s in sentences}
        produced_by: dict[str, dict[str, np.ndarray]] = {}  # system -> clip id -> (U, J, 3) metres
        for name, loaded in systems.items():
            frames = generate(loaded.model, samples, loaded.text_vocab, loaded.model.cfg.max_frames, cfg.counter,
                              cfg.batch_size)
            report = score_production(samples, frames, graph, loaded.model.cfg.max_frames, progress)
            summary.update({f"{name}/{split}/{k}": v for k, v in report.summary.items()})
            per_clip.extend({"system": name, "split": split, **row} for row in report.per_clip)
            produced_by[name] = {s.clip_id: produced_points(frames[s.clip_id], graph, s.clip.scale) for s in samples}
            for s in samples:
                if len(produced_by[name][s.clip_id]):
                    export_skeleton_pose(out / "pose" / name / f"{s.clip_id}.pose", produced_by[name][s.clip_id],
                                         graph, s.clip.fitted.clip.fps or 25.0)
            if cfg.backtranslate and sentences:
                judged = _judge(data.skeleton_judge_dir,
                                {s.clip_id: (s.language, frames[s.clip_id][:, :-1]) for s in sentences}, texts, judge)
                summary.update({f"{name}/{split}/bt/{k}": v for k, v in judged.summary.items()})
                bt_rows.extend({"system": name, "split": split, **r} for r in judged.per_clip)
        smlm = _smlm_params(data, split, body)
        if smlm is not None:
            posed = score_posed(SMLM_SYSTEM, split, smlm, samples, graph, body, data.skeleton_judge_dir,
                                judge if cfg.backtranslate else None)
            summary.update(posed.summary)
            per_clip.extend(posed.per_clip)
            bt_rows.extend(posed.backtranslation)
            produced_by[SMLM_SYSTEM] = posed.points
        if cfg.backtranslate and sentences:
            judged = _judge(data.skeleton_judge_dir, {s.clip_id: (s.language, s.clip.coords) for s in sentences},
                            texts, judge)
            summary.update({f"{REFERENCE}/{split}/bt/{k}": v for k, v in judged.summary.items()})
            bt_rows.extend({"system": REFERENCE, "split": split, **r} for r in judged.per_clip)
        if split == cfg.splits[-1]:
            shown = samples[: cfg.render_clips]
            for s in shown:
                videos[s.clip_id] = {"reference": s.clip.points,
                                     **{name: produced[s.clip_id] for name, produced in produced_by.items()
                                        if s.clip_id in produced}}
    write_json(out / "metrics.json", summary)
    write_text(out / "per_clip.csv", frame_csv(per_clip))
    write_text(out / "backtranslation.csv", _bt_csv(bt_rows))
    write_jsonl(out / "skipped.jsonl", skipped)
    for cid, sequences in videos.items():
        fps = next(s.clip.fitted.clip.fps for s in samples if s.clip_id == cid) if samples else 25.0
        render_skeleton_video(sequences, graph, out / "videos" / f"{cid}.mp4", fps=fps, title=cid, progress=progress)
    attention = next((s for s in systems if systems[s].model.cfg.decoder_layers > 0), None)
    if attention is not None and shown:
        loaded = systems[attention]
        layer = loaded.model.cfg.decoder_layers - 1
        batch = collate(shown[:1], loaded.text_vocab).to(loaded.model_device)
        weights = loaded.model.self_attention(batch.text_ids, batch.text_mask, batch.frames_in, layer)[0]
        render_attention_map(weights.cpu().numpy(), out / "attention.png",
                             f"{loaded.model.cfg.variant}: self-attention of layer {layer + 1}, clip {shown[0].clip_id} "
                             "(teacher forced)")
    return summary


def _bt_csv(rows: list[dict]) -> str:
    """The judge's per-clip rows of every system and split (back-translation's columns after those two)."""
    if not rows:
        return ""
    return csv_text(rows, ("system", "split", *PER_CLIP_COLUMNS))


def evaluate_and_log(model_cfg: SGSAConfig, cfg: SGSAEvaluateConfig, body_cfg: BodyConfig, data: DataConfig,
                     experiment: ExperimentConfig, judge: BackTranslationConfig | None = None) -> dict[str, float]:
    summary = run_evaluate(model_cfg, cfg, load_body_model(body_cfg), data, judge)
    trained = data.sgsa_dir / checkpoint_name("sgsa")
    seed = load_sgsa(trained).train_config.get("seed", "") if trained.exists() else ""
    tags = {"counter": cfg.counter, "splits": ",".join(cfg.splits), "seed": str(seed), "body_model": body_cfg.model,
            "text_metric_definition": SLT_DEFINITION, "motion_metric_definition": "soke-dtw (skeleton)"}
    with start_run(experiment, "evaluate-sgsa", tags=tags, variant=model_cfg.variant) as run:
        run.log_params(section_params(sgsa=model_cfg, sgsa_evaluate=cfg, data=data))
        run.log_metrics({k: v for k, v in summary.items() if v == v and abs(v) != float("inf")})
        out = data.metrics("sgsa")
        for name in ("metrics.json", "per_clip.csv", "backtranslation.csv"):
            run.log_artifact(out / name)
        for path in sorted((out / "videos").glob("*.mp4")) + sorted(out.glob("attention.png")):
            run.log_artifact(path, "renders")
    return summary
