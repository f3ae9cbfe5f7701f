"""Prefect flow ``fit-corpus``: list clips -> (track + fit + write part) per clip in parallel -> shards.

Tasks are thin wrappers over :mod:`m3t.stages.fit_corpus`; retries only on the I/O tasks (listing and
consolidation); per-clip failures are quarantined by the library, not retried.
"""
from __future__ import annotations

from prefect import flow, get_run_logger, task, unmapped
from prefect.cache_policies import NO_CACHE
from prefect.task_runners import ThreadPoolTaskRunner

from m3t.config import load_params
from m3t.corpora.clip import Clip
from m3t.stages import fit_corpus as stage


# The library content-addresses its results itself; Prefect's input hashing would hash the body model.
@task(retries=2, retry_delay_seconds=2, cache_policy=NO_CACHE)
def list_clips(cfg: stage.FitCorpusConfig) -> list[Clip]:
    return stage.list_clips(cfg)


@task(cache_policy=NO_CACHE)
def process_clip(clip: Clip, ctx: stage.FitContext) -> stage.ClipOutcome:
    return stage.process_clip(clip, ctx)


@task(retries=1, retry_delay_seconds=2, cache_policy=NO_CACHE)
def consolidate(outcomes: list[stage.ClipOutcome], ctx: stage.FitContext, wall_seconds: float) -> stage.FitCorpusReport:
    return stage.consolidate(outcomes, ctx.body.layout, ctx.cfg, wall_seconds)


@flow(name="fit-corpus", task_runner=ThreadPoolTaskRunner(max_workers=2), log_prints=True)
def fit_corpus(params_path: str = "params.yaml", preset: str = "default", max_clips: int = -1, log_mlflow: bool = True) -> dict:
    """Fit every clip of the configured corpus into Parquet shards; returns the run summary."""
    import dataclasses
    import time

    logger = get_run_logger()
    params = load_params(params_path, preset=preset)
    cfg = params.fit_corpus if max_clips < 0 else dataclasses.replace(params.fit_corpus, max_clips=max_clips)
    ctx = stage.FitContext(cfg, params.body, params.tracker, params.fitting)
    ctx.body  # build the body model once, before worker threads share it
    start = time.perf_counter()
    clips = list_clips(cfg)
    futures = process_clip.map(clips, ctx=unmapped(ctx))
    outcomes = []
    for i, future in enumerate(futures, 1):
        outcome = future.result()
        outcomes.append(outcome)
        logger.info("[%d/%d] %s %s %s", i, len(clips), outcome.clip_id, outcome.status, outcome.reason or "")
    report = consolidate(outcomes, ctx, time.perf_counter() - start)
    if log_mlflow:
        stage.log_report(params, ctx, report)
    logger.info("fit-corpus summary: %s", report.summary)
    return report.summary
