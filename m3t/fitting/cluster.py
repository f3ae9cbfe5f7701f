"""Where fit-corpus fits its clips: params.yaml ``fit_corpus.executor`` -> the executor that
:func:`m3t.fitting.corpus.run_fit_corpus` sends clips to (:func:`open_executor`).

- ``local``: ``fit_corpus.workers`` spawned processes on this machine (one worker: clips run in this process);
- ``dask`` with ``dask_address: ""``: a ``distributed.LocalCluster`` of ``workers`` single-threaded worker
  processes, started for this run and closed after it;
- ``dask`` with ``dask_address: tcp://scheduler:8786``: a running Dask cluster (``dask scheduler`` + ``dask worker
  ADDRESS --nthreads 1`` on other machines, dask-jobqueue's ``SLURMCluster``, dask-kubernetes), left running.

Every worker must see the same files at the same paths as this process: the corpus, the body model files and
``fit_corpus.cache_dir``, where workers write tracks and part files (a shared filesystem when workers run on
other machines). Before a job is sent to Dask workers, its cache dir, corpus root and body-model cache are made
absolute against this process' working directory, so a relative ``.cache/fit`` names the same directory on
every worker that shares it, wherever the worker was started; licensed body files (``body.smplx_path`` ...) are
part of the fits' cache key as written, so they stay as given: start workers from the repository root or give
absolute paths. Workers must run this project's code at the same version (the same checkout or install).

Dask workers fit with one torch thread (one worker process per core; intra-op threads would oversubscribe),
set on every task so that it also holds on workers that join or restart mid-run, and build their body model once
per process (:func:`m3t.fitting.context.worker_context`). A run keeps at most one task (one clip, or one batch of
a signer's clips: ``fit_corpus.batch_clips``) per worker thread in flight (:meth:`DaskExecutor.capacity`), so a
worker that dies (out of memory, pre-empted) takes down only what it was fitting: Dask reschedules that task on
another worker up to ``distributed.scheduler.allowed-failures`` times (Dask config, default 3), then the engine
quarantines its clips ("worker died while fitting this clip") and the run goes on; the next run retries them.
A scheduler that stops answering stops the run with a message naming its address; finished clips are cached, so
a rerun resumes. A scheduler without workers holds the clips until workers join (a queued SLURM job, say).
"""
from __future__ import annotations

import os
import sys
import uuid
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future
from contextlib import contextmanager
from dataclasses import replace
from typing import Any

from m3t.fitting.config import FitCorpusConfig, FitJob

CONNECT_SECONDS = 30.0  # to reach a scheduler, and for every question asked of it during a run


class SchedulerLost(RuntimeError):
    """The run's Dask scheduler is gone or stopped answering: the run stops (finished clips are cached)."""


def one_thread() -> None:
    """One intra-op torch thread in this process: one worker process per core, more threads would oversubscribe."""
    from m3t.runtime import use_threads

    use_threads(1)


def process_pool(workers: int) -> Executor | None:
    """``workers`` spawned one-thread processes that end themselves when this process is killed
    (:func:`m3t.runtime.spawn_pool`); None for one worker: clips then run in this process."""
    if workers <= 1:
        return None
    from m3t.runtime import spawn_pool

    return spawn_pool(workers, threads=1)


def for_workers(job: FitJob) -> FitJob:
    """``job`` with the paths a worker opens made absolute against this process' working directory: the cache
    dir, the corpus root (``""`` = the adapter's packaged default, kept) and the body model's build cache (not
    part of any cache key, so fits and shards are unchanged)."""
    absolute = lambda path: os.path.abspath(path) if path else path
    return replace(job, run=replace(job.run, cache_dir=absolute(job.run.cache_dir)),
                   source=replace(job.source, root=absolute(job.source.root)),
                   body=replace(job.body, cache_dir=absolute(job.body.cache_dir)))


def on_worker(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """What a Dask worker runs for one task (a clip or a batch): ``fn(*args, **kwargs)`` with one torch thread."""
    one_thread()
    return fn(*args, **kwargs)


def worker_died(exc: BaseException) -> bool:
    """Whether ``exc`` (raised by a task's future) says the worker fitting its clips died: Dask's
    ``KilledWorker`` (the scheduler gave up after its allowed failures) or a closed connection to that worker
    (``CommClosedError``)."""
    if "distributed" not in sys.modules:  # only Dask raises these; never import it for a process pool
        return False
    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    return isinstance(exc, (KilledWorker, CommClosedError))


class DaskExecutor(Executor):
    """A Dask client as the engine's executor. ``submit`` sends ``fn(*args)`` to the cluster (a
    :class:`FitJob` argument with its paths made absolute, :func:`for_workers`) and returns a
    ``concurrent.futures.Future``; :meth:`capacity` is how many tasks to keep in flight and :meth:`check`
    raises :class:`SchedulerLost` when the scheduler is gone. ``shutdown`` closes the client and, when this
    executor started it, the local cluster."""

    def __init__(self, client, cluster=None):
        self.client = client
        self.address: str = client.scheduler.address
        self._cluster = cluster
        self._executor = client.get_executor()

    def submit(self, fn, /, *args, **kwargs) -> Future:
        args = tuple(for_workers(a) if isinstance(a, FitJob) else a for a in args)
        # a key of its own per task: the same clips sent twice (a retried run) are computed again, never shared
        return self._executor.submit(on_worker, fn, *args, key=f"fit-clips-{uuid.uuid4().hex}", **kwargs)

    def _identity(self) -> dict[str, Any]:
        """The scheduler's summary (no per-worker details), asked with a timeout."""
        if self.client.status != "running":
            raise self.lost(f"the client's connection is {self.client.status}")
        try:
            return self.client.sync(self.client.scheduler.identity, n_workers=0, callback_timeout=CONNECT_SECONDS)
        except Exception as exc:
            raise self.lost(f"it did not answer within {CONNECT_SECONDS:.0f} s: {type(exc).__name__}: {exc}") from exc

    def capacity(self) -> int:
        """Tasks to keep in flight: one per worker thread, so a dying worker takes only its own task down
        (Dask would otherwise queue several on each worker); at least one, so a run waits for workers to join."""
        return max(int(self._identity().get("total_threads", 0)), 1)

    def check(self) -> None:
        """Raise :class:`SchedulerLost` unless the scheduler answers."""
        self._identity()

    def lost(self, why: str) -> SchedulerLost:
        return SchedulerLost(f"lost the Dask scheduler at {self.address} ({why}); finished clips are cached, "
                             "rerun to resume")

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        try:
            if wait and not cancel_futures and self.client.status == "running":
                self._executor.shutdown(wait=True)
            self.client.close(timeout=CONNECT_SECONDS)  # the scheduler drops the tasks nobody holds any more
        finally:
            if self._cluster is not None:
                self._cluster.close(timeout=CONNECT_SECONDS)


def connect_dask(run: FitCorpusConfig) -> DaskExecutor:
    """A :class:`DaskExecutor` on ``run.dask_address``, or on a new ``LocalCluster`` of ``run.workers``
    single-threaded worker processes when the address is empty."""
    from distributed import Client, LocalCluster

    if not run.dask_address:
        cluster = LocalCluster(n_workers=max(run.workers, 1), threads_per_worker=1, processes=True,
                               dashboard_address="127.0.0.1:0")  # a free port: never a clash with another cluster's 8787
        try:
            return DaskExecutor(Client(cluster, set_as_default=False), cluster)
        except BaseException:
            cluster.close()
            raise
    try:
        client = Client(run.dask_address, timeout=CONNECT_SECONDS, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ConnectionError(
            f"fit_corpus.dask_address: no Dask scheduler answered at {run.dask_address!r} within "
            f"{CONNECT_SECONDS:.0f} s ({exc}); start one (`dask scheduler`, then `dask worker ADDRESS --nthreads 1` "
            "on each machine) or set fit_corpus.dask_address to '' for a cluster on this machine") from exc
    return DaskExecutor(client)


@contextmanager
def open_executor(run: FitCorpusConfig) -> Iterator[Executor | None]:
    """The executor of ``fit_corpus.executor`` for one run, shut down after it: None (in this process) for
    ``local`` with one worker, a process pool for ``local``, a :class:`DaskExecutor` for ``dask``."""
    if run.executor == "local":
        if run.dask_address:
            raise ValueError(f"fit_corpus.dask_address is {run.dask_address!r} but fit_corpus.executor is 'local': "
                             "set fit_corpus.executor to dask to fit on that cluster, or dask_address to ''")
        executor: Executor | None = process_pool(run.workers)
    elif run.executor == "dask":
        executor = connect_dask(run)
    else:
        raise ValueError(f"fit_corpus.executor: {run.executor!r} is not allowed; expected 'local' or 'dask'")
    try:
        yield executor
    finally:
        if executor is not None:
            executor.shutdown(cancel_futures=True)


@contextmanager
def stage_executor(cluster: FitCorpusConfig | None) -> Iterator[Executor | None]:
    """For a stage after fitting (tokenize, generate-smlm, evaluate-smlm): fit-corpus's Dask cluster when
    ``cluster.executor`` is ``dask`` (:func:`open_executor`), else None: the stage's own process does the work."""
    if cluster is None or cluster.executor != "dask":
        yield None
        return
    with open_executor(cluster) as executor:
        yield executor


def submitted_in_order(executor: Executor, fn: Callable[..., Any], calls: Iterable[tuple]) -> Iterator[Any]:
    """``fn(*args)`` for each ``args`` of ``calls`` on ``executor``, results in the order of ``calls``, with at most
    the executor's :meth:`DaskExecutor.capacity` (two for another executor) calls in flight, so a stage holds only
    that many inputs and results at once (tokenize's row groups, the evaluation's runs of clips)."""
    from collections import deque

    in_flight = executor.capacity() if isinstance(executor, DaskExecutor) else 2
    pending: deque[Future] = deque()
    for args in calls:
        pending.append(executor.submit(fn, *args))
        while len(pending) > in_flight:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()
