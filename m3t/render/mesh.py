"""Meshes of fitted frames: PLY / OBJ export (trimesh) and a shaded picture (matplotlib, headless).

The picture is drawn with a painter's algorithm: triangles are projected (through the fitted camera, or
an orthographic front view), sorted far to near and filled with Lambert shading (two-sided), which needs
no OpenGL and runs on any machine. :func:`log_fitted_frame` writes both and hands them to
:meth:`m3t.experiment.Run.log_artifact`.

Axis legend: V vertices, F faces, T frames.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from m3t.body.protocol import BodyModel, as_tensors


def export_mesh(vertices: np.ndarray, faces: np.ndarray, path: str | Path) -> Path:
    """Write (V, 3) vertices and (F, 3) faces as ``.ply`` or ``.obj`` (chosen by the suffix)."""
    import trimesh

    path = Path(path)
    if path.suffix.lower() not in (".ply", ".obj"):
        raise ValueError(f"{path}: mesh export supports .ply and .obj")
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(vertices=np.asarray(vertices, dtype=np.float64), faces=np.asarray(faces), process=False).export(path)
    return path


def _project(vertices: np.ndarray, camera: dict | None, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates (V, 2), depth (V,) and camera-frame vertices (V, 3)."""
    if camera is not None:
        rot, trans = np.asarray(camera["rotation"]), np.asarray(camera["translation"])
        cam = vertices @ rot.T + trans
        depth = np.clip(cam[:, 2], 1e-3, None)
        uv = np.stack([camera["fx"] * cam[:, 0] / depth + camera["cx"], camera["fy"] * cam[:, 1] / depth + camera["cy"]], 1)
        return uv, depth, cam
    # Orthographic front view of the protocol frame (Z up, the body faces -Y): image x = X, image y = -Z.
    cam = np.stack([vertices[:, 0], -vertices[:, 2], vertices[:, 1]], 1)
    lo, hi = cam[:, :2].min(0), cam[:, :2].max(0)
    scale = 0.9 * min(size) / max(float((hi - lo).max()), 1e-6)
    uv = (cam[:, :2] - (lo + hi) / 2) * scale + np.array(size) / 2
    return uv, cam[:, 2], cam


def render_mesh(vertices: np.ndarray, faces: np.ndarray, path: str | Path, camera: dict | None = None,
                size: tuple[int, int] | None = None, color=(0.55, 0.7, 0.9)) -> Path:
    """Save a PNG of the mesh, shaded, seen through ``camera`` (fitting's camera dict) or from the front."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    size = size or ((int(camera["width"]), int(camera["height"])) if camera else (512, 512))
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    uv, depth, cam = _project(vertices, camera, size)
    tri_cam = cam[faces]  # (F, 3, 3)
    normals = np.cross(tri_cam[:, 1] - tri_cam[:, 0], tri_cam[:, 2] - tri_cam[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
    shade = 0.25 + 0.75 * np.abs(normals[:, 2])  # light from the viewer, two-sided
    order = np.argsort(-depth[faces].mean(1))  # far first
    dpi = 100
    fig = plt.figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    ax = fig.add_axes((0, 0, 1, 1))
    colors = np.clip(np.asarray(color)[None] * shade[order, None], 0, 1)
    ax.add_collection(PolyCollection(uv[faces[order]], facecolors=colors, edgecolors=colors, linewidths=0.2))
    ax.set_xlim(0, size[0])
    ax.set_ylim(size[1], 0)  # image y grows downwards
    ax.set_axis_off()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, facecolor="white")
    plt.close(fig)
    return path


@torch.no_grad()
def frame_mesh(body: BodyModel, params: dict[str, np.ndarray], identity: np.ndarray, frame: int) -> np.ndarray:
    """(V, 3) vertices of one frame of a parameter sequence."""
    one = as_tensors({k: np.asarray(v)[frame:frame + 1] for k, v in params.items()})
    return body.forward(one, torch.as_tensor(identity, dtype=torch.float32)).vertices[0].cpu().numpy()


def log_fitted_frame(run, body: BodyModel, params: dict[str, np.ndarray], identity: np.ndarray, frame: int,
                     out_dir: str | Path, camera: dict | None = None, stem: str = "fit",
                     artifact_path: str = "meshes") -> list[Path]:
    """Write ``<stem>_<frame>.ply`` and ``.png`` of a fitted frame and log both as run artifacts."""
    vertices = frame_mesh(body, params, identity, frame)
    out_dir = Path(out_dir)
    paths = [export_mesh(vertices, body.faces, out_dir / f"{stem}_{frame:05d}.ply"),
             render_mesh(vertices, body.faces, out_dir / f"{stem}_{frame:05d}.png", camera)]
    for p in paths:
        run.log_artifact(p, artifact_path)
    return paths
