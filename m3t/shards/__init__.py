"""Fitted-motion shards: Parquet storage of fitted clips and torch access to them.

- :mod:`m3t.shards.schema`: the on-disk format (:class:`FittedClip`, :func:`arrow_schema`, version).
- :mod:`m3t.shards.io`: atomic :func:`write_shard`, :func:`read_shard`, :func:`shard_layout`.
- :mod:`m3t.shards.dataset`: :class:`ShardDataset`, :class:`LengthBucketSampler`, :func:`collate_motion`.
"""
from m3t.shards.dataset import (
    LengthBucketSampler,
    MotionBatch,
    MotionItem,
    ShardDataset,
    collate_motion,
)
from m3t.shards.io import ShardContents, read_shard, shard_layout, write_shard
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
    "arrow_schema",
    "collate_motion",
    "read_shard",
    "shard_layout",
    "write_shard",
]
