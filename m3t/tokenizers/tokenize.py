"""Fitted shards + trained tokenizers -> token shards (one per corpus and split), for the language models.

Every clip of every split of each corpus in ``data.train_corpora`` is encoded by the three selected
tokenizers (left hands mirrored into right hands for the shared hand tokenizer), giving four time-aligned
streams per clip, written to ``<tokens_root>/<corpus>/<split>.parquet``. A clip that cannot be tokenised
(non-finite parameters, a stream missing) is listed in that corpus' ``rejected.jsonl`` with its reason and
the others go on. Clips shorter than one token window are edge-padded to one token. The fitted clips are
streamed one shard row group at a time (:func:`m3t.shards.io.iter_shard`); only the token clips, a few integers
per frame window, are kept until their shard is written. With ``fit_corpus.executor: dask`` the row groups are
tokenised on the Dask cluster fit-corpus uses (:func:`m3t.fitting.cluster.stage_executor`; workers load the
tokenizers from the same paths, one torch thread each), and the token shards are the same bytes.
"""
from __future__ import annotations

from collections.abc import Iterator
from functools import lru_cache
from pathlib import Path

import numpy as np

from m3t.atomic import write_json, write_jsonl
from m3t.corpora.splits import SPLITS
from m3t.digest import file_digest
from m3t.fitting.cluster import stage_executor, submitted_in_order
from m3t.fitting.config import FitCorpusConfig
from m3t.shards.folders import DataConfig
from m3t.shards.io import iter_shard, split_shards
from m3t.shards.tokens import TokenClip, TokenInfo, write_token_shard
from m3t.tokenizers.checkpoint import load_tokenizer
from m3t.tokenizers.data import GROUPS, STREAMS, clip_sequences
from m3t.tokenizers.evaluate import encode_clip
from m3t.tokenizers.vae import MotionTokenizer


def load_tokenizers(tokenizers_dir: str | Path) -> tuple[dict[str, MotionTokenizer], TokenInfo]:
    """The three group tokenizers and the token-shard info (codebook sizes, downsampling, digests)."""
    models, digests = {}, {}
    for group in GROUPS:
        path = Path(tokenizers_dir) / f"{group}.pt"
        models[group] = load_tokenizer(path).model
        digests[group] = file_digest(path, length=16)
    factors = {m.cfg.downsample for m in models.values()}
    if len(factors) != 1:
        raise ValueError(f"tokenizers in {tokenizers_dir} downsample by different factors {sorted(factors)}; "
                         "the token streams would not align in time; retrain them with one tokenizer.down_stages")
    info = TokenInfo({s.name: models[g].codebook_size for g, streams in GROUPS.items() for s in streams},
                     factors.pop(), {s.name: digests[g] for g, streams in GROUPS.items() for s in streams})
    return models, info


def tokenize_clip(models: dict[str, MotionTokenizer], fitted) -> TokenClip:
    tokens = {}
    for group, streams in GROUPS.items():
        for stream, values in zip(streams, clip_sequences(fitted.params, group, fitted.clip.id)):
            tokens[stream.name] = encode_clip(models[group], values)
    return TokenClip(fitted.clip, fitted.num_frames, {s.name: tokens[s.name] for s in STREAMS})


def tokenize_clips(models: dict[str, MotionTokenizer], clips: list, split: str) -> tuple[list[TokenClip], list[dict]]:
    """Fitted clips of one split -> their token clips, and the records of those that cannot be tokenised."""
    tokens, rejected = [], []
    for fitted in clips:
        try:
            tokens.append(tokenize_clip(models, fitted))
        except (ValueError, KeyError) as exc:
            rejected.append({"clip_id": fitted.clip.id, "split": split, "reason": f"{type(exc).__name__}: {exc}"})
    return tokens, rejected


def tokenize_on_worker(tokenizers_dir: str, digests: dict[str, str], clips: list,
                       split: str) -> tuple[list[TokenClip], list[dict]]:
    """:func:`tokenize_clips` on a worker: the tokenizers are loaded once per process, and must be the files the
    run's own process loaded (``digests``)."""
    models, info = _worker_tokenizers(tokenizers_dir)
    if info.tokenizers != digests:
        raise RuntimeError(f"the tokenizers in {tokenizers_dir} seen by this worker differ from those of the run "
                           f"({info.tokenizers} vs {digests}); workers must see the run's files at the same paths")
    return tokenize_clips(models, clips, split)


@lru_cache(maxsize=2)
def _worker_tokenizers(tokenizers_dir: str) -> tuple[dict[str, MotionTokenizer], TokenInfo]:
    return load_tokenizers(tokenizers_dir)


def _tokenized_groups(models: dict[str, MotionTokenizer], info: TokenInfo, tokenizers_dir: Path | None, shard: Path,
                      split: str, executor) -> Iterator[tuple[list[TokenClip], list[dict]]]:
    """Each row group of ``shard`` tokenised, in file order: here, or on ``executor``'s workers with at most its
    capacity of groups in flight (:func:`m3t.fitting.cluster.submitted_in_order`)."""
    groups = iter_shard(shard)
    if executor is None:
        for group in groups:
            yield tokenize_clips(models, list(group.clips), split)
        return
    yield from submitted_in_order(executor, tokenize_on_worker, ((str(tokenizers_dir), info.tokenizers,
                                                                  list(group.clips), split) for group in groups))


def tokenize_corpus(models: dict[str, MotionTokenizer], info: TokenInfo, shards_dir: Path,
                    out: Path, executor=None, tokenizers_dir: Path | None = None) -> dict[str, float]:
    """One corpus' splits -> token shards + ``rejected.jsonl`` + ``summary.json`` in ``out``. Fitted clips are
    read one row group at a time and only their (small) tokens are kept; ``executor`` (with the folder the
    tokenizers came from): the groups are tokenised on its workers, the outputs are the same."""
    rejected, summary = [], {}
    for split in SPLITS:
        (shard,) = split_shards(shards_dir, split)
        clips = []
        for tokens, lost in _tokenized_groups(models, info, tokenizers_dir, shard, split, executor):
            clips += tokens
            rejected += lost
        out.mkdir(parents=True, exist_ok=True)
        write_token_shard(out / f"{split}.parquet", clips, info)
        summary[f"{split}_clips"] = len(clips)
        summary[f"{split}_tokens_per_stream"] = int(sum(c.num_tokens for c in clips))
    summary["rejected"] = len(rejected)
    summary["mean_tokens_per_clip"] = float(np.mean([summary[f"{s}_tokens_per_stream"] / max(summary[f"{s}_clips"], 1)
                                                     for s in SPLITS if summary[f"{s}_clips"]] or [0.0]))
    write_jsonl(out / "rejected.jsonl", rejected)
    write_json(out / "summary.json", summary)
    return summary


def run_tokenize(data: DataConfig, cluster: FitCorpusConfig | None = None) -> dict[str, dict[str, float]]:
    """Token shards of every training corpus, by corpus name. ``cluster`` (params ``fit_corpus``): with ``executor:
    dask`` the row groups are tokenised on that cluster (``dask_address``, or a LocalCluster of ``workers``
    processes); ``local`` tokenises in this process. The token shards are the same either way."""
    models, info = load_tokenizers(data.tokenizers_dir)
    with stage_executor(cluster) as executor:
        return {corpus: tokenize_corpus(models, info, data.shards_dir(corpus), data.tokens_dir(corpus), executor,
                                        data.tokenizers_dir)
                for corpus in data.train_corpora}
