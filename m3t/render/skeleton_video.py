"""Skeleton sequences side by side (reference / PT / SGSA / SMLM ...) as an animated GIF, and an attention map
picture (SGSA Sec. 4.3: a produced skeletal sequence is animated by drawing the graph's limb connections).

Every panel is a front view of the points, x right and the body's up axis up (Anny is z up, SMPL-FX y up: up is
taken from the first panel as the axis along which the neck sits furthest from the mean point), centred on each
frame's neck. Sequences
of different lengths play together; a finished one holds its last frame, its panel title saying so.

Axis legend: T frames, J joints.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from m3t.atomic import atomic_path
from m3t.body.skeleton import SkeletonGraph


def _up_axis(points: np.ndarray, graph: SkeletonGraph) -> int:
    """The axis (1 or 2) along which the neck (joint 0) sits furthest from the mean point, on average."""
    rel = points[:, 0] - points.mean(1)  # (T, 3)
    return 2 if abs(rel[:, 2].mean()) > abs(rel[:, 1].mean()) else 1


def render_skeleton_video(sequences: Mapping[str, np.ndarray], graph: SkeletonGraph, path: str | Path,
                          fps: float = 25.0, title: str = "", max_frames: int = 400) -> Path:
    """One GIF with a panel per sequence ({label: (T, J, 3) metres}); returns the path (written atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

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
    extent = max(float(np.abs(v).max()) for v in views.values()) * 1.1 or 1.0
    fig, axes = plt.subplots(1, len(labels), figsize=(2.6 * len(labels), 3.0), squeeze=False)
    lines = {}
    for ax, label in zip(axes[0], labels):
        ax.set_xlim(-extent, extent)
        ax.set_ylim(-extent, extent)
        ax.set_aspect("equal")
        ax.axis("off")
        ax.set_title(label, fontsize=9)
        lines[label] = [ax.plot([], [], lw=1.2, color="tab:blue" if label == "reference" else "tab:red")[0]
                        for _ in graph.edges]
    if title:
        fig.suptitle(title, fontsize=9)

    def draw(t: int):
        artists = []
        for ax, label in zip(axes[0], labels):
            view = views[label]
            k = min(t, len(view) - 1)
            ax.set_title(f"{label} ({k + 1}/{len(view)})" if t >= len(view) else label, fontsize=9)
            for line, (i, j) in zip(lines[label], graph.edges):
                line.set_data(view[k, [i, j], 0], view[k, [i, j], 1])
                artists.append(line)
        return artists

    animation = FuncAnimation(fig, draw, frames=frames, blit=False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, suffix=".gif") as tmp:
        animation.save(tmp, writer=PillowWriter(fps=max(1, int(round(fps)))))
    plt.close(fig)
    return path


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
