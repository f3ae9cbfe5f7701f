"""Config of the body model (params.yaml ``body``); no imports, so every stage can read it cheaply."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class BodyConfig:
    model: Literal["anny", "smplfx"] = "anny"
    cache_dir: str = ".cache/anny"  # Anny's built-model cache (~800 MB, built once in ~1 min)
    # SMPL-FX is built at load time from licensed files (see docs/body-models.md); relative paths resolve
    # against the working directory.
    smplx_path: str = "models/smplx/SMPLX_NEUTRAL.npz"
    flame_path: str = "models/flame/generic_model.pkl"
    flame_correspondence_path: str = "models/smplx/SMPL-X__FLAME_vertex_ids.npy"
    eyelids_path: str = ""  # optional: folder with l_eyelid.npy / r_eyelid.npy (Pixel3DMM / VHAP assets)
    flame_shape_dims: int = 100  # FLAME shape coefficients in the identity (10 SMPL-X + this; paper: 110)
    neck_rings: int = 5  # concentric FLAME rings blended from 0.9 (body side) to 0.1 (jaw side)
    head_alignment: Literal["eyes", "mean"] = "eyes"  # FLAME -> SMPL-X placement: eye joints or mean offset
