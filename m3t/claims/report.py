"""The judged claims written out: the stability sentence, the table cells shared with the docs pages, claims.md
and claims.json (:func:`write_claims`)."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from m3t.atomic import write_json, write_text
from m3t.claims.definitions import MOTION_DEFINITION, TEXT_DEFINITION
from m3t.claims.verdicts import claims_table, stability
from m3t.experiment import RunRecord
from m3t.reporting import markdown_table, significant


def stability_line(summary: dict) -> str:
    """One sentence on :func:`~m3t.claims.verdicts.stability` for claims.md and the dashboard."""
    if not summary["compared"]:
        return "Stability: no claim has 2 seeds yet, so none could be judged again on two disjoint seed halves."
    return (f"Stability: judged again on two disjoint halves of their seeds (first half, rest), {summary['flipped']} "
            f"of {summary['compared']} claims flip their verdict ({100 * summary['share_flipped']:.0f} %)"
            + (": " + "; ".join(f"{f['claim']} ({' / '.join(f['verdicts'])})" for f in summary["flips"])
               if summary["flips"] else "") + ".")


def _fmt(value: float | None) -> str:
    return significant(value, whole_from=100)


def means_cell(row: dict, fmt: Callable[[float], str], fmt_sd: Callable[[float], str]) -> str:
    """A judged row's ``A mean +- SD -> B mean +- SD``, means by ``fmt`` and SDs by ``fmt_sd``."""
    return (f"{row['a']} {fmt(row['mean_a'])} +- {fmt_sd(row['std_a'])} -> {row['b']} {fmt(row['mean_b'])} +- "
            f"{fmt_sd(row['std_b'])}")


def interval_cell(row: dict, fmt: Callable[[float], str]) -> str:
    """A judged row's ``value [low, high]`` by ``fmt``, then its equivalence band when the claim has one."""
    low, high = row["interval95"]
    band = f" (band {row['band'][0]:g} +- {row['band'][1]:g})" if row.get("band") else ""
    return f"{fmt(row['value'])} [{fmt(low)}, {fmt(high)}]{band}"


def claims_markdown(rows: list[dict], min_seeds: int) -> str:
    intro = (f"Claims of M3T and SGSA on this platform's runs. Ours: A -> B as mean +- std over seeds; the 95 % "
             f"interval is a hierarchical bootstrap over training seeds and test clips (over seeds for codebook "
             f"statistics), so it includes how much a retrained model moves. Verdicts need >= {min_seeds} seeds. "
             "Metric definitions in the metric column.")
    body = []
    for r in rows:
        if r["verdict"] == "not run":
            body.append([r["claim"], r["source"], r["paper"], r["metric"], "-", "-", f"not run: {r['note']}", 0, "-"])
            continue
        runs = ", ".join(sorted({i[:8] for i in r["runs_a"] + r["runs_b"]}))
        verdict = r["verdict"] + (f" ({r['note']})" if r["note"] else "")
        body.append([r["claim"], r["source"], r["paper"], r["metric"], means_cell(r, _fmt, _fmt),
                     f"{r['compared']} {interval_cell(r, _fmt)}", verdict, len(r["seeds"]), runs])
    table = markdown_table(["claim", "source", "paper", "metric", "ours: A -> B", "compared [95 % interval]", "verdict",
                            "seeds", "runs"], body)
    return "\n".join([intro, "", table, "", stability_line(stability(rows))]) + "\n"


def write_claims(records: list[RunRecord], out_dir: str | Path, min_seeds: int = 3) -> list[dict]:
    """Judge every claim and write ``claims.json`` and ``claims.md`` into ``out_dir``."""
    rows = claims_table(records, min_seeds)
    out = Path(out_dir)
    write_json(out / "claims.json", {"min_seeds": min_seeds, "motion_definition": MOTION_DEFINITION,
                                     "text_definition": TEXT_DEFINITION, "claims": rows,
                                     "stability": stability(rows)})
    write_text(out / "claims.md", claims_markdown(rows, min_seeds))
    return rows
