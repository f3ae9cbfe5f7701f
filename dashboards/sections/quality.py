"""The data quality page: each corpus' fitting report (quality.json), its quarantine reasons and per-clip
reprojection error and missing parts (quality.csv)."""
from __future__ import annotations

import csv
import json
from pathlib import Path

from dashboards import html as h
from dashboards.sections.common import figure_html
from m3t.config import Params


def _read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def quality(params: Params) -> str:
    import plotly.graph_objects as go

    out = []
    for corpus in params.corpora:
        folder = params.data.shards_dir(corpus)
        report = folder / "quality.json"
        if not report.exists():
            out.append(f"<h2>{h.esc(corpus)}</h2>" + h.empty(f"Not fitted yet: no {h.esc(report)}. Run "
                                                             f"<code>m3t fit-corpus</code> or <code>dvc repro</code>."))
            continue
        q = json.loads(report.read_text())
        shown = {k: v for k, v in q.items() if isinstance(v, (int, float))}
        rows = [(k, f"{v:.4g}" if isinstance(v, float) else v) for k, v in shown.items()]
        reasons = q.get("quarantine_reasons") or {}
        out.append(f"<h2>{h.esc(corpus)}</h2><div class=pair><div>{h.table(('measure', 'value'), rows, f'quality-{corpus}')}"
                   + (h.table(("quarantine reason", "clips"), sorted(reasons.items())) if reasons else
                      "<p class=note>no clip quarantined</p>") + "</div>")
        per_clip = [r for r in _read_csv(folder / "quality.csv") if r.get("status") == "fitted"] \
            if (folder / "quality.csv").exists() else []
        if per_clip:
            px = [float(r["reproj_px"]) for r in per_clip if r.get("reproj_px")]
            fig = go.Figure([go.Histogram(x=px, nbinsx=30)])
            fig.update_layout(title="reprojection error per clip (px)", xaxis_title="px", yaxis_title="clips")
            missing = go.Figure([go.Box(y=[float(r[k]) for r in per_clip if r.get(k)], name=k.replace("missing_", ""))
                                 for k in ("missing_left_hand", "missing_right_hand", "missing_face")])
            missing.update_layout(title="share of frames without the part, per clip")
            out.append(f"<div><figure>{figure_html(fig, f'reproj-{corpus}')}</figure>"
                       f"<figure>{figure_html(missing, f'missing-{corpus}')}</figure></div>")
        out.append("</div>")
    return "".join(out) or h.empty("No corpus configured in params.yaml <code>corpora</code>.")
