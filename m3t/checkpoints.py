"""Self-describing, resumable checkpoints: the digest naming a resumable run, the record every checkpoint stores
after its weights (:class:`CheckpointRecord`), the payload, its atomic write and checked read, and the global RNG
state a ``last`` checkpoint carries so a resumed run draws the same numbers."""
from __future__ import annotations

import os
import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

import numpy as np
import torch

from m3t.arithmetic import cache_parts
from m3t.atomic import atomic_path
from m3t.declared import check_zip
from m3t.digest import bytes_digest, json_digest


def run_digest(*parts: Any) -> str:
    """16-hex digest naming a resumable run: what its ``last`` checkpoint must agree on to be continued (the
    trainer's version string, model and training settings, vocabularies, data version). ``parts`` are
    JSON-dumped with sorted keys; bytes count by their SHA-256, anything else unknown to JSON by ``str``."""
    return json_digest([*parts, *cache_parts()], length=16,
                       default=lambda v: bytes_digest(v) if isinstance(v, bytes) else str(v))


@dataclass(frozen=True, kw_only=True)
class CheckpointRecord:
    """Where a checkpoint stands in its run, stored after its weights: ``epoch``, ``step`` (optimiser steps so
    far), ``data_version``, ``metrics`` (the epoch's record), ``train_config`` (the training settings) and, in
    a resumable ``last`` only, ``train_state``. A family's loaded checkpoint extends it with its model and what
    describes it (``LoadedSMLM(CheckpointRecord)``), built by :meth:`read`."""

    epoch: int
    step: int
    data_version: str
    metrics: dict[str, float]
    train_config: dict = field(default_factory=dict)
    train_state: dict[str, Any] | None = None

    def fields(self) -> dict[str, Any]:
        """The record as a checkpoint stores it, in file order (``train_state`` only when there is one)."""
        out = {"epoch": int(self.epoch), "step": int(self.step), "data_version": self.data_version,
               "metrics": {k: float(v) for k, v in self.metrics.items()}, "train_config": dict(self.train_config)}
        if self.train_state is not None:
            out["train_state"] = self.train_state
        return out

    @classmethod
    def read(cls, payload: dict[str, Any], **own: Any) -> Self:
        """``cls`` of a checkpoint's ``payload``: its record plus ``own``, the fields a family's subclass adds."""
        return cls(**own, epoch=payload["epoch"], step=payload["step"], data_version=payload["data_version"],
                   metrics=dict(payload["metrics"]), train_config=dict(payload.get("train_config", {})),
                   train_state=payload.get("train_state"))


def checkpoint_payload(fmt: str, model: torch.nn.Module, epoch: int, step: int, data_version: str,
                       metrics: dict[str, float], train_config: dict | None = None,
                       train_state: dict[str, Any] | None = None, **described: Any) -> dict[str, Any]:
    """The fields every self-describing checkpoint has: ``format``, what rebuilds the model (``described``:
    config, dims, vocabularies, ...), the weights on the CPU, then the :class:`CheckpointRecord`."""
    record = CheckpointRecord(epoch=epoch, step=step, data_version=data_version, metrics=metrics,
                              train_config=train_config or {}, train_state=train_state)
    return {"format": fmt, **described, "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
            **record.fields()}


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """``torch.save`` of a checkpoint payload, atomically (a reader never sees half a file). Saved through a
    file handle: given a path, ``torch.save`` names the zip archive after the (random) temporary file, so
    the same payload would never give the same bytes, and every digest of a checkpoint would change."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        torch.save(payload, fh)
    return Path(path)


def read_checkpoint(path: str | os.PathLike, fmt: str, kind: str, stage: str,
                    device: str | torch.device = "cpu") -> dict[str, Any]:
    """The payload of a self-describing checkpoint of format ``fmt`` (``weights_only`` loading); clear errors
    for a missing file (run ``stage``), an unreadable one and one of another format."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{kind} checkpoint {path} not found; run `dvc repro {stage}` first")
    try:
        check_zip(path)  # torch's reader allocates each record's declared size
        payload = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # any unreadable file gets the same advice
        raise ValueError(f"{path}: not a readable {kind} checkpoint ({type(exc).__name__}: {exc}); "
                         "delete it and retrain") from exc
    if not isinstance(payload, dict) or payload.get("format") != fmt:
        found = payload.get("format") if isinstance(payload, dict) else None
        raise ValueError(f"{path}: not an m3t {kind} checkpoint (format {found!r}, expected {fmt!r})")
    return payload


def rng_state() -> dict[str, Any]:
    """The global torch (CPU), numpy and python ``random`` generators, in types ``weights_only`` loads."""
    name, keys, pos, has_gauss, gauss = np.random.get_state()
    return {"torch": torch.get_rng_state(), "numpy": [name, keys.tolist(), pos, has_gauss, gauss],
            "python": random.getstate()}


def set_rng_state(state: dict[str, Any] | torch.Tensor) -> None:
    """Restore :func:`rng_state`'s generators (a bare tensor: a torch-only state of older checkpoints)."""
    if isinstance(state, torch.Tensor):
        state = {"torch": state}
    torch.set_rng_state(state["torch"].cpu())
    if "numpy" in state:
        name, keys, pos, has_gauss, gauss = state["numpy"]
        np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, gauss))
    if "python" in state:
        version, internal, gauss = state["python"]
        random.setstate((version, tuple(internal), gauss))

