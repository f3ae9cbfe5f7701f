"""Fitted-motion shards: Parquet storage of fitted clips and torch access to them.

- :mod:`m3t.shards.schema`: the on-disk format (:class:`FittedClip`, :func:`arrow_schema`, version).
- :mod:`m3t.shards.io`: atomic :func:`write_shard` / :class:`ShardWriter`, :func:`read_shard` /
  :func:`iter_shard` (one row group at a time), :func:`shard_layout`.
- :mod:`m3t.shards.dataset`: :class:`ShardDataset`, :class:`LengthBucketSampler`, :func:`collate_motion`.
"""
from m3t.shards.dataset import (
    LengthBucketSampler,
    MotionBatch,
    MotionItem,
    ShardDataset,
    collate_motion,
)
from m3t.shards.io import (
    ShardContents,
    ShardWriter,
    iter_shard,
    read_shard,
    shard_layout,
    write_shard,
)
from m3t.shards.schema import SCHEMA_VERSION, FittedClip, ShardFormatError, arrow_schema

__all__ = [
    "SCHEMA_VERSION",
    "FittedClip",
    "LengthBucketSampler",
    "MotionBatch",
    "MotionItem",
    "ShardContents",
    "ShardDataset",
    "ShardFormatError",
    "ShardWriter",
    "arrow_schema",
    "collate_motion",
    "iter_shard",
    "read_shard",
    "shard_layout",
    "write_shard",
]
