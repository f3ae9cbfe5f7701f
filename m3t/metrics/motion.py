"""DTW joint errors of produced motion against ground truth (M3T Tab. 1, SOKE's evaluation).

Per (prediction, ground truth) sequence pair and per region of ``m3t.body.metric_sets`` (``body``: 12 points,
neck first; ``left_hand`` / ``right_hand``: 21 points, wrist first; ``face``: vertices), on plain (T, K, 3)
arrays in metres, so no body model is needed here:

- ``dtw_jpe_<region>_m``: DTW raw accumulated cost of the root-relative mean point distance (SOKE
  ``dist_jpe``); for the face it is named ``dtw_vpe_face_m`` (vertices, same root-relative distance);
- ``dtw_pa_jpe_<region>_m``: the same with the distance after a similarity Procrustes of every
  prediction frame onto every ground-truth frame (SOKE ``dist_pa``), for ``procrustes_regions``;
- ``..._pathnorm_m``: the raw cost divided by the warping-path length (a mean per aligned frame pair);
- ``dtw_jpe_hand_m`` etc.: the mean of the left- and right-hand values, when both hands are given.

Raw costs grow with sequence length (SOKE reports them so); the path-normalised ones compare across lengths.

**Two backends** (:attr:`MotionMetricsConfig.backend`), the same numbers (``tests/metrics/test_dtw_kernels.py``: cost
matrices to ~1e-15 on motion with ``root_precision="float64"``, 1e-6 on degenerate frames such as collinear
points; identical paths; the float32 square root, the default in mode ``m3t``, moves costs by < 9e-8 relative).
``"numba"`` (the default) runs :mod:`m3t.metrics.kernels`: cost matrix, DP and backtrack fused per (pair,
region, metric) job, jobs in parallel on every core the process may use (its CPU affinity: ``taskset`` limits
it). ``"torch"`` computes the cost matrices with :mod:`m3t.metrics.dtw` /
:mod:`m3t.metrics.procrustes` on ``device`` (a GPU: the PA matrices of a batch in one batched call), then
the DP and backtrack by the numba kernel, or by the numpy sweep where numba is not installed. The numba backend
without numba fails naming the package rather than falling back: a silent 10-30x slowdown of an evaluation is
worse than an install step.

**Two modes** (:attr:`MotionMetricsConfig.mode`). ``"m3t"`` (the default, every table of this project) roots
the body at the neck and fits the body's Procrustes on its 12 points. Anny, the default body model, has no
SMPL-X pelvis or spine convention (its body stream moves two spine bones), and rooting at the neck measures
the signing space without the spine, which the two body models then share. Its rooting equals SOKE's
whenever the spine does not move relative to the pelvis, as in SOKE's own evaluation, which zeroes the spine,
and always on SMPL-FX, which has no spine joints: DTW-JPE is then the same number in both modes. ``"soke_exact"``
reproduces SOKE's released arithmetic (:mod:`m3t.metrics.soke`): the body region holds the root (SOKE's
pelvis) first, then the 12 measured points, then the further points SOKE's Procrustes fits; DTW-JPE translates
by the root and measures the 12, DTW-PA-JPE fits on all points and measures the 12; the hands are unchanged,
and SOKE's names are added (``DTW_MPJPE_PA_body`` / ``_lhand`` / ``_rhand``, which are DTW-JPE values).

Axis legend: T1 prediction frames, T2 ground-truth frames, K points of a region.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from tqdm.auto import tqdm

from m3t.metrics.dtw import DTWResult, dtw_batch, jpe_distance_matrix
from m3t.metrics.procrustes import pa_distance_matrices, pa_distance_matrix
from m3t.metrics.soke import BODY_MEASURED, soke_names

Regions = Mapping[str, "np.ndarray | torch.Tensor"]


@dataclass(frozen=True)
class MotionMetricsConfig:
    """Which regions get DTW-PA (Procrustes per frame pair is the costly part), the solver, the batch size,
    and whose conventions root and measure the body (``mode``, see the module docstring)."""

    procrustes_regions: tuple[str, ...] = ("body", "left_hand", "right_hand")
    procrustes_method: str = "quaternion"
    batch_pairs: int = 16  # pairs per round of jobs; on a GPU (backend "torch") one batched PA call: raise it
    # Threads computing cost matrices concurrently (torch releases the GIL inside ops). With workers > 1 set
    # torch.set_num_threads(1): intra-op threads on top oversubscribe the cores, and on a shared machine an
    # OpenMP barrier waiting for a descheduled thread was measured 10-30x slower.
    workers: int = 1  # backend "torch" only; the numba kernels use every core of the process's affinity
    mode: Literal["m3t", "soke_exact"] = "m3t"
    backend: Literal["numba", "torch"] = "numba"  # who computes the cost matrices (see the module docstring)
    device: str = "cpu"  # backend "torch": where the cost matrices are computed, e.g. "cuda"
    # backend "numba": each point distance's square root in float32 (~1.5x faster DTW-JPE; costs within 9e-8
    # relative) or float64 (the torch backend's arithmetic); squares, sums and the DP are float64 either way.
    # auto: float32 in mode m3t, float64 in soke_exact (whose numbers match SOKE's arithmetic to 1e-9)
    root_precision: Literal["auto", "float32", "float64"] = "auto"

    def __post_init__(self) -> None:
        if self.mode not in ("m3t", "soke_exact"):
            raise ValueError(f"motion metric mode {self.mode!r} unknown; use 'm3t' (neck-rooted body, this "
                             "project's tables) or 'soke_exact' (SOKE's pelvis-rooted body, needs SMPL-FX)")
        if self.backend not in ("numba", "torch"):
            raise ValueError(f"motion metric backend {self.backend!r} unknown; use 'numba' (fused CPU kernels) or "
                             "'torch' (cost matrices on any torch device)")
        if self.root_precision not in ("auto", "float32", "float64"):
            raise ValueError(f"motion metric root_precision {self.root_precision!r} unknown; use 'auto' (the "
                             "default), 'float32' or 'float64'")
        if self.backend == "numba" and torch.device(self.device).type != "cpu":
            raise ValueError(f"motion metric device {self.device!r} needs backend 'torch'; the numba kernels run on "
                             "the CPU")


    @property
    def root(self) -> str:
        """The square roots' precision in effect: ``root_precision`` with ``auto`` resolved by the mode."""
        if self.root_precision != "auto":
            return self.root_precision
        return "float64" if self.mode == "soke_exact" else "float32"


def error_name(region: str, procrustes: bool) -> str:
    """Metric stem of a region: ``dtw_jpe_body``, ``dtw_pa_jpe_left_hand``, ``dtw_vpe_face``, ..."""
    error = "vpe" if region == "face" else "jpe"
    return f"dtw_{'pa_' if procrustes else ''}{error}_{region}"


def _region_tensor(value: object, side: str, region: str, index: int) -> torch.Tensor:
    where = f"pair {index}, region {region!r}, {side}"
    try:
        tensor = torch.as_tensor(value if isinstance(value, torch.Tensor) else np.asarray(value), dtype=torch.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: cannot read as a float array ({exc})") from exc
    if tensor.ndim != 3 or tensor.shape[-1] != 3:
        raise ValueError(f"{where}: shape {tuple(tensor.shape)}, expected (T, K, 3) points in metres")
    if tensor.shape[0] == 0 or tensor.shape[1] == 0:
        raise ValueError(f"{where}: empty sequence of shape {tuple(tensor.shape)}; drop the pair or fix its frames")
    if not bool(torch.isfinite(tensor).all()):
        bad = int((~torch.isfinite(tensor)).any(-1).any(-1).nonzero()[0, 0])
        raise ValueError(f"{where}: non-finite values (first in frame {bad}) in shape {tuple(tensor.shape)}")
    return tensor


def _measured(region: str, config: MotionMetricsConfig) -> slice | None:
    """The points a region's distances average over (None: all of them)."""
    return BODY_MEASURED if config.mode == "soke_exact" and region == "body" else None


def _validated(pred: Regions, gt: Regions, index: int,
               config: MotionMetricsConfig) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """{region: (pred (T1, K, 3), gt (T2, K, 3))} float64, after checking both sides agree."""
    if set(pred) != set(gt):
        only_pred, only_gt = sorted(set(pred) - set(gt)), sorted(set(gt) - set(pred))
        raise ValueError(f"pair {index}: regions differ, only in prediction {only_pred}, only in ground truth "
                         f"{only_gt}; give both sides the same regions")
    if not pred:
        raise ValueError(f"pair {index}: no regions given; expected e.g. body, left_hand, right_hand, face")
    out = {}
    for region in pred:
        p = _region_tensor(pred[region], "prediction", region, index)
        g = _region_tensor(gt[region], "ground truth", region, index)
        if p.shape[1] != g.shape[1]:
            raise ValueError(f"pair {index}, region {region!r}: prediction {tuple(p.shape)} and ground truth "
                             f"{tuple(g.shape)} have different point counts; use the same metric set on both")
        measured = _measured(region, config)
        if measured is not None and p.shape[1] < measured.stop:
            raise ValueError(f"pair {index}, region {region!r}: {p.shape[1]} points, but motion metric mode "
                             f"'soke_exact' expects SOKE's layout of at least {measured.stop}: the root first, then "
                             "the 12 measured points, then the further points its Procrustes fits; pose them with "
                             "MotionScorer in that mode (body.model: smplfx) or score with mode 'm3t'")
        out[region] = (p, g)
    return out


def _add_hand_means(metrics: dict[str, float]) -> None:
    """``..._hand_...`` = mean of the left- and right-hand entries, for every metric both hands have."""
    for name in [n for n in metrics if "_left_hand_" in n]:
        right = name.replace("_left_hand_", "_right_hand_")
        if right in metrics:
            metrics[name.replace("_left_hand_", "_hand_")] = 0.5 * (metrics[name] + metrics[right])


Job = tuple[int, str, bool]  # (pair, region, procrustes)
GPU_CHUNK_PAIRS = 1 << 24  # frame pairs per batched PA call on a GPU: few, large launches
GPU_RESIDUAL_ELEMENTS = 1 << 26  # aligned residual entries at once on a GPU (512 MB in float64)


def _kernels():
    """:mod:`m3t.metrics.kernels`, imported on first use; a missing numba is named with its fix."""
    try:
        from m3t.metrics import kernels
    except ImportError as exc:
        if exc.name != "numba":
            raise
        raise ImportError("motion metric backend 'numba' needs the numba package: pip install numba (a dependency "
                          "of m3t-platform), or score with MotionMetricsConfig(backend='torch')") from exc
    return kernels


def _numba_dtw(checked: list[dict[str, tuple[torch.Tensor, torch.Tensor]]], jobs: list[Job],
               config: MotionMetricsConfig) -> list[DTWResult]:
    kernels = _kernels()
    return kernels.dtw_jobs([kernels.CostJob(checked[n][region][0].numpy(), checked[n][region][1].numpy(), pa,
                                             _measured(region, config)) for n, region, pa in jobs],
                            root_precision=config.root)


def _batched_pa(checked: list[dict[str, tuple[torch.Tensor, torch.Tensor]]], jobs: list[Job],
                config: MotionMetricsConfig) -> dict[int, torch.Tensor]:
    """{job: (T1, T2) PA cost} of the PA jobs, one zero-padded batched call per region on ``config.device``."""
    out = {}
    for region in sorted({r for _, r, pa in jobs if pa}):
        picked = [b for b, (_, r, pa) in enumerate(jobs) if pa and r == region]
        sides = [checked[jobs[b][0]][region] for b in picked]
        pred = torch.nn.utils.rnn.pad_sequence([p for p, _ in sides], batch_first=True).to(config.device)
        gt = torch.nn.utils.rnn.pad_sequence([g for _, g in sides], batch_first=True).to(config.device)
        costs = pa_distance_matrices(pred, gt, config.procrustes_method, GPU_CHUNK_PAIRS, _measured(region, config),
                                     GPU_RESIDUAL_ELEMENTS).cpu()
        out.update({b: costs[m, :p.shape[0], :g.shape[0]] for m, (b, (p, g)) in enumerate(zip(picked, sides))})
    return out


def _torch_dtw(checked: list[dict[str, tuple[torch.Tensor, torch.Tensor]]], jobs: list[Job],
               config: MotionMetricsConfig) -> list[DTWResult]:
    """Cost matrices by torch on ``config.device``, DTW by the numba kernel (numpy sweep without numba)."""
    on_cpu = torch.device(config.device).type == "cpu"
    costs = {} if on_cpu else _batched_pa(checked, jobs, config)  # {job: (T1, T2) CPU tensor}

    def fill(b: int) -> None:
        n, region, pa = jobs[b]
        p, g = (side.to(config.device) for side in checked[n][region])
        measure = _measured(region, config)
        costs[b] = (pa_distance_matrix(p, g, config.procrustes_method, measure=measure) if pa
                    else jpe_distance_matrix(p, g, measure=measure)).cpu()  # each job owns its key

    todo = [b for b in range(len(jobs)) if b not in costs]
    if config.workers > 1:
        with ThreadPoolExecutor(config.workers) as pool:
            list(pool.map(fill, todo))
    else:
        for b in todo:
            fill(b)
    try:
        kernels = _kernels()
    except ImportError:  # the numpy sweep gives the same costs and paths, ~10x slower
        return dtw_batch([costs[b] for b in range(len(jobs))])
    return kernels.dtw_costs([costs[b].numpy() for b in range(len(jobs))])


def evaluate_pairs(pairs: Sequence[tuple[Regions, Regions]], progress: bool = False,
                   config: MotionMetricsConfig = MotionMetricsConfig()) -> list[dict[str, float]]:
    """DTW metrics of many (prediction, ground truth) pairs, each a dict of region -> (T, K, 3) metres.

    Pairs are validated first (a bad one raises ``ValueError`` naming it before any work), then processed in
    batches of ``config.batch_pairs`` of similar length (their jobs run in parallel; on a GPU their zero-padded
    PA matrices are one call). Returns one metrics dict per pair, in input order.
    """
    checked = [_validated(p, g, n, config) for n, (p, g) in enumerate(pairs)]
    results: list[dict[str, float]] = [{} for _ in checked]
    # Similar lengths together keep the zero padding of each batch small.
    order = sorted(range(len(checked)), key=lambda n: max(p.shape[0] + g.shape[0] for p, g in checked[n].values()))
    with tqdm(total=len(checked), desc="dtw", unit="pair", disable=not progress) as bar:
        for start in range(0, len(order), config.batch_pairs):
            batch = order[start:start + config.batch_pairs]
            jobs = [(n, region, pa) for n in batch for region in checked[n]
                    for pa in ((False, True) if region in config.procrustes_regions else (False,))]
            dtw = _numba_dtw if config.backend == "numba" else _torch_dtw
            for (n, region, pa), res in zip(jobs, dtw(checked, jobs, config)):
                stem = error_name(region, pa)
                results[n][f"{stem}_m"] = res.cost_raw
                results[n][f"{stem}_pathnorm_m"] = res.cost_pathnorm
            bar.update(len(batch))
    for metrics in results:
        _add_hand_means(metrics)
        if config.mode == "soke_exact":
            metrics.update(soke_names(metrics))
    return results


def sequence_metrics(pred: Regions, gt: Regions,
                     config: MotionMetricsConfig = MotionMetricsConfig()) -> dict[str, float]:
    """DTW metrics of one pair: pred {region: (T1, K, 3)} against gt {region: (T2, K, 3)}, metres."""
    return evaluate_pairs([(pred, gt)], config=config)[0]


def summarise(results: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Mean of every metric over pairs (all pairs must report the same metrics)."""
    if not results:
        raise ValueError("no per-pair metrics to summarise; evaluate at least one pair")
    names = list(results[0])
    for n, metrics in enumerate(results):
        if set(metrics) != set(names):
            raise ValueError(f"pair {n} reports {sorted(set(metrics) ^ set(names))} unlike pair 0; evaluate all pairs "
                             f"with the same regions and config")
    return {name: float(np.mean([m[name] for m in results])) for name in names}
