"""The tiny pipeline's fit and tokenizer stages in one process, then a digest of every float they wrote: the
subject of tests/base/test_arithmetic.py, run there as a subprocess under different arithmetic settings.

``python tests/reproducible_run.py OUT WORKERS`` generates the tiny synthetic corpus (4 clips) under OUT, fits it
(``fit_corpus.workers`` = WORKERS), trains the three tokenizers (``tokenizer_train.group_workers`` = WORKERS) and
prints one JSON object: {output: sha256 of its arrays' bytes}. Arrays, not files: a Parquet or checkpoint file
also holds library versions and names that say nothing about the arithmetic.
"""
from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import m3t  # noqa: F401  first: M3T_REPRODUCIBLE applies before torch and numpy load

ROOT = Path(__file__).resolve().parents[1]


def digest(arrays) -> str:
    import numpy as np

    h = hashlib.sha256()
    for array in arrays:
        array = np.ascontiguousarray(array)
        h.update(str((array.dtype, array.shape)).encode())
        h.update(array.tobytes())
    return h.hexdigest()


def main(out: Path, workers: int) -> dict[str, str]:
    import torch

    from m3t.body.factory import load_body_model
    from m3t.config import load_params
    from m3t.corpora.synthetic import generate_corpus
    from m3t.corpora.synthetic_storage import write_corpus
    from m3t.fitting.corpus import fit_and_log
    from m3t.shards.io import read_shard
    from m3t.tokenizers.pipeline import train_and_log

    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "body": {"cache_dir": str(ROOT / ".cache" / "anny")},
        "corpora": {"synthetic": {"root": str(out / "corpus")}},
        "data": {"shards_root": str(out / "shards"), "models_dir": str(out / "models"),
                 "metrics_dir": str(out / "metrics")},
        "fit_corpus": {"cache_dir": str(out / "fit-cache"), "max_clips": 4, "workers": workers,
                       "render_clips": 0},
        "tokenizer_train": {"cache_dir": str(out / "tok-cache"), "group_workers": workers}})
    body = load_body_model(params.body)
    write_corpus(generate_corpus(params.synthetic_corpus, body), params.corpora["synthetic"].root)
    report = fit_and_log(params.fit_job("synthetic"), params.experiment, progress=False)  # fit-corpus's call
    result = {}
    for split, path in sorted(report.shards.items()):
        shard = read_shard(path)
        result[f"fit/{split}"] = digest([value for clip in shard.clips for _, value in sorted(clip.params.items())])
    train_and_log(params.tokenizer, params.tokenizer_train, params.body, params.data, params.experiment,
                  progress=False)
    for checkpoint in sorted((out / "models" / "tokenizers").glob("*.pt")):
        state = torch.load(checkpoint, map_location="cpu", weights_only=True)["state_dict"]
        result[f"tokenizer/{checkpoint.stem}"] = digest([state[k].numpy() for k in sorted(state)])
    return result


if __name__ == "__main__":
    print(json.dumps(main(Path(sys.argv[1]), int(sys.argv[2]))))
