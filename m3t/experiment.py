"""The one place that talks to MLflow.

Stages hand this module their params, metrics and artifact files; nothing else imports mlflow. The
tracking URI is made absolute (``sqlite:///<abs path>``) so runs from ``dvc exp`` temp dirs, Prefect
workers and tests all land in the same store. Telemetry is switched off before mlflow is imported.
"""
from __future__ import annotations

import contextvars
import dataclasses
import os
from collections.abc import Callable, Hashable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

TELEMETRY_OFF = {
    "DO_NOT_TRACK": "true",
    "MLFLOW_DISABLE_TELEMETRY": "true",
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "DVC_NO_ANALYTICS": "1",
}
# The experiment is model development, not GenAI. MLflow 3.17's UI does not read this tag to pick the landing
# page (it follows a "workflow type" from the link or the browser's memory, GenAI by default): links to the
# experiment carry UI_QUERY (:func:`ui_link`), which opens the runs table.
EXPERIMENT_KIND = {"mlflow.experimentKind": "custom_model_development"}
UI_QUERY = "workflowType=machine_learning"
# A saved runs view written on the experiment (MLflow 3.17's "Views" menu): the runs table with the tags that
# name the ablation axes as columns, where the default table shows none.
RUNS_VIEW = "m3t-runs"
RUNS_VIEW_COLUMNS = ("tags.`stage`", "tags.`variant`", "tags.`corpus`", "tags.`body_model`", "tags.`quantizer`",
                     "tags.`seed`", "tags.`scheduled`", "attributes.`Duration`")


@dataclass(frozen=True)
class ExperimentConfig:
    tracking_uri: str = "sqlite:///mlflow.db"  # relative paths resolve against the repository root
    artifact_dir: str = "mlruns"
    experiment: str = "m3t"
    enabled: bool = True
    dashboard_dir: str = "dashboards/site"  # the static dashboard over this store (dashboards/build.py)


def to_dict(obj: Any) -> Any:
    """Plain dicts / lists of a config dataclass (or a tree of them), for YAML and MLflow."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple):
        return [to_dict(x) for x in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


def saved_view_tag(view_id: str, name: str, columns: tuple[str, ...], now_ms: int) -> tuple[str, str]:
    """(key, value) of the experiment tag that MLflow 3.17's UI lists as a saved runs view showing ``columns``
    (``params.`x```, ``metrics.`x```, ``tags.`x```, ``attributes.`Duration```)."""
    import json

    state = json.dumps({"selectedColumns": list(columns)})
    return (f"mlflow.sharedViewState.{view_id}",
            json.dumps({"name": name, "createdAt": now_ms, "updatedAt": now_ms, "state": state}))


def experiment_tags() -> dict[str, str]:
    """The tags every experiment of the platform carries: its kind and the saved runs view."""
    import time

    key, value = saved_view_tag(RUNS_VIEW, "m3t runs: stage, variant, axes", RUNS_VIEW_COLUMNS, int(time.time() * 1000))
    return {**EXPERIMENT_KIND, key: value}


def ui_link(base_url: str, experiment_id: str, run_id: str | None = None, view: str | None = RUNS_VIEW) -> str:
    """The MLflow UI link of an experiment (or one run) that opens on the runs table, with the saved view."""
    if run_id:
        return f"{base_url}/#/experiments/{experiment_id}/runs/{run_id}?{UI_QUERY}"
    return f"{base_url}/#/experiments/{experiment_id}/runs?{UI_QUERY}{f'&viewStateShareKey={view}' if view else ''}"


def experiment_ui_link(cfg: "ExperimentConfig", base_url: str, root: str | Path = ".") -> str | None:
    """:func:`ui_link` of ``cfg``'s experiment in the store, or None while it has no experiment yet."""
    disable_telemetry()
    from mlflow.tracking import MlflowClient

    experiment = MlflowClient(tracking_uri=tracking_uri(cfg, Path(root))).get_experiment_by_name(cfg.experiment)
    return None if experiment is None else ui_link(base_url.rstrip("/"), experiment.experiment_id)


def section_params(**sections: Any) -> dict[str, Any]:
    """``section.key -> value`` of the given config sections (``section_params(fitting=cfg)``), for logging."""
    return {f"{name}.{key}": value for name, cfg in sections.items() for key, value in to_dict(cfg).items()}


def disable_telemetry() -> None:
    for key, value in TELEMETRY_OFF.items():
        os.environ.setdefault(key, value)


def absolute_uri(uri: str, root: Path) -> str:
    """``sqlite:///rel.db`` -> ``sqlite:////abs/rel.db``; plain paths -> ``file://`` URIs; others unchanged."""
    prefix = "sqlite:///"
    if uri.startswith(prefix) and not uri[len(prefix):].startswith("/"):
        return prefix + str((root / uri[len(prefix):]).resolve())
    if "://" not in uri:
        return (root / uri).resolve().as_uri()
    return uri


def tracking_uri(cfg: ExperimentConfig, root: Path) -> str:
    """``MLFLOW_TRACKING_URI`` when set (how ``dvc exp run --temp`` copies reach the workspace's store), else
    the configured URI made absolute against ``root``."""
    return os.environ.get("MLFLOW_TRACKING_URI") or absolute_uri(cfg.tracking_uri, root)


class Run:
    """A thin handle over an active MLflow run (or a no-op when tracking is disabled)."""

    def __init__(self, mlflow_module: Any | None):
        self._mlflow = mlflow_module

    @property
    def run_id(self) -> str | None:
        return self._mlflow.active_run().info.run_id if self._mlflow else None

    def log_params(self, params: dict[str, Any]) -> None:
        if self._mlflow:
            self._mlflow.log_params({k: str(v)[:6000] for k, v in params.items()})

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        if self._mlflow:
            finite = {k: float(v) for k, v in metrics.items() if v is not None and v == v}
            self._mlflow.log_metrics(finite, step=step)

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        if self._mlflow and Path(path).exists():
            self._mlflow.log_artifact(str(path), artifact_path=artifact_path)

    def log_table(self, csv_path: str | Path, artifact_file: str) -> None:
        """A CSV (header row + rows) as an MLflow table (viewable and comparable in the UI) and as the file."""
        if self._mlflow and Path(csv_path).exists():
            import csv

            with open(csv_path, newline="") as fh:
                rows = list(csv.DictReader(fh))
            columns = {k: [r[k] for r in rows] for k in (rows[0] if rows else {})}
            self._mlflow.log_table(data=columns, artifact_file=artifact_file)
            self._mlflow.log_artifact(str(csv_path))

    def set_tags(self, tags: dict[str, str]) -> None:
        if self._mlflow:
            self._mlflow.set_tags(tags)


_EXTRA_TAGS: contextvars.ContextVar[dict[str, str]] = contextvars.ContextVar("m3t_run_tags", default={})


@contextmanager
def extra_tags(tags: dict[str, str]) -> Iterator[None]:
    """Add ``tags`` to every run started inside the block (the nightly re-evaluation tags its runs
    ``scheduled`` this way, without each model family's logger knowing about schedules)."""
    token = _EXTRA_TAGS.set({**_EXTRA_TAGS.get(), **tags})
    try:
        yield
    finally:
        _EXTRA_TAGS.reset(token)


def run_name(stage: str, variant: str | None = None, tags: dict[str, str] | None = None) -> str:
    """``stage · variant`` (``· scheduled`` appended for scheduled runs): what the MLflow UI lists."""
    parts = [stage, *([variant] if variant else [])]
    if (tags or {}).get("scheduled") == "true":
        parts.append("scheduled")
    return " · ".join(parts)


@contextmanager
def start_run(cfg: ExperimentConfig, stage: str, root: str | Path = ".", tags: dict[str, str] | None = None,
              variant: str | None = None) -> Iterator[Run]:
    """Open an MLflow run of ``stage`` named ``stage · variant`` and tagged ``stage`` / ``variant`` (plus the
    caller's tags and those of an enclosing :func:`extra_tags`); yields a :class:`Run` (no-op if ``cfg.enabled``
    is false)."""
    if not cfg.enabled:
        yield Run(None)
        return
    disable_telemetry()
    import mlflow

    root = Path(root)
    # mlflow.set_tracking_uri also writes MLFLOW_TRACKING_URI into os.environ, which tracking_uri() reads as the
    # user's choice: restored afterwards, or every later run of this process would go to this run's store.
    outer = os.environ.get("MLFLOW_TRACKING_URI")
    mlflow.set_tracking_uri(tracking_uri(cfg, root))
    try:
        with _open_run(mlflow, cfg, root, stage, tags, variant) as run:
            yield run
    finally:
        if outer is None:
            os.environ.pop("MLFLOW_TRACKING_URI", None)
        else:
            os.environ["MLFLOW_TRACKING_URI"] = outer


def _create_experiment(client: Any, cfg: ExperimentConfig, root: Path) -> None:
    client.create_experiment(cfg.experiment, artifact_location=(root / cfg.artifact_dir).resolve().as_uri(),
                             tags=experiment_tags())


def ensure_experiment(cfg: ExperimentConfig, root: str | Path = ".") -> None:
    """Create ``cfg.experiment`` in its store, artifacts under ``root``, unless it exists (or tracking is off):
    runs started later from a temporary copy of the workspace (``dvc exp run --temp``) keep their artifacts here."""
    if not cfg.enabled:
        return
    disable_telemetry()
    import mlflow

    client = mlflow.MlflowClient(tracking_uri(cfg, Path(root)))
    if client.get_experiment_by_name(cfg.experiment) is None:
        _create_experiment(client, cfg, Path(root))


@contextmanager
def _open_run(mlflow: Any, cfg: ExperimentConfig, root: Path, stage: str, tags: dict[str, str] | None,
              variant: str | None) -> Iterator[Run]:
    experiment = mlflow.get_experiment_by_name(cfg.experiment)
    if experiment is None:
        _create_experiment(mlflow.MlflowClient(), cfg, root)
    else:  # a store made before these tags (the saved view, once written, is the user's to edit)
        for key, value in experiment_tags().items():
            if key not in experiment.tags or key in EXPERIMENT_KIND and experiment.tags[key] != value:
                mlflow.MlflowClient().set_experiment_tag(experiment.experiment_id, key, value)
    mlflow.set_experiment(cfg.experiment)
    all_tags = {"stage": stage, **({"variant": variant} if variant else {}), **(tags or {}), **_EXTRA_TAGS.get()}
    with mlflow.start_run(run_name=run_name(stage, all_tags.get("variant"), all_tags), tags=all_tags):
        yield Run(mlflow)


@dataclass(frozen=True)
class RunRecord:
    run_id: str
    stage: str
    start_time: int  # ms since epoch
    status: str
    params: dict[str, str]
    metrics: dict[str, float]
    artifact_dir: Path | None  # local artifact folder when the store is on this machine
    tags: dict[str, str] = field(default_factory=dict)


def newest_finished(records: Iterable[RunRecord], key: Callable[[RunRecord], Hashable]) -> dict[Hashable, RunRecord]:
    """The newest finished run per ``key(run)``, from ``records`` newest first (as :func:`fetch_runs` gives
    them); keys in the order their newest run appears. Failed and running runs never count."""
    out: dict[Hashable, RunRecord] = {}
    for record in records:
        if record.status == "FINISHED":
            out.setdefault(key(record), record)
    return out


def variant_of(record: RunRecord) -> str:
    """The run's ``variant`` tag, or its id's first 8 characters when it has none."""
    return record.tags.get("variant", record.run_id[:8])


def fetch_runs(cfg: ExperimentConfig, root: str | Path = ".", stage: str | None = None) -> list[RunRecord]:
    """Runs of the experiment, newest first (optionally one stage only), for dashboards and tables."""
    disable_telemetry()
    from urllib.parse import unquote, urlparse

    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=tracking_uri(cfg, Path(root)))
    experiment = client.get_experiment_by_name(cfg.experiment)
    if experiment is None:
        return []
    query = f"tags.stage = '{stage}'" if stage else ""
    records = []
    for run in client.search_runs([experiment.experiment_id], filter_string=query, order_by=["attributes.start_time DESC"]):
        uri = urlparse(run.info.artifact_uri)
        local = Path(unquote(uri.path)) if uri.scheme in ("", "file") else None
        records.append(RunRecord(run.info.run_id, run.data.tags.get("stage", run.info.run_name or ""), run.info.start_time,
                                 run.info.status, dict(run.data.params), dict(run.data.metrics), local,
                                 dict(run.data.tags)))
    return records


def metric_histories(cfg: ExperimentConfig, run_id: str, keys: list[str], root: str | Path = ".",
                     min_points: int = 2) -> dict[str, list[tuple[int, float]]]:
    """``{key: [(step, value), ...]}`` of the run's metrics logged at ``min_points`` steps or more (training
    curves), in step order."""
    disable_telemetry()
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=tracking_uri(cfg, Path(root)))
    out = {}
    for key in keys:
        points = sorted((m.step, m.value) for m in client.get_metric_history(run_id, key))
        if len(points) >= min_points:
            out[key] = points
    return out
