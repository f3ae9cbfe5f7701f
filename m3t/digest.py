"""SHA-256 content digests: of a file, of a byte stream, of a JSON-able object.

Cache keys, data versions and checkpoint names are digests written into outputs, so each caller's recipe
(what bytes, in what order, hex or raw, how many hex characters) is part of its file format: these helpers
only hash, the caller decides what goes in. ``length`` keeps the first ``length`` hex characters (None: all 64).
"""
from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Iterable
from typing import Any

BLOCK = 1 << 20  # files are read in 1 MiB blocks (videos can be large)


def _file_hash(path: str | os.PathLike) -> hashlib._Hash:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(BLOCK), b""):
            h.update(block)
    return h


def file_digest(path: str | os.PathLike, length: int | None = None) -> str:
    """Hex SHA-256 of a file's bytes."""
    return _file_hash(path).hexdigest()[:length]


def file_digest_bytes(path: str | os.PathLike) -> bytes:
    """Raw (32-byte) SHA-256 of a file's bytes, for feeding into another digest."""
    return _file_hash(path).digest()


def bytes_digest(data: bytes, length: int | None = None) -> str:
    """Hex SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()[:length]


def chunks_digest(chunks: Iterable[bytes], length: int | None = None) -> str:
    """Hex SHA-256 of the concatenation of ``chunks``, fed in order (the caller adds any separators)."""
    h = hashlib.sha256()
    for chunk in chunks:
        h.update(chunk)
    return h.hexdigest()[:length]


def canonical_json(obj: Any, default: Callable[[Any], Any] = str) -> bytes:
    """``obj`` as UTF-8 JSON with sorted keys; values JSON does not know go through ``default``."""
    return json.dumps(obj, sort_keys=True, default=default).encode()


def json_digest(obj: Any, length: int | None = None, default: Callable[[Any], Any] = str) -> str:
    """Hex SHA-256 of :func:`canonical_json` of ``obj``."""
    return bytes_digest(canonical_json(obj, default), length)
