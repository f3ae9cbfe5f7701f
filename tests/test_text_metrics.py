"""BLEU-4 and ROUGE-L of translations: identical text, hand-computed ROUGE-L, Chinese segmentation, errors."""
from __future__ import annotations

import pytest

from m3t.metrics.text import bleu4, lcs_length, rouge_l, tokenize, translation_metrics

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
