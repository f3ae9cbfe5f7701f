"""Self-describing back-translation checkpoints, one per sign language: ``{format, language, config, dims, input,
text, text_vocabulary, gloss_vocabulary, gloss_source, state_dict, epoch, step, data_version, metrics,
train_config[, train_state]}``. Model, vocabularies, tokenisation rule and input layout are rebuilt from the file
alone, loaded with ``weights_only=True``; ``train_state`` is only in the resumable ``last`` checkpoint.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from m3t.backtranslation.config import BackTranslationConfig
from m3t.backtranslation.data import InputSpec
from m3t.backtranslation.model import BackTranslationDims, SignToText
from m3t.backtranslation.text import TextProcessor
from m3t.checkpoints import CheckpointRecord, checkpoint_payload, read_checkpoint, save_checkpoint
from m3t.dataclass_io import build_dataclass
from m3t.vocabulary import Vocabulary

FORMAT = "m3t-backtranslation-v1"
STAGE = "train-backtranslation"
SKELETON_STAGE = "train-backtranslation-skeleton"  # the judge of skeletal production models


@dataclass(frozen=True)
class LoadedBackTranslation(CheckpointRecord):
    model: SignToText
    language: str
    spec: InputSpec
    processor: TextProcessor
    text_vocab: Vocabulary
    gloss_vocab: Vocabulary | None
    gloss_source: str


def save_backtranslation(path: str | os.PathLike, model: SignToText, language: str, spec: InputSpec,
                         processor: TextProcessor, text_vocab: Vocabulary, gloss_vocab: Vocabulary | None,
                         gloss_source: str, epoch: int, step: int, data_version: str, metrics: dict[str, float],
                         train_config: dict | None = None, train_state: dict[str, Any] | None = None) -> Path:
    return save_checkpoint(path, checkpoint_payload(
        FORMAT, model, epoch, step, data_version, metrics, dict(train_config or {}), train_state,
        language=language,
        config=dataclasses.asdict(model.cfg),
        dims=dataclasses.asdict(model.dims),
        input=spec.to_dict(),
        text=dataclasses.asdict(processor),
        text_vocabulary=text_vocab.to_dict(),
        gloss_vocabulary=None if gloss_vocab is None else gloss_vocab.to_dict(),
        gloss_source=gloss_source,
    ))


def load_backtranslation(path: str | os.PathLike, device: str | torch.device = "cpu") -> LoadedBackTranslation:
    payload = read_checkpoint(path, FORMAT, "back-translation", STAGE, device)
    model = SignToText(build_dataclass(BackTranslationConfig, payload["config"], "config"),
                       build_dataclass(BackTranslationDims, payload["dims"], "dims"))
    model.load_state_dict(payload["state_dict"])
    model.to(device).eval()
    gloss = payload["gloss_vocabulary"]
    return LoadedBackTranslation.read(
        payload, model=model, language=payload["language"], spec=InputSpec.from_dict(payload["input"]),
        processor=build_dataclass(TextProcessor, payload["text"], "text"),
        text_vocab=Vocabulary.from_dict(payload["text_vocabulary"]),
        gloss_vocab=None if gloss is None else Vocabulary.from_dict(gloss), gloss_source=payload["gloss_source"])
