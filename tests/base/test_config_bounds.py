"""The bounds every model and stage section of ``params.yaml`` checks when it is built (SGSA, the recognition
probe and its trimming, the back-translation judge): the first value outside a bound is refused with a message
that names the key and the value, and the bound itself is accepted. Written because mutation testing showed
that no test touched these edges: a ``< 1`` turned into ``<= 1`` or an emptied message went unnoticed."""
from __future__ import annotations

import math
import re

import pytest

from m3t.backtranslation.config import BackTranslationConfig, BackTranslationTrainConfig
from m3t.sgsa.config import SGSAConfig, SGSAEvaluateConfig, SGSATrainConfig
from m3t.slr.config import SLRConfig, SLREvaluateConfig, SLRTrainConfig, TrimConfig

AT_LEAST_ONE = [(SGSAConfig, "sgsa", key) for key in ("encoder_layers", "encoder_heads", "decoder_heads",
                                                      "standard_layers", "max_frames", "max_text_tokens",
                                                      "min_token_frequency", "min_frames")]
AT_LEAST_ONE += [(SGSATrainConfig, "sgsa_train", key) for key in ("epochs", "batch_size", "eval_every", "workers")]
AT_LEAST_ONE += [(BackTranslationConfig, "backtranslation", key)
                 for key in ("attention_heads", "encoder_layers", "decoder_layers", "max_frames", "max_text_tokens",
                             "beam_size", "min_token_frequency")]
AT_LEAST_ONE += [(BackTranslationTrainConfig, "backtranslation_train", key)
                 for key in ("epochs", "batch_size", "eval_every", "workers")]
AT_LEAST_ONE += [(SLRTrainConfig, "slr_train", "workers")]


@pytest.mark.parametrize(("cls", "section", "key"), AT_LEAST_ONE, ids=lambda v: getattr(v, "__name__", v))
def test_counts_below_one_are_refused_by_name_and_one_is_accepted(cls, section, key):
    with pytest.raises(ValueError, match=rf"^{section}\.{key}: expected >= 1, got 0$"):
        cls(**{key: 0})
    assert getattr(cls(**{key: 1}), key) == 1


@pytest.mark.parametrize(("cls", "section", "key"), [
    (SGSAConfig, "sgsa", "gloss_weight"), (BackTranslationConfig, "backtranslation", "gloss_ctc_weight"),
    (SGSATrainConfig, "sgsa_train", "noise_rate"), (SGSATrainConfig, "sgsa_train", "noise_cap"),
    (SGSATrainConfig, "sgsa_train", "counter_weight")])
def test_weights_below_zero_are_refused_by_name_and_zero_is_accepted(cls, section, key):
    with pytest.raises(ValueError, match=rf"^{section}\.{key}: expected >= 0, got -0.5$"):
        cls(**{key: -0.5})
    assert getattr(cls(**{key: 0.0}), key) == 0.0


@pytest.mark.parametrize(("cls", "section"), [(SGSATrainConfig, "sgsa_train"),
                                              (BackTranslationTrainConfig, "backtranslation_train")])
def test_the_plateau_factor_lies_strictly_between_zero_and_one(cls, section):
    for bad in (0.0, 1.0, -0.1, 1.5):
        with pytest.raises(ValueError, match=rf"^{section}\.lr_factor: expected in \(0, 1\), got {bad}$"):
            cls(lr_factor=bad)
    assert cls(lr_factor=0.01).lr_factor == 0.01 and cls(lr_factor=0.99).lr_factor == 0.99


def test_sgsa_widths_must_split_into_heads_and_the_baselines_only_when_it_is_the_baseline():
    with pytest.raises(ValueError, match=r"^sgsa.encoder_width 10 is not divisible by encoder_heads 4$"):
        SGSAConfig(encoder_width=10, encoder_heads=4)
    assert SGSAConfig(encoder_width=12, encoder_heads=4).encoder_width == 12
    with pytest.raises(ValueError, match=r"^sgsa.standard_width 10 is not divisible by decoder_heads 4$"):
        SGSAConfig(decoder_layers=0, standard_width=10, decoder_heads=4)
    assert SGSAConfig(decoder_layers=1, standard_width=10, decoder_heads=4).standard_width == 10  # unused by SGSA
    for key in ("decoder_layers", "temporal_adjacency"):
        values = {"decoder_layers": 2, "temporal_adjacency": 1} | {key: -1}
        with pytest.raises(ValueError, match=re.escape(
                f"sgsa.decoder_layers / temporal_adjacency: expected >= 0, got {values['decoder_layers']} / "
                f"{values['temporal_adjacency']}")):
            SGSAConfig(**{key: -1})
    with pytest.raises(ValueError, match=r"^backtranslation.d_model 30 is not divisible by attention_heads 4$"):
        BackTranslationConfig(d_model=30, attention_heads=4)


def test_the_sgsa_system_names_its_variant_and_band():
    sgsa = SGSAConfig(decoder_layers=5, temporal_adjacency=0)
    assert (sgsa.system, sgsa.variant, sgsa.band) == ("SGSA", "SGSA L=5 N=inf", math.inf)
    banded = SGSAConfig(decoder_layers=2, temporal_adjacency=3)
    assert (banded.variant, banded.band) == ("SGSA L=2 N=3", 3.0)
    pt = banded.for_system("pt")
    assert (pt.decoder_layers, pt.temporal_adjacency, pt.system, pt.variant, pt.band) == (0, 0, "PT", "PT", math.inf)
    assert banded.for_system("sgsa") is banded
    with pytest.raises(ValueError, match=r"^system 'gpt' unknown; allowed: pt, sgsa$"):
        banded.for_system("gpt")


def test_system_variant_and_split_lists_must_be_known_distinct_and_non_empty():
    for systems in (("pt", "pt"), (), ("pt", "gpt")):
        with pytest.raises(ValueError, match=re.escape(f"sgsa_train.systems {list(systems)}: expected distinct "
                                                       "names of ['pt', 'sgsa']")):
            SGSATrainConfig(systems=systems)
    assert SGSATrainConfig(systems=("sgsa",)).systems == ("sgsa",)
    for variants in (("full", "full"), (), ("full", "hands")):
        with pytest.raises(ValueError, match=re.escape(f"variants {list(variants)}: expected distinct names of "
                                                       "['full', 'no_face']")):
            SLRTrainConfig(variants=variants)
    for variants in ((), ("hands",)):
        with pytest.raises(ValueError, match=re.escape(f"variants {list(variants)}: expected names of "
                                                       "['full', 'no_face']")):
            SLREvaluateConfig(variants=variants)
    assert SLREvaluateConfig(variants=("no_face", "no_face")).variants == ("no_face", "no_face")  # scoring twice
    for splits in ((), ("test", "val")):
        with pytest.raises(ValueError, match=re.escape(f"sgsa_evaluate.splits {list(splits)}: expected a non-empty "
                                                       "subset of train, dev, test")):
            SGSAEvaluateConfig(splits=splits)
    assert SGSAEvaluateConfig(splits=("train",)).splits == ("train",)
    with pytest.raises(ValueError, match=r"^sgsa_evaluate.counter 'oracle' unknown; allowed: predicted, "
                                         r"ground_truth$"):
        SGSAEvaluateConfig(counter="oracle")


def test_the_probe_and_its_trimming_check_their_sizes():
    for key in ("layers", "heads", "ffn_mult", "max_steps"):
        with pytest.raises(ValueError, match=r"^layers, heads, ffn_mult and max_steps must be >= 1, head_hidden >= 0$"):
            SLRConfig(**{key: 0})
        assert getattr(SLRConfig(**{key: 1}), key) == 1
    with pytest.raises(ValueError, match="head_hidden >= 0"):
        SLRConfig(head_hidden=-1)
    assert SLRConfig(head_hidden=0).head_hidden == 0
    for key in ("height_threshold", "displacement_threshold"):
        with pytest.raises(ValueError, match=r"^height_threshold and displacement_threshold must be > 0 "
                                             r"\(in shoulder widths\)$"):
            TrimConfig(**{key: 0.0})
        assert getattr(TrimConfig(**{key: 1e-3}), key) == 1e-3
    with pytest.raises(ValueError, match=r"^margin must be >= 0 and min_frames >= 1, got -1, 16$"):
        TrimConfig(margin=-1)
    with pytest.raises(ValueError, match=r"^margin must be >= 0 and min_frames >= 1, got 2, 0$"):
        TrimConfig(min_frames=0)
    assert (TrimConfig(margin=0, min_frames=1).margin, TrimConfig(min_frames=1).min_frames) == (0, 1)
    for confidence, bootstrap in ((0.0, 10), (1.0, 10), (0.9, 0)):
        with pytest.raises(ValueError, match=r"^confidence must be in \(0, 1\) and bootstrap >= 1$"):
            SLREvaluateConfig(confidence=confidence, bootstrap=bootstrap)
    assert SLREvaluateConfig(confidence=0.5, bootstrap=1).bootstrap == 1
