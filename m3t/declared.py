"""Sizes a file declares, checked before anything is allocated: zip archives (``.npz``, torch checkpoints),
``.npy`` headers, HDF5 datasets, and the lengths a pickle declares (plain or gzip-compressed).

A reader that trusts a declared size lets a small file allocate gigabytes: numpy allocates the shape a ``.npy``
header names before reading its bytes, torch's zip reader allocates the uncompressed size the archive's directory
names, and h5py allocates a dataset's declared shape before reading its chunks. Each check here compares what the
file declares with what it holds, and with a cap:

- an uncompressed size larger than :data:`MAX_BYTES` (``M3T_MAX_DECLARED_BYTES``) is refused, whatever the file;
- a member stored uncompressed must lie inside the file (its declared size equals its stored size);
- a compressed member, or an HDF5 dataset, may expand at most :data:`MAX_RATIO` times (``M3T_MAX_INFLATE_RATIO``)
  above :data:`RATIO_FLOOR` bytes: deflate cannot reach 1,032:1, and real arrays of floats compress 1-3:1, so a
  higher ratio is a compression bomb or a lie;
- a ``.npy`` header (alone or inside an ``.npz``) must declare no more bytes than its member holds.

The error (:class:`DeclaredSizeError`, a ``ValueError``, so the readers' existing handlers wrap it with their own
advice) names the file, the member, what is declared and what is stored, and the environment variable that raises
the cap for a legitimately huge file. The checks read only directories and headers: a refusal costs well under a
second and a few kB.
"""
from __future__ import annotations

import contextlib
import gzip
import os
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import numpy as np

MAX_BYTES_ENV = "M3T_MAX_DECLARED_BYTES"
MAX_BYTES = 16 * 2**30  # a paper-size SMLM checkpoint with its optimizer state is ~5 GB; SMPL-X's .npz ~0.3 GB
MAX_RATIO_ENV = "M3T_MAX_INFLATE_RATIO"
MAX_RATIO = 200
RATIO_FLOOR = 2**20  # a member this small may compress as well as it likes (a mask of zeros, a constant)


class DeclaredSizeError(ValueError):
    """A file declares more than it holds, or more than a cap allows."""


def cap(env: str, default: int) -> int:
    """The cap ``default``, or the positive integer the environment variable ``env`` sets."""
    value = os.environ.get(env, "").strip()
    if not value:
        return default
    try:
        number = int(float(value))
    except ValueError:
        number = 0
    if number <= 0:
        raise ValueError(f"{env}={value!r} is not a positive number; unset it or give a byte count / ratio")
    return number


def check_bytes(declared: int, stored: int, where: str, compressed: bool) -> None:
    """Refuse ``declared`` bytes (what ``where`` would allocate) against the cap, and against ``stored`` bytes:
    equal when stored plainly, at most the ratio cap times more when ``compressed``."""
    limit = cap(MAX_BYTES_ENV, MAX_BYTES)
    if declared > limit:
        raise DeclaredSizeError(f"{where} declares {declared:,} bytes, more than the cap of {limit:,}; "
                                f"a legitimately huge file: raise {MAX_BYTES_ENV}")
    if not compressed:
        if declared > stored:
            raise DeclaredSizeError(f"{where} declares {declared:,} bytes but holds {stored:,} (truncated or forged); "
                                    "re-export the file")
        return
    ratio = cap(MAX_RATIO_ENV, MAX_RATIO)
    if declared > RATIO_FLOOR and declared > ratio * max(stored, 1):
        raise DeclaredSizeError(f"{where} declares {declared:,} bytes from {stored:,} compressed, more than {ratio}:1 "
                                f"(a compression bomb?); a legitimately compressible file: raise {MAX_RATIO_ENV}")


def check_zip(path: str | Path, npy_members: bool = False) -> None:
    """Check every member of the zip archive ``path`` (an ``.npz``, a torch checkpoint) from its central
    directory, before any member is inflated; with ``npy_members``, also each ``.npy`` member's header.

    zipfile stops inflating at the directory's declared size, so bounding that size bounds the allocation."""
    path = Path(path)
    size = path.stat().st_size
    limit = cap(MAX_BYTES_ENV, MAX_BYTES)
    total = 0
    with zipfile.ZipFile(path) as archive:
        for info in archive.infolist():
            where = f"{path}: member {info.filename!r}"
            stored = info.compress_type == zipfile.ZIP_STORED
            if info.header_offset + info.compress_size > size:
                raise DeclaredSizeError(f"{where} ends at byte {info.header_offset + info.compress_size:,}, past the "
                                        f"end of the file ({size:,} bytes): truncated; re-export it")
            check_bytes(info.file_size, info.compress_size, where, compressed=not stored)
            total += info.file_size
            if total > limit:
                raise DeclaredSizeError(f"{path}: its members declare more than {limit:,} bytes in all; a "
                                        f"legitimately huge file: raise {MAX_BYTES_ENV}")
            if npy_members and info.filename.endswith(".npy"):
                with archive.open(info) as member:
                    check_npy_header(member, info.file_size, where)


def check_npy_header(fh: IO[bytes], size: int, where: str) -> None:
    """The ``.npy`` header at the start of ``fh`` must declare no more array bytes than the ``size`` bytes of the
    file (or member) hold after the header."""
    try:
        version = np.lib.format.read_magic(fh)
        reader = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        shape, _, dtype = reader[version](fh, max_header_size=1 << 16) if version in reader else (None, 0, None)
    except (ValueError, KeyError, SyntaxError, EOFError) as exc:
        raise DeclaredSizeError(f"{where}: not a readable .npy header ({exc}); re-export the file") from exc
    if shape is None:
        raise DeclaredSizeError(f"{where}: .npy format version {version} is not read here; save it with numpy.save")
    if dtype.hasobject:  # a pickled array: its bytes are no count of items, and allow_pickle=False refuses it
        return
    count = 1
    for n in shape:
        count *= int(n)
    header = fh.tell() if fh.seekable() else 0
    check_bytes(count * dtype.itemsize, size - header, where, compressed=False)


def check_npy(path: str | Path) -> None:
    """Check a ``.npy`` file's header against the file's size (numpy allocates the declared shape first)."""
    path = Path(path)
    with open(path, "rb") as fh:
        check_npy_header(fh, path.stat().st_size, str(path))


def check_hdf5_dataset(dataset, where: str) -> None:
    """An h5py dataset's declared size (shape x item size) against the storage the file gives it, before
    ``dataset[()]`` allocates it: contiguous storage must hold it, chunked or filtered storage may expand at most
    the ratio cap (HDF5 returns the fill value for unwritten chunks, which is how a tiny file declares terabytes)."""
    declared = int(dataset.size or 0) * int(dataset.dtype.itemsize)
    stored = int(dataset.id.get_storage_size())
    filtered = dataset.chunks is not None
    check_bytes(declared, stored, f"{where}: dataset {dataset.name.lstrip('/')!r}", compressed=filtered)


def open_npz(path: str | Path):
    """``numpy.load`` of an ``.npz`` (no pickles) after :func:`check_zip` of its members and their headers; use it
    as a context manager, like ``numpy.load``'s result."""
    check_zip(path, npy_members=True)
    return np.load(path, allow_pickle=False)


def load_npy(path: str | Path) -> np.ndarray:
    """``numpy.load`` of a ``.npy`` (no pickles) after :func:`check_npy`."""
    check_npy(path)
    return np.load(path, allow_pickle=False)


class BoundedReads:
    """A binary stream that refuses a read asking for more bytes than the file can still give, before reading (so
    before anything of that size is allocated). A pickle declares the length of each string, bytes object and
    frame it holds; read through this, a length the file cannot hold is refused instead of allocated.

    ``budget``: the bytes the stream may give in all (a plain file: its size; a gzip stream: the ratio cap times
    its compressed size); ``why``: what bounds the budget, for the message."""

    def __init__(self, stream: IO[bytes], budget: int, where: str, why: str):
        self._stream, self._left, self._where, self._why = stream, budget, where, why

    SMALL = 2**16  # a read this small past the end is left to end short, as at any end of file (a cut pickle)

    def _take(self, n: int) -> None:
        if n > self._left and n > self.SMALL:
            raise DeclaredSizeError(f"{self._where}: a record declares {n:,} bytes where at most {self._left:,} can "
                                    f"follow ({self._why})")

    def read(self, n: int | None = -1) -> bytes:
        if n is None or n < 0:
            data = self._stream.read(max(self._left, self.SMALL) + 1)
            self._take(len(data))
        else:
            self._take(n)
            data = self._stream.read(n)
        self._left = max(self._left - len(data), 0)
        return data

    def readline(self, limit: int | None = -1) -> bytes:
        data = self._stream.readline(max(self._left, self.SMALL) + 1)
        self._take(len(data))
        self._left = max(self._left - len(data), 0)
        return data

    def readinto(self, buffer) -> int:
        self._take(len(buffer))
        n = self._stream.readinto(buffer)
        self._left = max(self._left - n, 0)
        return n


@contextlib.contextmanager
def open_bounded(path: str | Path, compressed: bool = False) -> Iterator[BoundedReads]:
    """``path`` opened for reading through :class:`BoundedReads`; ``compressed``: a gzip file, whose trailer's size
    (the real size modulo 2^32) is checked first, then every read against the ratio cap."""
    path = Path(path)
    size = path.stat().st_size
    if not compressed:
        with open(path, "rb") as fh:
            yield BoundedReads(fh, size, str(path), f"the file has {size:,} bytes")
        return
    with open(path, "rb") as fh:
        fh.seek(max(size - 4, 0))
        declared = int.from_bytes(fh.read(4), "little")
    check_bytes(declared, size, f"{path}: its gzip trailer", compressed=True)
    ratio = cap(MAX_RATIO_ENV, MAX_RATIO)
    budget = min(cap(MAX_BYTES_ENV, MAX_BYTES), max(RATIO_FLOOR, ratio * size))
    with gzip.open(path, "rb") as fh:
        yield BoundedReads(fh, budget, str(path), f"{ratio}:1 of its {size:,} compressed bytes; a legitimately "
                                                  f"compressible file: raise {MAX_RATIO_ENV}")
