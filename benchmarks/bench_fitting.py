"""Fitting benchmark: today's solver vs the fast solver, and one clip per fit vs a signer's clips in one batch.

Every arm fits the same clips of the embedded synthetic corpus (``data/corpus/synthetic``, written by the
``synthetic-corpus`` stage; tracks from the simulated tracker, as ``fit-corpus`` makes them) in this process,
with ``--threads`` torch threads, and is scored against the corpus' ground truth:

- ``old``: the first solver as it shipped: Adam, 200 + 100 steps (``fitting.solver: adam``), on the first sparse
  forward (skinning by gathering the 9 bone transforms of every point, forward kinematics over all 104 bones),
  reproduced here by :class:`GatherSkinningBody`;
- ``new``: the default solver (L-BFGS with a convergence test, ``params.yaml`` ``fitting``) on the current
  sparse forward (dense skinning over the bones that move a landmark, kinematics over their chains only);
- ``new_signer_batch``: the same solver, a signer's clips packed into one batch with one shared identity
  (:func:`m3t.fitting.fit.fit_tracks`), batches of at most ``--batch-frames`` frames;
- ``new_budget``: the default solver per clip with a budget of ``--budget-iterations`` evaluations instead of
  ``fitting.iterations`` (the speed / accuracy trade-off of that one setting; 0 skips the arm).

Reported per arm: frames/s of the whole fit (camera stage included), the mean PA joint error (mm) and
reprojection error (px) over the clips, and for the batched arm the spread of the identity across a signer's
clips (per-clip fits give each clip its own). Ratios new/old come from the same run (the machine is noisy).
With ``--device cuda`` (when present) the batched arm also runs on the GPU.

    python benchmarks/bench_fitting.py [--clips 12] [--threads 1] [--batch-frames 1024] [--budget-iterations 150]
                                      [--out benchmarks/results/fitting.json]
"""
from __future__ import annotations

import argparse
import dataclasses
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
from m3t.corpora.synthetic import SyntheticCorpus  # noqa: E402
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


def batches(clips, tracks, max_frames: int) -> list[list[int]]:
    """Indices of clips grouped by signer, each group cut into batches of at most ``max_frames`` frames."""
    by_signer = defaultdict(list)
    for i, clip in enumerate(clips):
        by_signer[clip.signer].append(i)
    out = []
    for members in by_signer.values():
        current, frames = [], 0
        for i in members:
            if current and frames + tracks[i].num_frames > max_frames:
                out.append(current)
                current, frames = [], 0
            current.append(i)
            frames += tracks[i].num_frames
        out.append(current)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=12)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch-frames", type=int, default=1024)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--iterations", type=int, default=0, help="the new solver's budget (0: params.yaml)")
    parser.add_argument("--budget-iterations", type=int, default=150, help="budget of the new_budget arm (0: none)")
    parser.add_argument("--out", default="benchmarks/results/fitting.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    params = load_params()
    root = Path(params.corpora["synthetic"].root)
    if not (root / "clips.jsonl").exists():
        raise SystemExit(f"no synthetic corpus under {root}: run `dvc repro synthetic-corpus` first")
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
    new_cfg = dataclasses.replace(params.fitting, **({"iterations": args.iterations} if args.iterations else {}))
    old_cfg = dataclasses.replace(new_cfg, solver="adam", iterations=200, camera_iterations=100)
    fit_track(tracks[0], new_body, dataclasses.replace(new_cfg, iterations=3))  # warm-up

    def timed(fn):
        start = time.perf_counter()
        out = fn()
        return out, time.perf_counter() - start

    old, t_old = timed(lambda: [fit_track(t, old_body, old_cfg) for t in tracks])
    new, t_new = timed(lambda: [fit_track(t, new_body, new_cfg) for t in tracks])
    groups = batches(clips, tracks, args.batch_frames)

    def batched(cfg):
        out = [None] * len(tracks)
        for group in groups:
            for i, r in zip(group, fit_tracks([tracks[i] for i in group], new_body, cfg)):
                out[i] = r
        return out

    batch, t_batch = timed(lambda: batched(new_cfg))
    arms = [("old", old, t_old), ("new", new, t_new), ("new_signer_batch", batch, t_batch)]
    if args.budget_iterations:
        budget_cfg = dataclasses.replace(new_cfg, iterations=args.budget_iterations)
        arms.append(("new_budget", *timed(lambda: [fit_track(t, new_body, budget_cfg) for t in tracks])))
    result = {"clips": len(clips), "frames": frames, "signers": len({c.signer for c in clips}),
              "batches": len(groups), "batch_frames": args.batch_frames, "threads": torch.get_num_threads(),
              "old_solver": "adam 200 + 100 steps, gather skinning over all bones",
              "new_solver": f"{new_cfg.solver} <= {new_cfg.iterations} + {new_cfg.camera_iterations} evaluations, "
                            f"tolerance {new_cfg.tolerance}"}
    for name, results, seconds in arms:
        result[f"{name}_seconds"] = seconds
        result[f"{name}_frames_per_s"] = frames / seconds
        result[f"{name}_evaluations_mean"] = float(np.mean([len(r.loss_curve) for r in results]))
        result.update({f"{name}_{k}": v for k, v in scored(new_body, results, truths).items()})
    for name, _, _ in arms[1:]:
        result[f"speedup_{name}_vs_old"] = result[f"{name}_frames_per_s"] / result["old_frames_per_s"]
        result[f"goal_5x_no_worse_met_{name}"] = bool(
            result[f"speedup_{name}_vs_old"] >= 5.0 and result[f"{name}_pa_joint_mm"] <= result["old_pa_joint_mm"]
            and result[f"{name}_reproj_px"] <= result["old_reproj_px"])
    if args.budget_iterations:
        result["new_budget_iterations"] = args.budget_iterations
    true_ident = {c.signer: i for c, (_, i, _) in zip(clips, truths)}
    spread_clip, spread_batch, err_clip, err_batch = [], [], [], []
    for signer in true_ident:
        members = [i for i, c in enumerate(clips) if c.signer == signer]
        ids_clip = np.stack([new[i].identity for i in members])
        ids_batch = np.stack([batch[i].identity for i in members])
        spread_clip.append(float(ids_clip.std(0).mean()))
        spread_batch.append(float(ids_batch.std(0).mean()))
        err_clip.append(float(np.abs(ids_clip - true_ident[signer]).mean()))
        err_batch.append(float(np.abs(ids_batch - true_ident[signer]).mean()))
    result.update({"identity_spread_per_clip_fits": float(np.mean(spread_clip)),
                   "identity_spread_signer_batches": float(np.mean(spread_batch)),
                   "identity_abs_error_per_clip_fits": float(np.mean(err_clip)),
                   "identity_abs_error_signer_batches": float(np.mean(err_batch)),
                   "machine": platform.machine(), "torch": torch.__version__})
    if args.device != "cpu" and torch.cuda.is_available():
        gpu_cfg = dataclasses.replace(new_cfg, device=args.device)
        batched(gpu_cfg)  # warm-up
        gpu, t_gpu = timed(lambda: batched(gpu_cfg))
        result["gpu_signer_batch_frames_per_s"] = frames / t_gpu
        result.update({f"gpu_signer_batch_{k}": v for k, v in scored(new_body, gpu, truths).items()})
        result["gpu_device"] = torch.cuda.get_device_name()
    write_and_log(result, args.out, "benchmark-fitting")


if __name__ == "__main__":
    main()
