"""Configs of the motion tokenizers (params.yaml ``tokenizer`` and ``tokenizer_train``) and the
self-describing :class:`VAEConfig` a checkpoint rebuilds one tokenizer from. Plain dataclasses: importing
them costs no model code (so ``m3t.config`` and DVC's deps stay narrow)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

Quantizer = Literal["fsq", "vq", "vq_ema", "vq_plain"]
# the quantisers of the Tab. 3 ablation (m3t.tokenizers.vq says how the three VQs differ)
QUANTIZERS: dict[str, str] = {
    "fsq": "FSQ (M3T)",
    "vq": "VQ, EMA + dead-code reset (T2M-GPT)",
    "vq_ema": "VQ, EMA without reset",
    "vq_plain": "VQ-VAE, learned codebook (no EMA, no reset)",
}


@dataclass(frozen=True)
class VAEConfig:
    """Everything needed to rebuild one tokenizer; ``input_dim`` and ``levels`` come from the data."""

    input_dim: int
    levels: tuple[int, ...]
    quantizer: Quantizer = "fsq"
    width: int = 1024
    depth: int = 6
    down_stages: int = 2
    dilation_growth: int = 3
    vq_code_dim: int = 512
    vq_decay: float = 0.99
    vq_beta: float = 0.02

    @property
    def codebook_size(self) -> int:
        return math.prod(self.levels)

    @property
    def latent_dim(self) -> int:
        return len(self.levels) if self.quantizer == "fsq" else self.vq_code_dim

    @property
    def downsample(self) -> int:
        return 2 ** self.down_stages


@dataclass(frozen=True)
class TokenizerConfig:
    """``tokenizer`` section: the architecture shared by the three groups (App. 0.D.1) and the quantiser."""

    quantizer: Quantizer = "fsq"
    width: int = 128
    depth: int = 6
    down_stages: int = 2
    dilation_growth: int = 3
    levels_body: tuple[int, ...] = (5, 5, 4)
    levels_hand: tuple[int, ...] = (6, 6, 5)
    levels_face: tuple[int, ...] = (6, 6, 6)
    vq_code_dim: int = 64
    vq_decay: float = 0.99
    vq_beta: float = 0.02

    def vae_config(self, group: str, input_dim: int) -> VAEConfig:
        levels = {"body": self.levels_body, "hand": self.levels_hand, "face": self.levels_face}[group]
        return VAEConfig(input_dim=input_dim, levels=levels, quantizer=self.quantizer, width=self.width,
                         depth=self.depth, down_stages=self.down_stages, dilation_growth=self.dilation_growth,
                         vq_code_dim=self.vq_code_dim, vq_decay=self.vq_decay, vq_beta=self.vq_beta)


@dataclass(frozen=True)
class TokenizerTrainConfig:
    """``tokenizer_train`` section; defaults = params.yaml (the paper's Adam 1e-4, 100 epochs, batch 8, 25 warm-up
    epochs, floor 1e-6 are in ``presets/paper.yaml``)."""

    cache_dir: str = ".cache/tokenizers"
    groups: tuple[str, ...] = ("body", "hand", "face")
    extra_face_shards: tuple[str, ...] = ()  # face-only shards (e.g. MEAD) added to the face training set
    epochs: int = 30
    warmup_epochs: int = 5
    lr: float = 1e-3
    min_lr: float = 1e-6
    batch_size: int = 16
    window: int = 64
    windows_per_clip: int = 4  # random windows per clip and epoch; 0 = ceil(frames / window), covering the clip
    eval_every: int = 5
    val_max_frames: int = 2000  # dev frames measured per evaluation (and test frames in the report); 0 = all
    seed: int = 0
    device: str = "auto"
    precision: Literal["fp32", "bf16"] = "fp32"
    # CPU only: train the groups in this many processes at once, sharing the threads (1 = one group after
    # another on every thread). Small convolutions use two threads poorly: on 2 cores, 2 processes of one thread
    # finished the embedded stage 1.6x sooner (benchmarks/bench_stage_workers.py --stages train-tokenizers).
    group_workers: int = 2
