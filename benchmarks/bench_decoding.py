"""Benchmark: greedy SMLM decoding with the key/value cache vs recomputing the prefix every step.

Both arms decode the same batch to the same length (EOS suppressed until ``--steps``) with the same
model, alternating ``--repeats`` times and keeping each arm's fastest run; the tokens are checked equal.
Goal (issue): cached >= 5x faster. Writes ``benchmarks/results/decoding.json`` and logs it to MLflow.

    python benchmarks/bench_decoding.py [--steps 250] [--d-model 256] [--layers 3] [--batch 8]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.report import write_and_log  # noqa: E402
from m3t.smlm.generate import generate_motion  # noqa: E402
from m3t.smlm.config import SMLMConfig  # noqa: E402
from m3t.smlm.model import SignMotionLM, SMLMDims  # noqa: E402
from m3t.smlm.vocab import MOTION_STREAMS, build_vocabulary  # noqa: E402

CODEBOOKS = {"body": 100, "right_hand": 180, "left_hand": 180, "face": 216}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=250, help="motion steps decoded (250 steps = 1000 frames)")
    parser.add_argument("--d-model", type=int, default=256)
    parser.add_argument("--layers", type=int, default=3)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", default="benchmarks/results/decoding.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    texts = ["the friend buys a red car yesterday", "my father drinks water in the morning"] * (args.batch // 2 + 1)
    texts = texts[: args.batch]
    vocab = build_vocabulary(texts, ["ASL"], CODEBOOKS, 200)
    cfg = SMLMConfig(d_model=args.d_model, encoder_layers=args.layers, decoder_layers=args.layers,
                     attention_heads=max(1, args.d_model // 64), ffn_dim=4 * args.d_model, dropout=0.0,
                     max_motion_tokens=args.steps + 4)
    torch.manual_seed(0)
    model = SignMotionLM(cfg, SMLMDims.from_vocabulary(vocab)).eval()
    langs = ["ASL"] * args.batch
    best = {True: float("inf"), False: float("inf")}
    outputs = {}
    for _ in range(args.repeats):
        for cached in (True, False):
            start = time.perf_counter()
            outputs[cached] = generate_motion(model, vocab, texts, langs, max_steps=args.steps, min_steps=args.steps,
                                              use_cache=cached)
            best[cached] = min(best[cached], time.perf_counter() - start)
    same = all(np.array_equal(a.tokens[s], b.tokens[s]) for a, b in zip(outputs[True], outputs[False]) for s in MOTION_STREAMS)
    steps = args.steps * args.batch
    result = {
        "config": {"steps": args.steps, "batch": args.batch, "d_model": args.d_model, "layers": args.layers,
                   "threads": args.threads, "repeats": args.repeats},
        "cached_s": best[True], "uncached_s": best[False],
        "cached_steps_per_s": steps / best[True], "uncached_steps_per_s": steps / best[False],
        "speedup": best[False] / best[True], "goal_speedup": 5.0, "tokens_identical": bool(same),
    }
    result["goal_met"] = bool(result["speedup"] >= 5.0)
    write_and_log(result, args.out, "bench-decoding")
    print(f"cached {best[True]:.2f} s, uncached {best[False]:.2f} s: {result['speedup']:.1f}x "
          f"(goal 5x, identical tokens: {same})")
    return result


if __name__ == "__main__":
    main()
