"""The corpus-fitting engine: a corpus' clips -> tracks -> (fused) initialisation -> refined body-model
parameters -> one part file per clip -> shards (one per split) and the data-quality report.

One orchestration path for every caller: the DVC stage ``fit-corpus``, the Prefect flow ``fit-corpus`` and
tests all call :func:`run_fit_corpus` with a :class:`FitJob` (everything a worker needs, picklable: configs
only, never a built model) and, by default, the executor of ``fit_corpus.executor``
(:func:`m3t.fitting.cluster.open_executor`: local processes or a Dask cluster), or any
``concurrent.futures.Executor``-like runner passed in. The unit of work is a signer batch (:func:`plan_batches`,
:func:`fit_batch`: a signer's clips fitted together, :mod:`m3t.fitting.signer_batches`). Each worker process
builds its body model once (:func:`m3t.fitting.context.worker_context`) and reuses it for every batch it is sent.

What happens to one clip (track, initialisation, fit or import) is :mod:`m3t.fitting.per_clip`; the
content-addressed cache that lets a killed run resume and never re-fits an unchanged clip is
:mod:`m3t.fitting.cache`. A clip that fails is quarantined with its reason; the others go on.
:func:`m3t.fitting.report.consolidate` writes the shards and reports.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor
from pathlib import Path

from m3t.atomic import run_lock
from m3t.corpora.base import open_corpus
from m3t.corpora.clip import Clip
from m3t.corpora.listing import Listing
from m3t.fitting.config import FitCorpusConfig, FitJob  # noqa: F401 - FitCorpusConfig: the engine's config
from m3t.fitting.context import FitContext, worker_context
from m3t.fitting.imports import imported_kind, plan_import
from m3t.fitting.report import ClipOutcome, FitCorpusReport, consolidate
from m3t.fitting.signer_batches import process_batch
from m3t.trackers.dispatch import ground_truth, simulated_corpus


# ------------------------------------------------------------------------------------------ listing
def list_corpus(job: FitJob) -> Listing:
    """The adapter's listing (clips cut to ``max_clips``, its quarantined rows all kept)."""
    listing = open_corpus(job.corpus, job.source.root, **job.source.options).listing()
    clips = listing.clips[: job.run.max_clips] if job.run.max_clips > 0 else listing.clips
    return Listing(tuple(clips), listing.quarantined)


def listing_outcomes(listing: Listing) -> list[ClipOutcome]:
    """The rows the adapter refused, as quarantined outcomes (file + row + reason)."""
    return [ClipOutcome(q.clip_id or "", "", "quarantined", reason=q.reason, file=q.file, row=q.row,
                        group="listing: " + q.reason.split(":")[0].split(";")[0][:60], from_listing=True)
            for q in listing.quarantined]


# ------------------------------------------------------------------------------------------ batches
def plan_batches(clips: list[Clip], batch_clips: int) -> list[list[Clip]]:
    """Clips grouped by signer (in listing order), at most ``batch_clips`` per batch (1 = a batch per clip)."""
    if batch_clips <= 1:
        return [[c] for c in clips]
    by_signer: dict[str, list[Clip]] = {}
    for clip in clips:
        by_signer.setdefault(clip.signer, []).append(clip)
    return [group[i:i + batch_clips] for group in by_signer.values() for i in range(0, len(group), batch_clips)]


def fit_batch(job: FitJob, clips: list[Clip]) -> list[ClipOutcome]:
    """The unit sent to an executor: a picklable job and one batch of :func:`plan_batches`, processed with this
    process' context."""
    return process_batch(clips, worker_context(job))


# ------------------------------------------------------------------------------------ the whole run
LOCK_NAME = ".fit-corpus.lock"  # in the shards dir while a run writes it: a second run on it is refused
POLL_SECONDS = 10.0  # while no clip finishes, how often an executor is asked whether its cluster is still there


def _outcomes(job: FitJob, clips: list[Clip], executor: Executor | None,
              ctx: FitContext | None) -> Iterator[ClipOutcome]:
    """Outcomes in completion order, batch by batch (:func:`plan_batches`). An executor with ``capacity()``
    (Dask) gets at most that many batches at a time; one with ``check()`` is asked, while no batch finishes,
    whether its cluster is still there (it raises when not). The clips of a batch whose worker died are
    quarantined and the others go on (:mod:`m3t.fitting.cluster`)."""
    batches = plan_batches(clips, job.run.batch_clips)
    if executor is None:
        ctx = ctx or worker_context(job)
        for batch in batches:
            yield from process_batch(batch, ctx)
        return
    from concurrent.futures import FIRST_COMPLETED, CancelledError, Future, wait
    from concurrent.futures.process import BrokenProcessPool
    from itertools import islice

    from m3t.fitting.cluster import worker_died

    capacity = getattr(executor, "capacity", lambda: len(batches))
    check = getattr(executor, "check", lambda: None)
    todo, left = iter(batches), len(batches)
    running: dict[Future, list[Clip]] = {}
    try:
        while True:
            if left:
                sent = list(islice(todo, max(capacity() - len(running), 0)))
                left -= len(sent)
                running.update((executor.submit(fit_batch, job, b), b) for b in sent)
            if not running:
                return
            done, _ = wait(running, timeout=POLL_SECONDS, return_when=FIRST_COMPLETED)
            if not done:
                check()
            for future in done:
                batch = running.pop(future)
                try:
                    outcomes = future.result()
                except CancelledError as exc:  # Dask cancels every task when its scheduler connection drops
                    check()
                    raise RuntimeError(f"clip {batch[0].id}: the executor cancelled its task; finished clips are "
                                       "cached, rerun to resume") from exc
                except Exception as exc:
                    if not worker_died(exc):
                        raise
                    outcomes = [ClipOutcome(clip.id, clip.split, "quarantined", group="worker died", file=clip.media,
                                            reason=f"worker died while fitting this clip: {type(exc).__name__}: "
                                                   f"{exc} (the next run retries it)") for clip in batch]
                yield from outcomes
    except BrokenProcessPool as exc:
        raise RuntimeError("a fit-corpus worker process died (out of memory or killed); finished clips are "
                           "cached, rerun to resume") from exc
    finally:
        for future in running:
            future.cancel()


def run_fit_corpus(
    job: FitJob,
    executor: Executor | None = None,
    clips: Iterable[Clip] | None = None,
    progress: bool = True,
    on_outcome: Callable[[ClipOutcome], None] | None = None,
    ctx: FitContext | None = None,
) -> FitCorpusReport:
    """List the corpus (unless ``clips`` are given), process every clip on ``executor`` (default: the one of
    ``fit_corpus.executor``, :func:`m3t.fitting.cluster.open_executor`: a pool of ``fit_corpus.workers``
    processes, this process for one worker, or a Dask cluster) and consolidate the shards; the rows the listing
    refused are reported as quarantined. ``ctx`` (in-process runs only) reuses a built model."""
    from contextlib import ExitStack

    from tqdm.auto import tqdm

    from m3t.fitting.cluster import open_executor

    start = time.perf_counter()
    outcomes: list[ClipOutcome] = []
    if clips is None:
        listing = list_corpus(job)
        clips, outcomes = listing.clips, listing_outcomes(listing)
    clips = list(clips)
    layout = None
    kind = imported_kind(job.corpus)
    if kind is not None:  # already-fitted clips: the import's layout, clips it cannot shard together refused now
        layout, clips, refused = plan_import(kind, (ctx or worker_context(job)).import_settings, clips)
        outcomes += refused
    own = executor is None and ctx is None
    opened = ExitStack()  # the lock on the shards, then the run's own executor; released when the run ends or stops
    opened.enter_context(run_lock(Path(job.shards_dir) / LOCK_NAME, f"fit-corpus {job.corpus}"))
    try:
        executor = opened.enter_context(open_executor(job.run)) if own else executor
        with tqdm(total=len(clips), desc=f"fit-corpus {job.corpus}", unit="clip", disable=not progress) as bar:
            for outcome in _outcomes(job, clips, executor, ctx):
                outcomes.append(outcome)
                bar.update(1)
                bar.set_postfix(status=outcome.status,
                                quarantined=sum(o.status == "quarantined" for o in outcomes))
                if on_outcome is not None:
                    on_outcome(outcome)
        layout = layout or (ctx or worker_context(job)).body.layout
        return consolidate(outcomes, layout, job.shards_dir, job.corpus, time.perf_counter() - start)
    finally:
        opened.close()


def fit_and_log(job: FitJob, experiment, executor: Executor | None = None, progress: bool = True,
                on_outcome: Callable[[ClipOutcome], None] | None = None, log: bool = True) -> FitCorpusReport:
    """:func:`run_fit_corpus`, then the MLflow run of the corpus (params, results, quality, pictures)."""
    from m3t.experiment import section_params
    from m3t.fitting.report import log_fit_corpus

    report = run_fit_corpus(job, executor, progress=progress, on_outcome=on_outcome)
    if log:
        ctx = worker_context(job)
        kind = imported_kind(job.corpus)
        # pictures need the body model and full-body streams: none for face-only or slt feature shards
        render = job.run.render_clips if kind in (None, "smplx_params") else 0
        # a simulated corpus is configured by the simulated tracker's section and drawn against its ground truth;
        # every other corpus by the fusion of external tracker outputs
        simulated = simulated_corpus(job.corpus)
        sections = {"body": job.body, "fitting": job.fitting, "fit_corpus": job.run,
                    **({"tracker": job.tracker} if simulated else {"fusion": job.fusion})}
        logged = {**section_params(**sections), "corpus": job.corpus,
                  f"corpora.{job.corpus}": {"root": job.source.root, "options": job.source.options},
                  "shards_dir": job.shards_dir}
        truth = (lambda clip: ground_truth(clip, ctx.corpus.root)) if simulated else None
        log_fit_corpus(experiment, logged, report, ctx.body if render else None, job.corpus, job.shards_dir,
                       job.run.cache_dir, render, truth)
    return report
