"""The claims page: the papers' claims judged on the runs, a study's saved verdicts, and which digits of the
training figures repeat under other arithmetic."""
from __future__ import annotations

import json
from pathlib import Path

from dashboards import html as h
from m3t.claims.report import stability_line
from m3t.claims.verdicts import claims_table, stability
from m3t.experiment import RunRecord
from m3t.metrics.stats import agreeing_digits


def _claim_rows(rows: list[dict]) -> str:
    """The claims table of judged rows (:func:`m3t.claims.verdicts.claims_table`'s, live or read from a claims.json)."""
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
    """Every claim of :data:`m3t.claims.definitions.CLAIMS` judged on the runs (what ``m3t claims`` writes)."""
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
