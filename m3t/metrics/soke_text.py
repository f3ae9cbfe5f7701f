"""Definition "soke": the back-translation text metrics of SOKE (Zuo et al. 2025, ``2000ZRL/SOKE``).

SOKE scores back-translated sentences in ``mGPT/metrics/m2t.py`` (``M2TMetrics.update`` / ``compute``) through
``mGPT/metrics/utils.py`` (``bleu``, ``rouge``), its vendored SL-T sacreBLEU (``mGPT/metrics/sacrebleu.py``,
``raw_corpus_bleu``) and a ROUGE module taken from tf-seq2seq (``mGPT/metrics/Rouge.py``, ``rouge`` ->
``rouge_l_sentence_level`` -> ``_f_p_r_lcs``). Its BLEU is SL-T's; its ROUGE-L is **not** SL-T's MS-COCO
F-measure. Re-implemented here (not pasted):

- **Level.** ``"char"`` when the clip comes from CSL-Daily (``src == "csl"``), else ``"word"``
  (:func:`soke_level`: the project's Chinese languages, as :func:`m3t.metrics.text.is_chinese` names them).
- **Case.** Text is compared as given: SOKE lower-cases nothing (SL-T's data pipeline lower-cases before
  scoring; definition ``slt`` does too).
- **BLEU-1..4.** SL-T's arithmetic (:func:`m3t.metrics.text.slt_bleu_from_statistics`: corpus-level clipped
  n-grams, no smoothing, the cumulative scores of one 4-gram computation) on whitespace tokens; at the
  ``"char"`` level SOKE joins every character with spaces first, so spaces vanish and every other character is a
  token.
- **ROUGE-L.** Per sentence, on the tokens ``" ".join(tokens).split(" ")`` (word level: ``text.split()``; char
  level: ``list(text)``, so a space character becomes two empty tokens, and an empty sentence is one empty token):
  ``R = LCS / |ref|``, ``P = LCS / |hyp|``, then tf-seq2seq's F with ``beta = P / (R + 1e-12)``:
  ``F = (1 + beta^2) R P / (R + beta^2 P + 1e-12)``; the mean over sentences x 100. SL-T's ROUGE-L uses a fixed
  ``beta = 1.2`` and weighs recall; here ``beta`` follows the ratio of precision to recall, so the two differ most
  on sentences whose precision and recall differ (hypotheses much shorter or longer than their reference): up to
  19 points on one sentence, 1.5-2.1 on whole corpora.

Axis legend: none (lists of sentences).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from m3t.metrics.text import (
    _check,
    bleu_statistics,
    is_chinese,
    lcs_length,
    slt_bleu_from_statistics,
)

SOKE_DEFINITION = "soke"
SOKE_LEVELS = ("word", "char")
_EPS = 1e-12  # tf-seq2seq's guards in _f_p_r_lcs


def soke_level(language: str) -> str:
    """SOKE's scoring level of ``language``: ``"char"`` for Chinese (CSL-Daily), else ``"word"``."""
    return "char" if is_chinese(language) else "word"


def soke_bleu_tokens(text: str, level: str = "word") -> list[str]:
    """The tokens SOKE's BLEU counts: whitespace words, or at the char level every non-space character."""
    _check_level(level)
    return text.split() if level == "word" else list("".join(text.split()))


def soke_rouge_tokens(text: str, level: str = "word") -> list[str]:
    """The tokens SOKE's ROUGE-L compares (module docstring): the level's tokens joined by single spaces and split
    on single spaces again."""
    _check_level(level)
    tokens = text.split() if level == "word" else list(text)
    return " ".join(tokens).split(" ")


def soke_rouge_l_sentence(hyp: Sequence[str], ref: Sequence[str]) -> float:
    """tf-seq2seq's sentence-level ROUGE-L F (0-1) of token lists, with ``beta = P / R``."""
    if not hyp or not ref:
        raise ValueError("SOKE's ROUGE-L needs at least one token on each side (an empty sentence is one empty "
                         "token: use soke_rouge_tokens)")
    lcs = lcs_length(hyp, ref)
    recall, precision = lcs / len(ref), lcs / len(hyp)
    beta = precision / (recall + _EPS)
    return (1 + beta ** 2) * recall * precision / (recall + beta ** 2 * precision + _EPS)


@dataclass(frozen=True)
class SokeScores:
    """One corpus scored under definition "soke" at one level; all scores 0-100."""

    bleu1: float
    bleu2: float
    bleu3: float
    bleu4: float
    rouge_l: float
    level: str  # "word" | "char"
    sentences: int
    definition: str = SOKE_DEFINITION

    def as_dict(self, prefix: str = f"{SOKE_DEFINITION}_") -> dict[str, float]:
        """The five scores as ``{prefix + "bleu1", ..., prefix + "rouge_l"}`` (default prefix ``soke_``)."""
        return {prefix + k: float(getattr(self, k)) for k in ("bleu1", "bleu2", "bleu3", "bleu4", "rouge_l")}


def soke_scores(hyps: Sequence[str], refs: Sequence[str], level: str = "word") -> SokeScores:
    """BLEU-1..4 and ROUGE-L of hypotheses against one reference each, as SOKE computes them at ``level``."""
    _check_level(level)
    _check(hyps, refs)
    bleu = slt_bleu_from_statistics(bleu_statistics([soke_bleu_tokens(h, level) for h in hyps],
                                                    [soke_bleu_tokens(r, level) for r in refs]))
    rouge = [soke_rouge_l_sentence(soke_rouge_tokens(h, level), soke_rouge_tokens(r, level))
             for h, r in zip(hyps, refs)]
    return SokeScores(**bleu, rouge_l=100.0 * sum(rouge) / len(rouge), level=level, sentences=len(hyps))


def soke_translation_metrics(hyps: Sequence[str], refs: Sequence[str], language: str) -> dict[str, float]:
    """Definition "soke" for one language: ``soke_bleu1..soke_bleu4, soke_rouge_l`` at :func:`soke_level`."""
    return soke_scores(hyps, refs, soke_level(language)).as_dict()


def _check_level(level: str) -> None:
    if level not in SOKE_LEVELS:
        raise ValueError(f"unknown SOKE scoring level {level!r}; use one of {SOKE_LEVELS}")
