"""What each tokenizer is trained on: modality groups, mirrored left hands, fixed-length windows.

M3T trains one tokenizer per modality group (Sec. 3.2): ``body``, ``hand`` (one shared tokenizer: right
hands as they are, left hands mirrored into right hands with the single mirroring function of
:mod:`m3t.body.rotations`) and ``face``. Each group reads its streams from the fitted shards; every
stream of a clip becomes one training sequence, cropped to random windows of ``window`` frames per epoch:
a fixed number per clip, or (``windows_per_clip: 0``) ``ceil(T / window)`` windows tiling the clip from a
random offset, so that an epoch passes every frame of every clip (the paper preset: App. 0.D.1 counts
epochs but states no windows, and SOKE's tokenizer epochs pass each whole clip once). A clip shorter than a
window is padded by repeating its last frame and the padding is masked out of the loss; a clip with
non-finite values is rejected with its id.

Axis legend: T frames, D the group's per-frame dim, B batch, W window length.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Sequence

import numpy as np
import torch

from m3t.body.protocol import STREAM_ORDER, ModalityLayout
from m3t.body.rotations import mirror_rotations


@dataclass(frozen=True)
class Stream:
    """One token stream of a group: ``modality`` in the body layout, stored mirrored or not."""

    name: str
    modality: str
    mirrored: bool = False


GROUPS: dict[str, tuple[Stream, ...]] = {
    "body": (Stream("body", "body"),),
    "hand": (Stream("right_hand", "right_hand"), Stream("left_hand", "left_hand", mirrored=True)),
    "face": (Stream("face", "face"),),
}
"""Tokenizer group -> the token streams it serves (the token shards have one column per stream)."""

STREAMS: tuple[Stream, ...] = tuple(sorted((s for streams in GROUPS.values() for s in streams),
                                           key=lambda s: STREAM_ORDER.index(s.name)))
"""Every token stream, in the project's one stream order (:data:`m3t.body.protocol.STREAM_ORDER`)."""


def group_of(stream_name: str) -> str:
    for group, streams in GROUPS.items():
        if any(s.name == stream_name for s in streams):
            return group
    raise KeyError(f"no tokenizer group serves stream {stream_name!r}; streams: {[s.name for s in STREAMS]}")


def check_layout(layout: ModalityLayout, group: str) -> int:
    """The group's input dim; a clear error if the body model lacks a stream or the hands disagree."""
    if group not in GROUPS:
        raise ValueError(f"tokenizer group {group!r} unknown; allowed: {', '.join(GROUPS)}")
    dims = set()
    for stream in GROUPS[group]:
        if stream.modality not in layout.names:
            raise ValueError(f"tokenizer group {group!r} needs modality {stream.modality!r}; the body model's "
                             f"layout has {list(layout.names)}")
        if stream.mirrored and layout[stream.modality].kind != "rotation6d":
            raise ValueError(f"modality {stream.modality!r} must be rotation6d to be mirrored")
        dims.add(layout.dims[stream.modality])
    if len(dims) != 1:
        raise ValueError(f"streams of group {group!r} have different dims {sorted(dims)}")
    return dims.pop()


def to_canonical(values: np.ndarray | torch.Tensor, stream: Stream):
    """A stream's parameters as its tokenizer sees them (left hands mirrored into right hands)."""
    if not stream.mirrored:
        return values
    tensor = torch.as_tensor(values)
    out = mirror_rotations(tensor)
    return out.numpy() if isinstance(values, np.ndarray) else out


from_canonical = to_canonical  # mirroring is its own inverse


def pad_to_multiple(x: torch.Tensor, multiple: int, minimum: int = 0) -> torch.Tensor:
    """(B, T, D) -> (B, T', D), T' = max(minimum, ceil(T / multiple) * multiple), last frame repeated."""
    if x.shape[1] == 0:
        raise ValueError("cannot tokenise an empty sequence (0 frames)")
    target = max(minimum, -(-x.shape[1] // multiple) * multiple)
    if target == x.shape[1]:
        return x
    return torch.cat([x, x[:, -1:].expand(-1, target - x.shape[1], -1)], dim=1)


def clip_sequences(params: dict[str, np.ndarray], group: str, clip_id: str = "?") -> list[np.ndarray]:
    """The canonical (T, D) float32 sequences of one clip for a group (two for hands)."""
    out = []
    for stream in GROUPS[group]:
        values = np.asarray(params[stream.modality], dtype=np.float32)
        if values.ndim != 2 or values.shape[0] == 0:
            raise ValueError(f"clip {clip_id!r}, modality {stream.modality!r}: expected (T>0, D), got {values.shape}")
        if not np.isfinite(values).all():
            raise ValueError(f"clip {clip_id!r}, modality {stream.modality!r}: contains NaN or inf")
        out.append(np.ascontiguousarray(to_canonical(values, stream), dtype=np.float32))
    return out


def normalisation(sequences: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-dim mean and std over every frame of ``sequences`` -> ((D,), (D,))."""
    frames = np.concatenate(sequences, axis=0).astype(np.float64)
    return torch.from_numpy(frames.mean(0)).float(), torch.from_numpy(frames.std(0)).float()


class WindowSampler:
    """``window``-frame crops of each sequence in batches: ``per_sequence`` random crops per sequence and
    epoch, or (``per_sequence = 0``) ``ceil(T / window)`` crops tiling it from a random offset (every frame
    in at least one crop).

    Everything random is a function of ``(seed, epoch)``, so an epoch can be replayed exactly (resume).
    With ``world_size > 1`` rank ``r`` gets every ``world_size``-th item of the epoch's permutation, the
    permutation wrapped round so that every rank gets ``ceil(N / world_size)`` items (DDP steps in lockstep).
    """

    def __init__(self, sequences: Sequence[np.ndarray], window: int, batch_size: int, per_sequence: int = 1,
                 seed: int = 0, rank: int = 0, world_size: int = 1):
        if not sequences:
            raise ValueError("no training sequences: the shards hold no clips for this group")
        if window < 1 or batch_size < 1 or per_sequence < 0:
            raise ValueError(f"window ({window}) and batch_size ({batch_size}) must be >= 1 and windows_per_clip "
                             f"({per_sequence}) >= 0 (0 = as many as cover each clip)")
        self.sequences = list(sequences)
        self.window, self.batch_size, self.per_sequence = window, batch_size, per_sequence
        self.seed, self.rank, self.world_size = seed, rank, world_size
        # crops per sequence and epoch
        self.counts = (np.full(len(self.sequences), per_sequence) if per_sequence else
                       np.array([-(-len(s) // window) for s in self.sequences]))

    def __len__(self) -> int:
        items = -(-int(self.counts.sum()) // self.world_size)
        return -(-items // self.batch_size)

    def crops(self, epoch: int) -> tuple[np.ndarray, np.ndarray]:
        """The epoch's crops in batch order: (N,) sequence index and (N,) start frame."""
        rng = np.random.default_rng([self.seed, epoch])
        if self.per_sequence:
            items = np.tile(np.arange(len(self.sequences)), self.per_sequence)
            items = items[rng.permutation(len(items))]
            fractions = rng.random(len(items))
            lengths = np.array([len(self.sequences[i]) for i in items])
            return items, (fractions * np.maximum(lengths - self.window + 1, 1)).astype(np.int64)
        items, starts = [], []
        for i, (seq, n) in enumerate(zip(self.sequences, self.counts)):
            # n windows span n * window >= T frames; a random shift within the slack, the ends clamped
            shift = int(rng.integers(0, n * self.window - len(seq) + 1))
            items.append(np.full(n, i))
            starts.append(np.clip(np.arange(n) * self.window - shift, 0, max(len(seq) - self.window, 0)))
        order = rng.permutation(int(self.counts.sum()))
        return np.concatenate(items)[order], np.concatenate(starts)[order]

    def epoch(self, epoch: int) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """Yields (x (B, W, D), mask (B, W) bool) batches."""
        items, starts = self.crops(epoch)
        # equal step counts on every rank (DDP): the permutation is wrapped round to a multiple of world_size, so
        # a rank short of items (or with none: fewer items than ranks) takes the permutation's first ones again
        per_rank = -(-len(items) // self.world_size)
        mine = np.arange(self.rank, per_rank * self.world_size, self.world_size) % len(items)
        for b in range(0, len(mine), self.batch_size):
            xs, masks = [], []
            for k in mine[b: b + self.batch_size]:
                seq = self.sequences[items[k]]
                start = int(starts[k])
                crop = seq[start: start + self.window]
                mask = np.zeros(self.window, dtype=bool)
                mask[: len(crop)] = True
                if len(crop) < self.window:
                    crop = np.concatenate([crop, np.repeat(crop[-1:], self.window - len(crop), axis=0)])
                xs.append(crop)
                masks.append(mask)
            yield torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(masks))
