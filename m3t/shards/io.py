"""Writing and reading fitted-motion shards (Parquet, see :mod:`m3t.shards.schema`).

Writes are atomic: the shard is written to a temporary file next to the destination and moved into
place with :func:`os.replace`, so a reader never sees a half-written shard. A shard is stored in Parquet row
groups of whole clips holding about :data:`ROW_GROUP_FRAMES` frames each, so :class:`ShardWriter` and
:func:`iter_shard` needs memory for one row group, not the whole shard (How2Sign's train split is ~6M frames,
~7 GB of float32), and :func:`iter_split` for :data:`READ_BATCH_ROWS` clips. Arrays are converted in bulk (one
concatenation / one reshape per column and batch of rows), never frame by frame.

Axis legend: N clips in a shard (or row group), T frames, D_m per-frame dim of modality m, P identity dim.
"""
from __future__ import annotations

import json
import os
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from m3t.atomic import atomic_path
from m3t.body.protocol import ModalityLayout
from m3t.digest import chunks_digest, file_digest_bytes
from m3t.shards.schema import (
    IDENTITY_COLUMN,
    METADATA_COLUMNS,
    FittedClip,
    ShardFormatError,
    arrow_schema,
    check_column_types,
    check_schema_metadata,
    clip_from_columns,
    clip_metadata,
    metrics_from_json,
)

if TYPE_CHECKING:
    from typing_extensions import Self

# Fitted float32 parameters barely compress (zstd saved <10% on smooth motion but read ~4x slower).
COMPRESSION = "snappy"
ROW_GROUP_FRAMES = 65536
"""Frames per Parquet row group of a fitted shard: the memory :class:`ShardWriter` and :func:`iter_shard` need.

Groups hold whole clips: a clip that would take a group past this many frames starts the next group, and a
group that reaches it is closed, so a group holds at most this many frames except a clip longer than that,
which is a group of its own. 65536 frames of the Anny layout (304 float32 per frame) are ~80 MB. A shard of at
most this many frames is one row group, byte for byte the file written before groups were bounded (so its DVC
hash stays)."""
READ_BATCH_ROWS = 32
"""Clips decoded at a time when a row group is read. Arrow decodes a nested ``list<fixed_size_list<float>>``
column with temporaries (repetition and definition levels, pages, growing builders) that peak at several times
the group's float data, and its allocator keeps what it freed: a whole 65,536-frame group read at once raised a
process's resident memory by ~290 MB for ~80 MB of values. Decoded 32 clips at a time (about 6,000 frames at
How2Sign's mean length) the temporaries stay a fraction of that, at the same speed. :func:`iter_split` holds one
such batch of clips; :func:`iter_shard` and :func:`read_row_group` join a group's batches (its values once, in
NumPy)."""


@dataclass(frozen=True, eq=False)
class ShardContents:
    """A shard read back into memory.

    Attributes
    ----------
    path : Path
        The file it was read from.
    layout : ModalityLayout
        The layout stored in the file (all modalities, even when only some were read).
    clips : tuple[FittedClip, ...]
        The rows, in file order; ``params`` holds only the modalities that were read.
    lengths : np.ndarray
        (N,) int64 number of frames per clip (from the file, also when no modality was read).
    """

    path: Path
    layout: ModalityLayout
    clips: tuple[FittedClip, ...]
    lengths: np.ndarray

    def __len__(self) -> int:
        return len(self.clips)

    def __iter__(self) -> Iterator[FittedClip]:
        return iter(self.clips)

    @property
    def ids(self) -> list[str]:
        return [c.clip.id for c in self.clips]


def validate_clip(clip: FittedClip, layout: ModalityLayout) -> None:
    """Check one clip's arrays against ``layout``; errors name the clip id and the modality."""
    cid = clip.clip.id
    missing = [n for n in layout.names if n not in clip.params]
    unknown = sorted(set(clip.params) - set(layout.names))
    if missing or unknown:
        raise ValueError(
            f"clip {cid!r}: modalities do not match the layout (missing {missing}, unknown {unknown}); "
            f"layout has {list(layout.names)}"
        )
    frames = None
    for name, dim in layout.dims.items():
        arr = np.asarray(clip.params[name])
        if arr.ndim != 2 or arr.shape[1] != dim:
            raise ValueError(
                f"clip {cid!r}, modality {name!r}: shape {arr.shape}, layout expects (T, {dim}); "
                "check that the clip was fitted with the same body model as the layout"
            )
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"clip {cid!r}, modality {name!r}: dtype {arr.dtype}, expected float32")
        if not np.isfinite(arr).all():
            raise ValueError(f"clip {cid!r}, modality {name!r}: contains NaN or inf; the fit diverged")
        if frames is None:
            frames = arr.shape[0]
        elif arr.shape[0] != frames:
            raise ValueError(
                f"clip {cid!r}, modality {name!r}: {arr.shape[0]} frames, other modalities have {frames}"
            )
    if layout.names and frames == 0:
        raise ValueError(f"clip {cid!r}: has no frames; drop it before writing the shard")
    identity = np.asarray(clip.identity)
    if identity.shape != (layout.identity_dim,):
        raise ValueError(
            f"clip {cid!r}, identity: shape {identity.shape}, layout expects ({layout.identity_dim},)"
        )
    try:
        json.dumps(clip.camera)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"clip {cid!r}, camera: not JSON-serialisable ({exc}); store plain lists/floats") from exc


def _modality_array(arrays: Sequence[np.ndarray], dim: int) -> pa.Array:
    """list<fixed_size_list<float32, dim>> from per-clip (T_i, dim) arrays, in one concatenation."""
    lengths = np.array([a.shape[0] for a in arrays], dtype=np.int64)
    offsets = np.zeros(len(arrays) + 1, dtype=np.int32)
    offsets[1:] = np.cumsum(lengths)
    flat = np.concatenate([np.asarray(a, dtype=np.float32) for a in arrays]) if arrays else np.zeros((0, dim))
    values = pa.array(np.ascontiguousarray(flat, dtype=np.float32).reshape(-1))
    frames = pa.FixedSizeListArray.from_arrays(values, dim)
    return pa.ListArray.from_arrays(pa.array(offsets), frames)


def _check_clips(clips: Sequence[FittedClip], layout: ModalityLayout, seen: set[str]) -> set[str]:
    """Validate ``clips`` in order (:func:`validate_clip`) and return their ids, refusing an id repeated among
    them or already in ``seen`` (the shard's clips so far)."""
    ids: set[str] = set()
    for clip in clips:
        validate_clip(clip, layout)
        cid = clip.clip.id
        if cid in seen or cid in ids:
            raise ValueError(f"clip {cid!r} appears twice; clip ids must be unique within a shard")
        ids.add(cid)
    return ids


def _table(clips: Sequence[FittedClip], layout: ModalityLayout) -> pa.Table:
    """The shard table (one row per clip) of clips already validated against ``layout``."""
    schema = arrow_schema(layout)
    rows = [clip_metadata(c) for c in clips]
    columns: dict[str, pa.Array] = {
        name: pa.array([r[name] for r in rows], type=type_) for name, type_ in METADATA_COLUMNS.items()
    }
    identity = np.stack([np.asarray(c.identity, dtype=np.float32) for c in clips]) if clips else np.zeros((0,))
    columns[IDENTITY_COLUMN] = pa.FixedSizeListArray.from_arrays(
        pa.array(identity.astype(np.float32).reshape(-1)), layout.identity_dim
    )
    for modality in layout.modalities:
        columns[modality.name] = _modality_array([c.params[modality.name] for c in clips], modality.dim)
    return pa.Table.from_arrays([columns[f.name] for f in schema], schema=schema)


def to_table(clips: Sequence[FittedClip], layout: ModalityLayout) -> pa.Table:
    """Validate ``clips`` and build the shard table (one row per clip)."""
    _check_clips(clips, layout, set())
    return _table(clips, layout)


@contextmanager
def _parquet_writer(path: Path, schema: pa.Schema) -> Iterator[pq.ParquetWriter]:
    """A Parquet writer on a temporary file beside ``path`` (:func:`m3t.atomic.atomic_path`), flushed to disk and
    moved over ``path`` when the block ends cleanly; on any error the temporary file goes and ``path`` stays."""
    if not path.parent.is_dir():
        raise FileNotFoundError(f"cannot write shard {path}: directory {path.parent} does not exist; create it first")
    with atomic_path(path, keep_identical=True) as tmp, open(tmp, "wb") as fh:
        with pq.ParquetWriter(fh, schema, compression=COMPRESSION) as writer:
            yield writer
        fh.flush()
        os.fsync(fh.fileno())


class ShardWriter:
    """Write a fitted-motion shard batch by batch, in row groups of about :data:`ROW_GROUP_FRAMES` frames.

    Memory holds the clips of one unfinished row group, never the whole shard. The row groups depend only on
    the sequence of clips, not on how it was split into :meth:`write` calls, so the bytes equal those of
    :func:`write_shard` over all the clips. The file appears when the ``with`` block ends cleanly (atomically,
    as :func:`write_table_atomic`; an unchanged shard keeps its mtime); an exception inside the block leaves no
    file and an older shard at ``path`` untouched::

        with ShardWriter(path, layout) as writer:
            for batch in batches:
                writer.write(batch)

    Attributes
    ----------
    path : Path
        The shard being written.
    layout : ModalityLayout
        The layout every clip is checked against and which the file stores.
    clips_written, frames_written : int
        Clips (and their frames) accepted by :meth:`write` so far; the last row group's reach the file when the
        block ends.
    """

    def __init__(self, path: str | os.PathLike, layout: ModalityLayout):
        self.path = Path(path)
        self.layout = layout
        self.clips_written = 0
        self.frames_written = 0
        self._schema = arrow_schema(layout)
        self._ids: set[str] = set()
        self._group: list[FittedClip] = []
        self._group_frames = 0
        self._groups = 0
        self._opened = False
        self._stack: ExitStack | None = None
        self._writer: pq.ParquetWriter | None = None

    def __enter__(self) -> Self:
        if self._opened:
            raise RuntimeError(f"ShardWriter({self.path}) was already opened; make a new writer for each shard")
        self._opened = True
        stack = ExitStack()
        self._writer = stack.enter_context(_parquet_writer(self.path, self._schema))
        self._stack = stack
        return self

    def write(self, clips: Sequence[FittedClip]) -> None:
        """Validate ``clips`` (as :func:`to_table`; ids unique over the whole shard) and append them.

        A batch with a bad clip is refused whole (``ValueError`` naming the clip), before any of it is kept.
        """
        if self._writer is None:
            raise RuntimeError(f"ShardWriter({self.path}): write inside its `with` block, where the shard is open")
        clips = list(clips)
        self._ids |= _check_clips(clips, self.layout, self._ids)
        for clip in clips:
            frames = clip.num_frames
            if self._group and self._group_frames + frames > ROW_GROUP_FRAMES:
                self._write_group()
            self._group.append(clip)
            self._group_frames += frames
            if self._group_frames >= ROW_GROUP_FRAMES:
                self._write_group()
            self.clips_written += 1
            self.frames_written += frames

    def _write_group(self) -> None:
        self._writer.write_table(_table(self._group, self.layout))
        self._groups += 1
        self._group, self._group_frames = [], 0

    def __exit__(self, exc_type, exc, tb) -> None:
        stack, self._stack = self._stack, None
        try:
            if exc_type is not None:  # the temporary file goes, an older shard stays; the exception propagates
                stack.__exit__(exc_type, exc, tb)
            else:
                with stack:  # an error here (a full disk) also removes the temporary file
                    if self._group or not self._groups:  # an empty shard is one empty row group, as pq.write_table
                        self._write_group()
        finally:
            self._writer = None


def write_shard(path: str | os.PathLike, clips: Sequence[FittedClip], layout: ModalityLayout) -> Path:
    """Write ``clips`` to the Parquet shard ``path`` atomically and return the path.

    Every clip is validated against ``layout``. The data goes to a hidden temporary file in the destination
    directory, in row groups of about :data:`ROW_GROUP_FRAMES` frames (:class:`ShardWriter`), is flushed to
    disk and then moved over ``path``; on any error the temporary file is removed and an existing ``path`` is
    left untouched.
    """
    with ShardWriter(path, layout) as writer:
        writer.write(clips)
    return writer.path


def write_table_atomic(path: str | os.PathLike, table: pa.Table) -> Path:
    """Write an Arrow table to Parquet at ``path`` with :func:`m3t.atomic.atomic_path` (shared by all shards): a
    killed or failed write (a full disk names the file) leaves the previous shard intact and no temporary file,
    and a shard whose bytes would not change keeps its mtime."""
    path = Path(path)
    with _parquet_writer(path, table.schema) as writer:
        writer.write_table(table)
    return path


def parquet_file(path: Path) -> pq.ParquetFile:
    if not path.is_file():
        raise FileNotFoundError(f"shard {path} does not exist")
    try:
        return pq.ParquetFile(path)
    except pa.ArrowInvalid as exc:
        raise ShardFormatError(f"{path}: not a readable Parquet file ({exc}); the shard is damaged") from exc


def shard_layout(path: str | os.PathLike) -> ModalityLayout:
    """The modality layout stored in a shard's metadata (checks the schema version; reads no rows)."""
    path = Path(path)
    return check_schema_metadata(parquet_file(path).schema_arrow.metadata, str(path))


def _unstack_modality(column: pa.ChunkedArray, dim: int, lengths: np.ndarray, source: str, name: str,
                      first_row: int):
    """Per-row (T_i, dim) float32 arrays from a list<fixed_size_list> column, with one bulk copy; the column's
    rows start at row ``first_row`` of the shard (errors name the shard's row)."""
    lists = column.combine_chunks()
    if lists.null_count:
        raise ShardFormatError(f"{source}: column {name!r} has null rows; the shard is damaged")
    stored = lists.value_lengths().to_numpy(zero_copy_only=False).astype(np.int64)
    if not np.array_equal(stored, lengths):
        raise ShardFormatError(f"{source}: column {name!r} frame counts disagree with num_frames; the shard is damaged")
    frames = lists.flatten()
    values = frames.flatten().to_numpy(zero_copy_only=False)
    flat = np.array(values, dtype=np.float32).reshape(int(lengths.sum()), dim)  # writable copy
    finite = np.isfinite(flat).all(axis=1)  # (sum T,)
    if not finite.all():  # the writer refuses NaN / inf: such a shard was edited or damaged after writing
        row = first_row + int(np.searchsorted(np.cumsum(lengths), int(np.argmin(finite)), side="right"))
        raise ShardFormatError(f"{source}: row {row} (0-based), column {name!r} holds NaN or inf; the shard is damaged "
                               "(re-run the stage that wrote it)")
    return np.split(flat, np.cumsum(lengths)[:-1]) if len(lengths) else []


def _open_shard(path: Path, modalities: Sequence[str] | None) -> tuple[pq.ParquetFile, ModalityLayout, list[str]]:
    """The open file, its stored layout and the modalities to read, after the checks that need no rows."""
    source = str(path)
    pf = parquet_file(path)
    try:
        layout = check_schema_metadata(pf.schema_arrow.metadata, source)
        try:
            expected = arrow_schema(layout)
        except ValueError as exc:  # a layout no writer makes: the metadata was edited
            raise ShardFormatError(f"{source}: its stored layout cannot be a shard's ({exc}); the shard is "
                                   "damaged") from exc
        check_column_types(pf.schema_arrow, expected, source, "the shard was edited or not written by m3t; re-run "
                                                              "the stage that wrote it")
        names = list(layout.names if modalities is None else modalities)
        for name in names:
            if name not in layout.names:
                raise KeyError(f"{source}: no modality {name!r}; the shard has {list(layout.names)}")
    except BaseException:
        pf.close()
        raise
    return pf, layout, names


def _contents(table: pa.Table, path: Path, layout: ModalityLayout, names: list[str], first_row: int,
              seen: set[str]) -> ShardContents:
    """Rows of a shard (a row group, from row ``first_row``) -> :class:`ShardContents`; ``seen`` holds the ids
    of the rows before, and gets these."""
    source = str(path)
    n = table.num_rows
    meta = {name: table.column(name).to_pylist() for name in METADATA_COLUMNS}
    counts = Counter(meta["id"])
    if len(counts) != n or not seen.isdisjoint(counts):  # the writer refuses repeated ids: joins are keyed by them
        twice = sorted(i for i, count in counts.items() if count > 1 or i in seen)
        raise ShardFormatError(f"{source}: clip ids {twice[:5]} appear twice; the shard is damaged (re-run the "
                               "stage that wrote it)")
    seen.update(counts)
    lengths = np.asarray(meta["num_frames"], dtype=np.int64)
    identity_col = table.column(IDENTITY_COLUMN).combine_chunks()
    identity_values = identity_col.flatten().to_numpy(zero_copy_only=False)
    identity = np.array(identity_values, dtype=np.float32).reshape(n, layout.identity_dim)
    params = {
        name: _unstack_modality(table.column(name), layout.dims[name], lengths, source, name, first_row)
        for name in names
    }
    clips = []
    for i in range(n):
        clip = clip_from_columns(meta, i)
        clips.append(
            FittedClip(
                clip=clip,
                key=meta["key"][i],
                params={name: params[name][i] for name in names},
                identity=identity[i],
                camera=json.loads(meta["camera"][i]),
                metrics=metrics_from_json(meta["metrics"][i]),
                body_model=meta["body_model"][i],
            )
        )
    return ShardContents(path=path, layout=layout, clips=tuple(clips), lengths=lengths)


def _columns(names: Sequence[str]) -> list[str]:
    """The Parquet columns that reading the modalities ``names`` takes: the metadata, identity and those."""
    return [*METADATA_COLUMNS, IDENTITY_COLUMN, *names]


def _group_batches(pf: pq.ParquetFile, path: Path, layout: ModalityLayout, names: list[str], group: int,
                   first_row: int, seen: set[str]) -> Iterator[ShardContents]:
    """Row group ``group`` (whose first row is the shard's row ``first_row``), :data:`READ_BATCH_ROWS` rows at a
    time; ``seen`` holds the ids of the rows before and gets these."""
    for batch in pf.iter_batches(batch_size=READ_BATCH_ROWS, row_groups=[group], columns=_columns(names),
                                 use_threads=True):
        contents = _contents(pa.Table.from_batches([batch]), path, layout, names, first_row, seen)
        first_row += len(contents)
        yield contents


def _joined(path: Path, layout: ModalityLayout, parts: Sequence[ShardContents]) -> ShardContents:
    """Consecutive parts of one shard as one :class:`ShardContents`."""
    lengths = np.concatenate([p.lengths for p in parts]) if parts else np.zeros(0, dtype=np.int64)
    return ShardContents(path=path, layout=layout, clips=tuple(c for p in parts for c in p.clips), lengths=lengths)


def _shard_batches(pf: pq.ParquetFile, path: Path, layout: ModalityLayout, names: list[str],
                   whole_groups: bool) -> Iterator[ShardContents]:
    """The rows of an open shard in file order, one :class:`ShardContents` per row group (``whole_groups``) or
    per batch of at most :data:`READ_BATCH_ROWS` rows; closes the file when done."""
    seen: set[str] = set()
    first_row = 0
    with pf:
        for group in range(pf.num_row_groups):
            parts: Iterable[ShardContents] = _group_batches(pf, path, layout, names, group, first_row, seen)
            if whole_groups:
                parts = [_joined(path, layout, list(parts))]
            for contents in parts:
                first_row += len(contents)
                yield contents


def iter_shard(path: str | os.PathLike, modalities: Sequence[str] | None = None) -> Iterator[ShardContents]:
    """Read a shard one Parquet row group at a time (memory for one group, see :data:`ROW_GROUP_FRAMES`).

    The file's metadata is checked at the call, the rows as each group is read: the same checks, raising the
    same errors, as :func:`read_shard`, whose result is the concatenation of these groups. Errors name the row
    within the whole shard, and a clip id repeated in a later group is refused.

    Parameters
    ----------
    path : path of the shard.
    modalities : the modality columns to read (default: all in the stored layout).

    Returns
    -------
    Iterator[ShardContents]
        One per row group, in file order; each has the shard's ``path`` and ``layout``.
    """
    path = Path(path)
    pf, layout, names = _open_shard(path, modalities)
    return _shard_batches(pf, path, layout, names, whole_groups=True)


def read_row_group(path: str | os.PathLike, group: int, modalities: Sequence[str] | None = None) -> ShardContents:
    """One row group of a shard (``group`` counts from 0, as :func:`iter_shard` yields them), with the checks
    :func:`iter_shard` makes on it (errors name the row within the whole shard). Ids repeated in other groups are
    not looked for: read the shard through :func:`iter_shard` once to know them unique."""
    path = Path(path)
    pf, layout, names = _open_shard(path, modalities)
    with pf:
        if not 0 <= group < pf.num_row_groups:
            raise IndexError(f"{path}: no row group {group}; the shard has {pf.num_row_groups}")
        first_row = sum(pf.metadata.row_group(g).num_rows for g in range(group))
        return _joined(path, layout, list(_group_batches(pf, path, layout, names, group, first_row, set())))


def read_shard(path: str | os.PathLike, modalities: Sequence[str] | None = None) -> ShardContents:
    """Read a shard into memory (all its row groups; :func:`iter_shard` reads one at a time).

    Parameters
    ----------
    path : path of the shard.
    modalities : the modality columns to read (default: all in the stored layout).

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ShardFormatError
        Missing / other schema version, damaged metadata, a column of another type, a null or non-finite frame
        (naming its row), a repeated clip id; the message names the file.
    KeyError
        A requested modality is not in the shard's layout.
    """
    path = Path(path)
    pf, layout, names = _open_shard(path, modalities)
    return _joined(path, layout, list(_shard_batches(pf, path, layout, names, whole_groups=False)))


def iter_split(shards_dirs: Sequence[str | os.PathLike] | str | os.PathLike, split: str,
               modalities: Sequence[str] | None = None) -> Iterator[FittedClip]:
    """The fitted clips of ``split`` across one or several corpora's shard folders (in the given order),
    :data:`READ_BATCH_ROWS` clips in memory at a time.

    Every shard is checked to exist at the call (a missing one names the stage to run); a clip id found in two
    corpora is refused when it is reached (ids key every downstream join). Only the ids seen so far are kept.
    """
    return _split_clips(split_shards(shards_dirs, split), modalities)


def split_shards(shards_dirs: Sequence[str | os.PathLike] | str | os.PathLike, split: str) -> list[Path]:
    """The shard files of ``split`` in one or several corpora's folders; a missing one names the stage to run."""
    dirs = [shards_dirs] if isinstance(shards_dirs, (str, os.PathLike)) else list(shards_dirs)
    paths = []
    for folder in dirs:
        path = Path(folder) / f"{split}.parquet"
        if not path.exists():
            raise FileNotFoundError(f"shard {path} not found; run the fit-corpus stage for that corpus first "
                                    f"(dvc repro, or python -m m3t.stages.fit_corpus --corpus {Path(folder).name})")
        paths.append(path)
    return paths


def _split_clips(paths: list[Path], modalities: Sequence[str] | None) -> Iterator[FittedClip]:
    seen: dict[str, Path] = {}
    for path in paths:
        pf, layout, names = _open_shard(path, modalities)
        for batch in _shard_batches(pf, path, layout, names, whole_groups=False):
            for clip in batch.clips:
                if clip.clip.id in seen:
                    raise ValueError(f"clip id {clip.clip.id!r} is in both {seen[clip.clip.id]} and {path}; clip ids "
                                     "must be unique across data.train_corpora")
                seen[clip.clip.id] = path
                yield clip


def read_split(shards_dirs: Sequence[str | os.PathLike] | str | os.PathLike, split: str,
               modalities: Sequence[str] | None = None) -> list[FittedClip]:
    """The fitted clips of ``split`` across one or several corpora's shard folders, in memory (the list of
    :func:`iter_split`).

    A missing shard names the stage to run; a clip id found in two corpora is refused (ids key every
    downstream join)."""
    return list(iter_split(shards_dirs, split, modalities))


def read_production_split(data, split: str) -> list:
    """The fitted clips of ``split`` over ``data``'s training corpora (a :class:`m3t.shards.folders.DataConfig`),
    without the clip kinds ``data.production_skip_kinds`` leaves out: the data of the production models (SMLM,
    SGSA / PT, back-translation)."""
    return data.for_production(read_split(data.shards_dirs, split))


def production_data_version(data) -> str:
    """The data version a production model trains on: the digest of the train and dev shards, plus the kinds
    left out."""
    return data.production_version(data_version([folder / f"{split}.parquet" for folder in data.shards_dirs
                                                 for split in ("train", "dev")]))


def data_version(paths: list[Path]) -> str:
    """Digest of the data files a model is trained on, by name and bytes (part of every trainer's resume key and
    checkpoint)."""
    chunks: list[bytes] = []
    for path in paths:
        chunks += [Path(path).name.encode(), file_digest_bytes(path)]
    return chunks_digest(chunks, length=16)
