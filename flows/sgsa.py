"""Prefect flow of the skeletal production models (SGSA and its Progressive Transformers baseline).

- ``sgsa``: train-backtranslation-skeleton (the skeleton judge) -> train-sgsa (PT + SGSA) -> evaluate-sgsa (SGSA
  Tab. 1-3 numbers with the SMLM and the ground truth on the same split and judges; deployment ``sgsa/embedded``).

Thin tasks over :mod:`m3t.sgsa.pipeline` and :mod:`m3t.backtranslation.pipeline`, the functions the DVC stages
call; training is not retried (a failure there is not transient), the evaluation task is (it reads and writes files).
"""
from __future__ import annotations

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from m3t.backtranslation.pipeline import SkeletonInput
from m3t.backtranslation.pipeline import train_and_log as train_judge
from m3t.body.factory import load_body_model
from m3t.body.skeleton import graph_for
from m3t.config import Params, load_params
from m3t.experiment import extra_tags
from m3t.sgsa import pipeline
from m3t.stages import shards_version


@task(cache_policy=NO_CACHE)
def train_skeleton_judge(params: Params) -> dict:
    skeleton = SkeletonInput(load_body_model(params.body), graph_for(params.sgsa.skeleton, params.sgsa.face_points))
    return train_judge(params.backtranslation, params.backtranslation_train, params.data, params.experiment,
                       progress=False, skeleton=skeleton)


@task(cache_policy=NO_CACHE)
def train_sgsa(params: Params) -> dict:
    return pipeline.train_and_log(params.sgsa, params.sgsa_train, params.body, params.data, params.experiment,
                                  progress=False)


@task(retries=1, retry_delay_seconds=2, cache_policy=NO_CACHE)
def evaluate_sgsa(params: Params) -> dict:
    return pipeline.evaluate_and_log(params.sgsa, params.sgsa_evaluate, params.body, params.data, params.experiment,
                                     params.backtranslation)


@flow(name="sgsa", log_prints=True)
def sgsa_flow(params_path: str = "params.yaml", preset: str = "default", train_judge: bool = True) -> dict:
    """Train the skeleton judge (unless ``train_judge`` is false), PT and SGSA, then score them with the SMLM."""
    params = load_params(params_path, preset=preset)
    with extra_tags(shards_version(params)):  # runs tagged with the shards they read
        judge = train_skeleton_judge(params) if train_judge else {}
        report = train_sgsa(params)
        summary = evaluate_sgsa(params)
    headline = {k: round(v, 4) for k, v in summary.items() if k.endswith("/test/dtw_jpe_mean_m")}
    get_run_logger().info("sgsa %s: %s", params.sgsa.variant, headline)
    return {"judge": judge, "train": report, "evaluation": summary}
