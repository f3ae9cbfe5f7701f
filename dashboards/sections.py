"""The dashboard's sections, each a function from runs / params to an HTML fragment.

Runs come newest first (:func:`m3t.experiment.fetch_runs`). A section with nothing to show says which stage or
command produces its content instead.
"""
from __future__ import annotations

import csv
import datetime as dt
import json
import shutil
from collections import defaultdict
from pathlib import Path

from dashboards import html as h
from dashboards.paper import M3T, SGSA, PaperTable
from m3t.backtranslation.table import backtranslation_table
from m3t.claims import claims_table, stability, stability_line
from m3t.config import Params
from m3t.experiment import ExperimentConfig, RunRecord, metric_histories, newest_finished
from m3t.metrics.stats import agreeing_digits
from m3t.reporting import fixed
from m3t.sgsa.table import adjacency_table, cross_table, in_display_units, layers_table
from m3t.slr.table import recognition_table
from m3t.smlm.table import production_table
from m3t.tokenizers.ablation import ablation_table

TRAIN_STAGES = ("train-tokenizers", "train-backtranslation", "train-smlm", "train-slr",
                "train-backtranslation-skeleton", "train-sgsa")
PIPELINE = "<code>dvc repro</code> (or <code>m3t up</code>, then <code>prefect deployment run ...</code>)"


def _stage(runs: list[RunRecord], stage: str) -> list[RunRecord]:
    return [r for r in runs if r.stage == stage]


def _newest_per_variant(runs: list[RunRecord], stage: str, limit: int = 4) -> list[RunRecord]:
    return list(newest_finished(_stage(runs, stage), lambda r: r.tags.get("variant", "")).values())[:limit]


def _when(record: RunRecord) -> str:
    return dt.datetime.fromtimestamp(record.start_time / 1000).strftime("%Y-%m-%d %H:%M")


def _name(record: RunRecord) -> str:
    return record.tags.get("mlflow.runName", record.stage)


def _figure(fig, div_id: str, width: int = 560) -> str:
    fig.update_layout(margin=dict(l=50, r=20, t=40, b=40), height=320, width=width, template="plotly_white")
    return fig.to_html(full_html=False, include_plotlyjs=False, div_id=div_id)


# ------------------------------------------------------------------------------------------------ overview
def overview(runs: list[RunRecord], params: Params, root: str | Path) -> str:
    if not runs:
        return h.empty(f"No runs in the MLflow store yet (<code>{h.esc(params.experiment.tracking_uri)}</code>, "
                       f"experiment <code>{h.esc(params.experiment.experiment)}</code>). Run the embedded pipeline "
                       f"with {PIPELINE}, then rebuild this page with <code>python -m dashboards.build</code>.")
    by_stage: dict[str, list[RunRecord]] = defaultdict(list)
    for r in runs:
        by_stage[r.stage].append(r)
    rows = [(stage, len(rs), sum(r.status == "FINISHED" for r in rs), sum(r.tags.get("scheduled") == "true" for r in rs),
             _name(rs[0]), _when(rs[0]), rs[0].status) for stage, rs in sorted(by_stage.items())]
    body = h.table(("stage", "runs", "finished", "scheduled", "newest run", "started", "status"), rows, "stages")
    return (f"<p>{len(runs)} runs in experiment <code>{h.esc(params.experiment.experiment)}</code>. Pages: the paper "
            "tables filled from the newest runs, training curves, codebooks, data quality, videos, and every run "
            "with a filter.</p>" + body)


# ------------------------------------------------------------------------------------------------ tables
def _paper(table: PaperTable) -> str:
    return "<h4>Paper (reference)</h4><p class=note>" + h.esc(table.caption) + "</p>" + h.table(table.header, table.rows)


def paper_tables(runs: list[RunRecord]) -> str:
    """Each paper table: what this store measured (the ``m3t ...-table`` text) beside the paper's numbers."""
    smlm, sgsa = _stage(runs, "evaluate-smlm"), _stage(runs, "evaluate-sgsa")
    measured = {
        "M3T Tab. 1": production_table(smlm),
        "M3T Tab. 2": backtranslation_table(_stage(runs, "evaluate-backtranslation"), smlm),
        "M3T Tab. 3": ablation_table(_stage(runs, "train-tokenizers")),
        "M3T Tab. 4": recognition_table(_stage(runs, "evaluate-slr")),
        "SGSA Tab. 1": layers_table(sgsa),
        "SGSA Tab. 2": adjacency_table(sgsa),
        "SGSA Tab. 3": cross_table(sgsa),
    }
    out = ["<p class=note>Measured tables come from the newest finished runs of each variant, by the definitions "
           "each table names (SL-T text metrics, SOKE DTW motion metrics). The papers' numbers are on their own "
           "corpora: comparable in layout, not in value.</p>"]
    for key, text in measured.items():
        ident = key.lower().replace(". ", "").replace(" ", "-")  # "m3t-tab1"
        paper = (M3T | SGSA)[key]
        out.append(f'<h2 id="{ident}">{h.esc(key)}</h2><div class=pair><div><h4>This platform (measured)</h4>'
                   f"{h.markdown(text, ident + '-measured')}</div><div>{_paper(paper)}</div></div>")
    return "".join(out)


# ------------------------------------------------------------------------------------------------ curves
def curves(runs: list[RunRecord], experiment: ExperimentConfig, root: str | Path, max_figures: int = 8) -> str:
    import plotly.graph_objects as go

    out = []
    for stage in TRAIN_STAGES:
        for record in _newest_per_variant(runs, stage):
            histories = metric_histories(experiment, record.run_id, sorted(record.metrics), root)
            families: dict[str, dict[str, list[tuple[int, float]]]] = defaultdict(dict)
            for key, points in histories.items():
                prefix, _, name = key.rpartition("/")
                if name in ("epoch", "step"):
                    continue
                families[name][prefix or name] = points
            if not families:
                continue
            out.append(f"<h2>{h.esc(_name(record))}</h2><p class=note>run {record.run_id[:8]}, {_when(record)}</p>")
            for i, (name, traces) in enumerate(sorted(families.items())[:max_figures]):
                fig = go.Figure([go.Scatter(x=[s for s, _ in pts], y=[v for _, v in pts], mode="lines+markers",
                                            name=trace) for trace, pts in sorted(traces.items())])
                fig.update_layout(title=name, xaxis_title="epoch")
                out.append(f"<figure>{_figure(fig, f'curve-{record.run_id[:8]}-{i}')}</figure>")
    return "".join(out) or h.empty(f"No training run with per-epoch metrics yet: run {PIPELINE}.")


# ------------------------------------------------------------------------------------------------ codebooks
def _claim_rows(rows: list[dict]) -> str:
    """The claims table of judged rows (:func:`m3t.claims.claims_table`'s, live or read from a claims.json)."""
    body = []
    for r in rows:
        if r["verdict"] == "not run":
            body.append([r["claim"], r["source"], r["paper"], r["metric"], "-", "-", f"not run: {r['note']}", 0, "-"])
            continue
        low, high = r["interval95"]
        halves = r.get("halves") or {}
        flipped = len(set(halves.get("verdicts", []))) > 1
        body.append([r["claim"], r["source"], r["paper"], r["metric"],
                     f"{r['a']} {r['mean_a']:.3g} +- {r['std_a']:.2g} -> "
                     f"{r['b']} {r['mean_b']:.3g} +- {r['std_b']:.2g}",
                     f"{r['compared']} {r['value']:.3g} [{low:.3g}, {high:.3g}]",
                     r["verdict"] + (f" ({r['note']})" if r["note"] else "")
                     + (f"; seed halves: {' / '.join(halves['verdicts'])}" if flipped else ""), len(r["seeds"]),
                     ", ".join(sorted({i[:8] for i in r["runs_a"] + r["runs_b"]}))])
    header = ["claim", "source", "paper", "metric", "ours: A -> B", "compared [95 % interval]", "verdict", "seeds",
              "runs"]
    return h.table(header, body, "claims")


CLAIMS_NOTE = ("Ours: A -> B as mean +- std over seeds; the compared quantity with its 95 % hierarchical bootstrap "
               "interval over training seeds and test clips (over seeds for codebook statistics); runs of one data "
               "version only. Verdicts need >= 3 seeds. ")


def claims(runs: list[RunRecord]) -> str:
    """Every claim of :data:`m3t.claims.CLAIMS` judged on the runs (what ``m3t claims`` writes)."""
    rows = claims_table(runs)
    note = (CLAIMS_NOTE + "A claim with no runs says which command makes them. <code>m3t claims</code> writes the "
            "same table to claims.json / claims.md. " + h.esc(stability_line(stability(rows))))
    return f"<p class=note>{note}</p>" + _claim_rows(rows)


def saved_claims(path: Path, title: str, command: str) -> str:
    """A study's judged claims as ``m3t claims`` saved them (``claims.json``), its judged rows only."""
    if not path.exists():
        return f"<h2>{h.esc(title)}</h2>" + h.empty(f"Not run yet: <code>{h.esc(command)}</code>.")
    saved = json.loads(path.read_text())
    rows = [r for r in saved.get("claims", []) if r["verdict"] != "not run"]
    note = CLAIMS_NOTE + stability_line(stability(rows)) + f" ({path}, from {command})"
    return f"<h2>{h.esc(title)}</h2><p class=note>{h.esc(note)}</p>" + _claim_rows(rows)


def sgsa_study(path: Path) -> str:
    """The SGSA study's claims (``m3t sgsa-study``: ``claims.json``): verdicts with their seeds and hierarchical
    intervals, and how many verdicts flip between two disjoint halves of the seeds."""
    if not path.exists():
        return h.empty("No SGSA study yet: run <code>m3t sgsa-study --seeds 0 1 2 3 4</code>.")
    summary = json.loads(path.read_text())
    body = []
    for r in summary.get("comparisons", []):
        metric, mean_a, mean_b, difference, low, high = in_display_units(r)
        body.append([r["claim"], r["counter"], metric, f"{r['a']} {mean_a:.4g} -> {r['b']} {mean_b:.4g}",
                     f"{difference:.3g} [{low:.3g}, {high:.3g}]", r["verdict"]])
    steady = summary.get("stability") or {}
    if steady.get("compared"):
        first, second = steady["halves"]
        stability = (f"Judged again on seeds {first} and on seeds {second} separately, {steady['flipped']} of "
                     f"{steady['compared']} verdicts flip ({100 * steady['share_flipped']:.0f} %): a verdict that "
                     "one set of retrains gives and the other does not is not a finding.")
    else:
        stability = "One seed: no stability check (it needs two disjoint seed sets)."
    note = (f"SGSA study on the {summary.get('split', '?')} split, seeds {summary.get('seeds', [])}: B - A of the "
            "seed-averaged means over clips, 95 % hierarchical bootstrap over each side's seeds and the clips. "
            + stability)
    header = ["claim", "counter", "metric", "A -> B", "B - A [95 % interval]", "verdict"]
    return f"<h2>SGSA study</h2><p class=note>{h.esc(note)}</p>" + h.table(header, body, "sgsa-study")


def repeatability(path: Path) -> str:
    """Which digits of the training stages' figures repeat under other arithmetic: ``bench_reproducible.py``'s
    result (each stage at the machine's arithmetic and under ``M3T_REPRODUCIBLE=1``, same data and seeds)."""
    if not path.exists():
        return ("<h2>Which digits repeat</h2>" + h.empty("Not measured here yet: run <code>python "
                                                         "benchmarks/bench_reproducible.py</code>."))
    result = json.loads(path.read_text())
    body = []
    for stage, values in result.get("stages", {}).items():
        for figure, pair in values.get("figures", {}).items():
            old, new = pair.get("old"), pair.get("new")
            digits = agreeing_digits(float(old), float(new)) if None not in (old, new) else None
            body.append([stage, figure, f"{old:.6g}", "-" if new is None else f"{new:.6g}",
                         "-" if digits is None else ("all" if digits >= 15 else str(digits))])
    note = (f"Each training stage run twice on the same data and seeds, on {result.get('machine', '?')} "
            f"({result.get('cpu_count', '?')} cores): with the machine's own arithmetic and with the pinned one "
            f"(M3T_REPRODUCIBLE=1, {result.get('cost', float('nan')):.2f}x the time). Only the float order differs, "
            "so the digits the two share are those another machine can be expected to repeat. Under the mode every "
            "digit repeated across thread counts and kernel settings on one machine (tests/base/test_arithmetic.py). Seeds "
            "move the figures as much or more: see each claim's std over seeds.")
    return (f"<h2>Which digits repeat</h2><p class=note>{h.esc(note)}</p>"
            + h.table(["stage", "figure", "machine arithmetic", "pinned arithmetic", "digits that agree"], body,
                      "repeatability"))


def _token_counts(record: RunRecord) -> dict[str, dict]:
    if record.artifact_dir is None:
        return {}
    files = sorted(record.artifact_dir.glob("plots/tokens_*.json"))
    return {json.loads(f.read_text())["group"]: json.loads(f.read_text()) for f in files}


def codebooks(runs: list[RunRecord], params: Params) -> str:
    import plotly.graph_objects as go

    newest = newest_finished(_stage(runs, "train-tokenizers") + _stage(runs, "evaluate-tokenizers"),
                             lambda r: r.tags.get("quantizer", "?"))
    if not newest:
        return h.empty("No tokenizer run yet: run <code>dvc repro train-tokenizers</code>.")
    groups = ("body", "hand", "face")
    bars = go.Figure([go.Bar(name=q.upper(), x=list(groups),
                             y=[r.metrics.get(f"{g}/utilisation_pct") for g in groups]) for q, r in newest.items()])
    bars.update_layout(title="codebook utilisation on the test split (%)", barmode="group", yaxis_range=[0, 100])
    out = [f"<figure>{_figure(bars, 'utilisation')}</figure>"]
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
            out.append(f"<figure>{_figure(fig, f'tokens-{group}')}</figure>")
    return "".join(out)


# ------------------------------------------------------------------------------------------------ quality
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
            out.append(f"<div><figure>{_figure(fig, f'reproj-{corpus}')}</figure>"
                       f"<figure>{_figure(missing, f'missing-{corpus}')}</figure></div>")
        out.append("</div>")
    return "".join(out) or h.empty("No corpus configured in params.yaml <code>corpora</code>.")


# ------------------------------------------------------------------------------------------------ videos
def videos(runs: list[RunRecord], media: Path) -> str:
    """The newest evaluation videos of each production model, grouped by test clip, copied under ``media``."""
    clips: dict[str, list[tuple[str, str]]] = defaultdict(list)
    for stage, label in (("evaluate-smlm", "SMLM, body surface"), ("evaluate-sgsa", "PT / SGSA / SMLM, skeletons")):
        record = next((r for r in _stage(runs, stage) if r.status == "FINISHED" and r.artifact_dir
                       and any(r.artifact_dir.rglob("*.mp4"))), None)
        if record is None:
            continue
        for video in sorted(record.artifact_dir.rglob("*.mp4")):
            target = media / stage / video.name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(video, target)
            clip = video.stem.removesuffix("_skeleton")  # the SMLM's skeleton overlay beside its mesh video
            kind = "SMLM, skeleton" if clip != video.stem else label
            clips[clip].append((f"{kind} ({_name(record)})", f"media/{stage}/{video.name}"))
    if not clips:
        return h.empty("No rendered video yet: <code>dvc repro generate-smlm evaluate-smlm evaluate-sgsa</code> "
                       "renders the first test clips (<code>smlm_generate.render_clips</code>, "
                       "<code>sgsa_evaluate.render_clips</code>).")
    out = ["<p class=note>Each video shows the reference beside the model's output for the same test clip.</p>"]
    for clip, items in sorted(clips.items()):
        figures = "".join(f'<figure><video controls muted preload=metadata src="{h.esc(src)}"></video>'
                          f"<figcaption>{h.esc(label)}</figcaption></figure>" for label, src in items)
        out.append(f"<h2>{h.esc(clip)}</h2>{figures}")
    return "".join(out)


# ------------------------------------------------------------------------------------------------ runs
FILTER_JS = """
<script>
function filterRuns(){
  const stage=document.getElementById('stage').value, tag=document.getElementById('tag').value.trim().toLowerCase();
  const sched=document.getElementById('scheduled').checked; let shown=0;
  for(const row of document.querySelectorAll('#runs tbody tr')){
    const ok=(!stage||row.dataset.stage===stage)&&(!tag||row.dataset.tags.toLowerCase().includes(tag))
      &&(!sched||row.dataset.tags.includes('scheduled=true'));
    row.style.display=ok?'':'none'; if(ok) shown++;
  }
  document.getElementById('shown').textContent=shown;
}
function compareRuns(){
  const data=JSON.parse(document.getElementById('run-data').textContent);
  const ids=[...document.querySelectorAll('#runs input.pick:checked')].map(b=>b.value);
  const runs=ids.map(i=>data[i]); const out=document.getElementById('compare');
  if(runs.length<2){out.innerHTML='<p class=note>Tick two runs or more.</p>';return;}
  const esc=s=>String(s).replace(/[&<>"]/g,c=>({'&':'&amp;','<':'&lt;','>':'&gt;','"':'&quot;'}[c]));
  const rows=[];
  const params=[...new Set(runs.flatMap(r=>Object.keys(r.params)))].sort()
    .filter(k=>new Set(runs.map(r=>r.params[k])).size>1);
  for(const k of params) rows.push(['param '+k,...runs.map(r=>r.params[k]??'')]);
  const metrics=[...new Set(runs.flatMap(r=>Object.keys(r.metrics)))].sort();
  for(const k of metrics) rows.push([k,...runs.map(r=>k in r.metrics?Number(r.metrics[k]).toPrecision(4):'')]);
  out.innerHTML='<table id=compare-table><thead><tr><th></th>'+runs.map(r=>'<th>'+esc(r.name)+'</th>').join('')
    +'</tr></thead><tbody>'+rows.map(r=>'<tr>'+r.map((c,i)=>(i?'<td class=num>':'<td>')+esc(c)+'</td>').join('')+'</tr>').join('')
    +'</tbody></table>';
}
</script>"""


def runs_page(runs: list[RunRecord]) -> str:
    if not runs:
        return h.empty(f"No runs yet: run {PIPELINE}.")
    stages = sorted({r.stage for r in runs})
    options = "".join(f"<option>{h.esc(s)}</option>" for s in stages)
    rows = []
    for r in runs:
        tags = " ".join(f"{k}={v}" for k, v in sorted(r.tags.items()) if not k.startswith("mlflow."))
        cells = "".join(f"<td>{h.esc(c)}</td>" for c in (_name(r), r.stage, r.status, _when(r), r.run_id[:8], tags,
                                                          len(r.metrics)))
        pick = f'<td><input type=checkbox class=pick value="{h.esc(r.run_id)}"></td>'
        rows.append(f'<tr data-stage="{h.esc(r.stage)}" data-tags="{h.esc(tags)}">{pick}{cells}</tr>')
    head = "".join(f"<th>{c}</th>" for c in ("", "run", "stage", "status", "started", "id", "tags", "metrics"))
    data = {r.run_id: {"name": _name(r), "params": r.params, "metrics": r.metrics} for r in runs}
    # "</" cannot end the script element early once escaped: the JSON stays one text node
    payload = json.dumps(data).replace("</", "<\\/")
    return (f"{FILTER_JS}<div class=filters><label>stage <select id=stage onchange=filterRuns()><option value=''>all"
            f"</option>{options}</select></label><label>tag contains <input id=tag oninput=filterRuns() "
            f"placeholder='quantizer=fsq'></label><label><input type=checkbox id=scheduled onchange=filterRuns()> "
            f"scheduled only</label> <span id=shown>{len(runs)}</span> shown "
            f"<button id=compare-button onclick=compareRuns()>compare ticked runs</button></div><div id=compare></div>"
            f'<script type="application/json" id="run-data">{payload}</script>'
            f"<table id=runs><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>")
