"""Training the recognition probe (M3T App. 0.D.3): cross-entropy with label smoothing, Adam, cosine LR down to
``min_lr``, the checkpoint with the best validation Top-1 kept as ``best`` (the last epoch when there is no dev
clip), and a resumable ``last`` written at most every 30 s and at the end (:class:`m3t.training.EpochTail`): a run
killed part-way and started again with the same config and data continues the same loss curve (:func:`run_key`).

The encoders are not part of the model trained here: the probe reads cached features (:mod:`m3t.slr.features`),
so its optimiser holds the probe's parameters only.

Axis legend: B batch, N token steps, W width, C classes.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from m3t.checkpoints import run_digest
from m3t.optimizer import adam, optimizer_step, warmup_cosine
from m3t.runtime import autocast
from m3t.slr.checkpoint import ProbeMeta, load_slr, save_slr
from m3t.slr.config import SLRConfig, SLRTrainConfig
from m3t.slr.evaluate import topk_hits
from m3t.slr.features import Example, variant_streams
from m3t.slr.model import ProbeDims, SLRProbe
from m3t.training import (
    EpochTail,
    Selection,
    TrainRun,
    epoch_batches,
    run_epochs,
    scalar_settings,
    start_training,
)

TRAIN_VERSION = "slr-v1"  # part of the resume key: bump when a change makes older training state invalid


@dataclass(frozen=True)
class Batch:
    """features: stream -> (B, N, W) zero-padded; mask: (B, N) True on valid steps; targets: (B,) int64."""

    features: dict[str, torch.Tensor]
    mask: torch.Tensor
    targets: torch.Tensor


def collate(examples: Sequence[Example], streams: Sequence[str], device: torch.device | str = "cpu") -> Batch:
    steps = max(e.steps for e in examples)
    width = examples[0].features[streams[0]].shape[-1]
    features = {}
    for s in streams:
        x = torch.zeros(len(examples), steps, width)
        for i, e in enumerate(examples):
            x[i, : e.steps] = e.features[s].float()
        features[s] = x.to(device)
    mask = torch.zeros(len(examples), steps, dtype=torch.bool)
    for i, e in enumerate(examples):
        mask[i, : e.steps] = True
    targets = torch.tensor([e.target for e in examples], dtype=torch.long)
    return Batch(features, mask.to(device), targets.to(device))


def train_step(model: SLRProbe, batch: Batch, optim: torch.optim.Optimizer,
               scheduler: torch.optim.lr_scheduler.LRScheduler, precision: str = "fp32", grad_clip: float = 0.0,
               smoothing: float = 0.1) -> dict[str, float]:
    device = next(model.parameters()).device
    with autocast(device, precision):
        logits = model(batch.features, batch.mask)
    loss = F.cross_entropy(logits.float(), batch.targets, label_smoothing=smoothing)
    optimizer_step(loss, model, optim, scheduler, grad_clip)
    return {"loss": loss.item(), "top1": 100.0 * float((logits.argmax(-1) == batch.targets).float().mean())}


@torch.no_grad()
def predict_logits(model: SLRProbe, examples: Sequence[Example], batch_size: int = 64,
                   precision: str = "fp32") -> torch.Tensor:
    """(n, C) float32 logits of ``examples`` (on the CPU), in their order."""
    was_training = model.training
    model.eval()
    device = next(model.parameters()).device
    out = []
    for i in range(0, len(examples), batch_size):
        batch = collate(examples[i: i + batch_size], model.dims.streams, device)
        with autocast(device, precision):
            out.append(model(batch.features, batch.mask).float().cpu())
    model.train(was_training)
    return torch.cat(out) if out else torch.zeros(0, model.dims.num_classes)


def validation_metrics(model: SLRProbe, examples: Sequence[Example], batch_size: int, precision: str,
                       smoothing: float) -> dict[str, float]:
    """``top1`` / ``top5`` (%) and the smoothed cross-entropy ``loss`` on ``examples``."""
    logits = predict_logits(model, examples, batch_size, precision)
    targets = torch.tensor([e.target for e in examples], dtype=torch.long)
    return {"top1": 100.0 * float(topk_hits(logits, targets, 1).mean()),
            "top5": 100.0 * float(topk_hits(logits, targets, 5).mean()),
            "loss": float(F.cross_entropy(logits, targets, label_smoothing=smoothing))}


def run_key(cfg: SLRConfig, train_cfg: SLRTrainConfig, dims: ProbeDims, meta: ProbeMeta, data_version: str) -> str:
    """What a resumable ``last`` must agree on to be continued: the code's training version, the probe and
    training settings (not where files go nor the device), the classes, the tokenizers and the data."""
    settings = {k: v for k, v in dataclasses.asdict(train_cfg).items()
                if k not in ("cache_dir", "device", "variants", "workers")}
    return run_digest(TRAIN_VERSION, dataclasses.asdict(cfg), settings, dataclasses.asdict(dims),
                            dataclasses.asdict(meta), data_version)


def train_slr(cfg: SLRConfig, train_cfg: SLRTrainConfig, meta: ProbeMeta, width: int, train: Sequence[Example],
              dev: Sequence[Example], data_version: str, best_path: str | Path, last_path: str | Path | None = None,
              on_epoch: Callable[[dict[str, float], int], None] | None = None, progress: bool = True,
              stop_after_epochs: int | None = None) -> TrainRun:
    """Train one probe variant on ``train`` (features cached); select by Top-1 on ``dev`` (``val_top1``).

    ``last_path``: the resumable checkpoint, written at most every 30 s and at the end, and continued from when
    it exists
    (name it by :func:`run_key`); ``stop_after_epochs``: train at most that many more epochs."""
    if not train:
        raise ValueError(f"probe {meta.variant!r}: no training clips (every labelled train clip was skipped?)")
    device = start_training(train_cfg.device, train_cfg.seed)
    dims = ProbeDims(width, len(meta.classes), variant_streams(meta.variant))
    model = SLRProbe(cfg, dims).to(device)
    per_epoch = -(-len(train) // train_cfg.batch_size)
    optim = adam(model.parameters(), device, lr=train_cfg.lr, weight_decay=train_cfg.weight_decay)
    scheduler = warmup_cosine(optim, train_cfg.epochs, per_epoch, train_cfg.warmup_epochs, "epochs", train_cfg.min_lr)
    settings = scalar_settings(train_cfg)
    evaluate = None
    if dev:
        def evaluate() -> dict[str, float]:
            return validation_metrics(model, dev, train_cfg.batch_size, train_cfg.precision, train_cfg.label_smoothing)
    tail = EpochTail(
        train_cfg.epochs, train_cfg.eval_every,
        Selection("val_top1", "max") if dev else Selection("epoch", "max"),  # no dev clip: the last epoch
        optim, scheduler,
        save=lambda path, epoch, step, record, state: save_slr(path, model, meta, epoch, step, data_version, record,
                                                               settings, state),
        best_path=best_path, last_path=last_path, evaluate=evaluate, on_epoch=on_epoch)
    resumed_from_epoch = tail.resume_saved(model, lambda p: load_slr(p, device), f"the {meta.variant} probe")
    run_epochs(tail, model, lambda epoch: epoch_batches(train, train_cfg.batch_size, train_cfg.seed, epoch),
               lambda examples: train_step(model, collate(examples, dims.streams, device), optim, scheduler,
                                           train_cfg.precision, train_cfg.grad_clip, train_cfg.label_smoothing),
               f"slr {meta.variant}", progress, stop_after_epochs)
    return tail.result(model, resumed_from_epoch)
