"""``m3t study``: every variant and seed that the papers' claims (:mod:`m3t.claims`) need, run as DVC experiments
(:mod:`cli.variants`, planned by :mod:`cli.study_plan`) on the workspace's ``params.yaml`` with a preset, then the
claims judged on their MLflow runs.

It writes ``<out>/logs/<variant>.log``, ``<out>/timings.json``, ``<out>/claims.{json,md}`` and the study's dashboard
``<out>/dashboard``; the experiments themselves are DVC's (``dvc exp show``), their outputs in DVC's cache.

Resuming is DVC's: a second run restores every stage that already ran with the same settings from the run cache
(a killed training resumes from its last checkpoint in the shared caches), so only what changed or never finished
runs. A failed variant is reported; the others still run.
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

from cli.study_plan import parse_settings, plan, select, with_settings
from cli.variants import Runner, run_logged, run_variants, tracking_env, unflatten, workspace_of
from m3t.atomic import write_json
from m3t.claims.report import claims_markdown, write_claims
from m3t.config import load_params
from m3t.experiment import fetch_runs


def study(params_path: str | Path, preset: str, seeds: Sequence[int], out: str | Path | None = None,
          dry_run: bool = False, only: Sequence[str] = (), claims: bool = True, settings: Sequence[str] = (),
          runner: Runner = run_logged) -> int:
    """``m3t study``: plan, run (or with ``dry_run`` print the commands), judge the claims; 1 when a variant failed."""
    workspace = workspace_of(params_path)
    out = Path(out or Path("studies") / preset)
    extra = parse_settings(settings)
    params = load_params(params_path, preset=preset, overrides=unflatten(extra))  # what every variant starts from
    variants = with_settings(select(plan(params, seeds, f"{params_path} + preset {preset}"), only), extra)
    print(f"study {preset!r}, seeds {' '.join(map(str, seeds))}: {len(variants)} DVC experiments; logs under {out}")
    if not params.experiment.enabled:
        print(f"note: experiment.enabled is false in {params_path} + preset {preset}: the stages log no MLflow runs, "
              "so no claim can be judged")
    env = {} if dry_run else tracking_env(params.experiment, workspace)
    start = time.monotonic()
    summary = run_variants(variants, workspace, out / "logs", preset=preset, env=env, dry_run=dry_run,
                           runner=runner)
    if dry_run:
        return 0
    write_json(out / "timings.json", {"total_s": round(time.monotonic() - start, 1), "variants": [
        {"variant": v.name, "status": "failed" if v.name in summary.failed else "ok",
         "seconds": round(summary.seconds.get(v.name, 0.0), 1), "detail": summary.failed.get(v.name, "")}
        for v in variants]})
    for name, detail in summary.failed.items():
        print(f"  failed: {name}: {detail}")
    if claims and params.experiment.enabled:
        # the verdicts need 3 seeds whatever was asked for: a study with fewer seeds reads inconclusive
        rows = write_claims(fetch_runs(params.experiment, workspace), out)
        print(claims_markdown(rows, 3))
        print(f"written: {out / 'claims.json'}, {out / 'claims.md'}")
        from dashboards.build import build_dashboard

        print(f"dashboard of the study: {build_dashboard(params, out / 'dashboard', workspace)}")
    return 0 if summary.ok else 1
