"""What ``M3T_REPRODUCIBLE=1`` (:mod:`m3t.arithmetic`) costs: training stages on the embedded shards with the
machine's own arithmetic (old) and with the pinned one (new), same params otherwise.

Each arm is the whole stage in a fresh interpreter (:func:`bench_stage_workers.run_arm`: own temporary models
and cache folders, no MLflow). Arms alternate ``--repeats`` times; each keeps its fastest repeat. Also reported:
each stage's selection figures in both arms, which differ in float order only.

    python benchmarks/bench_reproducible.py [--stages train-sgsa train-slr ...] [--repeats 1]
        [--out benchmarks/results/reproducible.json]

Needs the embedded shards (``dvc repro fit-corpus``) and, for train-slr, the tokenizers.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_stage_workers import DEFAULT, ROOT, STAGES, compare_arms
from report import write_and_log

from m3t.arithmetic import PINNED, pinned_environment


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stages", nargs="+", choices=sorted(STAGES), default=list(DEFAULT))
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "reproducible.json"))
    args = ap.parse_args()
    if not (ROOT / "data" / "shards" / "synthetic" / "train.parquet").exists():
        sys.exit("data/shards/synthetic/train.parquet not found: run `dvc repro fit-corpus` first")
    machine = {k: v for k, v in os.environ.items() if k not in PINNED and k != "M3T_REPRODUCIBLE"}
    arms = {"old": machine, "new": pinned_environment(machine)}
    stages: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="bench-reproducible-") as tmp:
        for name in args.stages:
            # the default's 2 worker processes in both arms: the mode runs each with one thread
            stages[name] = compare_arms(name, {"old": (2, arms["old"]), "new": (2, arms["new"])}, Path(tmp),
                                        args.repeats)
            stages[name]["cost"] = stages[name]["new_seconds"] / stages[name]["old_seconds"]
    old_total = sum(s["old_seconds"] for s in stages.values())
    new_total = sum(s["new_seconds"] for s in stages.values())
    result = {"machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
              "repeats": args.repeats, "old_seconds": old_total, "new_seconds": new_total,
              "cost": new_total / old_total, **{f"cost {name}": s["cost"] for name, s in stages.items()},
              "pinned": PINNED, "stages": stages}
    write_and_log(result, args.out, "benchmark-reproducible")


if __name__ == "__main__":
    main()
