"""The solvers of ``fitting.solver``, behind one call (:func:`solve`): the camera stage and the joint stage of
:func:`m3t.fitting.fit.fit_tracks` minimise through it.

- ``lbfgs`` and ``adam`` minimise the clips' summed objective as one problem (:func:`minimise`);
- ``lbfgs_batched`` runs the ``lbfgs`` algorithm for every clip on its own, one objective evaluation serving them
  all (:func:`m3t.fitting.lbfgs.minimise_batched`);
- ``lbfgs_lockstep`` runs a vectorised L-BFGS per clip in lock-step (:func:`m3t.fitting.lockstep.minimise_rows`).
"""
from __future__ import annotations

from collections.abc import Callable

import torch

from m3t.fitting.config import FittingConfig
from m3t.fitting.lbfgs import lbfgs_rounds, minimise_batched
from m3t.fitting.lockstep import minimise_rows
from m3t.fitting.objective import ClipPack

PER_CLIP_VARIABLES = ("identity", "cam_rot", "cam_trans")  # one row per clip; every other variable one per frame


def minimise(loss_fn, variables: list[torch.Tensor], cfg: FittingConfig, stage: str, lr: float,
             curve: list[float], project_bounds=None) -> None:
    """Minimise ``loss_fn()`` over ``variables`` in place, appending every objective evaluation to ``curve``.

    The budget is ``iterations`` objective (and gradient) evaluations, ``camera_iterations`` for the camera
    stage. ``adam``: that many Adam steps at ``lr`` with a cosine decay to 5 %, the bounds projected after each
    step. ``lbfgs``: L-BFGS with a strong-Wolfe line search (``lr`` unused), in rounds of ``lbfgs_round``
    iterations, at most that many evaluations; it stops early once a round improved the loss by less than
    ``tolerance`` (relative). Bounded variables enter ``loss_fn`` clamped and are projected onto their bounds
    after every round.
    """
    iterations = cfg.camera_iterations if stage == "camera" else cfg.iterations
    if cfg.solver == "adam":
        opt = torch.optim.Adam(variables, lr=lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, iterations), eta_min=lr * 0.05)
        for _ in range(iterations):
            opt.zero_grad()
            loss = loss_fn()
            loss.backward()
            opt.step()
            sched.step()
            if project_bounds is not None:
                project_bounds()
            curve.append(float(loss.detach()))
        return
    if cfg.solver != "lbfgs":
        raise ValueError(f"fitting.solver is {cfg.solver!r}; expected 'lbfgs' or 'adam'")

    def evaluate(opt: torch.optim.Optimizer) -> torch.Tensor:
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        return loss

    curve.extend(lbfgs_rounds(variables, evaluate, iterations, cfg.lbfgs_round, cfg.lbfgs_history, cfg.tolerance,
                              project_bounds))


def solve(opt: dict[str, torch.Tensor], loss_per_clip: Callable[[], torch.Tensor], names: list[str], stage: str,
          lr: float, curve: list[float], cfg: FittingConfig, pack: ClipPack,
          bounds: dict[str, tuple[float, float]] | None = None, project_bounds=None) -> list[list[float]]:
    """Minimise the clips' summed objective ``loss_per_clip()`` (C,) over ``opt[names]`` in place; with
    ``lbfgs_batched`` / ``lbfgs_lockstep`` each clip its own, and each clip's curve is returned (else ``[]``,
    the one curve is appended to ``curve``). ``bounds`` go to ``lbfgs_batched`` when ``project_bounds`` is given."""
    if not cfg.per_clip_problems:
        minimise(lambda: loss_per_clip().sum(), [opt[k] for k in names], cfg, stage, lr, curve, project_bounds)
        return []
    per_clip = [k for k in names if k in PER_CLIP_VARIABLES]
    per_row = [k for k in names if k not in per_clip]
    budget = cfg.camera_iterations if stage == "camera" else cfg.iterations
    if cfg.solver == "lbfgs_batched":
        return minimise_batched(opt, per_row, per_clip, pack.slices, loss_per_clip, budget, cfg.lbfgs_round,
                                cfg.lbfgs_history, cfg.tolerance, bounds if project_bounds else None)
    return minimise_rows(opt, per_row, per_clip, pack.clip, loss_per_clip, budget, cfg.lbfgs_round,
                         cfg.tolerance, cfg.lbfgs_history, project_bounds)
