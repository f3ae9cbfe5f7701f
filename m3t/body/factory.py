"""Choose the body model from the ``body`` section of params.yaml."""
from __future__ import annotations

from m3t.body.config import BodyConfig
from m3t.body.protocol import BodyModel


def load_body_model(cfg: BodyConfig) -> BodyModel:
    if cfg.model == "anny":
        from m3t.body.anny_body import AnnyBody

        return AnnyBody(cache_dir=cfg.cache_dir)
    if cfg.model == "smplfx":
        from pathlib import Path

        from m3t.body.smplfx import SMPLFXBody
        from m3t.body.smplfx_build import SMPLFXFiles

        files = SMPLFXFiles(Path(cfg.smplx_path), Path(cfg.flame_path), Path(cfg.flame_correspondence_path),
                            Path(cfg.eyelids_path) if cfg.eyelids_path else None)
        return SMPLFXBody(files, flame_shape_dims=cfg.flame_shape_dims, neck_rings=cfg.neck_rings,
                          alignment=cfg.head_alignment)
    raise ValueError(f"body.model {cfg.model!r} unknown; allowed: anny, smplfx")


def body_cache_key(cfg: BodyConfig) -> object:
    """What identifies the body model for content-addressed caches: Anny is fixed by its name; SMPL-FX by
    its options and the bytes of the user's files (a new FLAME file invalidates cached fits)."""
    if cfg.model == "anny":
        return cfg.model
    import dataclasses
    from pathlib import Path

    from m3t.digest import file_digest

    digests = {}
    for name in ("smplx_path", "flame_path", "flame_correspondence_path"):
        path = Path(getattr(cfg, name))
        digests[name] = file_digest(path) if path.is_file() else "missing"
    return {**dataclasses.asdict(cfg), "cache_dir": None, "files": digests}
