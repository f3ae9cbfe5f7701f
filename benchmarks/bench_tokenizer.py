"""Tokenizer training throughput against the machine's matmul peak, measured in the same run.

Arms (alternating, ``--repeats`` times, each keeps its fastest repeat):
  * matmul peak: ``torch.mm`` of two ``--matmul-size`` square fp32 matrices -> GFLOP/s;
  * training: full train steps (window sampling from the fitted shards + forward + backward + fused Adam) of a
    width ``--width`` tokenizer -> achieved GFLOP/s, counting 2 * C_in * C_out * k * L_out per Conv1d in
    the forward pass and twice that for the backward pass (input and weight gradients);
  * data loading alone: batches/s of the window sampler, against the steps/s training consumes.

    python benchmarks/bench_tokenizer.py [--width 512] [--batch 16] [--window 64] [--steps 10] [--out ...]

Goal: training at >= 60% of the matmul peak at width 512, data loading included.
"""
from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))

from m3t.shards.io import read_shard  # noqa: E402
from m3t.tokenizers.data import WindowSampler, clip_sequences  # noqa: E402
from m3t.tokenizers.config import TokenizerConfig  # noqa: E402
from m3t.tokenizers.train import train_step  # noqa: E402
from m3t.optimizer import adam, lr_factor  # noqa: E402
from m3t.tokenizers.vae import MotionTokenizer, count_parameters  # noqa: E402
from report import write_and_log  # noqa: E402


def conv_flops(model: nn.Module, x: torch.Tensor) -> float:
    """Forward FLOPs of every Conv1d for input ``x`` (multiply-adds counted as 2)."""
    total = 0.0

    def hook(module: nn.Conv1d, _inputs, output):
        nonlocal total
        total += 2.0 * module.in_channels * module.out_channels * module.kernel_size[0] * output.shape[-1] * output.shape[0]

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Conv1d)]
    with torch.no_grad():
        model(x)
    for h in handles:
        h.remove()
    return total


def matmul_gflops(size: int, reps: int = 5) -> float:
    a, b = torch.randn(size, size), torch.randn(size, size)
    torch.mm(a, b)
    start = time.perf_counter()
    for _ in range(reps):
        torch.mm(a, b)
    return 2.0 * size**3 * reps / (time.perf_counter() - start) / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shards", default="data/shards/synthetic/train.parquet")
    parser.add_argument("--group", default="body")
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--depth", type=int, default=6)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--window", type=int, default=64)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--matmul-size", type=int, default=2048)
    parser.add_argument("--out", default="benchmarks/results/tokenizer.json")
    args = parser.parse_args()
    torch.manual_seed(0)
    seqs = [s for c in read_shard(args.shards).clips for s in clip_sequences(c.params, args.group, c.clip.id)]
    sampler = WindowSampler(seqs, args.window, args.batch, per_sequence=64, seed=0)
    model = MotionTokenizer(TokenizerConfig(width=args.width, depth=args.depth).vae_config(args.group, seqs[0].shape[1]))
    optim = adam(model.parameters(), "cpu", lr=1e-4)
    sched = torch.optim.lr_scheduler.LambdaLR(optim, lambda s: lr_factor(s, 10, 1000, 0.01))
    step_flops = 3.0 * conv_flops(model, torch.zeros(args.batch, args.window, seqs[0].shape[1]))

    def train_arm() -> float:
        batches = sampler.epoch(0)
        train_step(model, next(batches), optim, sched)  # warm-up step outside the timing
        start = time.perf_counter()
        for _ in range(args.steps):
            train_step(model, next(batches), optim, sched)  # sampling happens inside next(): data loading included
        return (time.perf_counter() - start) / args.steps

    def loader_arm() -> float:
        batches = sampler.epoch(1)
        start = time.perf_counter()
        n = sum(1 for _ in zip(range(50), batches))
        return (time.perf_counter() - start) / n

    peak, step_s, load_s = 0.0, float("inf"), float("inf")
    for _ in range(args.repeats):
        peak = max(peak, matmul_gflops(args.matmul_size))
        step_s = min(step_s, train_arm())
        load_s = min(load_s, loader_arm())
    achieved = step_flops / step_s / 1e9
    result = {
        "group": args.group, "width": args.width, "depth": args.depth, "batch": args.batch, "window": args.window,
        "parameters": count_parameters(model),
        "matmul_peak_gflops": peak,
        "train_step_s": step_s,
        "train_gflop_per_step": step_flops / 1e9,
        "train_gflops": achieved,
        "fraction_of_matmul_peak": achieved / peak,
        "train_windows_per_s": args.batch / step_s,
        "loader_batches_per_s": 1.0 / load_s,
        "train_steps_per_s": 1.0 / step_s,
        "loader_headroom": step_s / load_s,  # batches the loader makes in the time one step consumes
        "torch_threads": torch.get_num_threads(),
        "machine": platform.machine(),
        "torch": torch.__version__,
    }
    write_and_log(result, args.out, "benchmark-tokenizer")

if __name__ == "__main__":
    main()
