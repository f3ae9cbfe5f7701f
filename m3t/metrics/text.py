"""Translation metrics of back-translated or recognised text: corpus BLEU-4 (sacrebleu) and ROUGE-L.

Both are on a 0-100 scale. Tokenisation decides what a token is and must match across compared systems:

- ``"13a"``: sacrebleu's standard tokeniser (punctuation split off), for Latin-script text (Phoenix, How2Sign);
- ``"zh"``: jieba word segmentation, for Chinese (CSL-Daily reports word-level scores);
- ``"char"``: every non-space character is a token (character-level Chinese scores).

BLEU is sacrebleu's corpus BLEU (4-gram, brevity penalty, default ``exp`` smoothing) on the text as tokenised
here. ROUGE-L is computed here on the same tokens: per sentence, the longest common subsequence gives
precision ``P = LCS / |hyp|`` and recall ``R = LCS / |ref|``, ``F = (1 + b^2) P R / (R + b^2 P)`` (b = 1 by
default: the F1 of Lin 2004), then the mean over sentences. Text is compared as given (no lower-casing).
``translation_metrics_by_language`` scores a multilingual set one language at a time (Tab. 1's columns).

**Definition "slt"** (:func:`slt_scores`, :func:`slt_translation_metrics`, :func:`slt_metrics_by_language`): the
back-translation scoring of the field, the arithmetic of SL-T (Camgoz et al. 2020, ``neccam/slt``,
``signjoey/metrics.py`` over its vendored sacreBLEU 1.4.4 and MS-COCO ROUGE), copied unchanged by Progressive
Transformers and SignSparK_BT (SOKE kept its BLEU but not its ROUGE-L, and compares text as given: definition
``soke``, :mod:`m3t.metrics.soke_text`), re-implemented here (not pasted):

- text is lower-cased (SL-T's data pipeline, ``txt_lowercase: true``, does it before scoring) and split on
  whitespace (sacreBLEU ``raw_corpus_bleu``: ``tokenize="none"``; SL-T's ROUGE splits on single spaces, the same
  on its single-space-joined tokens), one reference per hypothesis;
- BLEU-n (n = 1..4) = ``BP * (p_1 ... p_n) ** (1 / n)`` x 100 on corpus-level clipped n-gram counts, with
  ``BP = exp(1 - ref_len / hyp_len)`` when the hypotheses are shorter (0 when they are empty), else 1. No
  smoothing (``smooth_method="floor", smooth_value=0``, i.e. sacreBLEU 2's ``"none"``): an order with no match
  makes that BLEU-n and every higher one 0. SL-T's BLEU-n are the cumulative scores of one 4-gram computation;
  its ``use_effective_order=True`` does not reach them, so an order the hypotheses never reach (no 4-gram in the
  whole corpus) also gives 0 there, where sacreBLEU 2's ``BLEU(max_ngram_order=n, effective_order=True)``
  would drop that order. Both agree whenever every order has at least one hypothesis n-gram;
- ROUGE-L = per sentence the MS-COCO F-measure ``(1 + b^2) P R / (R + b^2 P)`` of the LCS with ``b = 1.2``,
  averaged over sentences, x100;
- units (:func:`slt_unit`): ``"word"`` for every language but Chinese; Chinese (a language in ``CHINESE`` or
  with such a prefix before ``-``, e.g. ``CSL``, ``CSL-SYN``) is scored per character (SL-T's CSL-Daily
  convention: spaces removed, characters joined by spaces, punctuation kept as characters) and, beside it, per
  jieba word (``word_`` keys) on the same space-free text, as M3T segments Chinese with jieba.
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import sacrebleu
from sacrebleu.tokenizers.tokenizer_13a import Tokenizer13a

TOKENIZERS = ("13a", "zh", "char")
CHINESE = ("zh", "zho", "chinese", "csl", "csl-daily")


def is_chinese(language: str) -> bool:
    """Whether ``language`` (a sign or spoken language code, e.g. ``CSL``, ``CSL-SYN``, ``zh``) has Chinese text."""
    code = language.lower()
    return code in CHINESE or code.split("-")[0] in CHINESE


def _jieba():
    import jieba

    jieba.setLogLevel(logging.WARNING)  # its dictionary-loading chatter, once per process, not our output
    return jieba


def tokenize(text: str, method: str = "13a") -> list[str]:
    """Tokens of ``text`` under ``method`` (one of ``TOKENIZERS``)."""
    if method == "13a":
        return Tokenizer13a()(text).split()
    if method == "zh":
        return [w for w in _jieba().lcut(text) if w.strip()]
    if method == "char":
        return [c for c in text if not c.isspace()]
    raise ValueError(f"unknown tokenizer {method!r}; use one of {TOKENIZERS}")


def _check(hyps: Sequence[str], refs: Sequence[str]) -> None:
    if len(hyps) != len(refs):
        raise ValueError(f"{len(hyps)} hypotheses but {len(refs)} references; give one reference per hypothesis")
    if not hyps:
        raise ValueError("no hypotheses to score; give at least one (hypothesis, reference) pair")
    for n, (h, r) in enumerate(zip(hyps, refs)):
        if not isinstance(h, str) or not isinstance(r, str):
            raise TypeError(f"pair {n}: hypothesis and reference must be strings, got {type(h).__name__}, "
                             f"{type(r).__name__}")


def bleu4(hyps: Sequence[str], refs: Sequence[str], method: str = "13a") -> float:
    """Corpus BLEU-4 (0-100) of hypotheses against one reference each."""
    _check(hyps, refs)
    if method == "13a":
        return float(sacrebleu.corpus_bleu(list(hyps), [list(refs)], tokenize="13a").score)
    hyp_text = [" ".join(tokenize(h, method)) for h in hyps]
    ref_text = [" ".join(tokenize(r, method)) for r in refs]
    return float(sacrebleu.corpus_bleu(hyp_text, [ref_text], tokenize="none").score)


def lcs_length(a: Sequence[str], b: Sequence[str]) -> int:
    """Length of the longest common subsequence of two token lists (O(|a| |b|) DP, one row kept)."""
    if len(a) < len(b):
        a, b = b, a
    row = [0] * (len(b) + 1)
    for x in a:
        prev_diag = 0
        for j, y in enumerate(b, start=1):
            prev_diag, row[j] = row[j], prev_diag + 1 if x == y else max(row[j], row[j - 1])
    return row[-1]


def rouge_l_sentence(hyp: Sequence[str], ref: Sequence[str], beta: float = 1.0) -> float:
    """ROUGE-L F-measure (0-1) of one token list against one reference; two empty lists score 1."""
    if not hyp and not ref:
        return 1.0
    lcs = lcs_length(hyp, ref)
    if lcs == 0:
        return 0.0
    precision, recall = lcs / len(hyp), lcs / len(ref)
    return (1 + beta ** 2) * precision * recall / (recall + beta ** 2 * precision)


def rouge_l(hyps: Sequence[str], refs: Sequence[str], method: str = "13a", beta: float = 1.0) -> float:
    """Mean sentence ROUGE-L F-measure (0-100) of hypotheses against one reference each."""
    _check(hyps, refs)
    scores = [rouge_l_sentence(tokenize(h, method), tokenize(r, method), beta) for h, r in zip(hyps, refs)]
    return 100.0 * sum(scores) / len(scores)


def translation_metrics(hyps: Sequence[str], refs: Sequence[str], language: str,
                        method: str | None = None) -> dict[str, float]:
    """``{"bleu4", "rouge_l"}`` on a 0-100 scale; Chinese (``language`` or its prefix before ``-`` in
    ``CHINESE``, e.g. ``CSL`` or ``CSL-SYN``) is segmented by jieba, anything else uses sacrebleu's 13a
    tokeniser, unless ``method`` names a tokeniser explicitly."""
    method = method or ("zh" if is_chinese(language) else "13a")
    if method not in TOKENIZERS:
        raise ValueError(f"unknown tokenizer {method!r}; use one of {TOKENIZERS}")
    return {"bleu4": bleu4(hyps, refs, method), "rouge_l": rouge_l(hyps, refs, method)}


def translation_metrics_by_language(hyps: Sequence[str], refs: Sequence[str],
                                    languages: Sequence[str]) -> dict[str, float]:
    """:func:`translation_metrics` per language: ``translation/<language>/bleu4`` and ``.../rouge_l`` (languages
    in first-seen order), and ``translation_bleu4``, the mean of the per-language BLEU-4 (each language weighs
    alike, however many sentences it has; NaN when there is no sentence)."""
    if not len(hyps) == len(refs) == len(languages):
        raise ValueError(f"{len(hyps)} hypotheses, {len(refs)} references and {len(languages)} languages; give one "
                         "reference and one language per hypothesis")
    by_language: dict[str, tuple[list[str], list[str]]] = {}
    for hyp, ref, language in zip(hyps, refs, languages):
        pair = by_language.setdefault(language, ([], []))
        pair[0].append(hyp)
        pair[1].append(ref)
    out, bleu = {}, []
    for language, (lang_hyps, lang_refs) in by_language.items():
        scores = translation_metrics(lang_hyps, lang_refs, language)
        out.update({f"translation/{language}/{k}": v for k, v in scores.items()})
        bleu.append(scores["bleu4"])
    out["translation_bleu4"] = float(np.mean(bleu)) if bleu else float("nan")
    return out


# ---- definition "slt": SL-T's back-translation scoring ---------------------------------------------------
SLT_DEFINITION = "slt"
SLT_MAX_ORDER = 4
SLT_ROUGE_BETA = 1.2
SLT_UNITS = ("word", "char", "jieba")


def slt_unit(language: str) -> str:
    """The primary scoring unit of ``language`` under definition "slt": ``"char"`` for Chinese, else ``"word"``."""
    return "char" if is_chinese(language) else "word"


def slt_tokens(text: str, unit: str = "word") -> list[str]:
    """Tokens of ``text`` as definition "slt" scores them: lower-cased; ``"word"``: whitespace split; ``"char"``:
    every non-space character; ``"jieba"``: jieba words of the space-free text."""
    text = text.lower()
    if unit == "word":
        return text.split()
    compact = "".join(text.split())
    if unit == "char":
        return list(compact)
    if unit == "jieba":
        return [w for w in _jieba().lcut(compact) if w.strip()]
    raise ValueError(f"unknown scoring unit {unit!r}; use one of {SLT_UNITS}")


@dataclass(frozen=True)
class BleuStatistics:
    """Corpus-level sufficient statistics of BLEU: clipped n-gram matches and hypothesis n-gram counts per order
    (index 0 = unigrams), summed hypothesis and reference lengths in tokens."""

    matches: tuple[int, ...]
    totals: tuple[int, ...]
    hyp_len: int
    ref_len: int


def _ngrams(tokens: Sequence[str], max_order: int) -> Counter:
    return Counter(tuple(tokens[i:i + n]) for n in range(1, max_order + 1) for i in range(len(tokens) - n + 1))


def bleu_statistics(hyp_tokens: Sequence[Sequence[str]], ref_tokens: Sequence[Sequence[str]],
                    max_order: int = SLT_MAX_ORDER) -> BleuStatistics:
    """Clipped n-gram counts of tokenised hypotheses against one tokenised reference each."""
    matches, totals = [0] * max_order, [0] * max_order
    hyp_len = ref_len = 0
    for hyp, ref in zip(hyp_tokens, ref_tokens, strict=True):
        hyp_len, ref_len = hyp_len + len(hyp), ref_len + len(ref)
        ref_counts = _ngrams(ref, max_order)
        for gram, count in _ngrams(hyp, max_order).items():
            totals[len(gram) - 1] += count
            matches[len(gram) - 1] += min(count, ref_counts.get(gram, 0))
    return BleuStatistics(tuple(matches), tuple(totals), hyp_len, ref_len)


def slt_bleu_from_statistics(stats: BleuStatistics) -> dict[str, float]:
    """``{"bleu1", ..., "bleu<max order>"}`` (0-100) from corpus statistics, SL-T's arithmetic (module docstring)."""
    precisions = []
    for matched, total in zip(stats.matches, stats.totals):
        if total == 0:  # SL-T stops here: this order and every higher one keep precision 0
            break
        precisions.append(matched / total)
    precisions += [0.0] * (len(stats.matches) - len(precisions))
    if stats.hyp_len < stats.ref_len:
        bp = math.exp(1 - stats.ref_len / stats.hyp_len) if stats.hyp_len > 0 else 0.0
    else:
        bp = 1.0
    out = {}
    for n in range(1, len(precisions) + 1):
        head = precisions[:n]
        geo = 0.0 if min(head) == 0.0 else math.exp(sum(math.log(p) for p in head) / n)
        out[f"bleu{n}"] = 100.0 * bp * geo
    return out


@dataclass(frozen=True)
class SLTScores:
    """One corpus scored under definition "slt" in one unit; all scores 0-100."""

    bleu1: float
    bleu2: float
    bleu3: float
    bleu4: float
    rouge_l: float
    unit: str  # "word" | "char" | "jieba"
    sentences: int
    definition: str = SLT_DEFINITION

    def as_dict(self, prefix: str = "") -> dict[str, float]:
        """The five scores as ``{prefix + "bleu1", ..., prefix + "rouge_l"}``."""
        names = ("bleu1", "bleu2", "bleu3", "bleu4", "rouge_l")
        return {prefix + k: float(getattr(self, k)) for k in names}


def slt_scores(hyps: Sequence[str], refs: Sequence[str], unit: str = "word") -> SLTScores:
    """BLEU-1..4 and ROUGE-L (b = 1.2) of hypotheses against one reference each, definition "slt", in ``unit``.
    An empty hypothesis is a sentence like any other (it adds reference length and scores ROUGE-L 0)."""
    _check(hyps, refs)
    hyp_tokens = [slt_tokens(h, unit) for h in hyps]
    ref_tokens = [slt_tokens(r, unit) for r in refs]
    bleu = slt_bleu_from_statistics(bleu_statistics(hyp_tokens, ref_tokens))
    rouge = [rouge_l_sentence(h, r, SLT_ROUGE_BETA) for h, r in zip(hyp_tokens, ref_tokens)]
    return SLTScores(**bleu, rouge_l=100.0 * sum(rouge) / len(rouge), unit=unit, sentences=len(hyps))


def slt_translation_metrics(hyps: Sequence[str], refs: Sequence[str], language: str) -> dict[str, float]:
    """Definition "slt" for one language: ``bleu1..bleu4, rouge_l`` in :func:`slt_unit` (per character for
    Chinese), and for Chinese also ``word_bleu1..word_bleu4, word_rouge_l`` per jieba word."""
    out = slt_scores(hyps, refs, slt_unit(language)).as_dict()
    if is_chinese(language):
        out.update(slt_scores(hyps, refs, "jieba").as_dict("word_"))
    return out


def slt_metrics_by_language(hyps: Sequence[str], refs: Sequence[str], languages: Sequence[str],
                            prefix: str = SLT_DEFINITION) -> dict[str, float]:
    """:func:`slt_translation_metrics` per language: ``<prefix>/<language>/<metric>`` (languages in first-seen
    order) and ``<prefix>/<language>/sentences``; ``<prefix>_bleu4`` and ``<prefix>_rouge_l``, the means over
    languages (each language weighs alike; NaN when there is no sentence)."""
    if not len(hyps) == len(refs) == len(languages):
        raise ValueError(f"{len(hyps)} hypotheses, {len(refs)} references and {len(languages)} languages; give one "
                         "reference and one language per hypothesis")
    groups: dict[str, list[int]] = {}
    for i, language in enumerate(languages):
        groups.setdefault(language, []).append(i)
    out: dict[str, float] = {}
    bleu, rouge = [], []
    for language, rows in groups.items():
        scores = slt_translation_metrics([hyps[i] for i in rows], [refs[i] for i in rows], language)
        out.update({f"{prefix}/{language}/{k}": v for k, v in scores.items()})
        out[f"{prefix}/{language}/sentences"] = float(len(rows))
        bleu.append(scores["bleu4"])
        rouge.append(scores["rouge_l"])
    out[f"{prefix}_bleu4"] = float(np.mean(bleu)) if bleu else float("nan")
    out[f"{prefix}_rouge_l"] = float(np.mean(rouge)) if rouge else float("nan")
    return out
