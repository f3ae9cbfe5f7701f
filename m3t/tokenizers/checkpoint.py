"""Self-describing tokenizer checkpoints: ``{format, group, config, state_dict, epoch, step, data_version,
metrics[, train_state]}``; a tokenizer is rebuilt from the file alone and loaded with ``weights_only=True``.

``train_state`` (optimizer, scheduler, RNG, history) is present only in the resumable ``last`` checkpoint.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from m3t.checkpoints import CheckpointRecord, checkpoint_payload, read_checkpoint, save_checkpoint
from m3t.dataclass_io import build_dataclass
from m3t.tokenizers.config import VAEConfig
from m3t.tokenizers.vae import MotionTokenizer

FORMAT = "m3t-tokenizer-v1"


@dataclass(frozen=True)
class LoadedTokenizer(CheckpointRecord):
    model: MotionTokenizer
    group: str


def config_to_dict(cfg: VAEConfig) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(cfg).items()}


def save_tokenizer(path: str | os.PathLike, model: MotionTokenizer, group: str, epoch: int, step: int,
                   data_version: str, metrics: dict[str, float], train_state: dict[str, Any] | None = None) -> Path:
    return save_checkpoint(path, checkpoint_payload(
        FORMAT, model, epoch, step, data_version, metrics, None, train_state,
        group=group,
        config=config_to_dict(model.cfg),
    ))


def load_tokenizer(path: str | os.PathLike, device: str | torch.device = "cpu") -> LoadedTokenizer:
    payload = read_checkpoint(path, FORMAT, "tokenizer", "train-tokenizers", device)
    model = MotionTokenizer(build_dataclass(VAEConfig, payload["config"], "config")).to(device)
    model.load_state_dict(payload["state_dict"])
    model.eval()
    return LoadedTokenizer.read(payload, model=model, group=payload["group"])
