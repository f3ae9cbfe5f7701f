"""Prefect flow ``fit-corpus``: one task over the corpus-fitting engine (:func:`m3t.fitting.corpus.fit_and_log`),
the same orchestration path as the DVC stage: clips are fitted on the executor of ``fit_corpus.executor``
(:func:`m3t.fitting.cluster.open_executor`: ``fit_corpus.workers`` local processes, or a Dask cluster at
``fit_corpus.dask_address`` or started for the run; ``executor=`` takes any ``concurrent.futures.Executor``-like
runner instead), each clip's outcome is logged as it completes, shards and reports are consolidated.

Per-clip failures are quarantined by the engine, not retried; the engine resumes from its per-clip cache, so
the task is retried once on a failure of the run itself (a worker killed, a disk hiccup).
"""
from __future__ import annotations

import dataclasses

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from m3t.config import load_params
from m3t.fitting.corpus import FitJob, fit_and_log
from m3t.fitting.report import ClipOutcome, FitCorpusReport


@task(retries=1, retry_delay_seconds=2, cache_policy=NO_CACHE)
def fit_corpus_task(job: FitJob, experiment, log_mlflow: bool, executor=None) -> FitCorpusReport:
    logger = get_run_logger()
    done = [0]

    def logged(outcome: ClipOutcome) -> None:
        done[0] += 1
        logger.info("[%d] %s %s %s", done[0], outcome.clip_id, outcome.status, outcome.reason or "")

    return fit_and_log(job, experiment, executor, progress=False, on_outcome=logged, log=log_mlflow)


@flow(name="fit-corpus", log_prints=True)
def fit_corpus(params_path: str = "params.yaml", preset: str = "default", max_clips: int = -1, log_mlflow: bool = True,
               corpus: str = "", executor=None) -> dict:
    """Fit every clip of ``corpus`` (a name of ``corpora`` in params.yaml; "" = ``fit_corpus.default_corpus``)
    into Parquet shards; returns the results summary with the quality summary under ``quality``."""
    params = load_params(params_path, preset=preset)
    job = params.fit_job(corpus or None)
    if max_clips >= 0:
        job = dataclasses.replace(job, run=dataclasses.replace(job.run, max_clips=max_clips))
    report = fit_corpus_task(job, params.experiment, log_mlflow, executor)
    get_run_logger().info("fit-corpus %s: %s; run: %s; quality: %s", job.corpus, report.summary, report.run_stats,
                          report.quality)
    return {**report.summary, "quality": report.quality}
