"""Evaluating the SMLM (M3T Tab. 1): production by DTW joint errors against the fitted motion, translation
by BLEU-4 / ROUGE-L.

Production: text -> greedy motion tokens -> frozen FSQ decoders -> parameters, scored against the clip's
fitted motion by the one motion scorer (:class:`m3t.metrics.scorer.MotionScorer`: the metric point sets of
:mod:`m3t.body.metric_sets`, SOKE's DTW-JPE / DTW-PA-JPE, face DTW-VPE). Translation: the clip's ground-truth
motion tokens -> text, scored per language by :func:`m3t.metrics.text.translation_metrics_by_language`.

Results are reported overall and per ``<corpus>/<language>`` group, the columns of Tab. 1.
"""
from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from m3t.body.protocol import BodyModel
from m3t.digest import file_digest
from m3t.fitting.cluster import submitted_in_order
from m3t.journal import Journal
from m3t.metrics.motion import MotionMetricsConfig
from m3t.metrics.scorer import (
    REFERENCE_FRAMES,
    ClipScore,
    MotionPair,
    MotionScorer,
    MotionScores,
    budget_runs,
    score_on_worker,
)
from m3t.metrics.text import translation_metrics_by_language
from m3t.shards.references import StoredClip
from m3t.shards.schema import FittedClip
from m3t.smlm.checkpoint import LoadedSMLM, load_smlm
from m3t.smlm.data import Example
from m3t.smlm.generate import GeneratedMotion, generate_motion, translate
from m3t.smlm.model import SignMotionLM
from m3t.smlm.vocab import SignVocabulary
from m3t.tokenizers.evaluate import decode_streams
from m3t.tokenizers.vae import MotionTokenizer

JOURNAL_SECTION = "dtw"  # the scored clips of a resumable evaluation (m3t.journal)
SELECTION_METRIC = "dtw_jpe_mean_m"  # mean of body and hand DTW-JPE (raw), the checkpoint criterion


@dataclass
class EvaluationReport:
    summary: dict[str, float]
    per_clip: list[dict] = field(default_factory=list)
    generated: dict[str, GeneratedMotion] = field(default_factory=dict)
    translations: dict[str, str] = field(default_factory=dict)


def motion_summary(scores: MotionScores) -> dict[str, float]:
    """The selection figure (mean of body and hand DTW-JPE; inf without any clip: never selected) and the
    per-group figures, added to the overall ones of a summary."""
    if scores.overall:
        out = {SELECTION_METRIC: 0.5 * (scores.overall["dtw_jpe_body_m"] + scores.overall["dtw_jpe_hand_m"])}
    else:  # no evaluation clip at all (an empty generation is scored as the rest pose): never selected
        out = {SELECTION_METRIC: float("inf")}
    return {**out, **scores.group_summary}


def score_against(scorer: MotionScorer, references: Sequence[FittedClip],
                  motion: dict[str, dict[str, np.ndarray]]) -> MotionScores:
    """Parameters ``{clip id: {modality: (T, D_m)}}`` (``{}``: no motion, scored as the rest pose) of every
    reference clip, against it, both posed with the reference's identity, per ``<corpus>/<language>`` group (the
    SMLM evaluation's groups): how the SMLM's generations are scored, and any other system beside them."""
    lost = [r.clip.id for r in references if r.clip.id not in motion]
    if lost:
        raise KeyError(f"no motion for clips {lost[:5]} (of {len(lost)})")
    return scorer.score([MotionPair(r.clip.id, f"{r.clip.corpus}/{r.clip.language}", motion[r.clip.id], r.identity)
                         for r in references])


class SMLMEvaluator:
    """Holds the evaluation clips, their references (registered with the scorer, posed when scored and cached
    within ``frame_budget`` frames: :class:`m3t.metrics.scorer.MotionScorer`) and the frozen tokenizers.

    ``references`` maps clip ids to fitted clips, in memory (:class:`m3t.shards.schema.FittedClip`) or left in
    their shards (:class:`m3t.shards.references.SplitReferences`: parameters read when a clip is posed or its
    reference given to a worker, so the evaluator's memory does not grow with the split)."""

    def __init__(self, body: BodyModel, tokenizers: dict[str, MotionTokenizer], vocab: SignVocabulary,
                 examples: Sequence[Example], references: Mapping[str, FittedClip | StoredClip], batch_size: int = 16,
                 max_clips: int = 0, translation: bool = True, motion: MotionMetricsConfig = MotionMetricsConfig(),
                 frame_budget: int = REFERENCE_FRAMES, body_config=None):
        missing = [e.clip_id for e in examples if e.clip_id not in references]
        if missing:
            raise KeyError(f"no fitted motion for clips {missing[:5]} (of {len(missing)}); the token shards and the "
                           "fitted shards come from different runs: rerun `dvc repro tokenize`")
        self.body, self.tokenizers, self.vocab = body, tokenizers, vocab
        self.examples = list(examples)[: max_clips] if max_clips > 0 else list(examples)
        self.references = {e.clip_id: references[e.clip_id] for e in self.examples}
        self.batch_size, self.translation = batch_size, translation
        self.body_config = body_config  # m3t.body.config.BodyConfig: what workers build ``body`` from
        # motion.mode "soke_exact": SOKE's body rooting (SMPL-FX only)
        self.scorer = MotionScorer(body, motion, frame_budget)
        for cid, ref in self.references.items():  # posed at the first evaluation; reused while the budget holds them
            if isinstance(ref, StoredClip):  # parameters left in the shard until posed
                self.scorer.reference_on_demand(cid, ref.num_frames, ref.identity, lambda ref=ref: ref.params)
            else:
                self.scorer.reference(cid, ref.params, ref.identity)

    def points(self, params: dict[str, np.ndarray], identity: np.ndarray) -> dict[str, np.ndarray]:
        """{region: (T, K, 3) float64 metres} of a parameter sequence, as scored."""
        return self.scorer.points(params, identity)

    def motion_params(self, generated: GeneratedMotion) -> dict[str, np.ndarray]:
        return decode_streams(self.tokenizers, generated.tokens)

    def _chunks(self) -> list[list[Example]]:
        """The evaluation clips in decoding batches of ``batch_size``, in order."""
        return [self.examples[i: i + self.batch_size] for i in range(0, len(self.examples), self.batch_size)]

    def _decoded(self, desc: str, progress: bool, chunks: list[list[Example]], results: Iterable[list]) -> dict:
        """{clip id: result} of each chunk's results (made as they are drawn), with a progress bar over clips."""
        from tqdm.auto import tqdm

        out = {}
        with tqdm(total=len(self.examples), desc=desc, unit="clip", disable=not progress) as bar:
            for chunk, made in zip(chunks, results):
                out.update((e.clip_id, m) for e, m in zip(chunk, made, strict=True))
                bar.update(len(chunk))
        return out

    def generate(self, model: SignMotionLM, progress: bool = False, executor=None,
                 checkpoint: str | os.PathLike | None = None) -> dict[str, GeneratedMotion]:
        """Text -> motion tokens of every evaluation clip (greedy), a decoding batch at a time: here with
        ``model``, or with an ``executor`` (:func:`m3t.fitting.cluster.stage_executor`) on its workers, which
        load ``checkpoint`` (``model``'s file, at the same path) once per process; the same batches either way."""
        chunks = self._chunks()
        if executor is None:
            made = (generate_motion(model, self.vocab, [e.text for e in c], [e.language for e in c],
                                    truncate_text=True) for c in chunks)
        else:
            made = submitted_in_order(executor, generate_on_worker, ((worker_checkpoint(checkpoint),
                                                                       [e.text for e in c], [e.language for e in c])
                                                                      for c in chunks))
        return self._decoded("generate", progress, chunks, made)

    def evaluate(self, model: SignMotionLM) -> EvaluationReport:
        """Generate (and translate) every evaluation clip with ``model``, then score."""
        return self.score(self.generate(model), self.translate(model) if self.translation else None)

    def score(self, generated: dict[str, GeneratedMotion], translations: dict[str, str] | None = None,
              journal: Journal | None = None, executor=None) -> EvaluationReport:
        """Score generated tokens (and translations) of the evaluation clips, e.g. read back from disk; with a
        ``journal`` (:mod:`m3t.journal`), a killed scoring resumes (:meth:`score_generated`)."""
        lost = [e.clip_id for e in self.examples if e.clip_id not in generated]
        if lost:
            raise KeyError(f"no generated motion for clips {lost[:5]} (of {len(lost)}); rerun the generate stage")
        steps = {e.clip_id: len(generated[e.clip_id].tokens["body"]) for e in self.examples}
        scores = self.score_generated(generated, steps, journal, executor)
        rows = [{"clip_id": c.clip_id, "group": c.group, "steps": steps[c.clip_id],
                 "stopped": float(generated[c.clip_id].stopped), **c.metrics} for c in scores.per_clip]
        summary = dict(scores.overall)
        summary["stopped_rate"] = float(np.mean([r["stopped"] for r in rows])) if rows else 0.0
        summary["empty_rate"] = scores.empty_rate
        summary["mean_steps"] = float(np.mean([r["steps"] for r in rows])) if rows else 0.0
        summary.update(motion_summary(scores))
        report = EvaluationReport(summary, rows, generated)
        if translations is not None:
            lost = [e.clip_id for e in self.examples if e.clip_id not in translations]
            if lost:
                raise KeyError(f"no translation for clips {lost[:5]} (of {len(lost)}); rerun the generate stage")
            report.translations = translations
            report.summary.update(translation_metrics_by_language(
                [translations[e.clip_id] for e in self.examples], [e.text for e in self.examples],
                [e.language for e in self.examples]))
        return report

    def score_generated(self, generated: dict[str, GeneratedMotion], steps: dict[str, int],
                        journal: Journal | None = None, executor=None) -> MotionScores:
        """Decode and score the generations in runs of examples whose frames stay within the scorer's budget (a
        longer clip alone): decoded parameters never outlive their run, whatever the number of clips. EOS at the
        first step leaves nothing to decode: an empty prediction, scored as the rest pose and counted. With a
        ``journal``, clips it holds are not scored again and every run is added to it once scored (a clip's
        figures do not depend on its run). With an ``executor`` (:func:`m3t.fitting.cluster.open_executor`) the
        runs are scored on its workers, the same figures."""
        done = journal.done(JOURNAL_SECTION) if journal is not None else {}
        todo = [e for e in self.examples if e.clip_id not in done]
        down = next(iter(self.tokenizers.values())).cfg.downsample
        cost = [steps[e.clip_id] * down + self.references[e.clip_id].num_frames for e in todo]
        scored = {cid: ClipScore(**row["score"]) for cid, row in done.items()}
        runs = [todo[run] for run in budget_runs(cost, self.scorer.frame_budget)]
        for fresh in self._scored_runs(runs, generated, steps, executor):
            if journal is not None:
                journal.add(JOURNAL_SECTION, [{"clip_id": c.clip_id, "score": dataclasses.asdict(c)} for c in fresh])
            scored.update((c.clip_id, c) for c in fresh)
        return MotionScores.of([scored[e.clip_id] for e in self.examples])

    def _scored_runs(self, runs: list[list[Example]], generated: dict[str, GeneratedMotion], steps: dict[str, int],
                     executor) -> Iterator[list[ClipScore]]:
        """Each run's clip scores, in order: here, or on ``executor``'s workers (each pair carries its reference
        parameters; :func:`m3t.fitting.cluster.submitted_in_order`)."""
        def motion(run):
            return {e.clip_id: self.motion_params(generated[e.clip_id]) if steps[e.clip_id] else {} for e in run}

        if executor is None:
            for run in runs:
                yield score_against(self.scorer, [self.references[e.clip_id] for e in run], motion(run)).per_clip
            return
        if self.body_config is None:
            raise ValueError("scoring on workers needs the body model's config (SMLMEvaluator(body_config=...))")

        def pairs(run):
            made, refs = motion(run), [self.references[e.clip_id] for e in run]
            return [MotionPair(r.clip.id, f"{r.clip.corpus}/{r.clip.language}", made[r.clip.id], r.identity, r.params)
                    for r in refs]

        yield from submitted_in_order(executor, score_on_worker, ((self.body_config, self.scorer.config,
                                                                   self.scorer.frame_budget, pairs(run))
                                                                  for run in runs))

    def score_motion(self, motion: dict[str, dict[str, np.ndarray]]) -> MotionScores:
        """Parameters of every evaluation clip against its reference (:func:`score_against`)."""
        return score_against(self.scorer, [self.references[e.clip_id] for e in self.examples], motion)

    def __call__(self, model: SignMotionLM) -> dict[str, float]:
        return self.evaluate(model).summary

    def translate(self, model: SignMotionLM, progress: bool = False, executor=None,
                  checkpoint: str | os.PathLike | None = None) -> dict[str, str]:
        """Ground-truth motion tokens of every evaluation clip -> text; ``executor`` and ``checkpoint`` as in
        :meth:`generate`."""
        chunks = self._chunks()
        if executor is None:
            made = (translate(model, self.vocab, [e.motion for e in c], [e.language for e in c]) for c in chunks)
        else:
            made = submitted_in_order(executor, translate_on_worker, ((worker_checkpoint(checkpoint),
                                                                        [e.motion for e in c], [e.language for e in c])
                                                                       for c in chunks))
        return self._decoded("translate", progress, chunks, made)


# ------------------------------------------------------------------------------------------ decoding on workers
def worker_checkpoint(path: str | os.PathLike | None) -> tuple[str, str]:
    """How a worker finds the run's SMLM: its absolute path (workers see the run's files at the same paths, as
    fit-corpus's do) and the digest of its bytes, which the worker checks."""
    if path is None:
        raise ValueError("decoding on workers needs the checkpoint's path (generate(..., checkpoint=...))")
    return os.path.abspath(path), file_digest(path, length=16)


def generate_on_worker(checkpoint: tuple[str, str], texts: list[str], languages: list[str]) -> list[GeneratedMotion]:
    """One decoding batch of :meth:`SMLMEvaluator.generate` on a worker process."""
    loaded = _worker_smlm(checkpoint)
    return generate_motion(loaded.model, loaded.vocab, texts, languages, truncate_text=True)


def translate_on_worker(checkpoint: tuple[str, str], motions: list[np.ndarray], languages: list[str]) -> list[str]:
    """One decoding batch of :meth:`SMLMEvaluator.translate` on a worker process."""
    loaded = _worker_smlm(checkpoint)
    return translate(loaded.model, loaded.vocab, motions, languages)


_WORKER_SMLM: dict[tuple[str, str], LoadedSMLM] = {}


def _worker_smlm(checkpoint: tuple[str, str]) -> LoadedSMLM:
    """The checkpoint ``(path, digest)``, loaded once per worker process (the last one only: a 396M-parameter
    model is large); a file at that path with other bytes is refused."""
    if checkpoint not in _WORKER_SMLM:
        path, digest = checkpoint
        found = file_digest(path, length=16)
        if found != digest:
            raise RuntimeError(f"the SMLM checkpoint {path} seen by this worker (sha256 {found}...) is not the run's "
                               f"({digest}...); workers must see the run's files at the same paths")
        _WORKER_SMLM.clear()
        _WORKER_SMLM[checkpoint] = load_smlm(path)
    return _WORKER_SMLM[checkpoint]
