"""The batched L-BFGS (m3t.fitting.lbfgs.minimise_batched): the per-clip algorithm for every problem of a batch,
one objective evaluation for all.

On problems whose batched losses are computed exactly as their own losses (a loop over the problems), every
problem must end exactly where :func:`lbfgs_rounds` alone ends: same values, same loss curve, whatever the other
problems do (different scales, earlier stops, bounds). In fit_tracks, every clip ends where its own per-clip fit
ends up to float rounding, with its own identity.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from test_lockstep import clips  # noqa: F401 - the three signers' clips fixture

from m3t.fitting.fit import FittingConfig, fit_tracks
from m3t.fitting.lbfgs import lbfgs_rounds, minimise_batched

SCALES = [1.0, 30.0, 0.05, 3.0]  # Rosenbrock problems of very different scales
ROWS = [3, 5, 2, 4]  # rows (two values each) per problem, plus one per-problem value


def start(p: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(p)
    return torch.rand(ROWS[p], 2, generator=g) * 2 - 1, torch.rand(1, 1, generator=g)


def problem_loss(rows: torch.Tensor, tail: torch.Tensor, scale: float) -> torch.Tensor:
    a, b = rows[:, 0], rows[:, 1]
    return scale * (((1 - a) ** 2 + 100 * (b - a ** 2) ** 2).sum() + (tail[0, 0] - 0.5) ** 2)


def solve_alone(p: int, iterations: int, bounds=None) -> tuple[torch.Tensor, torch.Tensor, list[float]]:
    rows, tail = (t.clone().requires_grad_(True) for t in start(p))

    def evaluate(opt):
        opt.zero_grad()
        loss = problem_loss(rows, tail, SCALES[p])
        loss.backward()
        return loss

    def project():
        with torch.no_grad():
            tail.clamp_(*bounds["tail"])

    curve = lbfgs_rounds([rows, tail], evaluate, iterations, 10, 20, 1e-6, project if bounds else None)
    return rows.detach(), tail.detach(), curve


def solve_batched(which: list[int], iterations: int, bounds=None, fail_at: int | None = None):
    tensors = {"rows": torch.cat([start(p)[0] for p in which]).requires_grad_(True),
               "tail": torch.cat([start(p)[1] for p in which]).requires_grad_(True)}
    ends = np.cumsum([0] + [ROWS[p] for p in which])
    slices = [slice(int(a), int(b)) for a, b in zip(ends, ends[1:])]
    calls = []

    def loss_fn() -> torch.Tensor:
        calls.append(1)
        if fail_at is not None and len(calls) == fail_at:
            raise FloatingPointError("planted failure")
        return torch.stack([problem_loss(tensors["rows"][sl], tensors["tail"][c: c + 1], SCALES[p])
                            for c, (p, sl) in enumerate(zip(which, slices))])

    originals = dict(tensors)
    curves = minimise_batched(tensors, ["rows"], ["tail"], slices, loss_fn, iterations, 10, 20, 1e-6, bounds)
    assert tensors["rows"] is originals["rows"] and tensors["tail"] is originals["tail"]  # the leaves are back
    return tensors, slices, curves, len(calls)


@pytest.mark.parametrize("which", [[0, 1, 2, 3], [2, 0], [1]])
def test_every_problem_ends_exactly_where_it_ends_alone(which):
    tensors, slices, curves, evaluations = solve_batched(which, 80)
    for c, (p, sl) in enumerate(zip(which, slices)):
        rows, tail, curve = solve_alone(p, 80)
        assert torch.equal(tensors["rows"][sl].detach(), rows)
        assert torch.equal(tensors["tail"][c].detach(), tail[0])
        assert curves[c] == curve
    # one evaluation per batch step: as many as the longest problem needs, not the sum
    assert evaluations == max(len(c) for c in curves) < sum(len(c) for c in curves) or len(which) == 1
    lengths = {len(c) for c in curves}
    assert len(which) == 1 or len(lengths) > 1  # the problems stopped at different times


def test_it_runs_under_a_callers_no_grad_as_the_per_problem_solver_does():
    with torch.no_grad():
        tensors, slices, curves, _ = solve_batched([0, 2], 30)
    for c, (p, sl) in enumerate(zip([0, 2], slices)):
        rows, _, curve = solve_alone(p, 30)
        assert torch.equal(tensors["rows"][sl].detach(), rows) and curves[c] == curve


def test_bounds_are_projected_per_problem():
    bounds = {"tail": (0.0, 0.2)}
    tensors, _, curves, _ = solve_batched([0, 1, 2], 40, bounds)
    assert torch.all(tensors["tail"].detach() <= torch.tensor(0.2))  # the optimum, 0.5, lies outside
    for c, p in enumerate([0, 1, 2]):
        _, tail, curve = solve_alone(p, 40, bounds)
        assert torch.equal(tensors["tail"][c].detach(), tail[0])
        assert curves[c] == curve


def test_an_error_in_the_evaluation_stops_every_problem_and_is_raised():
    with pytest.raises(FloatingPointError, match="planted"):
        solve_batched([0, 1, 2], 40, fail_at=5)


def test_fit_tracks_batched_fits_each_clip_as_its_per_clip_fit(body, clips):  # noqa: F811
    per_clip_cfg = FittingConfig(iterations=30, camera_iterations=10)
    batch = fit_tracks(clips, body, dataclasses.replace(per_clip_cfg, solver="lbfgs_batched"))
    identities = np.stack([r.identity for r in batch])
    assert identities.shape == (3, 6) and np.abs(identities[0] - identities[1]).max() > 1e-3  # one per clip
    for track, result in zip(clips, batch):
        alone = fit_tracks([track], body, per_clip_cfg)[0]  # the per-clip solver (lbfgs), one clip
        # up to float32 rounding: the batch's products block differently, and 30 iterations amplify it
        for k in result.params:
            np.testing.assert_allclose(result.params[k], alone.params[k], atol=2e-3)
        np.testing.assert_allclose(result.identity, alone.identity, atol=2e-3)
        assert result.metrics["reproj_px"] == pytest.approx(alone.metrics["reproj_px"], rel=2e-2)
        assert len(result.loss_curve) <= per_clip_cfg.iterations


def test_fit_tracks_batched_is_deterministic(body, clips):  # noqa: F811
    cfg = FittingConfig(solver="lbfgs_batched", iterations=20, camera_iterations=5)
    a, b = fit_tracks(clips, body, cfg), fit_tracks(clips, body, cfg)
    for x, y in zip(a, b):
        for k in x.params:
            assert np.array_equal(x.params[k], y.params[k])
        assert x.loss_curve == y.loss_curve
