"""The shared training mechanics: schedule values, best selection in both directions, evaluation cadence,
rank-0-only saving, and a ``last`` checkpoint that continues the same run (optimizer, schedule, RNG)."""
from __future__ import annotations

import math
import random

import numpy as np
import pytest
import torch

from m3t.checkpoints import read_checkpoint, save_checkpoint
from m3t.optimizer import adam, optimizer_step, warmup_cosine
from m3t.training import EpochTail, Selection


def lrs(scheduler, steps: int) -> list[float]:
    """The LR used by each of the first ``steps`` optimiser steps."""
    out = []
    for _ in range(steps):
        out.append(scheduler.optimizer.param_groups[0]["lr"])
        scheduler.optimizer.step()
        scheduler.step()
    return out


def sgd(lr: float = 1.0) -> torch.optim.Optimizer:
    return torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=lr)


@pytest.mark.parametrize("decoupled", [False, True])
def test_adam_runs_the_fused_kernel_on_the_cpu_with_the_update_of_torchs_default_adam(decoupled):
    """Every trainer's optimiser: fused where the device has the kernel, the same update as torch's default
    (foreach) Adam / AdamW with the same options to float rounding, options passed through."""
    torch.manual_seed(0)
    start = [torch.randn(7, 5), torch.randn(5)]
    options = {"lr": 1e-2, "betas": (0.8, 0.95), "weight_decay": 0.1}
    runs = {}
    for fused in (False, True):
        params = [p.clone().requires_grad_(True) for p in start]
        reference = torch.optim.AdamW if decoupled else torch.optim.Adam
        optim = adam(params, "cpu", decoupled=decoupled, **options) if fused else reference(params, **options)
        assert isinstance(optim, reference) and optim.defaults["fused"] is (True if fused else None)
        assert optim.defaults["betas"] == (0.8, 0.95) and optim.defaults["weight_decay"] == 0.1
        generator = torch.Generator().manual_seed(1)
        for _ in range(20):
            for p in params:
                p.grad = torch.randn(p.shape, generator=generator)
            optim.step()
        runs[fused] = [p.detach() for p in params]
    moved = max(float((a - b).abs().max()) for a, b in zip(runs[True], start))
    assert moved > 0.05  # the steps did something
    for a, b in zip(runs[False], runs[True]):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
    # a device without the fused kernel gets torch's default implementation
    assert adam([torch.zeros(2, requires_grad=True)], "mps", lr=1e-3).defaults["fused"] is None


@pytest.mark.parametrize("unit, warmup", [("epochs", 2), ("steps", 20)])
def test_schedule_warms_up_then_decays_to_the_floor(unit, warmup):
    # 10 epochs x 10 steps, 20 warm-up steps (2 epochs), LR 2.0 -> 0.02
    lr = lrs(warmup_cosine(sgd(2.0), 10, 10, warmup, unit, min_lr=0.02), 101)
    assert lr[0] == pytest.approx(2.0 / 20)  # warm-up starts at 1/20
    assert lr[19] == pytest.approx(2.0)  # warm-up ends at the full LR
    assert all(a < b for a, b in zip(lr[:19], lr[1:20]))
    assert lr[60] == pytest.approx((2.0 + 0.02) / 2)  # half-way through the cosine
    assert all(a >= b for a, b in zip(lr[20:100], lr[21:101]))
    assert lr[100] == pytest.approx(0.02)  # the end of training: the floor


def test_schedule_without_warm_up_starts_at_the_full_lr_and_refuses_unknown_units():
    assert lrs(warmup_cosine(sgd(), 2, 5, 0, "steps", min_lr=0.0), 1) == [1.0]
    with pytest.raises(ValueError, match="warmup_unit 'minutes' unknown"):
        warmup_cosine(sgd(), 2, 5, 1, "minutes", 0.0)


def make_tail(tmp_path, scores, mode="min", eval_every=1, epochs=None, evaluate=True, is_main=True,
              selection=None, last_every_s=0.0):
    """A tail over a tiny model; ``evaluate`` returns the next of ``scores`` as ``val_score``."""
    model = torch.nn.Linear(2, 1)
    optim = torch.optim.Adam(model.parameters(), lr=0.1)
    scheduler = warmup_cosine(optim, epochs or len(scores), 1, 1, "epochs", 1e-3)
    saved, logged, values = [], [], iter(scores)

    def save(path, epoch, step, record, state):
        saved.append((path.name, epoch))
        save_checkpoint(path, {"format": "test", "state_dict": model.state_dict(), "train_state": state})

    selection = selection or Selection("val_score", mode)
    tail = EpochTail(epochs or len(scores), eval_every, selection, optim, scheduler, save,
                     tmp_path / "best.pt", tmp_path / "last.pt",
                     evaluate=(lambda: {"score": next(values)}) if evaluate else None, is_main=is_main,
                     on_epoch=lambda record, epoch: logged.append(epoch), last_every_s=last_every_s)
    return tail, model, saved, logged


def run(tail, model, epochs):
    for epoch in epochs:
        loss = model(torch.randn(4, 2)).pow(2).mean()
        optimizer_step(loss, model, tail.optim, tail.scheduler, grad_clip=1.0)
        tail.step += 1
        tail.end_epoch(epoch, {"train_loss": loss.item()})


@pytest.mark.parametrize("mode, best_epoch", [("min", 2), ("max", 4)])
def test_best_is_selected_by_the_named_metric_in_either_direction(tmp_path, mode, best_epoch):
    tail, model, saved, logged = make_tail(tmp_path, [3.0, 1.0, 2.0, 5.0, 1.0], mode)
    run(tail, model, tail.remaining())
    assert tail.best["epoch"] == best_epoch and tail.best["val_score"] == (1.0 if mode == "min" else 5.0)
    bests = [e for name, e in saved if name == "best.pt"]
    assert bests[-1] == best_epoch  # a tie (epoch 5 in "min") keeps the earlier epoch
    assert [h["epoch"] for h in tail.history] == logged == [1, 2, 3, 4, 5]
    assert read_checkpoint(tmp_path / "best.pt", "test", "test", "none")["train_state"] is None


def test_only_evaluated_epochs_compete_and_the_last_epoch_is_always_evaluated(tmp_path):
    tail, model, saved, _ = make_tail(tmp_path, [9.0, 8.0], eval_every=2, epochs=3)
    run(tail, model, tail.remaining())
    assert ["val_score" in h for h in tail.history] == [False, True, True]
    assert [e for name, e in saved if name == "best.pt"] == [2, 3]


def test_without_an_evaluator_every_epoch_competes_on_its_training_record(tmp_path):
    tail, model, saved, _ = make_tail(tmp_path, [], epochs=3, evaluate=False, selection=Selection("epoch", "max"))
    run(tail, model, tail.remaining())
    assert [e for name, e in saved if name == "best.pt"] == [1, 2, 3]
    tail, model, _, _ = make_tail(tmp_path / "b", [], epochs=1, evaluate=False)  # metric never logged: said so
    with pytest.raises(KeyError, match="selection metric 'val_score' is not in the record of epoch 1"):
        run(tail, model, tail.remaining())


def test_other_ranks_neither_evaluate_nor_save_nor_log(tmp_path):
    tail, model, saved, logged = make_tail(tmp_path, [1.0, 2.0], is_main=False)
    run(tail, model, tail.remaining())
    assert saved == [] and logged == [] and tail.history == [] and tail.epoch == 2 and tail.step == 2


def test_last_is_saved_at_most_every_last_every_s_and_always_where_the_run_or_its_range_ends(tmp_path, monkeypatch):
    clock = iter(float(t) for t in range(0, 1000, 10))  # every monotonic() call: 10 s later
    monkeypatch.setattr("m3t.training.time.monotonic", lambda: next(clock))
    tail, model, saved, _ = make_tail(tmp_path, [1.0] * 8, last_every_s=25.0)
    run(tail, model, tail.remaining(stop_after_epochs=6))
    # built at t=0; epoch 1 ends at 10 s, 2 at 20 s, 3 at 30 s (saved, clock read again: 40 s), 4 at 50 s,
    # 5 at 60 s, 6 at 70 s (saved: 30 s since 40 s), and the range ends at 6 anyway
    assert [e for name, e in saved if name == "last.pt"] == [3, 6]
    run(tail, model, tail.remaining())
    assert [e for name, e in saved if name == "last.pt"][-1] == 8  # the end of the run: always
    assert [e for name, e in saved if name == "best.pt"] == [1]  # best is not subject to the cadence

    tail, model, saved, _ = make_tail(tmp_path / "every", [1.0] * 3, last_every_s=0.0)
    run(tail, model, tail.remaining())
    assert [e for name, e in saved if name == "last.pt"] == [1, 2, 3]


def test_last_checkpoint_continues_the_same_run(tmp_path):
    scores = [3.0, 1.0, 2.0, 0.5]
    torch.manual_seed(0), np.random.seed(0), random.seed(0)
    straight, model, _, _ = make_tail(tmp_path / "a", scores)
    run(straight, model, straight.remaining())
    expected = (model.state_dict(), straight.history, torch.rand(3), np.random.rand(3), random.random())

    torch.manual_seed(0), np.random.seed(0), random.seed(0)
    part, model, _, _ = make_tail(tmp_path / "b", scores)
    run(part, model, part.remaining(stop_after_epochs=2))
    assert len(part.history) == 2
    torch.manual_seed(123), np.random.seed(123), random.seed(123)  # another process, other draws
    payload = read_checkpoint(tmp_path / "b" / "last.pt", "test", "test", "none")  # weights_only
    resumed, model, _, _ = make_tail(tmp_path / "b", scores[2:], epochs=4)
    model.load_state_dict(payload["state_dict"])
    resumed.resume(payload["train_state"])
    assert (resumed.epoch, resumed.step, resumed.best["epoch"]) == (2, 2, 2)
    assert list(resumed.remaining()) == [2, 3]
    run(resumed, model, resumed.remaining())
    state, history, torch_draw, numpy_draw, python_draw = expected
    assert resumed.history == history  # losses, LRs, validation values: exactly the same
    assert all(torch.equal(state[k], v) for k, v in model.state_dict().items())
    assert torch.equal(torch.rand(3), torch_draw) and np.array_equal(np.random.rand(3), numpy_draw)
    assert random.random() == python_draw
    assert resumed.best["epoch"] == 4 and math.isclose(resumed.best_score, 0.5)


def test_an_older_torch_only_rng_state_still_resumes(tmp_path):
    tail, model, _, _ = make_tail(tmp_path, [1.0, 2.0])
    run(tail, model, tail.remaining(1))
    state = dict(tail.train_state(), rng=torch.get_rng_state())
    expected = torch.rand(2)
    tail.resume(state)
    assert torch.equal(torch.rand(2), expected)


def test_the_same_checkpoint_payload_gives_the_same_bytes(tmp_path):
    """Digests of checkpoints (data versions, token-shard provenance, DVC) only change when the content does."""
    payload = {"format": "x", "state_dict": {"w": torch.arange(6.0).reshape(2, 3)}, "epoch": 3}
    a = save_checkpoint(tmp_path / "a.pt", payload).read_bytes()
    b = save_checkpoint(tmp_path / "sub" / "b.pt", payload).read_bytes()
    assert a == b
    assert read_checkpoint(tmp_path / "a.pt", "x", "test", "stage")["epoch"] == 3


# ---- run_jobs: independent trainings in worker processes ---------------------------------------------------
def _job_square(job: int, on_epoch) -> tuple[int, int, int]:
    """A job for run_jobs: two epoch records, then its square, its process and its thread count."""
    import os

    for epoch in (1, 2):
        if on_epoch is not None:
            on_epoch({"value": float(job * epoch)}, epoch)
    return job * job, os.getpid(), torch.get_num_threads()


def _job_fails(job: int, on_epoch) -> int:
    if job == 2:
        raise KeyError(f"job {job} has no data")
    return job


def _job_dies(job: int, on_epoch) -> int:
    import os

    if job == 1:
        os._exit(3)  # as the OOM killer would
    return job


def test_worker_split_uses_processes_only_for_several_jobs_on_the_cpu_without_ddp():
    from m3t.training_jobs import worker_split

    torch.set_num_threads(4)  # conftest restores the count
    assert worker_split(2, 3, "cpu") == (2, 2) and worker_split(4, 2, "cpu") == (2, 2)
    assert worker_split(8, 8, "cpu") == (8, 1)  # never fewer than one thread each
    assert worker_split(1, 3, "cpu") == (1, 0) and worker_split(2, 1, "cpu") == (1, 0)
    assert worker_split(2, 3, "cpu", world_size=2) == (1, 0)


@pytest.mark.slow
def test_run_jobs_in_workers_returns_in_job_order_with_the_records_of_one_process_per_job():
    """Here, each job's records reach on_epoch as they happen; in two spawned one-thread workers the same
    results come back in job order and the records are replayed in job order."""
    import os

    from m3t.training_jobs import run_jobs

    here: list = []
    results_here = run_jobs(_job_square, [3, 1, 2], ["c", "a", "b"], on_epoch=lambda *r: here.append(r))
    assert [r[0] for r in results_here] == [9, 1, 4] and {r[1] for r in results_here} == {os.getpid()}
    assert here == [("c", {"value": 3.0}, 1), ("c", {"value": 6.0}, 2), ("a", {"value": 1.0}, 1),
                    ("a", {"value": 2.0}, 2), ("b", {"value": 2.0}, 1), ("b", {"value": 4.0}, 2)]
    there: list = []
    results_there = run_jobs(_job_square, [3, 1, 2], ["c", "a", "b"], processes=2, threads=1,
                             on_epoch=lambda *r: there.append(r))
    assert [r[0] for r in results_there] == [9, 1, 4] and there == here
    assert os.getpid() not in {r[1] for r in results_there} and {r[2] for r in results_there} == {1}
    with pytest.raises(ValueError, match="3 jobs but 2 names"):
        run_jobs(_job_square, [1, 2, 3], ["a", "b"])


@pytest.mark.slow
def test_run_jobs_raises_a_jobs_error_as_raised_and_names_a_worker_that_died():
    from m3t.training_jobs import run_jobs

    with pytest.raises(KeyError, match="job 2 has no data"):
        run_jobs(_job_fails, [1, 2], ["one", "two"], processes=2, threads=1)
    # the first job's worker dies (when another job's did, the first may be reported broken too)
    with pytest.raises(RuntimeError, match=r"running system 'one' died .*set sgsa_train.workers: 1"):
        run_jobs(_job_dies, [1, 2], ["one", "two"], processes=2, threads=1, what="system",
                 setting="sgsa_train.workers")


def _job_sleeps(job: str, on_epoch) -> None:
    """Writes its process id to the file ``job``, then sleeps far longer than any test waits."""
    import os
    import time
    from pathlib import Path

    Path(job).write_text(str(os.getpid()))
    time.sleep(120)


STAGE_POOLS = {  # a stage whose worker writes its pid to the file {pid!r} and sleeps
    "trainer jobs": "from m3t.training_jobs import run_jobs; "
                    "run_jobs(t._job_sleeps, [{pid!r}, {pid!r}], ['a', 'b'], processes=2, threads=1)",
    "fit-corpus pool": "from m3t.fitting.cluster import process_pool; "
                       "pool = process_pool(2); pool.submit(t._job_sleeps, {pid!r}, None).result()",
}


@pytest.mark.slow
@pytest.mark.parametrize("pool", sorted(STAGE_POOLS))
def test_a_worker_ends_itself_when_the_stage_process_is_killed(tmp_path, pool):
    """``kill -9`` of a stage leaves its pool no chance to stop the workers; each notices its parent is gone and
    exits (an orphan would go on fitting or training on the cores the rerun needs, and a trainer's would hold
    the run's lock against it). Both of the project's pools: the trainers' jobs and fit-corpus's executor."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    pid_file = tmp_path / "worker.pid"
    code = "import test_training as t; " + STAGE_POOLS[pool].format(pid=str(pid_file))
    stage = subprocess.Popen([sys.executable, "-c", code], cwd=Path(__file__).parent)
    try:
        deadline = time.monotonic() + 60
        while not pid_file.exists() or not pid_file.read_text():
            assert time.monotonic() < deadline and stage.poll() is None, "the worker never started"
            time.sleep(0.2)
        worker = int(pid_file.read_text())
        os.kill(stage.pid, signal.SIGKILL)
        stage.wait()
        deadline = time.monotonic() + 10
        while Path(f"/proc/{worker}").exists() and "Z" not in Path(f"/proc/{worker}/stat").read_text().split()[2]:
            assert time.monotonic() < deadline, f"worker {worker} still runs 10 s after its stage was killed"
            time.sleep(0.2)
    finally:
        if stage.poll() is None:
            stage.kill()
