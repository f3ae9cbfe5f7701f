"""Active-window trimming's arithmetic (:func:`m3t.slr.trim.active_window`) and the trimmer without a body model,
on activity patterns whose kept windows are worked out by hand from the rule (M3T Sec. 3.4): keep the first to
the last active frame, ``margin`` more on each side within the clip, widened around its centre to ``min_frames``
within the clip. Written to pin behaviours that mutation testing found unchecked (the existing trimming tests
use ``margin=0`` and check a widened window only loosely)."""
from __future__ import annotations

import numpy as np
import pytest

from m3t.experiment import RunRecord
from m3t.slr.config import TrimConfig
from m3t.slr.table import recognition_table
from m3t.slr.trim import (
    ActiveWindow,
    ClipTooShortError,
    Trimmer,
    active_window,
    trim_params,
)


def activity(frames: int, *active: int) -> np.ndarray:
    out = np.zeros(frames, dtype=bool)
    out[list(active)] = True
    return out


@pytest.mark.parametrize(("active", "margin", "min_frames", "window"), [
    ((5, 6, 7, 8, 9), 2, 4, (3, 12)),  # 5 - 2 .. 9 + 1 + 2
    ((5, 6, 7, 8, 9), 0, 4, (5, 10)),
    ((1,), 2, 1, (0, 4)),  # the margin stops at the clip's first frame
    ((18,), 2, 1, (16, 20)),  # ... and at its last
    ((10, 11), 0, 8, (7, 15)),  # widened around the centre: (10 + 12 - 8) // 2 = 7
    ((10,), 0, 8, (6, 14)),  # (10 + 11 - 8) // 2 = 6
    ((1,), 0, 8, (0, 8)),  # widened, but not before the first frame
    ((19,), 0, 8, (12, 20)),  # ... nor past the last
    ((3, 15), 1, 4, (2, 17)),  # inactive frames between two active ones stay
])
def test_the_kept_window_follows_the_rule(active, margin, min_frames, window):
    got = active_window(activity(20, *active), TrimConfig(margin=margin, min_frames=min_frames))
    assert (got.start, got.end, got.frames, got.active_frames) == (*window, 20, len(active))
    assert got.kept == window[1] - window[0]
    assert got.trimmed_share == pytest.approx(1 - (window[1] - window[0]) / 20)  # a float quotient: approx


def test_a_clip_without_activity_or_with_trimming_off_is_kept_whole():
    assert active_window(activity(12), TrimConfig(min_frames=4)) == ActiveWindow(0, 12, 12, 0)
    off = TrimConfig(enabled=False, min_frames=4)
    assert active_window(activity(12, 3, 4, 5), off) == ActiveWindow(0, 12, 12, 3)
    assert ActiveWindow(0, 12, 12, 0).trimmed_share == 0.0
    assert ActiveWindow(0, 0, 0, 0).trimmed_share == 0.0  # no frames: nothing trimmed, no division by zero
    assert ActiveWindow(2, 5, 10, 1).to_dict() == {"start": 2, "end": 5, "frames": 10, "active_frames": 1}


def test_a_clip_shorter_than_min_frames_is_refused_by_name_and_one_of_exactly_min_frames_is_not():
    cfg = TrimConfig(min_frames=8)
    with pytest.raises(ClipTooShortError, match=r"'clip-7' has 7 frames, fewer than slr.trim.min_frames=8"):
        active_window(activity(7, 2), cfg, "clip-7")
    assert active_window(activity(8, 2), cfg).kept == 8


def test_trim_params_cuts_every_modality_to_the_window():
    params = {"body": np.arange(20).reshape(10, 2), "face": np.arange(10)[:, None]}
    kept = trim_params(params, ActiveWindow(3, 7, 10, 2))
    assert kept["body"].tolist() == [[6, 7], [8, 9], [10, 11], [12, 13]] and kept["face"][:, 0].tolist() == [3, 4, 5, 6]


def test_the_trimmer_without_trimming_needs_no_body_and_still_refuses_short_clips():
    with pytest.raises(ValueError, match="needs the body model"):
        Trimmer(None, TrimConfig(enabled=True))
    trimmer = Trimmer(None, TrimConfig(enabled=False, min_frames=4))
    params = {"body": np.ones((10, 3)), "face": np.zeros((10, 2))}
    kept, window = trimmer(params, np.zeros(4), "whole")
    assert window == ActiveWindow(0, 10, 10, 0) and kept["body"].shape == (10, 3) and kept["face"].shape == (10, 2)
    with pytest.raises(ClipTooShortError, match="'short'"):
        trimmer({"body": np.ones((3, 3))}, np.zeros(4), "short")


@pytest.mark.parametrize("bad", [{"height_threshold": 0.0}, {"displacement_threshold": -1.0}, {"margin": -1},
                                 {"min_frames": 0}])
def test_trim_settings_out_of_range_are_refused(bad):
    with pytest.raises(ValueError):
        TrimConfig(**bad)


# ------------------------------------------------------------------------------------------ Tab. 4 from MLflow
def slr_run(run_id: str, top1: float, status: str = "FINISHED", variants=("no_face", "full"),
            confidence: str = "0.9") -> RunRecord:
    metrics = {}
    for variant in variants:
        shift = 10.0 if variant == "full" else 0.0
        metrics.update({f"{variant}/overall/top1": top1 + shift, f"{variant}/overall/top1_ci_low": top1 + shift - 1,
                        f"{variant}/overall/top1_ci_high": top1 + shift + 1, f"{variant}/overall/top1_chance": 25.0,
                        f"{variant}/overall/top5": 100.0, f"{variant}/overall/top5_chance": 100.0,
                        f"{variant}/overall/clips": 8, f"{variant}/overall/classes": 4})
    return RunRecord(run_id, "evaluate-slr", 0, status, {"slr_evaluate.confidence": confidence}, metrics, None,
                     {"corpus": "synthetic", "split": "test", "subsets_reason": "no subset list"})


def test_the_recognition_table_is_the_newest_finished_run_full_probe_first():
    records = [slr_run("running", 90.0, status="RUNNING"), slr_run("newest", 40.0), slr_run("older", 70.0)]
    table = recognition_table(records)
    rows = [line for line in table.splitlines() if line.startswith("| M3T")]
    assert rows[0].startswith("| M3T probe (body, hands, face) | 50.0 [49.0, 51.0] | 100.0 [nan, nan] |")
    assert rows[1].startswith("| M3T probe w/o face | 40.0 [39.0, 41.0] |")
    assert "| chance (uniform guess) | 25.0 | 100.0 |" in table
    assert "synthetic, test split; accuracies in %, [90% percentile bootstrap interval over clips]." in table
    assert "Overall: 8 clip(s) of 4 class(es)" in table and "Subsets unavailable: no subset list" in table
    assert recognition_table([slr_run("failed", 1.0, status="FAILED")]).startswith("no finished evaluate-slr runs")
