"""Deployments and the nightly re-evaluation on a real local Prefect server: ``m3t up``'s engine serves every
deployment over a tiny pipeline's workspace, ``evaluate/nightly`` is registered with its cron schedule, and
triggering it by name re-evaluates every model family present (MLflow runs tagged ``scheduled``), skips the absent
ones with the stage to run, and rebuilds the dashboard."""
from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest

from m3t.experiment import fetch_runs

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def served(tiny_workspace, tmp_path_factory):
    from cli.services import ServicesConfig, down, up

    run_dir = tmp_path_factory.mktemp("services")
    cfg = ServicesConfig(run_dir=run_dir, params=tiny_workspace.params_file, prefect_port=free_port(),
                         mlflow_port=free_port(), root=ROOT, start_timeout_s=180)
    records = up(cfg, say=lambda _: None)
    try:
        yield {r.name: r for r in records}
    finally:
        down(run_dir, say=lambda _: None)


def test_every_deployment_is_served_and_nightly_completes(served, tiny_workspace):
    import anyio
    from prefect.client.orchestration import get_client
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_URL, temporary_settings

    api = served["prefect"].url + "/api"
    with temporary_settings({PREFECT_API_URL: api}):
        async def deployments():
            async with get_client() as client:
                return {f"{(await client.read_flow(d.flow_id)).name}/{d.name}": d for d in await client.read_deployments()}

        found = {}
        for _ in range(60):  # the runner registers them a moment after the server answers
            found = anyio.run(deployments)
            if "evaluate/nightly" in found:
                break
            time.sleep(1)
        corpora = tiny_workspace.params.corpora
        expected = {"fit-corpus/embedded", *(f"fit-corpus/{c}" for c in corpora), "train-tokenizers/embedded",
                    "backtranslation/embedded", "smlm/embedded", "evaluate-smlm/embedded", "slr/embedded",
                    "sgsa/embedded", "evaluate/nightly"}
        assert expected <= set(found), sorted(found)
        nightly = found["evaluate/nightly"]
        assert [s.schedule.cron for s in nightly.schedules] == ["0 3 * * *"]
        assert nightly.parameters["params_path"] == str(tiny_workspace.params_file.resolve())
        run = run_deployment("evaluate/nightly", timeout=600)
    assert run.state.is_completed(), run.state
    scheduled = [r for r in fetch_runs(tiny_workspace.params.experiment) if r.tags.get("scheduled") == "true"]
    assert {r.stage for r in scheduled} == {"evaluate-tokenizers", "evaluate-backtranslation", "evaluate-smlm"}
    assert all(r.status == "FINISHED" and r.tags["mlflow.runName"].endswith("· scheduled") for r in scheduled)
    index = Path(tiny_workspace.params.experiment.dashboard_dir) / "index.html"
    assert index.exists() and "evaluate-tokenizers" in index.read_text()
