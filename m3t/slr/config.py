"""Configs of the recognition probe (params.yaml ``slr``, ``slr_train``, ``slr_evaluate``). Plain dataclasses:
importing them costs no model code.

Defaults are sized for a CPU; the paper's probe (3 layers, 4 heads, width 1024 = the tokenizer width, Adam,
cosine 2e-4 -> 1e-6, 100 epochs, batch 64, label smoothing 0.1; App. 0.D.3) is the ``paper`` preset.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

VARIANTS = ("full", "no_face")
"""``full``: body, left hand, right hand and face features; ``no_face``: the same probe without the face
stream (Tab. 4's ablation): its features are never computed nor put into the sequence."""


@dataclass(frozen=True)
class TrimConfig:
    """Active-window trimming (M3T Sec. 3.4, following SignRep): a frame is active when a wrist is raised
    more than ``height_threshold`` above its rest height or lies more than ``displacement_threshold`` from its
    rest position, both in shoulder widths of the body model's rest pose under the clip's identity. Kept:
    the first to the last active frame, ``margin`` frames more on each side, never fewer than ``min_frames``.

    ``reference``: where a wrist rests. ``clip_rest`` (default): the wrist's lowest frame in the clip (a
    signer's own resting hands); ``body_rest``: the body model's rest pose itself. The body models' rest poses
    are A- or T-poses (Anny: wrists 0.45 m out to the side), so ``body_rest`` puts resting hands already
    ~0.9 shoulder widths "displaced" and only its height test separates rest from signing.
    """

    enabled: bool = True
    reference: Literal["clip_rest", "body_rest"] = "clip_rest"
    height_threshold: float = 0.2  # shoulder widths above the rest height
    displacement_threshold: float = 0.4  # shoulder widths from the rest position
    margin: int = 2  # frames kept before the first and after the last active frame
    min_frames: int = 16  # a trimmed clip keeps at least this many frames (>= the tokenizers' downsample)

    def __post_init__(self) -> None:
        if self.height_threshold <= 0 or self.displacement_threshold <= 0:
            raise ValueError("height_threshold and displacement_threshold must be > 0 (in shoulder widths)")
        if self.margin < 0 or self.min_frames < 1:
            raise ValueError(f"margin must be >= 0 and min_frames >= 1, got {self.margin}, {self.min_frames}")


@dataclass(frozen=True)
class SLRConfig:
    """params.yaml ``slr``: which corpus is recognised, the probe (its width is the frozen encoders' width W)
    and the trimming. Paper: 3 layers, 4 heads, width 1024 -> ~26M parameters on top of the encoders."""

    corpus: str = "synthetic"  # a corpus with isolated, labelled clips (data.shards_root/<corpus>)
    layers: int = 3
    heads: int = 4
    ffn_mult: int = 2  # FFN width = ffn_mult * W; 2 (2048 at W = 1024, torch's default) matches the paper's 26M
    head_hidden: int = 0  # 0: one linear layer on the pooled features (the paper's "linear MLP head")
    dropout: float = 0.1
    max_steps: int = 128  # token steps (4 frames each) a clip may have after trimming (learned positions)
    pooling: Literal["mean", "cls"] = "mean"  # mean over valid positions, or a learned CLS token
    trim: TrimConfig = field(default_factory=TrimConfig)

    def __post_init__(self) -> None:
        if min(self.layers, self.heads, self.ffn_mult, self.max_steps) < 1 or self.head_hidden < 0:
            raise ValueError("layers, heads, ffn_mult and max_steps must be >= 1, head_hidden >= 0")


@dataclass(frozen=True)
class SLRTrainConfig:
    """``slr_train`` section; the paper's Adam, cosine 2e-4 -> 1e-6, 100 epochs, batch 64 are in the paper preset."""

    cache_dir: str = ".cache/slr"  # best + resumable last checkpoints, named by the run key
    variants: tuple[str, ...] = VARIANTS
    epochs: int = 60
    batch_size: int = 16
    lr: float = 5e-4
    min_lr: float = 1e-6
    warmup_epochs: int = 0
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    label_smoothing: float = 0.1
    eval_every: int = 1
    seed: int = 0
    device: str = "auto"
    precision: Literal["fp32", "bf16"] = "fp32"
    feature_dtype: Literal["float32", "float16"] = "float32"  # cached encoder features (float16 halves memory)
    bad_clips: Literal["error", "skip"] = "error"  # a clip too short / too long: stop, or list it and go on
    workers: int = 2  # CPU: the variants trained in this many processes sharing the threads (1 = one after
    # another, as on a GPU)

    def __post_init__(self) -> None:
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown or not self.variants or len(set(self.variants)) != len(self.variants):
            raise ValueError(f"variants {list(self.variants)}: expected distinct names of {list(VARIANTS)}")
        if self.workers < 1:
            raise ValueError(f"slr_train.workers: expected >= 1, got {self.workers}")


@dataclass(frozen=True)
class SLREvaluateConfig:
    """``slr_evaluate`` section: the split scored, the variants (checkpoints of train-slr) and the bootstrap."""

    split: str = "test"
    variants: tuple[str, ...] = VARIANTS
    batch_size: int = 64
    bootstrap: int = 1000  # resamples of the test clips for the percentile confidence intervals
    confidence: float = 0.95
    seed: int = 0
    device: str = "auto"
    bad_clips: Literal["error", "skip"] = "error"

    def __post_init__(self) -> None:
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown or not self.variants:
            raise ValueError(f"variants {list(self.variants)}: expected names of {list(VARIANTS)}")
        if not 0 < self.confidence < 1 or self.bootstrap < 1:
            raise ValueError("confidence must be in (0, 1) and bootstrap >= 1")
