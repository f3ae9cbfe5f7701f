"""Training one skeletal production model, SGSA or its PT baseline (SGSA Sec. 4.2 / 5, Progressive Transformers).

Loss: MSE between predicted and ground-truth frames (skeleton coordinates and counter, real frames only), plus
``counter_weight`` x the counter's own squared error (0 = the papers' plain MSE, in which the counter is 1 of S
coordinates: on the embedded corpus it was never learned and stayed ~0.5 on every frame), plus ``gloss_weight`` x
the CTC loss of the encoder's gloss head over the clips that have glosses (gloss supervision).
Teacher forcing with **Gaussian noise augmentation** (PT): the previous frames fed to the decoder get noise
``N(0, 1) x min(noise_rate x std_d, noise_cap x spread_d)``, where ``std_d`` is the per-coordinate standard
deviation of the previous epoch's prediction error (none in the first epoch) and ``spread_d`` the coordinate's
standard deviation over the train split; the counter column is never perturbed. Without the cap the papers' rule
feeds back on itself (noise raises the error, which raises the noise: error std 2 -> 10 -> 51 -> NaN in one run
at rate 5). Adam at ``lr`` with default betas, ReduceLROnPlateau on the dev selection figure, gradient clipping;
the checkpoint with the lowest dev :data:`~m3t.sgsa.evaluate.SELECTION_METRIC` (generated with the predicted
counter; DTW-JPE times a length penalty, so a model is not selected for stopping after one frame) is ``best``. A resumable ``last`` is written at most
every 30 s and at the end (:class:`m3t.training.EpochTail`), the noise statistics with it: a killed run continues
the same curve.

Axis legend: B batch, U frames, S skeleton width with counter, K text tokens, G glosses.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from m3t.body.skeleton import SkeletonGraph
from m3t.checkpoints import run_digest
from m3t.optimizer import PlateauSchedule, adam, optimizer_step
from m3t.sgsa.checkpoint import build_model, load_sgsa, save_sgsa
from m3t.sgsa.config import SGSAConfig, SGSATrainConfig
from m3t.sgsa.data import Batch, Sample, collate
from m3t.sgsa.evaluate import SELECTION_METRIC, ProductionEvaluator
from m3t.sgsa.model import SGSAProduction
from m3t.training import (
    EpochTail,
    Selection,
    TrainRun,
    epoch_batches,
    run_epochs,
    scalar_settings,
    start_training,
)
from m3t.vocabulary import Vocabulary

TRAIN_VERSION = "sgsa-v2"  # part of the resume key: bump when older training state becomes invalid


def run_key(model_cfg: SGSAConfig, cfg: SGSATrainConfig, graph: SkeletonGraph, text_vocab: Vocabulary,
            gloss_vocab: Vocabulary | None, data_version: str) -> str:
    """What a resumable ``last`` must agree on: code version, model and training settings (not the cache folder or
    the device), graph, vocabularies and data."""
    settings = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("cache_dir", "device", "workers")}
    return run_digest(TRAIN_VERSION, dataclasses.asdict(model_cfg), settings, graph.to_dict(), text_vocab.to_dict(),
                      None if gloss_vocab is None else gloss_vocab.to_dict(), data_version)


def losses(model: SGSAProduction, batch: Batch, gloss_weight: float, noise_std: torch.Tensor | None = None,
           counter_weight: float = 0.0) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """``({"loss", "skeleton_loss"[, "gloss_ctc_loss"]}, errors)``: errors (N, S) = prediction - target of the
    real frames (for the next epoch's noise)."""
    frames_in = batch.frames_in
    if noise_std is not None:
        noise = torch.randn_like(frames_in) * noise_std
        noise[..., -1] = 0.0  # the counter is progress, not pose: never perturbed
        frames_in = frames_in + noise
    out = model(batch.text_ids, batch.text_mask, frames_in, batch.frame_mask)
    err = (out.frames - batch.target)[batch.frame_mask]  # (N, S)
    skeleton = err.pow(2).mean()
    result = {"loss": skeleton, "skeleton_loss": skeleton}
    if counter_weight > 0:  # the counter is 1 of S coordinates of the MSE: too faint a signal on a small corpus
        counter = err[:, -1].pow(2).mean()
        result.update(loss=skeleton + counter_weight * counter, counter_loss=counter)
    rows = batch.gloss_lengths > 0
    if out.gloss_logits is not None and gloss_weight > 0 and bool(rows.any()):
        log_probs = out.gloss_logits[rows].float().log_softmax(-1).transpose(0, 1)  # (K, B', G)
        ctc = F.ctc_loss(log_probs, batch.glosses[rows], batch.text_mask[rows].sum(1), batch.gloss_lengths[rows],
                         blank=0, reduction="mean", zero_infinity=True)
        result.update(loss=result["loss"] + gloss_weight * ctc, gloss_ctc_loss=ctc)
    return result, err.detach()


def train_step(model: SGSAProduction, batch: Batch, optim: torch.optim.Optimizer, schedule: PlateauSchedule,
               gloss_weight: float, noise_std: torch.Tensor | None = None, counter_weight: float = 0.0,
               grad_clip: float = 0.0) -> tuple[dict[str, float], torch.Tensor]:
    """One optimiser step on ``batch`` (on the model's device): its losses, and the prediction errors (N, S) of its
    real frames on the CPU (:func:`losses`)."""
    out, err = losses(model, batch, gloss_weight, noise_std, counter_weight)
    optimizer_step(out["loss"], model, optim, schedule, grad_clip)
    return {k: float(v.item()) for k, v in out.items()}, err.cpu()


def noise_ceiling(train: Sequence[Sample], noise_cap: float, device: torch.device) -> torch.Tensor | None:
    """(S,) the largest noise std per coordinate: ``noise_cap`` x the coordinate's std over the train split's frames
    (None with ``noise_cap`` 0: no cap)."""
    if noise_cap == 0:
        return None
    frames = np.concatenate([s.target for s in train]).astype(np.float64)  # (N, S)
    return torch.as_tensor(frames.std(0) * noise_cap, dtype=torch.float32, device=device)


def augmentation_std(error_std: torch.Tensor | None, noise_rate: float, ceiling: torch.Tensor | None,
                     device: torch.device) -> torch.Tensor | None:
    """(S,) the std of an epoch's input noise: ``noise_rate`` x the previous epoch's per-coordinate error std, at
    most ``ceiling`` (:func:`noise_ceiling`); None without an error std (the first epoch) or with rate 0."""
    if error_std is None or noise_rate == 0:
        return None
    std = torch.as_tensor(error_std, device=device) * noise_rate
    return std if ceiling is None else torch.minimum(std, ceiling)


def train_sgsa(model_cfg: SGSAConfig, cfg: SGSATrainConfig, graph: SkeletonGraph, text_vocab: Vocabulary,
               gloss_vocab: Vocabulary | None, train: Sequence[Sample], dev: Sequence[Sample], data_version: str,
               best_path: str | Path, last_path: str | Path | None = None,
               on_epoch: Callable[[dict[str, float], int], None] | None = None, progress: bool = True,
               stop_after_epochs: int | None = None) -> TrainRun:
    """Train one model on ``train``, selecting on ``dev`` (the first ``eval_max_clips``; without dev clips the
    last epoch is kept). ``last_path``: the resumable checkpoint, continued when it exists."""
    if not train:
        raise ValueError("no training clip for the skeletal production model")
    device = start_training(cfg.device, cfg.seed)
    model = build_model(model_cfg, graph, text_vocab, gloss_vocab).to(device)
    optim = adam(model.parameters(), device, lr=cfg.lr)
    schedule = PlateauSchedule(optim, "min", cfg.lr_factor, cfg.lr_patience, cfg.min_lr)
    settings = scalar_settings(cfg)
    dev = list(dev)[: cfg.eval_max_clips] if cfg.eval_max_clips > 0 else list(dev)
    evaluator = ProductionEvaluator(dev, graph, text_vocab, model_cfg.max_frames) if dev else None
    # per-coordinate std (S,) of the previous epoch's prediction error, and of this epoch's input noise
    noise = {"std": None, "input": None}
    errors: list[torch.Tensor] = []  # this epoch's prediction errors (N, S)
    cap = noise_ceiling(train, cfg.noise_cap, device)

    def evaluate() -> dict[str, float]:
        scores = evaluator(model)
        schedule.observe(scores[SELECTION_METRIC])
        return scores

    def save(path, epoch, step, record, state):
        if state is not None:
            state = {**state, "noise_std": noise["std"]}
        return save_sgsa(path, model, graph, text_vocab, gloss_vocab, epoch, step, data_version, record, settings,
                         state)

    tail = EpochTail(cfg.epochs, cfg.eval_every,
                     Selection(f"val_{SELECTION_METRIC}", "min") if dev else Selection("epoch", "max"), optim,
                     schedule, save=save, best_path=best_path, last_path=last_path,
                     evaluate=evaluate if evaluator is not None else None, on_epoch=on_epoch)

    def load(path):
        loaded = load_sgsa(path, device)
        if loaded.train_state is not None:
            noise["std"] = loaded.train_state.get("noise_std")
        return loaded

    resumed_from_epoch = tail.resume_saved(model, load, f"the {model_cfg.variant} model")

    def start_epoch(epoch: int) -> None:
        errors.clear()
        noise["input"] = augmentation_std(noise["std"], cfg.noise_rate, cap, device)

    def train_batch(samples: list[Sample]) -> dict[str, float]:
        stats, err = train_step(model, collate(samples, text_vocab).to(device), optim, schedule,
                                model_cfg.gloss_weight, noise["input"], cfg.counter_weight, cfg.grad_clip)
        errors.append(err)
        return stats

    def end_batches() -> None:
        noise["std"] = torch.cat(errors).double().std(0).float() if sum(len(e) for e in errors) > 1 else None

    samples = list(train)
    run_epochs(tail, model, lambda epoch: epoch_batches(samples, cfg.batch_size, cfg.seed, epoch), train_batch,
               f"train {model_cfg.variant}", progress, stop_after_epochs, before_epoch=start_epoch,
               after_batches=end_batches)
    return tail.result(model, resumed_from_epoch)
