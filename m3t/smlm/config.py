"""Configs of the Sign Motion Language Model (params.yaml ``smlm``, ``smlm_train``, ``smlm_generate``). Plain
dataclasses: importing them costs no model code."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class GenerateConfig:
    """params.yaml ``smlm_generate``: what generate-smlm and evaluate-smlm read (folders: ``data``)."""

    split: str = "test"
    batch_size: int = 16
    render_clips: int = 2
    export_pose: bool = True
    backtranslate: bool = True  # evaluate-smlm also scores the generated motion with the back-translation judge
    # motion metric variant (m3t.metrics.motion): "m3t" = neck-rooted body, every embedded-default table;
    # "soke_exact" = SOKE's released evaluation (pelvis-rooted body, PA on all joints; body.model: smplfx only)
    motion_metric: Literal["m3t", "soke_exact"] = "m3t"


@dataclass(frozen=True)
class SMLMConfig:
    """Model and vocabulary sizes (params section ``smlm``). Paper: mbart-large-cc25, 12 + 12 layers, 1024."""

    d_model: int = 128
    encoder_layers: int = 3
    decoder_layers: int = 3
    attention_heads: int = 4
    ffn_dim: int = 512
    dropout: float = 0.1
    max_text_tokens: int = 64  # longer input text is refused with a clear error
    max_motion_tokens: int = 256  # motion steps per clip (4 frames each); longer clips are skipped in training
    text_vocab_size: int = 1000  # upper bound for the tokenizer trained on the corpus text
    text_model_path: str = ""  # local mBART folder with sentencepiece.bpe.model; "" = train on the corpus
    pretrained_path: str = ""  # local mbart-large-cc25 weights; "" = random init
    reduce_text_vocab: bool = False  # keep only the pretrained text ids the training text uses (paper: 396M)


@dataclass(frozen=True)
class SMLMTrainConfig:
    """``smlm_train`` section; defaults = params.yaml (the paper's AdamW, cosine 2e-4 -> 1e-6, 200 epochs,
    batch 32 are in ``presets/paper.yaml``)."""

    cache_dir: str = ".cache/smlm"  # best + resumable last checkpoints, named by the run key
    epochs: int = 200
    batch_size: int = 8
    lr: float = 5e-4
    min_lr: float = 1e-6
    warmup_steps: int = 50
    weight_decay: float = 0.01
    grad_clip: float = 1.0
    translation_objective: bool = True
    translation_prob: float = 0.5
    # shared: each step is a translation batch with probability translation_prob, so production gets 1 - p of an
    # epoch's steps (the objective costs production updates: the ablation at equal epochs); added: every batch is a
    # production step and a translation step on the same batch follows with probability p / (1 - p) (p <= 0.5), so
    # production gets as many updates as without the objective (the ablation at equal production updates)
    translation_steps: Literal["shared", "added"] = "shared"
    label_smoothing: float = 0.0
    eval_every: int = 20
    eval_max_clips: int = 64  # dev clips scored per evaluation, first ones of the first corpus on; 0 = all
    seed: int = 0
    device: str = "auto"
    precision: Literal["fp32", "bf16"] = "fp32"

    def __post_init__(self) -> None:
        if self.translation_steps not in ("shared", "added"):
            raise ValueError(f"smlm_train.translation_steps {self.translation_steps!r} unknown; allowed: shared, added")
        if not 0.0 <= self.translation_prob <= 1.0:
            raise ValueError(f"smlm_train.translation_prob: expected in [0, 1], got {self.translation_prob}")
        if self.translation_steps == "added" and self.translation_prob > 0.5:
            raise ValueError(f"smlm_train.translation_prob {self.translation_prob} with translation_steps added: "
                             "expected <= 0.5 (at most one translation step per production step)")
