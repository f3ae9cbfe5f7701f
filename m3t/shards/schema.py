"""The on-disk format of fitted-motion shards: one Parquet row per clip, self-describing via metadata.

A shard row holds the :class:`~m3t.corpora.clip.Clip` record, the fitting key / body model / camera /
metrics, the identity vector and one column per modality of the body model's
:class:`~m3t.body.protocol.ModalityLayout`. The layout itself is stored in the schema metadata
(``m3t.layout``) next to ``m3t.schema_version``, so a shard can be read without the body model.

Axis legend: T frames, D_m per-frame dim of modality m, P identity dim.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa

from m3t.body.protocol import Modality, ModalityLayout
from m3t.corpora.clip import Clip
from m3t.dataclass_io import build_dataclass

SCHEMA_VERSION = 1
VERSION_KEY = b"m3t.schema_version"
LAYOUT_KEY = b"m3t.layout"


class ShardFormatError(ValueError):
    """A file is not a readable m3t shard (wrong version, missing or inconsistent metadata)."""


@dataclass(frozen=True, eq=False)
class FittedClip:
    """One clip after fitting, as stored in a shard.

    Attributes
    ----------
    clip : Clip
        The corpus record the motion was fitted from.
    key : str
        Content hash of the inputs and the fitting config (decides whether a refit is needed).
    params : dict[str, np.ndarray]
        Modality name -> (T, D_m) float32 per-frame parameters; every modality has the same T.
    identity : np.ndarray
        (P,) float32 identity (shape) parameters of the signer.
    camera : dict
        JSON-able camera description used for the fit.
    metrics : dict[str, float]
        Fit quality, e.g. ``reproj_px``, ``joint_mm``; may be empty, values may be NaN.
    body_model : str
        Name of the body model the parameters belong to.
    """

    clip: Clip
    key: str
    params: dict[str, np.ndarray]
    identity: np.ndarray
    camera: dict
    metrics: dict[str, float]
    body_model: str

    @property
    def num_frames(self) -> int:
        """T, taken from the first modality (0 when there are none)."""
        return next((int(np.shape(a)[0]) for a in self.params.values()), 0)


# Column name -> arrow type of the per-clip metadata columns (everything except identity and modalities).
METADATA_COLUMNS: dict[str, pa.DataType] = {
    "id": pa.string(),
    "corpus": pa.string(),
    "split": pa.string(),
    "language": pa.string(),
    "signer": pa.string(),
    "text": pa.string(),
    "gloss": pa.string(),
    "media": pa.string(),
    "fps": pa.float64(),
    "label": pa.int64(),
    "extra": pa.string(),  # JSON list of [key, value] pairs (keeps order and duplicates)
    "key": pa.string(),
    "body_model": pa.string(),
    "num_frames": pa.int32(),
    "camera": pa.string(),  # JSON object
    "metrics": pa.string(),  # JSON object; NaN stored as null
}
NULLABLE_COLUMNS = frozenset({"label"})
IDENTITY_COLUMN = "identity"
RESERVED_COLUMNS = frozenset(METADATA_COLUMNS) | {IDENTITY_COLUMN}


def modality_type(dim: int) -> pa.DataType:
    """Arrow type of a modality column: per clip a list of T frames, each a fixed-size list of D floats."""
    return pa.list_(pa.list_(pa.float32(), dim))


def arrow_schema(layout: ModalityLayout) -> pa.Schema:
    """The Arrow schema of a shard for ``layout``, with version and layout in the schema metadata.

    Raises
    ------
    ValueError
        When a modality name collides with a metadata column (rename the modality).
    """
    clash = sorted(RESERVED_COLUMNS & set(layout.names))
    if clash:
        raise ValueError(
            f"modality names {clash} collide with shard metadata columns {sorted(RESERVED_COLUMNS)}; "
            "rename the modality in the body model's layout"
        )
    empty = [m.name for m in layout.modalities if m.dim == 0] + (["identity"] if layout.identity_dim == 0 else [])
    if empty:
        # Arrow's fixed-size lists must have a positive size (size 0 crashes some pyarrow versions).
        raise ValueError(f"layout streams {empty} have dim 0; shards need every modality and the identity non-empty")
    if len(set(layout.names)) != len(layout.names):
        raise ValueError(f"layout has duplicate modality names: {list(layout.names)}")
    fields = [pa.field(n, t, nullable=n in NULLABLE_COLUMNS) for n, t in METADATA_COLUMNS.items()]
    fields.append(pa.field(IDENTITY_COLUMN, pa.list_(pa.float32(), layout.identity_dim), nullable=False))
    fields += [pa.field(m.name, modality_type(m.dim), nullable=False) for m in layout.modalities]
    metadata = {VERSION_KEY: str(SCHEMA_VERSION).encode(), LAYOUT_KEY: layout_to_json(layout).encode()}
    return pa.schema(fields, metadata=metadata)


def layout_to_json(layout: ModalityLayout) -> str:
    """Serialise a layout (names, kinds, dims, labels, mirrors, identity labels) as JSON."""
    return json.dumps(
        {
            "modalities": [
                {"name": m.name, "kind": m.kind, "dim": m.dim, "labels": list(m.labels), "mirror_of": m.mirror_of}
                for m in layout.modalities
            ],
            "identity_labels": list(layout.identity_labels),
        }
    )


def layout_from_json(text: str, source: str = "<json>") -> ModalityLayout:
    """Rebuild a layout written by :func:`layout_to_json`; ``source`` names the file in errors."""
    try:
        raw = json.loads(text)
        modalities = tuple(
            Modality(name=m["name"], kind=m["kind"], labels=tuple(m["labels"]), mirror_of=m.get("mirror_of"))
            for m in raw["modalities"]
        )
        layout = ModalityLayout(modalities=modalities, identity_labels=tuple(raw["identity_labels"]))
        stored_dims = {m["name"]: int(m["dim"]) for m in raw["modalities"]}
    except (ValueError, KeyError, TypeError) as exc:
        raise ShardFormatError(f"{source}: cannot parse the m3t.layout metadata ({exc}); the shard is damaged") from exc
    if stored_dims != layout.dims:
        raise ShardFormatError(
            f"{source}: m3t.layout dims {stored_dims} disagree with its labels {layout.dims}; the shard is damaged"
        )
    return layout


def check_schema_metadata(metadata: dict[bytes, bytes] | None, source: str) -> ModalityLayout:
    """Check the schema version in ``metadata`` and return the stored layout.

    Raises
    ------
    ShardFormatError
        When the version is missing or differs from :data:`SCHEMA_VERSION`, naming ``source``.
    """
    metadata = metadata or {}
    if VERSION_KEY not in metadata:
        raise ShardFormatError(
            f"{source}: no m3t.schema_version in the Parquet metadata (expected version {SCHEMA_VERSION}); "
            "this is not an m3t shard, rewrite it with m3t.shards.write_shard"
        )
    found = metadata[VERSION_KEY].decode(errors="replace")
    if found != str(SCHEMA_VERSION):
        raise ShardFormatError(
            f"{source}: shard schema version {found}, this code reads version {SCHEMA_VERSION}; "
            "re-export the shard with the current m3t (or use the m3t release that wrote it)"
        )
    if LAYOUT_KEY not in metadata:
        raise ShardFormatError(f"{source}: no m3t.layout in the Parquet metadata; the shard is damaged")
    return layout_from_json(metadata[LAYOUT_KEY].decode(), source)


def check_column_types(found: pa.Schema, expected: pa.Schema, source: str, remedy: str) -> None:
    """Every column of ``expected`` in ``found`` with exactly its Arrow type, checked on the file's schema before
    any row is read: a column of another type (int64 or string where float lists belong, a number stored as
    text) stops here with the file, the column and both types, not later in a model.

    Raises
    ------
    ShardFormatError
        A column is missing or has another type; ``remedy`` says what to do.
    """
    for field in expected:
        index = found.get_field_index(field.name)
        if index < 0:
            raise ShardFormatError(f"{source}: column {field.name!r} is missing (or repeated); {remedy}")
        if not found.field(index).type.equals(field.type):
            raise ShardFormatError(f"{source}: column {field.name!r} is {found.field(index).type}, expected "
                                   f"{field.type}; {remedy}")


def metrics_to_json(metrics: dict[str, float]) -> str:
    """Encode metrics as standard JSON (NaN / inf become null)."""
    return json.dumps({k: (float(v) if math.isfinite(float(v)) else None) for k, v in metrics.items()})


def metrics_from_json(text: str) -> dict[str, float]:
    """Inverse of :func:`metrics_to_json` (null becomes NaN)."""
    return {k: (math.nan if v is None else float(v)) for k, v in json.loads(text).items()}


def extra_to_json(extra: tuple[tuple[str, str], ...]) -> str:
    return json.dumps([[k, v] for k, v in extra])


def extra_from_json(text: str) -> tuple[tuple[str, str], ...]:
    return tuple((str(k), str(v)) for k, v in json.loads(text))


CLIP_COLUMNS = ("id", "corpus", "split", "language", "signer", "text", "gloss", "media", "fps", "label", "extra")
"""The metadata columns that hold the :class:`Clip` record (shared by fitted and token shards)."""


def clip_record(c: Clip) -> dict[str, Any]:
    """The :data:`CLIP_COLUMNS` values of one clip (``extra`` JSON-encoded)."""
    return {
        "id": c.id,
        "corpus": c.corpus,
        "split": c.split,
        "language": c.language,
        "signer": c.signer,
        "text": c.text,
        "gloss": c.gloss,
        "media": c.media,
        "fps": float(c.fps),
        "label": None if c.label is None else int(c.label),
        "extra": extra_to_json(c.extra),
    }


def clip_from_columns(columns: dict[str, list], row: int) -> Clip:
    """Inverse of :func:`clip_record` for row ``row`` of column lists."""
    values = {name: columns[name][row] for name in CLIP_COLUMNS}
    values["extra"] = extra_from_json(values["extra"])
    return build_dataclass(Clip, values, "clip")


def clip_metadata(clip: FittedClip) -> dict[str, Any]:
    """The metadata columns of one shard row (JSON fields already encoded)."""
    return {
        **clip_record(clip.clip),
        "key": clip.key,
        "body_model": clip.body_model,
        "num_frames": clip.num_frames,
        "camera": json.dumps(clip.camera),
        "metrics": metrics_to_json(clip.metrics),
    }
