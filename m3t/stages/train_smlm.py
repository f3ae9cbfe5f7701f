"""train-smlm: token shards -> the Sign Motion Language Model (M3T Sec. 3.3).

Builds the vocabulary (text tokenizer trained on the train-split text, or the local mBART one; prompts
for every language of the train split; one token per FSQ code), trains production + translation
(``smlm_train.translation_objective``), selects the checkpoint with the lowest mean validation DTW-JPE on
the dev split (generated motion decoded by the frozen tokenizers, against the fitted motion) and writes
``<out_dir>/smlm.pt``, ``metrics.json`` and ``skipped.jsonl`` (clips not used, with reasons).

Run as a DVC stage: ``python -m m3t.stages.train_smlm``; ``torchrun --nproc_per_node N -m m3t.stages.train_smlm``
for data-parallel training.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from m3t.body.protocol import BodyModel
from m3t.runtime import DistributedContext
from m3t.shards.schema import FittedClip
from m3t.shards.tokens import TokenShard, read_token_shard
from m3t.smlm.data import Example, examples_from_shard
from m3t.smlm.evaluate import SMLMEvaluator
from m3t.smlm.model import SMLMConfig
from m3t.smlm.train import SMLMTrainConfig, train_smlm
from m3t.smlm.vocab import SignVocabulary, build_vocabulary
from m3t.stages.train_tokenizers import atomic_copy, data_version, load_split
from m3t.stages.tokenize import load_tokenizers


def load_tokens(tokens_dir: str | Path, split: str) -> TokenShard:
    path = Path(tokens_dir) / f"{split}.parquet"
    if not path.exists():
        raise FileNotFoundError(f"token shard {path} not found; run the tokenize stage first (dvc repro tokenize)")
    return read_token_shard(path)


def references(shards_dir: str | Path, split: str) -> dict[str, FittedClip]:
    """The fitted motion of a split by clip id: the reference of the DTW evaluation."""
    return {c.clip.id: c for c in load_split(shards_dir, split)}


def vocabulary_for(model_cfg: SMLMConfig, train: TokenShard) -> SignVocabulary:
    return build_vocabulary([c.clip.text for c in train.clips], [c.clip.language for c in train.clips],
                            train.info.streams, model_cfg.text_vocab_size, model_cfg.text_model_path)


def split_examples(shard: TokenShard, vocab: SignVocabulary, model_cfg: SMLMConfig,
                   skipped: list[dict]) -> list[Example]:
    examples, lost = examples_from_shard(shard, vocab, model_cfg.max_text_tokens, model_cfg.max_motion_tokens)
    skipped.extend(lost)
    return examples


def run_train_smlm(model_cfg: SMLMConfig, cfg: SMLMTrainConfig, body: BodyModel, on_epoch=None,
                   dist_ctx: DistributedContext | None = None, progress: bool = True) -> dict[str, float]:
    dist_ctx = dist_ctx or DistributedContext()
    shards = {split: load_tokens(cfg.tokens_dir, split) for split in ("train", "dev")}
    vocab = vocabulary_for(model_cfg, shards["train"])
    skipped: list[dict] = []
    train = split_examples(shards["train"], vocab, model_cfg, skipped)
    dev = split_examples(shards["dev"], vocab, model_cfg, skipped)
    evaluator = None
    if dist_ctx.is_main and dev:
        tokenizers, _ = load_tokenizers(cfg.tokenizers_dir)
        evaluator = SMLMEvaluator(body, tokenizers, vocab, dev, references(cfg.shards_dir, "dev"),
                                  max_clips=cfg.eval_max_clips, translation=cfg.translation_objective)
    version = data_version([shards[s].path for s in ("train", "dev")])
    out_dir = Path(cfg.out_dir)
    best = out_dir / ".smlm.best.pt"  # renamed into place at the end: smlm.pt only ever holds a finished run
    result = train_smlm(model_cfg, cfg, vocab, train, evaluator, version, best, on_epoch=on_epoch,
                        dist_ctx=dist_ctx, progress=progress)
    if not dist_ctx.is_main:
        return {}
    atomic_copy(best, out_dir / "smlm.pt")
    best.unlink(missing_ok=True)
    report = {"train_examples": float(len(train)), "dev_examples": float(len(dev)), "skipped": float(len(skipped)),
              "vocabulary_size": float(len(vocab)), "text_vocabulary_size": float(vocab.text_size),
              "best_epoch": float(result.best.get("epoch", 0)),
              **{f"best_{k}": v for k, v in result.best.items() if k.startswith(("val_", "train_"))}}
    (out_dir / "metrics.json").write_text(json.dumps(report, indent=2, sort_keys=True, default=float))
    (out_dir / "skipped.jsonl").write_text("".join(json.dumps(r) + "\n" for r in skipped))
    return report


def train_and_log(params, progress: bool = True) -> dict[str, float]:
    from m3t.body.factory import load_body_model
    from m3t.config import flat_params
    from m3t.experiment import start_run
    from m3t.runtime import distributed_context

    dist_ctx = distributed_context(params.smlm_train.device)
    body = load_body_model(params.body)
    if not dist_ctx.is_main:
        return run_train_smlm(params.smlm, params.smlm_train, body, dist_ctx=dist_ctx, progress=False)
    tags = {"translation_objective": str(params.smlm_train.translation_objective), "d_model": str(params.smlm.d_model)}
    with start_run(params.experiment, "train-smlm", tags=tags) as run:
        run.log_params({k: v for k, v in flat_params(params).items() if k.split(".")[0] in ("smlm", "smlm_train")})
        report = run_train_smlm(params.smlm, params.smlm_train, body, dist_ctx=dist_ctx, progress=progress,
                                on_epoch=lambda record, epoch: run.log_metrics(record, step=epoch))
        run.log_metrics(report)
        for name in ("metrics.json", "skipped.jsonl"):
            run.log_artifact(Path(params.smlm_train.out_dir) / name)
    return report


def main(argv: list[str] | None = None) -> dict:
    from m3t.config import load_params

    parser = argparse.ArgumentParser(description="train-smlm: token shards -> Sign Motion Language Model")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--preset", default="default")
    args = parser.parse_args(argv)
    report = train_and_log(load_params(args.params, preset=args.preset))
    print(json.dumps(report, indent=2, sort_keys=True))
    return report


if __name__ == "__main__":
    main()
