"""train-tokenizers wall time: the three groups one after another on every thread (old) vs in worker processes
sharing the threads (new, ``tokenizer_train.group_workers``), on the embedded shards, same settings otherwise.

Each arm is the whole stage (``python -m m3t.stages.train_tokenizers --params ...``) in a fresh interpreter, so
imports, the body model's load, training, selection, the test report and the videos are all in the time. The
arms write to their own temporary models and cache folders (nothing of the pipeline's is touched or reused) and
log nothing to MLflow. Arms alternate ``--repeats`` times; each keeps its fastest repeat. Also reported: each
group's test PA-VPE and utilisation in both arms (float order differs with the thread count, so the runs are not
bit-identical; the test suite checks that a group in a worker equals the same group on one thread in one process).

    python benchmarks/bench_tokenizer_groups.py [--workers 2] [--repeats 1] [--out benchmarks/results/tokenizer_groups.json]

Needs the embedded shards (``dvc repro fit-corpus``).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from report import write_and_log

from m3t.config import load_params
from m3t.experiment import to_dict

KEEP = ("test_pa_vpe_mm", "utilisation_pct", "best_val_vpe_mm")


def run_arm(workers: int, work: Path, repeat: int) -> tuple[float, dict]:
    params = to_dict(load_params(ROOT / "params.yaml"))
    root = work / f"workers{workers}-{repeat}"
    params["tokenizer_train"].update(group_workers=workers, cache_dir=str(root / "cache"))
    params["data"]["models_dir"] = str(root / "models")
    params["experiment"]["enabled"] = False
    params_file = root / "params.yaml"
    root.mkdir(parents=True)
    params_file.write_text(yaml.safe_dump(params))
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "m3t.stages.train_tokenizers", "--params", str(params_file)],
                          cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, check=False)
    seconds = time.perf_counter() - start
    if done.returncode:
        sys.exit(f"train-tokenizers with group_workers {workers} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    metrics = json.loads((root / "models" / "tokenizers" / "metrics.json").read_text())
    return seconds, {g: {k: metrics[g][k] for k in KEEP} for g in metrics}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "tokenizer_groups.json"))
    args = ap.parse_args()
    shards = ROOT / "data" / "shards" / "synthetic" / "train.parquet"
    if not shards.exists():
        sys.exit(f"{shards} not found: run `dvc repro fit-corpus` first")
    times: dict[str, list[float]] = {"old": [], "new": []}
    metrics: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="bench-tok-groups-") as tmp:
        for repeat in range(args.repeats):
            for arm, workers in (("old", 1), ("new", args.workers)):
                seconds, metrics[arm] = run_arm(workers, Path(tmp), repeat)
                times[arm].append(seconds)
                print(f"{arm} (group_workers {workers}), repeat {repeat}: {seconds:.1f} s", flush=True)
    old, new = min(times["old"]), min(times["new"])
    result = {
        "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
        "workers": args.workers, "repeats": args.repeats,
        "old_seconds": old, "new_seconds": new, "speedup": old / new,
        "old_all_seconds": times["old"], "new_all_seconds": times["new"],
        "groups": {g: {f"{arm}_{k}": metrics[arm][g][k] for arm in ("old", "new") for k in KEEP}
                   for g in metrics["old"]},
    }
    write_and_log(result, args.out, "benchmark-tokenizer-groups")


if __name__ == "__main__":
    main()
