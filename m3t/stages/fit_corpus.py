"""fit-corpus: a corpus' clips -> tracks -> fitted body-model parameters -> Parquet shards (one per split).

Any corpus of :data:`m3t.corpora.base.CORPORA` (``--corpus NAME``; root, shards folder and adapter options
from ``corpora.NAME`` in params.yaml). Tracks come from the clip's media kind (:mod:`m3t.trackers.dispatch`:
simulated for the synthetic corpus, ``.pose`` files and spelled words converted, videos and frame folders
through MediaPipe); rows the adapter could not list are quarantined beside the clips that failed later.

Each clip is processed independently by :func:`process_clip` (the unit the Prefect flow parallelises):
its track and its fit are content-addressed by a hash of their inputs and configs, stored under the
cache dir (``tracks/`` and ``parts/``), written atomically, and reused when present, so a killed run
resumes without redoing a finished clip, and an unchanged clip is never re-fitted. A clip that fails
(missing / corrupt media, unusable track) is quarantined with its reason; the others go on.
:func:`consolidate` then writes ``<split>.parquet``, ``quarantine.jsonl``, ``summary.json`` and the data-quality
report (``quality.csv`` / ``quality.json``, :mod:`m3t.fitting.quality`).

Run as a DVC stage: ``python -m m3t.stages.fit_corpus --corpus NAME`` (reads params.yaml, logs to MLflow).
Ground-truth metrics exist for the synthetic corpus only.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from m3t.body.factory import BodyConfig, body_cache_key, load_body_model
from m3t.body.protocol import BodyModel
from m3t.corpora.base import CORPORA, CorpusAdapter, Listing, open_corpus
from m3t.corpora.clip import Clip
from m3t.fitting.evaluate import (
    as_tensors,
    ground_truth_errors,
    joints_for,
    procrustes_error_mm,
)
from m3t.fitting.fit import FittingConfig, fit_track
from m3t.fitting.quality import part_reprojection_px, track_coverage
from m3t.shards.io import read_shard, write_shard
from m3t.shards.schema import FittedClip
from m3t.stages.fit_corpus_report import (  # noqa: F401 - re-exported: the flow and tests use them from here
    STANDARD_SPLITS,
    FitCorpusReport,
    consolidate,
    log_report,
    summarise,
)
from m3t.trackers.dispatch import ClipRefused, media_key, media_kind, track_real_clip
from m3t.trackers.mediapipe_holistic import MediaPipeConfig
from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track
from m3t.trackers.track import load_track, save_track

KEY_VERSION = "fit-v2"  # bump when fitting code changes in a way that invalidates cached results


@dataclass(frozen=True)
class CorpusSource:
    """Where one corpus lives (params.yaml ``corpora.<name>``). ``root`` "" = the adapter's default (the
    fingerspelling lexicon inside its installed package); ``options`` = the adapter's option dataclass fields."""

    root: str = ""
    shards_dir: str = ""
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class FitCorpusConfig:
    """params.yaml ``fit_corpus``. ``corpus_dir``, ``shards_dir`` and ``options`` are filled from
    ``corpora.<corpus>`` by :func:`for_corpus` (params.yaml sets them there, not here)."""

    corpus: Literal[CORPORA] = "synthetic"  # the default of --corpus
    corpus_dir: str = "data/corpus/synthetic"
    shards_dir: str = "data/shards/synthetic"
    cache_dir: str = ".cache/fit"
    workers: int = 2
    max_clips: int = 0  # 0 = every clip
    render_clips: int = 2
    options: dict[str, Any] = field(default_factory=dict)


def for_corpus(params, corpus: str | None = None) -> FitCorpusConfig:
    """``params.fit_corpus`` for ``corpus`` (default ``fit_corpus.corpus``) with its ``corpora`` entry applied."""
    from m3t.config import ConfigError

    name = corpus or params.fit_corpus.corpus
    if name not in CORPORA:
        raise ConfigError(f"corpus {name!r} unknown; expected one of {', '.join(CORPORA)}")
    if name not in params.corpora:
        raise ConfigError(f"corpora.{name} is not in params.yaml; add it with root, shards_dir and options "
                          f"(see the commented examples there)")
    src = params.corpora[name]
    return dataclasses.replace(params.fit_corpus, corpus=name, corpus_dir=src.root,
                               shards_dir=src.shards_dir or f"data/shards/{name}", options=dict(src.options))


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
    group: str | None = None  # the short reason the quality report counts
    file: str | None = None  # quarantined: the listing file (or the clip's media) ...
    row: int | None = None  # ... and its row, when the adapter refused the row
    from_listing: bool = False
    coverage: dict[str, float] = field(default_factory=dict)  # missing_<part> ratios of the track
    track_frames: int = 0


def list_corpus(cfg: FitCorpusConfig) -> Listing:
    """The adapter's listing (clips cut to ``max_clips``, its quarantined rows all kept)."""
    listing = open_corpus(cfg.corpus, cfg.corpus_dir, **cfg.options).listing()
    clips = listing.clips[: cfg.max_clips] if cfg.max_clips > 0 else listing.clips
    return Listing(tuple(clips), listing.quarantined)


def list_clips(cfg: FitCorpusConfig) -> list[Clip]:
    return list(list_corpus(cfg).clips)


def listing_outcomes(listing: Listing) -> list[ClipOutcome]:
    """The rows the adapter refused, as quarantined outcomes (file + row + reason)."""
    return [ClipOutcome(q.clip_id or "", "", "quarantined", reason=q.reason, file=q.file, row=q.row,
                        group="listing: " + q.reason.split(":")[0].split(";")[0][:60], from_listing=True)
            for q in listing.quarantined]


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
    _corpus: CorpusAdapter | None = None
    _synthetic: object | None = None
    _body_key: object | None = None
    mediapipe_cfg: MediaPipeConfig = field(default_factory=MediaPipeConfig)

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
    def corpus(self) -> CorpusAdapter:
        if self._corpus is None:
            self._corpus = open_corpus(self.cfg.corpus, self.cfg.corpus_dir, **self.cfg.options)
        return self._corpus

    def ground_truth(self, clip: Clip):
        """(params, identity, camera) of a synthetic clip."""
        if self._synthetic is None:
            from m3t.corpora.synthetic import SyntheticCorpus

            self._synthetic = SyntheticCorpus(self.cfg.corpus_dir)
        return self._synthetic.ground_truth(clip)


def track_clip(clip: Clip, ctx: FitContext) -> Path:
    """The clip's cached track: simulated for synthetic clips, else by media kind; keyed by media content."""
    kind = media_kind(clip)
    root = ctx.corpus.root
    if kind == "synthetic":
        media = root / clip.media
        if not media.exists():
            raise FileNotFoundError(f"media file {media} of clip {clip.id} is missing")
        key = _digest(KEY_VERSION, _file_digest(media), ctx.tracker_cfg, ctx.body_key)
    else:
        key = _digest(KEY_VERSION, media_key(clip, root, ctx.mediapipe_cfg))
    path = Path(ctx.cfg.cache_dir) / "tracks" / f"{clip.id.replace('/', '_')}-{key}.npz"
    if not path.exists():
        if kind == "synthetic":
            params, identity, camera = ctx.ground_truth(clip)
            track = simulate_track(clip.id, as_tensors(params), torch.as_tensor(identity), camera, clip.fps,
                                   ctx.body, ctx.tracker_cfg)
        else:
            track = track_real_clip(clip, root, ctx.mediapipe_cfg)
        save_track(track, path)
    return path


def fit_key(track_path: Path, ctx: FitContext) -> str:
    """Content address of a fit: the track's bytes, the fitting config and the body model."""
    return _digest(KEY_VERSION, _file_digest(track_path), ctx.fitting_cfg, ctx.body_key)


def fit_clip(clip: Clip, track_path: Path, key: str, ctx: FitContext) -> FittedClip:
    track = load_track(track_path)
    result = fit_track(track, ctx.body, ctx.fitting_cfg)
    metrics = dict(result.metrics)
    metrics.update(part_reprojection_px(ctx.body, result.params, result.identity, result.camera, track))
    if media_kind(clip) == "synthetic":
        gt_params, gt_identity, gt_camera = ctx.ground_truth(clip)
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
    seen: dict[str, Any] = {}
    try:
        track_path = track_clip(clip, ctx)
        track = load_track(track_path)
        seen = {"coverage": track_coverage(track), "track_frames": track.num_frames}
        key = fit_key(track_path, ctx)
        part = Path(ctx.cfg.cache_dir) / "parts" / f"{clip.id.replace('/', '_')}-{key}.parquet"
        if part.exists():
            fitted = read_shard(part).clips[0]
            return ClipOutcome(clip.id, clip.split, "cached", str(part), metrics=fitted.metrics,
                               frames=fitted.num_frames, **seen)
        fitted = fit_clip(clip, track_path, key, ctx)
        part.parent.mkdir(parents=True, exist_ok=True)
        write_shard(part, [fitted], ctx.body.layout)
        return ClipOutcome(clip.id, clip.split, "fitted", str(part), metrics=fitted.metrics,
                           frames=fitted.num_frames, seconds=time.perf_counter() - start, **seen)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # noqa: BLE001 - any failure of one clip quarantines that clip only
        reason = f"{type(exc).__name__}: {exc}"
        group = exc.group if isinstance(exc, ClipRefused) else type(exc).__name__
        return ClipOutcome(clip.id, clip.split, "quarantined", reason=reason, seconds=time.perf_counter() - start,
                           group=group, file=clip.media, **seen)


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

    worker_ctx = FitContext(ctx.cfg, ctx.body_cfg, ctx.tracker_cfg, ctx.fitting_cfg,
                            mediapipe_cfg=ctx.mediapipe_cfg)  # workers build their own model
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
    """List the corpus (unless ``clips`` are given), process every clip (in ``cfg.workers`` processes) and
    consolidate the shards; the rows the listing refused are reported as quarantined."""
    from tqdm.auto import tqdm

    start = time.perf_counter()
    outcomes: list[ClipOutcome] = []
    if clips is None:
        listing = list_corpus(ctx.cfg)
        clips, outcomes = listing.clips, listing_outcomes(listing)
    clips = list(clips)
    with tqdm(total=len(clips), desc="fit-corpus", unit="clip", disable=not progress) as bar:
        for outcome in _outcomes(ctx, clips):
            outcomes.append(outcome)
            bar.update(1)
            bar.set_postfix(status=outcome.status, quarantined=sum(o.status == "quarantined" for o in outcomes))
            if on_outcome is not None:
                on_outcome(outcome)
    return consolidate(outcomes, ctx.body.layout, ctx.cfg, time.perf_counter() - start)


def main(argv: list[str] | None = None) -> FitCorpusReport:
    """DVC entry point: params.yaml -> shards + an MLflow run."""
    from m3t.config import load_params

    parser = argparse.ArgumentParser(description="fit-corpus: clips -> tracks -> fits -> Parquet shards")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--preset", default="default")
    parser.add_argument("--corpus", default=None, help="a name of corpora in params.yaml (default fit_corpus.corpus)")
    args = parser.parse_args(argv)
    params = load_params(args.params, preset=args.preset)
    ctx = FitContext(for_corpus(params, args.corpus), params.body, params.tracker, params.fitting)
    report = run_fit_corpus(ctx)
    log_report(params, ctx, report)
    print(json.dumps({**report.summary, "quality": report.quality}, indent=2, sort_keys=True, default=str))
    return report


if __name__ == "__main__":
    main()
