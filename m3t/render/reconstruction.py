"""Animated comparison of a clip and its tokenizer reconstruction: skeleton + face landmarks, projected
through the clip's camera, original in orange and reconstruction in blue, written as a GIF.

Axis legend: T frames, J joints, K face landmarks.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from m3t.body.metric_sets import metric_joints
from m3t.body.protocol import BodyModel, Correspondence, as_tensors
from m3t.render.skeleton import project_points, skeleton_edges
from m3t.shards.schema import FittedClip


def face_landmarks(body: BodyModel) -> Correspondence | None:
    """The face part of the body's MediaPipe correspondence (None when the model has none)."""
    try:
        corr = body.correspondence("mediapipe_holistic")
    except (FileNotFoundError, KeyError, NotImplementedError):
        return None
    keep = np.array([n.startswith("face:") for n in corr.names]) & corr.valid
    return Correspondence(tuple(np.array(corr.names)[keep]), corr.kind[keep], corr.index[keep])


@torch.no_grad()
def _points(body: BodyModel, params: dict, identity: np.ndarray, sets: list) -> list[torch.Tensor]:
    ident = torch.as_tensor(np.asarray(identity), dtype=torch.float32)
    return [body.forward_keypoints(as_tensors(params), ident, kp) for kp in sets]


def render_reconstruction(body: BodyModel, fitted: FittedClip, recon: dict[str, np.ndarray], path: str | Path,
                          title: str = "", max_frames: int = 120,
                          labels: tuple[str, str] = ("fitted", "reconstructed")) -> Path:
    """Write an animated GIF of ``fitted`` (orange) against the same clip with ``recon`` streams (blue).

    ``recon`` may replace every stream with a sequence of another length (generated motion): each side then
    holds its last frame once it ends.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

    joints = metric_joints(body)
    face = face_landmarks(body)
    sets = [body.keypoint_set(joints)] + ([body.keypoint_set(face)] if face is not None else [])
    edges = skeleton_edges(body, joints)
    reconstructed = {**fitted.params, **recon}
    has_camera = {"fx", "width", "height"} <= set(fitted.camera)
    views = []
    for params in (fitted.params, reconstructed):
        points = _points(body, params, fitted.identity, sets)
        # no stored camera (e.g. motion imported from 3D keypoints): an orthographic front view, x right, z up
        views.append([project_points(p, fitted.camera) if has_camera else -p[..., [0, 2]].numpy() * [-1, 1] for p in points])
    lengths = [view[0].shape[0] for view in views]
    frames = min(max(lengths), max_frames)
    fig, ax = plt.subplots(figsize=(4, 4))
    if has_camera:
        ax.set_xlim(0, fitted.camera["width"])
        ax.set_ylim(fitted.camera["height"], 0)
    else:
        every = np.concatenate([v.reshape(-1, 2) for view in views for v in view])
        low, high = every.min(0) - 0.05, every.max(0) + 0.05
        ax.set_xlim(low[0], high[0])
        ax.set_ylim(high[1], low[1])
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    artists = []
    for (joint_uv, *face_uv), colour in zip(views, ("tab:orange", "tab:blue")):
        lines = [ax.plot([], [], color=colour, lw=1.2)[0] for _ in edges]
        dots = ax.scatter([], [], s=1, color=colour) if face_uv else None
        artists.append((joint_uv, face_uv[0] if face_uv else None, lines, dots))
    ax.legend([artists[0][2][0], artists[1][2][0]], list(labels), fontsize=7, loc="lower left")
    ax.set_title(title or fitted.clip.id, fontsize=8)

    def draw(t: int):
        for (joint_uv, face_uv, lines, dots), n in zip(artists, lengths):
            i = min(t, n - 1)
            for line, (a, b) in zip(lines, edges):
                line.set_data(joint_uv[i, [a, b], 0], joint_uv[i, [a, b], 1])
            if dots is not None:
                dots.set_offsets(face_uv[i])
        return []

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    FuncAnimation(fig, draw, frames=frames).save(path, writer=PillowWriter(fps=max(1, int(round(fitted.clip.fps)))))
    plt.close(fig)
    return path
