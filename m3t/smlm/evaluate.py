"""Evaluating the SMLM (M3T Tab. 1): production by DTW joint errors against the fitted motion, translation
by BLEU-4 / ROUGE-L.

Production: text -> greedy motion tokens -> frozen FSQ decoders -> parameters -> body model -> the metric
point sets of :mod:`m3t.body.metric_sets` (12 upper-body points, 21 per hand, face vertices), compared with
the clip's fitted motion by :mod:`m3t.metrics.motion` (SOKE's DTW-JPE / DTW-PA-JPE, face DTW-VPE). Both
sides use the clip's signer identity, so the error is the motion's alone. Translation: the clip's
ground-truth motion tokens -> text.

Results are reported overall and per ``<corpus>/<language>`` group, the columns of Tab. 1.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch

from m3t.body.metric_sets import metric_keypoints, metric_points
from m3t.body.protocol import BodyModel
from m3t.fitting.evaluate import as_tensors
from m3t.metrics.motion import evaluate_pairs, summarise
from m3t.metrics.text import translation_metrics
from m3t.shards.schema import FittedClip
from m3t.smlm.data import Example
from m3t.smlm.generate import GeneratedMotion, generate_motion, translate
from m3t.smlm.model import SignMotionLM
from m3t.smlm.vocab import SignVocabulary
from m3t.tokenizers.evaluate import decode_streams
from m3t.tokenizers.vae import MotionTokenizer

SELECTION_METRIC = "dtw_jpe_mean_m"  # mean of body and hand DTW-JPE (raw), the checkpoint criterion


@dataclass
class EvaluationReport:
    summary: dict[str, float]
    per_clip: list[dict] = field(default_factory=list)
    generated: dict[str, GeneratedMotion] = field(default_factory=dict)
    translations: dict[str, str] = field(default_factory=dict)


def group_name(example: Example, reference: FittedClip) -> str:
    return f"{reference.clip.corpus}/{example.language}"


class SMLMEvaluator:
    """Holds the evaluation clips, their reference metric points and the frozen tokenizers."""

    def __init__(self, body: BodyModel, tokenizers: dict[str, MotionTokenizer], vocab: SignVocabulary,
                 examples: Sequence[Example], references: dict[str, FittedClip], batch_size: int = 16,
                 max_clips: int = 0, translation: bool = True):
        missing = [e.clip_id for e in examples if e.clip_id not in references]
        if missing:
            raise KeyError(f"no fitted motion for clips {missing[:5]} (of {len(missing)}); the token shards and the "
                           "fitted shards come from different runs: rerun `dvc repro tokenize`")
        self.body, self.tokenizers, self.vocab = body, tokenizers, vocab
        self.examples = list(examples)[: max_clips] if max_clips > 0 else list(examples)
        self.references = {e.clip_id: references[e.clip_id] for e in self.examples}
        self.batch_size, self.translation = batch_size, translation
        self.sets = metric_keypoints(body)
        self._truth = {cid: self.points(ref.params, ref.identity) for cid, ref in self.references.items()}

    @torch.no_grad()
    def points(self, params: dict[str, np.ndarray], identity: np.ndarray) -> dict[str, np.ndarray]:
        ident = torch.as_tensor(np.asarray(identity), dtype=torch.float32)
        return {k: v.numpy().astype(np.float64) for k, v in metric_points(self.body, as_tensors(params), ident, self.sets).items()}

    def motion_params(self, generated: GeneratedMotion) -> dict[str, np.ndarray]:
        return decode_streams(self.tokenizers, generated.tokens)

    def generate(self, model: SignMotionLM) -> dict[str, GeneratedMotion]:
        out = {}
        for i in range(0, len(self.examples), self.batch_size):
            chunk = self.examples[i: i + self.batch_size]
            for example, g in zip(chunk, generate_motion(model, self.vocab, [e.text for e in chunk],
                                                         [e.language for e in chunk])):
                out[example.clip_id] = g
        return out

    def evaluate(self, model: SignMotionLM) -> EvaluationReport:
        """Generate (and translate) every evaluation clip with ``model``, then score."""
        return self.score(self.generate(model), self.translate(model) if self.translation else None)

    def score(self, generated: dict[str, GeneratedMotion], translations: dict[str, str] | None = None) -> EvaluationReport:
        """Score generated tokens (and translations) of the evaluation clips, e.g. read back from disk."""
        lost = [e.clip_id for e in self.examples if e.clip_id not in generated]
        if lost:
            raise KeyError(f"no generated motion for clips {lost[:5]} (of {len(lost)}); rerun the generate stage")
        pairs, rows = [], []
        for example in self.examples:
            g = generated[example.clip_id]
            ref = self.references[example.clip_id]
            row = {"clip_id": example.clip_id, "group": group_name(example, ref), "steps": len(g.tokens["body"]),
                   "stopped": float(g.stopped)}
            if row["steps"] == 0:  # EOS at the first step: nothing to compare, counted as a failed generation
                rows.append(row)
                continue
            pairs.append((self.points(self.motion_params(g), ref.identity), self._truth[example.clip_id]))
            rows.append(row)
        scored = iter(evaluate_pairs(pairs))
        for row in rows:
            if row["steps"] > 0:
                row.update(next(scored))
        report = EvaluationReport(self._summary(rows), rows, generated)
        if translations is not None:
            report.translations = translations
            report.summary.update(self._text_scores(translations))
        return report

    def __call__(self, model: SignMotionLM) -> dict[str, float]:
        return self.evaluate(model).summary

    def _summary(self, rows: list[dict]) -> dict[str, float]:
        scored = [r for r in rows if r["steps"] > 0]
        metrics = {k: v for k, v in summarise([_metric_part(r) for r in scored]).items()} if scored else {}
        out = dict(metrics)
        out["stopped_rate"] = float(np.mean([r["stopped"] for r in rows])) if rows else 0.0
        out["empty_rate"] = float(np.mean([r["steps"] == 0 for r in rows])) if rows else 0.0
        out["mean_steps"] = float(np.mean([r["steps"] for r in rows])) if rows else 0.0
        if metrics:
            out[SELECTION_METRIC] = 0.5 * (metrics["dtw_jpe_body_m"] + metrics["dtw_jpe_hand_m"])
        else:  # nothing generated: the worst possible score, so such a checkpoint is never selected
            out[SELECTION_METRIC] = float("inf")
        groups = defaultdict(list)
        for r in scored:
            groups[r["group"]].append(_metric_part(r))
        for group, parts in groups.items():
            out.update({f"{group}/{k}": v for k, v in summarise(parts).items()})
        return out

    def translate(self, model: SignMotionLM) -> dict[str, str]:
        """Ground-truth motion tokens of every evaluation clip -> text."""
        out = {}
        for i in range(0, len(self.examples), self.batch_size):
            chunk = self.examples[i: i + self.batch_size]
            for example, text in zip(chunk, translate(model, self.vocab, [e.motion for e in chunk],
                                                      [e.language for e in chunk])):
                out[example.clip_id] = text
        return out

    def _text_scores(self, translations: dict[str, str]) -> dict[str, float]:
        by_language = defaultdict(lambda: ([], []))
        lost = [e.clip_id for e in self.examples if e.clip_id not in translations]
        if lost:
            raise KeyError(f"no translation for clips {lost[:5]} (of {len(lost)}); rerun the generate stage")
        for example in self.examples:
            hyps, refs = by_language[example.language]
            hyps.append(translations[example.clip_id])
            refs.append(example.text)
        out, bleu = {}, []
        for language, (hyps, refs) in by_language.items():
            scores = translation_metrics(hyps, refs, language)
            out.update({f"translation/{language}/{k}": v for k, v in scores.items()})
            bleu.append(scores["bleu4"])
        out["translation_bleu4"] = float(np.mean(bleu))
        return out


def _metric_part(row: dict) -> dict[str, float]:
    return {k: v for k, v in row.items() if k.startswith("dtw_")}
