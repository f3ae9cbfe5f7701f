"""Skeleton pictures: a fitted clip next to its ground truth, projected through each one's camera.

Axis legend: T frames, J joints.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from m3t.body.metric_sets import joints_for, metric_joints
from m3t.body.protocol import BodyModel, Correspondence
from m3t.camera import Camera, camera_tensors, project
from m3t.shards.schema import FittedClip


def skeleton_edges(body: BodyModel, correspondence: Correspondence) -> list[tuple[int, int]]:
    """Parent -> child edges among the joints of a joint-only correspondence."""
    parents = body.joint_parents
    position = {int(j): k for k, j in enumerate(correspondence.index)}
    edges = []
    for k, j in enumerate(correspondence.index):
        p = parents[int(j)]
        while p >= 0 and p not in position:  # skip bones outside the set (twist bones, metacarpals)
            p = parents[p]
        if p >= 0:
            edges.append((position[p], k))
    return edges


@torch.no_grad()
def project_points(points: torch.Tensor, camera: dict) -> np.ndarray:
    """(T, K, 3) world points -> (T, K, 2) pixels through a stored camera."""
    rot, trans, intr = camera_tensors(Camera.from_dict(camera))
    return project(points, rot, trans, intr).numpy()


@torch.no_grad()
def _project_joints(body: BodyModel, params: dict, identity: np.ndarray, camera: dict) -> np.ndarray:
    return project_points(joints_for(body, params, identity), camera)  # (T, J, 2)


def render_fit_comparison(
    body: BodyModel,
    fitted: FittedClip,
    ground_truth: tuple[dict, np.ndarray, Camera] | None,
    path: str | Path,
    frames: int = 4,
) -> Path:
    """Save a PNG strip of ``frames`` evenly spaced frames: fitted skeleton (blue) over ground truth (orange)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    corr = metric_joints(body)
    edges = skeleton_edges(body, corr)
    fit_uv = _project_joints(body, fitted.params, fitted.identity, fitted.camera)
    gt_uv = None
    if ground_truth is not None:
        params, identity, camera = ground_truth
        gt_uv = _project_joints(body, params, identity, camera.as_dict())
    T = fit_uv.shape[0]
    picks = np.linspace(0, T - 1, num=min(frames, T)).round().astype(int)
    width, height = fitted.camera["width"], fitted.camera["height"]
    fig, axes = plt.subplots(1, len(picks), figsize=(3.2 * len(picks), 3.4), squeeze=False)
    for ax, t in zip(axes[0], picks):
        for uv, colour, label in ((gt_uv, "tab:orange", "ground truth"), (fit_uv, "tab:blue", "fitted")):
            if uv is None:
                continue
            for a, b in edges:
                ax.plot(uv[t, [a, b], 0], uv[t, [a, b], 1], color=colour, lw=1.2)
            ax.scatter(uv[t, :, 0], uv[t, :, 1], s=3, color=colour, label=label)
        ax.set_xlim(0, width)
        ax.set_ylim(height, 0)
        ax.set_aspect("equal")
        ax.set_title(f"frame {t}", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    axes[0][0].legend(fontsize=7, loc="lower left")
    joint_mm = fitted.metrics.get("joint_mm")
    title = f"{fitted.clip.id}: reprojection {fitted.metrics.get('reproj_px', float('nan')):.1f} px"
    if joint_mm is not None:
        title += f", joints {joint_mm:.0f} mm vs ground truth"
    fig.suptitle(title, fontsize=9)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path
