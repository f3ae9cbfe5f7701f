"""Greedy decoding for both SMLM tasks (M3T Sec. 3.3), with or without a key/value cache.

Production predicts all four motion streams at every step (one step per 4 frames) and stops a sequence
when any stream emits EOS; translation predicts text ids until ``</s>``. With ``use_cache=True`` only the
new step goes through the decoder (past keys / values are reused); ``use_cache=False`` reruns the whole
prefix every step. Both pick the same tokens (tested), the cache is just faster.

Axis legend: B batch, S = 4 motion streams, U steps, D hidden size.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from m3t.smlm.data import (
    motion_global,
    motion_source,
    pad_sequences,
    prompt_step,
    text_source,
)
from m3t.smlm.model import SignMotionLM
from m3t.smlm.vocab import MOTION_STREAMS, SignVocabulary, VocabularyError


@dataclass(frozen=True)
class GeneratedMotion:
    tokens: dict[str, np.ndarray]  # stream -> (U,) codes, EOS excluded
    stopped: bool  # True when a stream emitted EOS, False when max_steps was reached


def _check_batch(texts: Sequence, languages: Sequence[str], vocab: SignVocabulary) -> None:
    if len(texts) != len(languages):
        raise ValueError(f"{len(texts)} inputs but {len(languages)} languages; give one language per input")
    if not texts:
        raise VocabularyError("nothing to generate: the input list is empty")
    for language in languages:
        vocab.check_language(language)


class _Stepper:
    """Runs the decoder one step at a time, cached or by recomputing the prefix."""

    def __init__(self, model: SignMotionLM, memory: torch.Tensor, memory_mask: torch.Tensor, use_cache: bool):
        self.model, self.memory, self.memory_mask, self.use_cache = model, memory, memory_mask, use_cache
        self.cache, self.prefix = None, None

    def __call__(self, embeds: torch.Tensor) -> torch.Tensor:
        """(B, 1, D) embeddings of the new step -> (B, D) last hidden state."""
        if self.use_cache:
            out = self.model.decode(embeds, self.memory, self.memory_mask, cache=self.cache, use_cache=True)
            self.cache = out.cache
        else:
            self.prefix = embeds if self.prefix is None else torch.cat([self.prefix, embeds], dim=1)
            out = self.model.decode(self.prefix, self.memory, self.memory_mask)
        return out.hidden[:, -1]


@torch.no_grad()
def generate_motion(model: SignMotionLM, vocab: SignVocabulary, texts: Sequence[str], languages: Sequence[str],
                    max_steps: int | None = None, use_cache: bool = True, min_steps: int = 0,
                    truncate_text: bool = False) -> list[GeneratedMotion]:
    """Text -> motion tokens for a batch of sentences (production); EOS is not allowed before ``min_steps``.
    A sentence over ``smlm.max_text_tokens`` is refused, or (``truncate_text``, evaluations) cut to it."""
    _check_batch(texts, languages, vocab)
    max_steps = max_steps or model.cfg.max_motion_tokens
    model.eval()
    device = next(model.parameters()).device
    sources = [text_source(vocab, np.asarray(vocab.encode_text(t, model.cfg.max_text_tokens, truncate_text)), lang)
               for t, lang in zip(texts, languages)]
    src, src_mask = (t.to(device) for t in pad_sequences(sources, vocab.pad_id))
    step = model.embed_fused(torch.from_numpy(np.stack([prompt_step(vocab, lang) for lang in languages]))[:, None].to(device))
    stepper = _Stepper(model, model.encode(model.embed(src), src_mask), src_mask, use_cache)
    eos = np.array([vocab.codebooks[s] for s in MOTION_STREAMS])  # each motion head's EOS class
    batch = len(texts)
    steps, lengths = [], np.full(batch, -1)
    for u in range(max_steps):
        hidden = stepper(step)
        logits = [model.heads[s](hidden) for s in MOTION_STREAMS]
        if u < min_steps:
            for lg in logits:
                lg[..., -1] = float("-inf")  # the EOS class is each motion head's last
        local = torch.stack([lg.argmax(-1) for lg in logits], dim=-1).cpu().numpy()  # (B, S)
        lengths[(lengths < 0) & (local == eos).any(-1)] = u
        steps.append(local)
        if (lengths >= 0).all():
            break
        codes = np.minimum(local, eos - 1)  # finished rows: any valid id, ignored
        step = model.embed_fused(torch.from_numpy(motion_global(vocab, codes))[:, None].to(device))
    tokens = np.stack(steps, axis=1) if steps else np.zeros((batch, 0, len(MOTION_STREAMS)), dtype=np.int64)
    out = []
    for b in range(batch):
        n = lengths[b] if lengths[b] >= 0 else tokens.shape[1]
        out.append(GeneratedMotion({s: tokens[b, :n, k].astype(np.int64) for k, s in enumerate(MOTION_STREAMS)},
                                   stopped=bool(lengths[b] >= 0)))
    return out


@torch.no_grad()
def translate(model: SignMotionLM, vocab: SignVocabulary, motions: Sequence[np.ndarray], languages: Sequence[str],
              max_tokens: int | None = None, use_cache: bool = True) -> list[str]:
    """Motion tokens ((U, S) head-local codes per clip) -> text (translation)."""
    _check_batch(motions, languages, vocab)
    for m in motions:
        if np.asarray(m).ndim != 2 or np.asarray(m).shape[1] != len(MOTION_STREAMS) or len(m) == 0:
            raise ValueError(f"motion must be (U > 0, {len(MOTION_STREAMS)}) codes in stream order {MOTION_STREAMS}, "
                             f"got {np.asarray(m).shape}")
    max_tokens = max_tokens or model.cfg.max_text_tokens + 1
    model.eval()
    device = next(model.parameters()).device
    sources = [motion_source(vocab, np.asarray(m), lang) for m, lang in zip(motions, languages)]
    src, src_mask = (t.to(device) for t in pad_sequences(sources, vocab.pad_id))
    stepper = _Stepper(model, model.encode(model.embed_fused(src), src_mask), src_mask, use_cache)
    ids = torch.tensor([[vocab.prompt_id(lang, "TXT")] for lang in languages], device=device)
    done = torch.zeros(len(motions), dtype=torch.bool, device=device)
    out: list[list[int]] = [[] for _ in motions]
    for _ in range(max_tokens):
        nxt = model.heads["text"](stepper(model.embed(ids))).argmax(-1)  # (B,)
        for b in torch.nonzero(~done & (nxt != vocab.eos_id)).flatten().tolist():
            out[b].append(int(nxt[b]))
        done |= nxt == vocab.eos_id
        if bool(done.all()):
            break
        ids = nxt[:, None]
    return [vocab.decode_text(o) for o in out]
