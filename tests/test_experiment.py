"""MLflow through m3t.experiment: absolute URIs, a logged run comes back with its metrics and artifacts."""
from __future__ import annotations

from pathlib import Path

from dashboards.report import render
from m3t.experiment import ExperimentConfig, RunRecord, absolute_uri, fetch_runs, start_run


def test_absolute_uri(tmp_path):
    assert absolute_uri("sqlite:///mlflow.db", tmp_path) == f"sqlite:///{tmp_path.resolve()}/mlflow.db"
    assert absolute_uri("sqlite:////abs/x.db", tmp_path) == "sqlite:////abs/x.db"
    assert absolute_uri("mlruns", tmp_path).startswith("file://")
    assert absolute_uri("http://127.0.0.1:5000", tmp_path) == "http://127.0.0.1:5000"


def test_run_is_logged_and_fetched(tmp_path):
    cfg = ExperimentConfig(tracking_uri="sqlite:///store.db", artifact_dir="artifacts", experiment="t")
    picture = tmp_path / "fit.png"
    picture.write_bytes(b"\x89PNG\r\n\x1a\n")
    with start_run(cfg, "fit-corpus", root=tmp_path) as run:
        run.log_params({"fitting.iterations": 3})
        run.log_metrics({"reproj_px_mean": 1.5, "nan_metric": float("nan")})
        run.log_artifact(picture, "fit_vs_ground_truth")
    runs = fetch_runs(cfg, root=tmp_path, stage="fit-corpus")
    assert len(runs) == 1
    assert runs[0].metrics == {"reproj_px_mean": 1.5}  # NaN is not logged
    assert runs[0].params == {"fitting.iterations": "3"}
    assert (runs[0].artifact_dir / "fit_vs_ground_truth" / "fit.png").exists()
    page = render(runs)
    assert "fit-corpus" in page and "1.5" in page and "data:image/png;base64" in page


def test_disabled_tracking_is_a_noop(tmp_path):
    with start_run(ExperimentConfig(enabled=False), "x", root=tmp_path) as run:
        run.log_metrics({"a": 1.0})
        assert run.run_id is None
    assert not list(tmp_path.iterdir())


def test_dashboard_without_runs():
    assert "No runs yet" in render([])
    record = RunRecord("abc", "stage", 0, "FINISHED", {}, {"m": 2.0}, Path("/nonexistent"))
    assert "stage" in render([record])
