"""Attention of the SGSA / PT production model (:mod:`m3t.sgsa.model`): the causal band mask, multi-head attention
with free widths and its key / value cache for generation (one new frame at a time, the memory's keys / values
projected once), and the standard pre-norm decoder layer of the Progressive Transformers baseline.

Axis legend: B batch, K text tokens, U frames (Tq / Tk: query / key frames), h heads, d head width, W width of the
PT decoder.
"""
from __future__ import annotations

import math

import torch
from torch import nn


def causal_band(queries: int, keys: int, band: float, device: torch.device | None = None) -> torch.Tensor:
    """(queries, keys) bool, True where query frame i may attend to key frame j: i - band <= j <= i."""
    i = torch.arange(queries, device=device)[:, None]
    j = torch.arange(keys, device=device)[None, :]
    allowed = j <= i
    if math.isfinite(band):
        allowed &= i - j <= band
    return allowed


class MultiHeadAttention(nn.Module):
    """Scaled dot-product attention with free widths: queries (.., query_width) and keys / values (.., key_width) are
    projected to ``heads`` x ``head_width``; the concatenated heads are projected to ``out_width``. Used for every
    attention of the model (SGSA: head_width = S; cross-attention: S -> E; PT: the standard W / h heads)."""

    def __init__(self, query_width: int, key_width: int, heads: int, head_width: int, out_width: int,
                 dropout: float):
        super().__init__()
        self.heads, self.head_width = heads, head_width
        self.q = nn.Linear(query_width, heads * head_width)
        self.k = nn.Linear(key_width, heads * head_width)
        self.v = nn.Linear(key_width, heads * head_width)
        self.out = nn.Linear(heads * head_width, out_width)
        self.dropout = nn.Dropout(dropout)

    def split(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, h * d) -> (B, h, T, d)."""
        return x.unflatten(-1, (self.heads, self.head_width)).transpose(1, 2)

    def forward(self, query: torch.Tensor, key: torch.Tensor | None, value: torch.Tensor | None,
                allowed: torch.Tensor | None = None, need_weights: bool = False,
                cached: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """query (B, Tq, .), key / value (B, Tk, .), allowed (B or 1, Tq, Tk) bool (True = may attend) ->
        (B, Tq, out_width) and the weights (B, h, Tq, Tk) when asked. Masked weights are exactly 0; a row with no
        allowed key gets all-zero weights (its output is the output bias). ``cached``: keys and values already
        projected and split (B, h, Tk, d), ``key`` / ``value`` unused."""
        q = self.split(self.q(query))
        k, v = cached if cached is not None else (self.split(self.k(key)), self.split(self.v(value)))
        scores = q @ k.transpose(-1, -2) / math.sqrt(self.head_width)
        if allowed is not None:
            allowed = allowed[:, None]  # broadcast over heads
            empty = ~allowed.any(-1, keepdim=True)
            # fully masked rows are opened before the softmax (no NaN) and zeroed after it
            weights = torch.softmax(scores.masked_fill(~(allowed | empty), -math.inf), dim=-1)
            weights = weights.masked_fill(empty, 0.0)
        else:
            weights = torch.softmax(scores, dim=-1)
        context = (self.dropout(weights) @ v).transpose(1, 2).flatten(2)
        return self.out(context), (weights if need_weights else None)

    def step(self, query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, cache: dict[str, torch.Tensor],
             window: float = math.inf) -> torch.Tensor:
        """Incremental self-attention of generation: one new frame (B, 1, .) appends its key / value to ``cache``
        and attends to the cached frames of the last ``window`` steps and itself (the causal band of
        :func:`causal_band`); the cache keeps no more than it can use. -> (B, 1, out_width)."""
        k, v = self.split(self.k(key)), self.split(self.v(value))
        keys = k if "k" not in cache else torch.cat([cache["k"], k], dim=2)
        values = v if "v" not in cache else torch.cat([cache["v"], v], dim=2)
        if math.isfinite(window):
            keys, values = keys[:, :, -(int(window) + 1):], values[:, :, -(int(window) + 1):]
        cache["k"], cache["v"] = keys, values
        q = self.split(self.q(query))
        weights = torch.softmax(q @ keys.transpose(-1, -2) / math.sqrt(self.head_width), dim=-1)
        return self.out((weights @ values).transpose(1, 2).flatten(2))

    def cross_step(self, query: torch.Tensor, memory: torch.Tensor, allowed: torch.Tensor,
                   cache: dict[str, torch.Tensor]) -> torch.Tensor:
        """Cross-attention of one new frame over the memory, whose keys / values are projected once per
        generation and kept in ``cache``. allowed (B, 1, K) -> (B, 1, out_width)."""
        if "mk" not in cache:
            cache["mk"], cache["mv"] = self.split(self.k(memory)), self.split(self.v(memory))
        return self(query, None, None, allowed, cached=(cache["mk"], cache["mv"]))[0]


class StandardDecoderLayer(nn.Module):
    """A standard pre-norm transformer decoder layer (PT's JoeyNMT layer; the math of nn.TransformerDecoderLayer with
    ReLU and norm_first=True): causal self-attention, cross-attention over the memory, feed-forward."""

    def __init__(self, width: int, heads: int, ffn: int, dropout: float):
        super().__init__()
        self.self_attn = MultiHeadAttention(width, width, heads, width // heads, width, dropout)
        self.cross_attn = MultiHeadAttention(width, width, heads, width // heads, width, dropout)
        self.ffn = nn.Sequential(nn.Linear(width, ffn), nn.ReLU(), nn.Dropout(dropout), nn.Linear(ffn, width))
        self.norm1, self.norm2, self.norm3 = nn.LayerNorm(width), nn.LayerNorm(width), nn.LayerNorm(width)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, memory: torch.Tensor, self_allowed: torch.Tensor,
                memory_allowed: torch.Tensor, need_weights: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """x (B, U, W), memory (B, K, W), self_allowed (B or 1, U, U), memory_allowed (B, 1, K) -> (B, U, W)."""
        h = self.norm1(x)
        a, weights = self.self_attn(h, h, h, self_allowed, need_weights)
        x = x + self.dropout(a)
        x = x + self.dropout(self.cross_attn(self.norm2(x), memory, memory, memory_allowed)[0])
        return x + self.dropout(self.ffn(self.norm3(x))), weights

    def step(self, x: torch.Tensor, memory: torch.Tensor, memory_allowed: torch.Tensor,
             cache: dict[str, torch.Tensor]) -> torch.Tensor:
        """One new frame x (B, 1, W) of generation with a key / value cache (see SGSADecoderLayer.step)."""
        h = self.norm1(x)
        x = x + self.self_attn.step(h, h, h, cache)
        x = x + self.cross_attn.cross_step(self.norm2(x), memory, memory_allowed, cache)
        return x + self.ffn(self.norm3(x))
