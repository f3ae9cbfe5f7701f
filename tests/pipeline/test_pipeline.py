"""fit-corpus end to end on a tiny synthetic corpus: resume after a kill, quarantine, executors, unchanged
outputs on an unchanged rerun, Prefect flow, DVC."""
from __future__ import annotations

import json
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from builders import tiny_params

from m3t.config import load_params
from m3t.corpora.synthetic import generate_corpus
from m3t.corpora.synthetic_storage import SyntheticCorpus, write_corpus
from m3t.experiment import to_dict
from m3t.fitting.context import FitContext
from m3t.fitting.corpus import fit_batch, plan_batches, run_fit_corpus
from m3t.shards.io import read_shard

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture()
def corpus_params(tmp_path, body):
    params = tiny_params(tmp_path, max_clips=4)
    clips = generate_corpus(params.synthetic_corpus, body)
    write_corpus(clips, params.corpora["synthetic"].root)
    return params


def shards(tmp_path: Path) -> Path:
    return tmp_path / "shards" / "synthetic"


def context(params, body) -> FitContext:
    return FitContext(params.fit_job("synthetic"), body)  # shares the session's body model


def no_temp_files(root: Path) -> bool:
    return not [p for p in root.rglob("*") if p.name.endswith(".tmp")]


def test_killed_run_resumes_without_refitting(corpus_params, body, tmp_path):
    ctx = context(corpus_params, body)
    seen = []

    def kill_after_two(outcome):
        seen.append(outcome)
        if len(seen) == 2:
            raise KeyboardInterrupt  # what Ctrl-C / a killed worker looks like to the loop

    with pytest.raises(KeyboardInterrupt):
        run_fit_corpus(ctx.job, ctx=ctx, progress=False, on_outcome=kill_after_two)
    finished = {o.clip_id for o in seen if o.status == "fitted"}
    assert len(finished) == 2
    assert no_temp_files(tmp_path)
    assert not shards(tmp_path).exists() or not list(shards(tmp_path).glob("*.parquet"))

    report = run_fit_corpus(ctx.job, ctx=ctx, progress=False)
    status = {o.clip_id: o.status for o in report.outcomes}
    assert {c for c, s in status.items() if s == "cached"} == finished
    assert sum(s == "fitted" for s in status.values()) == len(status) - 2
    assert no_temp_files(tmp_path)
    total = sum(len(read_shard(p)) for p in report.shards.values())
    assert total == len(status) == 4
    # A third run with nothing changed fits nothing and rewrites no output (DVC sees nothing new).
    outputs = sorted(shards(tmp_path).iterdir())
    stamps = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in outputs}
    again = run_fit_corpus(ctx.job, ctx=ctx, progress=False)
    assert all(o.status == "cached" for o in again.outcomes)
    assert {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted(shards(tmp_path).iterdir())} == stamps
    assert again.run_stats["clips_cached"] == 4 and "wall_seconds" not in again.summary


def test_any_executor_runs_the_engine_with_picklable_jobs(corpus_params, body, tmp_path):
    """The engine takes any Executor-like runner and sends it only the job (configs) and a batch of clips."""
    from concurrent.futures import ThreadPoolExecutor

    job = corpus_params.fit_job("synthetic")
    clone = pickle.loads(pickle.dumps(job))
    assert clone == job and clone.key() == job.key()
    clips = SyntheticCorpus(corpus_params.corpora["synthetic"].root).clips()[:2]
    sent = []

    class Recording(ThreadPoolExecutor):
        def submit(self, fn, *args, **kwargs):
            sent.append((fn, args))
            return super().submit(fn, *args, **kwargs)

    with Recording(2) as pool:
        report = run_fit_corpus(job, pool, clips=clips, progress=False)
    assert [fn for fn, _ in sent] == [fit_batch] * len(plan_batches(clips, job.run.batch_clips))
    assert sorted(c.id for _, (_, batch) in sent for c in batch) == sorted(c.id for c in clips)
    assert all(pickle.loads(pickle.dumps(args)) == args for _, args in sent)
    assert sorted(o.clip_id for o in report.outcomes) == sorted(c.id for c in clips)
    assert {o.status for o in report.outcomes} == {"fitted"}
    assert {o.init["init_source"] for o in report.outcomes} == {"simulated tracker initialisation"}


def test_bad_clips_are_quarantined_and_the_rest_completes(corpus_params, body, tmp_path):
    root = Path(corpus_params.corpora["synthetic"].root)
    clips = SyntheticCorpus(root).clips()[:4]
    (root / clips[0].media).unlink()  # missing media
    (root / clips[1].media).write_bytes(b"\x00garbage")  # corrupt media
    ctx = context(corpus_params, body)
    report = run_fit_corpus(ctx.job, ctx=ctx, clips=clips, progress=False)
    status = {o.clip_id: o for o in report.outcomes}
    assert status[clips[0].id].status == "quarantined" and clips[0].id in status[clips[0].id].reason
    assert status[clips[1].id].status == "quarantined"
    assert {status[c.id].status for c in clips[2:]} == {"fitted"}
    lines = (shards(tmp_path) / "quarantine.jsonl").read_text().splitlines()
    assert {json.loads(line)["clip_id"] for line in lines} == {clips[0].id, clips[1].id}
    summary = json.loads((shards(tmp_path) / "summary.json").read_text())
    assert summary["clips_quarantined"] == 2 and summary["clips_fitted"] == 2
    assert summary["pa_joint_mm_mean"] < summary["init_pa_joint_mm_mean"]


def test_flow_runs_under_prefect_test_harness(corpus_params, tmp_path):
    from prefect.testing.utilities import prefect_test_harness

    from flows.fit_corpus import fit_corpus

    params_file = tmp_path / "params.yaml"
    params_file.write_text(yaml.safe_dump(to_dict(corpus_params)))
    with prefect_test_harness():
        summary = fit_corpus(params_path=str(params_file), preset="default", max_clips=2, log_mlflow=False)
    assert summary["clips_fitted"] == 2 and summary["clips_quarantined"] == 0
    assert list(shards(tmp_path).glob("*.parquet"))


def test_dvc_repro_twice_is_a_noop(tmp_path):
    """The real dvc.yaml on a tiny params.yaml: the second `dvc repro` runs no stage."""
    repo = tmp_path / "repo"
    repo.mkdir()
    for name in ("dvc.yaml", "m3t", "dashboards"):
        src = ROOT / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, repo / name)
    anny_cache = str((ROOT / ".cache" / "anny").resolve())  # reuse the built model, not a second 1-min build
    # every clip of the tiny corpus (16 isolated signs, 9 sentences): the recognition probe needs the one,
    # the back-translation judge the other
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={"body": {"cache_dir": anny_cache}})
    (repo / "params.yaml").write_text(yaml.safe_dump(to_dict(params)))
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
               PYTHONPATH=str(repo),
               DVC_NO_ANALYTICS="1", GIT_AUTHOR_NAME="t", GIT_AUTHOR_EMAIL="t@t", GIT_COMMITTER_NAME="t",
               GIT_COMMITTER_EMAIL="t@t")
    dvc = [sys.executable, "-m", "dvc"]
    run = lambda *cmd: subprocess.run(cmd, cwd=repo, env=env, capture_output=True, text=True, timeout=600)  # noqa: E731
    assert run("git", "init", "-q").returncode == 0
    assert run(*dvc, "init", "-q").returncode == 0
    first = run(*dvc, "repro")
    assert first.returncode == 0, first.stdout + first.stderr
    assert (repo / "data" / "shards" / "synthetic" / "summary.json").exists()
    second = run(*dvc, "repro")
    assert second.returncode == 0, second.stdout + second.stderr
    assert "Running stage" not in second.stdout
    assert "didn't change" in second.stdout or "up to date" in second.stdout
    # fit-corpus run again outside DVC (as a Prefect deployment would) on the unchanged corpus: every clip
    # is cached, no tracked output changes, so DVC still sees the pipeline as up to date.
    again = subprocess.run([sys.executable, "-m", "m3t.stages.fit_corpus"], cwd=repo, env=env, capture_output=True,
                           text=True, timeout=600)
    assert again.returncode == 0, again.stdout + again.stderr
    status = run(*dvc, "status")
    assert status.returncode == 0 and "up to date" in status.stdout, status.stdout
