"""The training curves page: per-epoch metrics of the newest run of each training stage and variant."""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from dashboards import html as h
from dashboards.sections.common import (
    PIPELINE,
    TRAIN_STAGES,
    figure_html,
    newest_per_variant,
    run_name,
    started,
)
from m3t.experiment import ExperimentConfig, RunRecord, metric_histories


def curves(runs: list[RunRecord], experiment: ExperimentConfig, root: str | Path, max_figures: int = 8) -> str:
    import plotly.graph_objects as go

    out = []
    for stage in TRAIN_STAGES:
        for record in newest_per_variant(runs, stage):
            histories = metric_histories(experiment, record.run_id, sorted(record.metrics), root)
            families: dict[str, dict[str, list[tuple[int, float]]]] = defaultdict(dict)
            for key, points in histories.items():
                prefix, _, name = key.rpartition("/")
                if name in ("epoch", "step"):
                    continue
                families[name][prefix or name] = points
            if not families:
                continue
            out.append(f"<h2>{h.esc(run_name(record))}</h2><p class=note>run {record.run_id[:8]}, {started(record)}</p>")
            for i, (name, traces) in enumerate(sorted(families.items())[:max_figures]):
                fig = go.Figure([go.Scatter(x=[s for s, _ in pts], y=[v for _, v in pts], mode="lines+markers",
                                            name=trace) for trace, pts in sorted(traces.items())])
                fig.update_layout(title=name, xaxis_title="epoch")
                out.append(f"<figure>{figure_html(fig, f'curve-{record.run_id[:8]}-{i}')}</figure>")
    return "".join(out) or h.empty(f"No training run with per-epoch metrics yet: run {PIPELINE}.")
