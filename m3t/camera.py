"""Pinhole camera shared by the simulated tracker, fitting and rendering.

World coordinates are the body model's (metres). Image coordinates are pixels, origin top-left, y down.
Axis legend: ... leading axes, K points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from m3t.dataclass_io import build_dataclass


@dataclass(frozen=True)
class Camera:
    """Intrinsics (fx, fy, cx, cy), extrinsics world->camera (rotation (3, 3), translation (3,)), image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    rotation: tuple[tuple[float, float, float], ...]
    translation: tuple[float, float, float]
    width: int
    height: int

    def as_dict(self) -> dict:
        return {
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "rotation": [list(r) for r in self.rotation], "translation": list(self.translation),
            "width": self.width, "height": self.height,
        }

    @staticmethod
    def from_dict(d: dict) -> Camera:
        return build_dataclass(Camera, d, "camera", ignore_unknown=True)


def project(points: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """Project world points ``(..., K, 3)`` to pixels ``(..., K, 2)``.

    rotation (3, 3), translation (3,), intrinsics (4,) = (fx, fy, cx, cy); or one camera per leading index:
    (..., 3, 3), (..., 3), (..., 4). Points behind the camera are clamped to a small positive depth so
    gradients stay finite.
    """
    cam = points @ rotation.transpose(-1, -2) + translation[..., None, :]  # (..., K, 3)
    depth = cam[..., 2:3].clamp(min=1e-3)
    uv = cam[..., :2] / depth
    return uv * intrinsics[..., None, :2] + intrinsics[..., None, 2:]


def camera_tensors(camera: Camera, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(rotation (3, 3), translation (3,), intrinsics (4,)) tensors of a :class:`Camera`."""
    return (
        torch.tensor(np.asarray(camera.rotation), dtype=dtype),
        torch.tensor(camera.translation, dtype=dtype),
        torch.tensor([camera.fx, camera.fy, camera.cx, camera.cy], dtype=dtype),
    )


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World->camera rotation (3, 3) for a camera at ``eye`` looking at ``target`` (x right, y down, z forward)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])
