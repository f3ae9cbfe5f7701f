"""The overview (index page: runs per stage) and the runs page (every run, filtered by stage / tag, ticked runs
compared side by side)."""
from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

from dashboards import html as h
from dashboards.sections.common import PIPELINE, run_name, started
from m3t.config import Params
from m3t.experiment import RunRecord


def overview(runs: list[RunRecord], params: Params, root: str | Path) -> str:
    if not runs:
        return h.empty(f"No runs in the MLflow store yet (<code>{h.esc(params.experiment.tracking_uri)}</code>, "
                       f"experiment <code>{h.esc(params.experiment.experiment)}</code>). Run the embedded pipeline "
                       f"with {PIPELINE}, then rebuild this page with <code>python -m dashboards.build</code>.")
    by_stage: dict[str, list[RunRecord]] = defaultdict(list)
    for r in runs:
        by_stage[r.stage].append(r)
    rows = [(stage, len(rs), sum(r.status == "FINISHED" for r in rs), sum(r.tags.get("scheduled") == "true" for r in rs),
             run_name(rs[0]), started(rs[0]), rs[0].status) for stage, rs in sorted(by_stage.items())]
    body = h.table(("stage", "runs", "finished", "scheduled", "newest run", "started", "status"), rows, "stages")
    return (f"<p>{len(runs)} runs in experiment <code>{h.esc(params.experiment.experiment)}</code>. Pages: the paper "
            "tables filled from the newest runs, training curves, codebooks, data quality, videos, and every run "
            "with a filter.</p>" + body)


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
        cells = "".join(f"<td>{h.esc(c)}</td>" for c in (run_name(r), r.stage, r.status, started(r), r.run_id[:8], tags,
                                                          len(r.metrics)))
        pick = f'<td><input type=checkbox class=pick value="{h.esc(r.run_id)}"></td>'
        rows.append(f'<tr data-stage="{h.esc(r.stage)}" data-tags="{h.esc(tags)}">{pick}{cells}</tr>')
    head = "".join(f"<th>{c}</th>" for c in ("", "run", "stage", "status", "started", "id", "tags", "metrics"))
    data = {r.run_id: {"name": run_name(r), "params": r.params, "metrics": r.metrics} for r in runs}
    # "</" cannot end the script element early once escaped: the JSON stays one text node
    payload = json.dumps(data).replace("</", "<\\/")
    return (f"{FILTER_JS}<div class=filters><label>stage <select id=stage onchange=filterRuns()><option value=''>all"
            f"</option>{options}</select></label><label>tag contains <input id=tag oninput=filterRuns() "
            f"placeholder='quantizer=fsq'></label><label><input type=checkbox id=scheduled onchange=filterRuns()> "
            f"scheduled only</label> <span id=shown>{len(runs)}</span> shown "
            f"<button id=compare-button onclick=compareRuns()>compare ticked runs</button></div><div id=compare></div>"
            f'<script type="application/json" id="run-data">{payload}</script>'
            f"<table id=runs><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>")
