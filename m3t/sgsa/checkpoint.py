"""Self-describing SGSA / PT checkpoints: ``{format, system, config, dims, graph, text_vocabulary,
gloss_vocabulary, state_dict, epoch, step, data_version, metrics, train_config[, train_state]}``. The model, its
skeleton graph (and so the adjacency A*) and the vocabularies are rebuilt from the file alone, loaded with
``weights_only=True``; ``train_state`` (optimiser, plateau schedule, RNG, the noise augmentation's error std) is
only in the resumable ``last`` checkpoint.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from m3t.body.skeleton import SkeletonGraph, adjacency
from m3t.checkpoints import CheckpointRecord, checkpoint_payload, read_checkpoint, save_checkpoint
from m3t.dataclass_io import build_dataclass
from m3t.sgsa.config import SGSAConfig
from m3t.sgsa.model import SGSADims, SGSAProduction
from m3t.vocabulary import Vocabulary

FORMAT = "m3t-sgsa-v2"  # v2: both decoders pre-norm with a frame embedding and a final LayerNorm
OLDER_FORMATS = ("m3t-sgsa-v1",)
STAGE = "train-sgsa"


@dataclass(frozen=True)
class LoadedSGSA(CheckpointRecord):
    model: SGSAProduction
    graph: SkeletonGraph
    text_vocab: Vocabulary
    gloss_vocab: Vocabulary | None

    @property
    def model_device(self) -> torch.device:
        return next(self.model.parameters()).device


def build_model(cfg: SGSAConfig, graph: SkeletonGraph, text_vocab: Vocabulary,
                gloss_vocab: Vocabulary | None) -> SGSAProduction:
    """A fresh model for ``graph`` (width 3 x joints + counter; A* from the graph)."""
    dims = SGSADims(graph.width + 1, len(text_vocab), 0 if gloss_vocab is None else len(gloss_vocab))
    return SGSAProduction(cfg, dims, adjacency(graph, counter=True) if cfg.decoder_layers > 0 else None)


def save_sgsa(path: str | os.PathLike, model: SGSAProduction, graph: SkeletonGraph, text_vocab: Vocabulary,
              gloss_vocab: Vocabulary | None, epoch: int, step: int, data_version: str, metrics: dict[str, float],
              train_config: dict | None = None, train_state: dict[str, Any] | None = None) -> Path:
    return save_checkpoint(path, checkpoint_payload(
        FORMAT, model, epoch, step, data_version, metrics, dict(train_config or {}), train_state,
        system=model.cfg.system, variant=model.cfg.variant, config=dataclasses.asdict(model.cfg),
        dims=dataclasses.asdict(model.dims), graph=graph.to_dict(), text_vocabulary=text_vocab.to_dict(),
        gloss_vocabulary=None if gloss_vocab is None else gloss_vocab.to_dict()))


def load_sgsa(path: str | os.PathLike, device: str | torch.device = "cpu") -> LoadedSGSA:
    try:
        payload = read_checkpoint(path, FORMAT, "SGSA / PT", STAGE, device)
    except ValueError as exc:
        if any(repr(old) in str(exc) for old in OLDER_FORMATS):
            raise ValueError(f"{path}: an SGSA / PT checkpoint of an older decoder (post-norm layers fed raw frames, "
                             f"{FORMAT} expected); retrain it: `dvc repro {STAGE}`") from exc
        raise
    cfg = build_dataclass(SGSAConfig, payload["config"], "config")
    graph = SkeletonGraph.from_dict(payload["graph"])
    text_vocab = Vocabulary.from_dict(payload["text_vocabulary"])
    gloss = payload["gloss_vocabulary"]
    gloss_vocab = None if gloss is None else Vocabulary.from_dict(gloss)
    model = SGSAProduction(cfg, build_dataclass(SGSADims, payload["dims"], "dims"),
                           adjacency(graph, counter=True) if cfg.decoder_layers > 0 else None)
    model.load_state_dict(payload["state_dict"])
    model.to(device).eval()
    return LoadedSGSA.read(payload, model=model, graph=graph, text_vocab=text_vocab, gloss_vocab=gloss_vocab)
