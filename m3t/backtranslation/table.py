"""M3T Tab. 2 from MLflow: back-translation of the ground-truth motion (the upper bound, newest finished
``evaluate-backtranslation`` run) and of each production model's generated motion (newest finished
``evaluate-smlm`` run of each training variant: without / with the translation objective), ROUGE-L and
BLEU-4 per sign language, in the SL-T definition (lower-cased whitespace tokens, unsmoothed BLEU, ROUGE-L
beta 1.2, Chinese per character; :mod:`m3t.metrics.text`). Any future production model's evaluation that
logs the same ``bt/slt/<language>/...`` metrics gets a row.
"""
from __future__ import annotations

from m3t.experiment import RunRecord, newest_finished, variant_of
from m3t.metrics.text import SLT_DEFINITION
from m3t.reporting import fixed, markdown_table

GT_ROW = "GT motion (upper bound)"
VARIANT_ORDER = ("production only", "production + translation")


def backtranslation_table(ground_truth: list[RunRecord], production: list[RunRecord],
                          baselines: list[RunRecord] = ()) -> str:
    """Markdown: one row for the ground truth, one per production variant, one per baseline system (the newest
    finished evaluate-baselines run of each: same clips, same judge); ``R`` / ``B4`` per language."""
    from m3t.smlm.table import baseline_rows

    rows: list[tuple[str, dict[str, float]]] = []
    gt = newest_finished(ground_truth, lambda r: "gt")
    if gt:
        rows.append((GT_ROW, {k.removeprefix(f"{SLT_DEFINITION}/"): v for k, v in gt["gt"].metrics.items()}))
    variants = newest_finished([r for r in production if any(k.startswith("bt/") for k in r.metrics)], variant_of)
    order = {v: i for i, v in enumerate(VARIANT_ORDER)}
    prefix = f"bt/{SLT_DEFINITION}/"

    def judged(record: RunRecord) -> dict[str, float]:
        return {k.removeprefix(prefix): v for k, v in record.metrics.items() if k.startswith(prefix)}

    for name, record in sorted(variants.items(), key=lambda kv: (order.get(kv[0], len(order)), kv[0])):
        rows.append((f"SMLM, {name}", judged(record)))
    rows += [(f"baseline: {name}", judged(record)) for name, record in baseline_rows(baselines)]
    if not rows:
        return ("no finished evaluate-backtranslation / evaluate-smlm runs with back-translation yet: "
                "run `dvc repro evaluate-smlm`")
    languages = sorted({k.split("/")[0] for _, m in rows for k in m if k.endswith("/bleu4")})
    header = ["motion", *(f"{lang} {name}" for lang in languages for name in ("R", "B4"))]
    body = [[name, *(fixed(metrics.get(f"{lang}/{key}"), 2) for lang in languages for key in ("rouge_l", "bleu4"))]
            for name, metrics in rows]
    title = (f"Back-translation (text metrics: definition {SLT_DEFINITION!r}, SL-T: lower-cased whitespace tokens, "
             "BLEU-4 unsmoothed, ROUGE-L beta 1.2, Chinese per character)")
    return "\n".join([title, "", markdown_table(header, body)])
