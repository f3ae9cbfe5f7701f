"""Device and dtype choice: the one place that decides where tensors live."""
from __future__ import annotations

import torch


def choose_device(name: str = "auto") -> torch.device:
    """``"auto"`` -> CUDA when available, else CPU; otherwise the named device (fails clearly if absent)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {name!r} requested but no CUDA device is visible; use 'cpu' or 'auto'")
    return device
