"""Determinism on CPU (issue "Reliability harness", item 4): the tiny pipeline run twice from scratch with the same
seeds, in two roots that share nothing but the body model, gives identical outputs at every step:
generate-corpus -> simulated tracks -> fit-corpus (one clip per split) -> train-tokenizers (2 epochs) -> tokenize,
and the metrics written on the way (the tokenizers' reconstruction / codebook report, fit-corpus' summary).

Compared by content, not by file bytes, so that the test is about the data and not about the writers' containers
(Parquet's ``created_by``, zip member times, pickle framing): Parquet shards by their decoded table and schema
metadata, ``.npz`` files by their arrays, checkpoints by their tensors and the JSON of everything else. (The files
of these steps are byte-identical today as well; plots are not compared.)
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from builders import tiny_params

from m3t.corpora.synthetic import generate_corpus
from m3t.corpora.synthetic_storage import SyntheticCorpus, write_corpus
from m3t.fitting.context import FitContext
from m3t.fitting.corpus import run_fit_corpus
from m3t.tokenizers.pipeline import run_train_tokenizers
from m3t.tokenizers.tokenize import run_tokenize


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def parquet_digest(path: Path) -> str:
    """The decoded table with its schema (and the schema's key-value metadata), as an Arrow IPC stream."""
    table = pq.read_table(path)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table.combine_chunks())
    return _sha(sink.getvalue().to_pybytes())


def npz_digest(path: Path) -> str:
    with np.load(path, allow_pickle=False) as arrays:
        h = hashlib.sha256()
        for name in sorted(arrays.files):
            a = arrays[name]
            h.update(f"{name} {a.dtype} {a.shape}".encode())
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()


def checkpoint_digest(path: Path) -> str:
    """Every tensor of the checkpoint (state dict, buffers, optimiser) by name, dtype, shape and bytes, and the
    rest of it (config, step, data version) as sorted JSON."""
    h = hashlib.sha256()

    def walk(prefix: str, value: object) -> None:
        if isinstance(value, torch.Tensor):
            t = value.detach().cpu().contiguous()
            h.update(f"{prefix} {t.dtype} {tuple(t.shape)}".encode())
            h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
        elif isinstance(value, dict):
            for k in sorted(value, key=str):
                walk(f"{prefix}/{k}", value[k])
        elif isinstance(value, (list, tuple)):
            for i, v in enumerate(value):
                walk(f"{prefix}/{i}", v)
        else:
            h.update(f"{prefix}={json.dumps(value, sort_keys=True, default=str)}".encode())

    walk("", torch.load(path, map_location="cpu", weights_only=False))
    return h.hexdigest()


def json_digest(path: Path) -> str:
    return _sha(json.dumps(json.loads(path.read_text()), sort_keys=True).encode())


def digests(root: Path) -> dict[str, str]:
    """Content digest of every output under ``root`` that the pipeline wrote, by relative path (plots and
    logs of progress left out)."""
    out = {}
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = path.relative_to(root).as_posix()
        if path.suffix == ".parquet":
            out[rel] = parquet_digest(path)
        elif path.suffix == ".npz":
            out[rel] = npz_digest(path)
        elif path.suffix == ".pt":
            out[rel] = checkpoint_digest(path)
        elif path.suffix == ".json":
            out[rel] = json_digest(path)
        elif path.suffix in (".jsonl", ".csv"):
            out[rel] = _sha(path.read_bytes())
    return out


def run_pipeline(root: Path, body) -> tuple[dict[str, str], dict[str, dict[str, float]]]:
    torch.set_num_threads(1)
    params = tiny_params(root)
    data = dataclasses.replace(params.data, tokens_root=str(root / "tokens"), models_dir=str(root / "models"))
    train_cfg = dataclasses.replace(params.tokenizer_train, cache_dir=str(root / "tok-cache"), epochs=2)
    write_corpus(generate_corpus(params.synthetic_corpus, body), params.corpora["synthetic"].root)
    clips = SyntheticCorpus(Path(params.corpora["synthetic"].root)).clips()
    chosen = [next(c for c in clips if c.split == split) for split in ("train", "dev", "test")]
    job = params.fit_job("synthetic")
    report = run_fit_corpus(job, clips=chosen, progress=False, ctx=FitContext(job, body))
    assert [o.status for o in report.outcomes] == ["fitted"] * 3
    metrics = run_train_tokenizers(params.tokenizer, train_cfg, body, data, progress=False)
    run_tokenize(data)
    return digests(root), metrics


def test_same_seed_gives_identical_corpus_tracks_fits_tokens_checkpoints_and_metrics(body, tmp_path):
    first, metrics = run_pipeline(tmp_path / "a", body)
    second, _ = run_pipeline(tmp_path / "b", body)
    kinds = {
        "corpus": [k for k in first if k.startswith("corpus/")],
        "tracks": [k for k in first if k.startswith("cache/tracks/") and k.endswith(".npz")],
        "fits": [k for k in first if k.startswith("shards/synthetic/") and k.endswith(".parquet")],
        "tokens": [k for k in first if k.startswith("tokens/synthetic/") and k.endswith(".parquet")],
        "checkpoints": [k for k in first if k.startswith("models/tokenizers/") and k.endswith(".pt")],
        "metrics": ["models/tokenizers/metrics.json", "shards/synthetic/summary.json"],
    }
    assert all(kinds.values()), {k: len(v) for k, v in kinds.items()}  # every step left outputs to compare
    assert len(kinds["tracks"]) == 3 and len(kinds["fits"]) == 3 and len(kinds["tokens"]) == 3
    assert sorted(first) == sorted(second)
    differing = sorted(k for k in first if first[k] != second[k])
    assert not differing, differing
    assert all(np.isfinite(v) for group in metrics.values() for v in group.values())
