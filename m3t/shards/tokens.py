"""Token shards: the motion-token streams of every clip, the input of the language models.

One Parquet row per clip: the :class:`~m3t.corpora.clip.Clip` columns, ``num_frames`` (of the fitted
motion), and one ``list<int16>`` column per token stream (``body``, ``right_hand``, ``left_hand``,
``face``), all of length ``ceil(num_frames / downsample)`` and aligned in time: token ``i`` of every
stream covers frames ``[i * downsample, (i + 1) * downsample)``. The file metadata records the format
version, the downsampling factor, each stream's codebook size and the tokenizer checkpoints' digests.

Axis legend: N tokens per clip.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pyarrow as pa

from m3t.corpora.clip import Clip
from m3t.shards.io import parquet_file, write_table_atomic
from m3t.shards.schema import (
    CLIP_COLUMNS,
    METADATA_COLUMNS,
    ShardFormatError,
    check_column_types,
    clip_from_columns,
    clip_record,
)

TOKEN_SCHEMA_VERSION = 1
TOKEN_INFO_KEY = b"m3t.tokens"


@dataclass(frozen=True)
class TokenInfo:
    """streams: stream name -> codebook size; downsample: frames per token; tokenizers: stream -> checkpoint digest."""

    streams: dict[str, int]
    downsample: int
    tokenizers: dict[str, str]


@dataclass(frozen=True, eq=False)
class TokenClip:
    clip: Clip
    num_frames: int
    tokens: dict[str, np.ndarray]  # stream -> (N,) int64

    @property
    def num_tokens(self) -> int:
        return next((len(t) for t in self.tokens.values()), 0)


@dataclass(frozen=True, eq=False)
class TokenShard:
    path: Path
    info: TokenInfo
    clips: tuple[TokenClip, ...]


def _check(clip: TokenClip, info: TokenInfo) -> None:
    expected = -(-clip.num_frames // info.downsample)
    for stream, size in info.streams.items():
        if stream not in clip.tokens:
            raise ValueError(f"clip {clip.clip.id!r}: no tokens for stream {stream!r}")
        tokens = np.asarray(clip.tokens[stream])
        if tokens.shape != (expected,):
            raise ValueError(f"clip {clip.clip.id!r}, stream {stream!r}: {tokens.shape[0] if tokens.ndim else 0} tokens, "
                             f"expected ceil({clip.num_frames} / {info.downsample}) = {expected}")
        if tokens.size and (tokens.min() < 0 or tokens.max() >= size):
            raise ValueError(f"clip {clip.clip.id!r}, stream {stream!r}: token outside [0, {size})")


def token_schema(info: TokenInfo) -> pa.Schema:
    """The Arrow schema of a token shard of ``info``'s streams, with version and info in its metadata."""
    fields = [pa.field(n, METADATA_COLUMNS[n], nullable=n == "label") for n in CLIP_COLUMNS]
    fields.append(pa.field("num_frames", pa.int32(), nullable=False))
    fields += [pa.field(s, pa.list_(pa.int16()), nullable=False) for s in info.streams]
    meta = {b"m3t.token_schema_version": str(TOKEN_SCHEMA_VERSION).encode(),
            TOKEN_INFO_KEY: json.dumps({"streams": info.streams, "downsample": info.downsample,
                                        "tokenizers": info.tokenizers}).encode()}
    return pa.schema(fields, metadata=meta)


def write_token_shard(path: str | os.PathLike, clips: Sequence[TokenClip], info: TokenInfo) -> Path:
    """Validate and write ``clips`` atomically."""
    if max(info.streams.values(), default=0) > np.iinfo(np.int16).max:
        raise ValueError("codebooks above 32767 codes do not fit the int16 token columns")
    for clip in clips:
        _check(clip, info)
    rows = [clip_record(c.clip) for c in clips]
    schema = token_schema(info)
    arrays = [pa.array([r[n] for r in rows], type=METADATA_COLUMNS[n]) for n in CLIP_COLUMNS]
    arrays.append(pa.array([c.num_frames for c in clips], type=pa.int32()))
    arrays += [pa.array([np.asarray(c.tokens[s], dtype=np.int16) for c in clips], type=pa.list_(pa.int16()))
               for s in info.streams]
    return write_table_atomic(path, pa.Table.from_arrays(arrays, schema=schema))


def read_token_shard(path: str | os.PathLike) -> TokenShard:
    path = Path(path)
    pf = parquet_file(path)
    meta = pf.schema_arrow.metadata or {}
    version = meta.get(b"m3t.token_schema_version", b"").decode()
    if version != str(TOKEN_SCHEMA_VERSION) or TOKEN_INFO_KEY not in meta:
        raise ShardFormatError(f"{path}: not an m3t token shard of version {TOKEN_SCHEMA_VERSION} (found {version or 'none'}); "
                               "rerun the tokenize stage")
    try:
        raw = json.loads(meta[TOKEN_INFO_KEY])
        info = TokenInfo({k: int(v) for k, v in raw["streams"].items()}, int(raw["downsample"]),
                         dict(raw["tokenizers"]))
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise ShardFormatError(f"{path}: cannot parse the {TOKEN_INFO_KEY.decode()} metadata ({exc!r}); rerun the "
                               "tokenize stage") from exc
    check_column_types(pf.schema_arrow, token_schema(info), str(path), "the token shard was edited or not written "
                       "by m3t; rerun the tokenize stage")
    table = pf.read()
    columns = {n: table.column(n).to_pylist() for n in (*CLIP_COLUMNS, "num_frames")}
    streams = {s: table.column(s).to_pylist() for s in info.streams}
    clips = tuple(
        TokenClip(clip_from_columns(columns, i), int(columns["num_frames"][i]),
                  {s: np.asarray(streams[s][i], dtype=np.int64) for s in info.streams})
        for i in range(table.num_rows)
    )
    for row, clip in enumerate(clips):  # what the writer checks: a damaged or hand-edited file fails here, not in a model
        try:
            _check(clip, info)
        except ValueError as exc:
            raise ShardFormatError(f"{path}: row {row} (0-based): {exc}; rerun the tokenize stage") from exc
    return TokenShard(path, info, clips)
