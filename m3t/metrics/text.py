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
"""
from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import sacrebleu
from sacrebleu.tokenizers.tokenizer_13a import Tokenizer13a

TOKENIZERS = ("13a", "zh", "char")
CHINESE = ("zh", "zho", "chinese", "csl", "csl-daily")


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
    code = language.lower()
    method = method or ("zh" if code in CHINESE or code.split("-")[0] in CHINESE else "13a")
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
