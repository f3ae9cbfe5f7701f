"""evaluate-smlm's run over what generate-smlm wrote.

- :func:`evaluate_and_log`: scores what generation wrote (no model run): DTW metrics through the one motion
  scorer, BLEU-4 / ROUGE-L of the SMLM's own translations, and (``smlm_generate.backtranslate``) the
  generated motion of every sentence clip through the frozen back-translation judge (``bt/slt/...``, SL-T
  definition: M3T Tab. 2); ``<metrics>/smlm/metrics.json``, ``per_clip.csv``, ``backtranslation.csv``; the
  MLflow run is tagged with the training variant so ``m3t smlm-table`` / ``m3t bt-table`` print Tab. 1 / 2.
  Every clip of the split is scored: one over the model's text / motion limits is cut to them and kept
  (``clips_cut``), an empty generation is scored as the rest pose (``empty_rate``) and back-translates to the
  empty sentence; only clips the vocabulary cannot take at all are left out (``clips_unscorable``).
  Memory does not grow with the split: generations are decoded for a run of clips within the scorer's frame
  budget, or a block of the judge's batches, and dropped after it. A killed evaluation resumes: scored clips and
  judged sentences are journaled beside the metrics as they are made (:mod:`m3t.journal`, removed once the
  outputs are written), and the rerun writes what an uninterrupted run writes. With ``fit_corpus.executor:
  dask`` the DTW scoring (posing and the kernels, the evaluation's heavy part) runs on fit-corpus's Dask cluster.
"""
from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from m3t.atomic import write_json, write_text
from m3t.backtranslation.config import BackTranslationConfig
from m3t.backtranslation.data import skip_reason
from m3t.backtranslation.pipeline import (
    BackTranslationReport,
    backtranslate,
    per_clip_csv,
)
from m3t.body.factory import BodyConfig, load_body_model
from m3t.body.protocol import BodyModel
from m3t.digest import file_digest, json_digest
from m3t.experiment import ExperimentConfig, start_run
from m3t.fitting.cluster import stage_executor
from m3t.fitting.config import FitCorpusConfig
from m3t.journal import Journal
from m3t.metrics.text import SLT_DEFINITION
from m3t.reporting import frame_csv
from m3t.shards.folders import DataConfig
from m3t.shards.schema import FittedClip
from m3t.shards.tokens import (
    read_token_shard,
)
from m3t.smlm.config import GenerateConfig
from m3t.smlm.evaluate import EvaluationReport, SMLMEvaluator
from m3t.smlm.generate import GeneratedMotion
from m3t.smlm.generate_run import evaluator_for
from m3t.smlm.pipeline import variant_name

JOURNAL_NAME = ".evaluate-smlm.journal"  # beside the metrics while a run is in progress (m3t.journal)
JOURNAL_VERSION = "evaluate-smlm-journal-v1"  # bump when what a journaled row holds changes


def run_evaluate(cfg: GenerateConfig, data: DataConfig, body: BodyModel,
                 judge: BackTranslationConfig | None = None, cluster: FitCorpusConfig | None = None,
                 body_cfg: BodyConfig | None = None) -> tuple[EvaluationReport, dict]:
    """``judge``: the back-translation decoding settings (beam, length penalty; defaults when None). ``cluster``
    (params ``fit_corpus``) with ``executor: dask``: the DTW scoring runs on that cluster, whose workers build the
    body model of ``body_cfg``; the outputs are the same."""
    setup = evaluator_for(cfg, data, body)
    setup.evaluator.body_config = body_cfg
    loaded, evaluator = setup.loaded, setup.evaluator
    out = data.generated
    shard_path, text_path = out / "generated.parquet", out / "translations.jsonl"
    for path in (shard_path, text_path):
        if not path.exists():
            raise FileNotFoundError(f"{path} not found; run the generate-smlm stage first (dvc repro generate-smlm)")
    # generate-smlm decodes up to max_motion_tokens steps: a clip that ended earlier emitted EOS
    limit = loaded.model.cfg.max_motion_tokens
    generated = {c.clip.id: GeneratedMotion(dict(c.tokens), stopped=c.num_tokens < limit)
                 for c in read_token_shard(shard_path).clips}
    translations = {}
    for line_no, line in enumerate(text_path.read_text().splitlines(), 1):
        try:
            row = json.loads(line)
            translations[row["clip_id"]] = row["hypothesis"]
        except (json.JSONDecodeError, KeyError) as exc:
            raise ValueError(f"{text_path}, line {line_no}: not a translation record ({exc}); rerun generate-smlm") from exc
    metrics_dir = data.metrics("smlm")
    judge = judge or BackTranslationConfig()
    journal = Journal(metrics_dir / JOURNAL_NAME, evaluation_key(cfg, data, judge, [shard_path, text_path]))
    with stage_executor(cluster) as executor:
        report = evaluator.score(generated, translations, journal, executor)
    # every clip of the split is scored: clips over the model's limits were cut and kept; only clips the
    # vocabulary cannot take at all (a language without prompts, no text) are left out, and counted here
    report.summary.update({"clips_scored": float(len(evaluator.examples)), "clips_cut": float(len(setup.cut)),
                           "clips_unscorable": float(len(setup.skipped))})
    if cfg.backtranslate:
        judged = backtranslate_generated(evaluator, generated, data, body, judge, journal)
        report.summary["bt/clips"] = float(0 if judged is None else len(judged.per_clip))
        if judged is not None:  # None: the split has no sentence clip (isolated signs only)
            report.summary.update({f"bt/{k}": v for k, v in judged.summary.items()})
            write_text(metrics_dir / "backtranslation.csv", per_clip_csv(judged.per_clip))
    write_json(metrics_dir / "metrics.json", report.summary)
    write_text(metrics_dir / "per_clip.csv", frame_csv(report.per_clip))
    journal.finish()
    return report, loaded.train_config


def evaluation_key(cfg: GenerateConfig, data: DataConfig, judge: BackTranslationConfig, inputs: list[Path]) -> str:
    """What an evaluation's per-clip results depend on (its journal's key): the generation's files, the
    checkpoint, the reference shards, the tokenizers, the judges and the settings that score."""
    files = [*inputs, data.smlm_dir / "smlm.pt", *(folder / f"{cfg.split}.parquet" for folder in data.shards_dirs),
             *sorted(data.tokenizers_dir.glob("*.pt")), *sorted(data.backtranslation_dir.glob("*"))]
    return json_digest([JOURNAL_VERSION, cfg.split, cfg.motion_metric, cfg.backtranslate, judge.beam_size,
                        judge.length_penalty, [(p.name, file_digest(p)) for p in files if p.is_file()]], length=16)


def backtranslate_generated(evaluator: SMLMEvaluator, generated: dict[str, GeneratedMotion], data: DataConfig,
                            body: BodyModel, judge: BackTranslationConfig,
                            journal: Journal | None = None) -> BackTranslationReport | None:
    """The generated motion of every sentence clip (decoded by the frozen tokenizers) through the frozen
    back-translation judge of its language (definition "slt"); an empty generation is the empty sentence.
    Isolated signs are left to the recognition probe; None when the split has no sentence clip."""
    return backtranslate_motion([evaluator.references[e.clip_id] for e in evaluator.examples],
                                lambda cid: evaluator.motion_params(generated[cid])
                                if len(generated[cid].tokens["body"]) else {}, data, body, judge, journal)


def backtranslate_motion(references: Sequence[FittedClip], motion_of: Callable[[str], dict[str, np.ndarray]],
                         data: DataConfig, body: BodyModel, judge: BackTranslationConfig,
                         journal: Journal | None = None) -> BackTranslationReport | None:
    """Any system's parameters of every sentence clip of ``references`` (``motion_of(clip id)``; ``{}``: no motion,
    the empty sentence) through the frozen judge of its language, as :func:`backtranslate_generated`. A clip's
    motion is made when the judge reaches it, not all at once."""
    empty = {name: np.zeros((0, dim), np.float32) for name, dim in body.layout.dims.items()}
    clips, texts = {}, {}
    for ref in references:
        if skip_reason(ref.clip, ref.num_frames) is not None:
            continue
        clips[ref.clip.id] = (ref.clip.language, lambda cid=ref.clip.id: motion_of(cid) or empty)
        texts[ref.clip.id] = ref.clip.text
    if not clips:
        return None
    return backtranslate(data.backtranslation_dir, clips, texts, judge.beam_size, judge.length_penalty,
                         journal=journal)


def evaluate_and_log(cfg: GenerateConfig, data: DataConfig, body_cfg: BodyConfig, experiment: ExperimentConfig,
                     judge: BackTranslationConfig | None = None, cluster: FitCorpusConfig | None = None) -> dict[str, float]:
    report, train_config = run_evaluate(cfg, data, load_body_model(body_cfg), judge, cluster, body_cfg)
    tags = {"split": cfg.split, "translation_objective": str(train_config.get("translation_objective", True)),
            "translation_steps": str(train_config.get("translation_steps", "shared")), "body_model": body_cfg.model, "seed": str(train_config.get("seed", ""))}
    if cfg.backtranslate:
        tags["text_metric_definition"] = SLT_DEFINITION
    with start_run(experiment, "evaluate-smlm", tags=tags, variant=variant_name(train_config)) as run:
        run.log_params({f"smlm_train.{k}": v for k, v in train_config.items()})
        run.log_metrics({k: v for k, v in report.summary.items() if v == v and abs(v) != float("inf")})
        for name in ("metrics.json", "per_clip.csv", "backtranslation.csv"):
            if (data.metrics("smlm") / name).exists():
                run.log_artifact(data.metrics("smlm") / name)
        for video in sorted((data.generated / "renders").glob("*.mp4")):
            run.log_artifact(video, "renders")
    return report.summary
