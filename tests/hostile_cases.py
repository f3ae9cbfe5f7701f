"""Hostile inputs: files that declare more than they hold, bombs by compression and by aliasing, wrong types in
every column of every table format, and headers no writer makes.

Each case is a :class:`malformed_cases.Case`, judged by :func:`malformed_cases.classify`; the cases join the
malformed-input table (``tests/corpora/test_malformed_inputs.py``, ``benchmarks/malformed_report.py``, which
also measures each case's time and peak memory). Every file here is small (a few kB, one of a few MB): what it
*declares* is gigabytes, and a reader that trusted the declaration would allocate them.

Layouts: zip archives as APPNOTE.TXT (PKWARE) section 4.3 lays them out (the central directory's uncompressed
size at byte 24 of each ``PK\\x01\\x02`` entry), ``.npy`` headers as numpy's format specification (NEP 1), torch
checkpoints as ``torch.save``'s zip format writes them, HDF5 through h5py, ``.pose`` headers as pose-format
(``pose_format/pose_header.py``) writes them, the lexicon ``.pose`` files being real ones; the tables' rows are
those of :mod:`malformed_cases`, whose builders cite their sources.
"""
from __future__ import annotations

import gzip
import io
import pickle
import struct
import zipfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import malformed_cases as mc
import numpy as np
from malformed_cases import CLEAR, Case

GIB = 2**30


# ----------------------------------------------------------------------------------------- building blocks
def npy_header(shape: tuple[int, ...], descr: str = "<f4") -> bytes:
    """A version 1.0 ``.npy`` header declaring ``shape`` (NEP 1: magic, version, header length, dict literal)."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": descr, "fortran_order": False, "shape": shape})
    return buffer.getvalue()


def write_zip(path: Path, members: dict[str, bytes], deflate: bool = False) -> Path:
    mode = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", mode) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


def deflated_zeros(path: Path, name: str, nbytes: int, header: bytes = b"") -> None:
    """Append to the zip ``path`` a member of ``header`` + ``nbytes`` zero bytes, deflated while streamed (about
    1,000:1), so building a 64 MB bomb costs a 64 kB file and no 64 MB buffer."""
    with zipfile.ZipFile(path, "a", zipfile.ZIP_DEFLATED) as archive, archive.open(name, "w", force_zip64=True) as fh:
        fh.write(header)
        chunk = bytes(2**20)
        for _ in range(nbytes // len(chunk)):
            fh.write(chunk)


def forge_size(path: Path, member_suffix: str, size: int) -> None:
    """Rewrite the uncompressed size the central directory declares for the member ending in ``member_suffix``."""
    data = bytearray(path.read_bytes())
    at = data.find(b"PK\x01\x02")
    while at >= 0:
        name_length = struct.unpack_from("<H", data, at + 28)[0]
        name = bytes(data[at + 46: at + 46 + name_length]).decode()
        if name.endswith(member_suffix):
            struct.pack_into("<I", data, at + 24, size)
            path.write_bytes(bytes(data))
            return
        at = data.find(b"PK\x01\x02", at + 46)
    raise AssertionError(f"no member ending in {member_suffix!r} in {path}")


def track_archive(tmp: Path) -> tuple[Path, dict[str, np.ndarray]]:
    path = mc.track_file(tmp)
    with np.load(path) as data:
        return path, {name: data[name] for name in data.files}


def npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def load_track(path: Path):
    from m3t.trackers.track import load_track

    return load_track(path)


# ----------------------------------------------------------------------------------------- zip / npz / npy
def track_npy_declares(tmp: Path):
    """``keypoints.npy`` whose header declares (10**6, 543, 2) float32 (4.3 GB) over 24 bytes of data."""
    path, arrays = track_archive(tmp)
    members = {f"{k}.npy": npy_bytes(v) for k, v in arrays.items()}
    members["keypoints.npy"] = npy_header((10**6, 543, 2)) + bytes(24)
    write_zip(path, members)
    return lambda: load_track(path)


def track_zip_bomb(tmp: Path):
    """``keypoints.npy`` a real array of 64 MB of zeros, deflated to ~64 kB."""
    path, arrays = track_archive(tmp)
    write_zip(path, {f"{k}.npy": npy_bytes(v) for k, v in arrays.items() if k != "keypoints"})
    deflated_zeros(path, "keypoints.npy", 64 * 2**20, npy_header((16 * 2**20,)))
    return lambda: load_track(path)


def track_forged_directory(tmp: Path):
    """A stored member whose central-directory entry declares 2 GB (the member holds its real ~13 kB)."""
    path, arrays = track_archive(tmp)
    write_zip(path, {f"{k}.npy": npy_bytes(v) for k, v in arrays.items()})
    forge_size(path, "keypoints.npy", 2 * GIB)
    return lambda: load_track(path)


def track_npy_garbage_header(tmp: Path):
    """``confidence.npy`` whose header dict is not a Python literal."""
    path, arrays = track_archive(tmp)
    members = {f"{k}.npy": npy_bytes(v) for k, v in arrays.items()}
    text = b"{'descr': os.system('x'), 'fortran_order': False, 'shape': (3,), }"
    members["confidence.npy"] = b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text) + 1) + text + b"\n"
    write_zip(path, members)
    return lambda: load_track(path)


def model_npy_declares(tmp: Path):
    """A body-model ``.npy`` (SMPL-X eyelid buffers are shipped this way) declaring 10**10 float64."""
    from m3t.body.model_files import load_model_arrays

    path = tmp / "l_eyelid.npy"
    path.write_bytes(npy_header((10**10,), "<f8") + bytes(64))
    return lambda: load_model_arrays(path)


def model_pickle_declares(tmp: Path):
    """A 20-byte model pickle whose one bytes object (BINBYTES8) declares 8 GB: the C unpickler allocates a
    declared length before reading it."""
    from m3t.body.model_files import load_model_arrays

    path = tmp / "SMPLX_NEUTRAL.pkl"
    path.write_bytes(b"\x80\x04\x8e" + struct.pack("<Q", 8 * 10**9) + b"abc")
    return lambda: load_model_arrays(path)


def model_npz_bomb(tmp: Path):
    """A body-model ``.npz`` (SMPL-X's layout: ``v_template`` ...) whose ``shapedirs`` is 64 MB of deflated zeros."""
    from m3t.body.model_files import load_model_arrays

    path = write_zip(tmp / "SMPLX_NEUTRAL.npz", {"v_template.npy": npy_bytes(np.zeros((4, 3)))}, deflate=True)
    deflated_zeros(path, "shapedirs.npy", 64 * 2**20, npy_header((8 * 2**20,), "<f8"))
    return lambda: load_model_arrays(path)


def _checkpoint(tmp: Path) -> Path:
    import torch

    path = tmp / "tokenizer.pt"
    torch.save({"format": "m3t-tokenizer", "state_dict": {"w": torch.zeros(4)}}, path)
    return path


def read_tokenizer(path: Path):
    from m3t.checkpoints import read_checkpoint

    return read_checkpoint(path, "m3t-tokenizer", "tokenizer", "train_tokenizer")


def checkpoint_forged_record(tmp: Path):
    """A ``torch.save`` checkpoint whose tensor record's directory entry declares 3.9 GB (torch's reader allocates
    the declared size of a record before reading it)."""
    path = _checkpoint(tmp)
    forge_size(path, "data/0", 4_000_000_000)
    return lambda: read_tokenizer(path)


def checkpoint_deflated_member(tmp: Path):
    """A checkpoint with one more record: 64 MB of zeros deflated to ~64 kB."""
    path = _checkpoint(tmp)
    deflated_zeros(path, "tokenizer/data/1", 64 * 2**20)
    return lambda: read_tokenizer(path)


def nlf_forged_record(tmp: Path):
    """An NLF ``.pt`` output (``pose`` (N, 165), ``betas``, ``trans``) whose ``pose`` record declares 3.9 GB."""
    import torch

    from m3t.trackers.nlf_reader import read_nlf

    path = tmp / "clip.nlf.pt"
    torch.save({"pose": torch.zeros(2, 165), "betas": torch.zeros(2, 10), "trans": torch.zeros(2, 3)}, path)
    forge_size(path, "data/0", 4_000_000_000)
    return lambda: read_nlf(path)


def zip_member_past_end(tmp: Path):
    """A track whose last member was cut off while the central directory still lists it (a copy stopped early,
    then its directory appended by a tool that trusted it)."""
    path, arrays = track_archive(tmp)
    write_zip(path, {f"{k}.npy": npy_bytes(v) for k, v in arrays.items()})
    data = bytearray(path.read_bytes())
    at = data.find(b"PK\x01\x02")
    struct.pack_into("<I", data, at + 42, len(data))  # the first member's local header offset: past the end
    path.write_bytes(bytes(data))
    return lambda: load_track(path)


# ----------------------------------------------------------------------------------------- gzip pickles
def gzip_pickle_bomb(path: Path, nbytes: int = 300 * 2**20, trailer: int | None = None) -> None:
    """An slt split file: the pickle (protocol 3, unframed) of ``[{name, signer, gloss, text, sign}]`` whose
    ``sign`` is ``nbytes`` zero bytes, gzip-compressed while streamed (about 1,000:1), so the builder holds no
    ``nbytes`` buffer; ``trailer``: the size gzip's trailer then declares (the real size modulo 2^32 unless
    rewritten)."""
    placeholder = b"Z" * 300
    entry = {"name": "train/x", "signer": "s", "gloss": "", "text": "", "sign": placeholder}
    data = pickle.dumps([entry], protocol=3)
    opcode = b"B" + struct.pack("<I", len(placeholder)) + placeholder  # BINBYTES: length, then the bytes
    head, tail = data.split(opcode)
    with gzip.open(path, "wb") as fh:
        fh.write(head + b"B" + struct.pack("<I", nbytes))
        chunk = bytes(2**20)
        for _ in range(nbytes // len(chunk)):
            fh.write(chunk)
        fh.write(tail)
    if trailer is not None:
        data = bytearray(path.read_bytes())
        data[-4:] = trailer.to_bytes(4, "little")
        path.write_bytes(bytes(data))


def slt_gzip_bomb(tmp: Path):
    """An slt split file whose pickle holds 300 MB of zero bytes: 0.3 MB gzip-compressed."""
    root = mc.slt_entry(tmp, listing=False)
    gzip_pickle_bomb(root / mc.SLT_TRAIN)
    return lambda: mc.listed("slt_pickle", root, 7)


def slt_gzip_forged_trailer(tmp: Path):
    """The same bomb with gzip's size trailer rewritten to 100 bytes: refused while streaming instead."""
    root = mc.slt_entry(tmp, listing=False)
    gzip_pickle_bomb(root / mc.SLT_TRAIN, trailer=100)
    return lambda: mc.listed("slt_pickle", root, 7)


class _Calls:
    """Pickles as ``func(*args)``."""

    def __init__(self, func, *args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


def _slt_sign(tmp: Path, sign):
    root = mc.slt_entry(tmp, {"name": "train/odd", "signer": "s", "gloss": "G", "text": "t", "sign": sign}, listing=False)
    return lambda: mc.listed("slt_pickle", root, 7)


def slt_ndarray_shape(tmp: Path):
    """A record whose ``sign`` is ``numpy.ndarray((10**9, 12), float32)``: 48 GB, uninitialised."""
    return _slt_sign(tmp, _Calls(np.ndarray, (10**9, 12), np.dtype("float32")))


def slt_reconstruct_shape(tmp: Path):
    """A record whose ``sign`` is numpy's pickle reconstruction of an array started at 10**9 elements."""
    core = getattr(np, "_core", None) or np.core
    return _slt_sign(tmp, _Calls(core.multiarray._reconstruct, np.ndarray, (10**9,), b"b"))


# ----------------------------------------------------------------------------------------- HDF5 (MEAD)
def _mead(tmp: Path, write):
    """The released MEAD tree (:func:`corpus_fixtures.build_mead_release`) plus clip W009/front/x/level_1/001, a
    file ``write(h5py.File)`` makes beside the release's other arrays; read as fit-corpus reads it."""
    import corpus_fixtures as fx
    import h5py

    root, where = tmp / "mead", "W009/front/x/level_1/001"
    fx.build_mead_release(root)
    path = root / where / "shape_pose_cam.hdf5"
    path.parent.mkdir(parents=True)
    with h5py.File(path, "w") as f:
        for key, value in fx.flame_arrays(4, exp=100, shape=300, batch_axis=True).items():
            if key != "exp":
                f.create_dataset(key, data=value)
        write(f)
    return lambda: _mead_source(root, where)


def _mead_source(root: Path, where: str):
    from m3t.corpora.base import open_corpus

    corpus = open_corpus("mead", root)
    clip = next(c for c in corpus.listing().clips if c.media.startswith(where))
    return corpus.source(clip)


def mead_fill_bomb(tmp: Path):
    """``exp`` declared (1, 10**7, 10**4) float32 (400 GB), chunked and compressed, no chunk written: HDF5 returns
    the fill value for every unwritten chunk."""
    return _mead(tmp, lambda f: f.create_dataset("exp", shape=(1, 10**7, 10**4), dtype="f4", chunks=(1, 64, 100),
                                                 compression="gzip"))


def mead_compressed_bomb(tmp: Path):
    """``exp`` 64 MB of real zeros, gzip-compressed in chunks to ~100 kB."""
    def write(f):
        data = f.create_dataset("exp", shape=(1, 2**14, 1024), dtype="f4", chunks=(1, 1024, 1024), compression="gzip")
        for start in range(0, 2**14, 1024):
            data[0, start:start + 1024] = 0.0

    return _mead(tmp, write)


def mead_group(tmp: Path):
    """``exp`` a group holding the array instead of the array."""
    return _mead(tmp, lambda f: f.create_group("exp").create_dataset("values", data=np.zeros((1, 4, 100), "f4")))


# ----------------------------------------------------------------------------------------- params.yaml
def params_text(tmp: Path, text: str):
    from m3t.config import load_params

    path = tmp / "params.yaml"
    path.write_text(text, encoding="utf-8")
    return lambda: load_params(path)


def params_known_value(tmp: Path, value: str):
    """params.yaml with ``data.production_skip_kinds`` (a list) set to the YAML text ``value``."""
    text = (mc.ROOT / "params.yaml").read_text(encoding="utf-8")
    old = "  production_skip_kinds: []"
    assert old in text, f"params.yaml no longer holds {old!r}"
    return params_text(tmp, text.replace(old, f"  production_skip_kinds: {value}", 1))


def params_alias_bomb(tmp: Path):
    """A few hundred bytes of nested aliases under a known key that expand to 10**9 leaves: level 0 a list of ten
    strings, level i a list of ten aliases of level i - 1."""
    levels = ["&a0 [" + ", ".join(["lol"] * 10) + "]"]
    levels += [f"&a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 10)]
    return params_known_value(tmp, "[" + ", ".join(levels) + "]")


def params_recursive_alias(tmp: Path):
    """A value that contains itself (``&loop [*loop]``) under a known key."""
    return params_known_value(tmp, "&loop [*loop]")


def params_deep_nesting(tmp: Path):
    """50,000 nested lists under a known key."""
    return params_text(tmp, "data:\n  corpora: " + "[" * 50_000 + "]" * 50_000 + "\n")


def params_huge(tmp: Path):
    """params.yaml followed by a 17 MB comment: above the 16 MiB a params file may have."""
    from m3t.config import load_params

    path = tmp / "params.yaml"
    with open(path, "w", encoding="utf-8") as fh:
        fh.write((mc.ROOT / "params.yaml").read_text(encoding="utf-8") + "#")
        fh.writelines("x" * 2**20 for _ in range(17))
    return lambda: load_params(path)


# ----------------------------------------------------------------------------------------- .pose headers
def _pose_source(tmp: Path) -> Path:
    from m3t.corpora.fingerspelling import lexicon_root

    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        first = next(row for row in __import__("csv").DictReader(fh))
    return lexicon_root() / first["path"]


def pose_rewritten(change, body: bool = True):
    """A real lexicon ``.pose`` file whose header is rewritten by ``change(header)`` (pose-format's
    ``PoseHeader``) and written back with pose-format's own header writer, the body bytes kept."""

    def run(tmp: Path):
        from pose_format.pose_header import PoseHeader

        from m3t.corpora.posefile import _header, read_pose

        source = _pose_source(tmp)
        header, reader = _header(source)
        rest = source.read_bytes()[reader.read_offset:]
        change(header)
        buffer = io.BytesIO()
        PoseHeader.write(header, buffer)
        path = tmp / "clip.pose"
        path.write_bytes(buffer.getvalue() + rest)
        return lambda: read_pose(path)

    return run


def pose_body_field(offset: int, fmt: str, value):
    """A real lexicon ``.pose`` file with one field of its v0.2 body preamble (fps float, frames uint32, people
    uint16) rewritten; read header-only, as the listing reads it."""

    def run(tmp: Path):
        from m3t.corpora.posefile import _header, read_pose_info

        source = _pose_source(tmp)
        _, reader = _header(source)
        data = bytearray(source.read_bytes())
        struct.pack_into(fmt, data, reader.read_offset + offset, value)
        path = tmp / "clip.pose"
        path.write_bytes(bytes(data))
        return lambda: read_pose_info(path)

    return run


def _set_format(text: str, first_only: bool = False):
    def change(header):
        for component in header.components[:1] if first_only else header.components:
            component.format = text

    return change


def _no_points(header):
    for component in header.components:
        component.points, component.limbs = [], []
        component.colors = np.zeros((0, 3), np.int64)


# ----------------------------------------------------------------------------------------- wrong column types
def _wrong_array(field, rows: int):
    """A column of another Arrow type than ``field``'s, of ``rows`` rows: int64 for a list or a string, a string
    for anything else (numbers written as text)."""
    import pyarrow as pa

    if pa.types.is_list(field.type) or pa.types.is_fixed_size_list(field.type) or pa.types.is_string(field.type):
        return pa.array(list(range(rows)), pa.int64())
    return pa.array([str(i) for i in range(rows)], pa.string())


def wrong_type(column: str, write, read):
    """A table written by ``write(tmp)`` whose ``column`` is rewritten with another Arrow type; read by ``read``."""
    def build(tmp: Path):
        path = write(tmp)
        mc.rewrite(path, lambda t: t.set_column(t.schema.get_field_index(column), column,
                                                _wrong_array(t.schema.field(column), t.num_rows)))
        return lambda: read(path)

    return build


def _read_shard(path: Path):
    from m3t.shards import read_shard

    return read_shard(path)


def _read_token_shard(path: Path):
    from m3t.shards.tokens import read_token_shard

    return read_token_shard(path)


def _columns(schema_of) -> list[str]:
    return [field.name for field in schema_of()]


def _shard_columns():
    from m3t.shards.schema import arrow_schema

    return arrow_schema(mc._layout())


def _token_columns():
    from m3t.shards.tokens import TokenInfo, token_schema

    return token_schema(TokenInfo({"body": 16, "face": 8}, 4, {}))


# ----------------------------------------------------------------------------------------- frame images
def frame_declares(kind: str):
    """A frame image whose header declares more pixels than any camera gives, the pixel data absent: a PNG whose
    IHDR chunk (PNG spec 11.2.2: width, height, bit depth, colour type...) says 30,000 x 30,000 RGB, or a JPEG whose
    SOF0 segment (ITU T.81 B.2.2: precision, height, width, components) says 65,000 x 65,000."""

    def build(tmp: Path):
        import zlib

        from m3t.trackers.media import read_image_rgb

        if kind == "png":
            ihdr = struct.pack(">IIBBBBB", 30_000, 30_000, 8, 2, 0, 0, 0)
            data = (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr
                    + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr)) + bytes(64))
        else:
            sof = struct.pack(">BHHB", 8, 65_000, 65_000, 3) + b"\x01\x11\x00\x02\x11\x01\x03\x11\x01"
            data = b"\xff\xd8\xff\xc0" + struct.pack(">H", len(sof) + 2) + sof + bytes(64)
        path = tmp / f"00001.{kind}"
        path.write_bytes(data)
        return lambda: read_image_rgb(path)

    return build


# ----------------------------------------------------------------------------------------- the table
# Each builder above writes its input into the case's folder and returns the read (a callable); the case's
# ``build`` runs the builder, its ``run`` the read, so the report measures the read alone.
_PENDING: dict[Path, Callable[[], Any]] = {}


def _read_pending(tmp: Path):
    return _PENDING.pop(tmp)()


def _staged(case: Case) -> Case:
    builder = case.run
    return replace(case, run=_read_pending, build=lambda tmp: _PENDING.__setitem__(tmp, builder(tmp)))


_CASES: tuple[Case, ...] = (
    # declared by an archive's directory or an array header
    Case("track-npy-declares-4gb", "track (npz)", "keypoints.npy header declares (10^6, 543, 2) over 24 bytes",
         track_npy_declares, CLEAR, "clip.track.npz", "declares 4,344,000,000 bytes"),
    Case("track-zip-bomb", "track (npz)", "keypoints.npy: 64 MB of zeros deflated to ~64 kB", track_zip_bomb, CLEAR,
         "clip.track.npz", "compression bomb"),
    Case("track-forged-directory", "track (npz)", "central directory declares 2 GB for a 13 kB member",
         track_forged_directory, CLEAR, "clip.track.npz", "declares 2,147,483,648 bytes"),
    Case("track-npy-hostile-header", "track (npz)", "confidence.npy header dict calling os.system",
         track_npy_garbage_header, CLEAR, "clip.track.npz", "not a readable .npy header"),
    Case("track-member-past-end", "track (npz)", "a member's offset points past the end of the file",
         zip_member_past_end, CLEAR, "clip.track.npz", "past the end of the file"),
    Case("model-npy-declares-80gb", "load_model_arrays", ".npy header declares 10^10 float64 over 64 bytes",
         model_npy_declares, CLEAR, "l_eyelid.npy", "declares 80,000,000,000 bytes"),
    Case("model-pickle-declares-8gb", "load_model_arrays", "a bytes object declaring 8 GB in a 14-byte pickle",
         model_pickle_declares, CLEAR, "SMPLX_NEUTRAL.pkl", "a record declares 8,000,000,000 bytes"),
    Case("model-npz-bomb", "load_model_arrays", "shapedirs.npy: 64 MB of zeros deflated", model_npz_bomb, CLEAR,
         "SMPLX_NEUTRAL.npz", "compression bomb"),
    Case("checkpoint-forged-record", "read_checkpoint", "a tensor record's directory entry declares 3.9 GB",
         checkpoint_forged_record, CLEAR, "tokenizer.pt", "declares 4,000,000,000 bytes"),
    Case("checkpoint-deflated-bomb", "read_checkpoint", "an extra record of 64 MB of zeros deflated",
         checkpoint_deflated_member, CLEAR, "tokenizer.pt", "compression bomb"),
    Case("nlf-pt-forged-record", "NLF output", ".pt whose pose record declares 3.9 GB", nlf_forged_record, CLEAR,
         "clip.nlf.pt", "declares 4,000,000,000 bytes"),
    # gzip pickles
    Case("slt-gzip-bomb", "slt_pickle", "a pickle of 300 MB of zeros, 0.3 MB gzipped", slt_gzip_bomb, CLEAR,
         mc.SLT_TRAIN, "its gzip trailer declares"),
    Case("slt-gzip-forged-trailer", "slt_pickle", "the same bomb, gzip's size trailer rewritten to 100",
         slt_gzip_forged_trailer, CLEAR, mc.SLT_TRAIN, "a record declares 314,572,800 bytes"),
    Case("slt-ndarray-declares-48gb", "slt_pickle", "sign = numpy.ndarray((10^9, 12), float32)", slt_ndarray_shape,
         CLEAR, mc.SLT_TRAIN, "numpy.ndarray called with a shape"),
    Case("slt-reconstruct-declares", "slt_pickle", "sign = numpy's reconstruction started at 10^9 elements",
         slt_reconstruct_shape, CLEAR, mc.SLT_TRAIN, "shape (1000000000,)"),
    # HDF5
    Case("mead-hdf5-fill-bomb", "mead source", "exp declared 400 GB, chunked, no chunk written", mead_fill_bomb,
         CLEAR, "shape_pose_cam.hdf5", "declares 400,000,000,000 bytes"),
    Case("mead-hdf5-compressed-bomb", "mead source", "exp: 64 MB of zeros in gzip chunks", mead_compressed_bomb,
         CLEAR, "shape_pose_cam.hdf5", "compression bomb"),
    Case("mead-hdf5-wrong-type-group", "mead source", "exp a group, not a dataset", mead_group, CLEAR,
         "shape_pose_cam.hdf5", "'exp' is Group, not a dataset"),
    # frame images
    Case("frame-png-declares-900mp", "read_image_rgb", "PNG header declaring 30,000 x 30,000, no pixel data",
         frame_declares("png"), CLEAR, "00001.png", "declares 30000x30000 pixels"),
    Case("frame-jpeg-declares-4gp", "read_image_rgb", "JPEG SOF0 declaring 65,000 x 65,000, no scan",
         frame_declares("jpg"), CLEAR, "00001.jpg", "declares 65000x65000 pixels"),
    # aliasing and size of params.yaml
    Case("params-alias-bomb", "load_params", "aliases expanding to 10^9 values under a known key",
         params_alias_bomb, CLEAR, "params.yaml", "M3T_YAML_MAX_NODES"),
    Case("params-alias-recursive", "load_params", "a known key's value &loop [*loop]", params_recursive_alias, CLEAR,
         "data.production_skip_kinds", ""),
    Case("params-deep-nesting", "load_params", "50,000 nested lists", params_deep_nesting, CLEAR, "params.yaml",
         "nested too deeply"),
    Case("params-huge-file", "load_params", "a 17 MB params file", params_huge, CLEAR, "params.yaml",
         "M3T_YAML_MAX_BYTES"),
    # .pose headers
    Case("pose-header-no-coordinates", "posefile", "point format 'C' (no coordinate)", pose_rewritten(_set_format("C")),
         CLEAR, "clip.pose", "not XYC or XYZC"),
    Case("pose-header-five-coordinates", "posefile", "point format 'XYZWVC'", pose_rewritten(_set_format("XYZWVC")),
         CLEAR, "clip.pose", "not XYC or XYZC"),
    Case("pose-header-mixed-formats", "posefile", "first component XYC, the others XYZC",
         pose_rewritten(_set_format("XYC", first_only=True)), CLEAR, "clip.pose", "not XYC or XYZC"),
    Case("pose-header-no-points", "posefile", "every component without points", pose_rewritten(_no_points), CLEAR,
         "clip.pose", "declares no points"),
    Case("pose-declares-frames", "posefile", "frames = 2^32 - 1 in the body preamble",
         pose_body_field(4, "<I", 2**32 - 1), CLEAR, "clip.pose", "the header promises"),
    Case("pose-declares-people", "posefile", "people = 65,535 in the body preamble", pose_body_field(8, "<H", 65535),
         CLEAR, "clip.pose", "65535 people"),
    Case("pose-fps-nan", "posefile", "fps = NaN in the body preamble", pose_body_field(0, "<f", float("nan")), CLEAR,
         "clip.pose", "frame rate is nan"),
    # a wrong Arrow type in every column of both table formats
    *(Case(f"shard-wrong-type-{name}", "read_shard", f"column {name!r} of another Arrow type",
           wrong_type(name, mc.shard, _read_shard), CLEAR, "train.parquet", f"column {name!r} is")
      for name in _columns(_shard_columns)),
    *(Case(f"tokens-wrong-type-{name}", "read_token_shard", f"column {name!r} of another Arrow type",
           wrong_type(name, mc.token_shard, _read_token_shard), CLEAR, "train.tokens.parquet", f"column {name!r} is")
      for name in _columns(_token_columns)),
)
CASES: tuple[Case, ...] = tuple(_staged(case) for case in _CASES)
