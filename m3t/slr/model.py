"""The recognition probe (M3T Sec. 3.4, App. 0.D.3): interleaved frozen-encoder features -> transformer
encoder -> pooled -> classifier.

- **Sequence.** The per-stream features of one time step follow each other in :data:`STREAM_ORDER`
  ({body, left_hand, right_hand, face} for the full probe; the face-less probe simply has no face entry), so
  N steps of S streams give N * S positions. Each position gets a learned modality embedding (its stream) and
  a learned position embedding (its time step, shared by the step's streams).
- **Encoder.** ``layers`` pre-norm transformer layers of width W (the encoders' width), ``heads`` heads, FFN
  ``ffn_mult * W``, GELU, and a final LayerNorm; padding positions are masked out of attention.
- **Pooling.** ``mean`` over the valid positions (default), or a learned CLS token prepended (``cls``).
- **Head.** Dropout + linear layer to the classes (the paper's "linear MLP head"), or with ``head_hidden`` > 0
  one GELU hidden layer first.

Parameter count at the paper's width 1024 and NMFs-CSL's 1067 classes: 26.43M with FFN 2W = 2048 (torch's
default ``dim_feedforward``) and the linear head, the paper's "26M"; an FFN of 4W would give 39.0M, a hidden
head layer of W another 1.05M. Hence ``ffn_mult: 2`` and ``head_hidden: 0`` (tests/slr/test_slr.py checks it).

Axis legend: B batch, N token steps, S streams, L = N * S positions, W width, C classes.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from m3t.slr.config import SLRConfig


@dataclass(frozen=True)
class ProbeDims:
    """The data-dependent sizes: encoder width, number of classes and the streams read (in order)."""

    width: int
    num_classes: int
    streams: tuple[str, ...]


class SLRProbe(nn.Module):
    """features: stream -> (B, N, W); mask: (B, N) True on valid steps -> logits (B, C)."""

    def __init__(self, cfg: SLRConfig, dims: ProbeDims):
        super().__init__()
        if dims.width % cfg.heads:
            raise ValueError(f"probe width {dims.width} (the encoders' width) is not divisible by "
                             f"slr.heads={cfg.heads}")
        if not dims.streams or dims.num_classes < 2:
            raise ValueError(f"the probe needs >= 1 stream and >= 2 classes, got {dims.streams}, {dims.num_classes}")
        self.cfg, self.dims = cfg, dims
        width = dims.width
        self.modality = nn.Parameter(0.02 * torch.randn(len(dims.streams), width))  # (S, W)
        self.position = nn.Parameter(0.02 * torch.randn(cfg.max_steps, width))  # (max_steps, W)
        self.cls = nn.Parameter(0.02 * torch.randn(1, 1, width)) if cfg.pooling == "cls" else None
        layer = nn.TransformerEncoderLayer(width, cfg.heads, cfg.ffn_mult * width, cfg.dropout, activation="gelu",
                                           batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, cfg.layers, norm=nn.LayerNorm(width), enable_nested_tensor=False)
        if cfg.head_hidden:
            self.head = nn.Sequential(nn.Linear(width, cfg.head_hidden), nn.GELU(), nn.Dropout(cfg.dropout),
                                      nn.Linear(cfg.head_hidden, dims.num_classes))
        else:
            self.head = nn.Sequential(nn.Dropout(cfg.dropout), nn.Linear(width, dims.num_classes))

    def sequence(self, features: dict[str, torch.Tensor], mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The interleaved input: (B, L, W) with embeddings added, and its (B, L) valid mask. Reads only the
        probe's own streams (a face-less probe never touches a face entry)."""
        missing = [s for s in self.dims.streams if s not in features]
        if missing:
            raise KeyError(f"the probe reads streams {list(self.dims.streams)}; features lack {missing}")
        x = torch.stack([features[s] for s in self.dims.streams], dim=2).to(self.position.dtype)  # (B, N, S, W)
        steps = x.shape[1]
        if steps > self.cfg.max_steps:
            raise ValueError(f"{steps} token steps exceed slr.max_steps={self.cfg.max_steps}")
        x = x + self.modality[None, None] + self.position[:steps][None, :, None]
        x = x.flatten(1, 2)  # (B, N, S, W) -> (B, N * S, W): step-major, streams interleaved
        valid = mask.bool().repeat_interleave(len(self.dims.streams), dim=1)  # (B, N) -> (B, N * S)
        return x, valid

    def forward(self, features: dict[str, torch.Tensor], mask: torch.Tensor) -> torch.Tensor:
        x, valid = self.sequence(features, mask)
        if self.cls is not None:
            x = torch.cat([self.cls.expand(x.shape[0], -1, -1), x], dim=1)  # (B, 1 + L, W)
            valid = torch.cat([valid.new_ones(x.shape[0], 1), valid], dim=1)
        h = self.encoder(x, src_key_padding_mask=~valid)  # (B, L, W)
        if self.cls is not None:
            pooled = h[:, 0]
        else:
            weights = valid.unsqueeze(-1).to(h.dtype)  # (B, L, 1)
            pooled = (h * weights).sum(1) / weights.sum(1).clamp_min(1.0)
        return self.head(pooled)  # (B, C)


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
