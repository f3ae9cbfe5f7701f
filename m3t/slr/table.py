"""The M3T Tab. 4 layout of the probe's scores: one row per probe variant (full, without face), columns
Top-1 / Top-5 overall, on the confusing and on the normal subset, each with its bootstrap interval; a chance
row; as CSV (one wide row per variant, numbers only) and as Markdown (what the paper prints, plus clip and
class counts and what chance means).
"""
from __future__ import annotations

import math

from m3t.experiment import RunRecord, newest_finished
from m3t.reporting import csv_text, fixed, markdown_table
from m3t.slr.evaluate import PAIR_CHANCE_TOP1, Evaluation, Score, evaluations_from_flat

METHODS = {"full": "M3T probe (body, hands, face)", "no_face": "M3T probe w/o face"}
SUBSET_LABELS = {"overall": "Overall", "confusing": "Conf.", "normal": "Norm."}
METRICS = {"top1": "T-1", "top5": "T-5"}


def _cell(score: Score | None) -> str:
    if score is None or math.isnan(score.value):
        return "-"
    return f"{score.value:.1f} [{score.ci_low:.1f}, {score.ci_high:.1f}]"


def table_csv(evaluations: dict[str, Evaluation]) -> str:
    """One row per variant: ``<subset>_<metric>`` with ``_ci_low`` / ``_ci_high`` / ``_chance``, clip and class
    counts per subset, and ``confusing_pair_top1`` where pairs are known; empty cells where unavailable."""
    rows = []
    for variant, ev in evaluations.items():
        row = {"variant": variant, "method": METHODS.get(variant, variant),
               "subsets_available": str(ev.subsets_available).lower()}
        for subset in SUBSET_LABELS:
            s = ev.scores.get(subset)
            row[f"{subset}_clips"] = "" if s is None else str(s.clips)
            row[f"{subset}_classes"] = "" if s is None else str(s.classes)
            for metric in METRICS:
                score = None if s is None else getattr(s, metric)
                for key, attr in (("", "value"), ("_ci_low", "ci_low"), ("_ci_high", "ci_high"), ("_chance", "chance")):
                    row[f"{subset}_{metric}{key}"] = fixed(None if score is None else getattr(score, attr), 4, "")
        pair = ev.scores["confusing"].pair_top1 if "confusing" in ev.scores else None
        for key, attr in (("", "value"), ("_ci_low", "ci_low"), ("_ci_high", "ci_high"), ("_chance", "chance")):
            row[f"confusing_pair_top1{key}"] = fixed(None if pair is None else getattr(pair, attr), 4, "")
        rows.append(row)
    return csv_text(rows, list(rows[0]) if rows else ["variant"])


def table_markdown(evaluations: dict[str, Evaluation], corpus: str, split: str, confidence: float = 0.95) -> str:
    """Tab. 4 as Markdown: accuracies in % with ``[low, high]`` bootstrap intervals, a chance row, footnotes."""
    if not evaluations:
        return "no probe evaluated yet: run `dvc repro evaluate-slr`"
    first = next(iter(evaluations.values()))
    pairs = any("confusing" in ev.scores and ev.scores["confusing"].pair_top1 is not None
                for ev in evaluations.values())
    columns = [(s, m) for s in SUBSET_LABELS for m in METRICS]
    header = ["Method"] + [f"{SUBSET_LABELS[s]} {METRICS[m]}" for s, m in columns]
    header += ["Conf. pair T-1"] if pairs else []
    body = []
    for variant, ev in evaluations.items():
        cells = [_cell(getattr(ev.scores[s], m)) if s in ev.scores else "n/a" for s, m in columns]
        if pairs:
            cells.append(_cell(ev.scores["confusing"].pair_top1) if "confusing" in ev.scores else "n/a")
        body.append([METHODS.get(variant, variant), *cells])
    chance = [f"{getattr(first.scores['overall'], m).chance:.1f}" for _, m in columns]
    chance += [f"{PAIR_CHANCE_TOP1:.1f}"] if pairs else []
    body.append(["chance (uniform guess)", *chance])
    overall = first.scores["overall"]
    notes = [f"{corpus}, {split} split; accuracies in %, [{100 * confidence:.0f}% percentile bootstrap interval "
             "over clips].",
             f"Overall: {overall.clips} clip(s) of {overall.classes} class(es); chance = a uniform guess over the "
             "probe's classes (T-1 1/C, T-5 5/C)."]
    if first.subsets_available:
        for name in ("confusing", "normal"):
            s = first.scores[name]
            notes.append(f"{name.capitalize()}: {s.clips} clip(s) of {s.classes} class(es).")
        notes.append("Confusing signs share their manual form with another sign: a probe that reads hands and body "
                     "right but nothing from the face is at 1/k among the k manual-identical signs (50% for pairs).")
        if pairs:
            notes.append("Conf. pair T-1: the argmax over the two classes of the clip's manual-identical pair only "
                         "(chance 50%): the face alone decides.")
    else:
        notes.append(f"Subsets unavailable: {first.subsets_reason}")
    return markdown_table(header, body) + "\n\n" + "\n".join(f"- {n}" for n in notes) + "\n"


def recognition_table(records: list[RunRecord]) -> str:
    """Tab. 4 as Markdown from the newest finished evaluate-slr run (``records`` newest first), for the CLI."""
    for record in newest_finished(records, lambda r: "newest").values():
        evaluations = evaluations_from_flat(record.metrics, record.tags.get("subsets_reason", ""))
        order = {v: i for i, v in enumerate(METHODS)}
        evaluations = dict(sorted(evaluations.items(), key=lambda kv: order.get(kv[0], len(order))))
        confidence = float(record.params.get("slr_evaluate.confidence", 0.95))
        return table_markdown(evaluations, record.tags.get("corpus", "?"), record.tags.get("split", "?"), confidence)
    return "no finished evaluate-slr runs yet: run `dvc repro evaluate-slr`"
