"""Training mechanics shared by every trainer (tokenizers, SMLM, SLR, back-translation, SGSA): the warm-up +
cosine LR schedule, one optimiser step, the self-describing checkpoint file and its record, the epoch loop, and
the epoch tail: evaluation when due, selection of the ``best`` checkpoint by a named metric, the resumable
``last`` checkpoint (optimizer, scheduler, RNG), and rank-0-only logging. A trainer keeps only what is its own:
the model, its batches and its loss.

A trainer, with ``tail = EpochTail(...)`` (and ``tail.resume_saved(...)`` to continue a ``last``)::

    device = start_training(cfg.device, cfg.seed)
    ...  # model, optimiser, schedule, tail
    run_epochs(tail, model, lambda epoch: batches(epoch),
               lambda batch: train_step(model, batch, optim, scheduler), desc="name")  # ends in optimizer_step
"""
from __future__ import annotations

import math
import os
import random
import time
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Iterator, Literal, Self, Sequence

import numpy as np
import torch

from m3t.arithmetic import cache_parts

from m3t.atomic import atomic_path, remove_stale_temps, run_lock
from m3t.digest import bytes_digest, json_digest

if TYPE_CHECKING:
    from m3t.runtime import DistributedContext


# ---- schedule and step ----------------------------------------------------------------------------------
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


# ---- checkpoint files and RNG state ---------------------------------------------------------------------
def run_digest(*parts: Any) -> str:
    """16-hex digest naming a resumable run: what its ``last`` checkpoint must agree on to be continued (the
    trainer's version string, model and training settings, vocabularies, data version). ``parts`` are
    JSON-dumped with sorted keys; bytes count by their SHA-256, anything else unknown to JSON by ``str``."""
    return json_digest([*parts, *cache_parts()], length=16,
                       default=lambda v: bytes_digest(v) if isinstance(v, bytes) else str(v))


@dataclass(frozen=True, kw_only=True)
class CheckpointRecord:
    """Where a checkpoint stands in its run, stored after its weights: ``epoch``, ``step`` (optimiser steps so
    far), ``data_version``, ``metrics`` (the epoch's record), ``train_config`` (the training settings) and, in
    a resumable ``last`` only, ``train_state``. A family's loaded checkpoint extends it with its model and what
    describes it (``LoadedSMLM(CheckpointRecord)``), built by :meth:`read`."""

    epoch: int
    step: int
    data_version: str
    metrics: dict[str, float]
    train_config: dict = field(default_factory=dict)
    train_state: dict[str, Any] | None = None

    def fields(self) -> dict[str, Any]:
        """The record as a checkpoint stores it, in file order (``train_state`` only when there is one)."""
        out = {"epoch": int(self.epoch), "step": int(self.step), "data_version": self.data_version,
               "metrics": {k: float(v) for k, v in self.metrics.items()}, "train_config": dict(self.train_config)}
        if self.train_state is not None:
            out["train_state"] = self.train_state
        return out

    @classmethod
    def read(cls, payload: dict[str, Any], **own: Any) -> Self:
        """``cls`` of a checkpoint's ``payload``: its record plus ``own``, the fields a family's subclass adds."""
        return cls(**own, epoch=payload["epoch"], step=payload["step"], data_version=payload["data_version"],
                   metrics=dict(payload["metrics"]), train_config=dict(payload.get("train_config", {})),
                   train_state=payload.get("train_state"))


def checkpoint_payload(fmt: str, model: torch.nn.Module, epoch: int, step: int, data_version: str,
                       metrics: dict[str, float], train_config: dict | None = None,
                       train_state: dict[str, Any] | None = None, **described: Any) -> dict[str, Any]:
    """The fields every self-describing checkpoint has: ``format``, what rebuilds the model (``described``:
    config, dims, vocabularies, ...), the weights on the CPU, then the :class:`CheckpointRecord`."""
    record = CheckpointRecord(epoch=epoch, step=step, data_version=data_version, metrics=metrics,
                              train_config=train_config or {}, train_state=train_state)
    return {"format": fmt, **described, "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
            **record.fields()}


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """``torch.save`` of a checkpoint payload, atomically (a reader never sees half a file). Saved through a
    file handle: given a path, ``torch.save`` names the zip archive after the (random) temporary file, so
    the same payload would never give the same bytes, and every digest of a checkpoint would change."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        torch.save(payload, fh)
    return Path(path)


def read_checkpoint(path: str | os.PathLike, fmt: str, kind: str, stage: str,
                    device: str | torch.device = "cpu") -> dict[str, Any]:
    """The payload of a self-describing checkpoint of format ``fmt`` (``weights_only`` loading); clear errors
    for a missing file (run ``stage``), an unreadable one and one of another format."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{kind} checkpoint {path} not found; run `dvc repro {stage}` first")
    try:
        payload = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file gets the same advice
        raise ValueError(f"{path}: not a readable {kind} checkpoint ({type(exc).__name__}: {exc}); "
                         "delete it and retrain") from exc
    if not isinstance(payload, dict) or payload.get("format") != fmt:
        found = payload.get("format") if isinstance(payload, dict) else None
        raise ValueError(f"{path}: not an m3t {kind} checkpoint (format {found!r}, expected {fmt!r})")
    return payload


def rng_state() -> dict[str, Any]:
    """The global torch (CPU), numpy and python ``random`` generators, in types ``weights_only`` loads."""
    name, keys, pos, has_gauss, gauss = np.random.get_state()
    return {"torch": torch.get_rng_state(), "numpy": [name, keys.tolist(), pos, has_gauss, gauss],
            "python": random.getstate()}


def set_rng_state(state: dict[str, Any] | torch.Tensor) -> None:
    """Restore :func:`rng_state`'s generators (a bare tensor: a torch-only state of older checkpoints)."""
    if isinstance(state, torch.Tensor):
        state = {"torch": state}
    torch.set_rng_state(state["torch"].cpu())
    if "numpy" in state:
        name, keys, pos, has_gauss, gauss = state["numpy"]
        np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, gauss))
    if "python" in state:
        version, internal, gauss = state["python"]
        random.setstate((version, tuple(internal), gauss))


class PlateauSchedule:
    """ReduceLROnPlateau in the shape :func:`optimizer_step` and :class:`EpochTail` expect of a schedule:
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


# ---- independent trainings in worker processes ------------------------------------------------------------
EpochCallback = Callable[[dict[str, float], int], None]


def worker_split(workers: int, jobs: int, device: str = "auto", world_size: int = 1) -> tuple[int, int]:
    """(processes, threads each) for ``jobs`` independent trainings (tokenizer groups, SGSA / PT systems, probe
    variants, per-language judges): ``workers`` processes at most, one per job, sharing this process's threads;
    or (1, 0): one after another in this process. Only on the CPU and without DDP (``world_size`` 1): on a GPU
    one process already keeps the device busy. Small models often keep two threads poorly busy: on the 2-core
    machine the embedded train-tokenizers ran 1.60x, train-sgsa 1.29x and train-slr 1.12x faster in two
    one-thread processes, while the judges' languages gained nothing (``benchmarks/bench_stage_workers.py``)."""
    from m3t.runtime import choose_device

    workers = min(workers, jobs)
    if workers <= 1 or world_size > 1 or choose_device(device).type != "cpu":
        return 1, 0
    return workers, max(1, torch.get_num_threads() // workers)


def _job_in_worker(run: Callable[[Any, EpochCallback], Any], job: Any
                   ) -> tuple[Any, list[tuple[dict[str, float], int]]]:
    """One job in a worker process (its threads set by the pool); its epoch records come back with its result."""
    records: list[tuple[dict[str, float], int]] = []
    result = run(job, lambda record, epoch: records.append((dict(record), epoch)))
    return result, records


def run_jobs(run: Callable[[Any, EpochCallback | None], Any], jobs: list[Any], names: list[str],
             processes: int = 1, threads: int = 0, on_epoch: Callable[[str, dict[str, float], int], None] | None = None,
             what: str = "job", setting: str = "workers") -> list[Any]:
    """``[run(job, on_epoch_of_job) for job in jobs]``: here, one after another (``processes`` 1), or in that
    many spawned processes of ``threads`` threads each (:func:`worker_split`). A worker's epoch records reach
    ``on_epoch(name, record, epoch)`` in job order once its job is done; here they reach it as they happen.
    A job's results are those of one process running it on that many threads, whatever runs beside it.

    In workers, ``run`` and the jobs are pickled: a module-level function (or a ``functools.partial`` of one)
    and plain data. An error in a job is raised here as it was raised there; a worker that dies (out of memory,
    a signal) raises RuntimeError naming its ``what`` and ``setting`` (the trainers' ``last`` checkpoints let
    a rerun resume)."""
    if len(names) != len(jobs):
        raise ValueError(f"{len(jobs)} jobs but {len(names)} names")
    if processes <= 1:
        return [run(job, None if on_epoch is None else lambda record, epoch, n=name: on_epoch(n, record, epoch))
                for job, name in zip(jobs, names)]
    from concurrent.futures.process import BrokenProcessPool

    from m3t.runtime import spawn_pool

    results = []
    with spawn_pool(processes, threads) as pool:  # a worker whose stage is killed ends itself
        futures = [pool.submit(_job_in_worker, run, job) for job in jobs]
        for name, future in zip(names, futures):
            try:
                result, records = future.result()
            except BrokenProcessPool as exc:
                raise RuntimeError(f"the worker process running {what} {name!r} died ({exc}); rerun to resume from "
                                   f"the last saved epoch, or set {setting}: 1 to run in this process") from exc
            for record, epoch in records if on_epoch else ():
                on_epoch(name, record, epoch)
            results.append(result)
    return results
