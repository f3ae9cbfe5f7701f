"""Independent trainings (tokenizer groups, SGSA / PT systems, probe variants, per-language judges) run one
after another here or in spawned worker processes sharing this process's threads: :func:`worker_split` picks
how many, :func:`run_jobs` runs them and hands their epoch records back in job order."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

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
