"""Animated comparison of a clip and its tokenizer reconstruction (or generated motion): skeleton + face
landmarks, projected through the clip's camera, original in orange and reconstruction in blue, overlaid in one
panel (small reconstruction errors show as a colour fringe), drawn with OpenCV and written as an H.264 MP4
(a GIF when the target ends in ``.gif``, :mod:`m3t.render.video`).

Axis legend: T frames, J joints, K face landmarks.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from m3t.body.metric_sets import metric_joints
from m3t.body.protocol import BodyModel, Correspondence, as_tensors
from m3t.render.skeleton import project_points, skeleton_edges
from m3t.render.video import SUBPIXEL, held, progress_label, side_by_side, write_video
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
                          labels: tuple[str, str] = ("fitted", "reconstructed"), size: int = 400,
                          progress: bool = False) -> Path:
    """Write a video (MP4, or GIF by suffix) of ``fitted`` (orange) against the same clip with ``recon`` streams
    (blue), on a panel whose longer side is ``size`` pixels; returns ``path`` (written atomically).

    ``recon`` may replace every stream with a sequence of another length (generated motion): each side then
    holds its last frame once it ends, its legend entry saying so.
    """
    import cv2
    from tqdm.auto import tqdm

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
    if has_camera:  # the camera's image, scaled to the panel
        low, high = np.zeros(2), np.array([fitted.camera["width"], fitted.camera["height"]], dtype=np.float64)
    else:
        every = np.concatenate([v.reshape(-1, 2) for view in views for v in view])
        low, high = np.nanmin(every, 0) - 0.05, np.nanmax(every, 0) + 0.05
    zoom = size / max(float((high - low).max()), 1e-9)
    width, height = (max(1, round(float(d) * zoom)) for d in high - low)
    colours = ((255, 127, 14), (31, 119, 180))  # matplotlib's tab:orange, tab:blue (RGB)

    def pixels(uv: np.ndarray) -> np.ndarray:
        return np.round((uv - low) * zoom * (1 << SUBPIXEL)).astype(np.int64)  # OpenCV fixed point

    def pictures():
        for t in tqdm(range(frames), desc=f"render {Path(path).name}", disable=not progress, leave=False):
            panel = np.full((height, width, 3), 255, dtype=np.uint8)
            for (joint_uv, *face_uv), colour, n in zip(views, colours, lengths):
                k = held(n, t)
                finite = np.isfinite(joint_uv[k]).all(1)
                ends = pixels(np.where(finite[:, None], joint_uv[k], 0.0))
                for a, b in edges:
                    if finite[a] and finite[b]:
                        cv2.line(panel, tuple(map(int, ends[a])), tuple(map(int, ends[b])), colour, 1, cv2.LINE_AA,
                                 SUBPIXEL)
                if face_uv:
                    for point in pixels(face_uv[0][k][np.isfinite(face_uv[0][k]).all(1)]):
                        cv2.circle(panel, tuple(map(int, point)), 1 << SUBPIXEL, colour, -1, cv2.LINE_AA, SUBPIXEL)
            for row, (label, colour, n) in enumerate(zip(labels, colours, lengths)):
                cv2.putText(panel, progress_label(label, n, t), (6, height - 8 - 16 * (1 - row)),
                            cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
            yield side_by_side([panel], [title or fitted.clip.id])

    fps = fitted.clip.fps if fitted.clip.fps and fitted.clip.fps > 0 else 25.0
    return write_video(pictures(), path, fps)
