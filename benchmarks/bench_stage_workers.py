"""Training stages whose independent trainings run one after another on every thread (old, ``workers: 1``) vs in
worker processes sharing the threads (new, :func:`m3t.training_jobs.run_jobs`), on the embedded shards, same settings
otherwise: train-tokenizers (its groups, ``tokenizer_train.group_workers``), train-backtranslation and
train-backtranslation-skeleton (their languages, ``backtranslation_train.workers``), train-slr (its variants,
``slr_train.workers``) and train-sgsa (its systems, ``sgsa_train.workers``).

Each arm is the whole stage (``python -m m3t.stages.<stage> --params ...``) in a fresh interpreter, so imports,
the body model's load, training, selection, plots and videos are all in the time. The arms write to their own
temporary models and cache folders (nothing of the pipeline's is touched or reused; train-slr gets a copy of the
pipeline's tokenizers, its frozen encoders) and log nothing to MLflow. Arms alternate ``--repeats`` times; each
keeps its fastest repeat. Also reported: each stage's selection figures (``best_*`` of its metrics.json) in both
arms: float order differs with the thread count, so the arms are not bit-identical (the test suite checks that a
training in a worker equals the same training on one thread in one process).

    python benchmarks/bench_stage_workers.py [--stages train-sgsa train-slr ...] [--workers 2] [--old-workers 1]
        [--repeats 1] [--out benchmarks/results/stage_workers.json]

``--old-workers N`` compares two worker settings instead (e.g. ``--old-workers 2 --workers 3``: three tokenizer
groups in two processes, one of them training two groups, against one process per group).

Needs the embedded shards (``dvc repro fit-corpus``) and, for train-slr, the tokenizers (``dvc repro
train-tokenizers``). The default leaves train-tokenizers out (~8 min for its two arms; its result of 2026-11-27 is
``benchmarks/results/tokenizer_groups.json``).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from report import write_and_log

from m3t.config import load_params
from m3t.experiment import to_dict


@dataclass(frozen=True)
class Stage:
    module: str  # m3t.stages.<module>
    section: str  # the params section with the worker setting and the cache folder
    setting: str  # the worker setting
    out: str  # the models subfolder holding metrics.json
    needs: tuple[str, ...] = ()  # models subfolders the stage reads (copied from the pipeline's)


STAGES = {
    "train-tokenizers": Stage("train_tokenizers", "tokenizer_train", "group_workers", "tokenizers"),
    "train-backtranslation": Stage("train_backtranslation", "backtranslation_train", "workers", "backtranslation"),
    "train-backtranslation-skeleton": Stage("train_backtranslation_skeleton", "backtranslation_train", "workers",
                                            "backtranslation-skeleton"),
    "train-slr": Stage("train_slr", "slr_train", "workers", "slr", needs=("tokenizers",)),
    "train-sgsa": Stage("train_sgsa", "sgsa_train", "workers", "sgsa"),
}
DEFAULT = ("train-backtranslation", "train-slr", "train-backtranslation-skeleton", "train-sgsa")


def selection_figures(metrics: dict) -> dict[str, float]:
    """The ``best_*`` numbers of a metrics.json (flat, or one level of groups as train-tokenizers writes it)."""
    flat = {f"{k}/{kk}": vv for k, v in metrics.items() if isinstance(v, dict) for kk, vv in v.items()}
    flat.update({k: v for k, v in metrics.items() if not isinstance(v, dict)})
    return {k: float(v) for k, v in sorted(flat.items()) if k.rsplit("/", 1)[-1].startswith("best_")}


def run_arm(name: str, stage: Stage, workers: int, work: Path, repeat: int,
            env: dict[str, str] | None = None, label: str = "") -> tuple[float, dict[str, float]]:
    """One run of the stage ``name`` in a fresh interpreter (environment ``env``: default this one's); its wall
    time and its selection figures."""
    params = to_dict(load_params(ROOT / "params.yaml"))
    pipeline_models = ROOT / params["data"]["models_dir"]
    root = work / f"{name}-workers{workers}{label}-{repeat}"
    params[stage.section].update({stage.setting: workers, "cache_dir": str(root / "cache")})
    params["data"]["models_dir"] = str(root / "models")
    params["experiment"]["enabled"] = False
    root.mkdir(parents=True)
    for folder in stage.needs:
        if not (pipeline_models / folder).is_dir():
            sys.exit(f"{pipeline_models / folder} not found: {name} needs it (dvc repro {name})")
        shutil.copytree(pipeline_models / folder, root / "models" / folder)
    params_file = root / "params.yaml"
    params_file.write_text(yaml.safe_dump(params))
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", f"m3t.stages.{stage.module}", "--params", str(params_file)],
                          cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, check=False,
                          env=env)
    seconds = time.perf_counter() - start
    if done.returncode:
        sys.exit(f"{name} with {stage.section}.{stage.setting} {workers} failed ({done.returncode}):\n"
                 f"{done.stderr[-3000:]}")
    return seconds, selection_figures(json.loads((root / "models" / stage.out / "metrics.json").read_text()))


def compare_arms(name: str, arms: dict[str, tuple[int, dict[str, str] | None]], work: Path, repeats: int,
                 labels: dict[str, str] | None = None) -> dict:
    """The stage ``name`` in two arms, ``{"old": (workers, env), "new": (workers, env)}``, alternating ``repeats``
    times; each arm's fastest repeat (``old_seconds`` / ``new_seconds``), all its repeats and both arms'
    selection figures."""
    times: dict[str, list[float]] = {arm: [] for arm in arms}
    figures: dict[str, dict[str, float]] = {}
    for repeat in range(repeats):
        for arm, (workers, env) in arms.items():
            seconds, figures[arm] = run_arm(name, STAGES[name], workers, work, repeat, env,
                                            "" if env is None else f"-{arm}")
            times[arm].append(seconds)
            print(f"{name} {(labels or {}).get(arm, arm)}, repeat {repeat}: {seconds:.1f} s", flush=True)
    return {"old_seconds": min(times["old"]), "new_seconds": min(times["new"]),
            "old_all_seconds": times["old"], "new_all_seconds": times["new"],
            "figures": {k: {"old": figures["old"][k], "new": figures["new"].get(k)} for k in figures["old"]}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stages", nargs="+", choices=sorted(STAGES), default=list(DEFAULT))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--old-workers", type=int, default=1, help="the old arm's setting (1: one process)")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "stage_workers.json"))
    args = ap.parse_args()
    shards = ROOT / "data" / "shards" / "synthetic" / "train.parquet"
    if not shards.exists():
        sys.exit(f"{shards} not found: run `dvc repro fit-corpus` first")
    stages: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="bench-stage-workers-") as tmp:
        for name in args.stages:
            arms = {"old": (args.old_workers, None), "new": (args.workers, None)}
            stages[name] = {"setting": f"{STAGES[name].section}.{STAGES[name].setting}",
                            **compare_arms(name, arms, Path(tmp), args.repeats,
                                           {arm: f"{arm} ({STAGES[name].setting} {w})" for arm, (w, _) in arms.items()})}
            stages[name]["speedup"] = stages[name]["old_seconds"] / stages[name]["new_seconds"]
    old_total = sum(s["old_seconds"] for s in stages.values())
    new_total = sum(s["new_seconds"] for s in stages.values())
    result = {"machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
              "old_workers": args.old_workers, "workers": args.workers, "repeats": args.repeats,
              "old_seconds": old_total, "new_seconds": new_total,
              "speedup": old_total / new_total, **{f"speedup {name}": s["speedup"] for name, s in stages.items()},
              "stages": stages}
    write_and_log(result, args.out, "benchmark-stage-workers")


if __name__ == "__main__":
    main()
