"""The train-tokenizers run: fitted shards of ``data.train_corpora`` -> one FSQ-VAE (or VQ-VAE baseline) per
modality group -> checkpoints, codebook statistics, token histograms and reconstruction videos (MP4), logged to
MLflow.

For each group of ``tokenizer_train.groups`` (``body``, ``hand``, ``face``): train on the train splits of all
training corpora (+ face-only shards for ``face``), select by validation vertex error on their dev splits
(``val_max_frames`` of them, in corpus order; 0 = all), then tokenise with the selected checkpoint to measure
codebook utilisation / token-count SD / the token histogram on the test splits of all training corpora, as
M3T reports them (Tab. 3, Tab. A.2, Fig. A.3 "across all test sets"; the same over train + dev + test under
``all_splits_*``), and test-split VPE / PA-VPE (the Tab. 3 columns). Writes ``<models>/tokenizers/<group>.pt``,
``metrics.json``, ``plots/`` and ``rejected.jsonl`` (clips that could not be used, with reasons).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache, partial
from pathlib import Path
from typing import Callable

import numpy as np

from m3t.atomic import copy_file, write_json, write_jsonl
from m3t.body.factory import BodyConfig
from m3t.body.protocol import BodyModel
from m3t.corpora.splits import SPLITS
from m3t.experiment import ExperimentConfig, section_params
from m3t.metrics.codebook import codebook_stats, plot_token_histogram, token_counts
from m3t.runtime import DistributedContext
from m3t.shards.folders import DataConfig
from m3t.shards.io import data_version, read_shard, read_split
from m3t.shards.schema import FittedClip
from m3t.tokenizers.checkpoint import load_tokenizer
from m3t.tokenizers.config import TokenizerConfig, TokenizerTrainConfig, VAEConfig
from m3t.tokenizers.data import (
    GROUPS,
    check_layout,
    clip_sequences,
    from_canonical,
    to_canonical,
)
from m3t.tokenizers.evaluate import ReconstructionProbe, encode_clip, reconstruct_clip
from m3t.tokenizers.train import train_tokenizer
from m3t.tokenizers.vae import MotionTokenizer
from m3t.training_jobs import run_jobs, worker_split


def usable_sequences(group: str, clips: list[FittedClip], rejected: list[dict]) -> list[np.ndarray]:
    """Training sequences of ``clips``; a clip that cannot be used is recorded in ``rejected``, not raised."""
    out = []
    for clip in clips:
        try:
            out.extend(clip_sequences(clip.params, group, clip.clip.id))
        except (ValueError, KeyError) as exc:
            rejected.append({"clip_id": clip.clip.id, "group": group, "reason": f"{type(exc).__name__}: {exc}"})
    return out


def face_only_clips(paths: tuple[str, ...]) -> list[FittedClip]:
    clips = []
    for path in paths:
        clips.extend(read_shard(path, ["face"]).clips)
    return clips


def codebook_report(model: MotionTokenizer, group: str, splits: dict[str, list[FittedClip]]
                    ) -> tuple[dict[str, float], np.ndarray]:
    """Codebook statistics of the test split(s) (``utilisation_pct``, ``count_sd``, ``perplexity``, ``tokens``)
    and of every split (the same names prefixed ``all_splits_``), with the test token counts (K,). Without a
    test clip the test statistics are NaN (``tokens`` 0): nothing to measure, rather than a 0 % utilisation."""
    counts = {split: token_counts([encode_clip(model, to_canonical(np.asarray(c.params[s.modality]), s))
                                   for c in clips for s in GROUPS[group]], model.codebook_size)
              for split, clips in splits.items()}
    test = counts.get("test", np.zeros(model.codebook_size, dtype=np.int64))
    stats = codebook_stats(test)
    if not test.sum():
        stats = {k: (0.0 if k.startswith("tokens") else float("nan")) for k in stats}
    every = codebook_stats(np.sum(list(counts.values()), axis=0) if counts else test)
    return {**stats, **{f"all_splits_{k}": v for k, v in every.items()}}, test


def group_report(group: str, checkpoint: Path, splits: dict[str, list[FittedClip]], body: BodyModel,
                 plots_dir: Path, max_test_frames: int) -> dict[str, float]:
    """Codebook statistics (test splits; all splits under ``all_splits_*``) and test-split vertex errors of
    the selected checkpoint (``max_test_frames`` of them, 0 = all)."""
    from m3t.render.reconstruction import render_reconstruction

    model = load_tokenizer(checkpoint).model
    stats, counts = codebook_report(model, group, splits)
    plot_token_histogram(counts, f"{group} ({model.cfg.quantizer}, {model.codebook_size} codes), test",
                         plots_dir / f"tokens_{group}.png")
    # the counts themselves, for the dashboard's interactive histograms (FSQ vs VQ)
    write_json(plots_dir / f"tokens_{group}.json", {"group": group, "quantizer": model.cfg.quantizer,
                                                    "codebook_size": model.codebook_size, "counts": counts.tolist()})
    test = ReconstructionProbe(body, group, splits["test"], max_frames=max_test_frames).measure(model)
    report = {**stats, **{f"test_{k}": v for k, v in test.items()}, "codebook_size": float(model.codebook_size)}
    if splits["test"]:
        clip = splits["test"][0]
        recon = {s.modality: from_canonical(reconstruct_clip(model, to_canonical(np.asarray(clip.params[s.modality]), s)),
                                            s).numpy() for s in GROUPS[group]}
        render_reconstruction(body, clip, recon, plots_dir / f"reconstruction_{group}.mp4",
                              title=f"{clip.clip.id}: {group} tokens ({model.cfg.quantizer})")
    return report


@dataclass
class _GroupJob:
    """One group's training and report: what a worker process needs besides the body model."""

    group: str
    model_cfg: VAEConfig
    sequences: list[np.ndarray]
    usable: dict[str, list[FittedClip]]  # the splits without the clips rejected so far
    version: str
    out_dir: Path


def _train_group(job: _GroupJob, cfg: TokenizerTrainConfig, body: BodyModel,
                 on_epoch: Callable[[dict[str, float], int], None] | None, stop_after_epochs: int | None,
                 dist_ctx: DistributedContext, progress: bool) -> dict[str, float] | None:
    """Train one group and, on rank 0, copy its selected checkpoint out and return its report (``group_report``
    + the selected epoch's validation figures); other ranks return None."""
    dev = job.usable["dev"]
    probe = ReconstructionProbe(body, job.group, dev or job.usable["train"], cfg.val_max_frames) \
        if dist_ctx.is_main else None
    result = train_tokenizer(job.group, job.model_cfg, cfg, job.sequences, probe, job.version, on_epoch,
                             stop_after_epochs, dist_ctx, progress)
    if not dist_ctx.is_main:
        return None
    checkpoint = copy_file(result.best_path, job.out_dir / f"{job.group}.pt")
    report = {**group_report(job.group, checkpoint, job.usable, body, job.out_dir / "plots", cfg.val_max_frames),
              "best_epoch": float(result.best.get("epoch", 0)),
              **{f"best_{k}": v for k, v in result.best.items() if k.startswith("val_")}}
    return report


@lru_cache(maxsize=1)
def _worker_body(body_cfg: BodyConfig) -> BodyModel:
    """A worker process's body model, loaded once for all the groups it trains."""
    from m3t.body.factory import load_body_model

    return load_body_model(body_cfg)


def _group_in_worker(cfg: TokenizerTrainConfig, body_cfg: BodyConfig, stop_after_epochs: int | None, progress: bool,
                     job: _GroupJob, on_epoch: Callable[[dict[str, float], int], None] | None) -> dict[str, float] | None:
    """One group in a worker process of ``tokenizer_train.group_workers``, with the worker's body model."""
    return _train_group(job, cfg, _worker_body(body_cfg), on_epoch, stop_after_epochs, DistributedContext(), progress)


def group_workers(cfg: TokenizerTrainConfig, dist_ctx: DistributedContext) -> tuple[int, int]:
    """(worker processes, threads each) for the group runs (:func:`m3t.training_jobs.worker_split`)."""
    return worker_split(cfg.group_workers, len(cfg.groups), cfg.device, dist_ctx.world_size)


def run_train_tokenizers(
    tok_cfg: TokenizerConfig,
    cfg: TokenizerTrainConfig,
    body: BodyModel | None,
    data: DataConfig,
    on_epoch: Callable[[str, dict[str, float], int], None] | None = None,
    stop_after_epochs: int | None = None,
    dist_ctx: DistributedContext | None = None,
    progress: bool = True,
    body_cfg: BodyConfig | None = None,
) -> dict[str, dict[str, float]]:
    """Train every configured group; returns (and, on rank 0, writes) ``metrics.json``'s content.

    With ``tokenizer_train.group_workers`` > 1 (CPU, no DDP) the groups train in that many processes at once,
    each loading the body model of ``body_cfg`` and running on its share of this process's threads (``body`` is
    then unused and may be None). A group's
    results are those of one process training it on that many threads, whatever runs beside it; they differ in
    float order from a run on all the threads.
    """
    dist_ctx = dist_ctx or DistributedContext()
    splits = {split: read_split(data.shards_dirs, split) for split in SPLITS}
    if not splits["train"]:
        raise ValueError(f"the train shards of {', '.join(data.train_corpora)} hold no clips; the tokenizers "
                         "need training data")
    layout = read_shard(data.shards_dirs[0] / "train.parquet", []).layout
    version = data_version([d / f"{s}.parquet" for d in data.shards_dirs for s in ("train", "dev")]
                           + list(map(Path, cfg.extra_face_shards)))
    out_dir = data.tokenizers_dir
    rejected: list[dict] = []
    jobs = []
    for group in cfg.groups:  # a group's report leaves out the clips this group and the ones before it rejected
        input_dim = check_layout(layout, group)
        train_clips = splits["train"] + (face_only_clips(cfg.extra_face_shards) if group == "face" else [])
        sequences = usable_sequences(group, train_clips, rejected)
        rejected_ids = {r["clip_id"] for r in rejected}
        usable = {s: [c for c in clips if c.clip.id not in rejected_ids] for s, clips in splits.items()}
        jobs.append(_GroupJob(group, tok_cfg.vae_config(group, input_dim), sequences, usable, version, out_dir))
    workers, threads = group_workers(cfg, dist_ctx)
    if workers > 1:
        if body_cfg is None:
            raise ValueError("tokenizer_train.group_workers > 1 needs the body config (body_cfg) for its worker "
                             "processes to load the body model; pass it, or set group_workers: 1")
        run = partial(_group_in_worker, cfg, body_cfg, stop_after_epochs, progress)
    else:
        if body is None:
            raise ValueError("the tokenizers train in this process (group_workers 1, a GPU or DDP): pass the body "
                             "model")
        run = lambda job, on_group_epoch: _train_group(
            job, cfg, body, on_group_epoch, stop_after_epochs, dist_ctx, progress)
    results = run_jobs(run, jobs, [job.group for job in jobs], workers, threads, on_epoch, "tokenizer group",
                       "tokenizer_train.group_workers")
    # other DDP ranks get None
    report = {job.group: result for job, result in zip(jobs, results) if result is not None}
    if dist_ctx.is_main:
        write_json(out_dir / "metrics.json", report)
        write_jsonl(out_dir / "rejected.jsonl", rejected)
    return report


def train_and_log(tok_cfg: TokenizerConfig, cfg: TokenizerTrainConfig, body_cfg: BodyConfig, data: DataConfig,
                  experiment: ExperimentConfig, progress: bool = True) -> dict[str, dict[str, float]]:
    """Train the tokenizers (rank 0 logs params, per-epoch curves, final metrics and plots to MLflow)."""
    from m3t.body.factory import load_body_model
    from m3t.experiment import start_run
    from m3t.runtime import distributed_context

    dist_ctx = distributed_context(cfg.device)
    # worker processes load their own body model: this one needs it only to train here
    body = load_body_model(body_cfg) if group_workers(cfg, dist_ctx)[0] == 1 else None
    if not dist_ctx.is_main:
        return run_train_tokenizers(tok_cfg, cfg, body, data, dist_ctx=dist_ctx, progress=False, body_cfg=body_cfg)
    tags = {"quantizer": tok_cfg.quantizer, "width": str(tok_cfg.width), "batch_size": str(cfg.batch_size),
            "body_model": body_cfg.model, "corpus": ",".join(data.train_corpora), "seed": str(cfg.seed)}
    variant = f"{tok_cfg.quantizer.upper()} width {tok_cfg.width} batch {cfg.batch_size}"
    with start_run(experiment, "train-tokenizers", tags=tags, variant=variant) as run:
        run.log_params(section_params(body=body_cfg, tokenizer=tok_cfg, tokenizer_train=cfg, data=data))
        report = run_train_tokenizers(
            tok_cfg, cfg, body, data, dist_ctx=dist_ctx, progress=progress, body_cfg=body_cfg,
            on_epoch=lambda group, record, epoch: run.log_metrics({f"{group}/{k}": v for k, v in record.items()}, step=epoch))
        run.log_metrics({f"{group}/{k}": v for group, values in report.items() for k, v in values.items()})
        out_dir = data.tokenizers_dir
        run.log_artifact(out_dir / "metrics.json")
        run.log_artifact(out_dir / "rejected.jsonl")
        for plot in sorted((out_dir / "plots").glob("*")):
            run.log_artifact(plot, "plots")
    return report


def evaluate_and_log(cfg: TokenizerTrainConfig, body_cfg: BodyConfig, data: DataConfig,
                     experiment: ExperimentConfig) -> dict[str, dict[str, float]]:
    """Re-evaluate the current tokenizer checkpoints (``<tokenizers_dir>/<group>.pt``) without training: the
    codebook statistics and test-split vertex errors of :func:`group_report`, written to
    ``<metrics_dir>/tokenizers`` (the trained folder is a DVC output and stays untouched) and logged as an
    ``evaluate-tokenizers`` run. Groups without a checkpoint are left out; none at all is an error."""
    import json

    from m3t.body.factory import load_body_model
    from m3t.experiment import start_run

    present = [g for g in cfg.groups if (data.tokenizers_dir / f"{g}.pt").exists()]
    if not present:
        raise FileNotFoundError(f"no tokenizer checkpoint in {data.tokenizers_dir} (expected "
                                f"{', '.join(g + '.pt' for g in cfg.groups)}): run the train-tokenizers stage first")
    rejected_file = data.tokenizers_dir / "rejected.jsonl"
    rejected = {json.loads(line)["clip_id"] for line in rejected_file.read_text().splitlines() if line.strip()} \
        if rejected_file.exists() else set()
    splits = {split: [c for c in read_split(data.shards_dirs, split) if c.clip.id not in rejected] for split in SPLITS}
    body = load_body_model(body_cfg)
    out = data.metrics("tokenizers")
    report = {g: group_report(g, data.tokenizers_dir / f"{g}.pt", splits, body, out / "plots", cfg.val_max_frames)
              for g in present}
    write_json(out / "metrics.json", report)
    quantizer = load_tokenizer(data.tokenizers_dir / f"{present[0]}.pt").model.cfg.quantizer
    tags = {"quantizer": quantizer, "body_model": body_cfg.model, "corpus": ",".join(data.train_corpora)}
    with start_run(experiment, "evaluate-tokenizers", tags=tags, variant=quantizer.upper()) as run:
        run.log_metrics({f"{group}/{k}": v for group, values in report.items() for k, v in values.items()})
        run.log_artifact(out / "metrics.json")
        for plot in sorted((out / "plots").glob("*")):
            run.log_artifact(plot, "plots")
    return report
