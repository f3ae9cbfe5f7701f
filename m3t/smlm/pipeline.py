"""The SMLM's shared data loading for its three runs, each in its own module so that a stage's code deps are
only the run it makes (a renderer change reruns generate-smlm, not train-smlm):

- :mod:`m3t.smlm.train_run` (train-smlm), :mod:`m3t.smlm.generate_run` (generate-smlm) and
  :mod:`m3t.smlm.evaluate_run` (evaluate-smlm), over the token shards and fitted shards of ``data.train_corpora``;
- here: the token shards of a split, the fitted references, the vocabulary and the examples they all read.
"""
from __future__ import annotations

from dataclasses import replace

from m3t.shards.folders import DataConfig
from m3t.shards.references import SplitReferences
from m3t.shards.tokens import (
    TokenShard,
    read_token_shard,
)
from m3t.smlm.config import SMLMConfig
from m3t.smlm.data import Example, examples_from_shard
from m3t.smlm.vocab import SignVocabulary, build_vocabulary


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


def references(data: DataConfig, split: str) -> SplitReferences:
    """The fitted motion of a split by clip id: the reference of the DTW evaluation (metadata in memory,
    parameters read from the shards when a clip is posed: memory that does not grow with the split)."""
    return SplitReferences(data.shards_dirs, split)


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


def variant_name(train_config: dict) -> str:
    """The ablation's row name of a (checkpoint's) train config: production only, or production + translation
    (with "(added steps)" at equal production updates)."""
    objective = bool(train_config.get("translation_objective", True))
    if not objective:
        return "production only"
    added = train_config.get("translation_steps", "shared") == "added"
    return "production + translation" + (" (added steps)" if added else "")
