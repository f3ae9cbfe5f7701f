"""DTW benchmark: DTW-JPE and DTW-PA-JPE with paths, the torch path (old) vs the numba kernels (new), same pairs.

Each pair is one (prediction, ground truth) of ~250 frames (uniform in [200, 300], lengths differ) with SOKE's
three regions: body (12 points), left and right hand (21 each). Each metric is timed on its own: for DTW-JPE
the JPE cost matrices, DP, raw and path-normalised cost and path of the 3 regions; DTW-PA-JPE likewise.

- old: the code ``evaluate_pairs`` ran before the numba kernels: torch cost matrices (``jpe_distance_matrix``,
  QCP ``pa_distance_matrix``) computed by ``--threads`` worker threads of 1 torch thread each (its fastest
  configuration), zero-padded into batches of 16 pairs, numpy anti-diagonal DP and vectorised backtrack;
- new: ``m3t.metrics.kernels.dtw_jobs`` (cost matrix, DP and backtrack fused per job, jobs in parallel on
  a thread pool), after a warm-up: the compile is timed apart, cold (empty cache) and from the on-disk cache,
  each in a fresh interpreter; each point distance's square root in float32 (the default ``root_precision``),
  and the same kernels with a float64 root (``new_float64_root``), so the root's share is measured;
- checks: max |raw cost new - old| and the share of identical paths over all jobs; the raw costs of
  ``--baseline-pairs`` pairs against an independent numpy baseline (batched ``np.linalg.svd`` Procrustes,
  pure-Python DP); the end-to-end ``evaluate_pairs`` rate (both metrics, default config);
- ``--device cuda`` (when available): the torch PA cost matrices on the GPU, ``--gpu-batch`` pairs per batched
  call (``pa_distance_matrices``), then the numba DP and backtrack.

Also reported: PA cost matrices with the SVD solver vs the QCP solver (the faster is the torch default).

Instruction-set levels (``levels``): the new kernels' pairs/s and ``evaluate_pairs``' rate, each level in fresh
interpreters with their own numba cache, in alternating rounds (the best of ``--level-rounds`` counts): ``native``
(what numba targets on this host) and ``avx2`` (numba told the CPU is a Haswell without AVX-512:
``NUMBA_CPU_NAME=haswell``, ``NUMBA_CPU_FEATURES`` AVX2 + FMA; NumPy's OpenBLAS as its Haswell kernels,
``OPENBLAS_CORETYPE=Haswell``), beside the float64 matmul peak each level reaches. On an AVX-512 host this says
what the kernels lose without AVX-512 on the same silicon (``kernel_ratio`` native / avx2 against
``matmul_ratio``); on an AVX2 host both levels are the same code.

    python benchmarks/bench_dtw.py [--pairs 48] [--threads 2] [--device cuda] [--out benchmarks/results/dtw.json]
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
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")  # before numpy/torch load their thread pools

import numba
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from report import write_and_log

from m3t.metrics import kernels
from m3t.metrics.dtw import DTWResult, dtw_padded, jpe_distance_matrix
from m3t.metrics.motion import evaluate_pairs
from m3t.metrics.procrustes import pa_distance_matrices, pa_distance_matrix

GOALS = {"jpe": 1000.0, "pa": 100.0, "pa_gpu": 2000.0}  # pairs/s
REGIONS = {"body": (12, 0.15), "left_hand": (21, 0.05), "right_hand": (21, 0.05)}  # points, rest-shape spread (m)
OLD_BATCH = 16  # evaluate_pairs' batch_pairs
COMPILE_SNIPPET = """
import time
import numpy as np
from m3t.metrics import kernels
start = time.perf_counter()
rng = np.random.default_rng(0)
p, g = rng.normal(size=(5, 21, 3)), rng.normal(size=(4, 21, 3))
kernels.dtw_jobs([kernels.CostJob(p, g, False), kernels.CostJob(p, g, True)])
kernels.dtw_costs([rng.random((3, 4))])
print(time.perf_counter() - start)
"""


def make_pairs(count: int, seed: int) -> list[tuple[dict, dict]]:
    """Pairs sharing one rest skeleton per region (one signer), each side moving smoothly on its own."""
    rng = np.random.default_rng(seed)
    rest = {r: rng.normal(scale=s, size=(k, 3)) for r, (k, s) in REGIONS.items()}

    def sequence() -> dict[str, np.ndarray]:
        frames = int(rng.integers(200, 301))
        return {r: rest[r] + np.cumsum(rng.normal(scale=0.003, size=(frames, len(rest[r]), 3)), axis=0)
                for r in REGIONS}

    return [(sequence(), sequence()) for _ in range(count)]


# ---------------------------------------------------------------- old and new arms


def old_arm(pairs: list[tuple[dict, dict]], procrustes: bool, workers: int) -> list[DTWResult]:
    """The pre-kernel ``evaluate_pairs`` path for one metric: torch matrices by worker threads + numpy DP."""
    results = []
    for start in range(0, len(pairs), OLD_BATCH):
        jobs = [(torch.as_tensor(p[r]), torch.as_tensor(g[r])) for p, g in pairs[start:start + OLD_BATCH]
                for r in REGIONS]
        lengths = np.array([[len(p), len(g)] for p, g in jobs])
        tables = torch.zeros(*lengths.max(0), len(jobs), dtype=torch.float64)

        def fill(b: int) -> None:
            p, g = jobs[b]
            tables[:len(p), :len(g), b] = pa_distance_matrix(p, g) if procrustes else jpe_distance_matrix(p, g)

        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(fill, range(len(jobs))))
        results += dtw_padded(tables.numpy(), lengths)
    return results


def new_arm(pairs: list[tuple[dict, dict]], procrustes: bool, root_precision: str = "float32") -> list[DTWResult]:
    return kernels.dtw_jobs([kernels.CostJob(p[r], g[r], procrustes) for p, g in pairs for r in REGIONS],
                            root_precision=root_precision)


def gpu_arm(pairs: list[tuple[dict, dict]], device: str, batch: int) -> list[DTWResult]:
    """Torch PA cost matrices on ``device``, ``batch`` pairs per region per call, then the numba DP."""
    results = []
    for start in range(0, len(pairs), batch):
        chunk = pairs[start:start + batch]
        costs = {}
        for r in REGIONS:
            pred = torch.nn.utils.rnn.pad_sequence([torch.as_tensor(p[r]) for p, _ in chunk], batch_first=True)
            gt = torch.nn.utils.rnn.pad_sequence([torch.as_tensor(g[r]) for _, g in chunk], batch_first=True)
            costs[r] = pa_distance_matrices(pred.to(device), gt.to(device), chunk_pairs=1 << 24,
                                            residual_elements=1 << 26).cpu().numpy()
        results += kernels.dtw_costs([costs[r][n, :len(p[r]), :len(g[r])] for n, (p, g) in enumerate(chunk)
                                      for r in REGIONS])
    return results


def best_seconds(run, repeats: int) -> tuple[float, list]:
    """Fastest of ``repeats`` runs (the machine is shared) and the last result."""
    best, out = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        out = run()
        best = min(best, time.perf_counter() - start)
    return best, out


def agreement(new: list[DTWResult], old: list[DTWResult]) -> tuple[float, float]:
    """Max |raw cost difference| and the share of identical paths."""
    diff = max(abs(a.cost_raw - b.cost_raw) for a, b in zip(new, old, strict=True))
    same = np.mean([np.array_equal(a.path, b.path) for a, b in zip(new, old, strict=True)])
    return float(diff), float(same)


def compile_seconds() -> dict[str, float]:
    """Seconds of the first kernel calls in a fresh interpreter (imports excluded): empty cache, then cached."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env["NUMBA_CACHE_DIR"] = cache
        for name in ("compile_cold_s", "compile_cached_s"):
            run = subprocess.run([sys.executable, "-c", COMPILE_SNIPPET], env=env, capture_output=True, text=True,
                                 check=True)
            out[name] = float(run.stdout.split()[-1])
    return out


LEVELS = {"native": {},
          "avx2": {"NUMBA_CPU_NAME": "haswell", "OPENBLAS_CORETYPE": "Haswell",
                   "NUMBA_CPU_FEATURES": "+64bit,+avx,+avx2,+bmi,+bmi2,+cmov,+cx16,+f16c,+fma,+fsgsbase,+lzcnt,+movbe,"
                                         "+popcnt,+sse,+sse2,+sse3,+sse4.1,+sse4.2,+ssse3,+xsave,-avx512f,-avx512vl,"
                                         "-avx512bw,-avx512dq,-avx512cd"}}
LEVEL_SNIPPET = """
import json, sys, time
import numpy as np
sys.path.insert(0, {bench!r})
from bench_dtw import REGIONS, make_pairs, new_arm
from m3t.metrics.motion import evaluate_pairs
pairs = make_pairs({pairs}, seed=0)
new_arm(pairs[:1], False), new_arm(pairs[:1], True), evaluate_pairs(pairs[:1])  # compile / load
def best(run, repeats=3):
    times = []
    for _ in range(repeats):
        start = time.perf_counter(); run(); times.append(time.perf_counter() - start)
    return min(times)
a = np.random.default_rng(0).random((1024, 1024))
out = {{"jpe_pairs_per_s": len(pairs) / best(lambda: new_arm(pairs, False)),
        "pa_pairs_per_s": len(pairs) / best(lambda: new_arm(pairs, True)),
        "evaluate_pairs_pairs_per_s": len(pairs) / best(lambda: evaluate_pairs(pairs)),
        "matmul_gflops": 2 * 1024 ** 3 / best(lambda: a @ a, 5) / 1e9}}
import numba
out["numba_cpu"] = numba.config.CPU_NAME or "host"
print(json.dumps(out))
"""


def level_rates(pairs: int, rounds: int) -> dict:
    """The kernels' rates at each instruction-set level of :data:`LEVELS` (module doc), the best of ``rounds``
    alternating rounds, and the ratios native / avx2."""
    import llvmlite.binding as llvm

    root = Path(__file__).resolve().parents[1]
    snippet = LEVEL_SNIPPET.format(bench=str(root / "benchmarks"), pairs=pairs)
    best: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as caches:
        for _ in range(rounds):
            for level, settings in LEVELS.items():
                env = {**os.environ, "PYTHONPATH": str(root), "NUMBA_CACHE_DIR": str(Path(caches) / level),
                       **settings}
                run = subprocess.run([sys.executable, "-c", snippet], env=env, capture_output=True, text=True,
                                     check=True)
                rates = json.loads(run.stdout.strip().splitlines()[-1])
                kept = best.setdefault(level, rates)
                for key, value in rates.items():
                    if isinstance(value, float):
                        kept[key] = max(kept[key], value)
    llvm.initialize_native_target()
    out = {"host_cpu": llvm.get_host_cpu_name(), "host_avx512": "+avx512f" in llvm.get_host_cpu_features().flatten(),
           "rounds": rounds, "levels": best}
    for key in ("jpe_pairs_per_s", "pa_pairs_per_s", "evaluate_pairs_pairs_per_s", "matmul_gflops"):
        out[f"ratio_native_vs_avx2_{key}"] = best["native"][key] / best["avx2"][key]
    return out


# ---------------------------------------------------------------- independent numpy baseline


def numpy_jpe_matrix(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    x, y = pred - pred[:, :1], gt - gt[:, :1]
    return np.linalg.norm(x[:, None] - y[None], axis=-1).mean(-1)


def numpy_pa_matrix(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    x = pred - pred.mean(1, keepdims=True)  # (T1, K, 3)
    y = gt - gt.mean(1, keepdims=True)  # (T2, K, 3)
    cov = np.einsum("ika,jkb->ijab", x, y)  # (T1, T2, 3, 3)
    u, _, vh = np.linalg.svd(cov)
    v, ut = np.swapaxes(vh, -1, -2), np.swapaxes(u, -1, -2)
    z = np.ones(cov.shape[:-1])
    z[..., 2] = np.sign(np.linalg.det(v @ ut))
    rot = v @ (z[..., None] * ut)
    scale = np.einsum("ijaa->ij", rot @ cov) / (x ** 2).sum((1, 2))[:, None]
    aligned = scale[..., None, None] * np.einsum("ijab,ikb->ijka", rot, x)
    return np.linalg.norm(aligned - y[None], axis=-1).mean(-1)


def python_dtw(cost: np.ndarray) -> float:
    """Raw DTW cost by the textbook double loop."""
    c = cost.tolist()
    t1, t2 = len(c), len(c[0])
    inf = float("inf")
    d = [[inf] * t2 for _ in range(t1)]
    for i in range(t1):
        for j in range(t2):
            d[i][j] = c[0][0] if i == 0 and j == 0 else c[i][j] + min(
                d[i - 1][j] if i else inf, d[i][j - 1] if j else inf, d[i - 1][j - 1] if i and j else inf)
    return d[-1][-1]


def baseline_costs(pairs: list[tuple[dict, dict]], procrustes: bool) -> list[float]:
    matrix = numpy_pa_matrix if procrustes else numpy_jpe_matrix
    return [python_dtw(matrix(p[r], g[r])) for p, g in pairs for r in REGIONS]


# ---------------------------------------------------------------- main


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=48)
    parser.add_argument("--baseline-pairs", type=int, default=2)
    parser.add_argument("--solver-pairs", type=int, default=2, help="pairs for the SVD vs QCP solver comparison")
    parser.add_argument("--threads", type=int, default=2, help="worker threads of the old path")
    parser.add_argument("--repeats", type=int, default=5, help="runs of each new arm; the fastest counts")
    parser.add_argument("--device", default="cpu", help="cuda: also time the torch PA path on the GPU")
    parser.add_argument("--gpu-batch", type=int, default=64)
    parser.add_argument("--level-pairs", type=int, default=24, help="pairs per instruction-set level run")
    parser.add_argument("--level-rounds", type=int, default=3, help="alternating rounds of the levels (0: skip)")
    parser.add_argument("--out", default="benchmarks/results/dtw.json")
    args = parser.parse_args()
    pairs = make_pairs(args.pairs, seed=0)
    torch.set_num_threads(1)
    compiled = compile_seconds()
    new_arm(pairs[:1], False), new_arm(pairs[:1], True)  # load the compiled kernels in this process

    result: dict = {
        "pairs": args.pairs, "frames_per_sequence": "uniform 200-300",
        "regions": "body 12 + left_hand 21 + right_hand 21 points",
        "mean_frames": float(np.mean([len(p["body"]) for pair in pairs for p in pair])),
    }
    for metric, procrustes in (("jpe", False), ("pa", True)):
        old_s, old = best_seconds(lambda: old_arm(pairs, procrustes, args.threads), 1 if procrustes else 3)
        new_s, new = best_seconds(lambda: new_arm(pairs, procrustes), args.repeats)
        wide_s, wide = best_seconds(lambda: new_arm(pairs, procrustes, "float64"), args.repeats)
        diff, same = agreement(new, old)
        wide_diff, wide_same = agreement(wide, old)
        reference = baseline_costs(pairs[:args.baseline_pairs], procrustes)
        result.update({
            f"{metric}_old_pairs_per_s": args.pairs / old_s,
            f"{metric}_new_pairs_per_s": args.pairs / new_s,
            f"{metric}_speedup_new_vs_old": old_s / new_s,
            f"{metric}_goal_pairs_per_s": GOALS[metric],
            f"{metric}_goal_met": args.pairs / new_s >= GOALS[metric],
            f"{metric}_max_abs_cost_difference_new_vs_old_m": diff,
            f"{metric}_identical_paths_new_vs_old": same,
            f"{metric}_max_rel_cost_difference_new_vs_old": max(
                abs(a.cost_raw - b.cost_raw) / b.cost_raw for a, b in zip(new, old) if b.cost_raw > 0),
            f"{metric}_new_float64_root_pairs_per_s": args.pairs / wide_s,
            f"{metric}_speedup_float32_vs_float64_root": wide_s / new_s,
            f"{metric}_max_abs_cost_difference_new_float64_root_vs_old_m": wide_diff,
            f"{metric}_identical_paths_new_float64_root_vs_old": wide_same,
            f"{metric}_max_abs_cost_difference_new_vs_numpy_baseline_m": max(
                abs(a.cost_raw - b) for a, b in zip(new, reference)),
        })
    both_s, _ = best_seconds(lambda: evaluate_pairs(pairs), args.repeats)
    result["evaluate_pairs_both_metrics_pairs_per_s"] = args.pairs / both_s
    result.update(compiled)
    if args.level_rounds > 0:
        result["instruction_set_levels"] = level_rates(args.level_pairs, args.level_rounds)

    solver = {}
    for method in ("quaternion", "svd"):
        start = time.perf_counter()
        for pred, gt in pairs[:args.solver_pairs]:
            for region in REGIONS:
                pa_distance_matrix(torch.as_tensor(pred[region]), torch.as_tensor(gt[region]), method)
        solver[method] = (time.perf_counter() - start) / args.solver_pairs
    result.update({"torch_pa_matrices_s_per_pair_qcp": solver["quaternion"],
                   "torch_pa_matrices_s_per_pair_svd": solver["svd"],
                   "torch_qcp_speedup_vs_svd": solver["svd"] / solver["quaternion"]})

    if args.device != "cpu":
        if not torch.cuda.is_available() and args.device.startswith("cuda"):
            result["pa_gpu"] = f"not measured: device {args.device!r} unavailable"
        else:
            gpu_arm(pairs[:2], args.device, args.gpu_batch)  # warm-up
            gpu_s, gpu = best_seconds(lambda: gpu_arm(pairs, args.device, args.gpu_batch), args.repeats)
            diff, same = agreement(gpu, new_arm(pairs, True))
            result.update({"pa_gpu_pairs_per_s": args.pairs / gpu_s, "pa_gpu_goal_pairs_per_s": GOALS["pa_gpu"],
                           "pa_gpu_goal_met": args.pairs / gpu_s >= GOALS["pa_gpu"],
                           "pa_gpu_max_abs_cost_difference_vs_new_m": diff, "pa_gpu_identical_paths_vs_new": same,
                           "gpu": torch.cuda.get_device_name(args.device)})
    result.update({
        "old": f"torch cost matrices ({args.threads} worker threads x 1 torch thread), numpy anti-diagonal DP + "
               "vectorised backtrack, batches of 16 pairs",
        "new": "numba kernels: cost matrix + DP + backtrack fused per job, jobs on a thread pool, each point "
               "distance's square root in float32 (the default; new_float64_root: in float64)",
        "new_threads": kernels.available_cores(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "numba": numba.__version__,
    })
    write_and_log(result, args.out, "benchmark-dtw")


if __name__ == "__main__":
    main()
