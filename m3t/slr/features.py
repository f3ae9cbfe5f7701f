"""The probe's input: hidden states of the FROZEN tokenizer encoders (M3T App. 0.D.3), one sequence per stream.

Each stream of a trimmed clip goes through its group's encoder as the tokenizers see it (left hands mirrored
into the shared hand tokenizer, :func:`m3t.tokenizers.data.clip_sequences`), edge-padded to a multiple of the
downsampling, and :meth:`MotionTokenizer.hidden` gives the features just before the latent projection that
feeds FSQ (width W). The encoders are frozen three ways: ``requires_grad`` off, always in eval mode, and run
under ``no_grad``; the features are computed once per clip and cached (the probe never backpropagates into
them). Only the streams a variant uses are encoded: the face-less probe never runs the face encoder. Training
holds its splits' features (:func:`build_examples`); evaluation encodes a batch at a time and lets the features
go once every probe has scored them (:func:`iter_examples`, :func:`example_batches`), so its memory does not grow
with the split.

Axis legend: T frames, N = ceil(T / downsample) token steps, W encoder width.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from m3t.body.protocol import STREAM_ORDER
from m3t.corpora.clip import Clip
from m3t.shards.schema import FittedClip
from m3t.slr.trim import ActiveWindow, ClipTooShortError, Trimmer
from m3t.tokenizers.data import GROUPS, clip_sequences, pad_to_multiple
from m3t.tokenizers.vae import MotionTokenizer


def variant_streams(variant: str) -> tuple[str, ...]:
    """The streams a probe variant reads, in :data:`STREAM_ORDER`: ``full`` all four, ``no_face`` without face."""
    if variant == "full":
        return STREAM_ORDER
    if variant == "no_face":
        return tuple(s for s in STREAM_ORDER if s != "face")
    raise ValueError(f"probe variant {variant!r} unknown; allowed: full, no_face")


class FrozenEncoders(nn.Module):
    """The tokenizers' encoders, frozen: ``(T, D)`` params of a clip -> ``(N, W)`` features per stream."""

    def __init__(self, tokenizers: dict[str, MotionTokenizer]):
        super().__init__()
        missing = [g for g in GROUPS if g not in tokenizers]
        if missing:
            raise ValueError(f"the probe needs the tokenizers of groups {list(GROUPS)}; missing {missing}")
        self.tokenizers = nn.ModuleDict({g: tokenizers[g] for g in GROUPS})
        widths = {m.cfg.width for m in self.tokenizers.values()}
        factors = {m.cfg.downsample for m in self.tokenizers.values()}
        if len(widths) != 1 or len(factors) != 1:
            raise ValueError(f"the tokenizers disagree on width {sorted(widths)} or downsampling {sorted(factors)}; "
                             "the probe interleaves their features per time step, so they must agree")
        self.width, self.downsample = widths.pop(), factors.pop()
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> FrozenEncoders:
        return super().train(False)  # frozen means eval mode, whatever a caller asks

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    @torch.no_grad()
    def forward(self, params: dict[str, np.ndarray], streams: Sequence[str],
                clip_id: str = "?") -> dict[str, torch.Tensor]:
        """Features (N, W) of each stream in ``streams``; groups no stream asks for are never run."""
        unknown = [s for s in streams if s not in STREAM_ORDER]
        if unknown:
            raise ValueError(f"streams {unknown} unknown; allowed: {list(STREAM_ORDER)}")
        out = {}
        for group, group_streams in GROUPS.items():
            if not any(s.name in streams for s in group_streams):
                continue
            model = self.tokenizers[group]
            for stream, values in zip(group_streams, clip_sequences(params, group, clip_id)):
                if stream.name in streams:
                    x = pad_to_multiple(torch.from_numpy(values)[None].to(self.device), self.downsample)  # (1, T', D)
                    out[stream.name] = model.hidden(x)[0]  # (N, W)
        return {s: out[s] for s in streams}


@dataclass(frozen=True)
class Example:
    """One labelled clip as the probe sees it: features per stream (N, W), its class index and window."""

    clip: Clip
    target: int
    features: dict[str, torch.Tensor]
    window: ActiveWindow

    @property
    def steps(self) -> int:
        return next(iter(self.features.values())).shape[0]


def build_examples(clips: Iterable[FittedClip], class_index: dict[int, int], trimmer: Trimmer,
                   encoders: FrozenEncoders, streams: Sequence[str], max_steps: int,
                   dtype: torch.dtype = torch.float32, bad_clips: str = "error",
                   skipped: list[dict] | None = None) -> list[Example]:
    """Trim and encode every clip (labels mapped through ``class_index``), held in memory: what training reads
    every epoch. A clip too short for the window or with more than ``max_steps`` steps raises naming it, or with
    ``bad_clips="skip"`` is listed in ``skipped`` (:func:`iter_examples`, one clip at a time)."""
    return list(iter_examples(clips, class_index, trimmer, encoders, streams, max_steps, dtype, bad_clips, skipped))


def iter_examples(clips: Iterable[FittedClip], class_index: dict[int, int], trimmer: Trimmer,
                  encoders: FrozenEncoders, streams: Sequence[str], max_steps: int,
                  dtype: torch.dtype = torch.float32, bad_clips: str = "error",
                  skipped: list[dict] | None = None) -> Iterator[Example]:
    """:func:`build_examples` one clip at a time, in order: a clip is read from ``clips`` when the example
    before it has been taken, so an evaluation that lets each go holds one clip's motion and features."""
    if trimmer.cfg.min_frames < encoders.downsample:
        raise ValueError(f"slr.trim.min_frames={trimmer.cfg.min_frames} is below the tokenizers' downsampling "
                         f"({encoders.downsample} frames per token); raise it to at least {encoders.downsample}")
    for fitted in clips:
        clip = fitted.clip
        try:
            if clip.label not in class_index:
                raise KeyError(f"clip {clip.id!r}: label {clip.label} is not among the probe's classes")
            params, window = trimmer(fitted.params, fitted.identity, clip.id)
            steps = -(-window.kept // encoders.downsample)
            if steps > max_steps:
                raise ValueError(f"clip {clip.id!r} keeps {window.kept} frames = {steps} token steps after trimming, "
                                 f"more than slr.max_steps={max_steps}; raise slr.max_steps")
            feats = {k: v.to("cpu", dtype) for k, v in encoders(params, streams, clip.id).items()}
        except (ClipTooShortError, ValueError, KeyError) as exc:
            if bad_clips != "skip":
                raise
            if skipped is not None:
                skipped.append({"clip_id": clip.id, "split": clip.split, "reason": f"{type(exc).__name__}: {exc}"})
            continue
        yield Example(clip, class_index[clip.label], feats, window)


def example_batches(examples: Iterable[Example], batch_size: int) -> Iterator[list[Example]]:
    """Consecutive batches of ``batch_size`` examples (the last shorter), drawn from ``examples`` as needed."""
    batch: list[Example] = []
    for example in examples:
        batch.append(example)
        if len(batch) == batch_size:
            yield batch
            batch = []
    if batch:
        yield batch


def without_features(example: Example) -> Example:
    """``example`` once its features are used: clip, target and window kept (what predictions are reported with)."""
    return Example(example.clip, example.target, {}, example.window)
