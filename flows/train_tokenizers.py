"""Prefect flow ``train-tokenizers``: fitted shards -> FSQ-VAE tokenizers (logged to MLflow) -> token shards.

Thin tasks over :mod:`m3t.tokenizers.pipeline` and :mod:`m3t.tokenizers.tokenize`; training resumes from
its own cache after an interruption, so the task is not retried; tokenisation (I/O) is.
"""
from __future__ import annotations

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from m3t.config import Params, load_params
from m3t.experiment import extra_tags
from m3t.shards.folders import DataConfig
from m3t.stages import shards_version
from m3t.tokenizers.pipeline import train_and_log
from m3t.tokenizers.tokenize import run_tokenize


@task(cache_policy=NO_CACHE)
def train_tokenizers(params: Params) -> dict:
    return train_and_log(params.tokenizer, params.tokenizer_train, params.body, params.data, params.experiment,
                         progress=False)


@task(retries=1, retry_delay_seconds=2, cache_policy=NO_CACHE)
def tokenize(data: DataConfig) -> dict:
    return run_tokenize(data)


@flow(name="train-tokenizers", log_prints=True)
def train_tokenizers_flow(params_path: str = "params.yaml", preset: str = "default") -> dict:
    """Train the body / hand / face tokenizers, then write token shards for every split."""
    logger = get_run_logger()
    params = load_params(params_path, preset=preset)
    with extra_tags(shards_version(params)):  # runs tagged with the shards they read
        report = train_tokenizers(params)
    for group, values in report.items():
        logger.info("%s: PA-VPE %.2f mm, utilisation %.1f%%", group, values.get("test_pa_vpe_mm", float("nan")),
                    values["utilisation_pct"])
    summary = tokenize(params.data)
    logger.info("token shards: %s", summary)
    return {"tokenizers": report, "tokens": summary}
