"""A split's fitted clips by id, their parameters read from the shards when asked for.

Evaluation keeps every clip of a split at hand (its metadata, identity and length: what generation, the judges and
the scorer's planning need), but the parameters of a How2Sign-sized test split are ~0.5 GB of float32 and grow
with the corpus. :class:`SplitReferences` holds the metadata only (one pass over the shards reading no parameter
column) and reads a clip's parameters from its Parquet row group when :attr:`StoredClip.params` is asked for,
keeping the last row group read: clips asked for in shard order read every group once.

Axis legend: T frames, D_m per-frame dim of modality m, P identity dim.
"""
from __future__ import annotations

import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from m3t.corpora.clip import Clip
from m3t.shards.io import iter_shard, read_row_group, split_shards


@dataclass(frozen=True, eq=False)
class StoredClip:
    """A fitted clip (duck-typed :class:`m3t.shards.schema.FittedClip`) whose parameters stay in its shard until
    :attr:`params` is read; nothing holds them after the caller lets go (but the source's last row group)."""

    clip: Clip
    key: str
    identity: np.ndarray  # (P,) float32
    camera: dict
    metrics: dict[str, float]
    body_model: str
    num_frames: int  # T, from the shard's metadata
    source: SplitReferences = field(repr=False)

    @property
    def params(self) -> dict[str, np.ndarray]:
        """Modality name -> (T, D_m) float32, read from the shard (checked as every shard read is)."""
        return self.source.params(self.clip.id)


class SplitReferences(Mapping[str, StoredClip]):
    """The fitted clips of ``split`` in ``shards_dirs`` (several corpora's folders, in order), by clip id, in
    shard order; the same checks as :func:`m3t.shards.io.read_split` (a missing shard names the stage to run, a
    clip id in two corpora is refused), parameter columns checked when their row group is read."""

    def __init__(self, shards_dirs: Sequence[str | os.PathLike] | str | os.PathLike, split: str):
        self._clips: dict[str, StoredClip] = {}
        self._where: dict[str, tuple[Path, int]] = {}  # clip id -> (shard, row group)
        self._group: tuple[tuple[Path, int], dict[str, dict[str, np.ndarray]]] | None = None
        for path in split_shards(shards_dirs, split):
            for group, contents in enumerate(iter_shard(path, modalities=[])):
                for fitted, frames in zip(contents.clips, contents.lengths):
                    cid = fitted.clip.id
                    if cid in self._where:
                        raise ValueError(f"clip id {cid!r} is in both {self._where[cid][0]} and {path}; clip ids "
                                         "must be unique across data.train_corpora")
                    self._where[cid] = (path, group)
                    self._clips[cid] = StoredClip(fitted.clip, fitted.key, fitted.identity, fitted.camera,
                                                  fitted.metrics, fitted.body_model, int(frames), self)

    def __getitem__(self, clip_id: str) -> StoredClip:
        return self._clips[clip_id]

    def __iter__(self) -> Iterator[str]:
        return iter(self._clips)

    def __len__(self) -> int:
        return len(self._clips)

    def params(self, clip_id: str) -> dict[str, np.ndarray]:
        """The parameters of ``clip_id``, from its row group (read unless it is the last one read)."""
        where = self._where[clip_id]
        if self._group is None or self._group[0] != where:
            self._group = None  # the previous group is let go before the next is read
            contents = read_row_group(*where)
            self._group = (where, {c.clip.id: c.params for c in contents.clips})
        return self._group[1][clip_id]
