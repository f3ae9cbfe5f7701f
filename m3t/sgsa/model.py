"""The text -> skeleton production model of SGSA (Saunders et al. 2022, "Skeletal Graph Self-Attention") and its
Progressive Transformers baseline (PT, Saunders et al. 2020), one class picked by ``cfg.decoder_layers``.

Spoken-language encoder (Sec. 4.1): word embedding x sqrt(E) + sinusoidal positions -> pre-norm transformer encoder
with a final LayerNorm (JoeyNMT) -> memory (B, K, E); optional gloss head on the memory (CTC logits, class 0 = blank).

Both decoders take the input path of Progressive Transformers' JoeyNMT decoder: frames embedded by a Linear layer,
plus sinusoidal positions, dropout, then pre-norm layers (x + sublayer(LayerNorm(x))) and a final LayerNorm before
the output Linear. Pre-norm with the final LayerNorm is what keeps the residual stream bounded under noise
augmentation; post-norm layers fed raw frames (this model's first form) never learned the counter on the embedded
corpus, and pre-norm without the final LayerNorm diverged under noise.

SGSA decoder (Sec. 4.2, ``decoder_layers = L >= 1``): width S throughout ("an embedding size of S": the embedding is
Linear(S, S), so every layer's stream keeps the skeleton's S columns). Each of the L layers: skeletal graph
self-attention (h heads of full width S; values V_A = x A* W_V on the normalised stream; causal mask banded to the
last N frames) -> encoder-decoder attention (S -> E queries over the memory, back to S) -> feed-forward S -> S -> S;
a final Linear(S, S) gives the next frames.
PT decoder (``decoder_layers = 0``): frames embedded Linear(S, W) -> ``standard_layers`` standard transformer decoder
layers (memory projected E -> W when E != W) -> Linear(W, S).

Training input convention (teacher forcing): for a target clip of U frames, ``frames_in[:, 0]`` is the start frame
(all zeros, counter 0) and ``frames_in[:, t] = target[:, t - 1]``; the output at t predicts ``target[:, t]``. The
target's counter (last) column is (t + 1) / U for frame t (0-based), so the last frame has counter 1.
Generation (counter decoding, PT) feeds each prediction back and stops a sequence at its first frame t (1-based),
t >= ``cfg.min_frames``, at which t reaches the length its counters so far point to (:class:`CounterStop`).

The attention blocks, their key / value cache and PT's layer are in :mod:`m3t.sgsa.attention`, the SGSA layer in
:mod:`m3t.sgsa.skeletal_attention`.

Axis legend: B batch, K text tokens, E encoder width, G gloss classes, U frames, S skeleton width (coordinates + 1
counter, the counter last), W width of the PT decoder, h heads.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from m3t.positional_encoding import sinusoid_table
from m3t.sgsa.attention import StandardDecoderLayer, causal_band
from m3t.sgsa.config import SGSAConfig
from m3t.sgsa.skeletal_attention import SGSADecoderLayer


@dataclass(frozen=True)
class SGSADims:
    """Data-dependent sizes: skeleton width S (coordinates + the counter, last), text vocabulary (id 0 = PAD), gloss
    classes incl. the CTC blank at 0 (0 = no gloss head)."""

    width: int
    text_vocab: int
    gloss_vocab: int = 0


@dataclass(frozen=True)
class SGSAOutput:
    frames: torch.Tensor  # (B, U, S) predicted next frames (counter in the last column)
    gloss_logits: torch.Tensor | None  # (B, K, G) or None without a gloss head


class CounterStop:
    """Counter decoding's stop rule, read from the trend of a sequence's counters rather than from the last one.

    The counter of frame i of a U-frame clip is i / U. After frame t the counters c_1 .. c_t give the least-squares
    length through the origin, U_t = sum(i^2) / sum(i c_i); the sequence ends at its first frame t >= ``min_frames``
    with t >= U_t - 1/2 (while sum(i c_i) <= 0 it goes on). A perfect counter gives U_t = U and ends at t = U
    exactly, as the rule of Progressive Transformers (the last counter reaching 1 - 0.5 / t) does. A learned counter
    free-running in its own output lags near the end (on the embedded dev split the last counters crawled from
    ~0.85 to 1 over a third of the clip's length more), and the last-counter rule then ran ~1.4x too long for SGSA:
    within +-25 % of the true length on 4 of 23 dev clips, against 22 of 23 with the trend (PT: 17 and 21).
    Tracks a batch: ``update`` takes the active rows' counters of frame t and says which rows end there."""

    def __init__(self, batch: int, min_frames: int, device: torch.device | None = None):
        self.min_frames = min_frames
        self.weighted = torch.zeros(batch, dtype=torch.float64, device=device)  # sum of i c_i per row
        self.squares = 0.0  # sum of i^2, the same for every row

    def update(self, t: int, counters: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """counters (B_active,) of frame t (1-based) of batch rows ``rows`` -> (B_active,) bool: ends at t."""
        self.weighted[rows] += t * counters.double()
        self.squares += float(t * t)
        weighted = self.weighted[rows]
        length = self.squares / weighted.clamp(min=1e-12)
        return (weighted > 0) & (t >= length - 0.5) & (t >= self.min_frames)


class SGSAProduction(nn.Module):
    """Text ids -> skeleton frames: SGSA (``cfg.decoder_layers >= 1``) or PT (``cfg.decoder_layers == 0``)."""

    def __init__(self, cfg: SGSAConfig, dims: SGSADims, adjacency: np.ndarray | torch.Tensor | None):
        super().__init__()
        self.cfg, self.dims = cfg, dims
        e, s = cfg.encoder_width, dims.width
        self.text_embedding = nn.Embedding(dims.text_vocab, e, padding_idx=0)
        encoder_layer = nn.TransformerEncoderLayer(e, cfg.encoder_heads, cfg.encoder_ffn, cfg.dropout,
                                                   batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(encoder_layer, cfg.encoder_layers, norm=nn.LayerNorm(e),
                                             enable_nested_tensor=False)
        self.gloss_head = nn.Linear(e, dims.gloss_vocab) if dims.gloss_vocab > 0 else None
        self.dropout = nn.Dropout(cfg.dropout)
        if cfg.decoder_layers > 0:
            if adjacency is None:
                raise ValueError("SGSA (decoder_layers > 0) needs the (S, S) normalised adjacency A*")
            if e % cfg.decoder_heads:
                raise ValueError(f"sgsa.encoder_width {e} is not divisible by decoder_heads {cfg.decoder_heads} "
                                 "(the cross-attention heads)")
            a = torch.as_tensor(adjacency, dtype=torch.float32)
            w = s
            self.layers = nn.ModuleList(SGSADecoderLayer(s, e, cfg.decoder_heads, a, cfg.band, cfg.dropout)
                                        for _ in range(cfg.decoder_layers))
            self.memory_projection = None
        else:
            w = cfg.standard_width
            self.memory_projection = nn.Linear(e, w) if e != w else None
            self.layers = nn.ModuleList(StandardDecoderLayer(w, cfg.decoder_heads, cfg.standard_ffn, cfg.dropout)
                                        for _ in range(cfg.standard_layers))
        self.frame_embedding = nn.Linear(s, w)
        self.final_norm = nn.LayerNorm(w)
        self.output = nn.Linear(w, s)
        # derived from the config, so kept out of the state dict; longer inputs get a fresh table
        self.register_buffer("text_positions", sinusoid_table(cfg.max_text_tokens + 2, e), persistent=False)
        self.register_buffer("frame_positions", sinusoid_table(cfg.max_frames + 1, w), persistent=False)
        for p in self.parameters():  # Xavier initialisation (SGSA Sec. 5)
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)
        with torch.no_grad():
            self.text_embedding.weight[0].zero_()  # PAD stays a zero vector (it gets no gradient)

    @staticmethod
    def _positions(table: torch.Tensor, length: int) -> torch.Tensor:
        """The first ``length`` rows of a sinusoid table, computed afresh past its end."""
        if length <= table.shape[0]:
            return table[:length]
        return sinusoid_table(length, table.shape[1]).to(table)

    def encode(self, text_ids: torch.Tensor, text_mask: torch.Tensor) -> torch.Tensor:
        """text_ids (B, K), text_mask (B, K) True on real tokens -> memory (B, K, E)."""
        e = self.cfg.encoder_width
        x = self.text_embedding(text_ids) * math.sqrt(e) + self._positions(self.text_positions, text_ids.shape[1])
        return self.encoder(self.dropout(x), src_key_padding_mask=~text_mask)

    def gloss_logits(self, memory: torch.Tensor) -> torch.Tensor | None:
        """(B, K, G) CTC logits of the gloss head (class 0 = blank), None without one."""
        return None if self.gloss_head is None else self.gloss_head(memory)

    def _decode(self, memory: torch.Tensor, text_mask: torch.Tensor, frames_in: torch.Tensor,
                frame_mask: torch.Tensor | None, weights_of: int | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """decode, and the self-attention weights (B, h, U, U) of layer ``weights_of`` when not None."""
        memory_allowed = text_mask[:, None, :]
        weights = None
        u = frames_in.shape[1]
        x = self.dropout(self.frame_embedding(frames_in) + self._positions(self.frame_positions, u))
        if self.cfg.decoder_layers > 0:  # SGSA: its layers build their banded mask
            for i, layer in enumerate(self.layers):
                x, w = layer(x, memory, frame_mask, memory_allowed, need_weights=i == weights_of)
                weights = w if i == weights_of else weights
        else:  # PT
            if self.memory_projection is not None:
                memory = self.memory_projection(memory)
            self_allowed = causal_band(u, u, math.inf, x.device)[None]
            if frame_mask is not None:
                self_allowed = self_allowed & frame_mask[:, None, :]
            for i, layer in enumerate(self.layers):
                x, w = layer(x, memory, self_allowed, memory_allowed, need_weights=i == weights_of)
                weights = w if i == weights_of else weights
        return self.output(self.final_norm(x)), weights

    def decode(self, memory: torch.Tensor, text_mask: torch.Tensor, frames_in: torch.Tensor,
               frame_mask: torch.Tensor | None = None) -> torch.Tensor:
        """memory (B, K, E), text_mask (B, K), frames_in (B, U, S) (start frame then the previous targets, see the
        module docstring), frame_mask (B, U) True on real frames -> predicted next frames (B, U, S)."""
        return self._decode(memory, text_mask, frames_in, frame_mask, None)[0]

    def forward(self, text_ids: torch.Tensor, text_mask: torch.Tensor, frames_in: torch.Tensor,
                frame_mask: torch.Tensor | None = None) -> SGSAOutput:
        memory = self.encode(text_ids, text_mask)
        return SGSAOutput(self.decode(memory, text_mask, frames_in, frame_mask), self.gloss_logits(memory))

    @contextmanager
    def _evaluating(self) -> Iterator[None]:
        """eval mode (no dropout) for the duration, the previous mode restored after."""
        was_training = self.training
        self.eval()
        try:
            yield
        finally:
            self.train(was_training)

    @torch.no_grad()
    def generate(self, text_ids: torch.Tensor, text_mask: torch.Tensor, max_frames: int,
                 true_lengths: torch.Tensor | None = None) -> list[torch.Tensor]:
        """Autoregressive counter decoding in eval mode: text_ids / text_mask (B, K) -> per sequence the produced
        frames (U_b, S), counter included. A sequence stops where :class:`CounterStop` ends it, or after
        ``max_frames``. With ``true_lengths`` (B,) (ground-truth counter: parity with published
        PT numbers only) sequence b runs exactly U_b = true_lengths[b] frames (max_frames is not applied) and the
        counter of its produced frame t (1-based) is overwritten by the true t / U_b before it is fed back.
        Finished sequences are dropped from the batch, so nothing of theirs changes after they stop."""
        b, s = text_ids.shape[0], self.dims.width
        with self._evaluating():
            memory = self.encode(text_ids, text_mask)
            if true_lengths is not None:
                true_lengths = torch.as_tensor(true_lengths, device=text_ids.device).long().reshape(b)
                if (true_lengths < 1).any():
                    raise ValueError(f"generate: true_lengths must be >= 1, got {true_lengths.tolist()}")
                steps = int(true_lengths.max()) if b else 0
            else:
                steps = max_frames
            if self.memory_projection is not None:
                memory = self.memory_projection(memory)
            allowed = text_mask[:, None, :]
            caches: list[dict[str, torch.Tensor]] = [{} for _ in self.layers]  # per layer: keys / values so far
            frame = torch.zeros(b, 1, s, device=memory.device, dtype=memory.dtype)  # the start frame
            produced = torch.zeros(b, steps, s, device=memory.device, dtype=memory.dtype)
            lengths = torch.full((b,), steps, dtype=torch.long, device=memory.device)
            active = torch.arange(b, device=memory.device)  # unfinished sequences; finished ones are not re-run
            stop = CounterStop(b, self.cfg.min_frames, memory.device)
            for t in range(1, steps + 1):
                if not len(active):
                    break
                pred = self._step(frame, t - 1, memory, allowed, caches)[:, 0]  # (B_active, S)
                if true_lengths is not None:
                    pred[:, -1] = t / true_lengths[active].to(pred.dtype)
                    done = true_lengths[active] == t
                else:
                    done = stop.update(t, pred[:, -1], active)
                produced[active, t - 1] = pred
                lengths[active[done]] = t
                keep = ~done
                active, frame, memory, allowed = active[keep], pred[keep, None], memory[keep], allowed[keep]
                for cache in caches:
                    for key in cache:
                        cache[key] = cache[key][keep]
        return [produced[i, : int(lengths[i])] for i in range(b)]

    def _step(self, frame: torch.Tensor, position: int, memory: torch.Tensor, allowed: torch.Tensor,
              caches: list[dict[str, torch.Tensor]]) -> torch.Tensor:
        """The decoder on one new input frame (B, 1, S) at ``position`` (0 = the start frame), the earlier frames
        in ``caches``; memory already projected for PT -> the predicted next frame (B, 1, S)."""
        x = self.frame_embedding(frame) + self._positions(self.frame_positions, position + 1)[position]
        for layer, cache in zip(self.layers, caches):
            x = layer.step(x, memory, allowed, cache)
        return self.output(self.final_norm(x))

    @torch.no_grad()
    def self_attention(self, text_ids: torch.Tensor, text_mask: torch.Tensor, frames_in: torch.Tensor,
                       layer: int) -> torch.Tensor:
        """(B, h, U, U) self-attention weights of decoder layer ``layer`` (0-based; SGSA or PT layer), teacher forced
        on frames_in (B, U, S), in eval mode: for an attention-map picture."""
        if not 0 <= layer < len(self.layers):
            raise ValueError(f"self_attention: layer {layer} out of range 0..{len(self.layers) - 1}")
        with self._evaluating():
            memory = self.encode(text_ids, text_mask)
            return self._decode(memory, text_mask, frames_in, None, layer)[1]
