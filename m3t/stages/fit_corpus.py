"""fit-corpus: clips -> tracks -> fitted body-model parameters -> Parquet shards (one per split).

Each clip is processed independently by :func:`process_clip` (the unit the Prefect flow parallelises):
its track and its fit are content-addressed by a hash of their inputs and configs, stored under the
cache dir (``tracks/`` and ``parts/``), written atomically, and reused when present, so a killed run
resumes without redoing a finished clip, and an unchanged clip is never re-fitted. A clip that fails
(missing / corrupt media, unusable track) is quarantined with its reason; the others go on.
:func:`consolidate` then writes ``<split>.parquet``, ``quarantine.jsonl`` and ``summary.json``.

Run as a DVC stage: ``python -m m3t.stages.fit_corpus`` (reads params.yaml, logs to MLflow).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator, Literal

import numpy as np
import torch

from m3t.body.factory import BodyConfig, body_cache_key, load_body_model
from m3t.body.protocol import BodyModel
from m3t.corpora.clip import Clip
from m3t.fitting.evaluate import as_tensors, ground_truth_errors, joints_for, procrustes_error_mm
from m3t.fitting.fit import FittingConfig, fit_track
from m3t.shards.io import read_shard, write_shard
from m3t.shards.schema import FittedClip
from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track
from m3t.trackers.track import load_track, save_track

STANDARD_SPLITS = ("train", "dev", "test")
KEY_VERSION = "fit-v1"  # bump when fitting code changes in a way that invalidates cached results


@dataclass(frozen=True)
class FitCorpusConfig:
    corpus: Literal["synthetic"] = "synthetic"
    corpus_dir: str = "data/corpus/synthetic"
    shards_dir: str = "data/shards/synthetic"
    cache_dir: str = ".cache/fit"
    workers: int = 2
    max_clips: int = 0  # 0 = every clip
    render_clips: int = 2


@dataclass(frozen=True)
class ClipOutcome:
    clip_id: str
    split: str
    status: Literal["fitted", "cached", "quarantined"]
    part: str | None = None
    reason: str | None = None
    metrics: dict[str, float] = field(default_factory=dict)
    frames: int = 0
    seconds: float = 0.0


def open_corpus(cfg: FitCorpusConfig):
    if cfg.corpus == "synthetic":
        from m3t.corpora.synthetic import SyntheticCorpus

        return SyntheticCorpus(cfg.corpus_dir)
    raise ValueError(f"fit_corpus.corpus {cfg.corpus!r} unknown; allowed: synthetic")


def list_clips(cfg: FitCorpusConfig) -> list[Clip]:
    clips = open_corpus(cfg).clips()
    return clips[: cfg.max_clips] if cfg.max_clips > 0 else clips


def _digest(*parts: object) -> str:
    h = hashlib.sha256()
    for part in parts:
        h.update(part if isinstance(part, bytes) else json.dumps(part, sort_keys=True, default=str).encode())
        h.update(b"\0")
    return h.hexdigest()[:16]


def _file_digest(path: Path) -> bytes:
    return hashlib.sha256(path.read_bytes()).digest()


@dataclass
class FitContext:
    """What every clip needs; built once per worker process."""

    cfg: FitCorpusConfig
    body_cfg: BodyConfig
    tracker_cfg: SimulatedTrackerConfig
    fitting_cfg: FittingConfig
    _body: BodyModel | None = None
    _corpus: object | None = None
    _body_key: object | None = None

    @property
    def body(self) -> BodyModel:
        if self._body is None:
            self._body = load_body_model(self.body_cfg)
        return self._body

    @property
    def body_key(self) -> object:
        if self._body_key is None:  # hashing licensed model files once per process, not once per clip
            self._body_key = body_cache_key(self.body_cfg)
        return self._body_key

    @property
    def corpus(self):
        if self._corpus is None:
            self._corpus = open_corpus(self.cfg)
        return self._corpus


def track_clip(clip: Clip, ctx: FitContext) -> Path:
    """Simulated tracking of a synthetic clip, cached by (motion file, tracker config, body model)."""
    media = Path(ctx.cfg.corpus_dir) / clip.media
    if not media.exists():
        raise FileNotFoundError(f"media file {media} of clip {clip.id} is missing")
    key = _digest(KEY_VERSION, _file_digest(media), ctx.tracker_cfg, ctx.body_key)
    path = Path(ctx.cfg.cache_dir) / "tracks" / f"{clip.id}-{key}.npz"
    if not path.exists():
        params, identity, camera = ctx.corpus.ground_truth(clip)
        track = simulate_track(clip.id, as_tensors(params), torch.as_tensor(identity), camera, clip.fps, ctx.body, ctx.tracker_cfg)
        save_track(track, path)
    return path


def fit_key(track_path: Path, ctx: FitContext) -> str:
    """Content address of a fit: the track's bytes, the fitting config and the body model."""
    return _digest(KEY_VERSION, _file_digest(track_path), ctx.fitting_cfg, ctx.body_key)


def fit_clip(clip: Clip, track_path: Path, key: str, ctx: FitContext) -> FittedClip:
    track = load_track(track_path)
    result = fit_track(track, ctx.body, ctx.fitting_cfg)
    metrics = dict(result.metrics)
    if ctx.cfg.corpus == "synthetic":
        gt_params, gt_identity, gt_camera = ctx.corpus.ground_truth(clip)
        metrics.update(ground_truth_errors(ctx.body, result.params, result.identity, result.camera,
                                           gt_params, gt_identity, gt_camera.as_dict()))
        if track.init is not None:  # what refinement gained over the tracker initialisation
            with torch.no_grad():
                truth_joints = joints_for(ctx.body, gt_params, gt_identity)
                init_joints = joints_for(ctx.body, track.init, ctx.body.default_identity().numpy())
            metrics["init_pa_joint_mm"] = procrustes_error_mm(init_joints, truth_joints)
    return FittedClip(clip=clip, key=key, params=result.params, identity=result.identity, camera=result.camera,
                      metrics=metrics, body_model=ctx.body.name)


def process_clip(clip: Clip, ctx: FitContext) -> ClipOutcome:
    """Track + fit + write one clip's part file; never raises for a bad clip (quarantines it)."""
    start = time.perf_counter()
    try:
        track_path = track_clip(clip, ctx)
        key = fit_key(track_path, ctx)
        part = Path(ctx.cfg.cache_dir) / "parts" / f"{clip.id}-{key}.parquet"
        if part.exists():
            fitted = read_shard(part).clips[0]
            return ClipOutcome(clip.id, clip.split, "cached", str(part), metrics=fitted.metrics, frames=fitted.num_frames)
        fitted = fit_clip(clip, track_path, key, ctx)
        part.parent.mkdir(parents=True, exist_ok=True)
        write_shard(part, [fitted], ctx.body.layout)
        return ClipOutcome(clip.id, clip.split, "fitted", str(part), metrics=fitted.metrics,
                           frames=fitted.num_frames, seconds=time.perf_counter() - start)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # noqa: BLE001 - any failure of one clip quarantines that clip only
        reason = f"{type(exc).__name__}: {exc}"
        return ClipOutcome(clip.id, clip.split, "quarantined", reason=reason, seconds=time.perf_counter() - start)


def _atomic_write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


@dataclass(frozen=True)
class FitCorpusReport:
    shards: dict[str, str]
    outcomes: list[ClipOutcome]
    summary: dict[str, float]


def summarise(outcomes: list[ClipOutcome], wall_seconds: float) -> dict[str, float]:
    done = [o for o in outcomes if o.status != "quarantined"]
    fitted = [o for o in outcomes if o.status == "fitted"]
    summary: dict[str, float] = {
        "clips_total": len(outcomes),
        "clips_fitted": len(fitted),
        "clips_cached": sum(o.status == "cached" for o in outcomes),
        "clips_quarantined": sum(o.status == "quarantined" for o in outcomes),
        "frames": sum(o.frames for o in done),
        "wall_seconds": wall_seconds,
        # per worker process (frames / seconds spent fitting) and for the whole run (frames / wall time)
        "fit_frames_per_s_per_worker": (sum(o.frames for o in fitted) / sum(o.seconds for o in fitted)) if fitted else math.nan,
        "fit_frames_per_s_wall": sum(o.frames for o in fitted) / wall_seconds if fitted and wall_seconds > 0 else math.nan,
    }
    keys = sorted({k for o in done for k in o.metrics})
    for key in keys:
        values = [o.metrics[key] for o in done if key in o.metrics and o.metrics[key] == o.metrics[key]]
        if values:
            summary[f"{key}_mean"] = float(np.mean(values))
            summary[f"{key}_median"] = float(np.median(values))
    return summary


def consolidate(outcomes: list[ClipOutcome], layout, cfg: FitCorpusConfig, wall_seconds: float) -> FitCorpusReport:
    """Gather part files into one shard per split; write the quarantine report and summary."""
    out_dir = Path(cfg.shards_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # Every standard split gets a shard (possibly empty), so downstream stages and DVC outputs always exist.
    by_split: dict[str, list[FittedClip]] = {split: [] for split in STANDARD_SPLITS}
    for o in sorted(outcomes, key=lambda o: o.clip_id):
        if o.part is not None:
            by_split.setdefault(o.split, []).extend(read_shard(o.part).clips)
    shards = {split: str(write_shard(out_dir / f"{split}.parquet", clips, layout)) for split, clips in by_split.items()}
    for stale in out_dir.glob("*.parquet"):
        if str(stale) not in shards.values():
            stale.unlink()
    quarantine = [{"clip_id": o.clip_id, "split": o.split, "reason": o.reason} for o in outcomes if o.status == "quarantined"]
    _atomic_write_text(out_dir / "quarantine.jsonl", "".join(json.dumps(q) + "\n" for q in quarantine))
    summary = summarise(outcomes, wall_seconds)
    _atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=2, sort_keys=True))
    return FitCorpusReport(shards=shards, outcomes=outcomes, summary=summary)


_WORKER_CTX: FitContext | None = None


def _worker_init(ctx: FitContext) -> None:
    global _WORKER_CTX
    torch.set_num_threads(1)  # one process per core; intra-op threads would oversubscribe
    _WORKER_CTX = ctx


def _worker_process(clip: Clip) -> ClipOutcome:
    assert _WORKER_CTX is not None
    return process_clip(clip, _WORKER_CTX)


def _outcomes(ctx: FitContext, clips: list[Clip]) -> Iterator[ClipOutcome]:
    """Outcomes in completion order, from this process or from ``cfg.workers`` worker processes."""
    if ctx.cfg.workers <= 1:
        yield from (process_clip(c, ctx) for c in clips)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    worker_ctx = FitContext(ctx.cfg, ctx.body_cfg, ctx.tracker_cfg, ctx.fitting_cfg)  # workers build their own model
    with ProcessPoolExecutor(ctx.cfg.workers, mp_context=mp.get_context("spawn"), initializer=_worker_init,
                             initargs=(worker_ctx,)) as pool:
        futures = [pool.submit(_worker_process, c) for c in clips]
        try:
            for future in as_completed(futures):
                yield future.result()
        except BrokenProcessPool as exc:
            raise RuntimeError("a fit-corpus worker process died (out of memory or killed); finished clips are "
                               "cached, rerun to resume") from exc
        finally:
            for future in futures:
                future.cancel()


def run_fit_corpus(
    ctx: FitContext,
    clips: Iterable[Clip] | None = None,
    progress: bool = True,
    on_outcome: Callable[[ClipOutcome], None] | None = None,
) -> FitCorpusReport:
    """Process every clip (in ``cfg.workers`` processes) and consolidate the shards."""
    from tqdm.auto import tqdm

    clips = list(clips) if clips is not None else list_clips(ctx.cfg)
    start = time.perf_counter()
    outcomes: list[ClipOutcome] = []
    with tqdm(total=len(clips), desc="fit-corpus", unit="clip", disable=not progress) as bar:
        for outcome in _outcomes(ctx, clips):
            outcomes.append(outcome)
            bar.update(1)
            bar.set_postfix(status=outcome.status, quarantined=sum(o.status == "quarantined" for o in outcomes))
            if on_outcome is not None:
                on_outcome(outcome)
    return consolidate(outcomes, ctx.body.layout, ctx.cfg, time.perf_counter() - start)


def log_report(params, ctx: FitContext, report: FitCorpusReport) -> str | None:
    """Log a fit-corpus run to MLflow: params, summary metrics, quarantine report, fitted-vs-truth pictures."""
    from m3t.config import flat_params
    from m3t.experiment import start_run
    from m3t.render.mesh import log_fitted_frame
    from m3t.render.skeleton import render_fit_comparison

    with start_run(params.experiment, "fit-corpus") as run:
        sections = ("body", "tracker", "fitting", "fit_corpus")
        run.log_params({k: v for k, v in flat_params(params).items() if k.split(".")[0] in sections})
        run.log_metrics(report.summary)
        out_dir = Path(ctx.cfg.shards_dir)
        run.log_artifact(out_dir / "quarantine.jsonl")
        run.log_artifact(out_dir / "summary.json")
        for outcome in [o for o in report.outcomes if o.part is not None][: ctx.cfg.render_clips]:
            fitted = read_shard(outcome.part).clips[0]
            truth = ctx.corpus.ground_truth(fitted.clip) if ctx.cfg.corpus == "synthetic" else None
            image = Path(ctx.cfg.cache_dir) / "render" / f"{fitted.clip.id}.png"
            run.log_artifact(render_fit_comparison(ctx.body, fitted, truth, image), "fit_vs_ground_truth")
            # the fitted mesh of the middle frame: PLY + a rendered picture
            log_fitted_frame(run, ctx.body, fitted.params, fitted.identity, fitted.num_frames // 2,
                             Path(ctx.cfg.cache_dir) / "render", fitted.camera, stem=fitted.clip.id)
        return run.run_id


def main(argv: list[str] | None = None) -> FitCorpusReport:
    """DVC entry point: params.yaml -> shards + an MLflow run."""
    from m3t.config import load_params

    parser = argparse.ArgumentParser(description="fit-corpus: clips -> tracks -> fits -> Parquet shards")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--preset", default="default")
    args = parser.parse_args(argv)
    params = load_params(args.params, preset=args.preset)
    ctx = FitContext(params.fit_corpus, params.body, params.tracker, params.fitting)
    report = run_fit_corpus(ctx)
    log_report(params, ctx, report)
    print(json.dumps(report.summary, indent=2, sort_keys=True))
    return report


if __name__ == "__main__":
    main()
