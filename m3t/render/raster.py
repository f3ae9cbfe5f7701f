"""Offscreen triangle rasteriser (numba): a z-buffer with two-sided Lambert shading, no OpenGL and no display.

:func:`rasterise` fills every pixel whose centre lies in a triangle (inclusive edge test, so neighbouring
triangles leave no gaps) with the nearest triangle's depth, index and shade. Shading is Lambert's
``ambient + (1 - ambient) |n . l|`` evaluated at the vertices (area-weighted vertex normals) and interpolated
across each triangle (Gouraud); the absolute value makes it two-sided, so a mesh lit from the viewer looks the
same whatever its winding. Depth is interpolated linearly in screen space: exact for an orthographic view and
close enough for a camera whose depth range across a triangle is small (a body a metre or more away).

Coordinates: ``screen`` is pixels (x right, y down, origin at the top-left corner of the top-left pixel, whose
centre is (0.5, 0.5)) plus a depth (smaller is nearer); ``view`` holds the same vertices in a metric frame with
the same axes (x right, y down, z away from the viewer), where normals are measured.

The kernel is compiled once per machine (``cache=True``; where no cache directory is writable, once per
process). Axis legend: V vertices, F faces, H x W pixels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from m3t.runtime import jit

LIGHT = (0.0, -0.45, -1.0)  # towards the light, view frame: from the viewer and a little above
AMBIENT = 0.3
COLOR = (0.55, 0.7, 0.9)  # the body's colour at full light (RGB in [0, 1])


@jit(nogil=True)
def _vertex_shade(view, faces, light, ambient, out):
    """Lambert shade per vertex from area-weighted vertex normals: out (V,) float64."""
    normals = np.zeros((view.shape[0], 3))
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        e1x, e1y, e1z = view[b, 0] - view[a, 0], view[b, 1] - view[a, 1], view[b, 2] - view[a, 2]
        e2x, e2y, e2z = view[c, 0] - view[a, 0], view[c, 1] - view[a, 1], view[c, 2] - view[a, 2]
        nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x  # |n| = 2 x area
        if not (np.isfinite(nx) and np.isfinite(ny) and np.isfinite(nz)):
            continue
        for v in (a, b, c):
            normals[v, 0] += nx
            normals[v, 1] += ny
            normals[v, 2] += nz
    for v in range(view.shape[0]):
        norm = np.sqrt(normals[v, 0] ** 2 + normals[v, 1] ** 2 + normals[v, 2] ** 2)
        cosine = 0.0
        if norm > 0.0:
            cosine = abs(normals[v, 0] * light[0] + normals[v, 1] * light[1] + normals[v, 2] * light[2]) / norm
        out[v] = ambient + (1.0 - ambient) * cosine


@jit(nogil=True)
def _draw(screen, faces, shade, depth_buf, face_buf, shade_buf):
    """Z-buffered scan of every triangle's bounding box; buffers (H, W) updated in place."""
    height, width = depth_buf.shape
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        xa, ya, za = screen[a, 0], screen[a, 1], screen[a, 2]
        xb, yb, zb = screen[b, 0], screen[b, 1], screen[b, 2]
        xc, yc, zc = screen[c, 0], screen[c, 1], screen[c, 2]
        area = (xb - xa) * (yc - ya) - (xc - xa) * (yb - ya)  # twice the signed area
        if not np.isfinite(area) or abs(area) < 1e-12 or not (np.isfinite(za) and np.isfinite(zb) and np.isfinite(zc)):
            continue
        # pixel x covers [x, x + 1): its centre x + 0.5 can be inside only when min - 0.5 <= x <= max - 0.5
        x0 = int(np.ceil(max(min(xa, xb, xc) - 0.5, -1.0)))
        x1 = int(np.floor(min(max(xa, xb, xc) - 0.5, float(width))))
        y0 = int(np.ceil(max(min(ya, yb, yc) - 0.5, -1.0)))
        y1 = int(np.floor(min(max(ya, yb, yc) - 0.5, float(height))))
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width - 1), min(y1, height - 1)
        inverse = 1.0 / area
        for y in range(y0, y1 + 1):
            py = y + 0.5
            for x in range(x0, x1 + 1):
                px = x + 0.5
                wa = ((xb - px) * (yc - py) - (xc - px) * (yb - py)) * inverse
                wb = ((xc - px) * (ya - py) - (xa - px) * (yc - py)) * inverse
                wc = 1.0 - wa - wb
                if wa < 0.0 or wb < 0.0 or wc < 0.0:
                    continue
                z = wa * za + wb * zb + wc * zc
                if z < depth_buf[y, x]:
                    depth_buf[y, x] = z
                    face_buf[y, x] = f
                    shade_buf[y, x] = wa * shade[a] + wb * shade[b] + wc * shade[c]


@jit(nogil=True)
def _paint(face_buf, shade_buf, color, background, out):
    """(H, W, 3) uint8: ``color`` (0-255 floats) x shade where a face is visible, ``background`` elsewhere."""
    height, width = face_buf.shape
    for y in range(height):
        for x in range(width):
            for k in range(3):
                if face_buf[y, x] >= 0:
                    out[y, x, k] = np.uint8(min(255.0, max(0.0, color[k] * shade_buf[y, x] + 0.5)))
                else:
                    out[y, x, k] = background[k]


@dataclass(frozen=True)
class Raster:
    """face: (H, W) int32 index of the visible triangle, -1 on the background; depth: (H, W) float64, inf on
    the background; shade: (H, W) float32 Lambert shade in [ambient, 1] (0 on the background)."""

    face: np.ndarray
    depth: np.ndarray
    shade: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: pixels covered by the mesh."""
        return self.face >= 0


def rasterise(screen: np.ndarray, faces: np.ndarray, width: int, height: int, view: np.ndarray | None = None,
              light: tuple[float, float, float] = LIGHT, ambient: float = AMBIENT) -> Raster:
    """Rasterise a triangle mesh seen in ``screen`` coordinates onto a ``width`` x ``height`` image.

    Parameters
    ----------
    screen : (V, 3) pixel x, pixel y and depth of each vertex (see the module docstring)
    faces : (F, 3) vertex indices
    width, height : image size in pixels
    view : (V, 3) the vertices in a metric view frame (x right, y down, z away) for the normals; defaults to
        ``screen`` (right for an orthographic view whose depth shares the pixel scale)
    light : direction towards the light in the view frame (normalised here)
    ambient : shade of a surface seen edge-on to the light
    """
    screen = np.ascontiguousarray(screen, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    if screen.ndim != 2 or screen.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"rasterise: screen {screen.shape} and faces {faces.shape}; expected (V, 3) and (F, 3)")
    if faces.size and (faces.min() < 0 or faces.max() >= len(screen)):
        raise ValueError(f"rasterise: face indices span {faces.min()}..{faces.max()}, but there are {len(screen)} "
                         "vertices")
    if width < 1 or height < 1:
        raise ValueError(f"rasterise: image {width} x {height} px; both sides must be >= 1")
    view = screen if view is None else np.ascontiguousarray(view, dtype=np.float64)
    if view.shape != screen.shape:
        raise ValueError(f"rasterise: view {view.shape} and screen {screen.shape} differ")
    direction = np.asarray(light, dtype=np.float64)
    direction = direction / max(float(np.linalg.norm(direction)), 1e-12)
    shade = np.empty(len(screen))
    _vertex_shade(view, faces, direction, float(ambient), shade)
    depth = np.full((int(height), int(width)), np.inf)
    face = np.full((int(height), int(width)), -1, dtype=np.int32)
    shade_buf = np.zeros((int(height), int(width)), dtype=np.float32)
    _draw(screen, faces, shade, depth, face, shade_buf)
    return Raster(face, depth, shade_buf)


def colorise(raster: Raster, color: tuple[float, float, float] = COLOR,
             background: tuple[int, int, int] = (255, 255, 255)) -> np.ndarray:
    """(H, W, 3) uint8 RGB picture of a :class:`Raster`: ``color`` x shade on the mesh, ``background`` elsewhere."""
    out = np.empty((*raster.face.shape, 3), dtype=np.uint8)
    _paint(raster.face, raster.shade, 255.0 * np.asarray(color, dtype=np.float64),
           np.asarray(background, dtype=np.uint8), out)
    return out
