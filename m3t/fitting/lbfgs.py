"""L-BFGS in rounds with a convergence test (``fitting.solver: lbfgs``), for one problem or for a batch of
independent problems sharing their objective evaluations (``lbfgs_batched``).

:func:`lbfgs_rounds` is the per-clip solver: ``torch.optim.LBFGS`` with a strong-Wolfe line search, in rounds of
``round_length`` iterations, at most ``iterations`` objective evaluations, the bounds projected after every
round; it stops once a round improved the best loss by less than ``tolerance`` (relative).

:func:`minimise_batched` runs exactly that algorithm for every problem of a batch (a clip: its frames' rows and
its own camera and identity), each on its own variables with its own ``torch.optim.LBFGS``, line searches and
convergence test, while one evaluation of the batch's objective serves all of them: each problem runs in a
thread, and the calling thread gives the problems turns, one at a time, each running until its closure asks
for an evaluation; the batch's per-problem losses are then computed in one forward and one backward (each
problem's leaves get their own gradient: the problems' terms do not share variables) and every closure gets
its problem's loss at its next turn. A problem that has stopped keeps its values and gets no more turns. One
thread runs at a time, in a fixed order, so the results do not depend on the threads' timing; they equal the
per-clip fits up to float rounding (the batch's reductions order the same sums differently).

Unlike :mod:`m3t.fitting.lockstep` (its own vectorised L-BFGS with a backtracking line search, for large
batches on a GPU), every problem here pays ``torch.optim.LBFGS``'s own bookkeeping, as a per-clip fit does;
what is saved is the evaluations' fixed costs, shared by the batch (measured on 1 CPU thread: batches of 4
clips 1.3-1.4x faster than per-clip fits).
"""
from __future__ import annotations

import threading
from collections.abc import Callable

import torch

Bounds = dict[str, tuple[float, float]]


def lbfgs_rounds(variables: list[torch.Tensor], evaluate: Callable[[torch.optim.Optimizer], torch.Tensor],
                 iterations: int, round_length: int, history: int, tolerance: float,
                 project: Callable[[], None] | None = None) -> list[float]:
    """Minimise over ``variables`` in place; ``evaluate(optimizer)`` returns the loss with the variables'
    gradients set. Returns the loss of every evaluation."""
    if iterations <= 0:
        return []
    opt = torch.optim.LBFGS(variables, lr=1.0, max_iter=round_length, history_size=history,
                            line_search_fn="strong_wolfe", tolerance_grad=1e-9, tolerance_change=1e-12)
    evaluations: list[float] = []

    def closure() -> torch.Tensor:
        loss = evaluate(opt)
        evaluations.append(float(loss.detach()))
        return loss

    previous = float("inf")
    while len(evaluations) < iterations:
        opt.param_groups[0]["max_eval"] = min(iterations - len(evaluations), round_length * 5 // 4)
        opt.step(closure)
        if project is not None:
            project()
        best = min(evaluations)
        if previous - best <= tolerance * abs(best):
            break
        previous = best
    return evaluations


class _Stopped(Exception):
    """Raised in a problem's thread when the batch stops on an error elsewhere."""


class _SharedEvaluations:
    """The problems' threads and the batch's evaluation, run in turns: the calling thread lets one problem at a
    time run until it asks for an evaluation (or ends), then evaluates the batch for all of them. One thread runs
    at any moment, so the problems' bookkeeping never contends for the interpreter, and the order of everything
    is fixed."""

    def __init__(self, problems: int, evaluate_all: Callable[[], torch.Tensor]):
        self.go = [threading.Semaphore(0) for _ in range(problems)]  # the problem's turn
        self.back = threading.Semaphore(0)  # the turn handed back to the calling thread
        self.running = list(range(problems))
        self.finished: set[int] = set()
        self.losses: torch.Tensor | None = None
        self.error: BaseException | None = None
        self.evaluate_all = evaluate_all

    def request(self, problem: int) -> torch.Tensor:
        """In a problem's thread: hand the turn back, wait for the next one, return this problem's loss."""
        self.back.release()
        self.go[problem].acquire()
        if self.error is not None:
            raise _Stopped
        return self.losses[problem]

    def start(self, problem: int) -> None:
        """In a problem's thread, before anything else: wait for its first turn."""
        self.go[problem].acquire()
        if self.error is not None:
            raise _Stopped

    def done(self, problem: int, error: BaseException | None = None) -> None:
        """In a problem's thread, last: record the end (and a first error) and hand the turn back."""
        self.finished.add(problem)
        if error is not None and not isinstance(error, _Stopped) and self.error is None:
            self.error = error
        self.back.release()

    def serve(self) -> None:
        """In the calling thread: turns and evaluations until every problem has ended or one failed."""
        while self.running:
            for problem in self.running:
                self.go[problem].release()
                self.back.acquire()
                if self.error is not None:
                    return
            self.running = [p for p in self.running if p not in self.finished]
            if not self.running:
                return
            try:
                self.losses = self.evaluate_all()
            except BaseException as exc:  # noqa: BLE001 - handed to the caller after the threads stop
                self.error = exc
                return

    def stop(self) -> None:
        """Release every problem still waiting for a turn (after an error) so that its thread ends."""
        if self.error is None:
            self.error = RuntimeError("the batched L-BFGS stopped before its problems finished")
        for problem in self.running:
            if problem not in self.finished:
                self.go[problem].release()


def minimise_batched(tensors: dict[str, torch.Tensor], per_row: list[str], per_problem: list[str],
                     slices: list[slice], loss_fn: Callable[[], torch.Tensor], iterations: int, round_length: int,
                     history: int, tolerance: float, bounds: Bounds | None = None) -> list[list[float]]:
    """:func:`lbfgs_rounds` for every problem, in place: ``tensors[per_row]`` are (R, D_k) with problem c's rows
    at ``slices[c]``, ``tensors[per_problem]`` (C, D_k); ``loss_fn()`` gives the (C,) per-problem losses from
    ``tensors``. ``bounds``: name -> (low, high) of entries projected after every round (each problem its own).
    Returns each problem's loss curve. While it runs, ``tensors`` holds the batch assembled from the problems'
    variables; afterwards the original tensors, updated, are back."""
    originals = {k: tensors[k] for k in (*per_row, *per_problem)}
    leaves = [{**{k: tensors[k][sl].detach().clone().requires_grad_(True) for k in per_row},
               **{k: tensors[k][c: c + 1].detach().clone().requires_grad_(True) for k in per_problem}}
              for c, sl in enumerate(slices)]

    def evaluate_all() -> torch.Tensor:
        for own in leaves:
            for leaf in own.values():
                leaf.grad = None
        with torch.enable_grad():  # as torch's LBFGS runs its closure, whatever the caller's grad mode
            tensors.update({k: torch.cat([own[k] for own in leaves]) for k in originals})
            losses = loss_fn()
            losses.sum().backward()
        return losses.detach()

    shared = _SharedEvaluations(len(slices), evaluate_all)
    curves: list[list[float]] = [[] for _ in slices]

    def run(c: int) -> None:
        own = leaves[c]

        def project() -> None:
            with torch.no_grad():
                for k, (low, high) in (bounds or {}).items():
                    if k in own:
                        own[k].clamp_(low, high)

        try:
            shared.start(c)
            curves[c] = lbfgs_rounds(list(own.values()), lambda _opt: shared.request(c), iterations, round_length,
                                     history, tolerance, project if bounds else None)
        except BaseException as exc:  # noqa: BLE001 - reported by the calling thread
            shared.done(c, exc)
        else:
            shared.done(c)

    threads = [threading.Thread(target=run, args=(c,), name=f"lbfgs-problem-{c}", daemon=True)
               for c in range(len(slices))]
    try:
        for thread in threads:
            thread.start()
        shared.serve()
    finally:
        if shared.error is not None or shared.running:  # stopped early: let every waiting thread end
            shared.stop()
        for thread in threads:
            thread.join()
        with torch.no_grad():
            for k, original in originals.items():
                original.copy_(torch.cat([own[k] for own in leaves]))
        tensors.update(originals)
    if shared.error is not None:
        raise shared.error
    return curves
