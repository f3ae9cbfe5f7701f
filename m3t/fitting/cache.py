"""fit-corpus's content-addressed cache: the keys of tracks, fits and imports, and the part files they name.

Every key is :func:`cache_key` of what the cached result depends on, led by :data:`KEY_VERSION`; a changed key
redoes the clip, an unchanged one reuses its file. Tracks (``tracks/<clip>-<key>.npz``) and part files
(``parts/<clip>-<key>.parquet``, with their initialisation record ``.init.json``) are written atomically, each
followed by its SHA-256 (``.sha256``): a file on disk that its digest does not vouch for is redone, never read.
"""
from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from m3t.arithmetic import cache_parts
from m3t.atomic import write_json, write_text
from m3t.body.protocol import ModalityLayout
from m3t.corpora.clip import Clip
from m3t.digest import canonical_json, chunks_digest, file_digest
from m3t.fitting.context import FitContext
from m3t.fitting.report import ClipOutcome
from m3t.shards.io import read_shard, write_shard
from m3t.shards.schema import FittedClip

KEY_VERSION = "fit-v2"  # bump when fitting code changes in a way that invalidates cached results


def cache_key(*parts: object) -> str:
    """16-hex key of :data:`KEY_VERSION` and ``parts``: bytes as they are, anything else as sorted-key JSON, each
    followed by NUL (the pinned-arithmetic marker of :func:`m3t.arithmetic.cache_parts` last)."""
    chunks: list[bytes] = []
    for part in (KEY_VERSION, *parts, *cache_parts()):
        chunks += [part if isinstance(part, bytes) else canonical_json(part), b"\0"]
    return chunks_digest(chunks, length=16)


def part_path(clip: Clip, key: str, ctx: FitContext) -> Path:
    return Path(ctx.job.run.cache_dir) / "parts" / f"{clip.id.replace('/', '_')}-{key}.parquet"


def track_path(clip: Clip, key: str, ctx: FitContext) -> Path:
    return Path(ctx.job.run.cache_dir) / "tracks" / f"{clip.id.replace('/', '_')}-{key}.npz"


def _checksum_file(cached: Path) -> Path:
    return cached.with_suffix(".sha256")


def vouch(cached: Path) -> None:
    """Write the SHA-256 of a cached track or part beside it, after the file itself: the digest vouches for it."""
    write_text(_checksum_file(cached), file_digest(cached))


def cache_intact(cached: Path, read: Callable[[Path], object]) -> bool:
    """Whether a cached track or part file is the one its run wrote: its SHA-256 matches the digest written
    beside it (a flipped byte on disk is redone, never read). A file cached before digests existed is trusted
    once ``read`` reads it back, and gets its digest."""
    digest = file_digest(cached)
    checksum = _checksum_file(cached)
    if checksum.exists():
        return checksum.read_text().strip() == digest
    try:
        read(cached)
    except Exception:  # noqa: BLE001 - unreadable: redo it
        return False
    write_text(checksum, digest)
    return True


def part_outcome(clip: Clip, part: Path, make: Callable[[], tuple[FittedClip, dict[str, Any]]],
                 layout: ModalityLayout, start: float, seen: dict[str, Any]) -> ClipOutcome:
    """The clip's part file from the cache when it and its record exist, else ``make()`` written atomically."""
    init_file = part.with_suffix(".init.json")
    if part.exists() and init_file.exists() and cache_intact(part, read_shard):
        fitted = read_shard(part).clips[0]
        return ClipOutcome(clip.id, clip.split, "cached", str(part), metrics=fitted.metrics,
                           frames=fitted.num_frames, init=json.loads(init_file.read_text()), **seen)
    fitted, init = make()
    part.parent.mkdir(parents=True, exist_ok=True)
    write_json(init_file, init)  # before the part: a part on disk always has its record
    write_shard(part, [fitted], layout)
    vouch(part)
    return ClipOutcome(clip.id, clip.split, "fitted", str(part), metrics=fitted.metrics,
                       frames=fitted.num_frames, seconds=time.perf_counter() - start, init=init, **seen)
