"""MLflow's own UI (the version installed, 3.17 when written) over a store written by the project's logger, in
headless Chromium: the experiment link opens on the runs table with the runs, not on the GenAI pages.

What decides the landing page (read in MLflow 3.17.2's UI bundle, mlflow/server/js/build):
- the experiment tag ``mlflow.experimentKind`` (which m3t.experiment.start_run sets) is *not* consulted while the
  UI's hard-coded ``workflowType`` feature flag is on, as it is in 3.17.2;
- the kind comes from ``workflowType``: the URL query parameter ``?workflowType=machine_learning|genai``, else
  the browser's localStorage ``mlflow.workflowType_v1`` (set when the user clicks "Model training" in the side
  bar), else ``genai``: Overview / Traces. Nothing on the server sets that default, so links to the experiment
  carry the parameter (:func:`m3t.experiment.ui_link`, printed by ``m3t up``);
- the runs table shows no parameter, metric or tag columns until the user picks them, or a saved view selects
  them: an experiment tag ``mlflow.sharedViewState.<id>`` (:func:`m3t.experiment.saved_view_tag`), listed under
  "Views" and opened by ``?viewStateShareKey=<id>``; start_run writes one (``RUNS_VIEW``) on the experiment.

One MLflow server per module (~10 s to start on two cores) over a temporary store; its process group is ended
afterwards. Screenshots land in the test artifacts folder (tests/browser.py).
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import pytest

from browser import browser, require_chromium  # noqa: F401 - browser: the fixture
from m3t.experiment import RUNS_VIEW, ExperimentConfig, saved_view_tag, start_run, ui_link

# MLflow's UI asks who is signed in; a server without the basic-auth app answers 404 (MLflow's own request).
MLFLOW_OWN_404 = "/ajax-api/2.0/mlflow/users/current: HTTP 404"
RUNS = ({"variant": "fsq", "quantizer": "fsq", "ablation.quantizer": "fsq"},
        {"variant": "vq", "quantizer": "vq", "ablation.quantizer": "vq"})
PARAM, TAG, METRIC = "tokenizers.codebook", "ablation.quantizer", "recon_jpe_mm"


def call(base_url: str, path: str, body: dict | None = None) -> dict:
    data = json.dumps(body).encode() if body is not None else None
    request = urllib.request.Request(f"{base_url}{path}", data=data, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as response:
        return json.loads(response.read() or b"{}")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """An MLflow server over a store holding two train-tokenizers runs logged by m3t.experiment:
    ``{"url", "experiment_id", "run_names", "experiment_tags"}``."""
    require_chromium()  # before the slow part: without a browser there is nothing to look at
    root = tmp_path_factory.mktemp("mlflow_ui")
    cfg = ExperimentConfig(tracking_uri=f"sqlite:///{root / 'mlflow.db'}", artifact_dir=str(root / "mlruns"),
                           experiment="m3t")
    for i, tags in enumerate(RUNS):
        with start_run(cfg, "train-tokenizers", root=root, tags=tags, variant=tags["variant"]) as run:
            run.log_params({PARAM: 512 * (i + 1)})
            run.log_metrics({METRIC: 12.5 + 1.25 * i})
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env["MLFLOW_SERVER_ENABLE_JOB_EXECUTION"] = "false"
    log = root / "server.log"
    with open(log, "wb") as out:
        process = subprocess.Popen(
            [sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(port), "--workers", "1",
             "--backend-store-uri", cfg.tracking_uri, "--default-artifact-root", (root / "mlruns").as_uri()],
            stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 90
        while True:
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2):
                    break
            except OSError:
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"mlflow server did not answer at {url}/health; the end of {log}:\n"
                                       + "\n".join(log.read_text(errors="replace").splitlines()[-20:])) from None
                time.sleep(0.3)
        experiment = call(url, "/api/2.0/mlflow/experiments/get-by-name?experiment_name=m3t")["experiment"]
        runs = call(url, "/api/2.0/mlflow/runs/search", {"experiment_ids": [experiment["experiment_id"]]})["runs"]
        yield {"url": url, "experiment_id": experiment["experiment_id"],
               "run_names": sorted(r["info"]["run_name"] for r in runs),
               "experiment_tags": {t["key"]: t["value"] for t in experiment.get("tags", [])}}
    finally:
        for sig in (signal.SIGTERM, signal.SIGKILL):
            try:
                os.killpg(process.pid, sig)
                process.wait(10)
                break
            except ProcessLookupError:
                break
            except subprocess.TimeoutExpired:
                continue


def page_problems(page) -> list[str]:
    return page.console_errors + [f for f in page.failed_requests if MLFLOW_OWN_404 not in f]


RUN_LINKS = "[...document.querySelectorAll('a')].map(a => a.textContent.trim())"
HEADERS = "[...document.querySelectorAll('[role=columnheader]')].map(h => h.textContent.trim())"


def test_experiment_link_opens_on_the_runs_table(browser, server):  # noqa: F811
    assert server["experiment_tags"]["mlflow.experimentKind"] == "custom_model_development"  # set by start_run
    assert len(server["run_names"]) == 2 and all(n.startswith("train-tokenizers") for n in server["run_names"])
    browser.goto(ui_link(server["url"], server["experiment_id"], view=None))
    names = json.dumps(server["run_names"])
    browser.wait_for(f"{names}.every(n => {RUN_LINKS}.includes(n))", timeout=45)
    browser.screenshot("mlflow_runs.png")
    assert browser.evaluate("location.hash").startswith(f"#/experiments/{server['experiment_id']}/runs?")
    assert "Run Name" in browser.evaluate(HEADERS)
    text = browser.evaluate("document.body.innerText")
    assert "2 matching runs" in text and "Token Usage" not in text and "Detect Issues" not in text
    assert page_problems(browser) == []


def test_plain_link_still_opens_genai_pages(browser, server):  # noqa: F811
    """MLflow 3.17 ignores ``mlflow.experimentKind``: a fresh browser opening the plain experiment link lands on
    the GenAI overview. When this fails, the UI honours the tag again and links need no workflowType."""
    browser.goto(f"{server['url']}/#/experiments/{server['experiment_id']}")
    browser.wait_for("location.hash.includes('/overview') || location.hash.includes('/runs')", timeout=45)
    assert "/overview" in browser.evaluate("location.hash")


def test_the_projects_saved_view_shows_stage_and_variant_columns(browser, server):  # noqa: F811
    """The link ``m3t up`` prints opens the view start_run wrote on the experiment: stage / variant columns."""
    assert f"mlflow.sharedViewState.{RUNS_VIEW}" in server["experiment_tags"]
    browser.goto(ui_link(server["url"], server["experiment_id"]))
    browser.wait_for(f"{HEADERS}.includes('variant') && {RUN_LINKS}.includes({json.dumps(server['run_names'][0])})",
                     timeout=45)
    browser.screenshot("mlflow_runs_m3t_view.png")
    headers = browser.evaluate(HEADERS)
    assert {"stage", "variant", "quantizer"} <= set(headers), headers
    text = browser.evaluate("document.body.innerText")
    assert "train-tokenizers" in text and "fsq" in text and "vq" in text
    assert page_problems(browser) == []


def test_saved_view_shows_params_metrics_and_tags(browser, server):  # noqa: F811
    columns = ["attributes.`Duration`", f"params.`{PARAM}`", f"metrics.`{METRIC}`", f"tags.`{TAG}`"]
    key, value = saved_view_tag("m3t", "m3t ablations", tuple(columns), int(time.time() * 1000))
    call(server["url"], "/api/2.0/mlflow/experiments/set-experiment-tag",
         {"experiment_id": server["experiment_id"], "key": key, "value": value})
    browser.goto(ui_link(server["url"], server["experiment_id"], view="m3t"))
    browser.wait_for(f"{HEADERS}.includes('{TAG}') && {RUN_LINKS}.includes({json.dumps(server['run_names'][0])})",
                     timeout=45)
    browser.screenshot("mlflow_runs_view.png")
    headers = browser.evaluate(HEADERS)
    assert {"Parameters", "Metrics", "Tags", PARAM, METRIC, TAG} <= set(headers), headers
    text = browser.evaluate("document.body.innerText")
    assert all(value in text for value in ("512", "1024", "fsq", "vq", "12.5", "13.75")), text
    # the tag was read as a saved view (a malformed one would still apply its columns, as an unnamed shared view)
    assert browser.evaluate("document.querySelector('[data-testid=saved-views-trigger]').textContent") \
        == "m3t ablations"
    assert page_problems(browser) == []
