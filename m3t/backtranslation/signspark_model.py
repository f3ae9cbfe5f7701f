"""SignSparK_BT's network (their ``SignModel`` for inference), rebuilt under their module names so that a released
``model_state`` loads with ``strict=True``; the sources, the layer layout and the departures are described in
:mod:`m3t.backtranslation.signspark`, which reads their model directory and decodes with it.

Axis legend: B batch, T frames, F input features (240), L text tokens, D hidden size, H heads, V text vocabulary.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from m3t.positional_encoding import sinusoid_table

ACTIVATIONS = {"relu": nn.ReLU, "relu6": nn.ReLU6, "prelu": nn.PReLU, "selu": nn.SELU, "celu": nn.CELU,
               "gelu": nn.GELU, "sigmoid": nn.Sigmoid, "softplus": nn.Softplus, "softshrink": nn.Softshrink,
               "softsign": nn.Softsign, "tanh": nn.Tanh, "tanhshrink": nn.Tanhshrink}
MAX_POSITIONS = 5000  # their PositionalEncoding's max_len


@dataclass(frozen=True)
class SignSparkConfig:
    """Sizes and embedding choices of one released model (their ``config.yaml`` ``model`` section and vocabularies)."""

    feature_size: int
    hidden_size: int
    text_vocab_size: int
    gloss_vocab_size: int | None  # None: trained without the CTC head
    encoder_layers: int = 8
    encoder_heads: int = 4
    encoder_ff_size: int = 2048
    decoder_layers: int = 4
    decoder_heads: int = 8
    decoder_ff_size: int = 2048
    sign_norm: str | None = None  # "batch" | "layer" | "group"
    sign_activation: str | None = None
    sign_scale: float | None = None  # factor the embedding is multiplied by; None: not scaled
    text_norm: str | None = None
    text_activation: str | None = None
    text_scale: float | None = None
    text_padding_idx: int = 1
    tied_softmax: bool = False
    max_positions: int = MAX_POSITIONS


class _Attention(nn.Module):
    """Their ``MultiHeadedAttention``: q, k, v projections, scaled dot product, ``output_layer``."""

    def __init__(self, heads: int, size: int):
        super().__init__()
        self.num_heads, self.head_size = heads, size // heads
        self.k_layer, self.v_layer, self.q_layer = nn.Linear(size, size), nn.Linear(size, size), nn.Linear(size, size)
        self.output_layer = nn.Linear(size, size)

    def forward(self, k: torch.Tensor, v: torch.Tensor, q: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """k, v (B, M, D), q (B, N, D), mask (B or 1, 1 or N, M) bool (True: attend) -> (B, N, D)."""
        def heads(x: torch.Tensor) -> torch.Tensor:
            return x.reshape(x.shape[0], -1, self.num_heads, self.head_size).transpose(1, 2)  # (B, H, M, D / H)

        keys, values = heads(self.k_layer(k)), heads(self.v_layer(v))
        queries = heads(self.q_layer(q)) / math.sqrt(self.head_size)
        scores = (queries @ keys.transpose(2, 3)).masked_fill(~mask[:, None], float("-inf"))  # (B, H, N, M)
        context = (scores.softmax(-1) @ values).transpose(1, 2)  # (B, N, H, D / H)
        return self.output_layer(context.reshape(context.shape[0], -1, self.num_heads * self.head_size))


class _FeedForward(nn.Module):
    def __init__(self, size: int, ff_size: int):
        super().__init__()
        self.layer_norm = nn.LayerNorm(size, eps=1e-6)
        # weights at indices 0 and 3, as in their Sequential(Linear, ReLU, Dropout, Linear, Dropout)
        self.pwff_layer = nn.Sequential(nn.Linear(size, ff_size), nn.ReLU(), nn.Identity(), nn.Linear(ff_size, size))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pwff_layer(self.layer_norm(x)) + x


class _Positions(nn.Module):
    def __init__(self, size: int, max_len: int):
        super().__init__()
        self.register_buffer("pe", sinusoid_table(max_len, size)[None])  # (1, max_len, D): in their state dict

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[1] > self.pe.shape[1]:
            raise ValueError(f"{x.shape[1]} steps, more than the model's {self.pe.shape[1]} positions")
        return x + self.pe[:, : x.shape[1]]


class _EncoderLayer(nn.Module):
    def __init__(self, size: int, ff_size: int, heads: int):
        super().__init__()
        self.layer_norm = nn.LayerNorm(size, eps=1e-6)
        self.src_src_att = _Attention(heads, size)
        self.feed_forward = _FeedForward(size, ff_size)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        h = self.layer_norm(x)
        return self.feed_forward(self.src_src_att(h, h, h, mask) + x)


class _DecoderLayer(nn.Module):
    def __init__(self, size: int, ff_size: int, heads: int):
        super().__init__()
        self.trg_trg_att, self.src_trg_att = _Attention(heads, size), _Attention(heads, size)
        self.feed_forward = _FeedForward(size, ff_size)
        self.x_layer_norm, self.dec_layer_norm = nn.LayerNorm(size, eps=1e-6), nn.LayerNorm(size, eps=1e-6)

    def forward(self, x: torch.Tensor, memory: torch.Tensor, src_mask: torch.Tensor,
                trg_mask: torch.Tensor) -> torch.Tensor:
        h = self.x_layer_norm(x)
        h1 = self.trg_trg_att(h, h, h, trg_mask) + x
        return self.feed_forward(self.src_trg_att(memory, memory, self.dec_layer_norm(h1), src_mask) + h1)


class _Stack(nn.Module):
    """Their TransformerEncoder / TransformerDecoder: positions, layers, final LayerNorm (+ ``output_layer``)."""

    def __init__(self, layers: list[nn.Module], size: int, max_len: int, vocab: int | None = None):
        super().__init__()
        self.layers = nn.ModuleList(layers)
        self.layer_norm = nn.LayerNorm(size, eps=1e-6)
        self.pe = _Positions(size, max_len)
        if vocab is not None:
            self.output_layer = nn.Linear(size, vocab, bias=False)


class _Norm(nn.Module):
    """Their ``MaskedNorm`` at evaluation: the norm (under ``.norm``) over every frame of (B, T, D)."""

    def __init__(self, kind: str, groups: int, features: int):
        super().__init__()
        norms = {"batch": lambda: nn.BatchNorm1d(features), "layer": lambda: nn.LayerNorm(features),
                 "group": lambda: nn.GroupNorm(groups, features)}
        self.norm = norms[kind]()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm(x.reshape(-1, x.shape[-1])).reshape(x.shape)


class _Embedding(nn.Module):
    """Their SpatialEmbeddings (``ln``: frames) and Embeddings (``lut``: words): first layer, norm, activation,
    scale."""

    def __init__(self, first: str, layer: nn.Module, size: int, heads: int, norm: str | None,
                 activation: str | None, scale: float | None):
        super().__init__()
        self.first, self.scale = first, scale
        self.add_module(first, layer)
        self.norm = _Norm(norm, heads, size) if norm else None
        self.activation = ACTIVATIONS[activation]() if activation else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = getattr(self, self.first)(x)
        x = self.norm(x) if self.norm is not None else x
        x = self.activation(x) if self.activation is not None else x
        return x * self.scale if self.scale is not None else x


class SignSparkBT(nn.Module):
    """Their ``SignModel`` for inference, module names as theirs so that ``model_state`` loads strictly."""

    def __init__(self, cfg: SignSparkConfig):
        super().__init__()
        self.cfg = cfg
        d = cfg.hidden_size
        self.sgn_embed = _Embedding("ln", nn.Linear(cfg.feature_size, d), d, cfg.encoder_heads, cfg.sign_norm,
                                    cfg.sign_activation, cfg.sign_scale)
        self.encoder = _Stack([_EncoderLayer(d, cfg.encoder_ff_size, cfg.encoder_heads)
                               for _ in range(cfg.encoder_layers)], d, cfg.max_positions)
        self.gloss_output_layer = nn.Linear(d, cfg.gloss_vocab_size) if cfg.gloss_vocab_size else None
        self.txt_embed = _Embedding("lut", nn.Embedding(cfg.text_vocab_size, d, padding_idx=cfg.text_padding_idx), d,
                                    cfg.decoder_heads, cfg.text_norm, cfg.text_activation, cfg.text_scale)
        self.decoder = _Stack([_DecoderLayer(d, cfg.decoder_ff_size, cfg.decoder_heads)
                               for _ in range(cfg.decoder_layers)], d, cfg.max_positions, cfg.text_vocab_size)
        if cfg.tied_softmax:
            self.decoder.output_layer.weight = self.txt_embed.lut.weight

    def encode(self, frames: torch.Tensor, frame_mask: torch.Tensor) -> torch.Tensor:
        """frames (B, T, F), frame_mask (B, T) bool (True: a frame) -> memory (B, T, D)."""
        x = self.encoder.pe(self.sgn_embed(frames))
        for layer in self.encoder.layers:
            x = layer(x, frame_mask[:, None])
        return self.encoder.layer_norm(x)

    def decode(self, memory: torch.Tensor, frame_mask: torch.Tensor, tokens: torch.Tensor) -> torch.Tensor:
        """memory (B, T, D), frame_mask (B, T), tokens (B, L) -> word logits (B, L, V), each step seeing only
        the tokens up to it."""
        x = self.decoder.pe(self.txt_embed(tokens))
        causal = torch.ones(tokens.shape[1], tokens.shape[1], dtype=torch.bool, device=tokens.device).tril()[None]
        for layer in self.decoder.layers:
            x = layer(x, memory, frame_mask[:, None], causal)
        return self.decoder.output_layer(self.decoder.layer_norm(x))
