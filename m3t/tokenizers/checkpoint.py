"""Self-describing tokenizer checkpoints: ``{format, group, config, state_dict, epoch, step, data_version,
metrics[, train_state]}``; a tokenizer is rebuilt from the file alone and loaded with ``weights_only=True``.

``train_state`` (optimizer, scheduler, RNG, history) is present only in the resumable ``last`` checkpoint.
"""
from __future__ import annotations

import dataclasses
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from m3t.tokenizers.vae import MotionTokenizer, VAEConfig

FORMAT = "m3t-tokenizer-v1"


@dataclass(frozen=True)
class LoadedTokenizer:
    model: MotionTokenizer
    group: str
    epoch: int
    step: int
    data_version: str
    metrics: dict[str, float]
    train_state: dict[str, Any] | None


def atomic_torch_save(obj: Any, path: str | os.PathLike) -> Path:
    """torch.save to a temp file next to ``path``, then rename (never a half-written checkpoint)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        torch.save(obj, tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def config_to_dict(cfg: VAEConfig) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(cfg).items()}


def save_tokenizer(path: str | os.PathLike, model: MotionTokenizer, group: str, epoch: int, step: int,
                   data_version: str, metrics: dict[str, float], train_state: dict[str, Any] | None = None) -> Path:
    payload = {
        "format": FORMAT,
        "group": group,
        "config": config_to_dict(model.cfg),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "epoch": int(epoch),
        "step": int(step),
        "data_version": data_version,
        "metrics": {k: float(v) for k, v in metrics.items()},
    }
    if train_state is not None:
        payload["train_state"] = train_state
    return atomic_torch_save(payload, path)


def read_checkpoint(path: str | os.PathLike, fmt: str, kind: str, stage: str,
                    device: str | torch.device = "cpu") -> dict[str, Any]:
    """The payload of a self-describing checkpoint of format ``fmt`` (``weights_only`` loading); clear errors
    for a missing file (run ``stage``), an unreadable one and one of another format."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{kind} checkpoint {path} not found; run `dvc repro {stage}` first")
    try:
        payload = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file gets the same advice
        raise ValueError(f"{path}: not a readable {kind} checkpoint ({type(exc).__name__}: {exc}); "
                         "delete it and retrain") from exc
    if not isinstance(payload, dict) or payload.get("format") != fmt:
        found = payload.get("format") if isinstance(payload, dict) else None
        raise ValueError(f"{path}: not an m3t {kind} checkpoint (format {found!r}, expected {fmt!r})")
    return payload


def load_tokenizer(path: str | os.PathLike, device: str | torch.device = "cpu") -> LoadedTokenizer:
    payload = read_checkpoint(path, FORMAT, "tokenizer", "train-tokenizers", device)
    raw = dict(payload["config"])
    raw["levels"] = tuple(raw["levels"])
    model = MotionTokenizer(VAEConfig(**raw)).to(device)
    model.load_state_dict(payload["state_dict"])
    model.eval()
    return LoadedTokenizer(model, payload["group"], payload["epoch"], payload["step"], payload["data_version"],
                           dict(payload["metrics"]), payload.get("train_state"))
