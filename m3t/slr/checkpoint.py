"""Self-describing probe checkpoints: ``{format, variant, config, dims, classes, class_names, tokenizers,
state_dict, epoch, step, data_version, metrics, train_config[, train_state]}``, loaded with ``weights_only=True``.

``config`` is the ``slr`` section the probe was trained with, trimming included (evaluation trims the same
way); ``dims`` holds the encoder width, the number of classes and the streams read; ``classes`` / ``class_names``
map output index -> corpus label id / gloss; ``tokenizers`` holds the digests of the frozen tokenizer files
whose features the probe was trained on (evaluation refuses other tokenizers). ``train_state`` (optimizer,
scheduler, RNG, history) is present only in the resumable ``last`` checkpoint.
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
from m3t.slr.config import SLRConfig
from m3t.slr.model import ProbeDims, SLRProbe

FORMAT = "m3t-slr-v1"


@dataclass(frozen=True)
class ProbeMeta:
    """What a probe's outputs mean and which inputs it expects, beyond its config and dims."""

    variant: str  # full | no_face
    classes: tuple[int, ...]  # output index -> corpus label id
    class_names: tuple[str, ...]  # output index -> gloss
    tokenizers: dict[str, str]  # tokenizer group -> digest of the frozen checkpoint file


@dataclass(frozen=True)
class LoadedSLR(CheckpointRecord):
    model: SLRProbe
    meta: ProbeMeta


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value


def save_slr(path: str | os.PathLike, model: SLRProbe, meta: ProbeMeta, epoch: int, step: int, data_version: str,
             metrics: dict[str, float], train_config: dict | None = None,
             train_state: dict[str, Any] | None = None) -> Path:
    return save_checkpoint(path, checkpoint_payload(
        FORMAT, model, epoch, step, data_version, metrics, _plain(dict(train_config or {})), train_state,
        variant=meta.variant,
        config=_plain(dataclasses.asdict(model.cfg)),
        dims=_plain(dataclasses.asdict(model.dims)),
        classes=[int(c) for c in meta.classes],
        class_names=[str(n) for n in meta.class_names],
        tokenizers=dict(meta.tokenizers),
    ))


def config_from_dict(raw: dict) -> SLRConfig:
    return build_dataclass(SLRConfig, raw, "config")


def load_slr(path: str | os.PathLike, device: str | torch.device = "cpu") -> LoadedSLR:
    payload = read_checkpoint(path, FORMAT, "SLR probe", "train-slr", device)
    model = SLRProbe(config_from_dict(payload["config"]), build_dataclass(ProbeDims, payload["dims"], "dims"))
    model.load_state_dict(payload["state_dict"])
    model.to(device).eval()
    meta = ProbeMeta(payload["variant"], tuple(payload["classes"]), tuple(payload["class_names"]),
                     dict(payload["tokenizers"]))
    return LoadedSLR.read(payload, model=model, meta=meta)
