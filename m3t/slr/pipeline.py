"""The recognition probe runs behind the train-slr and evaluate-slr stages, over the isolated, labelled clips of
one corpus (``slr.corpus``: its fitted shards ``data.shards_dir(corpus)``) and the frozen tokenizers of
``data.tokenizers_dir``.

- :func:`run_train_slr` / :func:`train_and_log`: trim (:mod:`~m3t.slr.trim`), encode once with the frozen
  encoders (:mod:`~m3t.slr.features`), then train each variant of ``slr_train.variants`` (the full probe and
  the face-less ablation) on the train split, selected by dev Top-1. Writes ``<models>/slr/<variant>.pt``,
  ``metrics.json`` (clips, classes, trimmed share, best epochs), ``skipped.jsonl`` and the dev confusion
  matrices ``confusion_dev_<variant>.png``; MLflow gets the params, per-epoch curves and the pictures.
- :func:`run_evaluate_slr` / :func:`evaluate_and_log`: the checkpoints on ``slr_evaluate.split``: Tab. 4 scores
  with bootstrap intervals (:mod:`~m3t.slr.evaluate`), ``<metrics>/slr/metrics.json``, ``table.csv``,
  ``table.md``, ``predictions.csv``, ``skipped.jsonl`` and ``confusion_<variant>.png``.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

from m3t.atomic import copy_file, write_json, write_jsonl, write_text
from m3t.body.factory import BodyConfig, load_body_model
from m3t.body.protocol import STREAM_ORDER, BodyModel
from m3t.corpora.nmfs_csl import SUBSET_HINT
from m3t.experiment import ExperimentConfig, section_params, start_run
from m3t.reporting import csv_text
from m3t.runtime import choose_device
from m3t.shards.folders import DataConfig
from m3t.shards.io import data_version, iter_split, read_split
from m3t.shards.schema import FittedClip
from m3t.slr.checkpoint import LoadedSLR, ProbeMeta, load_slr
from m3t.slr.config import SLRConfig, SLREvaluateConfig, SLRTrainConfig
from m3t.slr.evaluate import (
    Evaluation,
    clip_pair,
    clip_subset,
    evaluate_logits,
    pair_hits,
    plot_confusion,
    topk_hits,
)
from m3t.slr.features import (
    Example,
    FrozenEncoders,
    build_examples,
    example_batches,
    iter_examples,
    variant_streams,
    without_features,
)
from m3t.slr.model import ProbeDims
from m3t.slr.table import table_csv, table_markdown
from m3t.slr.train import predict_logits, run_key, train_slr
from m3t.slr.trim import Trimmer
from m3t.tokenizers.data import GROUPS
from m3t.tokenizers.tokenize import load_tokenizers
from m3t.training_jobs import run_jobs, worker_split

SPLITS = ("train", "dev", "test")


# ------------------------------------------------------------------------------------------- data
@dataclass(frozen=True)
class ClassTable:
    """The probe's classes: output index -> corpus label id and gloss, over every split of the corpus."""

    labels: tuple[int, ...]
    names: tuple[str, ...]

    @property
    def index(self) -> dict[int, int]:
        return {label: i for i, label in enumerate(self.labels)}


def labelled(clips: Iterable[FittedClip]) -> list[FittedClip]:
    """The isolated-sign clips (``label`` set); sentence clips of the same corpus are not the probe's."""
    return [c for c in clips if c.clip.label is not None]


def labelled_motion(data: DataConfig, corpus: str, split: str) -> Iterator[FittedClip]:
    """The labelled clips of a split with their motion, read a few clips at a time (for
    :func:`m3t.slr.features.iter_examples`: the features are what a run keeps, not the motion)."""
    return (c for c in iter_split(data.shards_dir(corpus), split) if c.clip.label is not None)


def corpus_metadata(data: DataConfig, corpus: str) -> dict[str, list[FittedClip]]:
    """Every split's labelled clips without their motion (metadata only); a clear error when there are none."""
    splits = {split: labelled(read_split(data.shards_dir(corpus), split, modalities=[])) for split in SPLITS}
    if not any(splits.values()):
        raise ValueError(f"corpus {corpus!r} has no labelled (isolated-sign) clips in {data.shards_dir(corpus)}/"
                         "{train,dev,test}.parquet; the recognition probe needs class labels: point slr.corpus at an "
                         "isolated-sign corpus (nmfs_csl, or synthetic, whose isolated clips carry labels)")
    return splits


def class_table(clips: Iterable[FittedClip]) -> ClassTable:
    names: dict[int, str] = {}
    for c in clips:
        names.setdefault(int(c.clip.label), c.clip.gloss or c.clip.text or str(c.clip.label))
    labels = tuple(sorted(names))
    return ClassTable(labels, tuple(names[label] for label in labels))


def pair_classes(clips: Iterable[FittedClip], index: dict[int, int]) -> dict[str, tuple[int, ...]]:
    """Manual-identical pair id -> the class indices of its confusing signs (from the clips' ``pair`` extra)."""
    pairs: dict[str, set[int]] = {}
    for c in clips:
        pair = clip_pair(c.clip)
        if pair is not None and clip_subset(c.clip) == "confusing" and c.clip.label in index:
            pairs.setdefault(pair, set()).add(index[c.clip.label])
    return {k: tuple(sorted(v)) for k, v in pairs.items()}


def tokenizer_digests(tokenizers_dir: Path) -> tuple[FrozenEncoders, dict[str, str]]:
    """The frozen encoders and the digest of each group's tokenizer file."""
    models, info = load_tokenizers(tokenizers_dir)
    return FrozenEncoders(models), {g: info.tokenizers[streams[0].name] for g, streams in GROUPS.items()}


def streams_of(variants: Iterable[str]) -> tuple[str, ...]:
    """The streams any of ``variants`` reads, in stream order (face only when a variant needs it)."""
    wanted = {s for v in variants for s in variant_streams(v)}
    return tuple(s for s in STREAM_ORDER if s in wanted)


def trim_summary(examples: Iterable[Example]) -> dict[str, float]:
    windows = [e.window for e in examples]
    frames = sum(w.frames for w in windows)
    return {"clips": float(len(windows)),
            "trimmed_share": 1.0 - sum(w.kept for w in windows) / frames if frames else 0.0,
            "mean_kept_frames": float(np.mean([w.kept for w in windows])) if windows else 0.0,
            "clips_without_active_frames": float(sum(w.active_frames == 0 for w in windows))}


# ------------------------------------------------------------------------------------------ train
def _train_variant(cfg: SLRConfig, train_cfg: SLRTrainConfig, classes: ClassTable, width: int,
                   digests: dict[str, str], train: list[Example], dev: list[Example], version: str, out_dir: Path,
                   corpus: str, progress: bool, variant: str,
                   on_epoch: Callable[[dict[str, float], int], None] | None) -> dict[str, float]:
    """Train one probe variant into ``out_dir/<variant>.pt`` (here or in a worker process), with its dev
    confusion plot; its numbers for metrics.json."""
    meta = ProbeMeta(variant, classes.labels, classes.names, digests)
    dims = ProbeDims(width, len(classes.labels), variant_streams(variant))
    # best and last live in the cache under the run key (a killed run continues where it stopped; a finished
    # one is not redone); <variant>.pt only ever holds the best of a finished run
    key = run_key(cfg, train_cfg, dims, meta, version)
    cache = Path(train_cfg.cache_dir)
    best, last = cache / f"{variant}-{key}.best.pt", cache / f"{variant}-{key}.last.pt"
    result = train_slr(cfg, train_cfg, meta, width, train, dev, version, best, last, on_epoch, progress)
    copy_file(best, out_dir / f"{variant}.pt")
    numbers = {f"{variant}/best_epoch": float(result.best.get("epoch", 0)),
               **{f"{variant}/best_{k}": v for k, v in result.best.items() if k.startswith(("val_", "train_"))}}
    if dev:
        loaded = load_slr(best, choose_device(train_cfg.device))
        logits = predict_logits(loaded.model, dev, train_cfg.batch_size)
        plot_confusion(np.array([e.target for e in dev]), logits.argmax(-1).numpy(), classes.names,
                       out_dir / f"confusion_dev_{variant}.png", f"{corpus} dev, probe {variant}")
    return numbers


def run_train_slr(cfg: SLRConfig, train_cfg: SLRTrainConfig, body: BodyModel | None, data: DataConfig,
                  corpus: str | None = None, on_epoch: Callable[[str, dict[str, float], int], None] | None = None,
                  progress: bool = True) -> dict[str, float]:
    """Train every probe variant on ``corpus`` (default ``cfg.corpus``); ``on_epoch(variant, record, epoch)``.
    ``body`` may be None only with trimming off."""
    corpus = corpus or cfg.corpus
    meta_splits = corpus_metadata(data, corpus)
    if not meta_splits["train"]:
        raise ValueError(f"corpus {corpus!r}: no labelled clip in the train split of {data.shards_dir(corpus)}")
    classes = class_table(c for split in SPLITS for c in meta_splits[split])
    device = choose_device(train_cfg.device)
    encoders, digests = tokenizer_digests(data.tokenizers_dir)
    encoders.to(device)
    trimmer = Trimmer(body, cfg.trim)
    streams = streams_of(train_cfg.variants)
    dtype = torch.float16 if train_cfg.feature_dtype == "float16" else torch.float32
    skipped: list[dict] = []
    examples = {split: build_examples(labelled_motion(data, corpus, split), classes.index, trimmer, encoders, streams,
                                      cfg.max_steps, dtype, train_cfg.bad_clips, skipped)
                for split in ("train", "dev")}
    version = data_version([data.shards_dir(corpus) / f"{s}.parquet" for s in ("train", "dev")]
                           + [data.tokenizers_dir / f"{g}.pt" for g in GROUPS])
    out_dir = data.slr_dir
    trim = trim_summary(examples["train"] + examples["dev"])
    report: dict[str, float] = {"classes": float(len(classes.labels)), "train_clips": float(len(examples["train"])),
                                "dev_clips": float(len(examples["dev"])), "skipped": float(len(skipped)),
                                "encoder_width": float(encoders.width), "trimmed_share": trim["trimmed_share"],
                                "mean_kept_frames": trim["mean_kept_frames"],
                                "clips_without_active_frames": trim["clips_without_active_frames"]}
    processes, threads = worker_split(train_cfg.workers, len(train_cfg.variants), train_cfg.device)
    run = partial(_train_variant, cfg, train_cfg, classes, encoders.width, digests, examples["train"], examples["dev"],
                  version, out_dir, corpus, progress)
    for numbers in run_jobs(run, list(train_cfg.variants), list(train_cfg.variants), processes, threads, on_epoch,
                            "probe variant", "slr_train.workers"):
        report.update(numbers)
    write_json(out_dir / "metrics.json", report)
    write_jsonl(out_dir / "skipped.jsonl", skipped)
    return report


def train_and_log(cfg: SLRConfig, train_cfg: SLRTrainConfig, body_cfg: BodyConfig, data: DataConfig,
                  experiment: ExperimentConfig, corpus: str | None = None, progress: bool = True) -> dict[str, float]:
    body = load_body_model(body_cfg) if cfg.trim.enabled else None
    corpus = corpus or cfg.corpus
    tags = {"corpus": corpus, "variants": ",".join(train_cfg.variants), "body_model": body_cfg.model,
            "seed": str(train_cfg.seed)}
    with start_run(experiment, "train-slr", tags=tags, variant=corpus) as run:
        run.log_params(section_params(slr=cfg, slr_train=train_cfg, data=data))
        report = run_train_slr(cfg, train_cfg, body, data, corpus, progress=progress,
                               on_epoch=lambda v, record, epoch: run.log_metrics(
                                   {f"{v}/{k}": x for k, x in record.items()}, step=epoch))
        run.log_metrics(report)
        out_dir = data.slr_dir
        for path in [out_dir / "metrics.json", out_dir / "skipped.jsonl", *sorted(out_dir.glob("confusion_dev_*.png"))]:
            run.log_artifact(path)
    return report


# --------------------------------------------------------------------------------------- evaluate
@dataclass(frozen=True)
class SLREvaluation:
    corpus: str
    evaluations: dict[str, Evaluation]  # variant -> scores
    summary: dict[str, float]  # flat numbers: "<variant>/<subset>/<metric>", clips, trimmed share
    train_configs: dict[str, dict]  # variant -> the checkpoint's training settings


def load_probes(data: DataConfig, variants: Iterable[str], device: torch.device) -> dict[str, LoadedSLR]:
    probes = {v: load_slr(data.slr_dir / f"{v}.pt", device) for v in variants}
    first = next(iter(probes.values()))
    for v, p in probes.items():
        if p.meta.classes != first.meta.classes or p.model.cfg.trim != first.model.cfg.trim:
            raise ValueError(f"probe checkpoints {list(probes)} disagree on classes or trimming; rerun train-slr")
        if p.meta.variant != v:
            raise ValueError(f"{Path(data.models_dir) / 'slr' / f'{v}.pt'} holds variant {p.meta.variant!r}, not {v!r}")
    return probes


def prediction_rows(variant: str, examples: list[Example], logits: torch.Tensor, classes: ClassTable,
                    pairs: dict[str, tuple[int, ...]] | None = None) -> list[dict]:
    """One row per clip; ``correct_pair`` (confusing clips of a two-class pair in ``pairs``, else empty): the
    target's logit beats its pair partner's, the per-clip hit of ``pair_top1``."""
    targets = torch.tensor([e.target for e in examples], dtype=torch.long)
    top5 = logits.topk(min(5, logits.shape[1]), dim=-1).indices  # (n, 5)
    hit1, hit5 = topk_hits(logits, targets, 1), topk_hits(logits, targets, 5)
    rows = []
    for i, e in enumerate(examples):
        pred = int(top5[i, 0])
        hit = (pair_hits(logits[i: i + 1], targets[i: i + 1], [clip_pair(e.clip)], pairs or {})
               if clip_subset(e.clip) == "confusing" else [])  # empty unless a two-class pair holds the target
        pair_hit = int(hit[0]) if len(hit) else ""
        rows.append({"variant": variant, "clip_id": e.clip.id, "label": e.clip.label, "gloss": classes.names[e.target],
                     "subset": clip_subset(e.clip), "pair": clip_pair(e.clip) or "",
                     "predicted_label": classes.labels[pred], "predicted_gloss": classes.names[pred],
                     "top5_labels": " ".join(str(classes.labels[int(j)]) for j in top5[i]),
                     "correct_top1": int(hit1[i]), "correct_top5": int(hit5[i]), "correct_pair": pair_hit,
                     "frames": e.window.frames, "kept_start": e.window.start, "kept_end": e.window.end})
    return rows


def run_evaluate_slr(eval_cfg: SLREvaluateConfig, body: BodyModel | None, data: DataConfig,
                     corpus: str | None = None) -> SLREvaluation:
    """Score the probes of ``eval_cfg.variants`` on ``eval_cfg.split`` of ``corpus`` (default: the corpus the
    probes were trained on); trimming as in training (from the checkpoint)."""
    device = choose_device(eval_cfg.device)
    probes = load_probes(data, eval_cfg.variants, device)
    first = next(iter(probes.values()))
    trained_on = first.model.cfg.corpus
    corpus = corpus or trained_on
    if corpus != trained_on:
        raise ValueError(f"the probes were trained on corpus {trained_on!r}, not {corpus!r}; rerun train-slr with "
                         f"slr.corpus: {corpus}")
    encoders, digests = tokenizer_digests(data.tokenizers_dir)
    if digests != first.meta.tokenizers:
        raise ValueError(f"the tokenizers in {data.tokenizers_dir} are not those the probes were trained on "
                         "(digests differ); rerun train-slr")
    encoders.to(device)
    classes = ClassTable(first.meta.classes, first.meta.class_names)
    meta_splits = corpus_metadata(data, corpus)
    clips = labelled(read_split(data.shards_dir(corpus), eval_cfg.split, modalities=[]))  # metadata: the checks
    if not clips:
        raise ValueError(f"corpus {corpus!r}: no labelled clip in the {eval_cfg.split} split of "
                         f"{data.shards_dir(corpus)}")
    unknown = sorted({c.clip.label for c in clips} - set(classes.labels))
    if unknown:
        raise ValueError(f"{eval_cfg.split} clips of corpus {corpus!r} have labels {unknown[:10]} the probes were not "
                         "trained with; rerun train-slr")
    skipped: list[dict] = []
    trimmer = Trimmer(body, first.model.cfg.trim)
    motion = labelled_motion(data, corpus, eval_cfg.split)
    examples, logits_of = [], {variant: [] for variant in probes}
    # a batch of clips is encoded, scored by every probe and let go: memory for one batch, whatever the split
    for batch in example_batches(iter_examples(motion, classes.index, trimmer, encoders, streams_of(probes),
                                               first.model.cfg.max_steps, bad_clips=eval_cfg.bad_clips,
                                               skipped=skipped), eval_cfg.batch_size):
        for variant, probe in probes.items():
            logits_of[variant].append(predict_logits(probe.model, batch, eval_cfg.batch_size))
        examples += [without_features(e) for e in batch]
    if not examples:
        raise ValueError(f"every {eval_cfg.split} clip of corpus {corpus!r} was skipped (see skipped.jsonl)")
    pairs = pair_classes((c for split in SPLITS for c in meta_splits[split]), classes.index)
    targets = torch.tensor([e.target for e in examples], dtype=torch.long)
    out = data.metrics("slr")
    evaluations, rows = {}, []
    for variant in probes:
        logits = torch.cat(logits_of[variant])
        evaluations[variant] = evaluate_logits(logits, targets, [e.clip for e in examples], pairs, eval_cfg.bootstrap,
                                               eval_cfg.confidence, eval_cfg.seed, f"NMFs-CSL: {SUBSET_HINT}")
        rows += prediction_rows(variant, examples, logits, classes, pairs)
        plot_confusion(targets.numpy(), logits.argmax(-1).numpy(), classes.names, out / f"confusion_{variant}.png",
                       f"{corpus} {eval_cfg.split}, probe {variant}")
    trim = trim_summary(examples)
    summary = {"clips": float(len(examples)), "skipped": float(len(skipped)), "classes": float(len(classes.labels)),
               "trimmed_share": trim["trimmed_share"],
               **{f"{v}/{subset}/{k}": x for v, ev in evaluations.items() for subset, s in ev.scores.items()
                  for k, x in s.to_dict().items()}}
    write_json(out / "metrics.json", {"corpus": corpus, "split": eval_cfg.split, "clips": len(examples),
                                      "skipped": len(skipped), "classes": len(classes.labels), "trim": trim,
                                      "variants": {v: ev.to_dict() for v, ev in evaluations.items()}})
    write_text(out / "table.csv", table_csv(evaluations))
    write_text(out / "table.md", table_markdown(evaluations, corpus, eval_cfg.split, eval_cfg.confidence))
    write_text(out / "predictions.csv", csv_text(rows, list(rows[0])))
    write_jsonl(out / "skipped.jsonl", skipped)
    return SLREvaluation(corpus, evaluations, summary, {v: p.train_config for v, p in probes.items()})


def evaluate_and_log(eval_cfg: SLREvaluateConfig, body_cfg: BodyConfig, data: DataConfig,
                     experiment: ExperimentConfig, corpus: str | None = None) -> dict[str, float]:
    body = load_body_model(body_cfg)
    result = run_evaluate_slr(eval_cfg, body, data, corpus)
    out = data.metrics("slr")
    reasons = {ev.subsets_reason for ev in result.evaluations.values() if ev.subsets_reason}
    tags = {"split": eval_cfg.split, "corpus": result.corpus, "subsets_reason": " ".join(sorted(reasons)),
            "body_model": body_cfg.model}
    with start_run(experiment, "evaluate-slr", tags=tags, variant=result.corpus) as run:
        run.log_params(section_params(slr_evaluate=eval_cfg))
        run.log_params({f"{v}.slr_train.{k}": x for v, cfg in result.train_configs.items() for k, x in cfg.items()})
        run.log_metrics({k: v for k, v in result.summary.items() if v == v and abs(v) != float("inf")})
        run.log_table(out / "table.csv", "slr_table.json")
        for name in ("metrics.json", "table.md", "predictions.csv", "skipped.jsonl"):
            run.log_artifact(out / name)
        for png in sorted(out.glob("confusion_*.png")):
            run.log_artifact(png, "confusion")
    return result.summary
