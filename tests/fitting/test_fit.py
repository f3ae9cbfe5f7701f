"""Fitting recovers ground truth from simulated 2D tracks; missing keypoints are masked."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from builders import front_camera, smooth_motion

from m3t.fitting.evaluate import ground_truth_errors, joints_for, procrustes_error_mm
from m3t.fitting.fit import FittingConfig, fit_track
from m3t.fitting.objective import acceleration_loss, reprojection_loss
from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track
from m3t.trackers.track import TrackError, load_track, save_track

FIT = FittingConfig(iterations=200, camera_iterations=80, lr=0.02)


@pytest.fixture(scope="module")
def clip(body):
    params = smooth_motion(body)
    identity = torch.tensor([0.4, 0.5, 0.5, 0.45, 0.6, 0.5])
    camera = front_camera()
    track = simulate_track("clip-0", params, identity, camera, 25.0, body, SimulatedTrackerConfig(seed=1))
    return params, identity, camera, track


@pytest.mark.slow
def test_fit_recovers_ground_truth(body, clip):
    params, identity, camera, track = clip
    result = fit_track(track, body, FIT)
    truth = {k: v.numpy() for k, v in params.items()}
    errors = ground_truth_errors(body, result.params, result.identity, result.camera, truth, identity.numpy(), camera.as_dict())
    with torch.no_grad():
        init_pa = procrustes_error_mm(joints_for(body, track.init, body.default_identity().numpy()),
                                      joints_for(body, truth, identity.numpy()))
    # The simulated detector has 0.8-2 px noise (more at low confidence): a good fit explains the points to
    # about that level, and refinement must improve the articulation over the noisy 3D initialisation.
    assert result.metrics["reproj_px"] < 3.0
    assert errors["pa_joint_mm"] < 0.75 * init_pa  # measured: ~0.65 (about 20 mm vs 31 mm)
    assert errors["pa_joint_mm"] < 30.0
    assert result.loss_curve[-1] < 0.05 * result.loss_curve[0]
    assert set(result.params) == set(body.layout.names)
    assert all(v.shape == (track.num_frames, body.layout.dims[k]) for k, v in result.params.items())
    assert np.all((result.params["face"] >= 0) & (result.params["face"] <= 1))


def test_nan_keypoints_are_masked(body, clip, tmp_path):
    _, _, _, track = clip
    kp = track.keypoints.copy()
    kp[:, 33:54] = np.nan  # the left hand vanishes
    conf = track.confidence.copy()
    conf[:, 33:54] = 0.7  # a tracker that reports NaN with a non-zero confidence
    path = save_track(dataclasses.replace(track, keypoints=kp, confidence=conf), tmp_path / "t.npz")
    loaded = load_track(path)
    assert np.all(loaded.confidence[:, 33:54] == 0)
    target = torch.as_tensor(np.nan_to_num(loaded.keypoints, nan=0.0))
    pred = target + 1.0
    loss = reprojection_loss(pred, target, torch.as_tensor(loaded.confidence), [slice(0, 543)])
    assert torch.isfinite(loss)
    result = fit_track(loaded, body, dataclasses.replace(FIT, iterations=10, camera_iterations=5))
    assert all(np.isfinite(v).all() for v in result.params.values())


def test_track_round_trip_and_errors(clip, tmp_path):
    _, _, _, track = clip
    path = save_track(track, tmp_path / "a.npz")
    loaded = load_track(path)
    np.testing.assert_array_equal(np.isnan(loaded.keypoints), np.isnan(track.keypoints))
    np.testing.assert_allclose(np.nan_to_num(loaded.keypoints), np.nan_to_num(track.keypoints))
    assert set(loaded.init) == set(track.init)
    assert not list(tmp_path.glob("*.tmp"))
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(TrackError, match="bad.npz"):
        load_track(tmp_path / "bad.npz")
    with pytest.raises(TrackError, match="does not exist"):
        load_track(tmp_path / "missing.npz")


def test_acceleration_loss_zero_for_constant_velocity():
    t = torch.arange(10.0)[:, None, None]
    points = torch.cat([t * 0.01, t * 0.0, t * 0.02], dim=-1).expand(10, 4, 3)
    assert float(acceleration_loss(points)) == pytest.approx(0.0, abs=1e-8)
    assert float(acceleration_loss(points ** 2)) > 0
    # three frames are enough for one acceleration: 1 cm up, then back -> (-2 cm)^2 on one axis
    bump = torch.zeros(3, 1, 3)
    bump[1, 0, 1] = 0.01
    assert float(acceleration_loss(bump)) == pytest.approx(4.0)
    assert float(acceleration_loss(bump[:2])) == 0.0


def test_consolidated_summary_does_not_depend_on_completion_order(tmp_path):
    """A resumed or distributed run finishes its clips in another order; the means must still be summed in clip
    order, or ``summary.json`` differs in the last digit from an uninterrupted run's (seen in the kill harness:
    ``(0.1 + 0.2) + 0.3 != (0.3 + 0.2) + 0.1``)."""
    from m3t.body.smplfx import smplfx_layout
    from m3t.fitting.report import ClipOutcome, consolidate

    outcomes = [ClipOutcome(f"clip-{i}", "train", "fitted", metrics={"pa_joint_mm": v}, frames=10,
                            seconds=1.0)
                for i, v in enumerate((0.1, 0.2, 0.3))]
    written = []
    for order, name in ((outcomes, "a"), (outcomes[::-1], "b")):
        consolidate(order, smplfx_layout(), tmp_path / name, "synthetic", 1.0)
        written.append((tmp_path / name / "summary.json").read_bytes())
    assert written[0] == written[1]
    assert b"0.20000000000000004" in written[0]  # (0.1 + 0.2 + 0.3) / 3 summed in clip order


def test_consolidate_writes_each_quarantine_line_and_counts_this_runs_work(tmp_path):
    import json

    from m3t.body.smplfx import smplfx_layout
    from m3t.fitting.report import ClipOutcome, consolidate

    outcomes = [ClipOutcome("a", "train", "fitted", metrics={"pa_joint_mm": 1.0}, frames=30, seconds=3.0),
                ClipOutcome("b", "train", "cached", metrics={"pa_joint_mm": 2.0}, frames=50),
                ClipOutcome("c", "dev", "quarantined", reason="track has no frames", group="empty track",
                            file="media/c.mp4", row=7)]
    report = consolidate(outcomes, smplfx_layout(), tmp_path / "out", "synthetic", 2.0)
    lines = [json.loads(line) for line in (tmp_path / "out" / "quarantine.jsonl").read_text().splitlines()]
    assert lines == [{"clip_id": "c", "split": "dev", "file": "media/c.mp4", "row": 7, "reason": "track has no frames",
                      "group": "empty track"}]
    assert report.summary["clips_fitted"] == 2 and report.summary["clips_quarantined"] == 1
    assert report.summary["frames"] == 80
    assert report.run_stats["clips_fitted_now"] == 1 and report.run_stats["clips_cached"] == 1
    assert report.run_stats["fit_frames_per_s_per_worker"] == 10.0  # 30 frames fitted now in 3 s
    assert report.run_stats["fit_frames_per_s_wall"] == 15.0  # over the run's 2 s
