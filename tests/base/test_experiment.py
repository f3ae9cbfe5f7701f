"""MLflow through m3t.experiment: absolute URIs, a logged run comes back with its metrics and artifacts."""
from __future__ import annotations

from m3t.experiment import (EXPERIMENT_KIND, ExperimentConfig, absolute_uri, extra_tags, fetch_runs, metric_histories,
                            start_run)


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


def test_runs_are_named_tagged_and_the_experiment_opens_on_runs(tmp_path):
    """Run names ``stage · variant`` (``· scheduled`` inside :func:`extra_tags`), the variant and caller's tags on
    the run, per-epoch histories readable back, and the experiment marked as model development (MLflow 3's UI
    otherwise opens it on the GenAI traces page)."""
    import mlflow

    cfg = ExperimentConfig(tracking_uri="sqlite:///store.db", artifact_dir="artifacts", experiment="t")
    with start_run(cfg, "train-tokenizers", root=tmp_path, tags={"quantizer": "fsq"}, variant="FSQ width 32") as run:
        for epoch in (1, 2, 3):
            run.log_metrics({"body/train_loss": 1.0 / epoch}, step=epoch)
        run.log_metrics({"body/utilisation_pct": 50.0})
    with extra_tags({"scheduled": "true"}):
        with start_run(cfg, "evaluate-smlm", root=tmp_path, variant="production only"):
            pass
    with start_run(cfg, "evaluate-smlm", root=tmp_path):  # the extra tags end with their block
        pass
    runs = fetch_runs(cfg, root=tmp_path)
    names = [r.tags["mlflow.runName"] for r in runs]
    assert names == ["evaluate-smlm", "evaluate-smlm · production only · scheduled", "train-tokenizers · FSQ width 32"]
    assert runs[1].tags["scheduled"] == "true" and "scheduled" not in runs[0].tags
    assert runs[2].tags["variant"] == "FSQ width 32" and runs[2].tags["quantizer"] == "fsq"
    curves = metric_histories(cfg, runs[2].run_id, sorted(runs[2].metrics), root=tmp_path)
    assert curves == {"body/train_loss": [(1, 1.0), (2, 0.5), (3, 1.0 / 3)]}  # one-point metrics are no curve
    experiment = mlflow.MlflowClient(tracking_uri=absolute_uri(cfg.tracking_uri, tmp_path)).get_experiment_by_name("t")
    assert all(experiment.tags.get(k) == v for k, v in EXPERIMENT_KIND.items())


def test_a_store_made_before_the_kind_tag_is_marked(tmp_path):
    import mlflow

    uri = absolute_uri("sqlite:///store.db", tmp_path)
    client = mlflow.MlflowClient(tracking_uri=uri)
    client.create_experiment("old", artifact_location=(tmp_path / "a").as_uri())
    assert "mlflow.experimentKind" not in client.get_experiment_by_name("old").tags
    with start_run(ExperimentConfig(tracking_uri="sqlite:///store.db", experiment="old"), "x", root=tmp_path):
        pass
    assert client.get_experiment_by_name("old").tags["mlflow.experimentKind"] == "custom_model_development"


def test_disabled_tracking_is_a_noop(tmp_path):
    with start_run(ExperimentConfig(enabled=False), "x", root=tmp_path) as run:
        run.log_metrics({"a": 1.0})
        assert run.run_id is None
    assert not list(tmp_path.iterdir())



def test_newest_finished_keeps_the_first_finished_run_per_key_in_newest_first_order():
    from m3t.experiment import RunRecord, newest_finished, variant_of

    def run(run_id, status, variant=None):
        return RunRecord(run_id, "evaluate-smlm", 0, status, {}, {}, None, {"variant": variant} if variant else {})

    records = [run("a-running", "RUNNING", "x"), run("b-failed", "FAILED", "y"), run("c-newest-x", "FINISHED", "x"),
               run("d-newest-y", "FINISHED", "y"), run("e-older-x", "FINISHED", "x"), run("f12345678-untagged", "FINISHED")]
    newest = newest_finished(records, variant_of)
    assert list(newest) == ["x", "y", "f1234567"]
    assert [r.run_id for r in newest.values()] == ["c-newest-x", "d-newest-y", "f12345678-untagged"]
    assert newest_finished([run("a", "FAILED", "x")], variant_of) == {}


def test_metric_histories_read_the_configured_store_not_mlflows_current_one(tmp_path):
    """Curves come from the store of ``cfg`` (made absolute against ``root``), whatever store MLflow's process-wide
    tracking URI points at when they are read (e.g. the last one another run used)."""
    import os

    import mlflow

    cfg = ExperimentConfig(tracking_uri="sqlite:///store.db", artifact_dir="artifacts", experiment="t")
    with start_run(cfg, "train-tokenizers", root=tmp_path) as run:
        for epoch in (1, 2):
            run.log_metrics({"loss": float(epoch)}, step=epoch)
    run_id = fetch_runs(cfg, root=tmp_path)[0].run_id
    uri_before, env_before = mlflow.get_tracking_uri(), os.environ.get("MLFLOW_TRACKING_URI")
    try:
        mlflow.set_tracking_uri(absolute_uri("sqlite:///elsewhere.db", tmp_path))
        os.environ.pop("MLFLOW_TRACKING_URI", None)  # set_tracking_uri also exports it: the user's choice
        assert metric_histories(cfg, run_id, ["loss"], root=tmp_path) == {"loss": [(1, 1.0), (2, 2.0)]}
    finally:  # both exactly as before: a leaked URI would send every later test's runs to this store
        mlflow.set_tracking_uri(uri_before)
        if env_before is None:
            os.environ.pop("MLFLOW_TRACKING_URI", None)
        else:
            os.environ["MLFLOW_TRACKING_URI"] = env_before
