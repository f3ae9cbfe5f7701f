"""The epoch loop every trainer (tokenizers, SMLM, SLR, back-translation, SGSA) runs and its tail: evaluation
when due, selection of the ``best`` checkpoint by a named metric, the resumable ``last`` checkpoint (optimizer,
scheduler, RNG), and rank-0-only logging; plus the trainers' preamble (device, seed) and shuffled batches. A
trainer keeps only what is its own: the model, its batches and its loss. The LR schedules and the optimiser step
are in :mod:`m3t.optimizer`, the checkpoint files in :mod:`m3t.checkpoints`, worker processes in
:mod:`m3t.training_jobs`.

A trainer, with ``tail = EpochTail(...)`` (and ``tail.resume_saved(...)`` to continue a ``last``)::

    device = start_training(cfg.device, cfg.seed)
    ...  # model, optimiser, schedule, tail
    run_epochs(tail, model, lambda epoch: batches(epoch),
               lambda batch: train_step(model, batch, optim, scheduler), desc="name")  # ends in optimizer_step
"""
from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch

from m3t.atomic import remove_stale_temps, run_lock
from m3t.checkpoints import rng_state, set_rng_state

if TYPE_CHECKING:
    from m3t.runtime import DistributedContext


# ---- the epoch tail -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Selection:
    """The ``best`` epoch: the one whose record has the lowest (``"min"``) or highest (``"max"``) ``metric``;
    a tie keeps the earlier epoch."""

    metric: str
    mode: Literal["min", "max"] = "min"

    def __post_init__(self):
        if self.mode not in ("min", "max"):
            raise ValueError(f"selection mode {self.mode!r} unknown; allowed: min, max")

    @property
    def worst(self) -> float:
        return math.inf if self.mode == "min" else -math.inf

    def better(self, value: float, than: float) -> bool:
        return value < than if self.mode == "min" else value > than


@dataclass
class TrainRun:
    """What a trainer returns: where its ``best`` checkpoint is, the per-epoch records and the best one (rank 0),
    the model after the last epoch (not the selected one) and the epoch a resumed run started at."""

    best_path: Path
    history: list[dict[str, float]] = field(default_factory=list)
    best: dict[str, float] = field(default_factory=dict)
    model: Any = None
    resumed_from_epoch: int = 0


LAST_EVERY_S = 30.0  # the resumable ``last`` checkpoint: at most this often, besides the end of a run (EpochTail)


class EpochTail:
    """Everything after an epoch's batches. ``end_epoch`` adds ``epoch`` and ``lr`` to the epoch's training
    means; on rank 0 only it then runs ``evaluate()`` every ``eval_every`` epochs and after the last one
    (values logged as ``val_<name>``), saves ``best_path`` when the record is a new best by ``selection``,
    appends the record to ``history``, saves ``last_path`` with :meth:`train_state` (when a path is given:
    after the last epoch of the run or of :meth:`remaining`'s range, and otherwise once ``last_every_s``
    seconds have passed since the previous save, so that a run of short epochs does not spend its time writing
    checkpoints; a killed run redoes at most that much) and calls ``on_epoch(record, epoch)``.

    Candidates for ``best`` are the evaluated epochs, or every epoch when there is no ``evaluate``.
    ``save(path, epoch, step, record, train_state)`` writes the trainer's own checkpoint; ``train_state``
    is None for ``best``. ``step`` (optimiser steps so far) is counted by the trainer's loop.
    """

    def __init__(self, epochs: int, eval_every: int, selection: Selection, optim: torch.optim.Optimizer,
                 scheduler: torch.optim.lr_scheduler.LRScheduler,
                 save: Callable[[Path, int, int, dict[str, float], dict[str, Any] | None], Any],
                 best_path: str | os.PathLike, last_path: str | os.PathLike | None = None,
                 evaluate: Callable[[], dict[str, float]] | None = None, is_main: bool = True,
                 on_epoch: Callable[[dict[str, float], int], None] | None = None,
                 last_every_s: float | None = None):
        self.epochs, self.eval_every, self.selection = epochs, eval_every, selection
        self.optim, self.scheduler, self.save, self.evaluate = optim, scheduler, save, evaluate
        self.best_path, self.last_path = Path(best_path), None if last_path is None else Path(last_path)
        self.is_main, self.on_epoch = is_main, on_epoch
        self.epoch, self.step, self.best_score = 0, 0, selection.worst
        self.history: list[dict[str, float]] = []
        self.best: dict[str, float] = {}
        self._lock = ExitStack()  # the run's lock beside its ``last`` checkpoint (resume_saved .. result)
        self.last_every_s = LAST_EVERY_S if last_every_s is None else last_every_s
        self._end = epochs  # the last epoch this call trains (remaining() may stop earlier)
        self._last_saved = time.monotonic()

    def remaining(self, stop_after_epochs: int | None = None) -> range:
        """Epoch indices still to train (from a resumed epoch on), at most ``stop_after_epochs`` of them."""
        end = self.epochs if stop_after_epochs is None else min(self.epochs, self.epoch + stop_after_epochs)
        self._end = end
        return range(self.epoch, end)

    def train_state(self) -> dict[str, Any]:
        """What a ``last`` checkpoint carries to continue the same run exactly."""
        return {"optimizer": self.optim.state_dict(), "scheduler": self.scheduler.state_dict(),
                "rng": rng_state(), "epoch": self.epoch, "step": self.step, "best_score": self.best_score,
                "history": self.history, "best": self.best}

    def resume(self, state: dict[str, Any]) -> None:
        """Continue from a :meth:`train_state` (the model's weights are the trainer's to load)."""
        self.optim.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        set_rng_state(state["rng"])
        self.epoch, self.step, self.best_score = state["epoch"], state["step"], state["best_score"]
        self.history, self.best = list(state["history"]), dict(state["best"])

    def result(self, model: torch.nn.Module, resumed_from_epoch: int = 0) -> TrainRun:
        """The run's :class:`TrainRun` once the loop is done (releases the lock :meth:`resume_saved` took)."""
        self._lock.close()
        return TrainRun(self.best_path, self.history, self.best, model, resumed_from_epoch)

    def resume_saved(self, model: torch.nn.Module, load: Callable[[Path], Any], what: str) -> int:
        """Continue from the ``last`` checkpoint when one exists: ``load(path)`` gives an object with ``model``
        and ``train_state`` (a trainer's checkpoint reader); returns the epoch training resumes at (0: none).

        On rank 0, first takes the lock ``<last>.lock`` until :meth:`result`: a second run of the same training
        (same run key) stops with an error naming the first one's pid instead of both writing one ``last``."""
        if self.last_path is not None and self.is_main:
            self._lock.enter_context(run_lock(self.last_path.with_name(self.last_path.name + ".lock"), f"training {what}"))
            for path in (self.last_path, self.best_path):  # a run killed while writing one left its temporary file
                remove_stale_temps(path)
        if self.last_path is None or not self.last_path.exists():
            return self.epoch
        loaded = load(self.last_path)
        if loaded.train_state is None:
            raise ValueError(f"{self.last_path} has no training state; delete it to train {what} afresh")
        model.load_state_dict(loaded.model.state_dict())
        self.resume(loaded.train_state)
        return self.epoch

    def end_epoch(self, epoch: int, train_means: dict[str, float], bar: Any = None) -> dict[str, float] | None:
        """Close epoch ``epoch`` (0-based); returns its record on rank 0, None on the others. ``bar``: a
        progress bar (``set_postfix``) to show the training means and the selection metric on."""
        self.epoch = epoch + 1
        record = {**train_means, "epoch": self.epoch, "lr": self.optim.param_groups[0]["lr"]}
        if not self.is_main:
            return None
        evaluated = self.evaluate is not None and (self.epoch % self.eval_every == 0 or self.epoch == self.epochs)
        if evaluated:
            record.update({f"val_{k}": v for k, v in self.evaluate().items()})
        if evaluated or self.evaluate is None:
            if self.selection.metric not in record:
                raise KeyError(f"selection metric {self.selection.metric!r} is not in the record of epoch "
                               f"{self.epoch} (keys: {', '.join(record)}); the evaluation must return it")
            score = record[self.selection.metric]
            if self.selection.better(score, self.best_score):
                self.best_score, self.best = score, dict(record)
                self.save(self.best_path, self.epoch, self.step, record, None)
        self.history.append(record)
        if self.last_path is not None and (self.epoch >= self._end
                                           or time.monotonic() - self._last_saved >= self.last_every_s):
            self.save(self.last_path, self.epoch, self.step, record, self.train_state())
            self._last_saved = time.monotonic()
        if bar is not None:
            bar.set_postfix({k.removeprefix("train_"): f"{v:.4g}" for k, v in record.items()
                             if k.startswith("train_") or k == self.selection.metric})
        if self.on_epoch is not None:
            self.on_epoch(record, self.epoch)
        return record


# ---- the trainers' preamble and epoch loop -----------------------------------------------------------------
def start_training(device: str, seed: int, dist_ctx: DistributedContext | None = None) -> torch.device:
    """The device a trainer runs on (the rank's own under DDP, else :func:`m3t.runtime.choose_device`), with
    torch's generator then seeded by ``seed``: the model's initial weights are its next draws."""
    from m3t.runtime import choose_device

    chosen = dist_ctx.device if dist_ctx is not None and dist_ctx.world_size > 1 else choose_device(device)
    torch.manual_seed(seed)
    return chosen


def scalar_settings(cfg: Any) -> dict[str, bool | int | float | str]:
    """The scalar fields of a training config dataclass: the ``train_config`` its checkpoints store."""
    return {k: v for k, v in asdict(cfg).items() if isinstance(v, (bool, int, float, str))}


def epoch_batches(samples: Sequence[Any], batch_size: int, seed: int, epoch: int) -> Iterator[list[Any]]:
    """The batches of one epoch, shuffled by (seed, epoch): the same on a resumed run."""
    order = np.random.default_rng([seed, epoch]).permutation(len(samples))
    for i in range(0, len(order), batch_size):
        yield [samples[j] for j in order[i: i + batch_size]]


def _mean(values: list[float]) -> float:
    return float(np.mean(values))


def run_epochs(tail: EpochTail, model: torch.nn.Module, batches: Callable[[int], Iterable[Any]],
               train_step: Callable[[Any], dict[str, float]], desc: str, progress: bool = True,
               stop_after_epochs: int | None = None, average: Callable[[list[float]], float] = _mean,
               before_epoch: Callable[[int], None] | None = None,
               after_batches: Callable[[], None] | None = None) -> None:
    """The epoch loop: for each epoch :meth:`EpochTail.remaining`, ``model`` in training mode,
    ``before_epoch(epoch)``, ``train_step(batch)`` (one optimiser step, counted in ``tail.step``) on each of
    ``batches(epoch)``, ``after_batches()``, then :meth:`EpochTail.end_epoch` with ``average`` (the mean) of
    each statistic the steps returned as ``train_<name>``. A progress bar ``desc`` on rank 0 unless not
    ``progress``."""
    from tqdm.auto import tqdm

    bar = tqdm(tail.remaining(stop_after_epochs), desc=desc, unit="epoch", disable=not progress or not tail.is_main)
    for epoch in bar:
        model.train()
        if before_epoch is not None:
            before_epoch(epoch)
        stats: dict[str, list[float]] = {}
        for batch in batches(epoch):
            for k, v in train_step(batch).items():
                stats.setdefault(k, []).append(v)
            tail.step += 1
        if after_batches is not None:
            after_batches()
        tail.end_epoch(epoch, {f"train_{k}": average(v) for k, v in stats.items()}, bar)
