"""Prefect flow ``evaluate``: re-evaluate every current checkpoint, then rebuild the dashboard.

Deployment ``evaluate/nightly`` runs it on a cron schedule (``m3t up`` / ``python -m flows.deploy``). Each model
family whose checkpoints are in place is evaluated on its configured split(s) by the same library function its
DVC stage calls, and logs one MLflow run tagged ``scheduled=true`` (run name ``<stage> · <variant> ·
scheduled``); a family without checkpoints is reported as skipped with the stage that makes them. Order: the
tokenizers, the back-translation judges (ground-truth upper bound), the SMLM (generation + scoring), the
recognition probes, the skeletal models (PT, SGSA). A family that fails is reported and the others still run.
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from dashboards.build import build_dashboard
from m3t.backtranslation import pipeline as backtranslation
from m3t.config import Params, load_params
from m3t.experiment import extra_tags
from m3t.sgsa import pipeline as sgsa
from m3t.slr import pipeline as slr
from m3t.smlm.evaluate_run import evaluate_and_log as evaluate_smlm
from m3t.smlm.generate_run import generate as generate_smlm
from m3t.stages import shards_version
from m3t.tokenizers import pipeline as tokenizers

SCHEDULED = {"scheduled": "true"}


def _has(folder: Path, pattern: str = "*.pt") -> bool:
    return folder.is_dir() and any(folder.glob(pattern))


def _families(params: Params) -> list[tuple[str, str, bool, Callable[[], dict]]]:
    """(family, the stage that makes its checkpoints, checkpoints present, evaluation) in evaluation order."""
    p, data = params, params.data

    def smlm_evaluation() -> dict:
        generate_smlm(p.smlm_generate, data, p.body, progress=False)
        return evaluate_smlm(p.smlm_generate, data, p.body, p.experiment, p.backtranslation)

    return [
        ("tokenizers", "train-tokenizers", _has(data.tokenizers_dir),
         lambda: tokenizers.evaluate_and_log(p.tokenizer_train, p.body, data, p.experiment)),
        ("backtranslation", "train-backtranslation", _has(data.backtranslation_dir),
         lambda: backtranslation.evaluate_and_log(p.backtranslation, data, p.experiment)),
        ("smlm", "train-smlm", (data.smlm_dir / "smlm.pt").exists() and _has(data.tokenizers_dir), smlm_evaluation),
        ("slr", "train-slr", _has(data.slr_dir),
         lambda: slr.evaluate_and_log(p.slr_evaluate, p.body, data, p.experiment, corpus=p.slr.corpus)),
        ("sgsa", "train-sgsa", _has(data.sgsa_dir),
         lambda: sgsa.evaluate_and_log(p.sgsa, p.sgsa_evaluate, p.body, data, p.experiment, p.backtranslation)),
    ]


@task(retries=1, retry_delay_seconds=2, cache_policy=NO_CACHE)
def evaluate_family(name: str, evaluation: Callable[[], dict]) -> dict:
    with extra_tags(SCHEDULED):
        return evaluation()


@task(cache_policy=NO_CACHE)
def rebuild_dashboard(params: Params) -> str:
    return str(build_dashboard(params))


@flow(name="evaluate", log_prints=True)
def evaluate_flow(params_path: str = "params.yaml", preset: str = "default", dashboard: bool = True) -> dict:
    """Evaluate every model family whose checkpoints exist (runs tagged ``scheduled``), then rebuild the
    dashboard in ``experiment.dashboard_dir`` (unless ``dashboard`` is false). Returns ``{family: "evaluated" |
    "skipped: ..." | "failed: ..."}`` with the dashboard's index page under ``dashboard``."""
    logger = get_run_logger()
    params = load_params(params_path, preset=preset)
    outcome: dict[str, str] = {}
    for name, stage, present, evaluation in _families(params):
        if not present:
            outcome[name] = f"skipped: no checkpoint (run the {stage} stage)"
            logger.info("%s: %s", name, outcome[name])
            continue
        with extra_tags(shards_version(params)):  # runs tagged with the shards they read
            state = evaluate_family.with_options(name=f"evaluate-{name}")(name, evaluation, return_state=True)
        if state.is_completed():
            outcome[name] = "evaluated"
            logger.info("%s: evaluated", name)
        else:
            outcome[name] = f"failed: {state.message}"
            logger.error("%s: %s", name, outcome[name])
    if dashboard:
        outcome["dashboard"] = rebuild_dashboard(params)
    if any(v.startswith("failed") for v in outcome.values()):
        raise RuntimeError(f"re-evaluation failed for: {', '.join(k for k, v in outcome.items() if v.startswith('failed'))}"
                           f" ({outcome})")
    return outcome
