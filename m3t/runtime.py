"""Where work runs: device and dtype choice (the one place that decides where tensors live), the DDP context,
the threads of a process and the one pool of worker processes."""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from concurrent.futures import ProcessPoolExecutor


def choose_device(name: str = "auto") -> torch.device:
    """``"auto"`` -> CUDA when available, else CPU; otherwise the named device (fails clearly if absent)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {name!r} requested but no CUDA device is visible; use 'cpu' or 'auto'")
    return device


def autocast(device: torch.device, precision: str):
    """bf16 autocast when ``precision == 'bf16'`` (CUDA or CPU), else a no-op context."""
    if precision not in ("fp32", "bf16"):
        raise ValueError(f"precision {precision!r} unknown; allowed: fp32, bf16")
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=precision == "bf16")


class DistributedContext:
    """Rank / world size of this process; world size 1 unless started by ``torchrun`` (or a test) with
    ``init_process_group``. NCCL on CUDA, gloo on CPU."""

    def __init__(self, rank: int = 0, world_size: int = 1, device: torch.device | None = None):
        self.rank, self.world_size = rank, world_size
        self.device = device or torch.device("cpu")

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def spawn_pool(workers: int, threads: int = 0) -> ProcessPoolExecutor:
    """A ``concurrent.futures.ProcessPoolExecutor`` of ``workers`` spawned processes (never forked: a fork
    inherits torch's thread pool and the locks of a process that already computed), each with ``threads``
    intra-op torch threads (0: torch's default) and a watcher that ends the worker when this process is gone.
    ``kill -9`` of a stage gives its pool no chance to stop the workers; an orphan would go on fitting or
    training on the cores the rerun needs (and, for a trainer, hold the run's lock against it). The one pool
    of the project's worker processes: fit-corpus's local executor and the trainers' independent jobs."""
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor

    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker,
                               initargs=(os.getpid(), threads))


def use_threads(threads: int) -> None:
    """``threads`` intra-op torch threads in this process (0: leave torch's count); an equal count is left as it
    is rather than set again."""
    if threads and torch.get_num_threads() != threads:
        torch.set_num_threads(threads)


def _start_worker(parent: int, threads: int) -> None:
    """A :func:`spawn_pool` worker's initialiser: its thread count, and the watcher of its parent."""
    import threading

    use_threads(threads)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True, name="exit-with-parent").start()


def _exit_with_parent(parent: int) -> None:
    """Poll (each second) whether the process that started this worker is still its parent; exit when not."""
    import os
    import time

    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(1)


def distributed_context(device_name: str = "auto") -> DistributedContext:
    """Join the process group described by ``torchrun``'s environment (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_*);
    a single-process context when those are absent."""
    import os

    import torch.distributed as dist

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistributedContext(device=choose_device(device_name))
    device = choose_device(device_name)
    if device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return DistributedContext(dist.get_rank(), dist.get_world_size(), device)


def jit(**options):
    """``numba.njit(error_model="numpy", **options)`` with an on-disk cache where one is writable: numba raises
    at decoration when no cache directory is usable, and the kernel is then compiled once per process instead.
    The one decorator of the project's compiled kernels (DTW, the mesh rasteriser)."""
    import numba

    def wrap(func):
        try:
            return numba.njit(cache=True, error_model="numpy", **options)(func)
        except RuntimeError:
            return numba.njit(cache=False, error_model="numpy", **options)(func)
    return wrap
