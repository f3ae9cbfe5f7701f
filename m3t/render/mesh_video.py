"""Body-surface videos: mesh sequences side by side (reference / generated ...) as one MP4, rendered offscreen
by :mod:`m3t.render.raster` (no OpenGL, no display).

Every panel is an orthographic front view: x right and the body's up axis up, taken from the data as in
:mod:`m3t.render.skeleton_video` (the protocol frame is Z up with the body facing -Y, Anny's and SMPL-FX's
output; a mesh whose vertical extent lies along Y is read as SMPL-X's own frame, Y up and facing +Z). The view
is framed once per clip, so the camera never moves: the top ``visible_height`` of the body (head to mid-thigh
by default, the signing space, as a sign-language video is framed) fills the panel up to a margin, one scale
shared by all panels (equal sizes stay equal) and each panel centred on its own body. With a fitted ``camera``
(fitting's camera dict) every panel is seen through it instead, scaled to the panel size.

Sequences of different lengths play together; a finished one holds its last frame, its label saying so.

Axis legend: T frames, V vertices, F faces.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.render.mesh import project_camera
from m3t.render.raster import COLOR, colorise, rasterise
from m3t.render.video import held, progress_label, side_by_side, write_video

# world -> view axes (x right, y down, z away from the viewer)
Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # protocol frame: Z up, facing -Y
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # SMPL-X's frame: Y up, facing +Z
MARGIN = 0.06  # fraction of the panel left free on each side
VISIBLE_HEIGHT = 0.6  # fraction of the body's height framed, from the top: head to mid-thigh
FRAMING_SAMPLES = 64  # frames of each clip the framing looks at (evenly spaced)


def up_rotation(vertices: np.ndarray) -> np.ndarray:
    """(3, 3) world -> view rotation for (T, V, 3) vertices: Z up unless the first frame is taller along Y."""
    first = np.asarray(vertices[0], dtype=np.float64)
    extent = np.nanmax(first, axis=0) - np.nanmin(first, axis=0)
    return Y_UP if extent[1] > extent[2] else Z_UP


@dataclass(frozen=True)
class FrontView:
    """An orthographic view: ``rotation`` world -> view axes, ``scale`` pixels per metre, ``centre`` (2,) the
    view-plane point (metres) at the middle of a ``width`` x ``height`` panel."""

    rotation: np.ndarray
    scale: float
    centre: np.ndarray
    width: int
    height: int

    def screen(self, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(V, 3) world vertices -> (screen (V, 3) pixels + depth in pixels, view (V, 3) metres)."""
        view = vertices @ self.rotation.T  # (V, 3)
        screen = view * self.scale
        screen[:, 0] += self.width / 2 - self.centre[0] * self.scale
        screen[:, 1] += self.height / 2 - self.centre[1] * self.scale
        return screen, view


def _framed_box(label: str, view: np.ndarray, visible_height: float) -> tuple[np.ndarray, np.ndarray]:
    """(low (2,), high (2,)) of the top ``visible_height`` of the body in (N, V, 3) view coordinates (y down)."""
    finite = view[np.isfinite(view).all(-1)]  # (K, 3)
    if not len(finite):
        raise ValueError(f"mesh video panel {label!r}: no finite vertex to frame the view on")
    top, bottom = finite[:, 1].min(), finite[:, 1].max()
    cut = top + visible_height * (bottom - top)
    kept = finite[finite[:, 1] <= cut]  # (K', 3), never empty: the top vertex is kept
    return np.array([kept[:, 0].min(), top]), np.array([kept[:, 0].max(), cut])


def front_views(panels: Mapping[str, np.ndarray], size: int, visible_height: float = VISIBLE_HEIGHT,
                margin: float = MARGIN) -> dict[str, FrontView]:
    """One :class:`FrontView` per panel ({label: (T, V, 3)}): up axis from the first panel, one shared scale,
    each panel centred on its own framed box (over evenly spaced frames of its clip)."""
    if not 0 < visible_height <= 1:
        raise ValueError(f"visible_height {visible_height}; expected a fraction in (0, 1]")
    rotation = up_rotation(next(iter(panels.values())))
    boxes = {}
    for label, vertices in panels.items():
        count = min(FRAMING_SAMPLES, len(vertices))
        picks = np.unique(np.linspace(0, len(vertices) - 1, num=count).round().astype(int))
        boxes[label] = _framed_box(label, np.asarray(vertices[picks], dtype=np.float64) @ rotation.T, visible_height)
    span = max(float((high - low).max()) for low, high in boxes.values())
    scale = size * (1 - 2 * margin) / max(span, 1e-6)
    return {label: FrontView(rotation, scale, (low + high) / 2, size, size) for label, (low, high) in boxes.items()}


@dataclass(frozen=True)
class CameraView:
    """A fitted pinhole camera (fitting's camera dict: fx, fy, cx, cy, rotation, translation, width, height),
    its image scaled by ``zoom`` onto a ``width`` x ``height`` panel."""

    camera: dict
    zoom: float
    width: int
    height: int

    @classmethod
    def fit(cls, camera: dict, size: int) -> CameraView:
        missing = {"fx", "fy", "cx", "cy", "rotation", "translation", "width", "height"} - set(camera)
        if missing:
            raise ValueError(f"mesh video camera lacks {sorted(missing)}; expected fitting's camera dict")
        zoom = size / max(int(camera["width"]), int(camera["height"]))
        return cls(camera, zoom, max(1, round(camera["width"] * zoom)), max(1, round(camera["height"] * zoom)))

    def screen(self, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(V, 3) world vertices -> (screen (V, 3) pixels + camera depth, camera frame (V, 3) metres)."""
        uv, depth, cam = project_camera(vertices, self.camera)
        return np.column_stack([uv * self.zoom, depth]), cam


def render_mesh_frame(vertices: np.ndarray, faces: np.ndarray, view: FrontView | CameraView,
                      color: tuple[float, float, float] = COLOR) -> np.ndarray:
    """(height, width, 3) uint8 picture of one frame's (V, 3) vertices seen through ``view``."""
    screen, metric = view.screen(np.asarray(vertices, dtype=np.float64))
    return colorise(rasterise(screen, faces, view.width, view.height, metric), color)


def render_mesh_video(panels: Mapping[str, np.ndarray], faces: np.ndarray, path: str | Path, fps: float = 25.0,
                      size: int = 256, progress: bool = False, title: str = "", camera: dict | None = None,
                      visible_height: float = VISIBLE_HEIGHT, max_frames: int = 400) -> Path:
    """One video (MP4, or GIF by suffix) with a panel per mesh sequence ({label: (T, V, 3) metres}), the panels'
    labels above them and ``title`` above all; ``size`` is each panel's side in pixels (the longer side with a
    ``camera``). Returns ``path`` (written atomically)."""
    from tqdm.auto import tqdm

    if not panels:
        raise ValueError("mesh video: no sequence to render")
    faces = np.asarray(faces)
    sequences = {}
    for label, vertices in panels.items():
        vertices = np.asarray(vertices)
        if vertices.ndim != 3 or vertices.shape[2] != 3 or not len(vertices):
            raise ValueError(f"mesh video panel {label!r}: vertices of shape {vertices.shape}, expected (T, V, 3)")
        if faces.size and faces.max() >= vertices.shape[1]:
            raise ValueError(f"mesh video panel {label!r}: {vertices.shape[1]} vertices, but the faces index "
                             f"vertex {faces.max()}; the panels must be meshes of the body model these faces are of")
        sequences[label] = vertices
    views = ({label: CameraView.fit(camera, size) for label in sequences} if camera is not None
             else front_views(sequences, size, visible_height))
    lengths = {label: len(v) for label, v in sequences.items()}
    frames = min(max(lengths.values()), max_frames)

    def pictures():
        last: dict[str, np.ndarray] = {}
        for t in tqdm(range(frames), desc=f"render {Path(path).name}", disable=not progress, leave=False):
            for label, vertices in sequences.items():
                if t < lengths[label] or label not in last:  # a finished sequence keeps its last picture
                    last[label] = render_mesh_frame(vertices[held(lengths[label], t)], faces, views[label])
            yield side_by_side([last[label] for label in sequences],
                               [progress_label(label, lengths[label], t) for label in sequences], title)

    return write_video(pictures(), path, fps)
