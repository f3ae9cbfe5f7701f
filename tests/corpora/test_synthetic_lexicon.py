"""The synthetic corpus's lexicon (:mod:`m3t.corpora.synthetic_lexicon`): minimal pairs, distinct manual forms of
normal signs, sentence lengths and each language's word order, mouthings.
"""
from __future__ import annotations

import numpy as np
import pytest

from m3t.corpora.synthetic_lexicon import (
    CONCEPTS,
    LANGUAGES,
    VISEMES,
    build_lexicon,
    make_sentence,
)


# ----------------------------------------------------------------------------------------- synthetic lexicon
def test_lexicon_can_be_all_minimal_pairs_but_not_more_pairs_than_signs():
    signs = build_lexicon(6, 3, np.random.default_rng(0))
    assert [s.group for s in signs] == ["confusing"] * 6 and [s.pair for s in signs] == [0, 0, 1, 1, 2, 2]
    for a, b in zip(signs[::2], signs[1::2]):
        assert a.manual() == b.manual() and a.mouthing != b.mouthing and a.brows != b.brows
    assert len(build_lexicon(5, 2, np.random.default_rng(0))) == 5
    with pytest.raises(ValueError, match=r"corpus.confusing_pairs=3 needs at least 6 signs"):
        build_lexicon(5, 3, np.random.default_rng(0))
    with pytest.raises(ValueError, match=rf"corpus.num_signs=29 exceeds the {len(CONCEPTS)} concepts"):
        build_lexicon(len(CONCEPTS) + 1, 0, np.random.default_rng(0))


@pytest.mark.parametrize("seed", range(6))
def test_normal_signs_differ_in_their_manual_form(seed):
    """Normal signs are told apart by the hands alone: no two share handshape, location, movement and
    handedness (only the minimal pairs share a manual form)."""
    signs = build_lexicon(len(CONCEPTS), 2, np.random.default_rng(seed))
    np.testing.assert_allclose([np.linalg.norm(s.axis) for s in signs], 1.0)  # movement directions are unit vectors
    normal = [s.manual()[:4] for s in signs if s.group == "normal"]
    assert len(normal) == len(CONCEPTS) - 4 and len(set(normal)) == len(normal)


def test_sentences_have_as_many_glosses_as_asked_in_each_word_order():
    signs = build_lexicon(len(CONCEPTS), 0, np.random.default_rng(1))
    rng = np.random.default_rng(2)
    for language in LANGUAGES:
        for length in (2, 3, 4):
            for _ in range(5):
                text, gloss = make_sentence(signs, language, length, rng)
                roles = [CONCEPTS[g][0] for g in gloss]
                assert len(gloss) == length and sorted(roles) == sorted(["person", "verb", "thing", "time"][:length])
                assert text and (text.endswith("。") if language == "CSL-SYN" else text[0].isupper())
    _, gloss = make_sentence(signs, "ASL-SYN", 4, np.random.default_rng(3))
    assert [CONCEPTS[g][0] for g in gloss] == ["time", "thing", "person", "verb"]


def test_sentence_text_follows_each_languages_word_order():
    signs = build_lexicon(28, 2, np.random.default_rng(0))
    column = {"ASL-SYN": 1, "DGS-SYN": 2, "CSL-SYN": 3}
    for language, col in column.items():
        for length in (2, 3, 4):
            for seed in range(3):
                text, gloss = make_sentence(signs, language, length, np.random.default_rng(seed))
                role = {CONCEPTS[g][0]: CONCEPTS[g][col] for g in gloss}
                s, v, o, t = (role.get(r) for r in ("person", "verb", "thing", "time"))
                if language == "ASL-SYN":
                    words = [s, v, o, t]
                elif language == "DGS-SYN":
                    words = [t, v, s, o] if t else [s, v, o]
                else:
                    words = [t, s, v, o]
                words = [x for x in words if x]
                if language == "CSL-SYN":
                    assert text == "".join(words) + "。"
                else:
                    joined = " ".join(words)
                    assert text == joined[0].upper() + joined[1:]


def test_mouthings_run_one_to_three_visemes():
    signs = build_lexicon(len(CONCEPTS), 2, np.random.default_rng(0))
    assert all(set(s.mouthing) <= set(VISEMES) for s in signs)
    assert {len(s.mouthing) for s in signs if s.group == "normal"} == {1, 2, 3}
    assert {len(s.mouthing) for s in signs if s.group == "confusing"} <= {1, 2, 3}
