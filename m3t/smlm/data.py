"""Token shards -> SMLM examples and padded batches for both tasks.

Sequence formats (``P`` = the language's prompt step, fused from ``<L_B> <L_LH> <L_RH> <L_F>``):

- production:  encoder ``s_1 .. s_K </s> <L_TXT>``;  decoder in ``P m_1 .. m_U``;  targets ``m_1 .. m_U EOS``
- translation: encoder ``P m_1 .. m_U E`` (E = ``</s>`` in every stream);  decoder in ``<L_TXT> s_1 .. s_K``;
  targets ``s_1 .. s_K </s>``

Targets are head-local ids (a motion head's EOS is its class ``C_m``), padded with ``IGNORE``.

Axis legend: B batch, K text tokens, U motion steps, S = 4 motion streams (body, left hand, right hand, face).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from m3t.shards.tokens import TokenShard
from m3t.smlm.vocab import (
    MOTION_STREAMS,
    STREAM_PROMPT,
    SignVocabulary,
    VocabularyError,
)

IGNORE = -100


@dataclass(frozen=True, eq=False)
class Example:
    clip_id: str
    language: str
    text: str
    text_ids: np.ndarray  # (K,) text ids, no specials
    motion: np.ndarray  # (U, S) head-local codes


def examples_from_shard(shard: TokenShard, vocab: SignVocabulary, max_text_tokens: int, max_motion_tokens: int,
                        cut: list[dict[str, str]] | None = None) -> tuple[list[Example], list[dict[str, str]]]:
    """Every usable clip of a token shard; the others are returned with their reason (never dropped silently).

    ``cut`` given (evaluation): a clip over the limits is kept, its text cut to ``max_text_tokens`` ids and its
    motion tokens to ``max_motion_tokens`` steps, and recorded in ``cut`` with the reason, so an evaluation
    scores every clip against its whole reference. Without it (training) such a clip is skipped."""
    examples, skipped = [], []
    for tc in shard.clips:
        clip = tc.clip
        try:
            vocab.check_language(clip.language)
            if tc.num_tokens == 0:
                raise VocabularyError("no motion tokens")
            over = []
            ids = vocab.encode_text(clip.text, None)
            if len(ids) > max_text_tokens:
                over.append(f"text of {len(ids)} tokens > smlm.max_text_tokens = {max_text_tokens}")
            if tc.num_tokens > max_motion_tokens:
                over.append(f"{tc.num_tokens} motion steps > smlm.max_motion_tokens = {max_motion_tokens}")
            if over and cut is None:
                raise VocabularyError("; ".join(over))
            motion = np.stack([np.asarray(tc.tokens[s], dtype=np.int64) for s in MOTION_STREAMS], axis=1)
        except (VocabularyError, KeyError) as exc:
            skipped.append({"clip_id": clip.id, "split": clip.split, "reason": str(exc)})
            continue
        if over:
            cut.append({"clip_id": clip.id, "split": clip.split, "reason": "; ".join(over) + " (kept, cut to the limit)"})
        examples.append(Example(clip.id, clip.language, clip.text, np.asarray(ids[:max_text_tokens], dtype=np.int64),
                                motion[:max_motion_tokens]))
    return examples, skipped


def prompt_step(vocab: SignVocabulary, language: str) -> np.ndarray:
    """(S,) global ids of the language's motion prompts."""
    return np.array([vocab.prompt_id(language, STREAM_PROMPT[s]) for s in MOTION_STREAMS], dtype=np.int64)


def motion_global(vocab: SignVocabulary, motion: np.ndarray) -> np.ndarray:
    """(U, S) head-local codes -> (U, S) global ids."""
    return np.stack([vocab.motion_ids(s, motion[:, k]) for k, s in enumerate(MOTION_STREAMS)], axis=1)


def text_source(vocab: SignVocabulary, text_ids: np.ndarray, language: str) -> np.ndarray:
    """(K,) -> (K + 2,) encoder ids ``s </s> <L_TXT>``."""
    return np.concatenate([text_ids, [vocab.eos_id, vocab.prompt_id(language, "TXT")]]).astype(np.int64)


def motion_source(vocab: SignVocabulary, motion: np.ndarray, language: str) -> np.ndarray:
    """(U, S) local codes -> (U + 2, S) encoder ids ``P m E``."""
    eos = np.full((1, len(MOTION_STREAMS)), vocab.eos_id, dtype=np.int64)
    return np.concatenate([prompt_step(vocab, language)[None], motion_global(vocab, motion), eos])


def pad_sequences(rows: Sequence[np.ndarray], value: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Right-pad (n_i, ...) arrays -> (B, N, ...) tensor and (B, N) mask."""
    n = max(len(r) for r in rows)
    out = np.full((len(rows), n, *rows[0].shape[1:]), value, dtype=np.int64)
    mask = np.zeros((len(rows), n), dtype=np.int64)
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
        mask[i, : len(r)] = 1
    return torch.from_numpy(out), torch.from_numpy(mask)


@dataclass
class ProductionBatch:
    text_ids: torch.Tensor  # (B, K + 2)
    text_mask: torch.Tensor
    motion_in: torch.Tensor  # (B, U + 1, S) global ids
    motion_mask: torch.Tensor  # (B, U + 1)
    targets: torch.Tensor  # (B, U + 1, S) head-local, IGNORE on padding


@dataclass
class TranslationBatch:
    motion_ids: torch.Tensor  # (B, U + 2, S) global ids
    motion_mask: torch.Tensor
    text_in: torch.Tensor  # (B, K + 1)
    text_mask: torch.Tensor
    targets: torch.Tensor  # (B, K + 1), IGNORE on padding


def production_batch(examples: Sequence[Example], vocab: SignVocabulary) -> ProductionBatch:
    sources = [text_source(vocab, e.text_ids, e.language) for e in examples]
    inputs = [np.concatenate([prompt_step(vocab, e.language)[None], motion_global(vocab, e.motion)]) for e in examples]
    eos = np.array([vocab.codebooks[s] for s in MOTION_STREAMS], dtype=np.int64)
    targets = [np.concatenate([e.motion, eos[None]]) for e in examples]
    text_ids, text_mask = pad_sequences(sources, vocab.pad_id)
    motion_in, motion_mask = pad_sequences(inputs, vocab.pad_id)
    return ProductionBatch(text_ids, text_mask, motion_in, motion_mask, pad_sequences(targets, IGNORE)[0])


def translation_batch(examples: Sequence[Example], vocab: SignVocabulary) -> TranslationBatch:
    sources = [motion_source(vocab, e.motion, e.language) for e in examples]
    inputs = [np.concatenate([[vocab.prompt_id(e.language, "TXT")], e.text_ids]) for e in examples]
    targets = [np.concatenate([e.text_ids, [vocab.eos_id]]) for e in examples]
    motion_ids, motion_mask = pad_sequences(sources, vocab.pad_id)
    text_in, text_mask = pad_sequences(inputs, vocab.pad_id)
    return TranslationBatch(motion_ids, motion_mask, text_in, text_mask, pad_sequences(targets, IGNORE)[0])
