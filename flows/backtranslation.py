"""Prefect flow of the back-translation judge (M3T App. 0.D.4, Tab. 2).

- ``backtranslation``: train-backtranslation (one sign-to-text model per sign language, on the ground-truth
  motion of ``data.train_corpora``) -> evaluate-backtranslation (the ground-truth upper bound on the test
  split) (deployment ``backtranslation/embedded``). Production models are scored through the same judge by
  their own evaluation (``evaluate-smlm``).

Thin tasks over :mod:`m3t.backtranslation.pipeline`, the functions the DVC stages call.
"""
from __future__ import annotations

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from m3t.backtranslation import pipeline
from m3t.config import Params, load_params
from m3t.experiment import extra_tags
from m3t.stages import shards_version


@task(cache_policy=NO_CACHE)
def train_backtranslation(params: Params) -> dict:
    return pipeline.train_and_log(params.backtranslation, params.backtranslation_train, params.data,
                                  params.experiment, progress=False)


@task(retries=1, retry_delay_seconds=2, cache_policy=NO_CACHE)
def evaluate_backtranslation(params: Params) -> dict:
    return pipeline.evaluate_and_log(params.backtranslation, params.data, params.experiment)


@flow(name="backtranslation", log_prints=True)
def backtranslation_flow(params_path: str = "params.yaml", preset: str = "default") -> dict:
    """Train the back-translation judges, then score the ground-truth motion of the test split with them."""
    params = load_params(params_path, preset=preset)
    with extra_tags(shards_version(params)):  # runs tagged with the shards they read
        report = train_backtranslation(params)
        summary = evaluate_backtranslation(params)
    headline = {k: round(v, 2) for k, v in summary.items() if k in ("slt_bleu4", "slt_rouge_l")}
    get_run_logger().info("back-translation upper bound (SL-T definition): %s", headline)
    return {"train": report, "evaluation": summary}
