"""Prefect flows of the Sign Motion Language Model.

- ``smlm``: token shards -> train-smlm -> generate-smlm -> evaluate-smlm (deployment ``smlm/embedded``);
- ``evaluate-smlm``: generate + evaluate with the current checkpoint only (deployment
  ``evaluate-smlm/embedded``; the nightly schedule re-evaluates every model family: ``evaluate/nightly``).

Thin tasks over the SMLM runs (:mod:`m3t.smlm.train_run`, :mod:`m3t.smlm.generate_run`, :mod:`m3t.smlm.evaluate_run`); training is not retried (a failure there is not transient), the
generation / evaluation tasks are (they read and write files).
"""
from __future__ import annotations

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from m3t.config import Params, load_params
from m3t.experiment import extra_tags
from m3t.smlm import evaluate_run, generate_run, train_run
from m3t.stages import shards_version


@task(cache_policy=NO_CACHE)
def train_smlm(params: Params) -> dict:
    return train_run.train_and_log(params.smlm, params.smlm_train, params.body, params.data, params.experiment,
                                  progress=False)


@task(retries=1, retry_delay_seconds=2, cache_policy=NO_CACHE)
def generate(params: Params) -> dict:
    return generate_run.generate(params.smlm_generate, params.data, params.body, progress=False)


@task(retries=1, retry_delay_seconds=2, cache_policy=NO_CACHE)
def evaluate(params: Params) -> dict:
    return evaluate_run.evaluate_and_log(params.smlm_generate, params.data, params.body, params.experiment,
                                     params.backtranslation)


def _headline(summary: dict) -> str:
    keys = ("dtw_jpe_body_m", "dtw_jpe_hand_m", "dtw_pa_jpe_body_m", "dtw_pa_jpe_hand_m", "translation_bleu4")
    return ", ".join(f"{k} {summary[k]:.3f}" for k in keys if k in summary)


@flow(name="evaluate-smlm", log_prints=True)
def evaluate_smlm_flow(params_path: str = "params.yaml", preset: str = "default") -> dict:
    """Generate with the current checkpoint and score it (logged to MLflow)."""
    params = load_params(params_path, preset=preset)
    with extra_tags(shards_version(params)):  # runs tagged with the shards they read
        generated = generate(params)
        summary = evaluate(params)
        get_run_logger().info("generated %s; %s", generated, _headline(summary))
        return summary


@flow(name="smlm", log_prints=True)
def smlm_flow(params_path: str = "params.yaml", preset: str = "default") -> dict:
    """Train the SMLM on the token shards, then generate and evaluate on the configured split."""
    params = load_params(params_path, preset=preset)
    with extra_tags(shards_version(params)):  # runs tagged with the shards they read
        report = train_smlm(params)
        get_run_logger().info("trained: best epoch %s", report.get("best_epoch"))
        generated = generate(params)
        summary = evaluate(params)
        get_run_logger().info("generated %s; %s", generated, _headline(summary))
        return {"train": report, "evaluation": summary}
