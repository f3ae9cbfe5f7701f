"""Choose the body model from the ``body`` section of params.yaml."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from m3t.body.protocol import BodyModel


@dataclass(frozen=True)
class BodyConfig:
    model: Literal["anny", "smplfx"] = "anny"
    cache_dir: str = ".cache/anny"  # Anny's built-model cache (~800 MB, built once in ~1 min)


def load_body_model(cfg: BodyConfig) -> BodyModel:
    if cfg.model == "anny":
        from m3t.body.anny_body import AnnyBody

        return AnnyBody(cache_dir=cfg.cache_dir)
    raise NotImplementedError(
        "body.model 'smplfx' needs the licensed SMPL-X (SMPLX_NEUTRAL.npz) and FLAME 2020 files plus the "
        "SMPL-X <-> FLAME vertex correspondence; SMPL-FX support is not part of this release yet. "
        "Use body.model: anny (the embedded open model)."
    )
