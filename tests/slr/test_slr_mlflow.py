"""The train-slr and evaluate-slr runs with MLflow on: params, per-epoch curves of both probes, the table and
the confusion matrices land in the run, and the CLI's Tab. 4 comes back from it."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from m3t.body.config import BodyConfig
from m3t.experiment import ExperimentConfig, fetch_runs
from m3t.slr.config import SLREvaluateConfig
from m3t.slr.pipeline import evaluate_and_log, train_and_log
from m3t.slr.table import recognition_table
from test_slr import TINY_PROBE, TINY_TRAIN, corpus, data, tokenizers  # noqa: F401 - fixtures

ROOT = Path(__file__).resolve().parents[2]


def test_train_and_evaluate_log_to_mlflow(data, tmp_path):  # noqa: F811
    experiment = ExperimentConfig(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}",
                                  artifact_dir=str(tmp_path / "mlruns"))
    body_cfg = BodyConfig(cache_dir=str(ROOT / ".cache" / "anny"))
    train_cfg = dataclasses.replace(TINY_TRAIN, cache_dir=str(tmp_path / "cache"))
    report = train_and_log(TINY_PROBE, train_cfg, body_cfg, data, experiment, progress=False)
    summary = evaluate_and_log(SLREvaluateConfig(bootstrap=100, device="cpu"), body_cfg, data, experiment)
    assert report["train_clips"] > 0 and "full/overall/top1" in summary
    train_run = fetch_runs(experiment, stage="train-slr")[0]
    assert train_run.params["slr.layers"] == "1" and "no_face/train_loss" in train_run.metrics
    assert sorted(p.name for p in (train_run.artifact_dir).iterdir()) == [
        "confusion_dev_full.png", "confusion_dev_no_face.png", "metrics.json", "skipped.jsonl"]
    runs = fetch_runs(experiment, stage="evaluate-slr")
    assert (runs[0].artifact_dir / "confusion" / "confusion_full.png").exists()
    assert recognition_table(runs) == (data.metrics("slr") / "table.md").read_text()
