"""The ``retrieval`` baseline: the training clip whose text is nearest the input, its motion returned unchanged.

The copy baseline of the SLRTP 2025 challenge's winner (ZechengLi19/CVPRW-SLP-2025, ``main.py``: the ground-truth
poses of a training clip whenever the test sentence appears word for word in the training set), extended to every
sentence by a nearest-text rule:

Every training clip with text and motion is a candidate, isolated signs included (their text names the sign).

1. **exact match** of the normalised text (Unicode NFKC, lower case, punctuation removed, whitespace collapsed) in
   the same sign language; several matches: the lowest clip id;
2. else the **highest sentence chrF** (sacreBLEU's ``CHRF()`` defaults: character 6-grams, beta 2; a character
   measure, so it needs no word tokeniser and works for Chinese) between the normalised input and each normalised
   training text of the language; ties: the lowest clip id. chrF 0 (no shared character n-gram) still retrieves
   the lowest-id clip, and the report says so.

Never tuned on test data: no threshold, no learned similarity. The returned clip's id, text, match kind and score
are reported with the motion; the input's words that the retrieved text lacks are listed (they are not signed;
words are split on whitespace, Chinese by jieba).
"""
from __future__ import annotations

import re
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass

from sacrebleu.metrics import CHRF

from m3t.metrics.text import is_chinese, slt_tokens
from m3t.shards.schema import FittedClip

_PUNCTUATION = re.compile(r"[^\w\s]", flags=re.UNICODE)
_SPACES = re.compile(r"\s+")


def normalise(text: str) -> str:
    """NFKC, lower case, punctuation removed, whitespace collapsed: the form texts are compared in."""
    text = unicodedata.normalize("NFKC", text).lower()
    return _SPACES.sub(" ", _PUNCTUATION.sub(" ", text)).strip()


@dataclass(frozen=True)
class Retrieved:
    """The retrieved training clip, how it matched (``"exact"`` or ``"chrf"``) and the chrF (100 for exact)."""

    clip: FittedClip
    match: str
    score: float
    missing_words: tuple[str, ...]  # input words (normalised) absent from the retrieved text


class RetrievalIndex:
    """Training clips with text, by sign language (built once; :meth:`nearest` per query)."""

    def __init__(self, clips: Sequence[FittedClip]):
        self._by_language: dict[str, list[tuple[str, str, FittedClip]]] = {}
        for c in clips:
            if c.clip.text.strip() and c.num_frames > 0:  # isolated signs too: a one-sign input retrieves one
                self._by_language.setdefault(c.clip.language, []).append((normalise(c.clip.text), c.clip.id, c))
        for entries in self._by_language.values():
            entries.sort(key=lambda e: e[1])
        self._chrf = CHRF()

    @property
    def languages(self) -> list[str]:
        return sorted(self._by_language)

    def nearest(self, text: str, language: str) -> Retrieved:
        """The nearest training clip of ``language`` to ``text`` (see the module doc)."""
        entries = self._by_language.get(language)
        if not entries:
            raise ValueError(f"no training clip with text in sign language {language!r}; the training shards hold "
                             f"{self.languages or 'none'}")
        query = normalise(text)
        if not query:
            raise ValueError("empty text: give a sentence to produce")
        best = next((e for e in entries if e[0] == query), None)
        if best is not None:
            match, score = "exact", 100.0
        else:
            scored = [(self._chrf.sentence_score(query, [e[0]]).score, e) for e in entries]
            score = max(s for s, _ in scored)
            best = next(e for s, e in scored if s == score)  # entries are in id order: the lowest id wins a tie
            match = "chrf"
        have = set(words(best[0], language))
        missing = tuple(dict.fromkeys(w for w in words(query, language) if w not in have))
        return Retrieved(best[2], match, float(score), missing)


def words(text: str, language: str) -> list[str]:
    """The words of a normalised text: whitespace-separated, or jieba words for Chinese (written without spaces)."""
    return slt_tokens(text, "jieba" if is_chinese(language) else "word")
