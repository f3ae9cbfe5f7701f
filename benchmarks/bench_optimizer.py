"""Adam's step on the pipeline's trained models: torch's default (foreach, ``old``) vs its fused kernel
(``new``, :func:`m3t.optimizer.adam`, what every trainer uses), in the same run.

For each checkpoint of the embedded pipeline (tokenizers, SMLM, back-translation judge, PT / SGSA, recognition
probe): the model's parameters get fixed random gradients, then each arm runs ``--steps`` optimiser steps
from the same state; the arms alternate ``--repeats`` times and each keeps its fastest repeat. Also: the
tokenizer's whole training step (forward, backward, step on a random batch of the embedded size), where the
optimiser's share showed up in the profile of train-tokenizers; and the largest parameter difference between
the two arms after ``--steps`` steps from the same start (the same update up to float rounding).

    python benchmarks/bench_optimizer.py [--steps 50] [--repeats 3] [--out benchmarks/results/optimizer.json]

Needs the trained models (``dvc repro``); a missing checkpoint is skipped and named.
"""
from __future__ import annotations

import argparse
import copy
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from m3t.config import load_params  # noqa: E402
from m3t.optimizer import adam  # noqa: E402
from report import write_and_log  # noqa: E402


def checkpoints(models: Path) -> dict[str, Callable[[], torch.nn.Module]]:
    from m3t.backtranslation.checkpoint import load_backtranslation
    from m3t.sgsa.checkpoint import load_sgsa
    from m3t.slr.checkpoint import load_slr
    from m3t.smlm.checkpoint import load_smlm
    from m3t.tokenizers.checkpoint import load_tokenizer

    judge = next(iter(sorted((models / "backtranslation").glob("*.pt"))), models / "backtranslation" / "<language>.pt")
    return {
        "tokenizer_body": lambda: load_tokenizer(models / "tokenizers" / "body.pt").model,
        "tokenizer_hand": lambda: load_tokenizer(models / "tokenizers" / "hand.pt").model,
        "tokenizer_face": lambda: load_tokenizer(models / "tokenizers" / "face.pt").model,
        "smlm": lambda: load_smlm(models / "smlm" / "smlm.pt").model,
        "backtranslation": lambda: load_backtranslation(judge).model,
        "pt": lambda: load_sgsa(models / "sgsa" / "pt.pt").model,
        "sgsa": lambda: load_sgsa(models / "sgsa" / "sgsa.pt").model,
        "slr_full": lambda: load_slr(models / "slr" / "full.pt").model,
    }


def optimiser_arm(model: torch.nn.Module, fused: bool, steps: int) -> tuple[float, list[torch.Tensor]]:
    """Seconds per step of ``steps`` Adam steps on a copy of ``model`` with seeded gradients; the final weights."""
    model = copy.deepcopy(model)
    params = [p for p in model.parameters() if p.requires_grad]
    generator = torch.Generator().manual_seed(0)
    for p in params:
        p.grad = torch.randn(p.shape, generator=generator, dtype=p.dtype) * 1e-2
    optim = adam(params, "cpu", lr=1e-3) if fused else torch.optim.Adam(params, lr=1e-3)
    optim.step()  # state allocation outside the timing
    start = time.perf_counter()
    for _ in range(steps):
        optim.step()
    return (time.perf_counter() - start) / steps, [p.detach() for p in params]


def tokenizer_step_arm(model: torch.nn.Module, fused: bool, steps: int, batch: int, window: int) -> float:
    from m3t.tokenizers.train import train_step

    model = copy.deepcopy(model)
    optim = adam(model.parameters(), "cpu", lr=1e-4) if fused else torch.optim.Adam(model.parameters(), lr=1e-4)
    sched = torch.optim.lr_scheduler.LambdaLR(optim, lambda s: 1.0)
    generator = torch.Generator().manual_seed(0)
    x = torch.randn(batch, window, model.cfg.input_dim, generator=generator)
    mask = torch.ones(batch, window, dtype=torch.bool)
    train_step(model, (x, mask), optim, sched)
    start = time.perf_counter()
    for _ in range(steps):
        train_step(model, (x, mask), optim, sched)
    return (time.perf_counter() - start) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="benchmarks/results/optimizer.json")
    args = parser.parse_args()
    params = load_params()
    result: dict = {"steps": args.steps, "repeats": args.repeats, "torch_threads": torch.get_num_threads(),
                    "machine": platform.machine(), "torch": torch.__version__, "skipped": {}}
    for name, load in checkpoints(Path(params.data.models_dir)).items():
        try:
            model = load()
        except FileNotFoundError as exc:
            result["skipped"][name] = f"{exc} (run dvc repro first)"
            continue
        best = {"old": float("inf"), "new": float("inf")}
        weights = {}
        for _ in range(args.repeats):
            for arm in ("old", "new"):
                seconds, weights[arm] = optimiser_arm(model, arm == "new", args.steps)
                best[arm] = min(best[arm], seconds)
        diff = max(float((a - b).abs().max()) for a, b in zip(weights["old"], weights["new"]))
        result[f"{name}_parameters"] = sum(p.numel() for p in model.parameters())
        result[f"{name}_tensors"] = sum(1 for _ in model.parameters())
        result[f"{name}_step_ms_old"] = best["old"] * 1e3
        result[f"{name}_step_ms_new"] = best["new"] * 1e3
        result[f"{name}_speedup"] = best["old"] / best["new"]
        result[f"{name}_max_abs_diff"] = diff
        if name.startswith("tokenizer_"):
            cfg = params.tokenizer_train
            step = {"old": float("inf"), "new": float("inf")}
            for _ in range(args.repeats):
                for arm in ("old", "new"):
                    step[arm] = min(step[arm], tokenizer_step_arm(model, arm == "new", max(args.steps // 5, 5),
                                                                  cfg.batch_size, cfg.window))
            result[f"{name}_train_step_ms_old"] = step["old"] * 1e3
            result[f"{name}_train_step_ms_new"] = step["new"] * 1e3
            result[f"{name}_train_step_speedup"] = step["old"] / step["new"]
        print(f"{name}: step {best['old'] * 1e3:.2f} -> {best['new'] * 1e3:.2f} ms ({best['old'] / best['new']:.2f}x), "
              f"max |diff| {diff:.1e}", flush=True)
    write_and_log(result, args.out, "benchmark-optimizer")


if __name__ == "__main__":
    main()
