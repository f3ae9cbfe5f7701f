"""Prefect flow ``fit-corpus``: list a corpus' clips -> (track + fit + write part) per clip in parallel ->
shards + the data-quality report (``quality.csv`` / ``quality.json``).

Tasks are thin wrappers over :mod:`m3t.stages.fit_corpus`; retries only on the I/O tasks (listing and
consolidation); per-clip failures are quarantined by the library, not retried.
"""
from __future__ import annotations

from prefect import flow, get_run_logger, task, unmapped
from prefect.cache_policies import NO_CACHE
from prefect.task_runners import ThreadPoolTaskRunner

from m3t.config import load_params
from m3t.corpora.base import Listing
from m3t.stages import fit_corpus as stage


# The library content-addresses its results itself; Prefect's input hashing would hash the body model.
@task(retries=2, retry_delay_seconds=2, cache_policy=NO_CACHE)
def list_corpus(cfg: stage.FitCorpusConfig) -> Listing:
    return stage.list_corpus(cfg)


@task(cache_policy=NO_CACHE)
def process_clip(clip, ctx: stage.FitContext) -> stage.ClipOutcome:
    return stage.process_clip(clip, ctx)


@task(retries=1, retry_delay_seconds=2, cache_policy=NO_CACHE)
def consolidate(outcomes: list[stage.ClipOutcome], ctx: stage.FitContext, wall_seconds: float) -> stage.FitCorpusReport:
    return stage.consolidate(outcomes, ctx.body.layout, ctx.cfg, wall_seconds)


@flow(name="fit-corpus", task_runner=ThreadPoolTaskRunner(max_workers=2), log_prints=True)
def fit_corpus(params_path: str = "params.yaml", preset: str = "default", max_clips: int = -1, log_mlflow: bool = True,
               corpus: str = "") -> dict:
    """Fit every clip of ``corpus`` (a name of ``corpora`` in params.yaml; "" = ``fit_corpus.corpus``) into
    Parquet shards; returns the run summary with the quality summary under ``quality``."""
    import dataclasses
    import time

    logger = get_run_logger()
    params = load_params(params_path, preset=preset)
    cfg = stage.for_corpus(params, corpus or None)
    cfg = cfg if max_clips < 0 else dataclasses.replace(cfg, max_clips=max_clips)
    ctx = stage.FitContext(cfg, params.body, params.tracker, params.fitting)
    ctx.body  # build the body model once, before worker threads share it
    start = time.perf_counter()
    listing = list_corpus(cfg)
    clips = list(listing.clips)
    for q in listing.quarantined:
        logger.warning("listing quarantined %s row %s (%s): %s", q.file, q.row, q.clip_id, q.reason)
    futures = process_clip.map(clips, ctx=unmapped(ctx))
    outcomes = stage.listing_outcomes(listing)
    for i, future in enumerate(futures, 1):
        outcome = future.result()
        outcomes.append(outcome)
        logger.info("[%d/%d] %s %s %s", i, len(clips), outcome.clip_id, outcome.status, outcome.reason or "")
    report = consolidate(outcomes, ctx, time.perf_counter() - start)
    if log_mlflow:
        stage.log_report(params, ctx, report)
    logger.info("fit-corpus summary: %s; quality: %s", report.summary, report.quality)
    return {**report.summary, "quality": report.quality}
