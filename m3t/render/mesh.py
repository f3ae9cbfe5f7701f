"""Meshes of fitted frames: PLY / OBJ export (trimesh), a shaded picture, and the vertices of whole clips.

The picture is rasterised offscreen by :mod:`m3t.render.raster` (z-buffer, two-sided Lambert shading; no
OpenGL, no display), seen through the fitted camera or from an orthographic front view.
:func:`log_fitted_frame` writes both and hands them to :meth:`m3t.experiment.Run.log_artifact`.
:func:`clip_vertices` poses a parameter sequence with the batched forward (what mesh videos,
:mod:`m3t.render.mesh_video`, show).

Axis legend: V vertices, F faces, T frames.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from m3t.atomic import write_bytes
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


def project_camera(vertices: np.ndarray, camera: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V, 3) world vertices through fitting's camera dict -> pixels (V, 2), depth (V,) (clamped to 1 mm in
    front of the camera) and camera-frame vertices (V, 3) (x right, y down, z forward, metres)."""
    rot, trans = np.asarray(camera["rotation"], dtype=np.float64), np.asarray(camera["translation"], dtype=np.float64)
    cam = vertices @ rot.T + trans
    depth = np.clip(cam[:, 2], 1e-3, None)
    uv = np.stack([camera["fx"] * cam[:, 0] / depth + camera["cx"], camera["fy"] * cam[:, 1] / depth + camera["cy"]], 1)
    return uv, depth, cam


def _project(vertices: np.ndarray, camera: dict | None, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates (V, 2), depth (V,) and camera-frame vertices (V, 3)."""
    if camera is not None:
        return project_camera(vertices, camera)
    # Orthographic front view of the protocol frame (Z up, the body faces -Y): image x = X, image y = -Z.
    cam = np.stack([vertices[:, 0], -vertices[:, 2], vertices[:, 1]], 1)
    lo, hi = cam[:, :2].min(0), cam[:, :2].max(0)
    scale = 0.9 * min(size) / max(float((hi - lo).max()), 1e-6)
    uv = (cam[:, :2] - (lo + hi) / 2) * scale + np.array(size) / 2
    return uv, cam[:, 2], cam


def render_mesh(vertices: np.ndarray, faces: np.ndarray, path: str | Path, camera: dict | None = None,
                size: tuple[int, int] | None = None, color=(0.55, 0.7, 0.9)) -> Path:
    """Save a PNG of the mesh, shaded, seen through ``camera`` (fitting's camera dict) or from the front
    (written atomically)."""
    import cv2

    from m3t.render.raster import colorise, rasterise

    size = size or ((int(camera["width"]), int(camera["height"])) if camera else (512, 512))
    vertices = np.asarray(vertices, dtype=np.float64)
    uv, depth, cam = _project(vertices, camera, size)
    picture = colorise(rasterise(np.column_stack([uv, depth]), faces, size[0], size[1], cam), color)
    ok, png = cv2.imencode(".png", np.ascontiguousarray(picture[..., ::-1]))  # OpenCV writes BGR
    if not ok:
        raise RuntimeError(f"{path}: OpenCV could not encode a {size[0]} x {size[1]} PNG")
    path = Path(path)
    write_bytes(path, png.tobytes())
    return path


@torch.no_grad()
def frame_mesh(body: BodyModel, params: dict[str, np.ndarray], identity: np.ndarray, frame: int) -> np.ndarray:
    """(V, 3) vertices of one frame of a parameter sequence."""
    one = as_tensors({k: np.asarray(v)[frame:frame + 1] for k, v in params.items()})
    return body.forward(one, torch.as_tensor(identity, dtype=torch.float32)).vertices[0].cpu().numpy()


@torch.no_grad()
def clip_vertices(body: BodyModel, params: dict[str, np.ndarray], identity: np.ndarray,
                  chunk: int = 64) -> np.ndarray:
    """(T, V, 3) float32 vertices of a parameter sequence ((T, D_m) per modality, (P,) identity), posed by the
    batched forward ``chunk`` frames at a time (a long clip never holds the forward's intermediates of all its
    frames at once)."""
    tensors = as_tensors(params)
    frames = body.layout.check(tensors)
    ident = torch.as_tensor(np.asarray(identity), dtype=torch.float32)
    if frames == 0:
        raise ValueError("clip vertices: the parameter sequence has no frames")
    parts = [body.forward({k: v[i:i + chunk] for k, v in tensors.items()}, ident).vertices.cpu().numpy()
             for i in range(0, frames, max(1, chunk))]
    return np.concatenate(parts).astype(np.float32, copy=False)


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
