"""Prefect flow ``train-tokenizers``: fitted shards -> FSQ-VAE tokenizers (logged to MLflow) -> token shards.

Thin tasks over :mod:`m3t.stages.train_tokenizers` and :mod:`m3t.stages.tokenize`; training resumes from
its own cache after an interruption, so the task is not retried; tokenisation (I/O) is.
"""
from __future__ import annotations

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from m3t.config import Params, load_params
from m3t.stages import tokenize as tokenize_stage
from m3t.stages import train_tokenizers as train_stage


@task(cache_policy=NO_CACHE)
def train_tokenizers(params: Params) -> dict:
    return train_stage.train_and_log(params, progress=False)


@task(retries=1, retry_delay_seconds=2, cache_policy=NO_CACHE)
def tokenize(cfg: tokenize_stage.TokenizeConfig) -> dict:
    return tokenize_stage.run_tokenize(cfg)


@flow(name="train-tokenizers", log_prints=True)
def train_tokenizers_flow(params_path: str = "params.yaml", preset: str = "default") -> dict:
    """Train the body / hand / face tokenizers, then write token shards for every split."""
    logger = get_run_logger()
    params = load_params(params_path, preset=preset)
    report = train_tokenizers(params)
    for group, values in report.items():
        logger.info("%s: PA-VPE %.2f mm, utilisation %.1f%%", group, values.get("test_pa_vpe_mm", float("nan")),
                    values["utilisation_pct"])
    summary = tokenize(params.tokenize)
    logger.info("token shards: %s", summary)
    return {"tokenizers": report, "tokens": summary}
