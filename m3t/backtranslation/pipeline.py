"""Back-translation behind the train-backtranslation and evaluate-backtranslation stages, and the scorer any
production model's output goes through.

- :func:`run_train_backtranslation` / :func:`train_and_log`: one model per sign language of the train split of
  ``data.train_corpora`` (sentence clips; isolated signs are skipped with their reason), selected on its dev
  split; writes ``<models>/backtranslation/<language>.pt`` (only the finished run's best; best and resumable
  last live in ``backtranslation_train.cache_dir`` under the run key), ``metrics.json`` (numbers),
  ``languages.json`` (per language: checkpoint, input layout, gloss source and pseudo-gloss method, scoring
  unit) and ``skipped.jsonl``. A checkpoint left there by an earlier run for a language this run does not
  train is removed, so the folder holds exactly one run's models.
- With :class:`SkeletonInput` the same trainer makes the **skeleton judge** (stage train-backtranslation-skeleton):
  models reading normalised skeleton coordinates, in ``<models>/backtranslation-skeleton``; it scores the
  skeletal production models (PT, SGSA) and, posed into the same graph, the SMLM and the ground truth.
- :func:`backtranslate`: motion parameters of any clips (ground truth or generated) -> sentences -> SL-T
  metrics per language (definition "slt", :mod:`m3t.metrics.text`). A generation with no frames is scored as
  the empty sentence, never dropped.
- :func:`run_evaluate_backtranslation` / :func:`evaluate_and_log`: the upper bound of M3T Tab. 2 - the
  ground-truth motion of a split (default test) back-translated; ``<metrics>/backtranslation/metrics.json``,
  ``per_clip.csv`` and ``skipped.jsonl``.
"""
from __future__ import annotations

import json
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from m3t.atomic import copy_file, write_json, write_jsonl, write_text
from m3t.backtranslation.checkpoint import SKELETON_STAGE, STAGE, LoadedBackTranslation, load_backtranslation
from m3t.backtranslation.config import BackTranslationConfig, BackTranslationTrainConfig
from m3t.backtranslation.data import InputSpec, LanguageCorpus, language_corpus, skip_reason
from m3t.backtranslation.decode import translate
from m3t.backtranslation.train import run_key, train_backtranslation
from m3t.body.protocol import BodyModel
from m3t.body.skeleton import SkeletonGraph
from m3t.experiment import ExperimentConfig, section_params, start_run
from m3t.journal import Journal
from m3t.metrics.text import SLT_DEFINITION, slt_metrics_by_language, slt_scores, slt_unit
from m3t.reporting import csv_text
from m3t.shards.folders import DataConfig
from m3t.shards.io import production_data_version, read_production_split, shard_layout
from m3t.shards.schema import FittedClip, layout_to_json
from m3t.shards.skeletons import skeleton_clip
from m3t.training_jobs import run_jobs, worker_split

PER_CLIP_COLUMNS = ("clip_id", "language", "frames", "reference", "hypothesis", "bleu1", "bleu2", "bleu3", "bleu4",
                    "rouge_l")


def checkpoint_name(language: str) -> str:
    """The file name of a language's model (characters other than letters, digits, ``_ . -`` become ``_``)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", language) + ".pt"


def _by_language(clips) -> dict[str, list]:
    out: dict[str, list] = {}
    for clip in clips:
        out.setdefault(clip.clip.language, []).append(clip)
    return out


def _selected_languages(cfg: BackTranslationConfig, train) -> list[str]:
    """Languages with sentence clips in the train split (first-seen order), restricted to ``cfg.languages``."""
    found = list(dict.fromkeys(c.clip.language for c in train if c.clip.label is None))
    if not cfg.languages:
        return found
    missing = [lang for lang in cfg.languages if lang not in found]
    if missing:
        raise ValueError(f"backtranslation.languages names {missing}, which have no sentence clip in the train split "
                         f"of {list(cfg.languages)}; found {found}")
    return list(cfg.languages)


def _layout(data: DataConfig):
    layouts = {folder: shard_layout(folder / "train.parquet") for folder in data.shards_dirs}
    if len({layout_to_json(v) for v in layouts.values()}) != 1:
        raise ValueError(f"the corpora {list(data.train_corpora)} were fitted with different body layouts; "
                         "back-translation needs one input layout (refit them with the same body model)")
    return next(iter(layouts.values()))


# ------------------------------------------------------------------------------------------------ train
@dataclass(frozen=True)
class SkeletonInput:
    """A judge that reads skeletons: every clip posed into ``graph`` by ``body`` and normalised
    (:mod:`m3t.shards.skeletons`), trained into ``DataConfig.skeleton_judge_dir``."""

    body: BodyModel
    graph: SkeletonGraph

    def view(self, clips: list[FittedClip]) -> list[FittedClip]:
        """Clips with their skeleton coordinates as the one stream; clips without frames stay (skipped later)."""
        return [skeleton_clip(self.body, c, self.graph).as_fitted() if c.num_frames else c for c in clips]


def _train_language(model_cfg: BackTranslationConfig, train_cfg: BackTranslationTrainConfig, spec: InputSpec,
                    version: str, out: Path, progress: bool, corpus: LanguageCorpus,
                    on_epoch: Callable[[dict[str, float], int], None] | None) -> tuple[dict[str, float], dict]:
    """Train one language's model into ``out`` (here or in a worker process); its numbers for metrics.json and
    its entry of languages.json."""
    language = corpus.language
    key = run_key(model_cfg, train_cfg, corpus, spec, version)
    cache = Path(train_cfg.cache_dir)
    best, last = cache / f"{key}.best.pt", cache / f"{key}.last.pt"
    result = train_backtranslation(model_cfg, train_cfg, corpus, spec, version, best, last, progress=progress,
                                   on_epoch=on_epoch)
    copy_file(best, out / checkpoint_name(language))
    numbers = {
        f"{language}/train_clips": float(len(corpus.train)), f"{language}/dev_clips": float(len(corpus.dev)),
        f"{language}/skipped_clips": float(len(corpus.skipped)),
        f"{language}/truncated_clips": float(corpus.truncated),
        f"{language}/text_vocabulary_size": float(len(corpus.text_vocab)),
        f"{language}/gloss_vocabulary_size": float(len(corpus.gloss_vocab or ())),
        f"{language}/best_epoch": float(result.best.get("epoch", 0)),
        **{f"{language}/best_{k}": float(v) for k, v in result.best.items() if k.startswith(("val_", "train_"))}}
    described = {"checkpoint": checkpoint_name(language), "input": spec.describe(),
                 "text_rule": corpus.processor.rule, "gloss_source": corpus.gloss_source,
                 "scoring": f"{SLT_DEFINITION}, per {slt_unit(language)}", "selected_on_dev": bool(corpus.dev)}
    return numbers, described


def run_train_backtranslation(model_cfg: BackTranslationConfig, train_cfg: BackTranslationTrainConfig,
                              data: DataConfig, on_epoch=None, progress: bool = True,
                              skeleton: SkeletonInput | None = None) -> dict[str, float]:
    """Train every language's model; ``on_epoch(language, record, epoch)`` sees each epoch's record. Returns
    the numbers written to ``metrics.json`` (``<language>/<name>``). With ``skeleton`` the models read skeletons
    (``backtranslation.input_layout`` is ignored) and go to ``data.skeleton_judge_dir``."""
    train = read_production_split(data, "train")
    dev = read_production_split(data, "dev")
    if not train:
        raise ValueError(f"the train split of {list(data.train_corpora)} has no clip")
    if skeleton is not None:
        spec, out = InputSpec.for_skeleton(skeleton.graph), data.skeleton_judge_dir
        train, dev = skeleton.view(train), skeleton.view(dev)
    else:
        spec, out = InputSpec.from_layout(model_cfg.input_layout, _layout(data), train[0].body_model), \
            data.backtranslation_dir
    languages = _selected_languages(model_cfg, train)
    if not languages:
        raise ValueError(f"the train split of {list(data.train_corpora)} has no sentence clip (only isolated signs); "
                         "back-translation needs sentences")
    version = production_data_version(data)
    train_by, dev_by = _by_language(train), _by_language(dev)
    skipped = [{"clip_id": c.clip.id, "split": c.clip.split, "language": c.clip.language,
                "reason": skip_reason(c.clip, c.num_frames) or "language not in backtranslation.languages"}
               for c in train + dev if c.clip.language not in languages]
    report: dict[str, float] = {}
    described: dict[str, dict] = {}
    corpora = [language_corpus(language, train_by[language], dev_by.get(language, []), spec, model_cfg)
               for language in languages]
    processes, threads = worker_split(train_cfg.workers, len(corpora), train_cfg.device)
    run = partial(_train_language, model_cfg, train_cfg, spec, version, out, progress)
    results = run_jobs(run, corpora, languages, processes, threads, on_epoch, "language",
                       "backtranslation_train.workers")
    for corpus, (numbers, description) in zip(corpora, results):
        skipped.extend(corpus.skipped)
        report.update(numbers)
        described[corpus.language] = description
    for stale in out.glob("*.pt"):
        if stale.name not in {checkpoint_name(lang) for lang in languages}:
            stale.unlink()
    write_json(out / "metrics.json", report)
    write_json(out / "languages.json", described)
    write_jsonl(out / "skipped.jsonl", skipped)
    return report


def train_and_log(model_cfg: BackTranslationConfig, train_cfg: BackTranslationTrainConfig, data: DataConfig,
                  experiment: ExperimentConfig, progress: bool = True,
                  skeleton: SkeletonInput | None = None) -> dict[str, float]:
    """:func:`run_train_backtranslation` inside an MLflow run (params, per-epoch records, the written files)."""
    layout = model_cfg.input_layout if skeleton is None else f"skeleton ({skeleton.graph.name})"
    stage = STAGE if skeleton is None else SKELETON_STAGE
    tags = {"input_layout": layout, "corpus": ",".join(data.train_corpora), "seed": str(train_cfg.seed)}
    with start_run(experiment, stage, tags=tags, variant=layout) as run:
        run.log_params(section_params(backtranslation=model_cfg, backtranslation_train=train_cfg, data=data))
        report = run_train_backtranslation(
            model_cfg, train_cfg, data, progress=progress, skeleton=skeleton,
            on_epoch=lambda language, record, epoch: run.log_metrics(
                {f"{language}/{k}": v for k, v in record.items()}, step=epoch))
        run.log_metrics(report)
        out = data.backtranslation_dir if skeleton is None else data.skeleton_judge_dir
        described = json.loads((out / "languages.json").read_text())
        run.set_tags({f"gloss_source/{lang}": d["gloss_source"] for lang, d in described.items()})
        for name in ("metrics.json", "languages.json", "skipped.jsonl"):
            run.log_artifact(out / name)
    return report


# ------------------------------------------------------------------------------------------- evaluation
@dataclass
class BackTranslationReport:
    hypotheses: dict[str, str]  # clip id -> back-translated sentence ("" for an empty generation)
    per_clip: list[dict]  # PER_CLIP_COLUMNS; sentence-level scores in the language's primary unit
    summary: dict[str, float]  # slt/<language>/<metric>, .../sentences, .../empty_generations, slt_bleu4, ...


def load_models(models_dir: str | Path, device: str = "cpu") -> dict[str, LoadedBackTranslation]:
    """Every ``*.pt`` of ``models_dir`` by the language stored in it."""
    folder = Path(models_dir)
    files = sorted(folder.glob("*.pt")) if folder.is_dir() else []
    if not files:
        raise FileNotFoundError(f"no back-translation checkpoint in {folder}; run `dvc repro {STAGE}` "
                                "(python -m m3t.stages.train_backtranslation) first")
    models = {}
    for path in files:
        loaded = load_backtranslation(path, device)
        models[loaded.language] = loaded
    return models


ClipParams = Mapping[str, np.ndarray] | Callable[[], Mapping[str, np.ndarray]]
"""A clip's {modality: (T, D) parameters}, or what makes them when they are needed (decoded generations)."""
JOURNAL_SECTION = "backtranslation"  # the sentences of a resumable evaluation (m3t.journal)
BLOCK_BATCHES = 8  # decoding batches whose inputs are made at once: memory stays flat in the number of clips


def backtranslate(models_dir: str | Path, clips_params: Mapping[str, tuple[str, ClipParams]],
                  references: Mapping[str, str], beam_size: int = 1, length_penalty: float = 1.0,
                  device: str = "cpu", batch_size: int = 16, progress: bool = False,
                  journal: Journal | None = None) -> BackTranslationReport:
    """Back-translate ``clips_params`` (clip id -> (sign language, {modality: (T, D) parameters} or a callable
    giving them)) with the language's model of ``models_dir`` and score them against ``references`` (clip id ->
    spoken sentence), tokenised by the model's text rule, under definition "slt". T = 0 is the empty sentence
    (scored 0). Inputs are made for ``BLOCK_BATCHES`` decoding batches at a time, cut where the decoder's own
    batches end, so the sentences are those of one call over every clip. With a ``journal`` (:mod:`m3t.journal`)
    each block's sentences are added to it once made, and the blocks it holds are not made again: they are whole
    blocks from a language's first clip on, so the blocks left start where the decoder's batches would."""
    missing = [cid for cid in clips_params if cid not in references]
    if missing:
        raise ValueError(f"no reference sentence for clips {missing[:5]}{' ...' if len(missing) > 5 else ''}")
    models = load_models(models_dir, device)
    for cid, (language, _) in clips_params.items():
        if language not in models:
            raise ValueError(f"clip {cid!r}: no back-translation model for language {language!r} in {models_dir} "
                             f"(models: {sorted(models)}); train one with `dvc repro {STAGE}` on a corpus of that "
                             "language")
        if not references[cid].strip():
            raise ValueError(f"clip {cid!r}: empty reference sentence; nothing to score against")
    from tqdm.auto import tqdm

    ids = list(clips_params)
    hypotheses, refs, frames = {}, {}, {}
    for language, loaded in tqdm(models.items(), desc="back-translate", unit="language", disable=not progress):
        rows = [cid for cid in ids if clips_params[cid][0] == language]
        if not rows:
            continue
        done = journal.done(JOURNAL_SECTION) if journal is not None else {}
        for cid in rows:
            if cid in done:
                hypotheses[cid], frames[cid] = done[cid]["hypothesis"], done[cid]["frames"]
                refs[cid] = loaded.processor.reference(references[cid])
        rows = [cid for cid in rows if cid not in done]
        block: list[tuple[str, np.ndarray]] = []
        for k, cid in enumerate(rows):
            params = clips_params[cid][1]
            block.append((cid, loaded.spec.features(params() if callable(params) else params, cid)))
            if k + 1 < len(rows) and sum(len(x) > 0 for _, x in block) < BLOCK_BATCHES * batch_size:
                continue
            sentences = translate(loaded.model, loaded.text_vocab, loaded.processor, [x for _, x in block],
                                  beam_size, length_penalty, batch_size)
            for (cid_, x), sentence in zip(block, sentences):
                hypotheses[cid_], refs[cid_], frames[cid_] = sentence, loaded.processor.reference(references[cid_]), len(x)
            if journal is not None:
                journal.add(JOURNAL_SECTION, [{"clip_id": c, "hypothesis": hypotheses[c], "frames": frames[c]}
                                              for c, _ in block])
            block = []
    languages = [clips_params[cid][0] for cid in ids]
    summary = slt_metrics_by_language([hypotheses[c] for c in ids], [refs[c] for c in ids], languages)
    per_clip = []
    for cid, language in zip(ids, languages):
        scores = slt_scores([hypotheses[cid]], [refs[cid]], slt_unit(language)).as_dict()
        per_clip.append({"clip_id": cid, "language": language, "frames": frames[cid], "reference": refs[cid],
                         "hypothesis": hypotheses[cid], **scores})
    for language in dict.fromkeys(languages):
        summary[f"{SLT_DEFINITION}/{language}/empty_generations"] = float(
            sum(frames[c] == 0 for c, lang in zip(ids, languages) if lang == language))
    return BackTranslationReport(hypotheses, per_clip, summary)


def per_clip_csv(rows: list[dict]) -> str:
    return csv_text(rows, PER_CLIP_COLUMNS)


def run_evaluate_backtranslation(model_cfg: BackTranslationConfig, data: DataConfig, split: str = "test",
                                 device: str = "cpu") -> BackTranslationReport:
    """The ground-truth upper bound (M3T Tab. 2, "GT 3DMM"): the fitted motion of ``split`` back-translated.
    Isolated signs, clips with empty text and languages outside ``backtranslation.languages`` are skipped with
    their reason; every other clip is scored."""
    clips = read_production_split(data, split)
    chosen, skipped = {}, []
    for c in clips:
        reason = skip_reason(c.clip, c.num_frames)
        if reason is None and model_cfg.languages and c.clip.language not in model_cfg.languages:
            reason = "language not in backtranslation.languages"
        if reason is None:
            chosen[c.clip.id] = c
        else:
            skipped.append({"clip_id": c.clip.id, "split": split, "language": c.clip.language, "reason": reason})
    if not chosen:
        raise ValueError(f"the {split} split of {list(data.train_corpora)} has no sentence clip to back-translate "
                         f"({len(skipped)} skipped)")
    report = backtranslate(data.backtranslation_dir, {cid: (c.clip.language, c.params) for cid, c in chosen.items()},
                           {cid: c.clip.text for cid, c in chosen.items()}, model_cfg.beam_size,
                           model_cfg.length_penalty, device)
    out = data.metrics("backtranslation")
    write_json(out / "metrics.json", {**report.summary, "skipped_clips": float(len(skipped))})
    write_text(out / "per_clip.csv", per_clip_csv(report.per_clip))
    write_jsonl(out / "skipped.jsonl", skipped)
    return report


def evaluate_and_log(model_cfg: BackTranslationConfig, data: DataConfig, experiment: ExperimentConfig,
                     split: str = "test") -> dict[str, float]:
    """:func:`run_evaluate_backtranslation` inside an MLflow run tagged with the source, split and definition."""
    report = run_evaluate_backtranslation(model_cfg, data, split)
    tags = {"source": "ground-truth", "split": split, "text_metric_definition": SLT_DEFINITION,
            "beam_size": str(model_cfg.beam_size)}
    with start_run(experiment, "evaluate-backtranslation", tags=tags, variant=f"ground truth, {split}") as run:
        run.log_params(section_params(backtranslation=model_cfg, data=data))
        run.log_metrics(report.summary)
        for name in ("metrics.json", "per_clip.csv", "skipped.jsonl"):
            run.log_artifact(data.metrics("backtranslation") / name)
    return report.summary
