"""Configs of the back-translation models (params.yaml ``backtranslation`` and ``backtranslation_train``). Plain
dataclasses: importing them costs no model code.

Defaults are small CPU sizes for the embedded corpus; the values of the papers are in the comments (M3T App.
0.D.4 for the recipe, SL-T / SignSparK_BT ``configs/*.yaml`` for the architecture it builds on).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class BackTranslationConfig:
    """params.yaml ``backtranslation``: the sign-to-text model (one per sign language), what it reads and how it
    decodes. SL-T / SignSparK_BT: 3 + 3 layers, 8 heads, width 512, feed-forward 1024 (SL-T's paper 2048),
    dropout 0.1, at most 300 frames, 30 decoded tokens."""

    input_layout: Literal["model", "smplx240"] = "model"  # "model": every modality of the shards, STREAM_ORDER;
    # "smplx240": SignSparK_BT's 240-d SMPL-X 6D input (body 60 + hands 90 + 90; needs SMPL-X joint names)
    d_model: int = 64
    encoder_layers: int = 2
    decoder_layers: int = 2
    attention_heads: int = 4
    ffn_dim: int = 256
    dropout: float = 0.1
    max_frames: int = 400  # longer clips are cut to their first max_frames frames (SignSparK_BT: 300)
    max_text_tokens: int = 40  # longest decoded sentence; longer training sentences are skipped, with the reason
    gloss_ctc_weight: float = 1.0  # weight of the gloss CTC head on the encoder; 0 = no head (SL-T: 5, SignSparK: 1)
    pseudo_glosses: bool = True  # derive glosses from the text where a corpus has none (How2Sign), for the CTC head
    min_token_frequency: int = 1  # train-split words seen fewer times become <unk>
    languages: tuple[str, ...] = ()  # sign languages to train / score; () = every language of the train split
    beam_size: int = 1  # decode-time: 1 = greedy; >1 = beam search (read by evaluation, not stored as a model choice)
    length_penalty: float = 1.0  # decode-time: beam length penalty alpha, ((5 + len) / 6) ** alpha (JoeyNMT)

    def __post_init__(self) -> None:
        # counts first: a head count of 0 is named, not a division by zero in the width check below
        for key in ("attention_heads", "encoder_layers", "decoder_layers", "max_frames", "max_text_tokens",
                    "beam_size", "min_token_frequency"):
            if getattr(self, key) < 1:
                raise ValueError(f"backtranslation.{key}: expected >= 1, got {getattr(self, key)}")
        if self.d_model % self.attention_heads:
            raise ValueError(f"backtranslation.d_model {self.d_model} is not divisible by attention_heads "
                             f"{self.attention_heads}")
        if self.gloss_ctc_weight < 0:
            raise ValueError(f"backtranslation.gloss_ctc_weight: expected >= 0, got {self.gloss_ctc_weight}")


@dataclass(frozen=True)
class BackTranslationTrainConfig:
    """params.yaml ``backtranslation_train``. M3T App. 0.D.4: Adam, lr 2.5e-4, batch 256 (128 for How2Sign),
    ReduceLROnPlateau on validation BLEU-4 (patience 10, factor 0.8), checkpoint with the best validation BLEU-4.
    SL-T's Adam betas (0.9, 0.998) and weight decay 1e-3; label smoothing 0.1 as SignSparK_BT. The defaults
    here (lr 1e-3, batch 16, 60 epochs) suit the tiny embedded corpus."""

    cache_dir: str = ".cache/backtranslation"  # best + resumable last checkpoints per language, by run key
    epochs: int = 60
    batch_size: int = 16
    lr: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.998)
    weight_decay: float = 1e-3
    lr_patience: int = 10  # evaluations without a better validation BLEU-4 before the LR is cut
    lr_factor: float = 0.8
    min_lr: float = 1e-6
    label_smoothing: float = 0.1
    grad_clip: float = 0.0  # 0 = no clipping
    eval_every: int = 5  # epochs between validations (the plateau patience counts validations)
    seed: int = 0
    device: str = "auto"
    precision: Literal["fp32", "bf16"] = "fp32"
    workers: int = 1  # CPU: the languages trained in this many processes sharing the threads; 1 (one after another,
    # as on a GPU): on the 2-core machine 2 gained nothing (0.97-0.98x, benchmarks/results/stage_workers.json)

    def __post_init__(self) -> None:
        for key in ("epochs", "batch_size", "eval_every", "workers"):
            if getattr(self, key) < 1:
                raise ValueError(f"backtranslation_train.{key}: expected >= 1, got {getattr(self, key)}")
        if not 0 < self.lr_factor < 1:
            raise ValueError(f"backtranslation_train.lr_factor: expected in (0, 1), got {self.lr_factor}")
