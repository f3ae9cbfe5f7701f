"""fit-corpus on a Dask cluster (``fit_corpus.executor: dask``, :mod:`m3t.fitting.cluster`): the same shards as
the in-process runner, byte for byte; a running cluster reached by its address; resume from the cache; a worker
that dies quarantines only its clip; a lost scheduler stops the run naming its address.

The corpus is the embedded synthetic one (``m3t.corpora.synthetic``, the tiny preset, as in
``tests/pipeline/test_pipeline.py``): no published layout is involved, the clips and their ground truth are generated.
One module cluster (2 single-threaded worker processes, ``allowed-failures`` 0 so a dying worker fails its clip
at once) serves the "existing cluster" tests; one test starts and closes a LocalCluster of its own.
"""
from __future__ import annotations

import dataclasses
import json
import os
import threading
import time
from pathlib import Path

import pytest
import torch

from m3t.config import load_params
from m3t.corpora.synthetic import generate_corpus
from m3t.corpora.synthetic_storage import SyntheticCorpus, write_corpus
from m3t.fitting.cluster import DaskExecutor, SchedulerLost, on_worker, open_executor
from m3t.fitting.context import FitContext
from m3t.fitting.corpus import run_fit_corpus

ROOT = Path(__file__).resolve().parents[2]
CLIPS = 3


@pytest.fixture(scope="module")
def corpus_root(tmp_path_factory, body) -> Path:
    root = tmp_path_factory.mktemp("dask-corpus") / "corpus"
    write_corpus(generate_corpus(load_params(ROOT / "params.yaml", preset="tiny").synthetic_corpus, body), root)
    return root


def params_for(out: Path, corpus_root: Path | str, **fit_corpus):
    """The tiny preset on the first ``CLIPS`` clips, shards and cache under ``out``."""
    return load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "body": {"cache_dir": str(ROOT / ".cache" / "anny")},  # the built model, wherever a test runs from
        "data": {"shards_root": str(out / "shards")},
        "corpora": {"synthetic": {"root": str(corpus_root)}},
        "fit_corpus": {"cache_dir": str(out / "cache"), "max_clips": CLIPS, **fit_corpus}})


def job_for(out: Path, corpus_root: Path | str, **fit_corpus):
    return params_for(out, corpus_root, **fit_corpus).fit_job("synthetic")


def tasks_done(cluster) -> int:
    """Fit tasks (a batch of clips each) the cluster has completed so far."""
    prefix = cluster.scheduler.task_prefixes.get("fit-clips")
    return prefix.state_counts["memory"] if prefix is not None else 0


def shards_dir(job) -> Path:
    return Path(job.shards_dir)


@pytest.fixture()
def one_torch_thread():
    """Dask workers fit with one torch thread; the in-process reference must too (for the same bits).
    Restored after: other tests depend on the suite's thread count."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def cluster():
    """A running cluster, as `dask scheduler` + `dask worker ADDRESS --nthreads 1` would give."""
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        started = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0")
    yield started
    started.close()


def test_local_cluster_fit_equals_the_in_process_fit_byte_for_byte(tmp_path, corpus_root, body, one_torch_thread):
    local = job_for(tmp_path / "local", corpus_root)
    reference = run_fit_corpus(local, ctx=FitContext(local, body), progress=False)
    dask = job_for(tmp_path / "dask", corpus_root, executor="dask", workers=2)
    with open_executor(dask.run) as executor:
        assert isinstance(executor, DaskExecutor) and executor.capacity() == 2  # its own 2 x 1-thread workers
        cluster = executor._cluster
        report = run_fit_corpus(dask, executor, progress=False)
    assert cluster.status.name == "closed"  # started for the run, closed after it

    assert {o.status for o in report.outcomes} == {"fitted"} and len(report.outcomes) == CLIPS
    parquet = sorted(p.name for p in shards_dir(local).glob("*.parquet"))
    assert parquet == ["dev.parquet", "test.parquet", "train.parquet"]
    for name in parquet + ["quality.csv", "quality.json", "summary.json", "quarantine.jsonl"]:
        assert (shards_dir(dask) / name).read_bytes() == (shards_dir(local) / name).read_bytes(), name
    # per clip, everything but where the part lies and how long it took
    strip = lambda o: dataclasses.replace(o, part=None, seconds=0.0)  # noqa: E731
    assert sorted(map(strip, report.outcomes), key=lambda o: o.clip_id) == \
        sorted(map(strip, reference.outcomes), key=lambda o: o.clip_id)


def test_existing_cluster_by_address_with_relative_paths_then_resume(tmp_path, corpus_root, cluster, monkeypatch):
    """The workers were started elsewhere (in the repository root): relative paths of the job mean this
    process' working directory on them; a second run, opened from params alone, fits nothing and rewrites no
    part."""
    monkeypatch.chdir(tmp_path)
    job = job_for(Path("out"), os.path.relpath(corpus_root, tmp_path), executor="dask",
                  dask_address=cluster.scheduler_address)
    assert not Path(job.run.cache_dir).is_absolute() and not Path(job.source.root).is_absolute()
    before = tasks_done(cluster)
    with open_executor(job.run) as executor:
        assert executor.address == cluster.scheduler_address
        first = run_fit_corpus(job, executor, progress=False)
    assert {o.status for o in first.outcomes} == {"fitted"} and tasks_done(cluster) > before
    parts = sorted((tmp_path / "out" / "cache" / "parts").glob("*.parquet"))
    assert len(parts) == CLIPS and not (ROOT / "out").exists()
    stamps = {p: p.stat().st_mtime_ns for p in parts}

    # the way the stage and the flow run it: no executor given, the engine opens the one params.yaml names
    # (the cluster outlived the first run's client)
    before = tasks_done(cluster)
    again = run_fit_corpus(job, progress=False)
    assert {o.status for o in again.outcomes} == {"cached"} and again.run_stats["clips_fitted_now"] == 0
    assert tasks_done(cluster) > before
    assert {p: p.stat().st_mtime_ns for p in parts} == stamps
    assert sorted((tmp_path / "out" / "cache" / "parts").glob("*.parquet")) == parts


class DiesOn(DaskExecutor):
    """The cluster's executor, except that the worker given the batch holding ``clip_id`` exits on the spot
    (as when the kernel's out-of-memory killer ends it)."""

    def __init__(self, inner: DaskExecutor, clip_id: str):
        self.__dict__.update(inner.__dict__)
        self.clip_id = clip_id

    def submit(self, fn, /, *args, **kwargs):
        if any(clip.id == self.clip_id for clip in args[1]):
            fn = lambda job, clips: os._exit(3)  # noqa: E731 - pickled by value: no import of this module there
        return super().submit(fn, *args, **kwargs)


def test_a_worker_that_dies_quarantines_its_clip_and_the_run_goes_on(tmp_path, corpus_root, cluster):
    # one clip per task, so that "only the dying worker's clip" is visible
    job = job_for(tmp_path, corpus_root, executor="dask", dask_address=cluster.scheduler_address, batch_clips=1)
    clips = SyntheticCorpus(corpus_root).clips()[:CLIPS]
    victim = clips[1].id
    with open_executor(job.run) as executor:
        report = run_fit_corpus(job, DiesOn(executor, victim), clips=clips, progress=False)
    status = {o.clip_id: o for o in report.outcomes}
    assert status[victim].status == "quarantined"
    assert status[victim].reason.startswith("worker died while fitting this clip: KilledWorker")
    # one clip in flight per worker: the clip the other worker held, and the clips after, are fitted
    assert {status[c.id].status for c in clips if c.id != victim} == {"fitted"}
    lines = [json.loads(line) for line in (shards_dir(job) / "quarantine.jsonl").read_text().splitlines()]
    assert [(q["clip_id"], q["group"]) for q in lines] == [(victim, "worker died")]
    assert json.loads((shards_dir(job) / "summary.json").read_text())["clips_fitted"] == CLIPS - 1

    with open_executor(job.run) as executor:  # the next run fits the lost clip, the others come from the cache
        rerun = run_fit_corpus(job, executor, clips=clips, progress=False)
    assert {o.clip_id: o.status for o in rerun.outcomes} == {c.id: "fitted" if c.id == victim else "cached"
                                                            for c in clips}


def test_lost_scheduler_stops_the_run_naming_its_address(tmp_path, corpus_root):
    """A scheduler without workers holds the clips; it goes away: the run stops at once, saying where."""
    from distributed import Client, LocalCluster

    bare = LocalCluster(n_workers=0, processes=False, dashboard_address=":0")
    address = bare.scheduler_address
    executor = DaskExecutor(Client(address, set_as_default=False))
    job = job_for(tmp_path, corpus_root, executor="dask", dask_address=address)
    threading.Timer(1.0, bare.close).start()
    start = time.perf_counter()
    try:
        with pytest.raises(SchedulerLost, match=f"{address}.*finished clips are cached, rerun to resume"):
            run_fit_corpus(job, executor, progress=False)
    finally:
        executor.shutdown(cancel_futures=True)
        bare.close()
    assert time.perf_counter() - start < 20


def test_unreachable_address_and_contradictory_settings_are_refused(monkeypatch):
    from m3t.fitting import cluster as cluster_module
    from m3t.fitting.config import FitCorpusConfig

    monkeypatch.setattr(cluster_module, "CONNECT_SECONDS", 1.0)
    with pytest.raises(ConnectionError, match=r"fit_corpus.dask_address: no Dask scheduler answered at "
                                              r"'tcp://127.0.0.1:9'"):
        with open_executor(FitCorpusConfig(executor="dask", dask_address="tcp://127.0.0.1:9")):
            pass
    with pytest.raises(ValueError, match="fit_corpus.executor is 'local'"):
        with open_executor(FitCorpusConfig(dask_address="tcp://127.0.0.1:9")):
            pass


def test_tasks_run_with_one_torch_thread():
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert on_worker(torch.get_num_threads) == 1
    finally:
        torch.set_num_threads(before)
