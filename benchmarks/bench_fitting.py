"""Fitting benchmark: sparse-keypoint forward vs full-mesh forward, same fit, same run.

Both arms fit the same simulated clip with the same seed and config; the only difference is how the
landmarks are computed each iteration: the body model's sparse keypoint forward (blendshapes + skinning
for the ~540 landmark points only) or the full forward (all 13,718 vertices and every joint) followed by
indexing. Reports seconds per iteration, the speed-up ratio (goal >= 20x), frames/s of the whole fit, and
the final errors of both arms (they must agree: the sparse forward is exact, not an approximation).

    python benchmarks/bench_fitting.py [--frames 50] [--iterations 30] [--repeats 3] [--out benchmarks/results/fitting.json]

The two arms alternate ``--repeats`` times and each keeps its fastest repeat (the machine is noisy).
"""
from __future__ import annotations

import argparse
import dataclasses
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from m3t.body.anny_body import AnnyBody  # noqa: E402
from m3t.body.protocol import KeypointIndex  # noqa: E402
from m3t.fitting.fit import FittingConfig, fit_track  # noqa: E402
from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track  # noqa: E402
from report import write_and_log  # noqa: E402
from test_fitting import front_camera, smooth_motion  # noqa: E402


class FullMeshBody(AnnyBody):
    """Anny whose keypoint forward runs the full-mesh forward and then picks the landmarks."""

    def forward_keypoints(self, params, identity, keypoints: KeypointIndex) -> torch.Tensor:
        out = self.forward(params, identity)
        vertices = out.vertices[:, keypoints.vertex_index]
        joints = out.joints[:, keypoints.joint_index]
        points = torch.where(keypoints.is_vertex[None, :, None], vertices, joints)
        return points * keypoints.valid[None, :, None]


def timed_fit(body, track, cfg):
    start = time.perf_counter()
    result = fit_track(track, body, cfg)
    return result, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--iterations", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="benchmarks/results/fitting.json")
    args = parser.parse_args()
    torch.manual_seed(0)
    sparse_body, full_body = AnnyBody(), FullMeshBody()
    params = smooth_motion(sparse_body, frames=args.frames)
    identity = torch.tensor([0.4, 0.5, 0.5, 0.45, 0.6, 0.5])
    track = simulate_track("bench", params, identity, front_camera(), 25.0, sparse_body, SimulatedTrackerConfig(seed=1))
    cfg = FittingConfig(iterations=args.iterations, camera_iterations=0)
    fit_track(track, sparse_body, dataclasses.replace(cfg, iterations=2))  # warm-up
    t_sparse = t_full = float("inf")
    for _ in range(args.repeats):
        sparse, t = timed_fit(sparse_body, track, cfg)
        t_sparse = min(t_sparse, t)
        full, t = timed_fit(full_body, track, cfg)
        t_full = min(t_full, t)
    per_it_sparse, per_it_full = t_sparse / args.iterations, t_full / args.iterations
    max_param_diff = max(float(np.abs(sparse.params[k] - full.params[k]).max()) for k in sparse.params)
    result = {
        "frames": args.frames,
        "iterations": args.iterations,
        "repeats": args.repeats,
        "landmarks": int(track.keypoints.shape[1]),
        "vertices": int(sparse_body.template.shape[0]),
        "sparse_s_per_iteration": per_it_sparse,
        "full_s_per_iteration": per_it_full,
        "speedup_sparse_vs_full": per_it_full / per_it_sparse,
        "sparse_frame_iterations_per_s": args.frames / per_it_sparse,
        "sparse_reproj_px": sparse.metrics["reproj_px"],
        "full_reproj_px": full.metrics["reproj_px"],
        "max_param_difference": max_param_diff,
        "torch_threads": torch.get_num_threads(),
        "machine": platform.machine(),
        "torch": torch.__version__,
    }
    write_and_log(result, args.out, "benchmark-fitting")

if __name__ == "__main__":
    main()
