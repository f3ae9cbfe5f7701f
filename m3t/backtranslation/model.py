"""The sign-to-text transformer of back-translation (M3T App. 0.D.4: SL-T, Camgoz et al. 2020, without its CNN
front end, on ground-truth 3DMM parameters).

frames (B, T, D) -> per-dim standardisation (train-split mean / std, kept in the state dict) -> linear -> LayerNorm
-> softsign (SL-T's spatial embedding; LayerNorm instead of its BatchNorm, so padded frames never enter a
statistic) -> + sinusoidal positions -> pre-norm transformer encoder -> memory (B, T, d).
Text: word embedding + sinusoidal positions -> pre-norm transformer decoder (causal, cross-attending to the
memory) -> word logits. Optional gloss head on the memory: logits over ``<blank>`` + glosses for CTC (SL-T's
recognition loss; with pseudo-glosses where the corpus has none).

Axis legend: B batch, T frames, D input dim, d model width, K text tokens, V text vocabulary, G gloss classes.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from m3t.backtranslation.config import BackTranslationConfig
from m3t.positional_encoding import sinusoid_table


@dataclass(frozen=True)
class BackTranslationDims:
    """Data-dependent sizes: per-frame input dim, text vocabulary, gloss vocabulary (0 = no gloss head)."""

    input_dim: int
    text_vocab: int
    gloss_vocab: int = 0


@dataclass(frozen=True)
class BackTranslationOutput:
    text_logits: torch.Tensor  # (B, K, V)
    gloss_logits: torch.Tensor | None  # (B, T, G) or None without a gloss head


class SignToText(nn.Module):
    def __init__(self, cfg: BackTranslationConfig, dims: BackTranslationDims):
        super().__init__()
        self.cfg, self.dims = cfg, dims
        d = cfg.d_model
        self.register_buffer("feature_mean", torch.zeros(dims.input_dim))
        self.register_buffer("feature_std", torch.ones(dims.input_dim))
        # derived from the config, so kept out of the state dict
        self.register_buffer("positions", sinusoid_table(max(cfg.max_frames, cfg.max_text_tokens + 1), d),
                             persistent=False)
        self.frame_embedding = nn.Sequential(nn.Linear(dims.input_dim, d), nn.LayerNorm(d), nn.Softsign())
        self.text_embedding = nn.Embedding(dims.text_vocab, d)
        self.dropout = nn.Dropout(cfg.dropout)
        encoder_layer = nn.TransformerEncoderLayer(d, cfg.attention_heads, cfg.ffn_dim, cfg.dropout,
                                                   batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(encoder_layer, cfg.encoder_layers, norm=nn.LayerNorm(d),
                                             enable_nested_tensor=False)
        decoder_layer = nn.TransformerDecoderLayer(d, cfg.attention_heads, cfg.ffn_dim, cfg.dropout,
                                                   batch_first=True, norm_first=True)
        self.decoder = nn.TransformerDecoder(decoder_layer, cfg.decoder_layers, norm=nn.LayerNorm(d))
        self.text_head = nn.Linear(d, dims.text_vocab)
        self.gloss_head = nn.Linear(d, dims.gloss_vocab) if dims.gloss_vocab > 0 else None
        for p in self.parameters():  # SL-T: Xavier initialisation
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)

    def set_feature_statistics(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        """The train split's per-dim frame mean and std (D,), used to standardise every input."""
        self.feature_mean.copy_(torch.as_tensor(mean))
        self.feature_std.copy_(torch.as_tensor(std))

    def encode(self, frames: torch.Tensor, frame_mask: torch.Tensor) -> torch.Tensor:
        """frames (B, T, D), frame_mask (B, T) True on real frames -> memory (B, T, d)."""
        x = self.frame_embedding((frames - self.feature_mean) / self.feature_std)
        x = self.dropout(x + self.positions[: x.shape[1]])
        return self.encoder(x, src_key_padding_mask=~frame_mask)

    def decode(self, memory: torch.Tensor, frame_mask: torch.Tensor, text_in: torch.Tensor,
               text_mask: torch.Tensor | None = None) -> torch.Tensor:
        """memory (B, T, d), text_in (B, K) ids starting with BOS, text_mask (B, K) True on real tokens ->
        logits (B, K, V) of each next token."""
        k = text_in.shape[1]
        y = self.dropout(self.text_embedding(text_in) + self.positions[:k])
        causal = torch.triu(torch.ones(k, k, dtype=torch.bool, device=y.device), diagonal=1)
        y = self.decoder(y, memory, tgt_mask=causal, memory_key_padding_mask=~frame_mask,
                         tgt_key_padding_mask=None if text_mask is None else ~text_mask)
        return self.text_head(y)

    def gloss_logits(self, memory: torch.Tensor) -> torch.Tensor | None:
        """(B, T, G) CTC logits of the gloss head (class 0 = blank), None without one."""
        return None if self.gloss_head is None else self.gloss_head(memory)

    def forward(self, frames: torch.Tensor, frame_mask: torch.Tensor, text_in: torch.Tensor,
                text_mask: torch.Tensor | None = None) -> BackTranslationOutput:
        memory = self.encode(frames, frame_mask)
        return BackTranslationOutput(self.decode(memory, frame_mask, text_in, text_mask), self.gloss_logits(memory))
