"""BLEU-4 and ROUGE-L of translations: identical text, hand-computed ROUGE-L, Chinese segmentation, errors; and
definition "slt" (SL-T's back-translation scoring) against hand-counted n-grams."""
from __future__ import annotations

import math

import pytest

from m3t.metrics.text import (
    SLT_ROUGE_BETA,
    bleu4,
    bleu_statistics,
    lcs_length,
    rouge_l,
    slt_metrics_by_language,
    slt_scores,
    slt_tokens,
    slt_translation_metrics,
    tokenize,
    translation_metrics,
)

SENTENCES = ["am tag wird es regnen und kalt", "the weather stays dry in the north", "morgen scheint die sonne"]


@pytest.mark.parametrize("method", ["13a", "zh", "char"])
def test_identical_text_scores_100(method):
    out = translation_metrics(SENTENCES, SENTENCES, "de", method=method)
    assert out["bleu4"] == pytest.approx(100.0)
    assert out["rouge_l"] == pytest.approx(100.0)


def test_rouge_l_hand_computed():
    # "the cat on the mat" is common: LCS 5 of 6 and 6 tokens -> P = R = F = 5/6.
    # "a c" is common: LCS 2, P = 2/4, R = 2/3 -> F = 2 P R / (P + R) = 4/7.
    hyps, refs = ["the cat sat on the mat", "a b c d"], ["the cat is on the mat", "a c e"]
    assert lcs_length(["a", "b", "c", "d"], ["a", "c", "e"]) == 2
    assert rouge_l(hyps, refs) == pytest.approx(100 * (5 / 6 + 4 / 7) / 2)
    assert rouge_l(["x y"], ["z"]) == 0.0


def test_bleu_penalises_a_different_translation():
    assert bleu4(["the sun shines tomorrow in the south"], ["tomorrow it will rain in the north"]) < 30.0


def test_chinese_is_segmented_into_words_by_jieba():
    tokens = tokenize("我今天去学校", "zh")
    assert "今天" in tokens and "学校" in tokens
    assert tokenize("我 今天", "char") == ["我", "今", "天"]
    hyp, ref = ["我今天去学校"], ["我明天去学校"]
    words = translation_metrics(hyp, ref, "zh")  # jieba words: 3 of 4 shared
    chars = translation_metrics(hyp, ref, "zh", method="char")  # characters: 5 of 6 shared
    assert words["rouge_l"] == pytest.approx(75.0)
    assert chars["rouge_l"] == pytest.approx(100 * 5 / 6)


def test_latin_uses_13a_tokenisation():
    assert tokenize("Hello, world!") == ["Hello", ",", "world", "!"]
    # 13a splits off punctuation: 4 hypothesis tokens, 2 reference tokens, LCS 2 -> P = 1/2, R = 1, F = 2/3.
    out = translation_metrics(["Hello, world!"], ["Hello world"], "en")
    assert out["rouge_l"] == pytest.approx(100 * 2 / 3)


@pytest.mark.parametrize("hyps,refs,message", [
    (["a"], ["a", "b"], "1 hypotheses but 2 references"),
    ([], [], "no hypotheses"),
])
def test_bad_inputs_raise(hyps, refs, message):
    with pytest.raises(ValueError, match=message):
        translation_metrics(hyps, refs, "en")


def test_non_string_is_a_type_error():
    with pytest.raises(TypeError, match="must be strings"):
        translation_metrics([1], ["a"], "en")


def test_unknown_tokenizer_raises():
    with pytest.raises(ValueError, match="unknown tokenizer"):
        translation_metrics(["a"], ["a"], "en", method="spm")


def test_language_prefix_selects_the_chinese_segmentation():
    from m3t.metrics.text import translation_metrics

    hyps, refs = ["我的朋友买车"], ["我的朋友买车了"]
    assert translation_metrics(hyps, refs, "CSL-SYN") == translation_metrics(hyps, refs, "CSL")
    assert translation_metrics(hyps, refs, "CSL-SYN") != translation_metrics(hyps, refs, "ASL")


# ---- definition "slt": SL-T's back-translation scoring ------------------------------------------------------
LONG = ["am tag wird es regnen und kalt", "the weather stays dry in the north", "morgen scheint die sonne heute"]


def test_slt_bleu_against_hand_counted_ngrams():
    # hyp 1 "the cat sat on the mat" vs ref "the cat is on the mat":
    #   1-grams 6, matched 5 (the x2, cat, on, mat); 2-grams 5, matched 3 (the cat, on the, the mat);
    #   3-grams 4, matched 1 (on the mat); 4-grams 3, matched 0.
    # hyp 2 "a dog runs" vs ref "the dog runs fast": 1-grams 3 / 2 (dog, runs); 2-grams 2 / 1 (dog runs);
    #   3-grams 1 / 0; 4-grams none.
    hyps, refs = ["the cat sat on the mat", "a dog runs"], ["the cat is on the mat", "the dog runs fast"]
    stats = bleu_statistics([h.split() for h in hyps], [r.split() for r in refs])
    assert stats.matches == (7, 4, 1, 0) and stats.totals == (9, 7, 5, 3)
    assert (stats.hyp_len, stats.ref_len) == (9, 10)
    bp = math.exp(1 - 10 / 9)  # hypotheses shorter than the references
    out = slt_scores(hyps, refs)
    assert out.bleu1 == pytest.approx(100 * bp * 7 / 9)
    assert out.bleu2 == pytest.approx(100 * bp * (7 / 9 * 4 / 7) ** 0.5)
    assert out.bleu3 == pytest.approx(100 * bp * (7 / 9 * 4 / 7 * 1 / 5) ** (1 / 3))
    assert out.bleu4 == 0.0  # no 4-gram matched, no smoothing
    assert out.definition == "slt" and out.unit == "word" and out.sentences == 2


def test_slt_bleu_agrees_with_sacrebleu_when_every_order_has_ngrams():
    from sacrebleu.metrics import BLEU

    hyps = ["the cat sat on the mat today", "a dog runs in the park"]
    refs = ["the cat is on the mat today", "the dog runs in a big park"]
    ours = slt_scores(hyps, refs).as_dict()
    for n in range(1, 5):
        theirs = BLEU(tokenize="none", smooth_method="none", max_ngram_order=n, effective_order=True)
        assert ours[f"bleu{n}"] == pytest.approx(theirs.corpus_score(hyps, [refs]).score, abs=1e-9)


def test_slt_bleu_of_references_with_themselves_and_of_empty_hypotheses():
    assert slt_scores(LONG, LONG).as_dict() == pytest.approx(
        {"bleu1": 100, "bleu2": 100, "bleu3": 100, "bleu4": 100, "rouge_l": 100})
    empty = slt_scores(["", ""], LONG[:2])
    assert empty.as_dict() == {"bleu1": 0.0, "bleu2": 0.0, "bleu3": 0.0, "bleu4": 0.0, "rouge_l": 0.0}
    # SL-T stops at the first order no hypothesis reaches: 3-token sentences match themselves, yet BLEU-4 is 0
    short = slt_scores(["a b c"], ["a b c"])
    assert short.bleu3 == pytest.approx(100.0) and short.bleu4 == 0.0


def test_slt_rouge_l_uses_beta_1_2_on_a_hand_computed_lcs():
    # "a b c d" vs "a c e": LCS "a c" = 2, P = 2/4, R = 2/3
    p, r, b2 = 2 / 4, 2 / 3, SLT_ROUGE_BETA ** 2
    assert SLT_ROUGE_BETA == 1.2
    assert slt_scores(["a b c d"], ["a c e"]).rouge_l == pytest.approx(100 * (1 + b2) * p * r / (r + b2 * p))
    assert slt_scores(["a b c d", "x"], ["a c e", "x"]).rouge_l == pytest.approx(
        50 * ((1 + b2) * p * r / (r + b2 * p) + 1))


def test_slt_lower_cases_where_the_13a_definition_keeps_case():
    assert slt_scores(["The Weather Stays Dry"], ["the weather stays dry"]).bleu4 == pytest.approx(100.0)
    assert bleu4(["The Weather Stays Dry"], ["the weather stays dry"]) < 100.0
    assert slt_tokens("Guten Morgen, Welt.") == ["guten", "morgen,", "welt."]  # whitespace split only


def test_slt_chinese_is_scored_per_character_with_jieba_words_beside():
    assert slt_tokens("我 今天 去", "char") == ["我", "今", "天", "去"]
    out = slt_translation_metrics(["我今天去学校"], ["我明天去 学校"], "CSL-SYN")
    # characters: 1-grams 5/6, 2-grams 3/5, 3-grams 2/4, 4-grams 1/3, equal lengths (BP 1)
    assert out["bleu1"] == pytest.approx(100 * 5 / 6)
    assert out["bleu4"] == pytest.approx(100 * (5 / 6 * 3 / 5 * 2 / 4 * 1 / 3) ** 0.25)
    assert out["rouge_l"] == pytest.approx(100 * 5 / 6)  # P = R: beta does not matter
    # jieba words 我 / 今天 / 去 / 学校 vs 我 / 明天 / 去 / 学校: 3 of 4 unigrams, 1 of 3 bigrams, no trigram
    assert out["word_bleu1"] == pytest.approx(75.0) and out["word_bleu3"] == 0.0
    assert "word_bleu1" not in slt_translation_metrics(["a b"], ["a b"], "ASL")


def test_slt_metrics_by_language_names_the_definition_and_counts_sentences():
    hyps = LONG + ["我今天去学校"]
    refs = LONG[:2] + ["morgen scheint die sonne", "我今天去学校"]
    out = slt_metrics_by_language(hyps, refs, ["DGS", "ASL", "DGS", "CSL"])
    assert list(out)[0].startswith("slt/DGS/")
    assert out["slt/DGS/sentences"] == 2 and out["slt/CSL/bleu4"] == pytest.approx(100.0)
    assert out["slt_bleu4"] == pytest.approx((out["slt/DGS/bleu4"] + out["slt/ASL/bleu4"] + 100) / 3)
    with pytest.raises(ValueError, match="3 languages"):
        slt_metrics_by_language(hyps, refs, ["DGS", "ASL", "CSL"])


def test_bleu_refuses_a_tokenizer_name_it_does_not_know_even_in_another_case():
    for method in ("13A", "ZH", "intl"):
        with pytest.raises(ValueError, match=rf"^unknown tokenizer '{method}'; use one of \('13a', 'zh', 'char'\)$"):
            bleu4(["the friend buys a car"], ["the friend buys a red car"], method=method)
