"""The field's text scoring definitions by name (docs/scoring.md): one call scores back-translated sentences
under any of them, each result key carrying its definition's name.

- ``slt``: SL-T's metrics (:mod:`m3t.metrics.text`), keys ``slt_bleu1..4``, ``slt_rouge_l`` (and for Chinese the
  jieba-word scores ``slt_word_*``);
- ``soke``: SOKE's (:mod:`m3t.metrics.soke_text`), keys ``soke_bleu1..4``, ``soke_rouge_l``;
- ``slrtp``: the SLRTP 2025 challenge's (:mod:`m3t.metrics.slrtp`), keys ``slrtp_bleu1..4``, ``slrtp_chrf``,
  ``slrtp_rouge_l``, ``slrtp_wer``.

The motion definitions take different inputs (body-model parameters, 178 SLRTP keypoints, pose-format's holistic
points) and are called from their modules.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

from m3t.metrics.slrtp import slrtp_text_metrics
from m3t.metrics.soke_text import soke_translation_metrics
from m3t.metrics.text import slt_translation_metrics

TextDefinition = Callable[[Sequence[str], Sequence[str], str], dict[str, float]]

TEXT_DEFINITIONS: dict[str, TextDefinition] = {
    "slt": lambda hyps, refs, language: {f"slt_{k}": v for k, v in slt_translation_metrics(hyps, refs,
                                                                                            language).items()},
    "soke": soke_translation_metrics,
    "slrtp": lambda hyps, refs, language: slrtp_text_metrics(hyps, refs),
}


def text_metrics(hyps: Sequence[str], refs: Sequence[str], language: str,
                 definitions: Iterable[str] = tuple(TEXT_DEFINITIONS)) -> dict[str, float]:
    """The scores of ``hyps`` against ``refs`` (one language) under each named definition, keys prefixed by it."""
    definitions = list(definitions)
    unknown = [d for d in definitions if d not in TEXT_DEFINITIONS]
    if unknown or not definitions:
        raise ValueError(f"text scoring definitions {unknown or definitions}: choose from "
                         f"{', '.join(TEXT_DEFINITIONS)}")
    out: dict[str, float] = {}
    for name in definitions:
        out.update(TEXT_DEFINITIONS[name](hyps, refs, language))
    return out
