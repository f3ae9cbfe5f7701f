"""The optimiser side of every trainer: the warm-up + cosine LR schedule (and a plateau schedule in the same
shape), torch's Adam on its fused kernel, and one optimiser step (backward, gradient averaging over ranks,
clipping, step, schedule step)."""
from __future__ import annotations

import math
from typing import Any, Literal

import torch


def lr_factor(step: int, warmup_steps: int, total_steps: int, floor: float) -> float:
    """Multiplier of the base LR at optimiser step ``step``: linear warm-up to 1, then cosine to ``floor``."""
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
    return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * progress))


def warmup_cosine(optim: torch.optim.Optimizer, epochs: int, steps_per_epoch: int, warmup: int,
                  warmup_unit: Literal["epochs", "steps"], min_lr: float) -> torch.optim.lr_scheduler.LambdaLR:
    """The LR schedule of every trainer, stepped once per optimiser step: ``warmup`` epochs or steps (as
    ``warmup_unit`` says) of linear warm-up, then cosine from the optimiser's LR down to ``min_lr`` at the end
    of ``epochs * steps_per_epoch`` steps."""
    if warmup_unit not in ("epochs", "steps"):
        raise ValueError(f"warmup_unit {warmup_unit!r} unknown; allowed: epochs, steps")
    total = epochs * steps_per_epoch
    warm = warmup * steps_per_epoch if warmup_unit == "epochs" else warmup
    floor = min_lr / optim.defaults["lr"]
    return torch.optim.lr_scheduler.LambdaLR(optim, lambda s: lr_factor(s, warm, total, floor))


def average_gradients(model: torch.nn.Module) -> None:
    """Mean of every parameter's gradient over the ranks, for a model not wrapped in DDP. A parameter this
    step did not use gets a zero gradient first, so every rank reduces the same list in the same order."""
    world = torch.distributed.get_world_size()
    for p in model.parameters():
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        torch.distributed.all_reduce(p.grad)
        p.grad /= world


def adam(params, device: torch.device | str, decoupled: bool = False, **options: Any) -> torch.optim.Optimizer:
    """torch's Adam (``decoupled``: AdamW) with ``options``, on its fused kernel where ``device`` has one (CPU,
    CUDA): one pass over each parameter instead of about ten elementwise kernels per parameter list. The same
    update, equal up to float rounding; on the embedded CPU runs the unfused step was 11 % of the tokenizers'
    training time (measured with a sampling profiler)."""
    cls = torch.optim.AdamW if decoupled else torch.optim.Adam
    fused = torch.device(device).type in ("cpu", "cuda")
    return cls(params, fused=True, **options) if fused else cls(params, **options)


def optimizer_step(loss: torch.Tensor, model: torch.nn.Module, optim: torch.optim.Optimizer,
                   scheduler: torch.optim.lr_scheduler.LRScheduler, grad_clip: float = 0.0,
                   average_grads: bool = False) -> None:
    """Backward, then (``average_grads`` and a process group up) :func:`average_gradients`, clipping of the
    gradient norm to ``grad_clip`` (0 = none), the optimiser step and the LR schedule's step."""
    optim.zero_grad(set_to_none=True)
    loss.backward()
    if average_grads and torch.distributed.is_available() and torch.distributed.is_initialized():
        average_gradients(model)
    if grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
    optim.step()
    scheduler.step()


class PlateauSchedule:
    """ReduceLROnPlateau in the shape :func:`optimizer_step` and :class:`m3t.training.EpochTail` expect of a schedule:
    ``step()`` after each optimiser step does nothing, :meth:`observe` after each validation may cut the LR by
    ``factor`` once the validation score has not improved (``mode`` ``"min"`` / ``"max"``) for ``patience``
    validations; ``state_dict`` / ``load_state_dict`` carry it through a ``last`` checkpoint."""

    def __init__(self, optim: torch.optim.Optimizer, mode: Literal["min", "max"], factor: float, patience: int,
                 min_lr: float):
        self.plateau = torch.optim.lr_scheduler.ReduceLROnPlateau(optim, mode=mode, factor=factor,
                                                                  patience=patience, min_lr=min_lr)

    def step(self) -> None:
        pass

    def observe(self, score: float) -> None:
        self.plateau.step(score)

    def state_dict(self) -> dict[str, Any]:
        return self.plateau.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.plateau.load_state_dict(state)
