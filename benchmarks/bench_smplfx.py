"""SMPL-FX benchmark: forward and forward + backward for a batch of frames, full mesh vs sparse keypoints,
against the ``smplx`` package's own SMPL-X layer on the same (synthetic) model file, in the same run.

The model files are the synthetic stand-ins of ``tests/smplfx_fixtures.py`` (same key structure and array
sizes as the licensed ones: 400 shape + expression directions, 486 pose correctives; the mesh has more
vertices than the real 10,475 + 520). Arms:

- ``smplfx_full``: :meth:`SMPLFXBody.forward` (all vertices and joints) from 6D parameters;
- ``smplfx_sparse``: :meth:`SMPLFXBody.forward_keypoints` on the MediaPipe-Holistic correspondence
  (what fitting evaluates every iteration);
- ``smplx_full``: ``smplx.SMPLXLayer`` (0.1.28) with the same rotations as matrices (6D -> matrix
  inside the timed region for both), 10 betas and 10 expressions.

Backward: the sum of the outputs, gradients to the pose parameters and the identity. The arms alternate
``--repeats`` times; each keeps its fastest repeat (the machine is noisy).

    python benchmarks/bench_smplfx.py [--batch 64] [--iterations 10] [--repeats 3] [--out benchmarks/results/smplfx.json]
"""
from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from m3t.body.rotations import sixd_to_matrix  # noqa: E402
from report import write_and_log  # noqa: E402
from smplfx_fixtures import fixture_body, make_fixture_files, smplfx_motion  # noqa: E402


def _leaf(params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.clone().requires_grad_(True) for k, v in params.items()}


def arm_smplfx_full(body, params, identity, backward: bool) -> float:
    p, ident = _leaf(params), identity.clone().requires_grad_(backward)
    start = time.perf_counter()
    out = body.forward(p, ident)
    if backward:
        (out.vertices.sum() + out.joints.sum()).backward()
    return time.perf_counter() - start


def arm_smplfx_sparse(body, params, identity, kpset, backward: bool) -> float:
    p, ident = _leaf(params), identity.clone().requires_grad_(backward)
    start = time.perf_counter()
    out = body.forward_keypoints(p, ident, kpset)
    if backward:
        out.sum().backward()
    return time.perf_counter() - start


def arm_smplx(layer, body_names, fx_labels, params, backward: bool) -> float:
    p = _leaf(params)
    B = params["body"].shape[0]
    betas = torch.zeros(B, 10, requires_grad=backward)
    start = time.perf_counter()
    body_rot = sixd_to_matrix(p["body"].reshape(B, -1, 6))
    full = torch.eye(3).expand(B, 21, 3, 3)
    index = torch.tensor([body_names.index(n) for n in fx_labels])
    full = full.index_copy(1, index, body_rot)
    out = layer(betas=betas, body_pose=full, jaw_pose=sixd_to_matrix(p["face"][:, 102:])[:, None],
                left_hand_pose=sixd_to_matrix(p["left_hand"].reshape(B, 15, 6)),
                right_hand_pose=sixd_to_matrix(p["right_hand"].reshape(B, 15, 6)),
                expression=p["face"][:, :10])
    if backward:
        (out.vertices.sum() + out.joints.sum()).backward()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="benchmarks/results/smplfx.json")
    args = parser.parse_args()
    import smplx

    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        paths = make_fixture_files(Path(tmp))
        build_start = time.perf_counter()
        body = fixture_body(paths)
        build_s = time.perf_counter() - build_start
        layer = smplx.SMPLXLayer(str(paths.smplx), num_betas=10, num_expression_coeffs=10)
    params = smplfx_motion(body, frames=args.batch)
    identity = torch.zeros(body.layout.identity_dim)
    kpset = body.keypoint_set(body.correspondence("mediapipe_holistic"))
    n_keypoints = int(kpset.valid.sum())
    body_names = ("left_hip right_hip spine1 left_knee right_knee spine2 left_ankle right_ankle spine3 left_foot "
                  "right_foot neck left_collar right_collar head left_shoulder right_shoulder left_elbow right_elbow "
                  "left_wrist right_wrist").split()
    arms = {
        "smplfx_full": lambda bw: arm_smplfx_full(body, params, identity, bw),
        "smplfx_sparse": lambda bw: arm_smplfx_sparse(body, params, identity, kpset, bw),
        "smplx_full": lambda bw: arm_smplx(layer, body_names, body.layout["body"].labels, params, bw),
    }
    best = {f"{name}_{mode}": float("inf") for name in arms for mode in ("forward", "forward_backward")}
    for fn in arms.values():  # warm-up
        fn(False)
        fn(True)
    for _ in range(args.repeats):
        for name, fn in arms.items():  # alternate arms inside each repeat
            for mode, bw in (("forward", False), ("forward_backward", True)):
                if bw:
                    total = sum(fn(True) for _ in range(args.iterations))
                else:
                    with torch.no_grad():
                        total = sum(fn(False) for _ in range(args.iterations))
                best[f"{name}_{mode}"] = min(best[f"{name}_{mode}"], total / args.iterations)
    result = {
        "batch_frames": args.batch,
        "iterations": args.iterations,
        "repeats": args.repeats,
        "vertices_smplfx": int(body.template.shape[0]),
        "vertices_smplx": int(layer.v_template.shape[0]),
        "sparse_keypoints": n_keypoints,
        "build_seconds": build_s,
        **{f"{k}_s": v for k, v in best.items()},
        **{f"{k}_frames_per_s": args.batch / v for k, v in best.items()},
        "ratio_smplfx_full_vs_smplx_forward": best["smplfx_full_forward"] / best["smplx_full_forward"],
        "ratio_smplfx_full_vs_smplx_forward_backward": best["smplfx_full_forward_backward"] / best["smplx_full_forward_backward"],
        "speedup_sparse_vs_full_forward_backward": best["smplfx_full_forward_backward"] / best["smplfx_sparse_forward_backward"],
        "torch_threads": torch.get_num_threads(),
        "machine": platform.machine(),
        "torch": torch.__version__,
        "smplx": getattr(smplx, "__version__", "0.1.28"),
    }
    write_and_log(result, args.out, "benchmark-smplfx")

if __name__ == "__main__":
    main()
