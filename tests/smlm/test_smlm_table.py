"""The SMLM comparison table (:func:`m3t.smlm.table.production_table`): which run each row shows (the newest
finished run of each variant), its groups and columns, on hand-made run records. Written to pin behaviours that
mutation testing found unchecked (the table's only other test is the slow end-to-end flow)."""
from __future__ import annotations

from m3t.experiment import RunRecord
from m3t.smlm.table import production_table


def run(run_id: str, variant: str | None, value: float, status: str = "FINISHED", bleu: float | None = None,
        groups=("synthetic/ASL-SYN",)) -> RunRecord:
    metrics = {}
    for i, group in enumerate(groups):
        for j, key in enumerate(("dtw_pa_jpe_body_m", "dtw_pa_jpe_hand_m", "dtw_jpe_body_m", "dtw_jpe_hand_m")):
            metrics[f"{group}/{key}"] = value + i + j / 10
    if bleu is not None:
        metrics["translation_bleu4"] = bleu
    return RunRecord(run_id, "evaluate-smlm", 0, status, {}, metrics, None, {"variant": variant} if variant else {})


def test_each_variant_shows_its_newest_finished_run_in_name_order():
    records = [run("failed", "production only", 9.0, status="FAILED"), run("b-new", "production only", 1.0),
               run("a-new", "production + translation", 2.0, bleu=12.345), run("b-old", "production only", 5.0),
               run("abcdefgh-untagged", None, 3.0)]
    lines = production_table(records).splitlines()
    assert lines[0] == ("| variant | synthetic/ASL-SYN PA body | synthetic/ASL-SYN PA hand | synthetic/ASL-SYN JPE body "
                        "| synthetic/ASL-SYN JPE hand | BLEU-4 |")
    assert lines[2:] == ["| abcdefgh | 3.000 | 3.100 | 3.200 | 3.300 | - |",
                         "| production + translation | 2.000 | 2.100 | 2.200 | 2.300 | 12.35 |",
                         "| production only | 1.000 | 1.100 | 1.200 | 1.300 | - |"]


def test_groups_are_the_union_of_the_runs_sorted_and_a_missing_one_is_a_dash():
    records = [run("x", "a", 1.0, groups=("sent/DGS", "iso/ASL")), run("y", "b", 2.0, groups=("iso/ASL",))]
    lines = production_table(records, variant_tag="variant").splitlines()
    assert lines[0].split(" | ")[1] == "iso/ASL PA body" and lines[0].split(" | ")[5] == "sent/DGS PA body"
    assert lines[3].split(" | ")[5:9] == ["-", "-", "-", "-"]
    assert production_table([run("f", "a", 1.0, status="FAILED")]).startswith("no finished evaluate-smlm runs")
    # another tag names the rows
    tagged = RunRecord("z", "evaluate-smlm", 0, "FINISHED", {}, {"g/dtw_jpe_body_m": 1.0}, None, {"arm": "left"})
    assert "| left |" in production_table([tagged], variant_tag="arm")
