"""Finite Scalar Quantization (Mentzer et al. 2023), as used by the M3T tokenizers (paper Eq. 4).

Each of the ``d`` latent channels is squashed by ``tanh`` and rounded to one of ``L_i`` integer levels
with a straight-through estimator; the implicit codebook is the grid of all level combinations,
``C = prod(L_i)`` codes, with no learned parameters and no auxiliary loss.

Eq. 4 writes the bound as ``L/2 * tanh(z)``; taken literally that rounds to ``L + 1`` values when ``L``
is even (e.g. -3..3 for L = 6). We use the reference bound ``tanh(z + s) * (L - 1)(1 + eps)/2 - o``
(``o = 0.5`` for even ``L``, ``s = atanh(o / half)``), which yields exactly ``L`` levels per channel, so
that the codebook sizes are the paper's 100 / 180 / 216.

Axis legend: ``...`` leading axes (batch, time), d latent channels (= number of levels).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class QuantizerOutput:
    """codes: (..., d) quantised latents (straight-through gradient); indices: (...,) int64 codebook
    indices; loss: scalar auxiliary loss (0 for FSQ); perplexity: of the batch's code usage."""

    codes: torch.Tensor
    indices: torch.Tensor
    loss: torch.Tensor
    perplexity: torch.Tensor


def round_ste(x: torch.Tensor) -> torch.Tensor:
    """Round in the forward pass, identity gradient in the backward pass."""
    return x + (x.round() - x).detach()


def batch_perplexity(indices: torch.Tensor, codebook_size: int) -> torch.Tensor:
    """exp(entropy) of the code histogram of ``indices`` (any shape)."""
    counts = torch.bincount(indices.reshape(-1), minlength=codebook_size).float()
    probs = counts / counts.sum().clamp_min(1.0)
    return torch.exp(-(probs * torch.log(probs.clamp_min(1e-10))).sum())


class FSQ(nn.Module):
    """Finite scalar quantiser with ``levels`` per latent channel (e.g. ``(5, 5, 4)`` -> 100 codes)."""

    def __init__(self, levels: tuple[int, ...], eps: float = 1e-3):
        super().__init__()
        if not levels or any(int(l) < 2 for l in levels):
            raise ValueError(f"FSQ levels must be integers >= 2, got {levels}")
        self.levels = tuple(int(l) for l in levels)
        self.eps = eps
        lv = torch.tensor(self.levels, dtype=torch.float32)
        basis = torch.cumprod(torch.tensor((1,) + self.levels[:-1], dtype=torch.int64), dim=0)
        # Buffers are derived from ``levels`` (rebuilt from the config), so they stay out of state_dict.
        self.register_buffer("_levels", lv, persistent=False)
        self.register_buffer("_basis", basis, persistent=False)
        self.register_buffer("_half_width", torch.floor(lv / 2), persistent=False)

    @property
    def dim(self) -> int:
        return len(self.levels)

    @property
    def codebook_size(self) -> int:
        return math.prod(self.levels)

    def bound(self, z: torch.Tensor) -> torch.Tensor:
        """(..., d) -> (..., d) values whose rounding falls on exactly ``L_i`` integers per channel."""
        half = (self._levels - 1) * (1 + self.eps) / 2
        offset = torch.where(self._levels % 2 == 0, 0.5, 0.0)
        shift = torch.atanh(offset / half)
        return torch.tanh(z + shift) * half - offset

    def forward(self, z: torch.Tensor) -> QuantizerOutput:
        """Quantise (..., d) latents; codes are normalised to [-1, 1]."""
        if z.shape[-1] != self.dim:
            raise ValueError(f"FSQ with {self.dim} levels got latents with {z.shape[-1]} channels")
        codes = round_ste(self.bound(z.float())) / self._half_width  # (..., d)
        indices = self.codes_to_indices(codes.detach())
        return QuantizerOutput(codes, indices, z.new_zeros(()), batch_perplexity(indices, self.codebook_size))

    def codes_to_indices(self, codes: torch.Tensor) -> torch.Tensor:
        """(..., d) normalised codes -> (...,) int64 indices in [0, C)."""
        level_index = (codes * self._half_width + self._half_width).round().long()  # (..., d) in [0, L_i)
        return (level_index * self._basis).sum(dim=-1)

    def indices_to_codes(self, indices: torch.Tensor) -> torch.Tensor:
        """(...,) int64 indices -> (..., d) normalised codes."""
        if indices.numel() and (int(indices.min()) < 0 or int(indices.max()) >= self.codebook_size):
            raise ValueError(f"FSQ indices must lie in [0, {self.codebook_size}), got "
                             f"[{int(indices.min())}, {int(indices.max())}]")
        level_index = (indices.long().unsqueeze(-1) // self._basis) % self._levels.long()  # (..., d)
        return (level_index.float() - self._half_width) / self._half_width
