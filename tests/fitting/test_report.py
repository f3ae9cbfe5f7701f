"""The data-quality files, run statistics, import and run summaries and the run log of fit-corpus
(:mod:`m3t.fitting.report`, :mod:`m3t.fitting.quality`), and the quarantine records of a listing's refused rows.
Written to pin behaviours that mutation testing found unchecked.
"""
from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from m3t.corpora.clip import Clip
from m3t.fitting.per_clip import NO_EXTERNAL
from m3t.fitting.report import ClipOutcome


# ------------------------------------------------------------------------------------------ reports
def test_the_quality_report_counts_fits_cache_hits_quarantines_and_missing_parts():
    from m3t.fitting.quality import quality_report

    seen = {"missing_left_hand": 0.0, "missing_right_hand": 0.5, "missing_face": 0.1}
    outcomes = [
        ClipOutcome("e", "test", "quarantined", reason="ValueError: the fit diverged", group="ValueError",
                    file="motion/e.npz", track_frames=20,
                    coverage={"missing_left_hand": 1.0, "missing_right_hand": 1.0, "missing_face": 1.0}),
        ClipOutcome("b", "dev", "cached", "parts/b.parquet", frames=30, track_frames=30,
                    coverage={"missing_left_hand": 0.2, "missing_right_hand": 0.0, "missing_face": 0.0},
                    metrics={"reproj_px_parts": 4.0, "reproj_shoulder_frac": 0.04}, init={"init_source": NO_EXTERNAL}),
        ClipOutcome("", "", "quarantined", reason="no split", group="listing: no split", file="index.csv", row=7,
                    from_listing=True),
        ClipOutcome("a", "train", "fitted", "parts/a.parquet", frames=10, track_frames=10, coverage=seen,
                    metrics={"reproj_px_parts": 2.0, "reproj_shoulder_frac": 0.02, "reproj_px_pose": 1.5,
                             "pa_joint_mm": 9.0}, init={"init_source": "simulated tracker initialisation"}),
        ClipOutcome("c", "train", "quarantined", reason="FileNotFoundError: gone", group="FileNotFoundError",
                    file="motion/c.npz"),
    ]
    report = quality_report(outcomes, "synthetic")
    assert [(r["clip_id"], r["status"]) for r in report.rows] == [
        ("a", "fitted"), ("b", "fitted"), ("", "quarantined"), ("c", "quarantined"), ("e", "quarantined")]
    a, b, listing = report.rows[:3]
    assert (a["missing_right_hand"], a["reproj_px_pose"], a["init_source"], a["frames"]) == (
        0.5, 1.5, "simulated tracker initialisation", 10)
    assert "pa_joint_mm" not in a and a["reproj_px_face"] == "" and a["row"] == ""
    assert (b["split"], b["reproj_px_parts"], b["init_source"]) == ("dev", 4.0, NO_EXTERNAL)
    assert (listing["file"], listing["row"], listing["group"], listing["reason"]) == ("index.csv", 7,
                                                                                      "listing: no split", "no split")
    s = report.summary
    assert (s["corpus"], s["clips_listed"], s["clips_fitted"], s["clips_quarantined"],
            s["clips_quarantined_at_listing"], s["frames"]) == ("synthetic", 4, 2, 3, 1, 40)
    assert s["quarantine_reasons"] == {"listing: no split": 1, "FileNotFoundError": 1, "ValueError": 1}
    assert s["init_sources"] == {"simulated tracker initialisation": 1, "rest pose": 1}
    # every tracked clip counts (the quarantined one too): frame-weighted overall, plain mean per clip
    assert s["missing_left_hand_ratio"] == pytest.approx((0.0 * 10 + 0.2 * 30 + 1.0 * 20) / 60)
    assert s["missing_left_hand_ratio_clip_mean"] == pytest.approx(0.4)
    assert s["missing_right_hand_ratio"] == pytest.approx((0.5 * 10 + 1.0 * 20) / 60)
    assert (s["reproj_px_parts_median"], s["reproj_px_parts_max"]) == (3.0, 4.0)
    assert s["reproj_px_parts_p90"] == pytest.approx(3.8) and s["reproj_shoulder_frac_max"] == 0.04

    empty = quality_report([ClipOutcome("x", "train", "quarantined", group=None)], "slt")
    assert empty.summary["quarantine_reasons"] == {"unknown": 1} and empty.summary["frames"] == 0
    assert math.isnan(empty.summary["missing_face_ratio"]) and math.isnan(empty.summary["reproj_px_parts_median"])


def test_quality_files_hold_rounded_rows_and_null_for_missing_values(tmp_path):
    from m3t.atomic import write_text
    from m3t.fitting.quality import COLUMNS, quality_report, write_quality

    report = quality_report([ClipOutcome("a", "train", "fitted", frames=3, metrics={"reproj_px_parts": 1 / 3})], "x")
    csv_path, json_path = write_quality(report, tmp_path, write_text)
    rows = list(csv.DictReader(csv_path.open()))
    assert tuple(rows[0]) == COLUMNS and rows[0]["reproj_px_parts"] == "0.3333" and rows[0]["frames"] == "3"
    summary = json.loads(json_path.read_text())
    assert summary["missing_face_ratio"] is None and summary["reproj_px_parts_median"] == pytest.approx(1 / 3)


def test_the_import_summary_covers_imported_clips_only():
    from m3t.fitting.report import import_summary

    imported = {"init_source": "imported: slt sign arrays, no tracking or fitting"}
    outcomes = [
        ClipOutcome("i1", "train", "fitted", frames=10, init=imported,
                    metrics={"src_nonfinite_frame_frac": 0.1, "src_sign_min": -2.0, "src_sign_max": 3.0,
                             "src_betas_frame_std": 0.5}),
        ClipOutcome("i2", "dev", "cached", frames=30, init=imported,
                    metrics={"src_nonfinite_frame_frac": 0.0, "src_sign_min": -1.0, "src_sign_max": 5.0}),
        ClipOutcome("f", "train", "fitted", frames=50, init={"init_source": "simulated tracker initialisation"},
                    metrics={"src_sign_min": -100.0}),
        ClipOutcome("n", "train", "fitted", frames=50, metrics={"src_sign_max": 100.0}),
        ClipOutcome("q", "train", "quarantined", init=imported, metrics={"src_sign_max": 100.0}),
    ]
    assert import_summary(outcomes) == {"imported_clips": 2, "imported_nonfinite_frame_frac": pytest.approx(0.025),
                                        "imported_sign_min": -2.0, "imported_sign_max": 5.0}
    assert import_summary(outcomes[2:]) == {}
    no_frames = import_summary([dataclasses.replace(outcomes[0], frames=0)])
    assert no_frames["imported_clips"] == 1 and math.isnan(no_frames["imported_nonfinite_frame_frac"])


def test_the_listings_refused_rows_become_quarantine_records():
    from m3t.corpora.listing import Listing, Quarantined
    from m3t.fitting.corpus import listing_outcomes

    listing = Listing((), (Quarantined("index.csv", 7, "c7", "no split: 'val' is not train, dev or test; fix row 7"),
                           Quarantined("annotations/train.corpus.csv", 3, None, "3 '|'-separated columns, expected 7")))
    first, second = listing_outcomes(listing)
    assert first == ClipOutcome("c7", "", "quarantined", reason="no split: 'val' is not train, dev or test; fix row 7",
                                file="index.csv", row=7, group="listing: no split", from_listing=True)
    assert (second.clip_id, second.split, second.status, second.file, second.row) == (
        "", "", "quarantined", "annotations/train.corpus.csv", 3)
    assert second.group == "listing: 3 '|'-separated columns, expected 7" and second.from_listing
    assert second.part is None and second.frames == 0 and second.metrics == {}
    long = listing_outcomes(Listing((), (Quarantined("f", None, "x", "a" * 80 + ": detail"),)))[0]
    assert long.group == "listing: " + "a" * 60 and long.row is None


def fitted(batch) -> list[ClipOutcome]:
    return [ClipOutcome(c.id, c.split, "fitted", frames=3, seconds=0.5) for c in batch]


def test_run_statistics_count_this_runs_work_and_its_throughput():
    from m3t.fitting.report import run_stats

    outcomes = [ClipOutcome("a", "train", "fitted", frames=30, seconds=2.0),
                ClipOutcome("b", "dev", "fitted", frames=10, seconds=2.0),
                ClipOutcome("c", "train", "cached", frames=50),
                ClipOutcome("d", "test", "quarantined", seconds=1.0)]
    assert run_stats(outcomes, 8.0) == {"clips_fitted_now": 2, "clips_cached": 1, "wall_seconds": 8.0,
                                        "fit_frames_per_s_per_worker": 10.0, "fit_frames_per_s_wall": 5.0}
    resumed = run_stats(outcomes[2:], 3.0)  # nothing fitted now: no throughput to report
    assert (resumed["clips_fitted_now"], resumed["clips_cached"], resumed["wall_seconds"]) == (0, 1, 3.0)
    assert math.isnan(resumed["fit_frames_per_s_per_worker"]) and math.isnan(resumed["fit_frames_per_s_wall"])
    unclocked = run_stats(outcomes, 0.0)
    assert math.isnan(unclocked["fit_frames_per_s_wall"]) and unclocked["fit_frames_per_s_per_worker"] == 10.0


def test_an_imported_clip_without_a_non_finite_count_counts_as_all_finite():
    from m3t.fitting.report import import_summary

    imported = {"init_source": "imported: MEAD FLAME parameters, no tracking or fitting"}
    summary = import_summary([ClipOutcome("i1", "train", "fitted", frames=10, init=imported,
                                          metrics={"src_nonfinite_frame_frac": 0.1}),
                              ClipOutcome("i2", "train", "cached", frames=30, init=imported, metrics={})])
    assert summary == {"imported_clips": 2, "imported_nonfinite_frame_frac": pytest.approx(0.025)}


def test_the_quality_picture_is_a_small_png_written_where_asked(tmp_path):
    from m3t.fitting.quality import plot_quality, quality_report

    report = quality_report([ClipOutcome("a", "train", "fitted", frames=3, metrics={"reproj_px_parts": 2.5},
                                         coverage={"missing_left_hand": 0.5, "missing_right_hand": 0.0,
                                                   "missing_face": 0.0}, track_frames=3)], "synthetic")
    path = plot_quality(report, tmp_path / "render" / "quality-synthetic.png")
    assert path == tmp_path / "render" / "quality-synthetic.png"
    header = path.read_bytes()[:24]
    assert header[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(header[16:20], "big"), int.from_bytes(header[20:24], "big")
    assert (width, height) == (800, 320)  # 10 x 4 inches at 80 dpi: light enough for every run's artifacts


# ------------------------------------------------------------------------------------------ run results
def test_the_run_summary_counts_clips_and_averages_fit_metrics_of_fitted_clips_only():
    from m3t.fitting.report import summarise

    outcomes = [
        ClipOutcome("a", "train", "fitted", frames=10, metrics={"fit_px": 2.0, "reproj_px_parts": 9.0}),
        ClipOutcome("b", "dev", "cached", frames=30, metrics={"fit_px": 4.0, "pa_mm": float("nan")}),
        ClipOutcome("c", "train", "fitted", frames=5, metrics={"fit_px": 9.0, "reproj_shoulder_frac": 0.1}),
        ClipOutcome("q", "train", "quarantined", frames=99, metrics={"fit_px": 1000.0}),
    ]
    assert summarise(outcomes) == {"clips_total": 4, "clips_fitted": 3, "clips_quarantined": 1, "frames": 45,
                                   "fit_px_mean": 5.0, "fit_px_median": 4.0}
    assert summarise([]) == {"clips_total": 0, "clips_fitted": 0, "clips_quarantined": 0, "frames": 0}


def test_consolidate_creates_a_nested_shards_folder_and_writes_every_split(tmp_path):
    from m3t.corpora.splits import SPLITS
    from m3t.fitting.imports import ImportSettings
    from m3t.fitting.report import consolidate

    layout = ImportSettings("smplfx", 100).layout("keypoints", 6)
    out = tmp_path / "data" / "shards" / "synthetic"
    outcomes = [ClipOutcome("q", "train", "quarantined", reason="ValueError: bad", group="ValueError",
                            file="motion/q.npz")]
    report = consolidate(outcomes, layout, out, "synthetic", 1.0)
    assert set(report.shards) == set(SPLITS) and all(Path(p).parent == out for p in report.shards.values())
    assert sorted(p.name for p in out.glob("*.parquet")) == sorted(f"{s}.parquet" for s in SPLITS)
    (out / "holdout.parquet").write_bytes((out / "train.parquet").read_bytes())  # a split of an older run
    consolidate(outcomes, layout, out, "synthetic", 1.0)
    assert sorted(p.name for p in out.glob("*.parquet")) == sorted(f"{s}.parquet" for s in SPLITS)
    assert [json.loads(line) for line in (out / "quarantine.jsonl").read_text().splitlines()] == [
        {"clip_id": "q", "split": "train", "file": "motion/q.npz", "row": None, "reason": "ValueError: bad",
         "group": "ValueError"}]
    assert json.loads((out / "summary.json").read_text())["clips_quarantined"] == 1


def test_quality_json_keys_are_sorted_so_identical_results_give_identical_bytes(tmp_path):
    from m3t.atomic import write_text
    from m3t.fitting.quality import QualityReport, write_quality

    _, json_path = write_quality(QualityReport([], {"zeta": 1, "alpha": float("inf"), "mid": "x"}), tmp_path,
                                 write_text)
    assert json_path.read_text() == '{\n  "alpha": null,\n  "mid": "x",\n  "zeta": 1\n}\n'


def test_a_quality_row_without_a_file_or_row_leaves_both_cells_empty():
    from m3t.fitting.quality import quality_report

    report = quality_report([ClipOutcome("q", "train", "quarantined", reason="boom", group="RuntimeError"),
                             ClipOutcome("r", "dev", "quarantined", reason="bad row", file="index.csv", row=0)], "x")
    q, r = report.rows
    assert (q["file"], q["row"], q["reason"], q["group"], q["split"]) == ("", "", "boom", "RuntimeError", "train")
    assert (r["file"], r["row"], r["group"]) == ("index.csv", 0, "")


def test_the_run_log_names_the_corpus_variant_and_draws_each_fit_against_its_truth(tmp_path, monkeypatch):
    """``log_fit_corpus`` with the MLflow run, the shard reader and the pictures replaced by recorders."""
    import contextlib
    from types import SimpleNamespace

    import m3t.experiment as experiment
    import m3t.fitting.report as report_module
    import m3t.render.mesh as mesh
    import m3t.render.skeleton as skeleton

    calls: dict[str, list] = {"start": [], "compare": [], "mesh": [], "artifacts": []}

    class FakeRun:
        run_id = "run-1"

        def log_params(self, params): pass

        def log_metrics(self, metrics): pass

        def log_table(self, path, name): pass

        def log_artifact(self, path, folder=None):
            calls["artifacts"].append((Path(path).name, folder))

    @contextlib.contextmanager
    def start_run(exp, stage, tags=None, variant=None):
        calls["start"].append((exp, stage, tags, variant))
        yield FakeRun()

    clip = Clip("s0-a", "synthetic", "train", "ISO-SYN", "s0", "", "", "motion/s0-a.npz", 25.0)
    fitted = SimpleNamespace(clip=clip, camera={"f": 1.0}, params={"body": np.zeros((4, 6))},
                             identity=np.zeros(6), num_frames=4)
    monkeypatch.setattr(experiment, "start_run", start_run)
    monkeypatch.setattr(report_module, "read_shard", lambda part: SimpleNamespace(clips=[fitted]))
    monkeypatch.setattr(report_module, "plot_quality", lambda quality, path: Path(path))
    monkeypatch.setattr(skeleton, "render_fit_comparison",
                        lambda body, fit, truth, image: calls["compare"].append((fit.clip.id, truth)) or image)
    monkeypatch.setattr(mesh, "log_fitted_frame",
                        lambda run, body, params, identity, frame, folder, camera, stem: calls["mesh"].append(
                            (frame, camera, stem)))
    report = report_module.FitCorpusReport(shards={}, outcomes=[ClipOutcome("s0-a", "train", "fitted", "p.parquet")],
                                           summary={}, quality={"clips_listed": 1, "corpus": "synthetic"},
                                           run_stats={})
    truths = {"s0-a": ("truth-params", "truth-identity", "truth-camera")}
    body = SimpleNamespace(name="anny")
    assert report_module.log_fit_corpus("exp", {}, report, body, "synthetic", tmp_path, tmp_path / "cache", 1,
                                        lambda c: truths[c.id]) == "run-1"
    assert calls["start"] == [("exp", "fit-corpus", {"corpus": "synthetic", "body_model": "anny"}, "synthetic")]
    assert calls["compare"] == [("s0-a", truths["s0-a"])] and calls["mesh"] == [(2, {"f": 1.0}, "s0-a")]
    assert ("s0-a.png", "fit_vs_ground_truth") in calls["artifacts"]
    calls["compare"].clear()
    report_module.log_fit_corpus("exp", {}, report, body, "synthetic", tmp_path, tmp_path / "cache", 1)
    assert calls["compare"] == [("s0-a", None)]  # no truth to draw: the fit alone


def test_a_listing_quarantine_is_grouped_by_its_reason_up_to_the_first_semicolon():
    from m3t.corpora.listing import Listing, Quarantined
    from m3t.fitting.corpus import listing_outcomes

    reasons = ("split 'foo'; expected one of train, dev, val, test", "bad times: end 5.0 s <= start 5.0 s",
               "plain reason", "b" * 61)
    listing = Listing((), tuple(Quarantined("annotation.csv", i + 2, f"c{i}", r) for i, r in enumerate(reasons)))
    assert [o.group for o in listing_outcomes(listing)] == ["listing: split 'foo'", "listing: bad times",
                                                           "listing: plain reason", "listing: " + "b" * 60]


def test_a_fit_without_a_recorded_initialisation_counts_as_unknown():
    from m3t.fitting.quality import quality_report

    outcomes = [ClipOutcome("a", "train", "fitted", frames=3), ClipOutcome("b", "train", "cached", frames=2,
                                                                           init={"init_source": "fused: nlf"})]
    summary = quality_report(outcomes, "x").summary
    assert summary["init_sources"] == {"unknown": 1, "fused": 1}
    assert quality_report(outcomes[:1], "x").summary["init_sources"] == {"unknown": 1}


def test_the_quality_picture_shows_each_parts_missing_ratio(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    from m3t.fitting.quality import MISSING_PARTS, plot_quality, quality_report

    coverage = {"missing_left_hand": 0.25, "missing_right_hand": 0.5, "missing_face": 0.75}
    report = quality_report([ClipOutcome("a", "train", "fitted", frames=4, track_frames=4, coverage=coverage,
                                         metrics={"reproj_px_parts": 3.0})], "synthetic")
    figures = []
    real_savefig = Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **kw: figures.append(fig) or real_savefig(fig, *a, **kw))
    path = plot_quality(report, tmp_path / "q.png")
    assert path.is_file() and path.stat().st_size > 0
    (fig,) = figures
    left, right = fig.axes
    assert [p.get_height() for p in right.patches] == [report.summary[f"missing_{p}_ratio"] for p in MISSING_PARTS]
    assert [t.get_text() for t in right.get_xticklabels()] == list(MISSING_PARTS)
    assert right.get_ylim() == (0, 1) and left.get_ylabel() == "clips"
    empty = quality_report([ClipOutcome("x", "train", "quarantined")], "slt")
    figures.clear()
    plot_quality(empty, tmp_path / "empty.png")
    assert [p.get_height() for p in figures[0].axes[1].patches] == [0.0] * len(MISSING_PARTS)
