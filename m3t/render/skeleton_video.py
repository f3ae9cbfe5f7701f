"""Skeleton sequences side by side (reference / PT / SGSA / SMLM ...) as a video (H.264 MP4, or a GIF when the
target ends in ``.gif``), and an attention map picture (SGSA Sec. 4.3: a produced skeletal sequence is animated
by drawing the graph's limb connections).

Every panel is a front view of the points, x right and the body's up axis up (Anny is z up, SMPL-FX y up: up is
taken from the first panel as the axis along which the neck sits furthest from the mean point), centred on each
frame's neck, one scale for all panels. The reference is drawn in blue, every other system in red; limbs with a
missing (NaN) end are left out. Sequences of different lengths play together; a finished one holds its last
frame, its panel label saying so. Limbs are drawn with OpenCV (anti-aliased, sub-pixel), frames encoded by
:mod:`m3t.render.video`.

Axis legend: T frames, J joints.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from m3t.atomic import atomic_path
from m3t.body.skeleton import SkeletonGraph
from m3t.render.video import SUBPIXEL, held, progress_label, side_by_side, write_video

REFERENCE_RGB = (31, 119, 180)  # matplotlib's tab:blue
SYSTEM_RGB = (214, 39, 40)  # tab:red


def _up_axis(points: np.ndarray, graph: SkeletonGraph) -> int:
    """The axis (1 or 2) along which the neck (joint 0) sits furthest from the mean point, on average."""
    rel = points[:, 0] - np.nanmean(points, axis=1)  # (T, 3)
    return 2 if abs(np.nanmean(rel[:, 2])) > abs(np.nanmean(rel[:, 1])) else 1


def draw_skeleton(points: np.ndarray, edges, size: int, extent: float, color: tuple[int, int, int],
                  thickness: int = 2) -> np.ndarray:
    """(size, size, 3) uint8 white picture of one frame's (J, 2) points (x right, up up, in [-extent, extent])."""
    import cv2

    picture = np.full((size, size, 3), 255, dtype=np.uint8)
    pixels = np.empty_like(points)
    pixels[:, 0] = (0.5 + 0.5 * points[:, 0] / extent) * size
    pixels[:, 1] = (0.5 - 0.5 * points[:, 1] / extent) * size
    finite = np.isfinite(pixels).all(axis=1)
    fixed = np.round(np.where(finite[:, None], pixels, 0.0) * (1 << SUBPIXEL)).astype(np.int64)
    for i, j in edges:
        if finite[i] and finite[j]:
            cv2.line(picture, (int(fixed[i, 0]), int(fixed[i, 1])), (int(fixed[j, 0]), int(fixed[j, 1])), color,
                     thickness, cv2.LINE_AA, SUBPIXEL)
    return picture


def render_skeleton_video(sequences: Mapping[str, np.ndarray], graph: SkeletonGraph, path: str | Path,
                          fps: float = 25.0, title: str = "", max_frames: int = 400, size: int = 256,
                          progress: bool = False) -> Path:
    """One video with a panel per sequence ({label: (T, J, 3) metres}), ``size`` pixels square each; MP4 or,
    by suffix, GIF; returns the path (written atomically)."""
    from tqdm.auto import tqdm

    if not sequences:
        raise ValueError("no sequence to render")
    labels = list(sequences)
    first = np.asarray(sequences[labels[0]], dtype=np.float64)
    up = _up_axis(first, graph)
    views = {}
    for label in labels:
        pts = np.asarray(sequences[label], dtype=np.float64)
        if pts.ndim != 3 or pts.shape[1:] != (len(graph.joints), 3) or not len(pts):
            raise ValueError(f"sequence {label!r}: shape {pts.shape}, expected (T, {len(graph.joints)}, 3)")
        centred = pts - pts[:, :1]
        views[label] = np.stack([centred[..., 0], centred[..., up]], axis=-1)  # (T, J, 2)
    frames = min(max(len(v) for v in views.values()), max_frames)
    extent = max(float(np.nanmax(np.abs(v), initial=0.0)) for v in views.values()) * 1.1 or 1.0
    colors = {label: REFERENCE_RGB if label == "reference" else SYSTEM_RGB for label in labels}

    def pictures():
        for t in tqdm(range(frames), desc=f"render {Path(path).name}", disable=not progress, leave=False):
            panels = [draw_skeleton(views[label][held(len(views[label]), t)], graph.edges, size, extent, colors[label])
                      for label in labels]
            yield side_by_side(panels, [progress_label(label, len(views[label]), t) for label in labels], title)

    return write_video(pictures(), path, fps)


def render_attention_map(weights: np.ndarray, path: str | Path, title: str = "") -> Path:
    """A picture of self-attention weights ((h, U, U) or (U, U); rows queries, columns keys), one panel per head."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w = np.asarray(weights, dtype=np.float64)
    w = w[None] if w.ndim == 2 else w
    if w.ndim != 3 or w.shape[1] != w.shape[2]:
        raise ValueError(f"attention weights of shape {np.shape(weights)}; expected (h, U, U) or (U, U)")
    fig, axes = plt.subplots(1, len(w), figsize=(3.0 * len(w), 3.2), squeeze=False)
    for h, ax in enumerate(axes[0]):
        ax.imshow(w[h], cmap="viridis", vmin=0.0, vmax=1.0, interpolation="nearest")
        ax.set_title(f"head {h + 1}", fontsize=9)
        ax.set_xlabel("key frame")
        ax.set_ylabel("query frame")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return path
