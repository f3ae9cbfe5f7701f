"""From skeleton clips (:mod:`m3t.shards.skeletons`) to text -> skeleton samples and padded batches.

A sample's text is its language token ``<2LANG>`` then the sentence's words (the back-translation tokenisation
of :class:`m3t.backtranslation.text.TextProcessor`: lower-cased words, Chinese segmented), so one model
serves every language of ``data.train_corpora``. Its target is the clip's normalised skeleton (SGSA Sec. 5)
with the counter of Progressive Transformers as the last column: frame ``t`` of ``U`` has counter
``(t + 1) / U`` (the last frame 1). Glosses, where a clip has them, supervise the encoder (CTC).

A clip that cannot be a training example is skipped with its reason (empty text, no frames, text longer than
``sgsa.max_text_tokens``); in evaluation only clips with no text or no frames are left out: longer text is cut
to the limit and counted. Clips longer than ``sgsa.max_frames`` are cut (counted) for training; evaluation
scores the generation against the whole reference.

Axis legend: B batch, U frames, S = C + 1 skeleton width with counter, C coordinates, K text tokens, G glosses.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from m3t.backtranslation.text import TextProcessor, annotated_gloss
from m3t.shards.skeletons import SkeletonClip
from m3t.sgsa.config import SGSAConfig
from m3t.vocabulary import PAD, Vocabulary, gloss_vocabulary, text_vocabulary


def language_token(language: str) -> str:
    return f"<2{language}>"


def counter_column(frames: int) -> np.ndarray:
    """(U,) float32 progress ``(t + 1) / U`` of each frame."""
    return (np.arange(1, frames + 1, dtype=np.float32) / max(frames, 1)).astype(np.float32)


def with_counter(coords: np.ndarray) -> np.ndarray:
    """(U, C) coordinates -> (U, C + 1) with the counter as the last column."""
    return np.concatenate([coords.astype(np.float32), counter_column(len(coords))[:, None]], axis=1)


@dataclass(frozen=True, eq=False)
class Sample:
    clip: SkeletonClip  # the reference: full-length points (metres), scale, identity, text
    text_ids: tuple[int, ...]  # language token + words, no BOS / EOS
    gloss_ids: tuple[int, ...]  # () = no gloss for the CTC loss
    target: np.ndarray  # (U, S) float32 normalised skeleton + counter, U <= max_frames

    @property
    def clip_id(self) -> str:
        return self.clip.clip_id

    @property
    def language(self) -> str:
        return self.clip.fitted.clip.language

    @property
    def group(self) -> str:
        return f"{self.clip.fitted.clip.corpus}/{self.language}"

    @property
    def sentence(self) -> bool:
        return self.clip.fitted.clip.label is None


def text_tokens(text: str, language: str) -> list[str]:
    return [language_token(language)] + TextProcessor.for_language(language).tokens(text)


def vocabularies(clips: Sequence[SkeletonClip], cfg: SGSAConfig) -> tuple[Vocabulary, Vocabulary | None]:
    """Text vocabulary (``<pad>`` = 0) and gloss vocabulary (``<blank>`` = 0; None without glosses or with
    ``gloss_weight`` 0) of the train split."""
    usable = [c.fitted.clip for c in clips if c.fitted.clip.text.strip()]
    text = text_vocabulary((text_tokens(c.text, c.language) for c in usable), cfg.min_token_frequency)
    glosses = [annotated_gloss(c.gloss) for c in usable if c.gloss.strip()]
    use = cfg.gloss_weight > 0 and any(glosses)
    return text, gloss_vocabulary(glosses) if use else None


@dataclass
class SampleSet:
    samples: list[Sample] = field(default_factory=list)
    skipped: list[dict] = field(default_factory=list)  # {clip_id, split, reason}
    cut_text: int = 0  # clips whose text was cut to max_text_tokens (evaluation)
    cut_frames: int = 0  # clips cut to max_frames (training)


def make_samples(clips: Iterable[SkeletonClip], text_vocab: Vocabulary, gloss_vocab: Vocabulary | None,
                 cfg: SGSAConfig, training: bool) -> SampleSet:
    """Samples of ``clips`` (see the module docstring for what is skipped or cut)."""
    out = SampleSet()
    for sk in clips:
        clip = sk.fitted.clip
        tokens = text_tokens(clip.text, clip.language) if clip.text.strip() else []
        reason = None
        if not tokens:
            reason = "empty text"
        elif not len(sk.coords):
            reason = "no frames"
        elif training and len(tokens) > cfg.max_text_tokens:
            reason = f"{len(tokens)} text tokens; sgsa.max_text_tokens is {cfg.max_text_tokens}"
        if reason is not None:
            out.skipped.append({"clip_id": clip.id, "split": clip.split, "reason": reason})
            continue
        if len(tokens) > cfg.max_text_tokens:
            tokens, out.cut_text = tokens[: cfg.max_text_tokens], out.cut_text + 1
        coords = sk.coords
        if training and len(coords) > cfg.max_frames:
            coords, out.cut_frames = coords[: cfg.max_frames], out.cut_frames + 1
        glosses = annotated_gloss(clip.gloss) if gloss_vocab is not None and clip.gloss.strip() else []
        out.samples.append(Sample(sk, tuple(text_vocab.encode(tokens)),
                                  tuple(gloss_vocab.encode(glosses)) if gloss_vocab is not None else (),
                                  with_counter(coords)))
    return out


@dataclass(frozen=True)
class Batch:
    text_ids: torch.Tensor  # (B, K) long, PAD after
    text_mask: torch.Tensor  # (B, K) bool, True on real tokens
    frames_in: torch.Tensor  # (B, U, S): the zero start frame, then target[:, :-1]
    target: torch.Tensor  # (B, U, S)
    frame_mask: torch.Tensor  # (B, U) bool, True on real frames
    glosses: torch.Tensor  # (B, G) long (G may be 0)
    gloss_lengths: torch.Tensor  # (B,) long, 0 = no gloss

    def to(self, device: torch.device) -> Batch:
        return Batch(*(getattr(self, f).to(device) for f in self.__dataclass_fields__))


def text_batch(samples: Sequence[Sample], pad_id: int) -> tuple[torch.Tensor, torch.Tensor]:
    k = max(len(s.text_ids) for s in samples)
    ids = torch.full((len(samples), k), pad_id, dtype=torch.long)
    for i, s in enumerate(samples):
        ids[i, : len(s.text_ids)] = torch.tensor(s.text_ids, dtype=torch.long)
    return ids, ids != pad_id


def collate(samples: Sequence[Sample], text_vocab: Vocabulary) -> Batch:
    text_ids, text_mask = text_batch(samples, text_vocab.stoi[PAD])
    u, width = max(len(s.target) for s in samples), samples[0].target.shape[1]
    target = torch.zeros(len(samples), u, width)
    mask = torch.zeros(len(samples), u, dtype=torch.bool)
    for i, s in enumerate(samples):
        target[i, : len(s.target)] = torch.as_tensor(s.target)
        mask[i, : len(s.target)] = True
    frames_in = torch.cat([torch.zeros(len(samples), 1, width), target[:, :-1]], dim=1)
    g = max(len(s.gloss_ids) for s in samples)
    glosses = torch.zeros(len(samples), g, dtype=torch.long)
    for i, s in enumerate(samples):
        glosses[i, : len(s.gloss_ids)] = torch.tensor(s.gloss_ids, dtype=torch.long)
    lengths = torch.tensor([len(s.gloss_ids) for s in samples], dtype=torch.long)
    return Batch(text_ids, text_mask, frames_in, target, mask, glosses, lengths)
