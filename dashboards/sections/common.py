"""What the dashboard's sections share: the training stages, the pipeline command to suggest, run selection and
labels, and the one way a plotly figure becomes HTML."""
from __future__ import annotations

import datetime as dt

from m3t.experiment import RunRecord, newest_finished

TRAIN_STAGES = ("train-tokenizers", "train-backtranslation", "train-smlm", "train-slr",
                "train-backtranslation-skeleton", "train-sgsa")
PIPELINE = "<code>dvc repro</code> (or <code>m3t up</code>, then <code>prefect deployment run ...</code>)"


def stage_runs(runs: list[RunRecord], stage: str) -> list[RunRecord]:
    return [r for r in runs if r.stage == stage]


def newest_per_variant(runs: list[RunRecord], stage: str, limit: int = 4) -> list[RunRecord]:
    return list(newest_finished(stage_runs(runs, stage), lambda r: r.tags.get("variant", "")).values())[:limit]


def started(record: RunRecord) -> str:
    return dt.datetime.fromtimestamp(record.start_time / 1000).strftime("%Y-%m-%d %H:%M")


def run_name(record: RunRecord) -> str:
    return record.tags.get("mlflow.runName", record.stage)


def figure_html(fig, div_id: str, width: int = 560) -> str:
    fig.update_layout(margin=dict(l=50, r=20, t=40, b=40), height=320, width=width, template="plotly_white")
    return fig.to_html(full_html=False, include_plotlyjs=False, div_id=div_id)
