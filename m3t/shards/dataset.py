"""Torch access to fitted-motion shards: a dataset, a length-bucketing batch sampler and a padding collate.

Typical use::

    ds = ShardDataset(["train-000.parquet", "train-001.parquet"], modalities=["body", "right_hand"])
    sampler = LengthBucketSampler(ds.lengths, batch_size=32, seed=0)
    loader = DataLoader(ds, batch_sampler=sampler, collate_fn=collate_motion)

Axis legend: B batch (clips), T frames (padded to the longest clip in a batch), D_m per-frame dim of
modality m, P identity dim.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from m3t.body.protocol import ModalityLayout
from m3t.shards.io import read_shard
from m3t.shards.schema import FittedClip


@dataclass(frozen=True)
class MotionItem:
    """One clip as served by :class:`ShardDataset`.

    params: modality -> (T, D_m) float32; identity: (P,) float32; metadata: the clip record fields plus
    ``key``, ``body_model``, ``camera``, ``metrics`` and ``shard`` (the file it came from); length: T.
    """

    clip_id: str
    params: dict[str, torch.Tensor]
    identity: torch.Tensor
    metadata: dict[str, Any]
    length: int


@dataclass(frozen=True)
class MotionBatch:
    """A padded batch.

    params: modality -> (B, T, D_m), zero beyond each clip's length; identity: (B, P); mask: (B, T) bool,
    True on real frames; lengths: (B,) int64; clip_ids and metadata: one entry per clip.
    """

    clip_ids: tuple[str, ...]
    params: dict[str, torch.Tensor]
    identity: torch.Tensor
    mask: torch.Tensor
    lengths: torch.Tensor
    metadata: tuple[dict[str, Any], ...]

    def to(self, device: torch.device | str, non_blocking: bool = False) -> MotionBatch:
        """The same batch with every tensor moved to ``device``."""
        def move(t: torch.Tensor) -> torch.Tensor:
            return t.to(device, non_blocking=non_blocking)

        return MotionBatch(
            clip_ids=self.clip_ids,
            params={k: move(v) for k, v in self.params.items()},
            identity=move(self.identity),
            mask=move(self.mask),
            lengths=move(self.lengths),
            metadata=self.metadata,
        )

    def pin_memory(self) -> MotionBatch:
        """Used by ``DataLoader(pin_memory=True)``."""
        return MotionBatch(
            clip_ids=self.clip_ids,
            params={k: v.pin_memory() for k, v in self.params.items()},
            identity=self.identity.pin_memory(),
            mask=self.mask.pin_memory(),
            lengths=self.lengths.pin_memory(),
            metadata=self.metadata,
        )


def _metadata(fitted: FittedClip, shard: Path) -> dict[str, Any]:
    clip = {f.name: getattr(fitted.clip, f.name) for f in dataclasses.fields(fitted.clip) if f.name != "id"}
    return {**clip, "extra": dict(fitted.clip.extra), "key": fitted.key, "body_model": fitted.body_model,
            "camera": fitted.camera, "metrics": fitted.metrics, "shard": str(shard)}


class ShardDataset(Dataset):
    """All clips of one or more shards, held in memory, served as :class:`MotionItem`.

    Parameters
    ----------
    paths : one shard path or a sequence of them; clips keep file order, shards the given order.
    modalities : modalities to load (default: all modalities of the first shard's layout). Every shard
        must contain them with the same dims.

    Attributes
    ----------
    layout : the first shard's stored layout.
    modalities : the loaded modality names.
    lengths : (N,) int64 frames per clip, for :class:`LengthBucketSampler`.
    """

    def __init__(self, paths: str | os.PathLike | Sequence[str | os.PathLike], modalities: Sequence[str] | None = None):
        if isinstance(paths, (str, os.PathLike)):
            paths = [paths]
        paths = [Path(p) for p in paths]
        if not paths:
            raise ValueError("ShardDataset needs at least one shard path")
        self.layout: ModalityLayout | None = None
        self.modalities: tuple[str, ...] = ()
        self._clips: list[FittedClip] = []
        self._sources: list[Path] = []
        lengths: list[np.ndarray] = []
        first_seen: dict[str, Path] = {}
        for path in paths:
            contents = read_shard(path, modalities if self.layout is None else self.modalities)
            if self.layout is None:
                self.layout = contents.layout
                self.modalities = tuple(contents.layout.names if modalities is None else modalities)
                if not self.modalities:
                    raise ValueError(f"no modalities to load from {path}; pass modalities=[...] or check the shard")
            else:
                self._check_compatible(contents.layout, path, paths[0])
            for fitted in contents.clips:
                cid = fitted.clip.id
                if cid in first_seen:
                    raise ValueError(
                        f"clip {cid!r} is in both {first_seen[cid]} and {path}; pass each shard once and keep clip ids unique"
                    )
                first_seen[cid] = path
            self._clips.extend(contents.clips)
            self._sources.extend([path] * len(contents))
            lengths.append(contents.lengths)
        self.lengths: np.ndarray = np.concatenate(lengths)

    def _check_compatible(self, layout: ModalityLayout, path: Path, first: Path) -> None:
        assert self.layout is not None
        for name in self.modalities:
            if layout.dims[name] != self.layout.dims[name]:
                raise ValueError(
                    f"{path}: modality {name!r} has dim {layout.dims[name]}, {first} has {self.layout.dims[name]}; "
                    "shards fitted with different body models cannot be mixed"
                )
        if layout.identity_dim != self.layout.identity_dim:
            raise ValueError(
                f"{path}: identity dim {layout.identity_dim}, {first} has {self.layout.identity_dim}; "
                "shards fitted with different body models cannot be mixed"
            )

    def __len__(self) -> int:
        return len(self._clips)

    def fitted(self, index: int) -> FittedClip:
        """The stored record of clip ``index`` (numpy arrays, no conversion)."""
        return self._clips[index]

    def __getitem__(self, index: int) -> MotionItem:
        fitted = self._clips[index]
        return MotionItem(
            clip_id=fitted.clip.id,
            params={name: torch.from_numpy(fitted.params[name]) for name in self.modalities},
            identity=torch.from_numpy(fitted.identity),
            metadata=_metadata(fitted, self._sources[index]),
            length=int(self.lengths[index]),
        )


class LengthBucketSampler(Sampler[list[int]]):
    """Batch sampler that groups clips of similar length to limit padding.

    With ``shuffle``: indices are permuted, cut into chunks of ``chunk_batches * batch_size``, sorted by
    length within each chunk, cut into batches, and the batch order is shuffled. Without: indices are
    sorted by length (stable) and batched in order. Every index appears exactly once per epoch (the last,
    smaller batch is dropped with ``drop_last``). Deterministic for a given ``seed`` and epoch; call
    :meth:`set_epoch` to get a different order each epoch.
    """

    def __init__(
        self,
        lengths: Sequence[int] | np.ndarray,
        batch_size: int,
        shuffle: bool = True,
        seed: int = 0,
        drop_last: bool = False,
        chunk_batches: int = 50,
    ):
        super().__init__()
        self.lengths = np.asarray(lengths, dtype=np.int64)
        if self.lengths.ndim != 1:
            raise ValueError(f"lengths must be 1-D (one per clip), got shape {self.lengths.shape}")
        if batch_size < 1 or chunk_batches < 1:
            raise ValueError(f"batch_size ({batch_size}) and chunk_batches ({chunk_batches}) must be >= 1")
        self.batch_size = int(batch_size)
        self.shuffle = shuffle
        self.seed = int(seed)
        self.drop_last = drop_last
        self.chunk_batches = int(chunk_batches)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _batches(self) -> list[np.ndarray]:
        n, size = len(self.lengths), self.batch_size
        if not self.shuffle:
            order = np.argsort(self.lengths, kind="stable")
            return [order[i : i + size] for i in range(0, n, size)]
        rng = np.random.default_rng([self.seed, self.epoch])
        perm = rng.permutation(n)
        chunk = size * self.chunk_batches
        batches: list[np.ndarray] = []
        for start in range(0, n, chunk):
            part = perm[start : start + chunk]
            part = part[np.argsort(self.lengths[part], kind="stable")]
            batches.extend(part[i : i + size] for i in range(0, len(part), size))
        order = rng.permutation(len(batches))
        return [batches[i] for i in order]

    def __iter__(self) -> Iterator[list[int]]:
        for batch in self._batches():
            if self.drop_last and len(batch) < self.batch_size:
                continue
            yield batch.tolist()

    def __len__(self) -> int:
        n = len(self.lengths)
        return n // self.batch_size if self.drop_last else -(-n // self.batch_size)


def collate_motion(items: Sequence[MotionItem]) -> MotionBatch:
    """Pad ``items`` to the longest clip (zeros) and stack them into a :class:`MotionBatch`."""
    if not items:
        raise ValueError("collate_motion got an empty batch")
    lengths = torch.tensor([item.length for item in items], dtype=torch.int64)
    batch, longest = len(items), int(lengths.max())
    params: dict[str, torch.Tensor] = {}
    for name, first in items[0].params.items():
        out = first.new_zeros((batch, longest, first.shape[-1]))
        for b, item in enumerate(items):
            out[b, : item.length] = item.params[name]
        params[name] = out
    mask = torch.arange(longest).unsqueeze(0) < lengths.unsqueeze(1)
    return MotionBatch(
        clip_ids=tuple(item.clip_id for item in items),
        params=params,
        identity=torch.stack([item.identity for item in items]),
        mask=mask,
        lengths=lengths,
        metadata=tuple(item.metadata for item in items),
    )
