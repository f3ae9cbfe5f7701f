"""A tiny workspace with real runs: fitted shards -> tokenizers -> token shards -> back-translation judge ->
SMLM (trained, generated, evaluated), every step through the library call its DVC stage makes, logged to an
MLflow store of its own. The dashboard and the nightly re-evaluation are tested on it (session fixture
``tiny_workspace`` in conftest.py).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import yaml

from m3t.config import Params, load_params
from m3t.corpora.clip import Clip
from m3t.experiment import to_dict
from m3t.shards.io import write_shard
from m3t.shards.schema import FittedClip

ROOT = Path(__file__).resolve().parents[1]
SPLITS = {"train": 4, "dev": 1, "test": 2}


@dataclass(frozen=True)
class Workspace:
    root: Path
    params_file: Path
    params: Params


def write_shards(folder: Path, body, splits: dict[str, int] = SPLITS,
                 text: Callable[[int], str] = lambda seed: f"sentence {seed % 3}") -> Path:
    """Fitted shards of smooth synthetic motion (clip ``c<seed>`` of 18 .. 41 frames, text ``text(seed)``), with
    and without a stored camera, ``splits[split]`` clips per split in ``folder`` (created); returns it."""
    from builders import front_camera, smooth_motion

    folder.mkdir(parents=True)
    seed = 0
    for split, count in splits.items():
        clips = []
        for _ in range(count):
            frames = 18 + 7 * seed % 24
            motion = {k: v.numpy() for k, v in smooth_motion(body, frames=frames, seed=seed).items()}
            clip = Clip(f"c{seed}", "synthetic", split, "ASL-SYN", "s0", text(seed), "G", f"c{seed}.npz", 25.0)
            camera = front_camera().as_dict() if seed % 2 else {}
            clips.append(FittedClip(clip, "k", motion, body.default_identity().numpy(), camera, {}, body.name))
            seed += 1
        write_shard(folder / f"{split}.parquet", clips, body.layout)
    return folder


def build_workspace(root: Path, body) -> Workspace:
    from m3t.backtranslation import pipeline as backtranslation
    from m3t.smlm import evaluate_run, generate_run, train_run
    from m3t.tokenizers.pipeline import train_and_log as train_tokenizers
    from m3t.tokenizers.tokenize import run_tokenize

    write_shards(root / "shards" / "synthetic", body)
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "body": {"cache_dir": str(ROOT / ".cache" / "anny")},
        "experiment": {"enabled": True, "tracking_uri": f"sqlite:///{root / 'mlflow.db'}",
                       "artifact_dir": str(root / "mlruns"), "dashboard_dir": str(root / "site")},
        "corpora": {"synthetic": {"root": str(root / "corpus")}},
        "data": {"shards_root": str(root / "shards"), "tokens_root": str(root / "tokens"),
                 "models_dir": str(root / "models"), "generated_dir": str(root / "gen"),
                 "metrics_dir": str(root / "metrics")},
        "tokenizer_train": {"cache_dir": str(root / "cache"), "epochs": 3},
        "backtranslation_train": {"cache_dir": str(root / "cache-bt")},
        "smlm_train": {"epochs": 3}})
    params_file = root / "params.yaml"
    params_file.write_text(yaml.safe_dump(to_dict(params), sort_keys=False))
    p = params
    train_tokenizers(p.tokenizer, p.tokenizer_train, p.body, p.data, p.experiment, progress=False)
    run_tokenize(p.data)
    backtranslation.train_and_log(p.backtranslation, p.backtranslation_train, p.data, p.experiment, progress=False)
    backtranslation.evaluate_and_log(p.backtranslation, p.data, p.experiment)
    train_run.train_and_log(p.smlm, p.smlm_train, p.body, p.data, p.experiment, progress=False)
    generate_run.generate(p.smlm_generate, p.data, p.body, progress=False)
    evaluate_run.evaluate_and_log(p.smlm_generate, p.data, p.body, p.experiment, p.backtranslation)
    return Workspace(root, params_file, params)
