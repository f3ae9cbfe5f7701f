"""The M3T Tab. 1-style comparison from MLflow: one row per SMLM variant (newest finished evaluate-smlm run
of each), columns DTW-PA-JPE and DTW-JPE for body and hands per ``<corpus>/<language>`` group.

Values are SOKE's raw DTW accumulated cost in metres (the numbers of the paper's table); the
path-length-normalised variant is in the run's metrics as ``..._pathnorm_m``.
"""
from __future__ import annotations

from m3t.experiment import RunRecord, newest_finished, variant_of
from m3t.reporting import fixed, markdown_table

COLUMNS = (("dtw_pa_jpe_body_m", "PA body"), ("dtw_pa_jpe_hand_m", "PA hand"),
           ("dtw_jpe_body_m", "JPE body"), ("dtw_jpe_hand_m", "JPE hand"))


def production_table(records: list[RunRecord], variant_tag: str = "variant", baselines: list[RunRecord] = ()) -> str:
    """Markdown table over the newest finished run of each variant; ``records`` newest first. ``baselines``:
    evaluate-baselines runs (one per system), each the newest finished one a row ``baseline: <system>`` below
    the models, scored on the same clips by the same scorer."""
    rows = newest_finished(records, lambda r: r.tags.get(variant_tag, r.run_id[:8]))
    if not rows:
        return "no finished evaluate-smlm runs yet: run `dvc repro evaluate-smlm`"
    named = [(name, record) for name, record in sorted(rows.items())]
    # the columns are the models' groups: a baseline run also logs its skeleton-path figures (<system>/<split>/..)
    groups = sorted({k.rsplit("/", 1)[0] for _, r in named for k in r.metrics if k.endswith("/dtw_jpe_body_m")})
    named += [(f"baseline: {name}", record) for name, record in baseline_rows(baselines)]
    header = ["variant", *(f"{g} {label}" for g in groups for _, label in COLUMNS), "BLEU-4"]
    body = [[name, *(fixed(record.metrics.get(f"{g}/{key}"), 3) for g in groups for key, _ in COLUMNS),
             fixed(record.metrics.get("translation_bleu4"), 2)] for name, record in named]
    return markdown_table(header, body)


BASELINE_ORDER = ("retrieval", "lexicon")


def baseline_rows(records: list[RunRecord]) -> list[tuple[str, RunRecord]]:
    """The newest finished evaluate-baselines run of each system (its ``variant`` tag), retrieval first."""
    newest = newest_finished(records, variant_of)
    order = {name: i for i, name in enumerate(BASELINE_ORDER)}
    return sorted(newest.items(), key=lambda kv: (order.get(kv[0], len(order)), kv[0]))
