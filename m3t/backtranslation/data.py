"""From fitted clips to back-translation samples and padded batches, one sign language at a time.

What the model reads per frame is an :class:`InputSpec` (stored in the checkpoint): ``"model"`` concatenates every
modality of the shard's layout, in ``STREAM_ORDER`` (body, left hand, right hand, face; 360-d for SMPL-FX, the
layout's own dims for Anny), then any other modality in layout order; ``"smplx240"`` is SignSparK_BT's input
(:mod:`m3t.backtranslation.smplx240`); ``"skeleton"`` reads a clip's normalised skeleton coordinates
(:mod:`m3t.shards.skeletons`, one stream ``skeleton``): the judge of skeletal production models (SGSA, PT) and of
any model whose motion is posed into the same graph. Clips longer than ``max_frames`` are cut (SL-T's ``max_sgn_length``).

A clip the model cannot learn from is skipped with its reason (isolated sign, empty text, no frames, sentence
longer than ``max_text_tokens``), never silently dropped.

Axis legend: B batch, T frames, D per-frame input dim, K text tokens (+1 for BOS / EOS), G glosses.
"""
from __future__ import annotations

import json
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from m3t.backtranslation.config import BackTranslationConfig
from m3t.backtranslation.smplx240 import SIGNSPARK_STREAMS, SMPLX240_DIM, smplx240_index, to_smplx240
from m3t.backtranslation.text import PseudoGlosser, TextProcessor, annotated_gloss
from m3t.body.protocol import STREAM_ORDER, ModalityLayout
from m3t.body.skeleton import SkeletonGraph
from m3t.corpora.clip import Clip
from m3t.dataclass_io import build_dataclass
from m3t.shards.schema import layout_from_json, layout_to_json
from m3t.shards.skeletons import SKELETON_STREAM
from m3t.vocabulary import BOS, EOS, PAD, Vocabulary, gloss_vocabulary, text_vocabulary

IGNORE = -100  # target id the losses skip (padding)


@dataclass(frozen=True)
class InputSpec:
    """The per-frame input of a back-translation model: which layout, from which streams of which body layout."""

    layout: str  # "model" | "smplx240" | "skeleton"
    streams: tuple[tuple[str, int], ...]  # (modality, dim) the model layout concatenates, in order
    source_layout: str  # the shards' ModalityLayout as JSON (m3t.shards.schema.layout_to_json); for "skeleton"
    # the SkeletonGraph as JSON
    layout_name: str = "layout"  # the body model's name, for messages

    @classmethod
    def from_layout(cls, kind: str, layout: ModalityLayout, layout_name: str = "layout") -> InputSpec:
        if kind not in ("model", "smplx240"):
            raise ValueError(f"backtranslation.input_layout {kind!r} unknown here; allowed: model, smplx240 "
                             "(skeleton inputs: InputSpec.for_skeleton)")
        if kind == "smplx240":
            smplx240_index(layout, layout_name)  # refuses a non-SMPL-X layout now, not at the first clip
        order = [n for n in STREAM_ORDER if n in layout.names] + [n for n in layout.names if n not in STREAM_ORDER]
        return cls(kind, tuple((n, layout.dims[n]) for n in order), layout_to_json(layout), layout_name)

    @classmethod
    def for_skeleton(cls, graph: SkeletonGraph) -> InputSpec:
        """Normalised skeleton coordinates of ``graph`` (no counter), stream ``skeleton``."""
        return cls("skeleton", ((SKELETON_STREAM, graph.width),), json.dumps(graph.to_dict(), sort_keys=True),
                   graph.name)

    @property
    def dim(self) -> int:
        return SMPLX240_DIM if self.layout == "smplx240" else sum(d for _, d in self.streams)

    def features(self, params: Mapping[str, np.ndarray], clip_id: str) -> np.ndarray:
        """(T, D) float32 input of one clip; T may be 0. Errors name the clip and the modality."""
        frames = None
        used = {n for n, _ in SIGNSPARK_STREAMS} if self.layout == "smplx240" else {n for n, _ in self.streams}
        for name, dim in (s for s in self.streams if s[0] in used):
            if name not in params:
                raise ValueError(f"clip {clip_id!r}: no {name!r} parameters; the back-translation model reads "
                                 f"{sorted(used)} ({self.layout_name} layout)")
            shape = np.shape(params[name])
            if len(shape) != 2 or shape[1] != dim:
                raise ValueError(f"clip {clip_id!r}, modality {name!r}: shape {shape}, expected (T, {dim}) of the "
                                 f"{self.layout_name} layout the model was trained on")
            if frames is not None and shape[0] != frames:
                raise ValueError(f"clip {clip_id!r}, modality {name!r}: {shape[0]} frames, other modalities {frames}")
            frames = shape[0]
        if self.layout == "smplx240":
            return to_smplx240(params, layout_from_json(self.source_layout), self.layout_name)
        return np.concatenate([np.asarray(params[n], dtype=np.float32) for n, _ in self.streams], axis=-1)

    def to_dict(self) -> dict:
        return {"layout": self.layout, "streams": [[n, d] for n, d in self.streams],
                "source_layout": self.source_layout, "layout_name": self.layout_name}

    @classmethod
    def from_dict(cls, raw: dict) -> InputSpec:
        return build_dataclass(cls, raw, "input", ignore_unknown=True)

    def describe(self) -> str:
        streams = " + ".join(f"{n} {d}" for n, d in self.streams)
        if self.layout == "skeleton":
            return f"skeleton ({self.layout_name} graph, {self.dim} normalised coordinates)"
        return f"smplx240 (SignSparK_BT, {SMPLX240_DIM}-d)" if self.layout == "smplx240" else f"model ({streams})"


@dataclass(frozen=True)
class Sample:
    clip_id: str
    frames: np.ndarray  # (T, D) float32, T >= 1
    text_ids: tuple[int, ...]  # without BOS / EOS
    gloss_ids: tuple[int, ...]  # empty: no gloss for the CTC head
    reference: str  # the sentence as scored (TextProcessor.reference)


@dataclass
class LanguageCorpus:
    """One sign language's training material."""

    language: str
    processor: TextProcessor
    text_vocab: Vocabulary
    gloss_vocab: Vocabulary | None  # None: no CTC head
    gloss_source: str  # "annotated", the pseudo-gloss method, both with counts, or "none"
    train: list[Sample]
    dev: list[Sample]
    skipped: list[dict] = field(default_factory=list)
    truncated: int = 0  # clips cut to max_frames


def skip_reason(clip: Clip, frames: int) -> str | None:
    """Why a clip cannot be a back-translation example, or None."""
    if clip.label is not None:
        return f"isolated sign (label {clip.label}): back-translation is sentence-level"
    if not clip.text.strip():
        return "empty text"
    if frames == 0:
        return "no frames"
    return None


def language_corpus(language: str, train: Sequence, dev: Sequence, spec: InputSpec,
                    cfg: BackTranslationConfig) -> LanguageCorpus:
    """Vocabularies (train split), glosses and samples of one language. ``train`` / ``dev``: FittedClips."""
    processor = TextProcessor.for_language(language)
    skipped: list[dict] = []
    glosser = PseudoGlosser(language) if cfg.pseudo_glosses else None

    def usable(clips: Sequence, training: bool) -> list[tuple]:
        """(clip, text tokens, glosses, gloss source) of the usable clips; glosses only for training. Only
        training clips are refused for long text (as SL-T filters the train split only)."""
        out = []
        for fitted in clips:
            clip = fitted.clip
            reason = skip_reason(clip, fitted.num_frames)
            tokens = processor.tokens(clip.text) if reason is None else []
            if reason is None and training and len(tokens) + 1 > cfg.max_text_tokens:
                reason = (f"{len(tokens)} text tokens; backtranslation.max_text_tokens {cfg.max_text_tokens} "
                          "allows one fewer (+ EOS)")
            if reason is not None:
                skipped.append({"clip_id": clip.id, "split": clip.split, "language": language, "reason": reason})
                continue
            if not training:
                glosses, source = [], "none"
            elif clip.gloss.strip():
                glosses, source = annotated_gloss(clip.gloss), "annotated"
            elif glosser is not None:
                glosses, source = glosser(clip.text), glosser.method
            else:
                glosses, source = [], "none"
            out.append((fitted, tokens, glosses, source))
        return out

    train_rows, dev_rows = usable(train, True), usable(dev, False)
    if not train_rows:
        reasons = Counter(s["reason"] for s in skipped if s["split"] == "train")
        raise ValueError(f"language {language!r}: no usable training clip ({len(train)} in the train split; skipped: "
                         f"{dict(reasons)}); drop it from backtranslation.languages or fix the corpus")
    text_vocab = text_vocabulary((t for _, t, _, _ in train_rows), cfg.min_token_frequency)
    use_glosses = cfg.gloss_ctc_weight > 0 and any(g for _, _, g, _ in train_rows)
    gloss_vocab = gloss_vocabulary(g for _, _, g, _ in train_rows) if use_glosses else None
    truncated = 0

    def samples(rows) -> list[Sample]:
        nonlocal truncated
        out = []
        for fitted, tokens, glosses, _ in rows:
            frames = spec.features(fitted.params, fitted.clip.id)
            truncated += len(frames) > cfg.max_frames
            out.append(Sample(fitted.clip.id, frames[: cfg.max_frames], tuple(text_vocab.encode(tokens)),
                              tuple(gloss_vocab.encode(glosses)) if gloss_vocab is not None else (),
                              processor.join(tokens)))
        return out

    sources = Counter(source for *_, source in train_rows)
    source = ", ".join(f"{k} ({v} clips)" for k, v in sorted(sources.items())) if len(sources) > 1 else \
        next(iter(sources), "none")
    return LanguageCorpus(language, processor, text_vocab, gloss_vocab, source if use_glosses else "none",
                          samples(train_rows), samples(dev_rows), skipped, truncated)


# --------------------------------------------------------------------------------------------- batches
@dataclass(frozen=True)
class Batch:
    frames: torch.Tensor  # (B, T, D)
    frame_mask: torch.Tensor  # (B, T) bool, True on real frames
    text_in: torch.Tensor  # (B, K) long: BOS + ids, PAD after
    text_out: torch.Tensor  # (B, K) long: ids + EOS, IGNORE after
    glosses: torch.Tensor  # (B, G) long, 0 after (G may be 0)
    gloss_lengths: torch.Tensor  # (B,) long, 0 = no gloss

    def to(self, device: torch.device) -> Batch:
        return Batch(*(getattr(self, f).to(device) for f in self.__dataclass_fields__))


def pad_frames(frames: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-clip (T_i, D) arrays -> (B, T, D) zeros-padded frames and the (B, T) mask of real frames."""
    longest = max(len(f) for f in frames)
    out = torch.zeros(len(frames), longest, frames[0].shape[-1])
    mask = torch.zeros(len(frames), longest, dtype=torch.bool)
    for i, f in enumerate(frames):
        out[i, : len(f)] = torch.as_tensor(f)
        mask[i, : len(f)] = True
    return out, mask


def collate(samples: Sequence[Sample], vocab: Vocabulary) -> Batch:
    frames, mask = pad_frames([s.frames for s in samples])
    k = max(len(s.text_ids) for s in samples) + 1
    text_in = torch.full((len(samples), k), vocab.stoi[PAD], dtype=torch.long)
    text_out = torch.full((len(samples), k), IGNORE, dtype=torch.long)
    g = max(len(s.gloss_ids) for s in samples)
    glosses = torch.zeros(len(samples), g, dtype=torch.long)
    for i, s in enumerate(samples):
        ids = list(s.text_ids)
        text_in[i, : len(ids) + 1] = torch.tensor([vocab.stoi[BOS]] + ids)
        text_out[i, : len(ids) + 1] = torch.tensor(ids + [vocab.stoi[EOS]])
        glosses[i, : len(s.gloss_ids)] = torch.tensor(s.gloss_ids, dtype=torch.long)
    lengths = torch.tensor([len(s.gloss_ids) for s in samples], dtype=torch.long)
    return Batch(frames, mask, text_in, text_out, glosses, lengths)


def feature_statistics(samples: Sequence[Sample]) -> tuple[np.ndarray, np.ndarray]:
    """Per-dim mean and standard deviation over every training frame (std floored at 1e-3)."""
    stacked = np.concatenate([s.frames for s in samples]).astype(np.float64)
    return stacked.mean(0).astype(np.float32), np.maximum(stacked.std(0), 1e-3).astype(np.float32)

