"""fit-corpus end to end on a tiny synthetic corpus: resume after a kill, quarantine, Prefect flow, DVC."""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from m3t.config import load_params, to_dict
from m3t.corpora.synthetic import SyntheticCorpus, generate_corpus, write_corpus
from m3t.shards.io import read_shard
from m3t.stages.fit_corpus import FitContext, for_corpus, run_fit_corpus

ROOT = Path(__file__).resolve().parents[1]
TINY_CORPUS: dict = {}  # the tiny preset already shrinks the corpus


def tiny_params(tmp_path: Path, **fit_corpus):
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "corpus": TINY_CORPUS,
        "corpora": {"synthetic": {"root": str(tmp_path / "corpus"), "shards_dir": str(tmp_path / "shards")}}})
    cfg = dataclasses.replace(for_corpus(params, "synthetic"), cache_dir=str(tmp_path / "cache"), **fit_corpus)
    return dataclasses.replace(params, fit_corpus=cfg)


@pytest.fixture()
def corpus_params(tmp_path, body):
    params = tiny_params(tmp_path, max_clips=4)
    clips = generate_corpus(params.corpus, body)
    write_corpus(clips, params.fit_corpus.corpus_dir)
    return params


def context(params, body):
    ctx = FitContext(params.fit_corpus, params.body, params.tracker, params.fitting)
    ctx._body = body  # share the session's body model
    return ctx


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
        run_fit_corpus(ctx, progress=False, on_outcome=kill_after_two)
    finished = {o.clip_id for o in seen if o.status == "fitted"}
    assert len(finished) == 2
    assert no_temp_files(tmp_path)
    assert not (tmp_path / "shards").exists() or not list((tmp_path / "shards").glob("*.parquet"))

    report = run_fit_corpus(ctx, progress=False)
    status = {o.clip_id: o.status for o in report.outcomes}
    assert {c for c, s in status.items() if s == "cached"} == finished
    assert sum(s == "fitted" for s in status.values()) == len(status) - 2
    assert no_temp_files(tmp_path)
    total = sum(len(read_shard(p)) for p in report.shards.values())
    assert total == len(status) == 4
    # A third run with nothing changed fits nothing.
    again = run_fit_corpus(ctx, progress=False)
    assert all(o.status == "cached" for o in again.outcomes)


def test_bad_clips_are_quarantined_and_the_rest_completes(corpus_params, body, tmp_path):
    corpus = SyntheticCorpus(corpus_params.fit_corpus.corpus_dir)
    clips = corpus.clips()[:4]
    root = Path(corpus_params.fit_corpus.corpus_dir)
    (root / clips[0].media).unlink()  # missing media
    (root / clips[1].media).write_bytes(b"\x00garbage")  # corrupt media
    report = run_fit_corpus(context(corpus_params, body), clips=clips, progress=False)
    status = {o.clip_id: o for o in report.outcomes}
    assert status[clips[0].id].status == "quarantined" and clips[0].id in status[clips[0].id].reason
    assert status[clips[1].id].status == "quarantined"
    assert {status[c.id].status for c in clips[2:]} == {"fitted"}
    lines = (tmp_path / "shards" / "quarantine.jsonl").read_text().splitlines()
    assert {json.loads(line)["clip_id"] for line in lines} == {clips[0].id, clips[1].id}
    summary = json.loads((tmp_path / "shards" / "summary.json").read_text())
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
    assert list((tmp_path / "shards").glob("*.parquet"))


def test_dvc_repro_twice_is_a_noop(tmp_path):
    """The real dvc.yaml on a tiny params.yaml: the second `dvc repro` runs no stage."""
    repo = tmp_path / "repo"
    repo.mkdir()
    for name in ("dvc.yaml", "m3t"):
        src = ROOT / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, repo / name)
    anny_cache = str((ROOT / ".cache" / "anny").resolve())  # reuse the built model, not a second 1-min build
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "corpus": TINY_CORPUS, "fit_corpus": {"max_clips": 2}, "body": {"cache_dir": anny_cache}})
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
