"""fit-corpus on Dask: 1 vs 2 single-threaded workers of a LocalCluster, same clips, same config.

Each arm fits the same ``--clips`` clips of the embedded synthetic corpus (the tiny preset's corpus and
fitting iterations; ``--batch-clips`` clips of one signer per task) into a fresh cache and shards folder,
through the production path (``fit_corpus.executor: dask``, :func:`m3t.fitting.cluster.open_executor`,
:func:`m3t.fitting.corpus.run_fit_corpus`).
Reports clips/s and frames/s of each arm (the fit's wall time; the cluster's start and the workers' warm-up,
imports and body model, apart), the 1 -> 2 worker scaling ratio, and whether every shard file is byte-identical
between the arms. Each arm's ``cpu_share`` (CPU seconds its workers got / (workers x wall)) says how much of
the machine it had: on a shared box, a second worker without a free core cannot scale.

    python benchmarks/bench_fit_dask.py [--clips 24] [--batch-clips 4] [--repeats 2]
                                        [--out benchmarks/results/fit_dask.json]

The arms alternate ``--repeats`` times and each keeps its fastest repeat (the machine is shared and noisy).
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from report import write_and_log  # noqa: E402


def params_for(out: Path, corpus: Path, clips: int, workers: int, batch_clips: int):
    from m3t.config import load_params

    return load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "body": {"cache_dir": str(ROOT / ".cache" / "anny")},
        "data": {"shards_root": str(out / "shards")},
        "corpora": {"synthetic": {"root": str(corpus)}},
        "fit_corpus": {"cache_dir": str(out / "cache"), "max_clips": clips, "workers": workers,
                       "batch_clips": batch_clips, "executor": "dask", "dask_address": ""}})


def warm_up(job) -> None:
    """On a worker: the imports and the body model that its first clip would otherwise pay for."""
    from m3t.fitting.context import worker_context

    worker_context(job).body


def cpu_seconds() -> float:
    """On a worker: CPU seconds this process has used (user + system)."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_arm(out: Path, corpus: Path, clips: int, workers: int, batch_clips: int) -> dict:
    """One fit of the clips on a fresh LocalCluster of ``workers`` workers, into ``out``."""
    from m3t.fitting.cluster import for_workers, open_executor
    from m3t.fitting.corpus import run_fit_corpus

    job = params_for(out, corpus, clips, workers, batch_clips).fit_job("synthetic")
    start = time.perf_counter()
    with open_executor(job.run) as executor:
        executor.client.wait_for_workers(workers)
        ready = time.perf_counter()
        executor.client.run(warm_up, for_workers(job))  # the job as the tasks get it: the same per-process context
        cpu_before = executor.client.run(cpu_seconds)
        started = time.perf_counter()
        report = run_fit_corpus(job, executor, progress=False)
        wall = time.perf_counter() - started
        cpu_after = executor.client.run(cpu_seconds)
    cpu = sum(cpu_after[w] - cpu_before[w] for w in cpu_before if w in cpu_after)
    statuses = {o.status for o in report.outcomes}
    if statuses != {"fitted"}:
        raise RuntimeError(f"arm with {workers} workers: outcomes {statuses}, expected every clip fitted")
    frames = sum(o.frames for o in report.outcomes)
    return {"cluster_start_s": ready - start, "warm_up_s": started - ready, "wall_s": wall,
            "clips": len(report.outcomes), "frames": frames,
            "clips_per_s": len(report.outcomes) / wall, "frames_per_s": frames / wall,
            # the share of its cores the arm got: 1.0 = each worker had a core to itself for the whole fit
            "worker_cpu_s": cpu, "cpu_share": cpu / (workers * wall),
            "shards": {p.name: p.read_bytes() for p in sorted(Path(job.shards_dir).glob("*.parquet"))}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=24)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--batch-clips", type=int, default=4, help="fit_corpus.batch_clips: clips per task")
    parser.add_argument("--out", default="benchmarks/results/fit_dask.json")
    args = parser.parse_args()

    import dask
    import torch

    from m3t.body.anny_body import AnnyBody
    from m3t.config import load_params
    from m3t.corpora.synthetic import generate_corpus
    from m3t.corpora.synthetic_storage import write_corpus

    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-fit-dask-") as tmp:
        corpus = Path(tmp) / "corpus"
        tiny = load_params(ROOT / "params.yaml", preset="tiny")
        write_corpus(generate_corpus(tiny.synthetic_corpus, AnnyBody(ROOT / ".cache" / "anny")), corpus)
        best: dict[int, dict] = {}
        shards: list[dict[str, bytes]] = []
        for repeat in range(args.repeats):
            for workers in (1, 2):
                arm = run_arm(Path(tmp) / f"w{workers}-r{repeat}", corpus, args.clips, workers, args.batch_clips)
                shards.append(arm.pop("shards"))
                print(f"repeat {repeat}, {workers} worker(s): {arm}")
                if workers not in best or arm["wall_s"] < best[workers]["wall_s"]:
                    best[workers] = arm
    one, two = best[1], best[2]
    result = {
        "clips": one["clips"],
        "frames": one["frames"],
        "fitting": dataclasses.asdict(tiny.fitting),
        "batch_clips": args.batch_clips,
        "repeats": args.repeats,
        **{f"w{w}_{k}": best[w][k] for w in (1, 2) for k in ("clips_per_s", "frames_per_s", "wall_s",
                                                               "cluster_start_s", "warm_up_s", "worker_cpu_s",
                                                               "cpu_share")},
        "scaling_1_to_2": two["clips_per_s"] / one["clips_per_s"],
        "shard_files": sorted(shards[0]),
        "shards_identical": all(s == shards[0] for s in shards),
        "cpu_count": os.cpu_count(),
        "load_average_before": load_before,  # the machine is shared: other work lowers the scaling
        "load_average_after": os.getloadavg()[0],
        "machine": platform.machine(),
        "torch": torch.__version__,
        "dask": dask.__version__,
    }
    write_and_log(result, ROOT / args.out, "benchmark-fit-dask")
    if not result["shards_identical"]:
        raise SystemExit("shard files differ between the arms: the executor changed the fits")


if __name__ == "__main__":
    main()
