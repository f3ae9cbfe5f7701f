"""Configs of the skeletal graph production models (params.yaml ``sgsa``, ``sgsa_train``, ``sgsa_evaluate``).
Plain dataclasses: importing them costs no model code.

One model family covers both systems of SGSA (Saunders et al. 2022) Tab. 1-3: ``decoder_layers = L >= 1``
Skeletal Graph Self-Attention layers (the paper's model), ``decoder_layers = 0`` the Progressive Transformers
baseline (``standard_layers`` standard self-attention decoder layers, as the paper compares). Defaults are small
CPU sizes for the embedded corpus; the paper's values are in the comments and in ``m3t/presets/paper.yaml``.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal


SYSTEMS = ("pt", "sgsa")


@dataclass(frozen=True)
class SGSAConfig:
    """params.yaml ``sgsa``. SGSA Sec. 5 "Implementation Details": spoken-language encoder 2 layers, 4 heads,
    width 256; graphical decoder 5 SGSA layers, 4 heads, width S (291 = 290 joint coordinates + 1 counter);
    gloss supervision on the encoder; about 9M trainable parameters."""

    skeleton: Literal["body", "holistic"] = "body"  # body: the body model's metric keypoints (12 upper body + 2 x 21
    # hand points) posed from the fitted shards; holistic: MediaPipe-Holistic points of .pose corpora
    face_points: bool = False  # add the graph's face points (mouth, eyes, brows) to the skeleton
    encoder_layers: int = 2
    encoder_heads: int = 4
    encoder_width: int = 64
    encoder_ffn: int = 128
    decoder_layers: int = 2  # L: SGSA layers; 0 = Progressive Transformers (standard_layers standard layers)
    decoder_heads: int = 2  # h: each SGSA head has the full width S; the output projection is h x S -> S
    temporal_adjacency: int = 1  # N: frames each SGSA query attends back to (band on the causal mask); 0 = inf
    standard_layers: int = 4  # decoder layers of the L = 0 baseline (SGSA Tab. 1 "0 (4 SA)")
    standard_width: int = 64  # the baseline decoder's width (frames embedded S -> width, as in PT)
    standard_ffn: int = 128
    dropout: float = 0.1
    max_frames: int = 300  # longest clip trained on (longer ones are cut, counted) and longest generation
    max_text_tokens: int = 64  # longer training sentences are skipped with the reason
    gloss_weight: float = 1.0  # weight of the gloss CTC loss on the encoder output; 0 = no gloss head
    min_token_frequency: int = 1  # train-split words seen fewer times become <unk>
    min_frames: int = 4  # counter decoding never ends a sequence before this frame (m3t.sgsa.model.CounterStop)

    def __post_init__(self) -> None:
        # counts first: a head count of 0 is named, not a division by zero in the width checks below
        for key in ("encoder_layers", "encoder_heads", "decoder_heads", "standard_layers", "max_frames",
                    "max_text_tokens", "min_token_frequency", "min_frames"):
            if getattr(self, key) < 1:
                raise ValueError(f"sgsa.{key}: expected >= 1, got {getattr(self, key)}")
        if self.encoder_width % self.encoder_heads:
            raise ValueError(f"sgsa.encoder_width {self.encoder_width} is not divisible by encoder_heads "
                             f"{self.encoder_heads}")
        if self.decoder_layers == 0 and self.standard_width % self.decoder_heads:
            raise ValueError(f"sgsa.standard_width {self.standard_width} is not divisible by decoder_heads "
                             f"{self.decoder_heads}")
        if self.decoder_layers < 0 or self.temporal_adjacency < 0:
            raise ValueError(f"sgsa.decoder_layers / temporal_adjacency: expected >= 0, got {self.decoder_layers} / "
                             f"{self.temporal_adjacency}")
        if self.gloss_weight < 0:
            raise ValueError(f"sgsa.gloss_weight: expected >= 0, got {self.gloss_weight}")

    @property
    def system(self) -> str:
        """``"PT"`` (L = 0) or ``"SGSA"``."""
        return "PT" if self.decoder_layers == 0 else "SGSA"

    @property
    def band(self) -> float:
        """N as a number: ``math.inf`` for 0 (plain causal attention)."""
        return math.inf if self.temporal_adjacency == 0 else float(self.temporal_adjacency)

    def for_system(self, system: str) -> SGSAConfig:
        """``pt``: this config as the Progressive Transformers baseline (L = 0, N = inf); ``sgsa``: unchanged."""
        if system not in SYSTEMS:
            raise ValueError(f"system {system!r} unknown; allowed: {', '.join(SYSTEMS)}")
        return dataclasses.replace(self, decoder_layers=0, temporal_adjacency=0) if system == "pt" else self

    @property
    def variant(self) -> str:
        """``PT``, ``SGSA L=5 N=inf``, ``SGSA L=5 N=1`` ...: the row name in the tables."""
        if self.decoder_layers == 0:
            return "PT"
        n = "inf" if self.temporal_adjacency == 0 else str(self.temporal_adjacency)
        return f"SGSA L={self.decoder_layers} N={n}"


@dataclass(frozen=True)
class SGSATrainConfig:
    """params.yaml ``sgsa_train``. SGSA Sec. 5 / Progressive Transformers: Xavier initialisation, Adam (default
    betas) at 1e-3, Gaussian noise augmentation with noise rate 5 (x the per-dimension std of the previous
    epoch's prediction error, here capped at ``noise_cap`` x the coordinate's own std over the train split),
    ReduceLROnPlateau on the validation figure, the checkpoint with the lowest dev DTW-JPE x length penalty kept
    (PT selects on DTW; :data:`m3t.sgsa.evaluate.SELECTION_METRIC`)."""

    cache_dir: str = ".cache/sgsa"  # best + resumable last checkpoints by run key
    systems: tuple[str, ...] = ("pt", "sgsa")  # pt: the sgsa section with decoder_layers 0 (Progressive
    # Transformers); sgsa: the section as configured. Each is trained into <models>/sgsa/<system>.pt
    epochs: int = 30
    batch_size: int = 8
    lr: float = 1e-3
    lr_patience: int = 5  # validations without a lower dev DTW-JPE before the LR is cut
    lr_factor: float = 0.7
    min_lr: float = 2e-4
    noise_rate: float = 5.0  # 0 = no noise augmentation
    noise_cap: float = 1.0  # the noise's std never exceeds this x the coordinate's std over the train split (the
    # papers' rule feeds back on itself: more noise, larger errors, more noise; 0 = no cap)
    counter_weight: float = 1.0  # extra weight on the counter's squared error: 1 gives the counter about as much of
    # the loss as all coordinates together; 0 = the papers' plain MSE, where the counter is 1 of S coordinates and
    # was never learned on the embedded corpus
    grad_clip: float = 5.0  # 0 = no clipping
    eval_every: int = 5
    eval_max_clips: int = 16  # dev clips generated at each validation (0 = all)
    seed: int = 0
    device: str = "auto"
    workers: int = 2  # CPU: the systems trained in this many processes sharing the threads (1 = one after
    # another, as on a GPU)

    def __post_init__(self) -> None:
        for key in ("epochs", "batch_size", "eval_every", "workers"):
            if getattr(self, key) < 1:
                raise ValueError(f"sgsa_train.{key}: expected >= 1, got {getattr(self, key)}")
        if not 0 < self.lr_factor < 1:
            raise ValueError(f"sgsa_train.lr_factor: expected in (0, 1), got {self.lr_factor}")
        for key in ("noise_rate", "noise_cap", "counter_weight"):
            if getattr(self, key) < 0:
                raise ValueError(f"sgsa_train.{key}: expected >= 0, got {getattr(self, key)}")
        unknown = [s for s in self.systems if s not in SYSTEMS]
        if unknown or not self.systems or len(set(self.systems)) != len(self.systems):
            raise ValueError(f"sgsa_train.systems {list(self.systems)}: expected distinct names of {list(SYSTEMS)}")


@dataclass(frozen=True)
class SGSAEvaluateConfig:
    """params.yaml ``sgsa_evaluate``: what evaluate-sgsa produces and scores."""

    splits: tuple[str, ...] = ("dev", "test")
    counter: Literal["predicted", "ground_truth"] = "predicted"  # ground_truth: the true length (parity with
    # published PT numbers only; never the default)
    backtranslate: bool = True  # score sentence clips with the frozen skeleton back-translation judge
    render_clips: int = 2  # side-by-side skeleton videos (reference / PT / SGSA / SMLM) of the first test clips
    batch_size: int = 16
    device: str = "auto"

    def __post_init__(self) -> None:
        if self.counter not in ("predicted", "ground_truth"):
            raise ValueError(f"sgsa_evaluate.counter {self.counter!r} unknown; allowed: predicted, ground_truth")
        unknown = [s for s in self.splits if s not in ("train", "dev", "test")]
        if unknown or not self.splits:
            raise ValueError(f"sgsa_evaluate.splits {list(self.splits)}: expected a non-empty subset of train, dev, "
                             "test")
