"""The executors of fit-corpus (:mod:`m3t.fitting.cluster`) built without starting a cluster, and the run's scheduler
(capacity, polling, dead workers, failing tasks) driven by in-process stand-in executors. Written to pin behaviours
that mutation testing found unchecked.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import ClassVar

import pytest
import torch

from m3t.config import load_params
from m3t.corpora.clip import Clip
from m3t.fitting.context import FitContext
from m3t.fitting.report import ClipOutcome

ROOT = Path(__file__).resolve().parents[2]


# lbfgs: a signer batch (fit_corpus.batch_clips) is one problem with one identity, what the batch tests here check;
# the default, lbfgs_batched (every clip its own problem), is tested in fitting/test_lbfgs.py and the pipeline tests
FAST = {"iterations": 4, "camera_iterations": 2, "solver": "lbfgs"}


@pytest.fixture(autouse=True)
def _one_thread():
    """Small fits run fastest on one intra-op thread (conftest restores the count after each test)."""
    torch.set_num_threads(1)


def fit_job(tmp_path: Path, corpus: str, root: Path, options: dict | None = None, fit_corpus: dict | None = None,
            **sections):
    """The tiny preset's job of ``corpus`` at ``root``, with its cache and shards under ``tmp_path``."""
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "corpora": {corpus: {"root": str(root), "options": options or {}}},
        "data": {"shards_root": str(tmp_path / "shards")},
        "fitting": {**FAST, **sections.pop("fitting", {})},
        "fit_corpus": {"cache_dir": str(tmp_path / "cache"), "workers": 1, **(fit_corpus or {})},
        **sections})
    return params.fit_job(corpus)


# ------------------------------------------------------------------------------------------ executors
@pytest.mark.slow
def test_the_local_process_pool_spawns_single_threaded_workers():
    """Spawned, not forked: a forked child inherits torch's thread pool and locks of a process that already
    fitted; each worker runs with one intra-op thread."""
    from concurrent.futures import ProcessPoolExecutor

    from m3t.fitting.cluster import open_executor, process_pool
    from m3t.fitting.config import FitCorpusConfig

    assert process_pool(1) is None and process_pool(0) is None  # one worker: clips run in this process
    torch.set_num_threads(2)  # what the workers must not inherit
    pool = process_pool(3)
    try:
        assert isinstance(pool, ProcessPoolExecutor) and pool._max_workers == 3
        assert pool._mp_context.get_start_method() == "spawn"
        assert pool.submit(torch.get_num_threads).result(timeout=120) == 1
    finally:
        pool.shutdown()
    with open_executor(FitCorpusConfig(executor="local", workers=1)) as executor:
        assert executor is None
    with (pytest.raises(ValueError, match=r"fit_corpus.executor: 'ray' is not allowed; expected 'local' or 'dask'"),
          open_executor(FitCorpusConfig(executor="ray"))):
        pass


class FakeCluster:
    """What ``connect_dask`` asks of ``distributed.LocalCluster``: its arguments, and ``close``."""

    made: ClassVar[list] = []

    def __init__(self, **kwargs):
        self.kwargs, self.closed = kwargs, False
        FakeCluster.made.append(self)

    def close(self, timeout=None):
        self.closed = True


class FakeClient:
    """What ``DaskExecutor`` asks of ``distributed.Client``: the scheduler's address, an executor, ``close``."""

    made: ClassVar[list] = []
    fail: ClassVar[Exception | None] = None

    def __init__(self, address, **kwargs):
        if FakeClient.fail is not None:
            raise FakeClient.fail
        self.address, self.kwargs, self.closed, self.status = address, kwargs, False, "closed"
        self.scheduler = type("Scheduler", (), {"address": address if isinstance(address, str) else "tcp://local"})
        FakeClient.made.append(self)

    def get_executor(self):
        return None

    def close(self, timeout=None):
        self.closed = True


@pytest.fixture()
def fake_dask(monkeypatch):
    import distributed

    monkeypatch.setattr(distributed, "LocalCluster", FakeCluster)
    monkeypatch.setattr(distributed, "Client", FakeClient)
    FakeCluster.made, FakeClient.made, FakeClient.fail = [], [], None
    yield
    FakeClient.fail = None


def test_a_dask_run_without_an_address_starts_and_closes_its_own_single_threaded_cluster(fake_dask):
    from m3t.fitting.cluster import CONNECT_SECONDS, connect_dask
    from m3t.fitting.config import FitCorpusConfig

    executor = connect_dask(FitCorpusConfig(executor="dask", workers=3))
    (cluster,), (client,) = FakeCluster.made, FakeClient.made
    assert {k: cluster.kwargs[k] for k in ("n_workers", "threads_per_worker", "processes")} == {
        "n_workers": 3, "threads_per_worker": 1, "processes": True}
    assert cluster.kwargs["dashboard_address"].endswith(":0")  # a free port, never the default 8787
    assert client.address is cluster and client.kwargs == {"set_as_default": False}  # never the process' default
    assert executor.client is client and executor.address == "tcp://local"
    executor.shutdown()
    assert client.closed and cluster.closed

    connect_dask(FitCorpusConfig(executor="dask", workers=0))
    assert FakeCluster.made[-1].kwargs["n_workers"] == 1

    FakeClient.fail = RuntimeError("no client")
    with pytest.raises(RuntimeError, match="no client"):
        connect_dask(FitCorpusConfig(executor="dask", workers=2))
    assert FakeCluster.made[-1].closed  # a cluster started for nothing is not left running

    FakeClient.fail = None
    remote = connect_dask(FitCorpusConfig(executor="dask", dask_address="tcp://scheduler:8786"))
    assert len(FakeCluster.made) == 3 and FakeClient.made[-1].address == "tcp://scheduler:8786"
    assert FakeClient.made[-1].kwargs == {"timeout": CONNECT_SECONDS, "set_as_default": False}
    remote.shutdown()
    assert FakeClient.made[-1].closed  # a running cluster is left running: only the client closes
    FakeClient.fail = OSError("refused")
    with pytest.raises(ConnectionError, match=rf"no Dask scheduler answered at 'tcp://scheduler:8786' within "
                                              rf"{CONNECT_SECONDS:.0f} s \(refused\)"):
        connect_dask(FitCorpusConfig(executor="dask", dask_address="tcp://scheduler:8786"))


# ------------------------------------------------------------------------------------------ jobs sent to workers
def test_a_worker_process_fits_with_one_torch_thread():
    from m3t.fitting.cluster import on_worker, one_thread

    torch.set_num_threads(2)
    one_thread()
    assert torch.get_num_threads() == 1
    one_thread()  # already one: stays one
    assert torch.get_num_threads() == 1
    torch.set_num_threads(3)
    assert on_worker(lambda a, b=0: (a, b, torch.get_num_threads()), "clip", b=4) == ("clip", 4, 1)


def test_a_job_sent_to_other_machines_names_its_paths_absolutely(tmp_path, monkeypatch):
    """The cache dir, the corpus root and the body model's build cache are made absolute against this process'
    working directory; an empty root (the adapter's packaged default) and the licensed body files (part of the
    fits' key as written) stay as given, and so does everything else of the job."""
    from m3t.fitting.cluster import for_workers

    job = fit_job(tmp_path, "synthetic", tmp_path)
    relative = dataclasses.replace(job, run=dataclasses.replace(job.run, cache_dir=".cache/fit"),
                                   source=dataclasses.replace(job.source, root="data/corpus"),
                                   body=dataclasses.replace(job.body, cache_dir=".cache/anny"))
    monkeypatch.chdir(tmp_path)
    moved = for_workers(relative)
    assert moved.run.cache_dir == str(tmp_path / ".cache" / "fit")
    assert moved.source.root == str(tmp_path / "data" / "corpus")
    assert moved.body.cache_dir == str(tmp_path / ".cache" / "anny")
    assert moved.body.smplx_path == relative.body.smplx_path == "models/smplx/SMPLX_NEUTRAL.npz"
    assert moved.source.options == relative.source.options and moved.run.workers == relative.run.workers
    assert (moved.corpus, moved.shards_dir, moved.fitting, moved.tracker) == (
        relative.corpus, relative.shards_dir, relative.fitting, relative.tracker)
    assert for_workers(moved) == moved  # absolute paths stay
    packaged = for_workers(dataclasses.replace(relative, source=dataclasses.replace(relative.source, root="")))
    assert packaged.source.root == ""


class SchedulerClient:
    """What :class:`m3t.fitting.cluster.DaskExecutor` asks of a ``distributed.Client``: its scheduler's address
    and ``identity`` (asked through ``sync``), an executor, ``status`` and ``close``; every call recorded."""

    def __init__(self, identity=None, fail: Exception | None = None, status: str = "running"):
        self.status, self.identity, self.fail = status, identity or {}, fail
        self.calls: list = []
        self.submitted: list = []
        self.scheduler = type("Scheduler", (), {"address": "tcp://10.0.0.2:8786", "identity": object()})()
        client = self

        class Tasks:
            def submit(self, fn, *args, key=None, **kwargs):
                client.submitted.append((fn, args, key, kwargs))
                return "future"

            def shutdown(self, wait=True):
                client.calls.append(("executor.shutdown", wait))

        self.tasks = Tasks()

    def get_executor(self):
        return self.tasks

    def sync(self, fn, **kwargs):
        self.calls.append(("sync", fn, kwargs))
        if self.fail is not None:
            raise self.fail
        return self.identity

    def close(self, timeout=None):
        self.calls.append(("close", timeout))
        self.status = "closed"


def test_a_dask_executor_keeps_one_task_per_worker_thread_in_flight():
    from m3t.fitting.cluster import CONNECT_SECONDS, DaskExecutor

    client = SchedulerClient({"total_threads": 3, "workers": {}})
    executor = DaskExecutor(client)
    assert executor.address == "tcp://10.0.0.2:8786" and executor.capacity() == 3
    # the scheduler's summary without per-worker details, asked with a timeout
    assert client.calls == [("sync", client.scheduler.identity, {"n_workers": 0, "callback_timeout": CONNECT_SECONDS})]
    executor.check()
    assert len(client.calls) == 2 and client.calls[1] == client.calls[0]
    for identity in ({"total_threads": 0}, {}):  # no worker yet: one task waits for one to join
        assert DaskExecutor(SchedulerClient(identity)).capacity() == 1


@pytest.mark.parametrize("client, why", [
    (SchedulerClient(status="closed"), "the client's connection is closed"),
    (SchedulerClient(fail=OSError("Timed out trying to connect")),
     "it did not answer within 30 s: OSError: Timed out trying to connect"),
])
def test_a_lost_scheduler_stops_the_run_naming_its_address(client, why):
    from m3t.fitting.cluster import DaskExecutor, SchedulerLost

    executor = DaskExecutor(client)
    for ask in (executor.check, executor.capacity):
        with pytest.raises(SchedulerLost) as info:
            ask()
        assert str(info.value) == (f"lost the Dask scheduler at tcp://10.0.0.2:8786 ({why}); finished clips are "
                                   "cached, rerun to resume")


def test_a_dask_task_carries_the_workers_job_and_a_key_of_its_own(tmp_path, monkeypatch):
    from m3t.fitting.cluster import DaskExecutor, on_worker
    from m3t.fitting.corpus import fit_batch

    job = fit_job(tmp_path, "synthetic", tmp_path)
    job = dataclasses.replace(job, run=dataclasses.replace(job.run, cache_dir="cache"))
    monkeypatch.chdir(tmp_path)
    client = SchedulerClient()
    executor = DaskExecutor(client)
    assert executor.submit(fit_batch, job, ["clip"], extra=1) == "future"
    executor.submit(fit_batch, job, ["clip"])
    (fn, args, key, kwargs), again = client.submitted
    assert fn is on_worker and args[0] is fit_batch and args[2] == ["clip"] and kwargs == {"extra": 1}
    assert args[1].run.cache_dir == str(tmp_path / "cache")  # the job as the workers must see it
    assert key.startswith("fit-clips-") and again[2].startswith("fit-clips-") and key != again[2]


def test_a_dask_executor_closes_its_client_and_only_the_cluster_it_started():
    from m3t.fitting.cluster import CONNECT_SECONDS, DaskExecutor

    client, cluster = SchedulerClient(), FakeCluster()
    DaskExecutor(client, cluster).shutdown()
    assert client.calls == [("executor.shutdown", True), ("close", CONNECT_SECONDS)] and cluster.closed
    for kwargs in ({"cancel_futures": True}, {"wait": False}):  # a stopped run waits for nothing
        client = SchedulerClient()
        DaskExecutor(client).shutdown(**kwargs)
        assert client.calls == [("close", CONNECT_SECONDS)]
    lost = SchedulerClient(status="closed")
    DaskExecutor(lost).shutdown()
    assert lost.calls == [("close", CONNECT_SECONDS)]

    class Failing(SchedulerClient):
        def close(self, timeout=None):
            raise OSError("connection reset")

    cluster = FakeCluster()
    with pytest.raises(OSError, match="connection reset"):
        DaskExecutor(Failing(), cluster).shutdown()
    assert cluster.closed  # the local cluster is closed whatever the client did


def test_only_a_dead_dask_worker_quarantines_a_batch():
    from types import SimpleNamespace

    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    from m3t.fitting.cluster import worker_died

    assert worker_died(KilledWorker("fit-clips-1", SimpleNamespace(address="tcp://10.0.0.7:4000"), 3))
    assert worker_died(CommClosedError("in <TCP (closed)>: Stream is closed"))
    assert not worker_died(ValueError("a bad clip")) and not worker_died(MemoryError())


def test_a_process_pools_failures_are_never_taken_for_dead_dask_workers(monkeypatch):
    """Only Dask raises a dead worker's errors: without Dask imported, nothing is one, and Dask stays unimported."""
    import sys

    from m3t.fitting.cluster import worker_died

    monkeypatch.delitem(sys.modules, "distributed", raising=False)
    assert not worker_died(MemoryError()) and not worker_died(OSError("Broken pipe"))
    assert "distributed" not in sys.modules


# ------------------------------------------------------------------------------------------ the run's scheduler
class BareExecutor:
    """An in-process stand-in for a process pool: ``submit`` records what it is sent and returns a future that
    ``plan(batch)`` settles at once (a list of outcomes, or an exception) or leaves pending (None) for the test
    to settle (:meth:`settle`); no process, no cluster."""

    def __init__(self, plan):
        self.plan, self.sent, self.futures = plan, [], {}

    def submit(self, fn, *args):
        from concurrent.futures import Future

        future = Future()
        self.sent.append((fn, args))
        self.futures[tuple(c.id for c in args[1])] = future
        result = self.plan(args[1])
        if isinstance(result, BaseException):
            future.set_exception(result)
        elif result is not None:
            future.set_result(result)
        return future

    def settle(self, *clip_ids: str) -> None:
        future = self.futures[clip_ids]
        if not future.done():
            future.set_result([ClipOutcome(i, "train", "fitted", frames=3, seconds=0.5) for i in clip_ids])


class ClusterExecutor(BareExecutor):
    """A stand-in for :class:`m3t.fitting.cluster.DaskExecutor`: ``capacity()`` worker threads and ``check()``,
    which counts the questions and raises ``lost`` when it is set."""

    def __init__(self, plan, slots: int, lost: Exception | None = None):
        super().__init__(plan)
        self.slots, self.lost, self.checks = slots, lost, 0

    def capacity(self) -> int:
        return self.slots

    def check(self) -> None:
        self.checks += 1
        if self.lost is not None:
            raise self.lost


def fitted(batch) -> list[ClipOutcome]:
    return [ClipOutcome(c.id, c.split, "fitted", frames=3, seconds=0.5) for c in batch]


def signer_clips(*signers: str) -> list[Clip]:
    """Clips ``<signer><n>`` of the given signers (one letter each), listed in that order; never opened."""
    seen: dict[str, int] = {}
    out = []
    for s in signers:
        seen[s] = seen.get(s, 0) + 1
        clip_id = f"{s}{seen[s]}"
        out.append(Clip(clip_id, "synthetic", "dev", "ASL-SYN", s, "", "", f"motion/{clip_id}.npz", 25.0))
    return out


def test_a_cluster_gets_at_most_its_capacity_and_each_batch_counts_when_it_ends(body, tmp_path, capsys):
    """Two worker threads: two batches in flight; a slow batch does not hold back the report of those sent after
    it, and the progress bar counts every clip."""
    import threading

    from m3t.fitting.corpus import fit_batch, run_fit_corpus

    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus")
    clips = signer_clips("a", "b", "c", "d")
    executor = ClusterExecutor(lambda batch: None if batch[0].id == "b1" else fitted(batch), slots=2)
    seen = []

    def on_outcome(outcome: ClipOutcome) -> None:
        seen.append((outcome.clip_id, executor.futures[("b1",)].done(), len(executor.sent)))
        if outcome.clip_id == "d1":
            executor.settle("b1")

    late = threading.Timer(3.0, executor.settle, ("b1",))  # never needed unless the run waits for every batch
    late.start()
    try:
        report = run_fit_corpus(job, executor, clips=clips, progress=True, on_outcome=on_outcome,
                                ctx=FitContext(job, body))
    finally:
        late.cancel()
    # b1 holds one of the two slots throughout: the others go one at a time
    assert seen == [("a1", False, 2), ("c1", False, 3), ("d1", False, 4), ("b1", True, 4)]
    assert [args for _, args in executor.sent] == [(job, [c]) for c in (clips[0], clips[1], clips[2], clips[3])]
    assert all(fn is fit_batch for fn, _ in executor.sent)
    assert [o.clip_id for o in report.outcomes] == ["a1", "b1", "c1", "d1"] and report.summary["clips_fitted"] == 4
    bar = capsys.readouterr().err
    assert "fit-corpus synthetic" in bar and "4/4" in bar


def test_a_run_shows_its_progress_bar_only_when_asked(body, tmp_path, capsys):
    from m3t.fitting.corpus import run_fit_corpus

    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus")
    run_fit_corpus(job, ClusterExecutor(fitted, slots=1), clips=signer_clips("a", "a"), progress=False,
                   ctx=FitContext(job, body))
    assert "fit-corpus" not in capsys.readouterr().err


def test_while_no_batch_ends_the_run_asks_whether_the_cluster_is_still_there(tmp_path, monkeypatch):
    import threading

    import m3t.fitting.corpus as engine
    from m3t.fitting.cluster import SchedulerLost

    monkeypatch.setattr(engine, "POLL_SECONDS", 0.02)
    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus")
    clips = signer_clips("a", "b")
    cluster = ClusterExecutor(lambda batch: None, slots=4)
    threading.Timer(0.3, lambda: [cluster.settle(i) for i in ("a1", "b1")]).start()
    assert sorted(o.clip_id for o in engine._outcomes(job, clips, cluster, None)) == ["a1", "b1"]
    assert cluster.checks >= 2

    pool = BareExecutor(lambda batch: None)  # no capacity: every batch at once; no check: only waiting
    sent = []
    threading.Timer(0.3, lambda: [sent.append(len(pool.sent)), *[pool.settle(i) for i in ("a1", "b1")]]).start()
    assert sorted(o.clip_id for o in engine._outcomes(job, clips, pool, None)) == ["a1", "b1"] and sent == [2]

    gone = ClusterExecutor(lambda batch: None, slots=4, lost=SchedulerLost("lost the Dask scheduler at tcp://s:8786"))
    with pytest.raises(SchedulerLost, match="tcp://s:8786"):
        list(engine._outcomes(job, clips, gone, None))
    assert all(f.cancelled() for f in gone.futures.values())  # nothing left running for nobody


def test_a_batch_whose_worker_died_is_quarantined_and_the_run_goes_on(tmp_path):
    from types import SimpleNamespace

    from distributed.scheduler import KilledWorker

    from m3t.fitting.corpus import _outcomes

    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus", fit_corpus={"batch_clips": 2})
    clips = signer_clips("a", "b", "a")
    killed = KilledWorker("fit-clips-7", SimpleNamespace(address="tcp://10.0.0.7:4000"), 3)
    executor = ClusterExecutor(lambda batch: killed if batch[0].signer == "a" else fitted(batch), slots=1)
    outcomes = {o.clip_id: o for o in _outcomes(job, clips, executor, None)}
    assert [args[1] for _, args in executor.sent] == [[clips[0], clips[2]], [clips[1]]]  # one batch per signer
    assert outcomes["b1"].status == "fitted"
    for clip in (clips[0], clips[2]):
        assert outcomes[clip.id] == ClipOutcome(
            clip.id, "dev", "quarantined", group="worker died", file=clip.media,
            reason=f"worker died while fitting this clip: KilledWorker: {killed} (the next run retries it)")


def test_a_failing_task_stops_the_run_and_cancels_the_others(tmp_path):
    from concurrent.futures.process import BrokenProcessPool

    from m3t.fitting.cluster import SchedulerLost
    from m3t.fitting.corpus import _outcomes

    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus")
    clips = signer_clips("a", "b")

    def failing(error):
        return ClusterExecutor(lambda batch: error if batch[0].id == "a1" else None, slots=2)

    bug = failing(ValueError("an engine bug"))
    with pytest.raises(ValueError, match="^an engine bug$"):
        list(_outcomes(job, clips, bug, None))
    assert bug.futures[("b1",)].cancelled()

    pool = failing(BrokenProcessPool("A child process terminated abruptly"))
    with pytest.raises(RuntimeError) as info:
        list(_outcomes(job, clips, pool, None))
    assert str(info.value) == ("a fit-corpus worker process died (out of memory or killed); finished clips are "
                               "cached, rerun to resume")
    assert isinstance(info.value.__cause__, BrokenProcessPool) and pool.futures[("b1",)].cancelled()

    class Cancelling(ClusterExecutor):
        def submit(self, fn, *args):
            future = super().submit(fn, *args)
            if args[1][0].id == "a1":
                future.cancel()  # what Dask does to every task when the scheduler connection drops
                future.set_running_or_notify_cancel()  # as an executor does: waiters see it end
            return future

    cancelled = Cancelling(lambda batch: None, slots=2)
    with pytest.raises(RuntimeError) as info:
        list(_outcomes(job, clips, cancelled, None))
    assert str(info.value) == "clip a1: the executor cancelled its task; finished clips are cached, rerun to resume"
    assert cancelled.checks == 1 and cancelled.futures[("b1",)].cancelled()
    lost = Cancelling(lambda batch: None, slots=2, lost=SchedulerLost("lost the Dask scheduler at tcp://s:8786"))
    with pytest.raises(SchedulerLost):  # the scheduler's loss is the reason given, when that is what happened
        list(_outcomes(job, clips, lost, None))


def test_a_run_given_an_executor_and_no_context_sends_it_every_batch_and_counts_each_clip_once(
        body, tmp_path, monkeypatch):
    """The run only opens an executor of its own when it is given none (and no in-process context); the
    progress bar ends at the number of clips."""
    import tqdm.auto

    import m3t.fitting.cluster as cluster
    import m3t.fitting.corpus as engine
    from m3t.fitting.corpus import fit_batch, run_fit_corpus

    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus", fit_corpus={"batch_clips": 2})
    clips = signer_clips("a", "b", "a", "c")
    monkeypatch.setattr(engine, "worker_context", lambda j: FitContext(j, body))

    def no_own_executor(run):
        raise AssertionError("the run opened an executor of its own")

    monkeypatch.setattr(cluster, "open_executor", no_own_executor)
    bars = []

    class Bar(tqdm.auto.tqdm):
        def close(self):
            bars.append(self.n)
            super().close()

    monkeypatch.setattr(tqdm.auto, "tqdm", Bar)
    executor = BareExecutor(fitted)
    report = run_fit_corpus(job, executor, clips=clips, progress=True)
    assert sorted(tuple(c.id for c in args[1]) for _, args in executor.sent) == [("a1", "a2"), ("b1",), ("c1",)]
    assert all(fn is fit_batch and args[0] is job for fn, args in executor.sent)
    assert sorted(o.clip_id for o in report.outcomes) == ["a1", "a2", "b1", "c1"]
    assert bars and set(bars) == {4}  # closed (once or twice: tqdm closes again when collected) at 4 of 4
