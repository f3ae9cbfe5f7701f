"""Fault injection: ``kill -9`` long jobs at random points, rerun them, and check that nothing was lost or redone.

Each job runs as its DVC stage (``python -m m3t.stages.<stage> --params P``) in a workspace of its own (the tiny
preset, every path under one folder, the body model's build cache of the repository reused). The uninterrupted
reference run goes first; then each of ``--kills`` trials clears the job's cache and outputs, starts it in a new
session, kills the whole process group (``SIGKILL``) after a seeded random time within the reference run's
duration, reruns it to completion and checks:

- every output file is byte-identical to the reference (Parquet shards also compared as decoded tables; for
  checkpoints, ``state_dict`` tensor by tensor on the CPU);
- no temporary, partial or lock file is left anywhere in the job's folders, and no process of the killed group;
- fit-corpus: no clip finished before the kill is fitted again (its part file is untouched) and exactly the
  others are fitted on the rerun;
- evaluate-smlm (on a generation of the whole tiny corpus's test split, models of its own): the rerun resumes
  from the journal of scored clips and judged sentences (``state_at_kill``), and writes the reference's metrics
  byte for byte; the journal is gone afterwards.

Time lost per resume = rerun time - (reference time - time before the kill): the work redone plus the restart.
Then one trial each of: a corrupt cached part file (refitted, not read), two runs of one stage at once (the
second refused, naming the first's pid), a disk full during a shard write (simulated ``ENOSPC``: the previous
shard intact, no temporary file, an error naming the file).

    python benchmarks/bench_faults.py [--kills 5] [--clips 6] [--seed 0] [--out benchmarks/results/faults.json]
        [--jobs fit-corpus,fit-corpus-dask,tokenizers,smlm,backtranslation,slr,sgsa,evaluate-smlm]

Writes the JSON and a Markdown table beside it (``faults.md``). Jobs run one after the other; the fit-corpus
reference feeds the trainers (its shards), and the tokenizer reference feeds the SMLM (through ``tokenize``) and
the recognition probe.
"""
from __future__ import annotations

import argparse
import errno
import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
JOBS = ("fit-corpus", "fit-corpus-dask", "tokenizers", "smlm", "backtranslation", "slr", "sgsa", "evaluate-smlm")
TRAINERS = ("tokenizers", "smlm", "backtranslation", "slr", "sgsa")  # they read the fitted shards
# these need the whole tiny corpus (sentences for the judge and SGSA, isolated signs in every split for the probe),
# fitted into shards of their own; the others train on the first --clips clips
WHOLE_CORPUS = ("backtranslation", "slr", "sgsa")
# evaluate-smlm scores a generation of the whole tiny corpus's test split with models of its own (folders "eval")
EVALUATION_SETUP = ("train_tokenizers", "tokenize", "train_smlm", "train_backtranslation", "generate_smlm")


@dataclass(frozen=True)
class Job:
    """A stage, the params file it runs with, the folders it writes (``state``: cleared before each trial) and
    those of them compared with the reference (``outputs``)."""

    name: str
    stage: str
    params: Path
    state: tuple[Path, ...]
    outputs: tuple[Path, ...]


def workspace(root: Path, clips: int, iterations: int) -> dict[str, Job]:
    """Params files (local and Dask fitting) of a tiny workspace under ``root`` and the jobs that use them."""
    import yaml

    from m3t.config import load_params
    from m3t.experiment import to_dict

    overrides = {
        "body": {"cache_dir": str(ROOT / ".cache" / "anny")},
        "corpora": {"synthetic": {"root": str(root / "corpus")}},
        "data": {"shards_root": str(root / "shards"), "tokens_root": str(root / "tokens"),
                 "models_dir": str(root / "models"), "generated_dir": str(root / "gen"),
                 "metrics_dir": str(root / "metrics")},
        "fitting": {"iterations": iterations, "camera_iterations": max(iterations // 2, 1)},
        "fit_corpus": {"cache_dir": str(root / "fit-cache"), "max_clips": clips, "render_clips": 0},
        "tokenizer_train": {"cache_dir": str(root / "tok-cache"), "epochs": 4},
        "smlm_train": {"cache_dir": str(root / "smlm-cache"), "epochs": 4},
        # more epochs than the others: their models are smaller, and a kill should mostly land in training
        "backtranslation_train": {"cache_dir": str(root / "bt-cache"), "epochs": 12},
        "slr_train": {"cache_dir": str(root / "slr-cache"), "epochs": 12},
        "sgsa_train": {"cache_dir": str(root / "sgsa-cache"), "epochs": 12}}
    files = {}
    # "slow": fits long enough that a second run starts while the first still holds its lock
    whole = {"data": {**overrides["data"], "shards_root": str(root / "shards-all"),
                      "tokens_root": str(root / "tokens-all")},
             "fit_corpus": {"max_clips": 0, "cache_dir": str(root / "fit-cache-all")}}  # its own: the part trials
                                                                                     # pick from the 6-clip cache
    evaluation = {"data": {**whole["data"], "models_dir": str(root / "models-eval"), "generated_dir": str(root / "gen-eval"),
                           "metrics_dir": str(root / "metrics-eval")},
                  "fit_corpus": whole["fit_corpus"], "smlm_generate": {"render_clips": 0, "export_pose": False}}
    for name, extra in (("local", {}), ("dask", {"fit_corpus": {"executor": "dask", "workers": 2}}),
                        ("slow", {"fitting": {"iterations": 150, "camera_iterations": 30}}), ("all", whole),
                        ("eval", evaluation)):
        over = {**overrides, **{k: {**overrides.get(k, {}), **v} for k, v in extra.items()}}
        params = load_params(ROOT / "params.yaml", preset="tiny", overrides=over)
        files[name] = root / f"params-{name}.yaml"
        files[name].write_text(yaml.safe_dump(to_dict(params), sort_keys=False))
    shards, fit_cache, shards_all = root / "shards" / "synthetic", root / "fit-cache", root / "shards-all" / "synthetic"
    models = root / "models"
    return {
        "fit-corpus": Job("fit-corpus", "fit_corpus", files["local"], (fit_cache, shards), (shards,)),
        "fit-corpus-dask": Job("fit-corpus-dask", "fit_corpus", files["dask"], (fit_cache, shards), (shards,)),
        "tokenizers": Job("tokenizers", "train_tokenizers", files["local"], (root / "tok-cache", models / "tokenizers"),
                          (models / "tokenizers",)),
        "smlm": Job("smlm", "train_smlm", files["local"], (root / "smlm-cache", models / "smlm"), (models / "smlm",)),
        "fit-all": Job("fit-all", "fit_corpus", files["all"], (root / "fit-cache-all", shards_all), (shards_all,)),
        "backtranslation": Job("backtranslation", "train_backtranslation", files["all"],
                               (root / "bt-cache", models / "backtranslation"), (models / "backtranslation",)),
        "slr": Job("slr", "train_slr", files["all"], (root / "slr-cache", models / "slr"), (models / "slr",)),
        "sgsa": Job("sgsa", "train_sgsa", files["all"], (root / "sgsa-cache", models / "sgsa"), (models / "sgsa",)),
        "evaluate-smlm": Job("evaluate-smlm", "evaluate_smlm", files["eval"], (root / "metrics-eval" / "smlm",),
                             (root / "metrics-eval" / "smlm",)),
    }


# ---- running and killing ----------------------------------------------------------------------------------
def start(stage: str, params: Path, log: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with open(log, "ab") as fh:  # the child keeps its own copy of the descriptor
        return subprocess.Popen([sys.executable, "-m", f"m3t.stages.{stage}", "--params", str(params)],
                                cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True)


def run_to_end(stage: str, params: Path, log: Path) -> float:
    """Run a stage to completion; its wall time (raises with the log's tail when it fails)."""
    began = time.perf_counter()
    proc = start(stage, params, log)
    if proc.wait() != 0:
        raise RuntimeError(f"{stage} failed (exit {proc.returncode}); end of {log}:\n{log.read_text()[-3000:]}")
    return time.perf_counter() - began


def group_alive(pgid: int) -> list[int]:
    """Processes still in process group ``pgid`` (Linux /proc)."""
    alive = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[2]) == pgid and fields[0] != "Z":
                alive.append(int(entry.name))
    return alive


def kill_after(stage: str, params: Path, log: Path, seconds: float) -> tuple[float, bool, list[int]]:
    """Start, ``SIGKILL`` the process group after ``seconds``; (time it ran, whether it had already finished,
    processes of its group still alive a moment after the kill)."""
    began = time.perf_counter()
    proc = start(stage, params, log)
    try:
        proc.wait(timeout=seconds)
        return time.perf_counter() - began, True, []
    except subprocess.TimeoutExpired:
        pass
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    ran = time.perf_counter() - began
    deadline = time.time() + 5.0
    while (alive := group_alive(proc.pid)) and time.time() < deadline:
        time.sleep(0.2)
    for pid in alive:  # never leave them running; reported as a failure
        os.kill(pid, signal.SIGKILL)
    return ran, False, alive


# ---- comparing ----------------------------------------------------------------------------------------------
def files_under(folders: tuple[Path, ...]) -> dict[str, Path]:
    return {str(p.relative_to(f.parent)): p for f in folders if f.exists() for p in sorted(f.rglob("*")) if p.is_file()}


def is_leftover(path: Path) -> bool:
    """A temporary, partial or lock file: a hidden name (``atomic_path`` makes ``.name.*``), ``*.tmp``, ``*.lock``."""
    return path.name.startswith(".") or path.suffix in (".tmp", ".lock")


def leftovers(folders: tuple[Path, ...]) -> list[str]:
    return [k for k, p in files_under(folders).items() if is_leftover(p)]


def same_file(a: Path, b: Path) -> tuple[bool, str]:
    """Whether ``b`` equals the reference ``a``: bytes, or for a checkpoint its tensors; and how it differs."""
    if a.read_bytes() == b.read_bytes():
        if a.suffix == ".parquet":
            import pyarrow.parquet as pq

            return (True, "") if pq.read_table(a).equals(pq.read_table(b)) else (False, "tables differ")
        return True, ""
    if a.suffix == ".pt":
        import torch

        sa, sb = (torch.load(p, map_location="cpu", weights_only=True)["state_dict"] for p in (a, b))
        if sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa):
            return True, "bytes differ, tensors equal"
        return False, "state_dict differs"
    return False, "bytes differ"


def compare(reference: dict[str, Path], folders: tuple[Path, ...]) -> list[str]:
    """Differences between the reference files and those now in ``folders`` (empty: identical)."""
    now = files_under(folders)
    problems = [f"missing {k}" for k in reference if k not in now]
    problems += [f"extra {k}" for k in now if k not in reference]
    for key in sorted(set(reference) & set(now)):
        ok, how = same_file(reference[key], now[key])
        if not ok:
            problems.append(f"{key}: {how}")
    return problems


def parts(cache: Path) -> dict[str, tuple[int, int]]:
    """Finished part files (those with their digest written) -> (inode, mtime): a rewritten part changes both."""
    found = {}
    for digest in (cache / "parts").glob("*.sha256"):
        part = digest.with_suffix(".parquet")
        if part.exists():
            st = part.stat()
            found[part.name] = (st.st_ino, st.st_mtime_ns)
    return found


def clear(job: Job) -> None:
    for folder in job.state:
        shutil.rmtree(folder, ignore_errors=True)


def snapshot(job: Job, into: Path) -> dict[str, Path]:
    """Copy the reference outputs aside (trials clear the folders)."""
    shutil.rmtree(into, ignore_errors=True)
    for folder in job.outputs:
        shutil.copytree(folder, into / folder.name)
    return files_under(tuple(into / f.name for f in job.outputs))


# ---- trials -------------------------------------------------------------------------------------------------
def kill_trials(job: Job, kills: int, rng: random.Random, logs: Path, scratch: Path) -> dict:
    """The reference run, then ``kills`` kill-and-resume trials; a dict of counts, failures and times."""
    clear(job)
    ref_seconds = run_to_end(job.stage, job.params, logs / f"{job.name}-reference.log")
    reference = snapshot(job, scratch / f"{job.name}-reference")
    total_parts = len(parts(job.state[0])) if job.stage == "fit_corpus" else 0
    trials = []
    for i in range(kills):
        clear(job)
        at = rng.uniform(0.05, 0.95) * ref_seconds
        log = logs / f"{job.name}-trial{i}.log"
        ran, finished, alive = kill_after(job.stage, job.params, log, at)
        before = parts(job.state[0]) if job.stage == "fit_corpus" else {}
        # what the rerun can resume from: finished parts, or the trainer's resumable checkpoint
        saved = [k for k, p in files_under((job.state[0],)).items() if not is_leftover(p) or p.suffix == ".journal"]
        rerun = run_to_end(job.stage, job.params, log)
        problems = compare(reference, job.outputs)
        problems += [f"left behind: {k}" for k in leftovers(job.state)]
        problems += [f"process {pid} of the killed group still alive" for pid in alive]
        trial = {"kill_at_s": round(ran, 2), "finished_before_kill": finished, "state_at_kill": bool(saved),
                 "rerun_s": round(rerun, 2),
                 "time_lost_s": round(rerun - (ref_seconds - ran), 2)}
        if job.stage == "fit_corpus":
            after = parts(job.state[0])
            refitted = [k for k, v in before.items() if after.get(k) != v]
            fitted_now = [k for k, v in after.items() if before.get(k) != v]
            problems += [f"finished clip refitted: {k}" for k in refitted]
            if len(fitted_now) != total_parts - len(before):
                problems.append(f"fitted {len(fitted_now)} clips on the rerun, expected {total_parts - len(before)}")
            trial.update(clips_done_before_kill=len(before), clips_fitted_on_rerun=len(fitted_now))
        trial["problems"] = problems
        trials.append(trial)
        print(f"{job.name} trial {i}: killed at {ran:.1f}s, rerun {rerun:.1f}s, problems: {problems or 'none'}",
              flush=True)
    lost = [t["time_lost_s"] for t in trials if not t["finished_before_kill"]]
    return {"reference_s": round(ref_seconds, 2), "trials": len(trials),
            "failures": sum(bool(t["problems"]) for t in trials),
            "killed_mid_run": len(lost),
            "resumed_from_state": sum(t["state_at_kill"] and not t["finished_before_kill"] for t in trials),
            "time_lost_mean_s": round(sum(lost) / len(lost), 2) if lost else None,
            "time_lost_max_s": max(lost) if lost else None, "parts_total": total_parts or None, "runs": trials}


def corrupt_part_trial(job: Job, reference: dict[str, Path], logs: Path) -> dict:
    """Flip bytes in one cached part file of a finished run: the rerun must refit that clip only (never read it)
    and give the reference shards."""
    cache = job.state[0]
    before = parts(cache)
    victim = cache / "parts" / sorted(before)[0]
    data = bytearray(victim.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 8] = bytes(b ^ 0xFF for b in data[middle:middle + 8])
    victim.write_bytes(bytes(data))
    before = parts(cache)
    run_to_end(job.stage, job.params, logs / "corrupt-part.log")
    after = parts(cache)
    rewritten = sorted(k for k, v in after.items() if before.get(k) != v)
    problems = compare(reference, job.outputs) + [f"left behind: {k}" for k in leftovers(job.state)]
    if rewritten != [victim.name]:
        problems.append(f"rewritten parts {rewritten}, expected only {victim.name}")
    return {"trials": 1, "failures": int(bool(problems)), "refitted": rewritten, "problems": problems}


def corrupt_track_trial(job: Job, reference: dict[str, Path], logs: Path) -> dict:
    """Flip bytes in one cached track file of a finished run: the rerun must track that clip again (never read
    the damaged track), which gives the same track bytes and so reuses every fitted part."""
    tracks = job.state[0] / "tracks"
    victim = sorted(tracks.glob("*.npz"))[0]
    intact = victim.read_bytes()
    data = bytearray(intact)
    middle = len(data) // 2
    data[middle:middle + 8] = bytes(b ^ 0xFF for b in data[middle:middle + 8])
    victim.write_bytes(bytes(data))
    before = parts(job.state[0])
    run_to_end(job.stage, job.params, logs / "corrupt-track.log")
    after = parts(job.state[0])
    problems = compare(reference, job.outputs) + [f"left behind: {k}" for k in leftovers(job.state)]
    if victim.read_bytes() != intact:
        problems.append(f"{victim.name} was not tracked again (its damaged bytes are still there)")
    refitted = sorted(k for k, v in after.items() if before.get(k) != v)
    if refitted:
        problems.append(f"parts refitted although the track came back identical: {refitted}")
    return {"trials": 1, "failures": int(bool(problems)), "retracked": victim.name, "problems": problems}


def concurrent_trial(job: Job, logs: Path, lock: Path) -> dict:
    """A second run of ``job`` while the first holds its lock: refused with the first one's pid, the first
    finishes."""
    log_a, log_b = logs / f"concurrent-{job.name}-first.log", logs / f"concurrent-{job.name}-second.log"
    clear(job)
    first = start(job.stage, job.params, log_a)
    deadline = time.time() + 300
    while not lock.exists() and first.poll() is None and time.time() < deadline:
        time.sleep(0.1)
    second = start(job.stage, job.params, log_b)
    second_rc = second.wait()
    first_rc = first.wait()
    said = log_b.read_text()
    problems = []
    if second_rc == 0:
        problems.append("the second run was not refused")
    elif "already running" not in said or f"pid {first.pid}" not in said:
        problems.append(f"the refusal does not name the running pid {first.pid}: {said.strip().splitlines()[-1:]}")
    if first_rc != 0:
        problems.append(f"the first run failed (exit {first_rc})")
    problems += [f"left behind: {k}" for k in leftovers(job.state)]
    refusal = [line for line in said.splitlines() if "already running" in line]
    return {"trials": 1, "failures": int(bool(problems)), "refusal": refusal[-1] if refusal else None,
            "problems": problems}


def disk_full_trial(scratch: Path) -> dict:
    """``ENOSPC`` in the middle of a shard write, in this process, through the shard writer every stage uses
    (:func:`m3t.shards.io.write_table_atomic`): the Parquet writer has put part of the new shard on disk when the
    device fills up. The previous shard must be intact, no temporary file left, and the error must name the file."""
    from unittest import mock

    import pyarrow as pa
    import pyarrow.parquet as pq

    from m3t.shards.io import write_table_atomic

    folder = scratch / "disk-full"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    shard = folder / "train.parquet"
    write_table_atomic(shard, pa.table({"x": list(range(100))}))
    old = hashlib.sha256(shard.read_bytes()).hexdigest()
    real_write = pq.ParquetWriter.write_table

    def fill_the_disk(writer, table, *args, **kwargs):
        real_write(writer, table.slice(0, len(table) // 2), *args, **kwargs)  # half the rows reach the file
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    message = ""
    try:
        with mock.patch.object(pq.ParquetWriter, "write_table", fill_the_disk):
            write_table_atomic(shard, pa.table({"x": list(range(1000))}))
    except OSError as exc:
        message = str(exc)
    problems = []
    if not message:
        problems.append("the write did not fail")
    if hashlib.sha256(shard.read_bytes()).hexdigest() != old:
        problems.append("the previous shard changed")
    if [p.name for p in folder.iterdir()] != ["train.parquet"]:
        problems.append(f"left behind: {sorted(p.name for p in folder.iterdir())}")
    if str(shard) not in message:
        problems.append(f"the error does not name the file: {message!r}")
    return {"trials": 1, "failures": int(bool(problems)), "error": message, "problems": problems}


# ---- the report ---------------------------------------------------------------------------------------------
def markdown(result: dict) -> str:
    rows = ["| job | trials | failures | killed mid-run | of which resumed from saved state | "
            "time lost per resume, mean / max (s) | reference (s) |", "|---|---|---|---|---|---|---|"]
    for name, r in result["jobs"].items():
        rows.append(f"| {name} | {r['trials']} | {r['failures']} | {r['killed_mid_run']} | "
                    f"{r.get('resumed_from_state', '-')} | {r['time_lost_mean_s']} / {r['time_lost_max_s']} | "
                    f"{r['reference_s']} |")
    for name, r in result["faults"].items():
        rows.append(f"| {name} | {r['trials']} | {r['failures']} | - | - | - | - |")
    head = (f"Fault injection (`python benchmarks/bench_faults.py --kills {result['kills']}`): {result['clips']} "
            f"clips, seed {result['seed']}; {result['trials']} trials, {result['failures']} failures.\n\n")
    return head + "\n".join(rows) + "\n"


def run(kills: int, jobs: list[str], clips: int, iterations: int, seed: int, root: Path) -> dict:
    unknown = [j for j in jobs if j not in JOBS]
    if unknown:
        raise SystemExit(f"--jobs: unknown {', '.join(unknown)}; allowed: {', '.join(JOBS)}")
    rng = random.Random(seed)
    logs, scratch = root / "logs", root / "scratch"
    logs.mkdir(parents=True, exist_ok=True)
    defined = workspace(root, clips, iterations)
    print(f"workspace {root}, logs in {logs}", flush=True)
    run_to_end("generate_corpus", defined["fit-corpus"].params, logs / "generate-corpus.log")
    result: dict = {"kills": kills, "clips": clips, "iterations": iterations, "seed": seed, "jobs": {}, "faults": {}}
    fit = defined["fit-corpus"]
    needs_fit = any(j in jobs for j in ("fit-corpus", *TRAINERS))
    for name in jobs:
        source = defined["fit-all"] if name in WHOLE_CORPUS else fit
        if name in TRAINERS and not (source.outputs[0] / "train.parquet").exists():
            clear(source)
            run_to_end(source.stage, source.params, logs / f"{source.name}-for-trainers.log")
        if name in ("smlm", "slr") and not list((root / "models" / "tokenizers").glob("*.pt")):
            clear(defined["tokenizers"])
            run_to_end("train_tokenizers", source.params, logs / "tokenizers-for-trainers.log")
        if name == "smlm":
            run_to_end("tokenize", fit.params, logs / "tokenize.log")
        if name == "evaluate-smlm":
            whole = defined["fit-all"]
            if not (whole.outputs[0] / "train.parquet").exists():
                clear(whole)
                run_to_end(whole.stage, whole.params, logs / "fit-all-for-evaluation.log")
            for stage in EVALUATION_SETUP:
                run_to_end(stage, defined[name].params, logs / f"{stage}-for-evaluation.log")
        result["jobs"][name] = kill_trials(defined[name], kills, rng, logs, scratch)
    if needs_fit:
        reference = files_under((scratch / "fit-corpus-reference" / "synthetic",)) if "fit-corpus" in jobs else None
        if reference:
            result["faults"]["corrupt part file"] = corrupt_part_trial(fit, reference, logs)
            result["faults"]["corrupt track file"] = corrupt_track_trial(fit, reference, logs)
        slow = Job("fit-corpus", fit.stage, root / "params-slow.yaml", fit.state, fit.outputs)
        result["faults"]["two fit-corpus runs at once"] = concurrent_trial(slow, logs, fit.outputs[0] / ".fit-corpus.lock")
    result["faults"]["disk full during a shard write"] = disk_full_trial(scratch)
    everything = list(result["jobs"].values()) + list(result["faults"].values())
    result["trials"] = sum(r["trials"] for r in everything)
    result["failures"] = sum(r["failures"] for r in everything)
    return result


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=5)
    parser.add_argument("--jobs", default=",".join(JOBS))
    parser.add_argument("--clips", type=int, default=6)
    parser.add_argument("--iterations", type=int, default=40, help="fitting.iterations of every fit")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workdir", default="", help="keep the workspace here (default: a temporary folder)")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "faults.json"))
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="m3t-faults-") as tmp:
        root = Path(args.workdir) if args.workdir else Path(tmp)
        result = run(args.kills, [j for j in args.jobs.split(",") if j], args.clips, args.iterations, args.seed, root)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown(result))
    print(markdown(result))
    return result


if __name__ == "__main__":
    main()
