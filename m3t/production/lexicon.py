"""The ``lexicon`` baseline: one stored sign per gloss, the signs of a sentence concatenated with smoothed
transitions (the recipe of spoken-to-signed, Moryossef et al. 2023, and of Spoken2Sign, Zuo et al. ECCV 2024:
look each gloss up in an isolated-sign dictionary, stitch the stored signs, smooth the joins).

**The dictionary** (:class:`Lexicon`) is built from the isolated signs of the training split (clips with a
``label``: one sign each, its gloss in ``clip.gloss``): per gloss **one** stored sign, the clip with the lowest id
(deterministic; no selection by quality, nothing tuned). The embedded corpus's isolated signs (sign language
``ISO-SYN``) are the one lexicon of its three sentence languages, which share their signs; a real corpus's lexicon
serves the sentences of its own sign language (:meth:`Lexicon.lookup`'s ``language`` filter applies when the
lexicon holds entries of that language).

**The input** is the sentence's gloss sequence when the corpus annotates one (``input="gloss"``, the Gloss2Pose
setting of Progressive Transformers: an oracle text-to-gloss step, which every table row of this baseline says),
else its words (``input="words"``, and the fallback for clips without glosses): a word names a sign when it occurs
in the texts of exactly one gloss's stored signs (``"the apple"`` -> ``apple`` names APPLE; ``the`` names none),
so the mapping comes from the lexicon itself, not from a hand-made list.

**Stitching** (:func:`concatenate`): the stored signs in order, each whole; between two signs
``transition_frames`` frames interpolated linearly from the last frame of one to the first frame of the next (the
parameters of every modality, including the 6D rotations, which the body model orthonormalises when posing).
Glosses / words without an entry are skipped **and counted** (:attr:`Lexical.missing`); a sentence with no entry at
all gives no motion (zero frames: scored as the rest pose, as an empty generation is).

Axis legend: T frames, D_m a modality's width.
"""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from m3t.production.retrieval import normalise, words
from m3t.shards.schema import FittedClip

INPUTS = ("gloss", "words")


@dataclass(frozen=True)
class Lexical:
    """A sentence produced from the lexicon: its motion, the entries used (gloss, clip id) and what was missing."""

    params: dict[str, np.ndarray]
    used: tuple[tuple[str, str], ...]
    missing: tuple[str, ...]
    input: str  # "gloss" or "words": what was looked up
    tokens: int  # how many glosses / words were looked up

    @property
    def frames(self) -> int:
        return next((len(v) for v in self.params.values()), 0)


class Lexicon:
    """One stored sign per gloss from isolated-sign clips (see the module doc)."""

    def __init__(self, clips: Sequence[FittedClip]):
        chosen: dict[str, FittedClip] = {}
        for c in sorted(clips, key=lambda c: c.clip.id):
            gloss = (c.clip.gloss or "").strip().upper()
            if c.clip.label is None or not gloss or len(gloss.split()) != 1 or c.num_frames < 1:
                continue
            chosen.setdefault(gloss, c)
        self.entries = chosen
        glosses_of: dict[str, set[str]] = defaultdict(set)
        for c in clips:
            gloss = (c.clip.gloss or "").strip().upper()
            if gloss in chosen:
                for word in words(normalise(c.clip.text), c.clip.language):
                    glosses_of[word].add(gloss)
        self.word_to_gloss = {w: next(iter(g)) for w, g in glosses_of.items() if len(g) == 1}
        self.languages = sorted({c.clip.language for c in chosen.values()})

    def __len__(self) -> int:
        return len(self.entries)

    def tokens(self, text: str, gloss: str | None, language: str, input: str = "gloss") -> tuple[list[str], str]:
        """The glosses (or words) of a sentence to look up, and which of the two they are."""
        if input not in INPUTS:
            raise ValueError(f"lexicon input {input!r} unknown; allowed: {', '.join(INPUTS)}")
        if input == "gloss" and gloss and gloss.strip():
            return gloss.upper().split(), "gloss"
        return words(normalise(text), language), "words"

    def lookup(self, text: str, gloss: str | None, language: str, input: str = "gloss",
               transition_frames: int = 6) -> Lexical:
        """Produce one sentence (module doc); ``language`` restricts the entries to that sign language when the
        lexicon has entries of it (otherwise every entry serves, as the embedded corpus's shared signs do)."""
        tokens, kind = self.tokens(text, gloss, language, input)
        own = language in self.languages
        used, missing, pieces = [], [], []
        for token in tokens:
            name = token if kind == "gloss" else self.word_to_gloss.get(token)
            entry = self.entries.get(name) if name else None
            if entry is None or (own and entry.clip.language != language):
                missing.append(token)
                continue
            used.append((name, entry.clip.id))
            pieces.append(entry.params)
        return Lexical(concatenate(pieces, transition_frames), tuple(used), tuple(missing), kind, len(tokens))


def concatenate(pieces: Sequence[dict[str, np.ndarray]], transition_frames: int) -> dict[str, np.ndarray]:
    """The pieces ({name: (T, ...)}) in order, ``transition_frames`` linearly interpolated frames between consecutive pieces
    (excluding both ends: the last frame of one piece and the first of the next are kept as they are). No piece:
    {} (no motion)."""
    if transition_frames < 0:
        raise ValueError(f"transition_frames must be >= 0, got {transition_frames}")
    if not pieces:
        return {}
    names = list(pieces[0])
    out: dict[str, list[np.ndarray]] = {n: [] for n in names}
    weights = np.arange(1, transition_frames + 1, dtype=np.float64) / (transition_frames + 1)
    for i, piece in enumerate(pieces):
        if set(piece) != set(names):
            raise ValueError(f"lexicon entries with different modalities: {sorted(piece)} vs {sorted(names)}")
        for n in names:
            if i and transition_frames:
                a, b = out[n][-1][-1].astype(np.float64), np.asarray(piece[n][0], np.float64)
                w = weights.reshape(-1, *([1] * a.ndim))  # (transition_frames, 1, ...) over a frame's shape
                out[n].append(((1.0 - w) * a + w * b).astype(np.float32))
            out[n].append(np.asarray(piece[n], np.float32))
    return {n: np.concatenate(v, axis=0) for n, v in out.items()}
