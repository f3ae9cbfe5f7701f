"""The SMLM runs behind the train-smlm, generate-smlm and evaluate-smlm stages, over the token shards and
fitted shards of ``data.train_corpora`` (trained jointly; checkpoint selected on all their dev splits).

- :func:`train_and_log`: vocabulary (text tokenizer trained on the train-split text, or the local mBART one,
  ``smlm.reduce_text_vocab``: cut to the ids of the train-split text; prompts for every language of the train
  splits; one token per FSQ code), production + translation
  (``smlm_train.translation_objective``), checkpoint with the lowest mean dev DTW-JPE over the dev clips of
  every training corpus (``smlm_train.eval_max_clips``: the first N of them, 0 = all); writes
  ``<models>/smlm/smlm.pt``, ``metrics.json`` and ``skipped.jsonl``.
- :func:`run_generate`: every clip of ``smlm_generate.split``: text -> motion tokens (greedy, KV cache) and
  ground-truth motion tokens -> text; writes ``generated.parquet``, ``translations.jsonl``,
  ``pose/<clip>.pose`` and, for the first ``smlm_generate.render_clips`` clips, ``renders/<clip>.mp4`` (the
  body surface, reference / generated side by side) and ``renders/<clip>_skeleton.mp4`` (their skeletons and
  face points overlaid) into ``data.generated``.
- :func:`evaluate_and_log`: scores what generation wrote (no model run): DTW metrics through the one motion
  scorer, BLEU-4 / ROUGE-L of the SMLM's own translations, and (``smlm_generate.backtranslate``) the
  generated motion of every sentence clip through the frozen back-translation judge (``bt/slt/...``, SL-T
  definition: M3T Tab. 2); ``<metrics>/smlm/metrics.json``, ``per_clip.csv``, ``backtranslation.csv``; the
  MLflow run is tagged with the training variant so ``m3t smlm-table`` / ``m3t bt-table`` print Tab. 1 / 2.
  Every clip of the split is scored: one over the model's text / motion limits is cut to them and kept
  (``clips_cut``), an empty generation is scored as the rest pose (``empty_rate``) and back-translates to the
  empty sentence; only clips the vocabulary cannot take at all are left out (``clips_unscorable``).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from m3t.atomic import copy_file, write_json, write_jsonl, write_text
from m3t.backtranslation.config import BackTranslationConfig
from m3t.backtranslation.data import skip_reason
from m3t.backtranslation.pipeline import BackTranslationReport, backtranslate, per_clip_csv
from m3t.body.factory import BodyConfig, load_body_model
from m3t.body.protocol import BodyModel
from m3t.experiment import ExperimentConfig, section_params, start_run, to_dict
from m3t.metrics.motion import MotionMetricsConfig
from m3t.metrics.text import SLT_DEFINITION
from m3t.reporting import frame_csv
from m3t.runtime import DistributedContext, distributed_context
from m3t.shards.folders import DataConfig
from m3t.shards.io import data_version, read_split
from m3t.shards.schema import FittedClip
from m3t.shards.tokens import (
    TokenClip,
    TokenInfo,
    TokenShard,
    read_token_shard,
    write_token_shard,
)
from m3t.smlm.checkpoint import LoadedSMLM, load_smlm
from m3t.smlm.config import GenerateConfig, SMLMConfig, SMLMTrainConfig
from m3t.smlm.data import Example, examples_from_shard
from m3t.smlm.evaluate import EvaluationReport, SMLMEvaluator
from m3t.smlm.generate import GeneratedMotion
from m3t.smlm.train import run_key, train_smlm
from m3t.smlm.vocab import SignVocabulary, build_vocabulary
from m3t.tokenizers.tokenize import load_tokenizers


# ------------------------------------------------------------------------------------------- data
def load_tokens(data: DataConfig, split: str) -> list[TokenShard]:
    """The token shards of ``split``, one per training corpus, without the clip kinds production leaves out."""
    shards = []
    for folder in data.tokens_dirs:
        path = folder / f"{split}.parquet"
        if not path.exists():
            raise FileNotFoundError(f"token shard {path} not found; run the tokenize stage first (dvc repro tokenize)")
        shard = read_token_shard(path)
        shards.append(replace(shard, clips=tuple(data.for_production(shard.clips))))
    return shards


def references(data: DataConfig, split: str) -> dict[str, FittedClip]:
    """The fitted motion of a split by clip id: the reference of the DTW evaluation."""
    return {c.clip.id: c for c in read_split(data.shards_dirs, split)}


def vocabulary_for(model_cfg: SMLMConfig, train: list[TokenShard]) -> SignVocabulary:
    streams = {tuple(sorted(s.info.streams.items())) for s in train}
    if len(streams) != 1:
        raise ValueError(f"the token shards {[str(s.path) for s in train]} come from different tokenizers "
                         f"({sorted(streams)}); rerun `dvc repro tokenize`")
    clips = [c for s in train for c in s.clips]
    return build_vocabulary([c.clip.text for c in clips], [c.clip.language for c in clips],
                            train[0].info.streams, model_cfg.text_vocab_size, model_cfg.text_model_path,
                            model_cfg.reduce_text_vocab)


def split_examples(shards: list[TokenShard], vocab: SignVocabulary, model_cfg: SMLMConfig,
                   skipped: list[dict], cut: list[dict] | None = None) -> list[Example]:
    """The examples of ``shards``; unusable clips go to ``skipped``; with ``cut`` (evaluation) clips over the
    model's limits are kept, cut to them, and listed there."""
    examples = []
    for shard in shards:
        found, lost = examples_from_shard(shard, vocab, model_cfg.max_text_tokens, model_cfg.max_motion_tokens, cut)
        examples.extend(found)
        skipped.extend(lost)
    return examples


# ------------------------------------------------------------------------------------------ train
def run_train_smlm(model_cfg: SMLMConfig, cfg: SMLMTrainConfig, body: BodyModel, data: DataConfig, on_epoch=None,
                   dist_ctx: DistributedContext | None = None, progress: bool = True) -> dict[str, float]:
    dist_ctx = dist_ctx or DistributedContext()
    shards = {split: load_tokens(data, split) for split in ("train", "dev")}
    vocab = vocabulary_for(model_cfg, shards["train"])
    skipped: list[dict] = []
    train = split_examples(shards["train"], vocab, model_cfg, skipped)
    dev = split_examples(shards["dev"], vocab, model_cfg, skipped)
    evaluator = None
    if dist_ctx.is_main and dev:
        tokenizers, _ = load_tokenizers(data.tokenizers_dir)
        evaluator = SMLMEvaluator(body, tokenizers, vocab, dev, references(data, "dev"),
                                  max_clips=cfg.eval_max_clips, translation=cfg.translation_objective)
    version = data.production_version(data_version([s.path for split in ("train", "dev") for s in shards[split]]))
    out_dir = data.smlm_dir
    # best and last live in the cache under the run key (a killed run continues where it stopped; a finished
    # one is not redone); smlm.pt only ever holds the best of a finished run
    key = run_key(model_cfg, cfg, vocab, version)
    best, last = Path(cfg.cache_dir) / f"{key}.best.pt", Path(cfg.cache_dir) / f"{key}.last.pt"
    result = train_smlm(model_cfg, cfg, vocab, train, evaluator, version, best, on_epoch=on_epoch,
                        dist_ctx=dist_ctx, progress=progress, last_path=last)
    if not dist_ctx.is_main:
        return {}
    copy_file(best, out_dir / "smlm.pt")
    report = {"train_examples": float(len(train)), "dev_examples": float(len(dev)), "skipped": float(len(skipped)),
              "vocabulary_size": float(len(vocab)), "text_vocabulary_size": float(vocab.text_size),
              "best_epoch": float(result.best.get("epoch", 0)),
              **{f"best_{k}": v for k, v in result.best.items() if k.startswith(("val_", "train_"))}}
    write_json(out_dir / "metrics.json", report)
    write_jsonl(out_dir / "skipped.jsonl", skipped)
    return report


def train_and_log(model_cfg: SMLMConfig, cfg: SMLMTrainConfig, body_cfg: BodyConfig, data: DataConfig,
                  experiment: ExperimentConfig, progress: bool = True) -> dict[str, float]:
    dist_ctx = distributed_context(cfg.device)
    body = load_body_model(body_cfg)
    if not dist_ctx.is_main:
        return run_train_smlm(model_cfg, cfg, body, data, dist_ctx=dist_ctx, progress=False)
    tags = {"translation_objective": str(cfg.translation_objective), "translation_steps": cfg.translation_steps,
            "d_model": str(model_cfg.d_model),
            "body_model": body_cfg.model, "corpus": ",".join(data.train_corpora), "seed": str(cfg.seed)}
    with start_run(experiment, "train-smlm", tags=tags, variant=variant_name(to_dict(cfg))) as run:
        run.log_params(section_params(smlm=model_cfg, smlm_train=cfg, data=data))
        report = run_train_smlm(model_cfg, cfg, body, data, dist_ctx=dist_ctx, progress=progress,
                                on_epoch=lambda record, epoch: run.log_metrics(record, step=epoch))
        run.log_metrics(report)
        for name in ("metrics.json", "skipped.jsonl"):
            run.log_artifact(data.smlm_dir / name)
    return report


# --------------------------------------------------------------------------------------- generate
@dataclass
class GenerationSetup:
    loaded: LoadedSMLM  # the checkpoint: model, vocabulary, training settings
    evaluator: SMLMEvaluator  # the split's clips, their references and the frozen tokenizers
    info: TokenInfo  # the tokenizers' streams, codebook sizes and downsampling
    skipped: list[dict]  # clips of the split the vocabulary cannot take (no language prompt, no text), with reasons
    cut: list[dict]  # clips over the model's text / motion limits: kept, cut to them, scored against the whole reference


def evaluator_for(cfg: GenerateConfig, data: DataConfig, body: BodyModel, device: str = "cpu") -> GenerationSetup:
    loaded = load_smlm(data.smlm_dir / "smlm.pt", device)
    tokenizers, info = load_tokenizers(data.tokenizers_dir)
    skipped: list[dict] = []
    cut: list[dict] = []
    examples = split_examples(load_tokens(data, cfg.split), loaded.vocab, loaded.model.cfg, skipped, cut)
    evaluator = SMLMEvaluator(body, tokenizers, loaded.vocab, examples, references(data, cfg.split),
                              batch_size=cfg.batch_size, motion=MotionMetricsConfig(mode=cfg.motion_metric))
    return GenerationSetup(loaded, evaluator, info, skipped, cut)


def run_generate(cfg: GenerateConfig, data: DataConfig, body: BodyModel, progress: bool = True) -> dict[str, float]:
    from tqdm.auto import tqdm

    from m3t.render.mesh import clip_vertices
    from m3t.render.mesh_video import render_mesh_video
    from m3t.render.posefile import export_pose
    from m3t.render.reconstruction import render_reconstruction

    setup = evaluator_for(cfg, data, body)
    loaded, evaluator, info, skipped = setup.loaded, setup.evaluator, setup.info, setup.skipped + setup.cut
    out = data.generated
    out.mkdir(parents=True, exist_ok=True)
    generated = evaluator.generate(loaded.model, progress)
    translations = evaluator.translate(loaded.model, progress)
    clips = []
    for example in evaluator.examples:
        g = generated[example.clip_id]
        steps = len(g.tokens["body"])
        clips.append(TokenClip(evaluator.references[example.clip_id].clip, steps * info.downsample,
                               {s: g.tokens[s] for s in info.streams}))
    write_token_shard(out / "generated.parquet", clips, info)
    write_jsonl(out / "translations.jsonl", ({"clip_id": e.clip_id, "language": e.language, "reference": e.text,
                                             "hypothesis": translations[e.clip_id]} for e in evaluator.examples))
    write_jsonl(out / "skipped.jsonl", skipped)
    rendered = 0
    for example in tqdm(evaluator.examples, desc="generate-smlm: export", disable=not progress):
        g, ref = generated[example.clip_id], evaluator.references[example.clip_id]
        if not g.tokens["body"].size:
            continue
        params = evaluator.motion_params(g)
        if cfg.export_pose:
            export_pose(out / "pose" / f"{example.clip_id}.pose", body, params, ref.identity, ref.clip.fps)
        if rendered < cfg.render_clips:
            title = f"{example.clip_id} ({example.language})"
            render_mesh_video({"reference": clip_vertices(body, ref.params, ref.identity),
                               "generated": clip_vertices(body, params, ref.identity)}, body.faces,
                              out / "renders" / f"{example.clip_id}.mp4", fps=ref.clip.fps or 25.0, title=title,
                              progress=progress)
            render_reconstruction(body, ref, params, out / "renders" / f"{example.clip_id}_skeleton.mp4",
                                  title=title, labels=("fitted", "generated"), progress=progress)
            rendered += 1
    return {"clips": float(len(clips)), "skipped": float(len(skipped)),
            "stopped_rate": float(sum(generated[e.clip_id].stopped for e in evaluator.examples) / max(len(clips), 1))}


def generate(cfg: GenerateConfig, data: DataConfig, body_cfg: BodyConfig, progress: bool = True) -> dict[str, float]:
    return run_generate(cfg, data, load_body_model(body_cfg), progress)


# --------------------------------------------------------------------------------------- evaluate
def variant_name(train_config: dict) -> str:
    """The ablation's row name of a (checkpoint's) train config: production only, or production + translation
    (with "(added steps)" at equal production updates)."""
    objective = bool(train_config.get("translation_objective", True))
    if not objective:
        return "production only"
    added = train_config.get("translation_steps", "shared") == "added"
    return "production + translation" + (" (added steps)" if added else "")


def run_evaluate(cfg: GenerateConfig, data: DataConfig, body: BodyModel,
                 judge: BackTranslationConfig | None = None) -> tuple[EvaluationReport, dict]:
    """``judge``: the back-translation decoding settings (beam, length penalty; defaults when None)."""
    setup = evaluator_for(cfg, data, body)
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
    report = evaluator.score(generated, translations)
    metrics_dir = data.metrics("smlm")
    # every clip of the split is scored: clips over the model's limits were cut and kept; only clips the
    # vocabulary cannot take at all (a language without prompts, no text) are left out, and counted here
    report.summary.update({"clips_scored": float(len(evaluator.examples)), "clips_cut": float(len(setup.cut)),
                           "clips_unscorable": float(len(setup.skipped))})
    if cfg.backtranslate:
        judged = backtranslate_generated(evaluator, generated, data, body, judge or BackTranslationConfig())
        report.summary["bt/clips"] = float(0 if judged is None else len(judged.per_clip))
        if judged is not None:  # None: the split has no sentence clip (isolated signs only)
            report.summary.update({f"bt/{k}": v for k, v in judged.summary.items()})
            write_text(metrics_dir / "backtranslation.csv", per_clip_csv(judged.per_clip))
    write_json(metrics_dir / "metrics.json", report.summary)
    write_text(metrics_dir / "per_clip.csv", frame_csv(report.per_clip))
    return report, loaded.train_config


def backtranslate_generated(evaluator: SMLMEvaluator, generated: dict[str, GeneratedMotion], data: DataConfig,
                            body: BodyModel, judge: BackTranslationConfig) -> BackTranslationReport | None:
    """The generated motion of every sentence clip (decoded by the frozen tokenizers) through the frozen
    back-translation judge of its language (definition "slt"); an empty generation is the empty sentence.
    Isolated signs are left to the recognition probe; None when the split has no sentence clip."""
    empty = {name: np.zeros((0, dim), np.float32) for name, dim in body.layout.dims.items()}
    clips, texts = {}, {}
    for e in evaluator.examples:
        ref = evaluator.references[e.clip_id]
        if skip_reason(ref.clip, ref.num_frames) is not None:
            continue
        g = generated[e.clip_id]
        clips[e.clip_id] = (e.language, evaluator.motion_params(g) if len(g.tokens["body"]) else empty)
        texts[e.clip_id] = ref.clip.text
    if not clips:
        return None
    return backtranslate(data.backtranslation_dir, clips, texts, judge.beam_size, judge.length_penalty)


def evaluate_and_log(cfg: GenerateConfig, data: DataConfig, body_cfg: BodyConfig, experiment: ExperimentConfig,
                     judge: BackTranslationConfig | None = None) -> dict[str, float]:
    report, train_config = run_evaluate(cfg, data, load_body_model(body_cfg), judge)
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
