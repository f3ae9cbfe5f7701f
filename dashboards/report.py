"""Static dashboard: one self-contained HTML page over the MLflow store.

    python -m dashboards.report [--out dashboards/site/index.html] [--params params.yaml]

For every stage: a table of its runs (newest first) with the key metrics, and the pictures each run
logged (e.g. fitted vs ground-truth skeletons of fit-corpus). Open the file in a browser; nothing to
serve, nothing fetched from the network.
"""
from __future__ import annotations

import argparse
import base64
import datetime as dt
import html
import os
from pathlib import Path

from m3t.config import load_params
from m3t.experiment import RunRecord, fetch_runs

KEY_METRICS = {
    "fit-corpus": ["clips_fitted", "clips_cached", "clips_quarantined", "reproj_px_mean", "joint_mm_mean",
                   "pa_joint_mm_mean", "init_pa_joint_mm_mean", "fit_frames_per_s_wall", "wall_seconds"],
}


def _table(runs: list[RunRecord], columns: list[str]) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in ["run", "started", "status", *columns])
    rows = []
    for r in runs:
        started = dt.datetime.fromtimestamp(r.start_time / 1000).strftime("%Y-%m-%d %H:%M")
        cells = [r.run_id[:8], started, r.status] + [
            f"{r.metrics[c]:.3g}" if c in r.metrics else "" for c in columns]
        rows.append("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in cells) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(rows)}</table>"


def _images(run: RunRecord, limit: int = 4) -> str:
    if run.artifact_dir is None or not run.artifact_dir.exists():
        return ""
    tags = []
    for png in sorted(run.artifact_dir.rglob("*.png"))[:limit]:
        data = base64.b64encode(png.read_bytes()).decode()
        tags.append(f'<figure><img src="data:image/png;base64,{data}"><figcaption>{html.escape(png.name)}</figcaption></figure>')
    return "".join(tags)


def render(runs: list[RunRecord]) -> str:
    stages: dict[str, list[RunRecord]] = {}
    for r in runs:
        stages.setdefault(r.stage, []).append(r)
    body = []
    for stage, stage_runs in stages.items():
        columns = KEY_METRICS.get(stage) or sorted({k for r in stage_runs for k in r.metrics})[:10]
        body.append(f"<h2>{html.escape(stage)}</h2>{_table(stage_runs, columns)}{_images(stage_runs[0])}")
    style = ("body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin:1em 0}"
             "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px}img{max-width:900px}")
    content = "".join(body) or "<p>No runs yet: run <code>dvc repro</code> first.</p>"
    return f"<!doctype html><meta charset=utf-8><title>M3T platform</title><style>{style}</style><h1>M3T platform runs</h1>{content}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--out", default="dashboards/site/index.html")
    args = parser.parse_args()
    runs = fetch_runs(load_params(args.params).experiment)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(render(runs), encoding="utf-8")
    os.replace(tmp, out)
    print(f"wrote {out} ({len(runs)} runs)")


if __name__ == "__main__":
    main()
