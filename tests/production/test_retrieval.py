"""The ``retrieval`` baseline: exact match of the normalised text first, then the highest sentence chrF, ties to
the lowest clip id; the input's words its text lacks are listed.

Clips are built in the shard row layout (:class:`m3t.shards.schema.FittedClip` over a corpus
:class:`m3t.corpora.clip.Clip`: id, corpus, split, language, signer, text, gloss, media, fps), e.g. a Phoenix-2014T
row ``Clip("01April_2010_Thursday_heute-6694", "phoenix14t", "train", "DGS", "Signer04", "und nun die
wettervorhersage für morgen donnerstag den zweiten april", "JETZT WETTER MORGEN DONNERSTAG ZWEITE APRIL", ...)``.
"""
from __future__ import annotations

import numpy as np
import pytest
from sacrebleu.metrics import CHRF

from m3t.corpora.clip import Clip
from m3t.production.retrieval import RetrievalIndex, normalise, words
from m3t.shards.schema import FittedClip


def clip(cid: str, text: str, language: str = "DGS", frames: int = 3, label: int | None = None) -> FittedClip:
    record = Clip(cid, "phoenix14t", "train", language, "Signer04", text, "", f"{cid}.mp4", 25.0, label)
    params = {"body": np.full((frames, 2), float(int(cid[1:])), np.float32)}
    return FittedClip(record, "k", params, np.zeros(3, np.float32), {}, {}, "anny")


INDEX = RetrievalIndex([
    clip("c3", "und nun die wettervorhersage für morgen donnerstag"),
    clip("c1", "Und nun die Wettervorhersage für morgen, Donnerstag!"),  # the same text, lower id
    clip("c2", "im norden regnet es"),
    clip("c4", "im süden scheint die sonne"),
    clip("c5", "", frames=3),  # no text: never retrieved
    clip("c6", "im norden regnet es", frames=0),  # no motion: never retrieved
    clip("c7", "regen", label=12),  # an isolated sign: retrieved by its own text
    clip("c8", "the weather is nice", language="ASL"),
])


def test_normalise():
    assert normalise("  Und nun, die\tWetter-Vorhersage!  ") == "und nun die wetter vorhersage"
    assert normalise("Ｈｅｌｌｏ") == "hello"  # NFKC folds full-width letters


def test_exact_match_first_lowest_id():
    found = INDEX.nearest("UND NUN DIE WETTERVORHERSAGE FÜR MORGEN DONNERSTAG", "DGS")
    assert (found.clip.clip.id, found.match, found.score, found.missing_words) == ("c1", "exact", 100.0, ())
    np.testing.assert_array_equal(found.clip.params["body"], np.full((3, 2), 1.0))  # the motion, unchanged


def test_nearest_by_chrf_and_missing_words():
    found = INDEX.nearest("im norden regnet es morgen", "DGS")
    assert found.clip.clip.id == "c2" and found.match == "chrf"
    assert found.score == pytest.approx(CHRF().sentence_score("im norden regnet es morgen",
                                                               ["im norden regnet es"]).score)
    assert found.missing_words == ("morgen",)
    assert INDEX.nearest("sonne im süden", "DGS").clip.clip.id == "c4"
    assert INDEX.nearest("Regen!", "DGS").clip.clip.id == "c7"  # an isolated sign's text names it exactly


def test_no_shared_ngram_retrieves_the_lowest_id():
    found = INDEX.nearest("xyz", "DGS")
    assert (found.clip.clip.id, found.score, found.missing_words) == ("c1", 0.0, ("xyz",))


def test_languages_and_refusals():
    assert INDEX.languages == ["ASL", "DGS"]
    assert INDEX.nearest("weather nice", "ASL").clip.clip.id == "c8"
    with pytest.raises(ValueError, match=r"no training clip with text in sign language 'CSL'; the training shards "
                                         r"hold \['ASL', 'DGS'\]"):
        INDEX.nearest("你好", "CSL")
    with pytest.raises(ValueError, match=r"empty text: give a sentence to produce"):
        INDEX.nearest(" !? ", "DGS")


def test_chinese_words_by_jieba():
    index = RetrievalIndex([clip("c1", "我爱北京", language="CSL")])
    found = index.nearest("我爱上海", "CSL")  # jieba: 我 / 爱 / 上海 against 我 / 爱 / 北京
    assert found.clip.clip.id == "c1" and found.missing_words == ("上海",)
    assert words("今天 天气", "DGS") == ["今天", "天气"]
