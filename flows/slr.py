"""Prefect flow of the recognition probe (M3T Sec. 3.4, Tab. 4).

- ``slr``: train-slr (full probe and face-less ablation on frozen tokenizer features) -> evaluate-slr
  (deployment ``slr/embedded``).

Thin tasks over :mod:`m3t.slr.pipeline`, the functions the DVC stages call; training is not retried (a
failure there is not transient), the evaluation task is (it reads and writes files).
"""
from __future__ import annotations

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from m3t.config import Params, load_params
from m3t.experiment import extra_tags
from m3t.slr import pipeline
from m3t.stages import shards_version


@task(cache_policy=NO_CACHE)
def train_slr(params: Params) -> dict:
    return pipeline.train_and_log(params.slr, params.slr_train, params.body, params.data, params.experiment,
                                  progress=False)


@task(retries=1, retry_delay_seconds=2, cache_policy=NO_CACHE)
def evaluate_slr(params: Params) -> dict:
    return pipeline.evaluate_and_log(params.slr_evaluate, params.body, params.data, params.experiment,
                                     corpus=params.slr.corpus)


@flow(name="slr", log_prints=True)
def slr_flow(params_path: str = "params.yaml", preset: str = "default") -> dict:
    """Train the recognition probes on ``slr.corpus``, then score them on ``slr_evaluate.split``."""
    params = load_params(params_path, preset=preset)
    with extra_tags(shards_version(params)):  # runs tagged with the shards they read
        report = train_slr(params)
        summary = evaluate_slr(params)
    headline = {k: round(v, 1) for k, v in summary.items() if k.endswith(("/top1",)) and "overall" in k}
    get_run_logger().info("slr %s: %s", params.slr.corpus, headline)
    return {"train": report, "evaluation": summary}
