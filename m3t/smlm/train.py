"""Training the SMLM (M3T Sec. 3.3, App. 0.D.2): AdamW, cosine 2e-4 -> 1e-6, cross-entropy on both tasks,
alternated per batch (translation with probability ``translation_prob``; ``translation_objective: false``
trains production only, the ablation of Tab. 1; ``translation_steps: added`` adds the translation steps to the
production ones instead of taking them from the epoch, the same ablation at equal production updates), the checkpoint with the lowest mean validation DTW-JPE
kept as ``best``, and a resumable ``last`` written at most every 30 s and at the end: a run killed part-way and started
again with the same config, vocabulary and data continues the same loss curve (:func:`run_key` names it).

GPU paths: device from :func:`m3t.runtime.choose_device`, optional bf16 autocast, data-parallel training
when launched by ``torchrun`` (each rank a disjoint share of every epoch's batches, gradients all-reduced
every step; the task of a step is drawn from a generator seeded identically on all ranks so they stay in
lockstep); rank 0 evaluates and saves.

Axis legend: B batch, U motion steps, S streams, K text tokens.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from m3t.checkpoints import run_digest
from m3t.optimizer import adam, optimizer_step, warmup_cosine
from m3t.runtime import DistributedContext, autocast
from m3t.smlm.checkpoint import load_smlm, save_smlm
from m3t.smlm.config import SMLMConfig, SMLMTrainConfig
from m3t.smlm.data import (
    IGNORE,
    Example,
    ProductionBatch,
    TranslationBatch,
    production_batch,
    translation_batch,
)
from m3t.smlm.model import SignMotionLM, SMLMDims
from m3t.smlm.vocab import MOTION_STREAMS, SignVocabulary
from m3t.training import (
    EpochTail,
    Selection,
    TrainRun,
    run_epochs,
    scalar_settings,
    start_training,
)

TRAIN_VERSION = "smlm-v1"  # part of the resume key: bump when a change makes older training state invalid


def production_loss(logits: dict[str, torch.Tensor], targets: torch.Tensor, smoothing: float = 0.0) -> torch.Tensor:
    """Mean over the four motion heads of the token cross-entropy. targets (B, U, S), IGNORE on padding."""
    losses = [F.cross_entropy(logits[s].flatten(0, 1).float(), targets[..., k].flatten(), ignore_index=IGNORE,
                              label_smoothing=smoothing) for k, s in enumerate(MOTION_STREAMS)]
    return torch.stack(losses).mean()


def translation_loss(logits: torch.Tensor, targets: torch.Tensor, smoothing: float = 0.0) -> torch.Tensor:
    """Token cross-entropy of the text head. logits (B, K, T), targets (B, K)."""
    return F.cross_entropy(logits.flatten(0, 1).float(), targets.flatten(), ignore_index=IGNORE,
                           label_smoothing=smoothing)


def task_loss(model: SignMotionLM, batch: ProductionBatch | TranslationBatch, smoothing: float = 0.0) -> torch.Tensor:
    if isinstance(batch, ProductionBatch):
        logits = model.production(batch.text_ids, batch.text_mask, batch.motion_in, batch.motion_mask)
        return production_loss(logits, batch.targets, smoothing)
    logits = model.translation(batch.motion_ids, batch.motion_mask, batch.text_in, batch.text_mask)
    return translation_loss(logits, batch.targets, smoothing)


def _to(batch, device: torch.device):
    return type(batch)(*(getattr(batch, f).to(device) for f in batch.__dataclass_fields__))


def train_step(model: SignMotionLM, batch: ProductionBatch | TranslationBatch, optim: torch.optim.Optimizer,
               scheduler: torch.optim.lr_scheduler.LRScheduler, precision: str = "fp32", grad_clip: float = 0.0,
               smoothing: float = 0.0) -> dict[str, float]:
    device = next(model.parameters()).device
    with autocast(device, precision):
        loss = task_loss(model, _to(batch, device), smoothing)
    # gradients averaged across ranks by the step rather than by a DDP wrapper: the two tasks use different
    # heads, and the task methods are not the module's forward() that DDP hooks
    optimizer_step(loss, model, optim, scheduler, grad_clip, average_grads=True)
    task = "production" if isinstance(batch, ProductionBatch) else "translation"
    return {f"{task}_loss": loss.item()}


def epoch_batches(examples: Sequence[Example], vocab: SignVocabulary, cfg: SMLMTrainConfig, epoch: int,
                  rank: int = 0, world_size: int = 1):
    """This rank's batches of one epoch, shuffled by (seed, epoch). ``translation_steps`` shared: each chunk of
    examples is one step, a translation batch with probability ``translation_prob``; added: each chunk is a
    production step, followed by a translation step on the same chunk with probability p / (1 - p). The tasks are
    drawn from a generator seeded alike on every rank, so the ranks stay in lockstep."""
    order = np.random.default_rng([cfg.seed, epoch]).permutation(len(examples))
    tasks = np.random.default_rng([cfg.seed, epoch, 1])
    chunks = [order[i: i + cfg.batch_size] for i in range(0, len(order), cfg.batch_size)]
    added = cfg.translation_steps == "added"
    p = cfg.translation_prob / (1.0 - cfg.translation_prob) if added else cfg.translation_prob  # added: p <= 0.5
    for step in range(steps_per_epoch(len(examples), cfg.batch_size, world_size)):
        translate = cfg.translation_objective and tasks.random() < p  # same on every rank
        batch = [examples[j] for j in chunks[step * world_size + rank]]
        if added:
            yield production_batch(batch, vocab)
            if translate:
                yield translation_batch(batch, vocab)
        else:
            yield translation_batch(batch, vocab) if translate else production_batch(batch, vocab)


def optimizer_steps_per_epoch(n_examples: int, cfg: SMLMTrainConfig, world_size: int = 1) -> int:
    """Optimiser steps of an epoch on one rank (expected, with added translation steps): the LR schedule's unit."""
    chunks = steps_per_epoch(n_examples, cfg.batch_size, world_size)
    if cfg.translation_objective and cfg.translation_steps == "added":
        return round(chunks / (1.0 - cfg.translation_prob))
    return chunks


def steps_per_epoch(n_examples: int, batch_size: int, world_size: int = 1) -> int:
    chunks = -(-n_examples // batch_size)
    return chunks // world_size if world_size > 1 else chunks


def run_key(model_cfg: SMLMConfig, cfg: SMLMTrainConfig, vocab: SignVocabulary, data_version: str) -> str:
    """What a resumable ``last`` must agree on to be continued: the code's training version, the model and
    training settings (not where files go nor the device), the vocabulary and the data."""
    settings = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("cache_dir", "device")}
    return run_digest(TRAIN_VERSION, dataclasses.asdict(model_cfg), settings, vocab.to_dict(), data_version)


def train_smlm(
    model_cfg: SMLMConfig,
    cfg: SMLMTrainConfig,
    vocab: SignVocabulary,
    train: Sequence[Example],
    evaluate: Callable[[SignMotionLM], dict[str, float]] | None,
    data_version: str,
    best_path: str | Path,
    on_epoch: Callable[[dict[str, float], int], None] | None = None,
    dist_ctx: DistributedContext | None = None,
    progress: bool = True,
    last_path: str | Path | None = None,
    stop_after_epochs: int | None = None,
) -> TrainRun:
    """Train the SMLM; ``evaluate(model)`` returns validation metrics incl. ``dtw_jpe_mean_m`` (selection).

    ``last_path``: the resumable checkpoint, written at most every 30 s and at the end, and continued from when
    it exists
    (name it by :func:`run_key` so that a different run never continues it); ``stop_after_epochs``: train
    at most that many more epochs (a deliberate interruption, for tests and time-boxed jobs)."""
    if not train:
        raise ValueError("no training examples: the token shards have no usable clip (see the skipped list)")
    dist_ctx = dist_ctx or DistributedContext()
    device = start_training(cfg.device, cfg.seed, dist_ctx)
    model = SignMotionLM(model_cfg, SMLMDims.from_vocabulary(vocab)).to(device)
    if dist_ctx.world_size > 1:  # identical start on every rank
        for p in model.parameters():
            torch.distributed.broadcast(p.data, 0)
    per_epoch = steps_per_epoch(len(train), cfg.batch_size, dist_ctx.world_size)
    if per_epoch == 0:
        raise ValueError(f"{len(train)} examples make no full batch for {dist_ctx.world_size} ranks; lower batch_size")
    optim = adam(model.parameters(), device, decoupled=True, lr=cfg.lr, weight_decay=cfg.weight_decay)
    scheduler = warmup_cosine(optim, cfg.epochs, optimizer_steps_per_epoch(len(train), cfg, dist_ctx.world_size),
                              cfg.warmup_steps, "steps", cfg.min_lr)
    settings = scalar_settings(cfg)
    tail = EpochTail(
        cfg.epochs, cfg.eval_every,
        # without an evaluator the last epoch is kept
        Selection("epoch", "max") if evaluate is None else Selection("val_dtw_jpe_mean_m"), optim, scheduler,
        save=lambda path, epoch, step, record, state: save_smlm(path, model, vocab, epoch, step, data_version,
                                                                record, settings, state),
        best_path=best_path, last_path=last_path, evaluate=None if evaluate is None else lambda: evaluate(model),
        is_main=dist_ctx.is_main, on_epoch=on_epoch)
    resumed_from_epoch = tail.resume_saved(model, lambda p: load_smlm(p, device), "the SMLM")
    # the mean per key: the two tasks' losses come from different numbers of steps
    run_epochs(tail, model, lambda epoch: epoch_batches(train, vocab, cfg, epoch, dist_ctx.rank, dist_ctx.world_size),
               lambda batch: train_step(model, batch, optim, scheduler, cfg.precision, cfg.grad_clip,
                                        cfg.label_smoothing),
               "smlm", progress, stop_after_epochs)
    return tail.result(model, resumed_from_epoch)
