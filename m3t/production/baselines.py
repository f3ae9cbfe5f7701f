"""evaluate-baselines: the copy baselines of the field produced for the evaluation clips and scored **exactly like
the models**, so every production table has them as rows.

Systems (params.yaml ``baselines.systems``):

- ``retrieval`` (:mod:`m3t.production.retrieval`): each clip gets the motion of the training clip whose text is
  nearest its text (exact match first, then sentence chrF), unchanged; the training clips are the production
  models' own (``data.production_skip_kinds`` applies);
- ``lexicon`` (:mod:`m3t.production.lexicon`): one stored sign per gloss from the training split's isolated
  signs, concatenated with interpolated transitions; its input is the corpus's gloss annotation
  (``baselines.lexicon_input: gloss``, an oracle text-to-gloss step) or the text's words.

Two scorings, each the models' own:

- **body-model path** (M3T Tab. 1-2): the clips of ``smlm_generate.split`` with text and frames (those
  evaluate-smlm scores whenever the SMLM's vocabulary has a prompt for every language; its ``clips_unscorable``
  says when not), through the SMLM evaluation's scoring (:func:`m3t.smlm.evaluate.score_against`: DTW-JPE /
  DTW-PA-JPE per region and ``<corpus>/<language>`` group, face DTW-VPE, ``smlm_generate.motion_metric``) and the
  same frozen back-translation judge (``bt/slt/...``);
- **skeleton path** (SGSA Tab. 1-3 and the cross-paper table): the samples evaluate-sgsa scores on
  ``sgsa_evaluate.splits`` (clips with text and frames) on train-sgsa's skeleton graph, posed with each reference
  signer's identity as the SMLM's motion is (:func:`m3t.sgsa.pipeline.score_posed`), and back-translated by the
  skeleton judge.

No trained production model is read: the baselines depend on the data and the judges alone, so retraining a model
never reruns them, and one run serves every seed of the claims study.

A clip a baseline cannot serve (no training text in its language, no lexicon entry for any of its glosses) gets no
motion: scored as the rest pose (as an empty generation is) and counted (``no_motion_rate``); glosses / words
without a lexicon entry are counted (``missing_rate``: their share of all looked up) and listed per clip.

Writes ``<metrics>/baselines/``: ``metrics.json`` (``<system>/<metric>`` on the body-model path, with
evaluate-smlm's metric names; ``<system>/skeleton/<split>/<metric>`` on the skeleton path, with evaluate-sgsa's),
``per_clip.csv``, ``produced.csv`` (what each clip got: retrieved clip, match, chrF, lexicon entries used,
missing words), ``backtranslation.csv``; and each system's motion for the body-model clips as a parameter shard
``<generated_dir>/baselines/<corpora>/<system>.parquet``, so ``m3t score`` reproduces the body-model figures from
the files (a clip without motion is not in the shard, which holds no empty clip: ``m3t score`` lists it as
unpaired, the stage scores it as the rest pose).
Each system is one MLflow run of stage ``evaluate-baselines`` (tag ``variant`` = the system), with the body-model
metrics under evaluate-smlm's names and the skeleton ones under evaluate-sgsa's (``<system>/<split>/...``): the
paper tables read them beside the models.

Axis legend: T frames, D_m a modality's width.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from m3t.atomic import write_json, write_text
from m3t.backtranslation.config import BackTranslationConfig
from m3t.body.protocol import BodyModel
from m3t.production.config import BaselinesConfig
from m3t.production.lexicon import Lexicon
from m3t.production.retrieval import RetrievalIndex
from m3t.reporting import csv_text, frame_csv
from m3t.shards.folders import DataConfig
from m3t.shards.schema import FittedClip

if TYPE_CHECKING:
    from m3t.body.config import BodyConfig
    from m3t.experiment import ExperimentConfig
    from m3t.sgsa.config import SGSAConfig, SGSAEvaluateConfig
    from m3t.smlm.config import GenerateConfig

STAGE = "evaluate-baselines"


@dataclass
class BaselineMotion:
    """One baseline's motion per clip (``{}``: no motion) and what it did for each clip (``produced.csv`` rows)."""

    system: str
    motion: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    rows: list[dict] = field(default_factory=list)

    def statistics(self) -> dict[str, float]:
        """``no_motion_rate``, ``mean_frames``; retrieval: ``exact_rate``, ``mean_chrf``; lexicon: ``missing_rate``."""
        n = max(len(self.rows), 1)
        out = {"no_motion_rate": sum(r["frames"] == 0 for r in self.rows) / n,
               "mean_frames": float(np.mean([r["frames"] for r in self.rows])) if self.rows else 0.0}
        if self.system == "retrieval":
            out["exact_rate"] = sum(r.get("match") == "exact" for r in self.rows) / n
            out["mean_chrf"] = float(np.mean([r.get("chrf", 0.0) for r in self.rows])) if self.rows else 0.0
        else:
            looked_up = sum(r.get("looked_up", 0) for r in self.rows)
            out["missing_rate"] = sum(r.get("missing", 0) for r in self.rows) / max(looked_up, 1)
        return out


def produce_baselines(clips: Sequence[FittedClip], train: Sequence[FittedClip], lexicon_clips: Sequence[FittedClip],
                      cfg: BaselinesConfig) -> dict[str, BaselineMotion]:
    """Every system of ``cfg`` for every clip: retrieval over ``train``, the lexicon over ``lexicon_clips``'s
    isolated signs (see the module doc)."""
    out: dict[str, BaselineMotion] = {}
    if "retrieval" in cfg.systems:
        index, result = RetrievalIndex(train), BaselineMotion("retrieval")
        for c in clips:
            row = {"system": "retrieval", "clip_id": c.clip.id, "language": c.clip.language}
            try:
                found = index.nearest(c.clip.text, c.clip.language)
            except ValueError as exc:  # no training text in the language, or no text
                result.motion[c.clip.id] = {}
                result.rows.append({**row, "frames": 0, "match": "none", "reason": str(exc)})
                continue
            result.motion[c.clip.id] = dict(found.clip.params)
            result.rows.append({**row, "frames": found.clip.num_frames, "match": found.match, "chrf": found.score,
                                "source": found.clip.clip.id, "missing": len(found.missing_words),
                                "missing_words": " ".join(found.missing_words)})
        out["retrieval"] = result
    if "lexicon" in cfg.systems:
        lexicon, result = Lexicon(lexicon_clips), BaselineMotion("lexicon")
        for c in clips:
            made = lexicon.lookup(c.clip.text, c.clip.gloss, c.clip.language, cfg.lexicon_input,
                                  cfg.transition_frames)
            result.motion[c.clip.id] = made.params
            result.rows.append({"system": "lexicon", "clip_id": c.clip.id, "language": c.clip.language,
                                "frames": made.frames, "input": made.input, "looked_up": made.tokens,
                                "missing": len(made.missing), "missing_words": " ".join(made.missing),
                                "source": " ".join(cid for _, cid in made.used)})
        out["lexicon"] = result
    return out


@dataclass
class BaselineReport:
    summary: dict[str, float]  # metrics.json
    runs: dict[str, dict[str, float]]  # system -> the MLflow run's metrics (the models' key names)
    per_clip: list[dict] = field(default_factory=list)
    produced: list[dict] = field(default_factory=list)
    backtranslation: list[dict] = field(default_factory=list)

    def add(self, system: str, run: dict[str, float], summary: dict[str, float]) -> None:
        self.runs.setdefault(system, {}).update(run)
        self.summary.update(summary)


def motion_dir(data: DataConfig) -> Path:
    """Where the baselines' motion shards go: ``<generated_dir>/baselines/<corpora joined by '+'>``."""
    return Path(data.generated_dir) / "baselines" / data.generated.name


def _body_model_path(cfg: BaselinesConfig, generate: GenerateConfig, data: DataConfig, body: BodyModel,
                     judge: BackTranslationConfig, report: BaselineReport, train: list, lexicon_clips: list) -> None:
    from m3t.metrics.motion import MotionMetricsConfig
    from m3t.metrics.scorer import MotionScorer
    from m3t.shards.io import read_production_split, write_shard
    from m3t.smlm.evaluate import motion_summary, score_against
    from m3t.smlm.evaluate_run import backtranslate_motion

    clips = [c for c in read_production_split(data, generate.split) if c.clip.text.strip() and c.num_frames > 0]
    scorer = MotionScorer(body, MotionMetricsConfig(mode=generate.motion_metric))
    for ref in clips:  # posed once for every system while they fit the scorer's frame budget (then when scored)
        scorer.reference(ref.clip.id, ref.params, ref.identity)
    for system, made in produce_baselines(clips, train, lexicon_clips, cfg).items():
        scores = score_against(scorer, clips, made.motion)
        metrics = {**scores.overall, "empty_rate": scores.empty_rate, **motion_summary(scores),
                   "clips_scored": float(len(clips)), **made.statistics()}
        if generate.backtranslate:
            judged = backtranslate_motion(clips, lambda cid, m=made: m.motion[cid], data, body, judge)
            metrics["bt/clips"] = float(0 if judged is None else len(judged.per_clip))
            if judged is not None:
                metrics.update({f"bt/{k}": v for k, v in judged.summary.items()})
                report.backtranslation += [{"system": system, "path": "body_model", "split": generate.split, **r}
                                           for r in judged.per_clip]
        report.add(system, metrics, {f"{system}/{k}": v for k, v in metrics.items()})
        report.per_clip += [{"system": system, "path": "body_model", "split": generate.split, "clip_id": c.clip_id,
                             "group": c.group, **c.metrics} for c in scores.per_clip]
        report.produced += [{"path": "body_model", "split": generate.split, **r} for r in made.rows]
        # a shard holds no empty clip: a clip without motion is left out (m3t score lists it as unpaired)
        stored = [replace(ref, key=f"{system}:{ref.key}", params=made.motion[ref.clip.id], metrics={})
                  for ref in clips if made.motion[ref.clip.id]]
        motion_dir(data).mkdir(parents=True, exist_ok=True)
        write_shard(motion_dir(data) / f"{system}.parquet", stored, body.layout)


def _skeleton_path(cfg: BaselinesConfig, sgsa_cfg: SGSAConfig, splits: Sequence[str], data: DataConfig,
                   body: BodyModel, judge: BackTranslationConfig | None, report: BaselineReport, train: list,
                   lexicon_clips: list, progress: bool) -> None:
    from m3t.body.skeleton import graph_for
    from m3t.sgsa.data import make_samples, vocabularies
    from m3t.sgsa.pipeline import score_posed
    from m3t.shards.io import read_production_split
    from m3t.shards.skeletons import skeleton_clips

    graph = graph_for(sgsa_cfg.skeleton, sgsa_cfg.face_points)  # train-sgsa's graph
    rest = {k: v.detach().cpu().numpy() for k, v in body.rest_params(1).items()}
    for split in splits:
        clips = skeleton_clips(body, read_production_split(data, split), graph, progress, f"skeletons: {split}")
        # evaluate-sgsa's samples (a clip is left out for no text or no frames, whatever the vocabulary); the
        # baselines read no text ids, so the split's own vocabulary serves
        text_vocab, gloss_vocab = vocabularies(clips, sgsa_cfg)
        samples = make_samples(clips, text_vocab, gloss_vocab, sgsa_cfg, training=False).samples
        for system, made in produce_baselines([s.clip.fitted for s in samples], train, lexicon_clips, cfg).items():
            motion = {cid: params or rest for cid, params in made.motion.items()}  # no motion: the rest pose
            posed = score_posed(system, split, motion, samples, graph, body, data.skeleton_judge_dir, judge)
            report.add(system, posed.summary,
                       {f"{system}/skeleton/{k.split('/', 1)[1]}": v for k, v in posed.summary.items()})
            report.per_clip += [{**r, "path": "skeleton"} for r in posed.per_clip]
            report.backtranslation += [{**r, "path": "skeleton"} for r in posed.backtranslation]
            report.produced += [{"path": "skeleton", "split": split, **r} for r in made.rows]


def run_evaluate(cfg: BaselinesConfig, data: DataConfig, body: BodyModel, generate: GenerateConfig,
                 sgsa_cfg: SGSAConfig, sgsa_evaluate: SGSAEvaluateConfig, judge: BackTranslationConfig | None = None,
                 progress: bool = True) -> BaselineReport:
    """Produce and score every baseline on both paths (module doc); write ``<metrics>/baselines``."""
    from m3t.backtranslation.pipeline import PER_CLIP_COLUMNS
    from m3t.shards.io import read_production_split, read_split

    judge = judge or BackTranslationConfig()
    report = BaselineReport({}, {})
    train = read_production_split(data, "train")
    lexicon_clips = read_split(data.shards_dirs, "train")
    _body_model_path(cfg, generate, data, body, judge, report, train, lexicon_clips)
    _skeleton_path(cfg, sgsa_cfg, sgsa_evaluate.splits, data, body, judge if sgsa_evaluate.backtranslate else None,
                   report, train, lexicon_clips, progress)
    out = data.metrics("baselines")
    write_json(out / "metrics.json", report.summary)
    write_text(out / "per_clip.csv", frame_csv(report.per_clip))
    write_text(out / "produced.csv", frame_csv(report.produced))
    write_text(out / "backtranslation.csv", csv_text(report.backtranslation,
                                                     ("system", "path", "split", *PER_CLIP_COLUMNS)))
    return report


def evaluate_and_log(cfg: BaselinesConfig, data: DataConfig, body_cfg: BodyConfig, generate: GenerateConfig,
                     sgsa_cfg: SGSAConfig, sgsa_evaluate: SGSAEvaluateConfig, experiment: ExperimentConfig,
                     judge: BackTranslationConfig | None = None) -> dict[str, float]:
    """:func:`run_evaluate`, then one MLflow run per system (tag ``variant`` = the system)."""
    from m3t.body.factory import load_body_model
    from m3t.experiment import section_params, start_run
    from m3t.metrics.text import SLT_DEFINITION

    report = run_evaluate(cfg, data, load_body_model(body_cfg), generate, sgsa_cfg, sgsa_evaluate, judge)
    out = data.metrics("baselines")
    for system, metrics in report.runs.items():
        tags = {"baseline": system, "split": generate.split, "body_model": body_cfg.model,
                "text_metric_definition": SLT_DEFINITION,
                **({"lexicon_input": cfg.lexicon_input} if system == "lexicon" else {})}
        with start_run(experiment, STAGE, tags=tags, variant=system) as run:
            run.log_params(section_params(baselines=cfg, data=data))
            run.log_metrics({k: v for k, v in metrics.items() if np.isfinite(v)})
            for name in ("metrics.json", "per_clip.csv", "produced.csv", "backtranslation.csv"):
                run.log_artifact(out / name)
    return report.summary
