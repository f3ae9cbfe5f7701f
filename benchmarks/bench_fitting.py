"""Fitting benchmark: today's solver vs the fast solver, and one clip per fit vs a signer's clips in one batch.

Every arm fits the same clips of the embedded synthetic corpus (``data/corpus/synthetic``, written by the
``generate-corpus`` stage; tracks from the simulated tracker, as ``fit-corpus`` makes them) in this process,
with ``--threads`` torch threads, and is scored against the corpus' ground truth:

- ``old``: the first solver as it shipped: Adam, 200 + 100 steps (``fitting.solver: adam``), on the first sparse
  forward (skinning by gathering the 9 bone transforms of every point, forward kinematics over all 104 bones),
  reproduced here by :class:`GatherSkinningBody`;
- ``new``: the default solver (L-BFGS with a convergence test, ``params.yaml`` ``fitting``) on the current
  sparse forward (dense skinning over the bones that move a landmark, kinematics over their chains only);
- ``new_signer_batch``: the same solver, a signer's clips packed into one batch with one shared identity
  (:func:`m3t.fitting.fit.fit_tracks`), batches of at most ``--batch-frames`` frames;
- ``new_lockstep``: the same batches, every clip its own L-BFGS and identity in lock-step
  (``fitting.solver: lbfgs_lockstep``, :mod:`m3t.fitting.lockstep`), one objective evaluation per batch;
- ``new_batched``: the same batches, every clip fitted by exactly the default algorithm on its own (its own
  ``torch.optim.LBFGS``, line searches, convergence test and identity), one objective evaluation per batch
  (``fitting.solver: lbfgs_batched``, :func:`m3t.fitting.lbfgs.minimise_batched`);
- ``new_budget``: the default solver per clip with a budget of ``--budget-iterations`` evaluations instead of
  ``fitting.iterations`` (the speed / accuracy trade-off of that one setting; 0 skips the arm).

Reported per arm: frames/s of the whole fit (camera stage included), the mean PA joint error (mm) and
reprojection error (px) over the clips, and for the batched arm the spread of the identity across a signer's
clips (per-clip fits give each clip its own). Ratios new/old come from the same run (the machine is noisy).
``--arms`` picks the CPU arms (``old`` is the baseline of every ratio).

With ``--device cuda`` (when present), the GPU sweep: signer batches on the GPU over ``--gpu-clips`` clips (0 =
the whole corpus; lock-step and batched batches mix signers), for every solver of ``--gpu-solvers`` x batch cap of ``--gpu-batch-frames`` x budget of
``--gpu-iterations``, with TF32
matrix products off and (``--gpu-tf32``) on, in this process and in ``--gpu-workers`` spawned processes sharing
the GPU (each builds its body model once, outside the timing); frames/s, PA and reprojection error per arm, and
the fastest arm whose errors are no worse than the CPU per-clip fits of the same clips on every core of this
machine (or those of an earlier result JSON, ``--gpu-reference``).

    python benchmarks/bench_fitting.py [--clips 12] [--threads 1] [--batch-frames 1024] [--budget-iterations 150]
                                      [--arms old,new,new_signer_batch,new_lockstep,new_batched,new_budget]
                                      [--device cuda]
                                      [--gpu-solvers lbfgs,lbfgs_lockstep,lbfgs_batched]
                                      [--gpu-clips 0] [--gpu-batch-frames 2048,8192] [--gpu-iterations 100,200]
                                      [--gpu-workers 3] [--out benchmarks/results/fitting.json]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from report import write_and_log  # noqa: E402

from m3t.body.anny_body import AnnyBody  # noqa: E402
from m3t.body.protocol import KeypointIndex  # noqa: E402
from m3t.config import load_params  # noqa: E402
from m3t.corpora.synthetic_storage import SyntheticCorpus  # noqa: E402
from m3t.fitting.evaluate import ground_truth_errors  # noqa: E402
from m3t.fitting.fit import fit_track, fit_tracks  # noqa: E402
from m3t.body.protocol import as_tensors  # noqa: E402
from m3t.trackers.simulated import simulate_track  # noqa: E402


class GatherSkinningBody(AnnyBody):
    """Anny with the first sparse forward: every point gathers its 9 bones' 4 x 4 transforms, over all bones."""

    def forward_keypoints(self, params, identity, keypoints: KeypointIndex) -> torch.Tensor:
        coeffs = self._identity_coeffs(identity)
        transforms, poses = self._bone_transforms(params, self._rest_bones(coeffs))
        vidx = keypoints.vertex_index
        rest = self.template[vidx] + torch.einsum("bn,nkc->bkc", coeffs, self.pheno_bs[:, vidx])
        rest = rest + torch.einsum("bf,fkc->bkc", params["face"], self.face_bs[:, vidx])
        skinned = self._skin(rest, transforms, self.skin_bones[vidx], self.skin_weights[vidx])
        joints = poses[:, keypoints.joint_index, :3, 3]
        out = torch.where(keypoints.is_vertex[None, :, None], skinned, joints)
        return out * keypoints.valid[None, :, None]


def scored(body, results, truths) -> dict[str, float]:
    pa, reproj = [], []
    for result, (params, identity, camera) in zip(results, truths):
        errors = ground_truth_errors(body, result.params, result.identity, result.camera, params, identity,
                                     camera.as_dict())
        pa.append(errors["pa_joint_mm"])
        reproj.append(result.metrics["reproj_px"])
    return {"pa_joint_mm": float(np.mean(pa)), "reproj_px": float(np.mean(reproj))}


def batches(clips, tracks, max_frames: int, by_signer: bool = True) -> list[list[int]]:
    """Indices of clips grouped by signer (or all together: lock-step batches need no shared identity), each
    group cut into batches of at most ``max_frames`` frames."""
    by_signer_groups = defaultdict(list)
    for i, clip in enumerate(clips):
        by_signer_groups[clip.signer if by_signer else ""].append(i)
    out = []
    for members in by_signer_groups.values():
        current, frames = [], 0
        for i in members:
            if current and frames + tracks[i].num_frames > max_frames:
                out.append(current)
                current, frames = [], 0
            current.append(i)
            frames += tracks[i].num_frames
        out.append(current)
    return out


_WORKER_BODY: list = []  # the body model of a worker process, built once


def _worker_fit(tracks: list, cfg) -> list:
    """One batch in a worker process (signer batch; a one-clip batch is a per-clip fit)."""
    if not _WORKER_BODY:
        _WORKER_BODY.append(AnnyBody())
    return fit_tracks(tracks, _WORKER_BODY[0], cfg)


def pooled(pool, groups: list[list[int]], tracks, cfg) -> list:
    """``groups`` fitted on ``pool`` (largest first, so the last batch to finish is a short one), in clip order."""
    order = sorted(range(len(groups)), key=lambda g: -sum(tracks[i].num_frames for i in groups[g]))
    futures = {g: pool.submit(_worker_fit, [tracks[i] for i in groups[g]], cfg) for g in order}
    out = [None] * len(tracks)
    for g, future in futures.items():
        for i, r in zip(groups[g], future.result()):
            out[i] = r
    return out


def gpu_sweep(args, params, new_cfg, body, listing, corpus) -> dict:
    """The GPU arms (module docstring) on ``--gpu-clips`` clips; the CPU per-clip fits of the same clips on
    every core of this machine as the reference of speed and error."""
    import os

    from m3t.fitting.cluster import process_pool

    clips = list(listing.clips)[: args.gpu_clips or None]
    truths = [corpus.ground_truth(c) for c in clips]
    tracks = [simulate_track(c.id, as_tensors(p), torch.as_tensor(i), cam, c.fps, body, params.tracker)
              for c, (p, i, cam) in zip(clips, truths)]
    frames = sum(t.num_frames for t in tracks)
    on_gpu = torch.device(args.device).type == "cuda"
    out: dict = {"gpu_device": torch.cuda.get_device_name(args.device) if on_gpu else args.device, "gpu_clips": len(clips), "gpu_frames": frames,
                 "gpu_signers": len({c.signer for c in clips}), "gpu_cpu_count": os.cpu_count()}

    def record(name: str, results: list, seconds: float, **extra) -> None:
        arm = {"frames_per_s": frames / seconds, "seconds": seconds,
               "evaluations_mean": float(np.mean([len(r.loss_curve) for r in results])),
               **scored(body, results, truths), **extra}
        out[name] = arm
        print(name, {k: round(v, 3) if isinstance(v, float) else v for k, v in arm.items()}, flush=True)

    cores = os.cpu_count() or 1
    if args.gpu_reference:  # the per-clip fits of an earlier run on these clips (same corpus, same settings)
        earlier = json.loads(Path(args.gpu_reference).read_text())
        if (earlier.get("gpu_clips"), earlier.get("gpu_frames")) != (len(clips), frames):
            raise SystemExit(f"{args.gpu_reference}: its reference fitted {earlier.get('gpu_clips')} clips / "
                             f"{earlier.get('gpu_frames')} frames, this sweep {len(clips)} / {frames}")
        out["gpu_reference_cpu_per_clip"] = {**earlier["gpu_reference_cpu_per_clip"], "from": args.gpu_reference}
    else:
        pool = process_pool(cores)
        try:
            pooled(pool, [[i] for i in range(min(cores, len(clips)))], tracks,
                   dataclasses.replace(new_cfg, iterations=3))
            start = time.perf_counter()
            reference = pooled(pool, [[i] for i in range(len(clips))], tracks, new_cfg)
            record("gpu_reference_cpu_per_clip", reference, time.perf_counter() - start, workers=cores)
        finally:
            pool.shutdown()
    ref = out["gpu_reference_cpu_per_clip"]
    gpu_cfg = dataclasses.replace(new_cfg, device=args.device)
    gpu_body = AnnyBody().to(args.device)  # its own buffers: ``body`` stays on the CPU for scoring
    arms = []
    for solver, cap in ((solver, cap) for solver in args.gpu_solvers for cap in args.gpu_batch_frames):
        groups = batches(clips, tracks, cap, by_signer=solver == "lbfgs")
        for iterations in args.gpu_iterations:
            for tf32 in (False, True) if args.gpu_tf32 else (False,):
                cfg = dataclasses.replace(gpu_cfg, iterations=iterations, solver=solver)
                torch.backends.cuda.matmul.allow_tf32 = tf32
                fit_tracks([tracks[i] for i in groups[0]], gpu_body, dataclasses.replace(cfg, iterations=3))  # warm-up
                if on_gpu:
                    torch.cuda.synchronize()
                start = time.perf_counter()
                results = [None] * len(tracks)
                for group in groups:
                    for i, r in zip(group, fit_tracks([tracks[i] for i in group], gpu_body, cfg)):
                        results[i] = r
                name = f"gpu_{solver}_b{cap}_it{iterations}" + ("_tf32" if tf32 else "")
                record(name, results, time.perf_counter() - start, batches=len(groups), tf32=tf32, workers=1)
                arms.append(name)
    torch.backends.cuda.matmul.allow_tf32 = False
    if args.gpu_workers > 1:
        for solver, cap in ((solver, cap) for solver in args.gpu_solvers for cap in args.gpu_batch_frames):
            groups = batches(clips, tracks, cap, by_signer=solver == "lbfgs")
            for iterations in args.gpu_iterations:
                cfg = dataclasses.replace(gpu_cfg, iterations=iterations, solver=solver)
                pool = process_pool(args.gpu_workers)
                try:
                    pooled(pool, groups[: args.gpu_workers], tracks, dataclasses.replace(cfg, iterations=3))
                    start = time.perf_counter()
                    results = pooled(pool, groups, tracks, cfg)
                    seconds = time.perf_counter() - start
                finally:
                    pool.shutdown()
                name = f"gpu_{solver}_b{cap}_it{iterations}_w{args.gpu_workers}"
                record(name, results, seconds, batches=len(groups), tf32=False, workers=args.gpu_workers)
                arms.append(name)
    good = [a for a in arms if out[a]["pa_joint_mm"] <= ref["pa_joint_mm"] and out[a]["reproj_px"] <= ref["reproj_px"]]
    best = max(good or arms, key=lambda a: out[a]["frames_per_s"])
    out.update({"gpu_best_arm": best, "gpu_best_arm_no_worse_than_cpu_per_clip": bool(good),
                "gpu_best_frames_per_s": out[best]["frames_per_s"],
                "gpu_best_speedup_vs_cpu_all_cores": out[best]["frames_per_s"] / ref["frames_per_s"],
                "gpu_goal_frames_per_s": 1000.0, "gpu_goal_met": out[best]["frames_per_s"] >= 1000.0})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=12)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch-frames", type=int, default=1024)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--iterations", type=int, default=0, help="the new solver's budget (0: params.yaml)")
    parser.add_argument("--budget-iterations", type=int, default=150, help="budget of the new_budget arm (0: none)")
    parser.add_argument("--arms", default="old,new,new_signer_batch,new_lockstep,new_batched,new_budget",
                        help="CPU arms to run (comma-separated; old is every ratio's baseline)")
    parser.add_argument("--gpu-clips", type=int, default=0, help="clips of the GPU sweep (0: the whole corpus)")
    parser.add_argument("--gpu-batch-frames", default="2048,8192", help="batch caps of the GPU sweep")
    parser.add_argument("--gpu-iterations", default="100,200", help="evaluation budgets of the GPU sweep")
    parser.add_argument("--gpu-tf32", action="store_true", help="also every GPU arm with TF32 matrix products")
    parser.add_argument("--gpu-workers", type=int, default=3, help="processes sharing the GPU (1: none)")
    parser.add_argument("--gpu-solvers", default="lbfgs,lbfgs_lockstep,lbfgs_batched",
                        help="fitting.solver values of the sweep")
    parser.add_argument("--gpu-reference", default="",
                        help="a result JSON whose CPU per-clip reference of the same clips to reuse (skips it)")
    parser.add_argument("--out", default="benchmarks/results/fitting.json")
    args = parser.parse_args()
    args.gpu_batch_frames = [int(v) for v in args.gpu_batch_frames.split(",")]
    args.gpu_iterations = [int(v) for v in args.gpu_iterations.split(",")]
    args.gpu_solvers = args.gpu_solvers.split(",")
    wanted = set(args.arms.split(","))
    torch.set_num_threads(args.threads)
    params = load_params()
    root = Path(params.corpora["synthetic"].root)
    if not (root / "clips.jsonl").exists():
        raise SystemExit(f"no synthetic corpus under {root}: run `dvc repro generate-corpus` first")
    corpus = SyntheticCorpus(root)
    from m3t.corpora.base import open_corpus

    listing = open_corpus("synthetic", root).listing()
    # clips of several signers, in listing order
    clips = list(listing.clips)[: args.clips]
    new_body, old_body = AnnyBody(), GatherSkinningBody()
    truths = [corpus.ground_truth(c) for c in clips]
    tracks = [simulate_track(c.id, as_tensors(p), torch.as_tensor(i), cam, c.fps, new_body, params.tracker)
              for c, (p, i, cam) in zip(clips, truths)]
    frames = sum(t.num_frames for t in tracks)
    new_cfg = dataclasses.replace(params.fitting, solver="lbfgs",  # per clip; the batched arms set their own
                                  **({"iterations": args.iterations} if args.iterations else {}))
    old_cfg = dataclasses.replace(new_cfg, solver="adam", iterations=200, camera_iterations=100)
    fit_track(tracks[0], new_body, dataclasses.replace(new_cfg, iterations=3))  # warm-up

    def timed(fn):
        start = time.perf_counter()
        out = fn()
        return out, time.perf_counter() - start

    groups = batches(clips, tracks, args.batch_frames)

    def batched(cfg):
        out = [None] * len(tracks)
        for group in groups:
            for i, r in zip(group, fit_tracks([tracks[i] for i in group], new_body, cfg)):
                out[i] = r
        return out

    budget_cfg = dataclasses.replace(new_cfg, iterations=args.budget_iterations)
    runs = {"old": lambda: [fit_track(t, old_body, old_cfg) for t in tracks],
            "new": lambda: [fit_track(t, new_body, new_cfg) for t in tracks],
            "new_signer_batch": lambda: batched(new_cfg),
            "new_lockstep": lambda: batched(dataclasses.replace(new_cfg, solver="lbfgs_lockstep")),
            "new_batched": lambda: batched(dataclasses.replace(new_cfg, solver="lbfgs_batched")),
            "new_budget": lambda: [fit_track(t, new_body, budget_cfg) for t in tracks]}
    if not args.budget_iterations:
        wanted.discard("new_budget")
    arms = [(name, *timed(run)) for name, run in runs.items() if name in wanted]
    result = {"clips": len(clips), "frames": frames, "signers": len({c.signer for c in clips}),
              "batches": len(groups), "batch_frames": args.batch_frames, "threads": torch.get_num_threads(),
              "old_solver": "adam 200 + 100 steps, gather skinning over all bones",
              "new_solver": f"{new_cfg.solver} <= {new_cfg.iterations} + {new_cfg.camera_iterations} evaluations, "
                            f"tolerance {new_cfg.tolerance}, history {new_cfg.lbfgs_history}"}
    for name, results, seconds in arms:
        result[f"{name}_seconds"] = seconds
        result[f"{name}_frames_per_s"] = frames / seconds
        result[f"{name}_evaluations_mean"] = float(np.mean([len(r.loss_curve) for r in results]))
        result.update({f"{name}_{k}": v for k, v in scored(new_body, results, truths).items()})
    for name, _, _ in arms:
        if name == "old" or "old" not in wanted:
            continue
        result[f"speedup_{name}_vs_old"] = result[f"{name}_frames_per_s"] / result["old_frames_per_s"]
        result[f"goal_5x_no_worse_met_{name}"] = bool(
            result[f"speedup_{name}_vs_old"] >= 5.0 and result[f"{name}_pa_joint_mm"] <= result["old_pa_joint_mm"]
            and result[f"{name}_reproj_px"] <= result["old_reproj_px"])
    if "new_budget" in wanted:
        result["new_budget_iterations"] = args.budget_iterations
    fitted = {name: results for name, results, _ in arms}
    if {"new", "new_signer_batch"} <= fitted.keys():
        true_ident = {c.signer: i for c, (_, i, _) in zip(clips, truths)}
        spread_clip, spread_batch, err_clip, err_batch = [], [], [], []
        for signer in true_ident:
            members = [i for i, c in enumerate(clips) if c.signer == signer]
            ids_clip = np.stack([fitted["new"][i].identity for i in members])
            ids_batch = np.stack([fitted["new_signer_batch"][i].identity for i in members])
            spread_clip.append(float(ids_clip.std(0).mean()))
            spread_batch.append(float(ids_batch.std(0).mean()))
            err_clip.append(float(np.abs(ids_clip - true_ident[signer]).mean()))
            err_batch.append(float(np.abs(ids_batch - true_ident[signer]).mean()))
        result.update({"identity_spread_per_clip_fits": float(np.mean(spread_clip)),
                       "identity_spread_signer_batches": float(np.mean(spread_batch)),
                       "identity_abs_error_per_clip_fits": float(np.mean(err_clip)),
                       "identity_abs_error_signer_batches": float(np.mean(err_batch))})
    result.update({"machine": platform.machine(), "torch": torch.__version__})
    if args.device != "cpu":
        if torch.cuda.is_available():
            result.update(gpu_sweep(args, params, new_cfg, new_body, listing, corpus))
        else:
            result["gpu"] = f"not measured: device {args.device!r} unavailable"
    write_and_log(result, args.out, "benchmark-fitting")


if __name__ == "__main__":
    main()
