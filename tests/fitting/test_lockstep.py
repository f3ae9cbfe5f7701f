"""The lock-step L-BFGS (m3t.fitting.lockstep): many independent problems, one evaluation for all.

Each problem must follow its own trajectory: solved in a batch, it ends where it ends solved alone (the other
problems' steps, backtracks and stops leave no trace in its history), it reaches its own minimum whatever the
other problems' scales, and a stopped problem stays put. In fit_tracks, every clip of a lock-step batch ends
where its own lock-step fit ends, with its own identity, and fits as well as the per-clip L-BFGS.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from builders import front_camera, smooth_motion

from m3t.fitting.fit import FittingConfig, fit_tracks
from m3t.fitting.lockstep import LockstepLBFGS
from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track

# Rosenbrock problems of very different scales: one shared step length would suit none of them.
SCALES = [1.0, 30.0, 0.05]
ROWS = [3, 5, 2]  # rows of the row block per problem (two values each), plus one per-problem value


def rosenbrock_batch(which: list[int]) -> tuple[torch.Tensor, torch.Tensor, int, callable]:
    """The problems ``which`` of SCALES in one flat tensor: [rows x 2 | one value per problem]."""
    owner = torch.cat([torch.full((ROWS[p],), i) for i, p in enumerate(which)])
    start = {p: (torch.rand(ROWS[p], 2, generator=torch.Generator().manual_seed(p)) * 2 - 1,
                 torch.rand(1, generator=torch.Generator().manual_seed(10 + p))) for p in range(len(SCALES))}
    x = torch.cat([torch.cat([start[p][0] for p in which]).reshape(-1), torch.cat([start[p][1] for p in which])])
    x.requires_grad_(True)
    scales = torch.tensor([SCALES[p] for p in which])
    split = owner.shape[0] * 2

    def loss() -> torch.Tensor:
        rows = x[:split].view(-1, 2)
        tail = x[split:]
        a, b = rows[:, 0], rows[:, 1]
        per_row = (1 - a) ** 2 + 100 * (b - a ** 2) ** 2
        per_problem = torch.zeros(len(which)).index_add(0, owner, per_row)
        return scales * (per_problem + (tail - 0.5) ** 2)

    return x, owner, len(which), loss


def solve(which: list[int], evaluations: int = 400, history: int = 1000) -> tuple[torch.Tensor, list]:
    x, owner, n, loss = rosenbrock_batch(which)
    curves = LockstepLBFGS(x, owner, 2, n, history).minimise(loss, evaluations, 25, 0.0)
    return x.detach(), curves


def problem_values(x: torch.Tensor, which: list[int], p: int) -> torch.Tensor:
    """Problem ``p``'s values (its rows, then its per-problem value) out of a batch's flat tensor."""
    rows = x[:sum(ROWS[q] for q in which) * 2].view(-1, 2)
    first = sum(ROWS[q] for q in which[:which.index(p)])
    return torch.cat([rows[first:first + ROWS[p]].reshape(-1), x[sum(ROWS[q] for q in which) * 2 + which.index(p)][None]])


def test_each_problem_reaches_its_own_minimum_whatever_the_others_scales():
    x, curves = solve([0, 1, 2])
    for p in range(3):
        assert torch.allclose(problem_values(x, [0, 1, 2], p), torch.cat([torch.ones(ROWS[p] * 2), torch.tensor([0.5])]),
                              atol=1e-3)
        assert curves[p][-1] < 1e-6 * SCALES[p]


def test_a_problem_in_a_batch_ends_where_it_ends_alone():
    x, curves = solve([0, 1, 2], evaluations=60)
    for p in range(3):
        alone, alone_curves = solve([p], evaluations=60)
        assert torch.allclose(problem_values(x, [0, 1, 2], p), alone, rtol=1e-5, atol=1e-6)
        assert np.allclose(curves[p], alone_curves[0], rtol=1e-5)


@pytest.mark.parametrize("owner", [[0, 0, 0, 1, 1, 3, 3, 3, 3], [3, 0, 1, 3, 0, 3, 1, 0, 3]],
                         ids=["grouped", "interleaved"])
def test_per_problem_sums_add_each_problems_own_elements_in_order(owner):
    """``dot`` sums a problem's rows in row order, whatever the other problems hold (here a problem with no row
    and a neighbour's inf): the bits a problem's own elements give, in a batch as alone."""
    owner = torch.tensor(owner)
    generator = torch.Generator().manual_seed(0)
    problems, width = 4, 3
    x = torch.zeros(owner.shape[0] * width + problems * 2)
    solver = LockstepLBFGS(x, owner, width, problems, 10)
    a = torch.randn(x.shape, generator=generator) * 10 ** torch.randint(-3, 4, x.shape, generator=generator)
    b = torch.randn(x.shape, generator=generator)
    a[1 * width] = float("inf")  # a row of problem owner[1]
    got = solver.dot(a, b)
    prod = (a * b)[:owner.shape[0] * width].view(-1, width).sum(1)
    for p in range(problems):
        expected = (a * b)[owner.shape[0] * width:].view(problems, -1)[p].sum()
        rows = torch.zeros(())
        for r in torch.nonzero(owner == p).flatten().tolist():
            rows = rows + prod[r]
        assert torch.equal(got[p], expected + rows), p
    assert torch.isinf(got[int(owner[1])]) and torch.isfinite(got[[p for p in range(problems) if p != owner[1]]]).all()


def test_accepted_points_never_increase_a_problems_loss():
    x, owner, n, loss = rosenbrock_batch([0, 1, 2])
    solver = LockstepLBFGS(x, owner, 2, n, 100)
    solver.minimise(loss, 80, 25, 0.0)
    final = loss().detach()
    initial = rosenbrock_batch([0, 1, 2])[3]().detach()
    assert bool((final <= initial).all())


def test_a_stopped_problem_stays_put_while_the_others_go_on():
    """With a tolerance, the easy problem stops at a round's end; its value no longer moves."""
    x, owner, n, loss = rosenbrock_batch([0, 1])
    with torch.no_grad():  # problem 0 starts at its minimum
        x[:ROWS[0] * 2] = 1.0
        x[(ROWS[0] + ROWS[1]) * 2] = 0.5
    curves = LockstepLBFGS(x, owner, 2, n, 100).minimise(loss, 200, 10, 1e-3)
    assert len(set(curves[0][11:])) == 1  # stopped after the first round: evaluated at the same point since
    assert curves[1][-1] < curves[1][10]


@pytest.fixture(scope="module")
def clips(body):
    """Three clips of three signers (identities apart), 8, 6 and 5 frames."""
    out = []
    for seed, frames in ((0, 8), (1, 6), (2, 5)):
        identity = torch.tensor([0.3, 0.5, 0.5, 0.45, 0.6, 0.5]) + 0.1 * seed
        params = smooth_motion(body, frames=frames, seed=seed)
        out.append(simulate_track(f"clip-{seed}", params, identity, front_camera(), 25.0, body,
                                  SimulatedTrackerConfig(seed=seed)))
    return out


@pytest.mark.slow
def test_fit_tracks_lockstep_fits_each_clip_on_its_own(body, clips):
    cfg = FittingConfig(solver="lbfgs_lockstep", iterations=30, camera_iterations=10)
    batch = fit_tracks(clips, body, cfg)
    identities = np.stack([r.identity for r in batch])
    assert identities.shape == (3, 6) and np.abs(identities[0] - identities[1]).max() > 1e-3  # one per clip
    # up to float32 rounding (the forward's products block differently for another batch size), which 30
    # iterations amplify to ~6e-5; the coupled L-BFGS (one line search and identity for the batch) ends 0.05-0.08
    # away from the clips' own fits here
    for track, result in zip(clips, batch):
        alone = fit_tracks([track], body, cfg)[0]
        for k in result.params:
            np.testing.assert_allclose(result.params[k], alone.params[k], atol=1e-3)
        np.testing.assert_allclose(result.identity, alone.identity, atol=1e-3)
        assert result.loss_curve == pytest.approx(alone.loss_curve, rel=1e-3)
        assert len(result.loss_curve) <= cfg.iterations


@pytest.mark.slow
def test_fit_tracks_lockstep_fits_as_well_as_per_clip_lbfgs(body, clips):
    """Per-clip L-BFGS (strong Wolfe) vs lock-step (Armijo backtracking): final reprojection within 10 %."""
    lbfgs = FittingConfig(iterations=60, camera_iterations=10)
    per_clip = [fit_tracks([t], body, lbfgs)[0] for t in clips]
    lockstep = fit_tracks(clips, body, dataclasses.replace(lbfgs, solver="lbfgs_lockstep"))
    for a, b in zip(per_clip, lockstep):
        assert b.metrics["reproj_px"] <= 1.1 * a.metrics["reproj_px"] + 0.05


@pytest.mark.parametrize("model", ["anny", "smplfx"])
def test_an_identity_per_clip_equals_the_identities_per_frame(model, request):
    """``identity_index`` (one identity per clip, each frame's row) gives what per-frame identities give."""
    from builders import random_params

    from m3t.body.protocol import Correspondence

    body = request.getfixturevalue("body" if model == "anny" else "fx")
    params = random_params(body, 5, seed=4)
    g = torch.Generator().manual_seed(2)
    identities = torch.rand(2, body.layout.identity_dim, generator=g) if model == "anny" \
        else 0.5 * torch.randn(2, body.layout.identity_dim, generator=g)
    index = torch.tensor([0, 0, 1, 1, 1])
    corr = Correspondence(("a", "b", "c"), np.array([0, 0, 1]), np.array([0, 5000, 3]))
    kp = body.keypoint_set(corr)
    per_clip = body.forward_keypoints(params, identities, kp, identity_index=index)
    per_frame = body.forward_keypoints(params, identities[index], kp)
    assert torch.allclose(per_clip, per_frame, atol=1e-6)
    assert not torch.allclose(per_clip[1], body.forward_keypoints(params, identities[1], kp)[1], atol=1e-4)
