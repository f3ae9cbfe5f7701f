"""The codebooks page: utilisation per quantizer and group, the statistics that say how far it can be read, and
token frequencies by rank."""
from __future__ import annotations

import json

from dashboards import html as h
from dashboards.sections.common import figure_html, stage_runs
from m3t.config import Params
from m3t.experiment import RunRecord, newest_finished
from m3t.reporting import fixed


def _token_counts(record: RunRecord) -> dict[str, dict]:
    if record.artifact_dir is None:
        return {}
    files = sorted(record.artifact_dir.glob("plots/tokens_*.json"))
    return {json.loads(f.read_text())["group"]: json.loads(f.read_text()) for f in files}


def codebooks(runs: list[RunRecord], params: Params) -> str:
    import plotly.graph_objects as go

    newest = newest_finished(stage_runs(runs, "train-tokenizers") + stage_runs(runs, "evaluate-tokenizers"),
                             lambda r: r.tags.get("quantizer", "?"))
    if not newest:
        return h.empty("No tokenizer run yet: run <code>dvc repro train-tokenizers</code>.")
    groups = ("body", "hand", "face")
    bars = go.Figure([go.Bar(name=q.upper(), x=list(groups),
                             y=[r.metrics.get(f"{g}/utilisation_pct") for g in groups]) for q, r in newest.items()])
    bars.update_layout(title="codebook utilisation on the test split (%)", barmode="group", yaxis_range=[0, 100])
    out = [f"<figure>{figure_html(bars, 'utilisation')}</figure>"]
    # utilisation saturates when tokens barely outnumber codes: the columns beside it say how far it can be read
    stats = (("util %", "utilisation_pct", 1), ("perplexity / K", "perplexity_per_code", 2),
             ("count SD", "count_sd", 1), ("tokens / K", "tokens_per_code", 1))
    rows = [[q.upper(), g] + [fixed(r.metrics.get(f"{g}/{key}"), digits) for _, key, digits in stats]
            for q, r in newest.items() for g in groups]
    out.append(h.table(["quantizer", "group"] + [name for name, _, _ in stats], rows, "codebook-stats",
                       "test split; a uniform code distribution has perplexity / K = 1, and at 10 tokens per code "
                       "leaves under 0.005 % of the codes unused"))
    if len(newest) < 2:
        out.append("<p class=note>Only one quantizer in the store; add the others with "
                   "<code>m3t ablate-tokenizers</code> or <code>dvc exp run -S tokenizer.quantizer=vq</code> "
                   "(<code>vq_ema</code>, <code>vq_plain</code>, <code>fsq</code>) to compare them.</p>")
    counts = {q: _token_counts(r) for q, r in newest.items()}
    for group in groups:
        traces = []
        for q, per_group in counts.items():
            if group in per_group:
                ranked = sorted(per_group[group]["counts"], reverse=True)
                total = sum(ranked) or 1
                traces.append(go.Bar(name=f"{q.upper()} ({per_group[group]['codebook_size']} codes)",
                                     x=list(range(1, len(ranked) + 1)), y=[c / total for c in ranked]))
        if traces:
            fig = go.Figure(traces)
            fig.update_layout(title=f"{group} token frequencies by rank (test split; cf. M3T Fig. 5)",
                              xaxis_title="code rank", yaxis_title="share of tokens", barmode="overlay")
            fig.update_traces(opacity=0.6)
            out.append(f"<figure>{figure_html(fig, f'tokens-{group}')}</figure>")
    return "".join(out)
