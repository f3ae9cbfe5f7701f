"""train-smlm's run over the token shards and fitted shards of ``data.train_corpora`` (trained jointly; checkpoint
selected on all their dev splits).

- :func:`train_and_log`: vocabulary (text tokenizer trained on the train-split text, or the local mBART one,
  ``smlm.reduce_text_vocab``: cut to the ids of the train-split text; prompts for every language of the train
  splits; one token per FSQ code), production + translation
  (``smlm_train.translation_objective``), checkpoint with the lowest mean dev DTW-JPE over the dev clips of
  every training corpus (``smlm_train.eval_max_clips``: the first N of them, 0 = all); writes
  ``<models>/smlm/smlm.pt``, ``metrics.json`` and ``skipped.jsonl``.
"""
from __future__ import annotations

from pathlib import Path

from m3t.atomic import copy_file, write_json, write_jsonl
from m3t.body.factory import BodyConfig, load_body_model
from m3t.body.protocol import BodyModel
from m3t.experiment import ExperimentConfig, section_params, start_run, to_dict
from m3t.runtime import DistributedContext, distributed_context
from m3t.shards.folders import DataConfig
from m3t.shards.io import data_version
from m3t.smlm.config import SMLMConfig, SMLMTrainConfig
from m3t.smlm.evaluate import SMLMEvaluator
from m3t.smlm.pipeline import (
    load_tokens,
    references,
    split_examples,
    variant_name,
    vocabulary_for,
)
from m3t.smlm.train import run_key, train_smlm
from m3t.tokenizers.tokenize import load_tokenizers


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


