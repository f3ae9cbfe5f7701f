"""Reproducible arithmetic: ``M3T_REPRODUCIBLE=1`` makes every float the pipeline computes on a CPU the same,
byte for byte, whatever the x86-64 processor and its core count.

Without it the libraries choose their arithmetic from the machine: MKL's and OpenBLAS's matrix kernels,
torch's vectorised kernels (AVX2 / AVX-512), oneDNN's convolutions, numpy's SIMD loops, numba's target, glibc's
``exp`` / ``log`` variants, and the number of threads that split each reduction. Each choice reorders float
sums, so two machines (or two thread counts) give results that differ in the last bits, and a trained model
amplifies that into different weights. The mode pins every one of those choices to a code path that every
x86-64 CPU runs the same way (:data:`PINNED`), at one thread per process, and turns torch's oneDNN kernels off
(their blocking follows the cache sizes): convolutions then go through im2col and MKL's pinned GEMM. On a GPU
it asks for torch's deterministic kernels: the same bytes from run to run on one GPU model, not across models.

How it applies: ``import m3t`` (the first thing every stage, worker and CLI does) calls :func:`pin`. Most of the
settings are read once, when a library loads (glibc's at process start), so when the environment does not hold
them yet the process starts itself again with them (``os.execve`` of the same command line); its children
(stage subprocesses, spawned workers) inherit the environment. Worker pools then run one thread each, which is
also what makes a pool's results equal those of one process.

What it costs is measured by ``benchmarks/bench_reproducible.py`` (a stage with and without the mode), and the
docs say which digits a user can expect to see again without it.
"""
from __future__ import annotations

import os
import sys

ENV = "M3T_REPRODUCIBLE"

# every setting that selects arithmetic, pinned to a path every x86-64 CPU takes the same way
PINNED: dict[str, str] = {
    "MKL_CBWR": "COMPATIBLE",  # MKL's conditional numerical reproducibility: the SSE2 path on any Intel or AMD CPU
    "MKL_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",  # torch's intra-op pool (and MKL's OpenMP)
    "OPENBLAS_CORETYPE": "Nehalem",  # numpy's OpenBLAS kernels: SSE4.2, x86-64-v2 (numpy's own baseline)
    "OPENBLAS_NUM_THREADS": "1",
    "ATEN_CPU_CAPABILITY": "default",  # torch's kernels without AVX2 / AVX-512 dispatch
    "ONEDNN_MAX_CPU_ISA": "SSE41",  # in case a oneDNN kernel still runs (torch's is turned off below)
    "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",  # numpy's loops at its x86-64-v2 baseline
    "NUMBA_CPU_NAME": "generic",  # numba compiles for a generic x86-64, not the host
    "NUMBA_NUM_THREADS": "1",
    "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX2,-FMA,-FMA4,-AVX512F",  # libm's exp / log / pow without FMA variants
    "CUBLAS_WORKSPACE_CONFIG": ":4096:8",  # on a GPU: cuBLAS without its run-to-run varying workspace split
}


def enabled(environ: dict[str, str] | os._Environ = os.environ) -> bool:
    """Whether the mode is asked for (``M3T_REPRODUCIBLE`` = 1 / true / yes / on)."""
    value = environ.get(ENV, "").strip().lower()
    if value in ("", "0", "false", "no", "off"):
        return False
    if value in ("1", "true", "yes", "on"):
        return True
    raise ValueError(f"{ENV}={environ.get(ENV)!r}: use 1 (reproducible arithmetic) or 0 (the machine's fastest)")


def missing(environ: dict[str, str] | os._Environ = os.environ) -> dict[str, str]:
    """The pinned settings the environment does not hold yet (name -> the value it needs)."""
    return {k: v for k, v in PINNED.items() if environ.get(k) != v}


def pinned_environment(environ: dict[str, str] | os._Environ = os.environ) -> dict[str, str]:
    """``environ`` with the mode asked for and every setting of :data:`PINNED` in place: for a subprocess."""
    return {**environ, ENV: "1", **PINNED}


def cache_parts() -> tuple[str, ...]:
    """What the content caches add to their keys: nothing at the machine's arithmetic (keys as ever), a marker
    under the mode, so that a fit or a resumable training of one arithmetic is never reused by the other."""
    return ("arithmetic: pinned",) if enabled() else ()


def cache_folder(folder: str | os.PathLike) -> str:
    """A cache folder of built data (the body model's): its ``pinned`` subfolder under the mode."""
    return os.path.join(folder, "pinned") if enabled() else os.fspath(folder)


def _restart() -> None:
    """Start this process again, same interpreter and command line, in the pinned environment."""
    argv = list(getattr(sys, "orig_argv", []) or [sys.executable, *sys.argv])
    if not argv or argv[0] != sys.executable:  # orig_argv[0] is the name the interpreter was called by
        argv = [sys.executable, *argv[1:]]
    sys.stdout.flush()
    sys.stderr.flush()
    # the same interpreter and argv this process was started with, no shell: nothing new is run
    os.execve(sys.executable, argv, pinned_environment())  # noqa: S606


def pin() -> None:
    """Apply the mode when ``M3T_REPRODUCIBLE`` asks for it (module docstring); nothing otherwise."""
    if not enabled():
        return
    if missing():
        if os.environ.get("M3T_REPRODUCIBLE_RESTARTED"):  # the restart did not take: say so rather than loop
            raise RuntimeError(f"{ENV}=1: the environment still lacks {sorted(missing())} after a restart; set them "
                               "yourself (python -m m3t.arithmetic prints them) and run again")
        os.environ["M3T_REPRODUCIBLE_RESTARTED"] = "1"
        _restart()
    import torch

    torch.backends.mkldnn.enabled = False  # conv / linear through MKL's pinned GEMM, not oneDNN's cache-sized blocks
    torch.set_num_threads(1)
    # On a GPU the mode can promise less: the same bytes from run to run on one GPU model and software stack
    # (kernels are chosen by the GPU's architecture). Deterministic kernels, no autotuning, no TF32; an op without
    # a deterministic kernel warns (naming itself) rather than stopping a long run.
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.backends.cudnn.benchmark = False
    torch.backends.cudnn.deterministic = True
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False


def describe() -> str:
    """Shell lines that set the mode's environment by hand (``python -m m3t.arithmetic``)."""
    return "\n".join(f"export {k}={v!r}" if " " in v or "," in v else f"export {k}={v}"
                     for k, v in {ENV: "1", **PINNED}.items())


if __name__ == "__main__":
    print(describe())
