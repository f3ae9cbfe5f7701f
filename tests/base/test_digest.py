"""The digest helpers, and the recipes built on them, give the values plain hashlib gives: digests are recorded in
outputs (cache keys, data versions, resume keys), so none may move."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

from m3t import digest
from m3t.arithmetic import cache_parts


def test_helpers_are_plain_sha256(tmp_path):
    data = bytes(range(256)) * 5000  # over 1 MiB: read in several blocks
    path = tmp_path / "blob.bin"
    path.write_bytes(data)
    want = hashlib.sha256(data)
    assert digest.file_digest(path) == want.hexdigest()
    assert digest.file_digest(path, length=16) == want.hexdigest()[:16]
    assert digest.file_digest_bytes(path) == want.digest()
    assert digest.bytes_digest(data, length=16) == want.hexdigest()[:16]
    assert digest.chunks_digest([data[:7], b"", data[7:]]) == want.hexdigest()
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    assert digest.file_digest(empty) == "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"  # no bytes
    obj = {"b": [1, 2.5, None, "é"], "a": Path("x/y")}
    assert digest.json_digest(obj, length=16) == \
        hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def test_data_version_run_digest_and_fit_keys_keep_their_recipes(tmp_path):
    from m3t.checkpoints import run_digest
    from m3t.fitting.cache import cache_key
    from m3t.shards.io import data_version

    paths = []
    for name, content in (("train.parquet", b"rows of train"), ("dev.parquet", b"rows of dev")):
        paths.append(tmp_path / name)
        paths[-1].write_bytes(content)
    h = hashlib.sha256()
    for p in paths:
        h.update(p.name.encode())
        h.update(hashlib.sha256(p.read_bytes()).digest())
    assert data_version(paths) == h.hexdigest()[:16]

    parts = ("trainer-v3", {"width": 64, "depth": 2}, b"\x00vocab", Path("a/b"))
    text = json.dumps([*parts, *cache_parts()], sort_keys=True,
                      default=lambda v: hashlib.sha256(v).hexdigest() if isinstance(v, bytes) else str(v))
    assert run_digest(*parts) == hashlib.sha256(text.encode()).hexdigest()[:16]

    h = hashlib.sha256()
    for part in ("fit-v2", b"\x01\x02", {"lr": 0.02, "path": Path("p")}, *cache_parts()):
        h.update(part if isinstance(part, bytes) else json.dumps(part, sort_keys=True, default=str).encode())
        h.update(b"\0")
    assert cache_key(b"\x01\x02", {"lr": 0.02, "path": Path("p")}) == h.hexdigest()[:16]  # led by KEY_VERSION


def test_tracker_outputs_digest_keeps_its_recipe(tmp_path):
    from m3t.trackers.external import TrackerOutputs

    nlf = tmp_path / "clip.nlf.pkl"
    nlf.write_bytes(b"nlf output")
    frames = tmp_path / "pixel3dmm"
    frames.mkdir()
    for name in ("b.frame", "a.frame"):
        (frames / name).write_bytes(name.encode() * 3)
    h = hashlib.sha256(b"m3t tracker outputs v1")
    h.update(b"\0nlf\x001")
    h.update(f"\0{nlf.name}\0{hashlib.sha256(nlf.read_bytes()).hexdigest()}".encode())
    h.update(b"\0pixel3dmm\x002")
    for name in ("a.frame", "b.frame"):
        h.update(f"\0{name}\0{hashlib.sha256((frames / name).read_bytes()).hexdigest()}".encode())
    assert TrackerOutputs(nlf=nlf, pixel3dmm=frames).digest() == h.hexdigest()
