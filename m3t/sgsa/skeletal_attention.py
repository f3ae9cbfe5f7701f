"""SGSA's skeletal graph self-attention and its decoder layer (Saunders et al. 2022, Sec. 4.2): attention whose
values mix a frame's coordinates only along the skeleton graph (x A*), banded to the last N frames, in a pre-norm
layer of width S with encoder-decoder attention and a feed-forward S -> S -> S.

Axis legend: B batch, K text tokens, E encoder width, U frames, S skeleton width (coordinates + 1 counter), h heads.
"""
from __future__ import annotations

import torch
from torch import nn

from m3t.sgsa.attention import MultiHeadAttention, causal_band


class SkeletalGraphSelfAttention(nn.Module):
    """SGSA Eq. 8 with h heads of full width S: softmax(x W_Q (x W_K)^T / sqrt(S)) x A* W_V per head, concatenated
    h x S -> S. The values mix coordinate j of each frame only from the coordinates k with A*[k, j] != 0 (x A* is a
    row vector times A*). Query frame i attends to key frames i - N .. i (N = ``band``, math.inf = plain causal)."""

    def __init__(self, width: int, heads: int, adjacency: torch.Tensor, band: float, dropout: float):
        super().__init__()
        adjacency = torch.as_tensor(adjacency, dtype=torch.float32)
        if adjacency.shape != (width, width):
            raise ValueError(f"SGSA adjacency: expected ({width}, {width}), got {tuple(adjacency.shape)}")
        self.band = float(band)
        self.register_buffer("adjacency", adjacency.clone())  # A*, fixed, kept in the state dict
        self.attention = MultiHeadAttention(width, width, heads, width, width, dropout)

    def values(self, x: torch.Tensor) -> torch.Tensor:
        """V_A = x A* W_V per head: (B, U, S) -> (B, h, U, S)."""
        return self.attention.split(self.attention.v(x @ self.adjacency))

    def forward(self, x: torch.Tensor, pad_mask: torch.Tensor | None = None,
                need_weights: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """x (B, U, S), pad_mask (B, U) True on real frames -> (B, U, S) and the weights (B, h, U, U) if asked."""
        u = x.shape[1]
        allowed = causal_band(u, u, self.band, x.device)[None]
        if pad_mask is not None:
            allowed = allowed & pad_mask[:, None, :]
        return self.attention(x, x, x @ self.adjacency, allowed, need_weights)


class SGSADecoderLayer(nn.Module):
    """One pre-norm SGSA decoder layer of width S (Sec. 4.2): SGSA, encoder-decoder attention, feed-forward S, each
    applied to the LayerNorm of the stream and added to it."""

    def __init__(self, width: int, memory_width: int, heads: int, adjacency: torch.Tensor, band: float,
                 dropout: float):
        super().__init__()
        self.self_attn = SkeletalGraphSelfAttention(width, heads, adjacency, band, dropout)
        self.cross_attn = MultiHeadAttention(width, memory_width, heads, memory_width // heads, width, dropout)
        self.ffn = nn.Sequential(nn.Linear(width, width), nn.ReLU(), nn.Dropout(dropout), nn.Linear(width, width))
        self.norm1, self.norm2, self.norm3 = nn.LayerNorm(width), nn.LayerNorm(width), nn.LayerNorm(width)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, memory: torch.Tensor, frame_mask: torch.Tensor | None,
                memory_allowed: torch.Tensor, need_weights: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """x (B, U, S), memory (B, K, E), memory_allowed (B, 1, K) -> (B, U, S), self-attention weights if asked."""
        a, weights = self.self_attn(self.norm1(x), frame_mask, need_weights)
        x = x + self.dropout(a)
        h = self.norm2(x)
        x = x + self.dropout(self.cross_attn(h, memory, memory, memory_allowed)[0])
        return x + self.dropout(self.ffn(self.norm3(x))), weights

    def step(self, x: torch.Tensor, memory: torch.Tensor, memory_allowed: torch.Tensor,
             cache: dict[str, torch.Tensor]) -> torch.Tensor:
        """The layer for one new frame x (B, 1, S) of generation, with the earlier frames' keys / values in
        ``cache``: the same numbers as :meth:`forward` on the whole prefix, at the cost of one frame."""
        sa = self.self_attn
        h = self.norm1(x)
        x = x + sa.attention.step(h, h, h @ sa.adjacency, cache, sa.band)
        x = x + self.cross_attn.cross_step(self.norm2(x), memory, memory_allowed, cache)
        return x + self.ffn(self.norm3(x))
