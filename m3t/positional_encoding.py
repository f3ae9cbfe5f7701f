"""Sinusoidal positional encodings (Vaswani et al. 2017), shared by the transformers of back-translation and SGSA."""
from __future__ import annotations

import math

import torch


def sinusoid_table(length: int, width: int) -> torch.Tensor:
    """(length, width) sinusoidal positions of Vaswani et al. (sin on even, cos on odd channels)."""
    position = torch.arange(length, dtype=torch.float32)[:, None]
    rate = torch.exp(torch.arange(0, width, 2, dtype=torch.float32) * (-math.log(10000.0) / width))
    table = torch.zeros(length, width)
    table[:, 0::2] = torch.sin(position * rate)
    table[:, 1::2] = torch.cos(position * rate[: width // 2])
    return table
