"""The one atomic-write mechanic: every output (shards, tracks, checkpoints, metrics JSON, reports, pictures)
is written to a temporary file beside its target and renamed into place, so a reader never sees a
half-written file and a killed run leaves the previous version intact.

``write_text`` / ``write_bytes`` / ``write_json`` / ``write_jsonl`` also leave a file alone when its bytes
would not change (they return whether they wrote): DVC then sees an unchanged output as unchanged, and a
rerun on unchanged inputs touches nothing.

For writers that want a path or a file object of their own (Parquet, ``np.savez``, ``torch.save``,
``pose.write``) use :func:`atomic_path`::

    with atomic_path(out) as tmp:
        torch.save(state, tmp)

A disk that fills up mid-write raises an ``OSError`` (``ENOSPC``) naming the target; the temporary file is
removed and the previous version stays. :func:`run_lock` keeps two runs of one job off the same outputs.
Whole folders (a generated corpus, the dashboard site) are built aside and swapped in by :func:`replace_dir`.

Outputs get the permissions a plain ``open(path, "w")`` gives a new file: 0666 less the process umask
(0644 under the usual umask 022), also when they replace an older file.
"""
from __future__ import annotations

import errno
import json
import glob
import os
import secrets
import shutil
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


def _new_temp(folder: Path, prefix: str, suffix: str) -> Path:
    """Create an empty, uniquely named file in ``folder`` with the mode ``open()`` gives a new file.

    Not ``tempfile.mkstemp``: its files are 0600, and the rename would hand that mode to every output
    (unreadable to the group, to a web server or a container running as another user).
    """
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    for _ in range(100):
        tmp = folder / f"{prefix}{secrets.token_hex(6)}{suffix}"
        try:
            os.close(os.open(tmp, flags, 0o666))  # the kernel applies the umask, as for open(path, "w")
        except FileExistsError:
            continue
        return tmp
    raise FileExistsError(f"{folder}: 100 temporary names {prefix}*{suffix} already exist; remove stale ones")


def _same_bytes(a: Path, b: Path) -> bool:
    return b.is_file() and a.stat().st_size == b.stat().st_size and a.read_bytes() == b.read_bytes()


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp", keep_identical: bool = False) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder; on success it replaces ``path``, on any error it is removed.

    ``suffix`` is the temporary name's ending (``".npz"`` for writers that append their own extension).
    The parent folder is created when missing. The file exists (empty) when yielded, with mode 0666 less the
    umask, which writers that open the path keep and the rename carries over to ``path``. With
    ``keep_identical`` a ``path`` whose bytes equal the new ones is left alone (its mtime too, so DVC sees no
    change) and the temporary file is dropped.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _new_temp(path.parent, f".{path.name}.", suffix)
    try:
        yield tmp
        if not (keep_identical and _same_bytes(tmp, path)):
            os.replace(tmp, path)
    except OSError as exc:
        if exc.errno != errno.ENOSPC:
            raise
        raise OSError(errno.ENOSPC, f"no space left on the device writing {path} (the previous version, if any, is "
                      "intact); free some space and rerun") from exc
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_bytes(path: str | os.PathLike, data: bytes, only_if_changed: bool = True) -> bool:
    """Write ``data`` atomically; with ``only_if_changed`` an identical file is left untouched. True if written."""
    path = Path(path)
    if only_if_changed and path.is_file() and path.stat().st_size == len(data) and path.read_bytes() == data:
        return False
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
    return True


def write_text(path: str | os.PathLike, text: str, only_if_changed: bool = True) -> bool:
    return write_bytes(path, text.encode("utf-8"), only_if_changed)


def _json_default(value: Any) -> Any:
    if hasattr(value, "item"):  # numpy / torch scalars
        return value.item()
    if isinstance(value, (set, tuple)):
        return list(value)
    return str(value)


def dumps(obj: Any) -> str:
    """The project's JSON text: sorted keys, indent 2, UTF-8 kept, numpy scalars as numbers."""
    return json.dumps(obj, indent=2, sort_keys=True, ensure_ascii=False, default=_json_default) + "\n"


def write_json(path: str | os.PathLike, obj: Any, only_if_changed: bool = True) -> bool:
    return write_text(path, dumps(obj), only_if_changed)


def write_jsonl(path: str | os.PathLike, rows: Iterable[Any], only_if_changed: bool = True) -> bool:
    """One JSON object per line (keys in the rows' own order)."""
    text = "".join(json.dumps(r, ensure_ascii=False, default=_json_default) + "\n" for r in rows)
    return write_text(path, text, only_if_changed)


def copy_file(source: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Copy ``source`` to ``target`` atomically; a missing source names itself."""
    source, target = Path(source), Path(target)
    if not source.is_file():
        raise FileNotFoundError(f"{source} not found; it should have been written by the step before this copy")
    with atomic_path(target) as tmp:
        shutil.copyfile(source, tmp)
    return target


def replace_dir(tmp: str | os.PathLike, dest: str | os.PathLike) -> Path:
    """Swap the finished folder ``tmp`` in as ``dest`` (same file system), so a reader sees the old folder or the
    new one, never a half-written one.

    The old ``dest`` is first renamed to ``.<name>.old`` beside it (one left by a run killed mid-swap is removed
    first), the new one is renamed into place, then the old one is removed: an interrupt there propagates with
    the new ``dest`` already in place, and an old folder that cannot be removed is left for the next swap.
    Returns ``dest``.
    """
    tmp, dest = Path(tmp), Path(dest)
    old = dest.with_name(f".{dest.name}.old")
    if dest.exists():
        if old.exists():
            shutil.rmtree(old)
        os.replace(dest, old)
    os.replace(tmp, dest)
    shutil.rmtree(old, ignore_errors=True)
    return dest


def remove_stale_temps(path: str | os.PathLike) -> list[Path]:
    """Delete the temporary files :func:`atomic_path` left beside ``path`` when its writer was killed mid-write
    (``.<name>.<12 hex>.<suffix>``); returns them. Only safe while holding the lock of the run that writes
    ``path`` (:func:`run_lock`): otherwise another writer's live temporary file could go."""
    path = Path(path)
    prefix = f".{path.name}."
    stale = [p for p in path.parent.glob(f"{glob.escape(prefix)}*") if p.is_file()
             and len(p.name) > len(prefix) + 12 and all(c in "0123456789abcdef" for c in p.name[len(prefix):len(prefix) + 12])]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


@contextmanager
def run_lock(path: str | os.PathLike, what: str) -> Iterator[Path]:
    """Hold the lock file ``path`` for the block, so that a second run of ``what`` on the same outputs stops with
    a clear error naming the running one's pid instead of writing beside it.

    An advisory ``flock``: the kernel releases it when its process dies, so a killed run (``kill -9``) never
    blocks the next one; its file, left behind, is taken over. The file is removed when the block ends."""
    import fcntl

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise RuntimeError(f"{what} is already running on these outputs (pid {holder}, lock {path}); wait for "
                               "it to finish or stop it, then rerun") from None
        try:  # the file may have been removed by the run that just finished: lock the one on disk
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield path
    finally:
        try:
            os.unlink(path)
        finally:
            os.close(fd)
