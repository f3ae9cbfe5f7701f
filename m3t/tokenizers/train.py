"""Training one modality group's tokenizer (M3T App. 0.D.1): Adam, linear warm-up then cosine decay to a
floor, L2 reconstruction on the parameters (Eq. 6; plus the commitment term for the VQ baseline), the
checkpoint with the lowest validation vertex error kept as ``best``, and a resumable ``last`` checkpoint
written after every epoch (a rerun with the same config and data continues the same loss curve).

GPU paths live here too: device from :func:`m3t.runtime.choose_device`, optional bf16 autocast, and DDP
when launched by ``torchrun`` (:func:`m3t.runtime.distributed_context`); rank 0 evaluates, logs and saves.

Axis legend: B batch, W window frames, D group dim.
"""
from __future__ import annotations

import dataclasses
import operator
from dataclasses import dataclass, field
from functools import reduce
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel

from m3t.checkpoints import run_digest
from m3t.optimizer import adam, optimizer_step, warmup_cosine
from m3t.runtime import DistributedContext, autocast
from m3t.tokenizers.checkpoint import load_tokenizer, save_tokenizer
from m3t.tokenizers.config import TokenizerTrainConfig, VAEConfig
from m3t.tokenizers.data import WindowSampler, normalisation
from m3t.tokenizers.evaluate import ReconstructionProbe
from m3t.tokenizers.vae import MotionTokenizer
from m3t.training import EpochTail, Selection, run_epochs, start_training

TRAIN_VERSION = "tok-v2"  # part of the resume key: bump when a change makes older training state invalid


@dataclass
class TrainResult:
    """best_path / last_path: the selected and the resumable checkpoint (both under the cache dir)."""

    group: str
    best_path: Path
    last_path: Path
    history: list[dict[str, float]] = field(default_factory=list)
    best: dict[str, float] = field(default_factory=dict)
    resumed_from_epoch: int = 0
    model: MotionTokenizer | None = None  # the model after the last epoch (not the selected one)


def masked_mse(recon: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over real frames only. recon/target (B, W, D), mask (B, W) bool."""
    weight = mask.unsqueeze(-1).to(recon.dtype)
    return ((recon - target).pow(2) * weight).sum() / (weight.sum() * recon.shape[-1]).clamp_min(1.0)


def train_step(model: torch.nn.Module, batch: tuple[torch.Tensor, torch.Tensor], optim: torch.optim.Optimizer,
               scheduler: torch.optim.lr_scheduler.LRScheduler, precision: str = "fp32") -> dict[str, float]:
    x, mask = batch
    with autocast(x.device, precision):
        out = model(x)
    # Eq. 6 on standardised parameters: every dim counts on the scale of its own variation (as MotionGPT),
    # otherwise low-variance streams (finger 6D entries, expression coefficients) barely contribute.
    std = getattr(model, "module", model).std
    recon = masked_mse(out.recon.float() / std, x / std, mask)
    loss = recon + out.quant_loss.float()
    optimizer_step(loss, model, optim, scheduler)  # a DDP-wrapped model averages its gradients itself
    return {"loss": loss.item(), "recon_mse": recon.item(), "perplexity": out.perplexity.item()}


def run_key(group: str, model_cfg: VAEConfig, cfg: TokenizerTrainConfig, data_version: str) -> str:
    # where and how it runs (device, processes) does not name the run: a checkpoint resumes on any of them
    where = ("out_dir", "cache_dir", "device", "group_workers")
    relevant = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in where}
    return run_digest(TRAIN_VERSION, group, dataclasses.asdict(model_cfg), relevant, data_version)


def train_tokenizer(
    group: str,
    model_cfg: VAEConfig,
    cfg: TokenizerTrainConfig,
    train_sequences: Sequence[np.ndarray],
    probe: ReconstructionProbe | None,
    data_version: str,
    on_epoch: Callable[[dict[str, float], int], None] | None = None,
    stop_after_epochs: int | None = None,
    dist_ctx: DistributedContext | None = None,
    progress: bool = True,
) -> TrainResult:
    """Train (or resume) one tokenizer; returns where its ``best`` and ``last`` checkpoints are."""
    dist_ctx = dist_ctx or DistributedContext()
    if cfg.window % model_cfg.downsample:
        raise ValueError(f"tokenizer_train.window ({cfg.window}) must be a multiple of the downsampling factor "
                         f"{model_cfg.downsample}")
    key = run_key(group, model_cfg, cfg, data_version)
    # Both checkpoints live in the cache under the run key (so a finished run is never redone); the
    # stage copies ``best`` to ``out_dir``.
    last_path = Path(cfg.cache_dir) / f"{group}-{key}.last.pt"
    best_path = Path(cfg.cache_dir) / f"{group}-{key}.best.pt"
    device = start_training(cfg.device, cfg.seed, dist_ctx)
    model = MotionTokenizer(model_cfg)
    model.set_normalisation(*normalisation(train_sequences))
    model.to(device)
    sampler = WindowSampler(train_sequences, cfg.window, cfg.batch_size, cfg.windows_per_clip, cfg.seed,
                            dist_ctx.rank, dist_ctx.world_size)
    steps_per_epoch = len(sampler)
    optim = adam(model.parameters(), device, lr=cfg.lr)
    scheduler = warmup_cosine(optim, cfg.epochs, steps_per_epoch, cfg.warmup_epochs, "epochs", cfg.min_lr)
    tail = EpochTail(
        cfg.epochs, cfg.eval_every,
        # validation vertex error on evaluation epochs; the training loss when there is no probe
        Selection("train_recon_mse" if probe is None else "val_vpe_mm"), optim, scheduler,
        save=lambda path, epoch, step, record, state: save_tokenizer(path, model, group, epoch, step, data_version,
                                                                     record, state),
        best_path=best_path, last_path=last_path, evaluate=None if probe is None else lambda: probe.measure(model),
        is_main=dist_ctx.is_main, on_epoch=on_epoch)
    # resume: same config + same data -> continue the same curve
    resumed_from_epoch = tail.resume_saved(model, lambda p: load_tokenizer(p, device), f"tokenizer {group!r}")
    net = DistributedDataParallel(model) if dist_ctx.world_size > 1 else model
    run_epochs(tail, net, sampler.epoch,
               lambda batch: train_step(net, tuple(t.to(device) for t in batch), optim, scheduler, cfg.precision),
               f"tokenizer:{group}", progress, stop_after_epochs,
               # summed in step order, over the sampler's steps: the recorded means keep their exact values
               average=lambda values: reduce(operator.add, values, 0.0) / steps_per_epoch)
    return TrainResult(group, best_path, last_path, tail.history, tail.best, resumed_from_epoch, model)
