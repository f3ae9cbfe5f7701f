"""Definition "soke" (:mod:`m3t.metrics.soke_text`): SOKE's back-translation BLEU and ROUGE-L on sentences whose
scores are worked out by hand below from SOKE's formulas (``mGPT/metrics/utils.py``, ``mGPT/metrics/Rouge.py``).

SOKE's ROUGE-L F with ``beta = P / R`` simplifies to ``(R^2 + P^2) R P / (R^3 + P^3)`` (symmetric in P and R), the
form the hand values use. Floats are compared with a relative tolerance of 1e-9: the implementation carries
tf-seq2seq's 1e-12 guards, which move the result by about 1e-12."""
from __future__ import annotations

import math

import pytest

from m3t.metrics.soke_text import (
    soke_level,
    soke_rouge_l_sentence,
    soke_rouge_tokens,
    soke_scores,
    soke_translation_metrics,
)
from m3t.metrics.text import slt_scores


def f_soke(recall: float, precision: float) -> float:
    return (recall ** 2 + precision ** 2) * recall * precision / (recall ** 3 + precision ** 3)


def test_rouge_l_follows_the_precision_recall_ratio_not_a_fixed_beta():
    # "the cat sat" vs "the cat sat on the mat": LCS 3, R = 3/6, P = 3/3 -> 5/9
    assert soke_scores(["the cat sat"], ["the cat sat on the mat"]).rouge_l == pytest.approx(100 * 5 / 9, rel=1e-9)
    assert f_soke(0.5, 1.0) == pytest.approx(5 / 9)
    # a hypothesis four times too long: P = 1/4, R = 1 -> SOKE 0.2615, SL-T (beta 1.2) 0.4485: 18.7 points apart
    soke = soke_scores(["a b c d"], ["a"]).rouge_l
    slt = slt_scores(["a b c d"], ["a"]).rouge_l
    assert soke == pytest.approx(100 * f_soke(1.0, 0.25), rel=1e-9) == pytest.approx(26.1538, abs=1e-4)
    assert slt == pytest.approx(100 * 2.44 * 0.25 / (1 + 1.44 * 0.25), rel=1e-9)
    assert slt - soke == pytest.approx(18.70, abs=0.01)


def test_text_is_compared_as_given_and_an_empty_hypothesis_scores_zero():
    # "The cat" vs "the cat": only "cat" matches (no lower-casing): P = R = 1/2 -> 1/2
    assert soke_scores(["The cat"], ["the cat"]).rouge_l == pytest.approx(50.0, rel=1e-9)
    assert soke_rouge_tokens("") == [""]  # SOKE splits "" into one empty token
    empty = soke_scores([""], ["a b"])
    assert empty.rouge_l == 0.0 and empty.bleu1 == 0.0
    assert soke_rouge_l_sentence(["a", "b", "c"], ["a", "b", "c"]) == pytest.approx(1.0, rel=1e-9)


def test_corpus_bleu_is_sl_ts_arithmetic_on_case_sensitive_whitespace_tokens():
    hyps = ["the cat sat", "a b c", "The cat"]
    refs = ["the cat sat on the mat", "a b c", "the cat"]
    scores = soke_scores(hyps, refs)
    # unigrams 7 / 8 ("The" misses), bigrams 4 / 5, trigrams 2 / 2, no 4-gram in any hypothesis;
    # hypothesis length 8 < reference length 11: brevity penalty exp(1 - 11 / 8)
    bp = math.exp(1 - 11 / 8)
    assert scores.bleu1 == pytest.approx(100 * bp * 7 / 8, rel=1e-9)
    assert scores.bleu2 == pytest.approx(100 * bp * (7 / 8 * 4 / 5) ** (1 / 2), rel=1e-9)
    assert scores.bleu3 == pytest.approx(100 * bp * (7 / 8 * 4 / 5 * 1) ** (1 / 3), rel=1e-9)
    assert scores.bleu4 == 0.0  # SL-T's cumulative 4-gram score: an order no hypothesis reaches gives 0
    assert scores.rouge_l == pytest.approx(100 * (5 / 9 + 1 + 1 / 2) / 3, rel=1e-9)
    assert (scores.sentences, scores.level, scores.definition) == (3, "word", "soke")


def test_chinese_is_scored_per_character_and_a_space_counts_in_rouge_only():
    assert (soke_level("CSL-Daily"), soke_level("CSL-SYN"), soke_level("ASL")) == ("char", "char", "word")
    # "我爱 你" vs "我爱你们": ROUGE tokens 我 爱 '' '' 你 (the space becomes two empty tokens) vs 我 爱 你 们:
    # LCS 3, P = 3/5, R = 3/4; BLEU tokens 我 爱 你 vs 我 爱 你 们: unigrams 3/3, bigrams 2/2, trigrams 1/1
    assert soke_rouge_tokens("我爱 你", "char") == ["我", "爱", "", "", "你"]
    metrics = soke_translation_metrics(["我爱 你"], ["我爱你们"], "CSL-Daily")
    assert metrics["soke_rouge_l"] == pytest.approx(100 * f_soke(0.75, 0.6), rel=1e-9)
    assert metrics["soke_rouge_l"] == pytest.approx(65.080, abs=1e-3)
    bp = math.exp(1 - 4 / 3)
    assert metrics["soke_bleu1"] == pytest.approx(100 * bp, rel=1e-9)
    assert metrics["soke_bleu3"] == pytest.approx(100 * bp, rel=1e-9) and metrics["soke_bleu4"] == 0.0
    assert set(metrics) == {"soke_bleu1", "soke_bleu2", "soke_bleu3", "soke_bleu4", "soke_rouge_l"}


def test_bad_input_is_named():
    with pytest.raises(ValueError, match=r"^2 hypotheses but 1 references; give one reference per hypothesis$"):
        soke_scores(["a", "b"], ["a"])
    with pytest.raises(ValueError, match=r"^no hypotheses to score; give at least one \(hypothesis, reference\) "
                                         r"pair$"):
        soke_scores([], [])
    with pytest.raises(TypeError, match=r"^pair 0: hypothesis and reference must be strings, got NoneType, str$"):
        soke_scores([None], ["a"])
    with pytest.raises(ValueError, match=r"unknown SOKE scoring level 'jieba'"):
        soke_scores(["a"], ["a"], "jieba")
    with pytest.raises(ValueError, match="at least one token on each side"):
        soke_rouge_l_sentence([], ["a"])
