"""The text scoring definitions by name (:mod:`m3t.metrics.definitions`): each selectable, each key named by its
definition, the same figures as each module's own call."""
from __future__ import annotations

import pytest

from m3t.metrics.definitions import TEXT_DEFINITIONS, text_metrics
from m3t.metrics.slrtp import slrtp_text_metrics
from m3t.metrics.soke_text import soke_translation_metrics
from m3t.metrics.text import slt_translation_metrics

HYPS = ["The cat sat on a mat", "we eat bread today"]
REFS = ["the cat sat on the mat", "we eat bread"]


def test_every_definition_is_selectable_and_names_its_keys():
    both = text_metrics(HYPS, REFS, "ASL", ("slt", "soke"))
    assert set(both) == {f"{d}_{k}" for d in ("slt", "soke") for k in ("bleu1", "bleu2", "bleu3", "bleu4",
                                                                       "rouge_l")}
    assert {k: v for k, v in both.items() if k.startswith("slt_")} == {
        f"slt_{k}": v for k, v in slt_translation_metrics(HYPS, REFS, "ASL").items()}
    assert {k: v for k, v in both.items() if k.startswith("soke_")} == soke_translation_metrics(HYPS, REFS, "ASL")
    assert text_metrics(HYPS, REFS, "DGS", ["slrtp"]) == slrtp_text_metrics(HYPS, REFS)
    everything = text_metrics(HYPS, REFS, "ASL")
    assert {k.split("_")[0] for k in everything} == set(TEXT_DEFINITIONS) == {"slt", "soke", "slrtp"}
    # lower-casing is where slt and soke part: "The" matches under slt only
    assert everything["slt_bleu1"] > everything["soke_bleu1"]


def test_chinese_gets_each_definitions_own_units():
    scores = text_metrics(["我爱你"], ["我爱你们"], "CSL-Daily", ["slt", "soke"])
    assert "slt_word_bleu1" in scores and "soke_bleu1" in scores and "soke_word_bleu1" not in scores


def test_an_unknown_or_empty_selection_is_refused_by_name():
    with pytest.raises(ValueError, match=r"text scoring definitions \['sacrebleu'\]: choose from slt, soke, slrtp"):
        text_metrics(HYPS, REFS, "ASL", ["slt", "sacrebleu"])
    with pytest.raises(ValueError, match="choose from slt, soke, slrtp"):
        text_metrics(HYPS, REFS, "ASL", [])
