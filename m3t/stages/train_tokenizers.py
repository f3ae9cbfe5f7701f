"""train-tokenizers: fitted shards -> one FSQ-VAE (or VQ-VAE baseline) per modality group -> checkpoints,
codebook statistics, token histograms and reconstruction GIFs.

For each group of ``tokenizer_train.groups`` (``body``, ``hand``, ``face``): train on the train split
(+ face-only shards for ``face``), select by validation vertex error on the dev split, then tokenise every
split with the selected checkpoint to measure codebook utilisation / token-count SD and test-split
VPE / PA-VPE (the Tab. 3 columns). Writes ``<out_dir>/<group>.pt``, ``<out_dir>/metrics.json``,
``<out_dir>/plots/`` and ``<out_dir>/rejected.jsonl`` (clips that could not be used, with reasons).

Run as a DVC stage: ``python -m m3t.stages.train_tokenizers`` (reads params.yaml, logs to MLflow), or
under ``torchrun --nproc_per_node N -m m3t.stages.train_tokenizers`` for DDP.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Callable

import numpy as np

from m3t.body.protocol import BodyModel
from m3t.metrics.codebook import codebook_stats, plot_token_histogram, token_counts
from m3t.runtime import DistributedContext
from m3t.shards.io import read_shard
from m3t.shards.schema import FittedClip
from m3t.tokenizers.checkpoint import load_tokenizer
from m3t.tokenizers.data import GROUPS, check_layout, clip_sequences, from_canonical, to_canonical
from m3t.tokenizers.evaluate import ReconstructionProbe, encode_clip, reconstruct_clip
from m3t.tokenizers.train import TokenizerConfig, TokenizerTrainConfig, TrainResult, train_tokenizer

SPLITS = ("train", "dev", "test")


def atomic_copy(source: Path, target: Path) -> Path:
    if not source.exists():
        raise FileNotFoundError(f"checkpoint {source} missing; delete {source.parent} and rerun train-tokenizers")
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.tmp")
    shutil.copyfile(source, tmp)
    os.replace(tmp, target)
    return target


def load_split(shards_dir: str | Path, split: str) -> list[FittedClip]:
    path = Path(shards_dir) / f"{split}.parquet"
    if not path.exists():
        raise FileNotFoundError(f"shard {path} not found; run the fit-corpus stage first (dvc repro fit-corpus)")
    return list(read_shard(path).clips)


def data_version(paths: list[Path]) -> str:
    """Digest of the shard files a tokenizer is trained on (part of the resume key and the checkpoint)."""
    h = hashlib.sha256()
    for path in paths:
        h.update(path.name.encode())
        h.update(hashlib.sha256(Path(path).read_bytes()).digest())
    return h.hexdigest()[:16]


def usable_sequences(group: str, clips: list[FittedClip], rejected: list[dict]) -> list[np.ndarray]:
    """Training sequences of ``clips``; a clip that cannot be used is recorded in ``rejected``, not raised."""
    out = []
    for clip in clips:
        try:
            out.extend(clip_sequences(clip.params, group, clip.clip.id))
        except (ValueError, KeyError) as exc:
            rejected.append({"clip_id": clip.clip.id, "group": group, "reason": f"{type(exc).__name__}: {exc}"})
    return out


def face_only_clips(paths: tuple[str, ...]) -> list[FittedClip]:
    clips = []
    for path in paths:
        clips.extend(read_shard(path, ["face"]).clips)
    return clips


def group_report(group: str, checkpoint: Path, splits: dict[str, list[FittedClip]], body: BodyModel,
                 plots_dir: Path, max_test_frames: int) -> dict[str, float]:
    """Codebook statistics over every split and test-split vertex errors of the selected checkpoint."""
    model = load_tokenizer(checkpoint).model
    indices = [encode_clip(model, to_canonical(np.asarray(c.params[s.modality]), s))
               for clips in splits.values() for c in clips for s in GROUPS[group]]
    counts = token_counts(indices, model.codebook_size)
    stats = codebook_stats(counts)
    plot_token_histogram(counts, f"{group} ({model.cfg.quantizer}, {model.codebook_size} codes)",
                         plots_dir / f"tokens_{group}.png")
    test = ReconstructionProbe(body, group, splits["test"], max_frames=max_test_frames).measure(model)
    report = {**stats, **{f"test_{k}": v for k, v in test.items()}, "codebook_size": float(model.codebook_size)}
    if splits["test"]:
        from m3t.render.reconstruction import render_reconstruction

        clip = splits["test"][0]
        recon = {s.modality: from_canonical(reconstruct_clip(model, to_canonical(np.asarray(clip.params[s.modality]), s)),
                                            s).numpy() for s in GROUPS[group]}
        render_reconstruction(body, clip, recon, plots_dir / f"reconstruction_{group}.gif",
                              title=f"{clip.clip.id}: {group} tokens ({model.cfg.quantizer})")
    return report


def run_train_tokenizers(
    tok_cfg: TokenizerConfig,
    cfg: TokenizerTrainConfig,
    body: BodyModel,
    on_epoch: Callable[[str, dict[str, float], int], None] | None = None,
    stop_after_epochs: int | None = None,
    dist_ctx: DistributedContext | None = None,
    progress: bool = True,
) -> dict[str, dict[str, float]]:
    """Train every configured group; returns (and, on rank 0, writes) ``metrics.json``'s content."""
    dist_ctx = dist_ctx or DistributedContext()
    shards = Path(cfg.shards_dir)
    splits = {split: load_split(shards, split) for split in SPLITS}
    if not splits["train"]:
        raise ValueError(f"{shards / 'train.parquet'} holds no clips; the tokenizers need training data")
    layout = read_shard(shards / "train.parquet", []).layout
    version = data_version([shards / "train.parquet", shards / "dev.parquet", *map(Path, cfg.extra_face_shards)])
    out_dir = Path(cfg.out_dir)
    plots = out_dir / "plots"
    rejected: list[dict] = []
    results: dict[str, TrainResult] = {}
    report: dict[str, dict[str, float]] = {}
    for group in cfg.groups:
        input_dim = check_layout(layout, group)
        train_clips = splits["train"] + (face_only_clips(cfg.extra_face_shards) if group == "face" else [])
        sequences = usable_sequences(group, train_clips, rejected)
        rejected_ids = {r["clip_id"] for r in rejected}
        usable = {s: [c for c in clips if c.clip.id not in rejected_ids] for s, clips in splits.items()}
        dev = usable["dev"]
        probe = ReconstructionProbe(body, group, dev or splits["train"], cfg.val_max_frames) if dist_ctx.is_main else None
        callback = (lambda record, epoch, g=group: on_epoch(g, record, epoch)) if on_epoch else None
        results[group] = train_tokenizer(group, tok_cfg.vae_config(group, input_dim), cfg, sequences, probe, version,
                                         callback, stop_after_epochs, dist_ctx, progress)
        if dist_ctx.is_main:
            atomic_copy(results[group].best_path, out_dir / f"{group}.pt")
            report[group] = {**group_report(group, out_dir / f"{group}.pt", usable, body, plots, cfg.val_max_frames),
                             "best_epoch": float(results[group].best.get("epoch", 0)),
                             **{f"best_{k}": v for k, v in results[group].best.items() if k.startswith("val_")}}
    if dist_ctx.is_main:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(report, indent=2, sort_keys=True))
        (out_dir / "rejected.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rejected))
    return report


def train_and_log(params, progress: bool = True) -> dict[str, dict[str, float]]:
    """Train the tokenizers of ``params`` (rank 0 logs params, per-epoch curves, final metrics and plots)."""
    from m3t.body.factory import load_body_model
    from m3t.config import flat_params
    from m3t.experiment import start_run
    from m3t.runtime import distributed_context

    dist_ctx = distributed_context(params.tokenizer_train.device)
    body = load_body_model(params.body)
    if not dist_ctx.is_main:
        return run_train_tokenizers(params.tokenizer, params.tokenizer_train, body, dist_ctx=dist_ctx, progress=False)
    tok, cfg = params.tokenizer, params.tokenizer_train
    tags = {"quantizer": tok.quantizer, "width": str(tok.width), "batch_size": str(cfg.batch_size)}
    with start_run(params.experiment, "train-tokenizers", tags=tags) as run:
        run.log_params({k: v for k, v in flat_params(params).items() if k.split(".")[0] in ("body", "tokenizer", "tokenizer_train")})
        report = run_train_tokenizers(
            tok, cfg, body, dist_ctx=dist_ctx, progress=progress,
            on_epoch=lambda group, record, epoch: run.log_metrics({f"{group}/{k}": v for k, v in record.items()}, step=epoch))
        run.log_metrics({f"{group}/{k}": v for group, values in report.items() for k, v in values.items()})
        out_dir = Path(cfg.out_dir)
        run.log_artifact(out_dir / "metrics.json")
        run.log_artifact(out_dir / "rejected.jsonl")
        for plot in sorted((out_dir / "plots").glob("*")):
            run.log_artifact(plot, "plots")
    return report


def main(argv: list[str] | None = None) -> dict:
    """DVC entry point: params.yaml -> tokenizers + metrics + an MLflow run."""
    from m3t.config import load_params

    parser = argparse.ArgumentParser(description="train-tokenizers: fitted shards -> FSQ-VAE tokenizers")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--preset", default="default")
    args = parser.parse_args(argv)
    report = train_and_log(load_params(args.params, preset=args.preset))
    print(json.dumps(report, indent=2, sort_keys=True))
    return report


if __name__ == "__main__":
    main()
