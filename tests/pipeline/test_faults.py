"""Faults a long job must survive (issue "Reliability harness"): ``kill -9`` at a random point of each job and a
rerun (the CI size of ``benchmarks/bench_faults.py``: one kill per job), a corrupt cached part file, two runs of
one stage at once, a disk full during a write."""
from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from m3t.atomic import atomic_path, run_lock
from m3t.config import load_params
from m3t.corpora.synthetic import generate_corpus
from m3t.corpora.synthetic_storage import write_corpus
from m3t.fitting.context import FitContext
from m3t.fitting.corpus import LOCK_NAME, run_fit_corpus

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_faults  # noqa: E402


@pytest.fixture()
def two_clips(tmp_path, body):
    """Two synthetic clips, fitted with few iterations, in a context sharing the session's body model."""
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "data": {"shards_root": str(tmp_path / "shards")},
        "corpora": {"synthetic": {"root": str(tmp_path / "corpus")}},
        "fitting": {"iterations": 8, "camera_iterations": 4},
        "fit_corpus": {"cache_dir": str(tmp_path / "cache"), "max_clips": 2}})
    write_corpus(generate_corpus(params.synthetic_corpus, body), params.corpora["synthetic"].root)
    return FitContext(params.fit_job("synthetic"), body)


def test_corrupt_part_file_is_refitted_not_read(two_clips, tmp_path):
    ctx = two_clips
    first = run_fit_corpus(ctx.job, ctx=ctx, progress=False)
    shards = {split: Path(p).read_bytes() for split, p in first.shards.items()}
    victim = Path(sorted(o.part for o in first.outcomes if o.part)[0])
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte: Parquet may well decode it without complaint
    victim.write_bytes(bytes(data))

    again = run_fit_corpus(ctx.job, ctx=ctx, progress=False)
    status = {Path(o.part).name: o.status for o in again.outcomes}
    assert status[victim.name] == "fitted"
    assert sorted(status.values()) == ["cached", "fitted"]
    assert {split: Path(p).read_bytes() for split, p in again.shards.items()} == shards


def test_second_fit_corpus_run_is_refused_naming_the_first(two_clips):
    ctx = two_clips
    with run_lock(Path(ctx.job.shards_dir) / LOCK_NAME, "fit-corpus synthetic"):
        with pytest.raises(RuntimeError, match=rf"already running .*pid {os.getpid()}"):
            run_fit_corpus(ctx.job, ctx=ctx, progress=False)
    assert not (Path(ctx.job.shards_dir) / LOCK_NAME).exists()


def test_second_training_on_one_last_checkpoint_is_refused(tmp_path):
    import torch

    from m3t.training import EpochTail, Selection

    def tail():
        model = torch.nn.Linear(2, 2)
        optim = torch.optim.SGD(model.parameters(), lr=0.1)
        return model, EpochTail(1, 1, Selection("train_loss"), optim, torch.optim.lr_scheduler.LambdaLR(optim, lambda s: 1),
                                save=lambda *a: None, best_path=tmp_path / "run.best.pt", last_path=tmp_path / "run.last.pt")

    model, first = tail()
    first.resume_saved(model, lambda p: None, "the test model")
    model2, second = tail()
    with pytest.raises(RuntimeError, match=rf"training the test model is already running .*pid {os.getpid()}"):
        second.resume_saved(model2, lambda p: None, "the test model")
    first.result(model)
    assert second.resume_saved(model2, lambda p: None, "the test model") == 0  # free once the first is done
    second.result(model2)
    assert list(tmp_path.iterdir()) == []


def test_a_resumed_training_removes_the_temp_file_of_a_killed_checkpoint_write(tmp_path):
    """A run killed while writing its ``last`` or ``best`` checkpoint leaves ``.run.last.pt.<hex>.tmp`` (seen in
    the kill harness, on the tokenizers and on SGSA); the rerun, holding the run's lock, removes both and keeps
    every other file."""
    import torch

    from m3t.training import EpochTail, Selection

    stale = tmp_path / ".run.last.pt.0123456789ab.tmp"
    stale.write_bytes(b"half a checkpoint")
    stale_best = tmp_path / ".run.best.pt.0123456789ab.tmp"
    stale_best.write_bytes(b"half a best checkpoint")
    other = tmp_path / ".other.last.pt.0123456789ab.tmp"  # another run's temporary: not this lock's to remove
    other.write_bytes(b"x")
    model = torch.nn.Linear(2, 2)
    optim = torch.optim.SGD(model.parameters(), lr=0.1)
    tail = EpochTail(1, 1, Selection("train_loss"), optim, torch.optim.lr_scheduler.LambdaLR(optim, lambda s: 1),
                     save=lambda *a: None, best_path=tmp_path / "run.best.pt", last_path=tmp_path / "run.last.pt")
    assert tail.resume_saved(model, lambda p: None, "the test model") == 0
    tail.result(model)
    assert not stale.exists() and not stale_best.exists() and other.exists()


def test_a_killed_lock_holder_does_not_block_the_rerun(tmp_path):
    lock = tmp_path / "out" / LOCK_NAME
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from m3t.atomic import run_lock\n"
                               f"with run_lock({str(lock)!r}, 'x'):\n print('held', flush=True); time.sleep(60)"],
                              cwd=ROOT, stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(RuntimeError, match=f"pid {holder.pid}"):
        with run_lock(lock, "x"):
            pass
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    assert lock.exists()  # kill -9 leaves the file, not the lock
    with run_lock(lock, "x"):
        assert lock.read_text().strip() == str(os.getpid())
    assert not lock.exists()


def test_disk_full_keeps_the_previous_file_and_names_the_target(tmp_path):
    target = tmp_path / "train.parquet"
    target.write_bytes(b"previous")
    with pytest.raises(OSError, match=f"no space left on the device writing {target}") as caught:
        with atomic_path(target) as tmp, open(tmp, "wb") as fh:
            fh.write(b"half a shard")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert caught.value.errno == errno.ENOSPC
    assert target.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["train.parquet"]
    assert bench_faults.disk_full_trial(tmp_path)["failures"] == 0


def test_kill_nine_and_rerun_fit_corpus(tmp_path):
    """The harness at CI size, on fit-corpus: one kill at a seeded random point, then the rerun; identical
    shards, nothing left behind, no finished clip refitted; plus the corrupt-part, corrupt-track, concurrent-run
    and disk-full trials. The trainers' kill trials run with ``python benchmarks/bench_faults.py``."""
    began = time.perf_counter()
    result = bench_faults.run(kills=1, jobs=["fit-corpus"], clips=2, iterations=10, seed=0, root=tmp_path)
    problems = {name: [t["problems"] for t in r["runs"]] for name, r in result["jobs"].items()}
    problems.update({name: r["problems"] for name, r in result["faults"].items()})
    assert result["failures"] == 0, problems
    assert set(result["jobs"]) == {"fit-corpus"} and result["trials"] == 1 + 4
    assert time.perf_counter() - began < 600
