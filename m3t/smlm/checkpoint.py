"""Self-describing SMLM checkpoints: ``{format, config, dims, backbone_config, vocabulary, state_dict, epoch,
step, data_version, metrics, train_config[, train_state]}``. The model and its vocabulary (with the trained
SentencePiece model inside) are rebuilt from the file alone, loaded with ``weights_only=True``.
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
from m3t.smlm.config import SMLMConfig
from m3t.smlm.model import SignMotionLM, SMLMDims
from m3t.smlm.vocab import SignVocabulary

FORMAT = "m3t-smlm-v1"


@dataclass(frozen=True)
class LoadedSMLM(CheckpointRecord):
    model: SignMotionLM
    vocab: SignVocabulary


def save_smlm(path: str | os.PathLike, model: SignMotionLM, vocab: SignVocabulary, epoch: int, step: int,
              data_version: str, metrics: dict[str, float], train_config: dict | None = None,
              train_state: dict[str, Any] | None = None) -> Path:
    """``train_config``: the training settings, kept so evaluations can say which variant they measure;
    ``train_state``: what continues the run (:meth:`m3t.training.EpochTail.train_state`), ``last`` only."""
    return save_checkpoint(path, checkpoint_payload(
        FORMAT, model, epoch, step, data_version, metrics, dict(train_config or {}), train_state,
        config=dataclasses.asdict(model.cfg),
        dims=dataclasses.asdict(model.dims),
        backbone_config=model.backbone.config.to_dict(),
        vocabulary=vocab.to_dict(),
    ))


def load_smlm(path: str | os.PathLike, device: str | torch.device = "cpu") -> LoadedSMLM:
    payload = read_checkpoint(path, FORMAT, "SMLM", "train-smlm", device)
    vocab = SignVocabulary.from_dict(payload["vocabulary"])
    dims = build_dataclass(SMLMDims, payload["dims"], "dims")
    model = SignMotionLM(build_dataclass(SMLMConfig, payload["config"], "config"), dims,
                         backbone_config=payload["backbone_config"])
    model.load_state_dict(payload["state_dict"])
    model.to(device).eval()
    return LoadedSMLM.read(payload, model=model, vocab=vocab)
