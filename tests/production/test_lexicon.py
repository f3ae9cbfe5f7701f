"""The lexicon baseline and the baselines' production for a split, on hand-made clips.

Clip records follow the embedded corpus's layout (``m3t/corpora/synthetic.py``): an isolated sign is
``Clip(id='iso-apple-signer00-1', corpus='synthetic', split='train', language='ISO-SYN', signer='signer00',
text='the apple', gloss='APPLE', ..., label=10)``; a sentence ``Clip(id='asl-syn-0003', ..., language='ASL-SYN',
text='The child reads the book', gloss='BOOK CHILD READ', label=None)``.
"""
from __future__ import annotations

import numpy as np
import pytest

from m3t.corpora.clip import Clip
from m3t.production.baselines import produce_baselines
from m3t.production.config import BaselinesConfig
from m3t.production.lexicon import Lexicon, concatenate
from m3t.shards.schema import FittedClip


def fitted(cid: str, text: str, gloss: str, language: str, value: float, frames: int = 3,
           label: int | None = None) -> FittedClip:
    record = Clip(cid, "synthetic", "train", language, "signer00", text, gloss, f"motion/{cid}.npz", 25.0, label)
    params = {"body": np.full((frames, 2), value, np.float32), "face": np.full((frames, 1), -value, np.float32)}
    return FittedClip(record, "k", params, np.zeros(3, np.float32), {}, {}, "anny")


SIGNS = [
    fitted("iso-apple-signer01-1", "the apple", "APPLE", "ISO-SYN", 2.0, label=10),
    fitted("iso-apple-signer00-1", "the apple", "APPLE", "ISO-SYN", 1.0, label=10),  # lowest id: the entry
    fitted("iso-book-signer00-1", "the book", "BOOK", "ISO-SYN", 5.0, frames=2, label=3),
    fitted("iso-read-signer00-1", "reads", "READ", "ISO-SYN", 9.0, frames=4, label=7),
    fitted("iso-pair-signer00-1", "two signs", "A B", "ISO-SYN", 7.0, label=1),  # not one gloss: no entry
    fitted("asl-syn-0003", "The child reads the book", "BOOK CHILD READ", "ASL-SYN", 3.0),  # a sentence: no entry
]


def test_one_entry_per_gloss_the_lowest_id_and_distinctive_words():
    lexicon = Lexicon(SIGNS)
    assert sorted(lexicon.entries) == ["APPLE", "BOOK", "READ"] and len(lexicon) == 3
    assert lexicon.entries["APPLE"].clip.id == "iso-apple-signer00-1"
    # "the" names two glosses, so it names none; the sentence's words are not the lexicon's
    assert lexicon.word_to_gloss == {"apple": "APPLE", "book": "BOOK", "reads": "READ"}
    assert lexicon.languages == ["ISO-SYN"]


def test_lookup_by_gloss_stitches_with_interpolated_transitions():
    made = Lexicon(SIGNS).lookup("The child reads the book", "BOOK CHILD READ", "ASL-SYN", "gloss", 3)
    assert made.input == "gloss" and made.tokens == 3
    assert made.used == (("BOOK", "iso-book-signer00-1"), ("READ", "iso-read-signer00-1"))
    assert made.missing == ("CHILD",)
    assert made.frames == 2 + 3 + 4
    body = made.params["body"][:, 0]
    # from 5 (BOOK's last frame) to 9 (READ's first) in 4 steps of 1: 6, 7, 8 between them
    np.testing.assert_allclose(body, [5, 5, 6, 7, 8, 9, 9, 9, 9])
    np.testing.assert_allclose(made.params["face"][:, 0], -body)  # every modality alike


def test_lookup_by_words_and_the_gloss_fallback():
    lexicon = Lexicon(SIGNS)
    made = lexicon.lookup("The child reads the book", "BOOK CHILD READ", "ASL-SYN", "words", 0)
    assert made.input == "words" and made.tokens == 5
    assert [g for g, _ in made.used] == ["READ", "BOOK"]  # in the text's order
    assert made.missing == ("the", "child", "the")
    assert made.frames == 4 + 2  # no transition frames
    unannotated = lexicon.lookup("an apple", "", "ASL-SYN", "gloss", 2)  # no gloss annotation: its words
    assert unannotated.input == "words" and unannotated.used == (("APPLE", "iso-apple-signer00-1"),)


def test_nothing_found_is_no_motion_and_own_language_entries_win():
    lexicon = Lexicon(SIGNS)
    made = lexicon.lookup("x", "HOUSE CAR", "ASL-SYN")
    assert made.params == {} and made.frames == 0 and made.missing == ("HOUSE", "CAR")
    # entries of the sentence's own sign language serve it alone
    own = Lexicon([*SIGNS, fitted("dgs-apple", "Apfel", "APPLE", "DGS-SYN", 4.0, label=10)])
    assert own.lookup("", "APPLE BOOK", "DGS-SYN").used == (("APPLE", "dgs-apple"),)
    with pytest.raises(ValueError, match="lexicon input 'letters' unknown; allowed: gloss, words"):
        lexicon.lookup("x", "A", "ASL-SYN", "letters")


def test_concatenate_edges():
    assert concatenate([], 3) == {}
    one = {"body": np.ones((2, 1), np.float32)}
    np.testing.assert_array_equal(concatenate([one], 5)["body"], one["body"])
    with pytest.raises(ValueError, match="transition_frames must be >= 0, got -1"):
        concatenate([one], -1)
    with pytest.raises(ValueError, match="lexicon entries with different modalities"):
        concatenate([one, {"face": np.ones((2, 1), np.float32)}], 1)


def test_produce_baselines_rows_and_statistics():
    train = [fitted("asl-syn-0001", "The child reads the book", "BOOK CHILD READ", "ASL-SYN", 3.0, frames=5),
             fitted("asl-syn-0002", "I see the car", "CAR I SEE", "ASL-SYN", 4.0, frames=6)]
    tests = [fitted("asl-syn-0009", "the child reads the book!", "BOOK CHILD READ", "ASL-SYN", 0.0),
             fitted("asl-syn-0010", "the child sees the car", "CAR CHILD SEE", "ASL-SYN", 0.0),
             fitted("dgs-syn-0001", "Das Kind liest", "CHILD READ", "DGS-SYN", 0.0)]
    made = produce_baselines(tests, train, SIGNS, BaselinesConfig(transition_frames=1))
    retrieval, lexicon = made["retrieval"], made["lexicon"]
    rows = {r["clip_id"]: r for r in retrieval.rows}
    assert (rows["asl-syn-0009"]["match"], rows["asl-syn-0009"]["source"]) == ("exact", "asl-syn-0001")
    np.testing.assert_array_equal(retrieval.motion["asl-syn-0009"]["body"], np.full((5, 2), 3.0))  # unchanged
    assert rows["asl-syn-0010"]["match"] == "chrf"
    assert rows["dgs-syn-0001"]["match"] == "none" and retrieval.motion["dgs-syn-0001"] == {}
    assert "no training clip with text in sign language 'DGS-SYN'" in rows["dgs-syn-0001"]["reason"]
    stats = retrieval.statistics()
    assert stats["exact_rate"] == pytest.approx(1 / 3) and stats["no_motion_rate"] == pytest.approx(1 / 3)
    assert stats["mean_frames"] == pytest.approx(np.mean([5, rows["asl-syn-0010"]["frames"], 0]))
    lex = {r["clip_id"]: r for r in lexicon.rows}
    assert lex["asl-syn-0009"]["source"] == "iso-book-signer00-1 iso-read-signer00-1"
    assert lex["asl-syn-0009"]["frames"] == 2 + 1 + 4
    assert lex["asl-syn-0010"]["missing_words"] == "CAR CHILD SEE" and lex["asl-syn-0010"]["frames"] == 0
    assert lexicon.statistics()["missing_rate"] == pytest.approx((1 + 3 + 1) / (3 + 3 + 2))
    only = produce_baselines(tests, train, SIGNS, BaselinesConfig(systems=("lexicon",)))
    assert list(only) == ["lexicon"]


def test_config_refusals():
    with pytest.raises(ValueError, match=r"baselines.systems \['copy'\]: expected a non-empty subset of retrieval, "
                                         r"lexicon"):
        BaselinesConfig(systems=("copy",))
    with pytest.raises(ValueError, match="baselines.lexicon_input 'letters' unknown; allowed: gloss, words"):
        BaselinesConfig(lexicon_input="letters")
    with pytest.raises(ValueError, match="baselines.transition_frames must be >= 0, got -2"):
        BaselinesConfig(transition_frames=-2)
