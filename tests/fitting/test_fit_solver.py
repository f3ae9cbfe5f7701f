"""The fitting solver in detail (:mod:`m3t.fitting.fit`): Adam's schedule, L-BFGS's evaluation budget and line search,
the bounds every objective evaluation respects, the identity a batch holds fixed, the default and torso-placed
camera, the landmark correspondence, per-part confidences and the batch's error message. Written to pin behaviours
that mutation testing found unchecked.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from builders import front_camera, smooth_motion

from m3t.fitting.report import ClipOutcome

IDENTITY = np.array([0.4, 0.5, 0.5, 0.45, 0.6, 0.5], np.float32)


@pytest.fixture(autouse=True)
def _one_thread():
    """Small fits run fastest on one intra-op thread (conftest restores the count after each test)."""
    torch.set_num_threads(1)


# ------------------------------------------------------------------------------------------ the solver
@pytest.fixture(scope="module")
def short_track(body):
    from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track

    return simulate_track("short", smooth_motion(body, frames=3), torch.as_tensor(IDENTITY), front_camera(), 25.0,
                          body, SimulatedTrackerConfig(seed=3))


def test_a_track_without_intrinsics_gets_a_centred_camera_of_the_guessed_focal_length(body, short_track):
    from m3t.fitting.fit import FittingConfig, fit_track

    cfg = FittingConfig(iterations=1, camera_iterations=1, focal_guess=1.5)
    track = dataclasses.replace(short_track, intrinsics=np.full(4, np.nan), image_size=(640, 480))
    camera = fit_track(track, body, cfg).camera
    assert (camera["fx"], camera["fy"], camera["cx"], camera["cy"]) == (960.0, 960.0, 320.0, 240.0)
    assert (camera["width"], camera["height"]) == (640, 480)
    known = dataclasses.replace(track, intrinsics=np.array([700.0, 710.0, 300.0, 250.0]))
    camera = fit_track(known, body, cfg).camera
    assert (camera["fx"], camera["fy"], camera["cx"], camera["cy"]) == (700.0, 710.0, 300.0, 250.0)


def test_a_batch_names_its_tracks_without_any_visible_landmark(body, short_track):
    from m3t.fitting.fit import FittingConfig, fit_tracks

    blind = dataclasses.replace(short_track, confidence=np.zeros_like(short_track.confidence))
    cfg = FittingConfig(iterations=1, camera_iterations=1)
    with pytest.raises(ValueError, match=r"^track\(s\) 0, 2 of the batch have no visible landmark with a body-model "
                                         r"correspondence in any frame$"):
        fit_tracks([blind, short_track, blind], body, cfg)
    with pytest.raises(ValueError, match=r"^the track has no visible landmark"):
        fit_tracks([blind], body, cfg)


def test_adam_steps_decay_on_a_cosine_to_five_percent_of_the_rate():
    """On a linear objective every Adam step moves the variable by the current learning rate."""
    from m3t.fitting.fit import FittingConfig
    from m3t.fitting.solvers import minimise

    x = torch.zeros(1, requires_grad=True)
    curve: list[float] = []
    projected = []
    cfg = FittingConfig(solver="adam", iterations=20, camera_iterations=3)
    minimise(lambda: x.sum(), [x], cfg, "full", 0.1, curve, project_bounds=lambda: projected.append(1))
    positions = [0.0, *curve[1:], float(x.detach())]
    steps = -np.diff(positions)  # step k: the rate after k decays
    assert len(curve) == 20 and len(projected) == 20 and curve[0] == 0.0
    assert steps[0] == pytest.approx(0.1, rel=1e-4)
    assert np.all(np.diff(steps) < 0)  # decaying
    assert 0.05 * 0.1 < steps[-1] < 0.06 * 0.1  # close to 5 % at the end (cosine: 5 % + 95 % * 0.6 %)
    assert steps[10] == pytest.approx(0.1 * (0.05 + 0.95 * 0.5), rel=1e-4)  # half-way: half of the decay

    camera: list[float] = []
    minimise(lambda: x.sum(), [x], cfg, "camera", 0.1, camera)
    assert len(camera) == 3  # the camera stage's own budget


def test_lbfgs_spends_at_most_its_evaluation_budget():
    from m3t.fitting.fit import FittingConfig
    from m3t.fitting.solvers import minimise

    x = torch.tensor([3.0, -2.0], requires_grad=True)
    curve: list[float] = []
    cfg = FittingConfig(solver="lbfgs", iterations=7, lbfgs_round=3)
    minimise(lambda: ((x - 1.0) ** 2).sum(), [x], cfg, "full", 0.0, curve)
    assert 0 < len(curve) <= 7 and curve[-1] < 1e-6 < curve[0]
    untouched = torch.tensor([3.0], requires_grad=True)
    none: list[float] = []
    minimise(lambda: (untouched ** 2).sum(), [untouched], FittingConfig(solver="lbfgs", iterations=0), "full", 0.0,
              none)
    assert none == [] and float(untouched.detach()) == 3.0


def fitted(batch) -> list[ClipOutcome]:
    return [ClipOutcome(c.id, c.split, "fitted", frames=3, seconds=0.5) for c in batch]


# ------------------------------------------------------------------------------------------ the solver (more)
def test_lbfgs_line_search_reaches_the_minimum_of_a_robust_loss():
    """A pseudo-Huber loss (curvature vanishing far from its minimum): full quasi-Newton steps overshoot and run
    away; the strong-Wolfe line search keeps every step a descent and reaches the minimum within the budget."""
    from m3t.fitting.fit import FittingConfig
    from m3t.fitting.solvers import minimise

    x = torch.tensor([0.0, 10.0, -5.0], dtype=torch.float64, requires_grad=True)
    curve: list[float] = []
    minimise(lambda: torch.sqrt(1 + (x - 3.0) ** 2).sum(), [x], FittingConfig(solver="lbfgs", iterations=30), "full",
              0.0, curve)
    assert len(curve) <= 30 and curve[-1] == pytest.approx(3.0, abs=1e-9)
    np.testing.assert_allclose(x.detach().numpy(), 3.0, atol=1e-4)


def test_a_fit_uses_the_landmark_correspondence_it_is_given(body, short_track):
    from m3t.fitting.fit import FittingConfig, fit_track, fit_tracks
    from m3t.trackers.track import landmark_slices

    cfg = FittingConfig(iterations=2, camera_iterations=2)
    default = body.correspondence(short_track.landmark_set)
    nowhere = dataclasses.replace(default, kind=np.full_like(default.kind, -1))
    with pytest.raises(ValueError, match=r"^the track has no visible landmark with a body-model correspondence"):
        fit_track(short_track, body, cfg, nowhere)
    pose = landmark_slices(short_track.landmark_set)["pose"]
    pose_only = dataclasses.replace(default, kind=np.where(np.arange(len(default.kind)) < pose.stop, default.kind, -1))
    result = fit_track(short_track, body, cfg, pose_only)
    assert np.array_equal(result.params["body"], fit_tracks([short_track], body, cfg, pose_only)[0].params["body"])
    assert not np.array_equal(result.params["body"], fit_track(short_track, body, cfg).params["body"])


def test_the_camera_is_placed_from_the_torso_and_head_points_alone(body, short_track):
    """The camera-only stage ignores the arms (pose points 13-22: elbows, wrists, hand points), the hands and the
    face mesh, which start far from the rest pose; the shoulders, the hips and the head's pose points place it."""
    from m3t.fitting.fit import FittingConfig, fit_track
    from m3t.trackers.track import landmark_slices

    cfg = FittingConfig(iterations=0, camera_iterations=3)
    parts = landmark_slices(short_track.landmark_set)

    def camera(*shift: tuple[slice, float]) -> dict:
        keypoints = short_track.keypoints.copy()
        for where, by in shift:
            keypoints[:, where] += by
        return fit_track(dataclasses.replace(short_track, keypoints=keypoints), body, cfg).camera

    placed = camera()
    pose = parts["pose"].start
    moved = camera((slice(pose + 13, pose + 23), 60.0), (parts["left_hand"], -50.0), (parts["right_hand"], 50.0),
                   (parts["face"], 30.0))
    assert moved["translation"] == placed["translation"] and moved["rotation"] == placed["rotation"]
    # shoulders, hip, nose
    for kept in (slice(pose + 11, pose + 13), slice(pose + 23, pose + 24), slice(pose, pose + 1)):
        assert camera((kept, 60.0))["translation"] != placed["translation"], kept


def test_refinement_starts_from_the_fused_initialisation_and_identity(body, short_track):
    from m3t.fitting.fit import FittingConfig
    from m3t.fitting.fusion import refine
    from m3t.fitting.stream_fusion import FusedInit

    cfg = FittingConfig(iterations=0, camera_iterations=1)  # no joint stage: the result is where it started
    init = {k: v[::-1].copy() for k, v in short_track.init.items()}  # another valid motion than the track's own
    identity = np.array([0.3, 0.6, 0.4, 0.5, 0.5, 0.7], np.float32)
    result = refine(short_track, FusedInit(init, {}, {}, identity), body, cfg)
    for k, v in init.items():
        np.testing.assert_allclose(result.params[k], v, atol=1e-5, err_msg=k)
    np.testing.assert_array_equal(result.identity, identity)
    default = refine(short_track, FusedInit(init, {}, {}, None), body, cfg)
    np.testing.assert_array_equal(default.identity, body.default_identity().numpy())
    with pytest.raises(ValueError, match=r"disagree on the number of frames \(3\)"):
        refine(short_track, FusedInit({k: v[:2] for k, v in init.items()}, {}, {}, None), body, cfg)


def test_reprojection_loss_weighs_each_part_by_its_own_confidence_even_when_it_is_small():
    from m3t.fitting.objective import reprojection_loss

    pred = torch.zeros(2, 3, 2)
    target = torch.zeros(2, 3, 2)
    target[:, 0, 0] = 2.0  # part 1: 4 px^2 at every confident point
    target[:, 2, 1] = 3.0  # part 2: 9 px^2
    conf = torch.tensor([[1.0, 1.0, 0.25], [1.0, 0.0, 0.25]])
    parts = [slice(0, 2), slice(2, 3), slice(1, 2)]
    # part 1: (4 + 4) / 3 over its confidence 3; part 2: 9 at total confidence 0.5; part 3: no error
    assert reprojection_loss(pred, target, conf, parts).item() == pytest.approx((8 / 3 + 9 + 0) / 3)
    unseen = conf.clone()
    unseen[:, 2] = 0.0  # a part nobody saw is left out, not counted as zero error
    assert reprojection_loss(pred, target, unseen, parts).item() == pytest.approx((8 / 3 + 0) / 2)


def test_a_known_identity_is_held_fixed_in_every_clips_fit(body, short_track):
    """``identity`` given (a signer's identity from an earlier chunk): every result carries exactly it, even with
    ``fit_identity`` on; without it the fit starts from the default identity and fits it, or keeps the default
    when ``fit_identity`` is off."""
    from m3t.fitting.fit import FittingConfig, fit_tracks

    cfg = FittingConfig(iterations=3, camera_iterations=1)
    assert cfg.fit_identity
    known = np.array([0.3, 0.6, 0.4, 0.55, 0.45, 0.7])  # float64, as read from a file: results are float32
    for fit_identity in (True, False):
        results = fit_tracks([short_track, short_track], body, dataclasses.replace(cfg, fit_identity=fit_identity),
                             identity=known)
        assert len(results) == 2
        for result in results:
            assert result.identity.dtype == np.float32
            np.testing.assert_array_equal(result.identity, known.astype(np.float32))
    default = body.default_identity().numpy()
    fitted = fit_tracks([short_track], body, cfg)[0].identity
    assert not np.array_equal(fitted, default) and np.all((fitted >= 0) & (fitted <= 1))
    held = fit_tracks([short_track], body, dataclasses.replace(cfg, fit_identity=False))[0].identity
    np.testing.assert_array_equal(held, default)


@pytest.mark.parametrize("solver", ["lbfgs", "adam"])
def test_bounded_streams_enter_the_objective_clamped_to_their_bounds(body, short_track, monkeypatch, solver):
    """Anny's facial actions live in [0, 1]: from an initialisation outside them (a tracker's estimate
    overshooting), every evaluation of the objective (the camera stage's and each solver step's or line-search
    trial's) hands the body model values clamped to the bounds, and the result lies within them."""
    from m3t.fitting.fit import FittingConfig, fit_track

    face = short_track.init["face"].copy()
    face[:, 0], face[:, 1], face[:, 2] = -0.4, 1.5, 3.0
    track = dataclasses.replace(short_track, init={**short_track.init, "face": face})
    seen: list[torch.Tensor] = []
    forward_keypoints = body.forward_keypoints

    def recording(params, identity, keypoints):
        seen.append(params["face"].detach().clone())
        return forward_keypoints(params, identity, keypoints)

    monkeypatch.setattr(body, "forward_keypoints", recording)
    result = fit_track(track, body, FittingConfig(solver=solver, iterations=4, camera_iterations=1))
    faces = torch.cat(seen)
    assert len(seen) >= 5 and float(faces.min()) >= 0.0 and float(faces.max()) <= 1.0
    assert result.params["face"].min() >= 0.0 and result.params["face"].max() <= 1.0
    np.testing.assert_array_equal(seen[0][:, :3].numpy(), np.tile([0.0, 1.0, 1.0], (3, 1)))


def test_lbfgs_minimises_a_loss_of_tiny_absolute_size_too():
    """Only the relative ``tolerance`` stops the solver early: a loss whose values are a millionth of the usual
    (the pseudo-Huber loss above, scaled) still reaches its minimum."""
    from m3t.fitting.fit import FittingConfig
    from m3t.fitting.solvers import minimise

    x = torch.tensor([0.0, 10.0, -5.0], dtype=torch.float64, requires_grad=True)
    curve: list[float] = []
    minimise(lambda: 1e-6 * torch.sqrt(1 + (x - 3.0) ** 2).sum(), [x], FittingConfig(solver="lbfgs", iterations=30),
              "full", 0.0, curve)
    assert 2 < len(curve) <= 30 and curve[-1] == pytest.approx(3e-6, rel=1e-6)
    np.testing.assert_allclose(x.detach().numpy(), 3.0, atol=1e-3)
