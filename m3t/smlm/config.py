"""Configs of the Sign Motion Language Model (params.yaml ``smlm_generate``; ``smlm`` / ``smlm_train`` follow)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class GenerateConfig:
    """params.yaml ``smlm_generate``: what generate-smlm and evaluate-smlm read (folders: ``data``)."""

    split: str = "test"
    batch_size: int = 16
    render_clips: int = 2
    export_pose: bool = True
