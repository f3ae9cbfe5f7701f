"""The corpus-fitting engine: a corpus' clips -> tracks -> (fused) initialisation -> refined body-model
parameters -> one part file per clip -> shards (one per split) and the data-quality report.

One orchestration path for every caller: the DVC stage ``fit-corpus``, the Prefect flow ``fit-corpus`` and
tests all call :func:`run_fit_corpus` with a :class:`FitJob` (everything a worker needs, picklable: configs
only, never a built model) and any ``concurrent.futures.Executor``-like runner (``submit`` returning
futures that ``concurrent.futures.as_completed`` accepts): a process pool (the default for
``fit_corpus.workers > 1``), a thread pool, or a Dask ``Client.get_executor()``. Each worker process builds
its body model once (:func:`worker_context`) and reuses it for every clip it is sent.

Per clip (:func:`process_clip`): the track is content-addressed by its media and tracker settings, the fit
by the track's bytes, the fitting config, the body model and (when the clip carries them) the external
tracker outputs; both live under the cache dir and are written atomically, so a killed run resumes and an
unchanged clip is never re-fitted. Initialisation (M3T App. 0.C):

- synthetic clips: the simulated tracker's noisy 3D initialisation;
- clips with NLF / WiLoR / Pixel3DMM outputs beside their media (:func:`m3t.trackers.external.find_tracker_outputs`)
  and ``fusion.use_external``: those streams fused (:mod:`m3t.fitting.fusion`), then refined around them;
- otherwise the rest pose, and the clip's quality record says that no external outputs were found.

Clips of already-fitted corpora (media kinds ``smplx_params``, ``flame_params``, ``keypoints``) are imported
instead (:mod:`m3t.fitting.imports`): no track, no fit; their part files are addressed by the source arrays'
bytes and the conversion settings, and go through the same cache, quarantine and reports.

A clip that fails is quarantined with its reason; the others go on. :func:`m3t.fitting.report.consolidate`
writes the shards and reports.
"""
from __future__ import annotations

import hashlib
import json
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import numpy as np
import torch

from m3t.atomic import write_json
from m3t.body.factory import body_cache_key, load_body_model
from m3t.body.metric_sets import joints_for
from m3t.body.protocol import BodyModel, ModalityLayout, as_tensors
from m3t.corpora.base import CorpusAdapter, Listing, open_corpus
from m3t.corpora.clip import Clip
from m3t.fitting.config import FitCorpusConfig, FitJob  # noqa: F401 - FitCorpusConfig: the engine's config
from m3t.fitting.evaluate import ground_truth_errors, procrustes_error_mm
from m3t.fitting.fit import fit_track
from m3t.fitting.fusion import (
    FusionUnsupported,
    describe,
    initialise_from_trackers,
    refine,
)
from m3t.fitting.imports import (
    IMPORTERS,
    ImportSettings,
    check_importable,
    import_clip,
    import_settings,
    imported_kind,
    plan_import,
    read_source,
)
from m3t.fitting.quality import part_reprojection_px, track_coverage
from m3t.fitting.report import ClipOutcome, FitCorpusReport, consolidate
from m3t.shards.io import read_shard, write_shard
from m3t.shards.schema import FittedClip
from m3t.trackers.dispatch import ClipRefused, media_key, media_kind, track_real_clip
from m3t.trackers.external import TrackerOutputs, find_tracker_outputs
from m3t.trackers.simulated import simulate_track
from m3t.trackers.track import Track, load_track, save_track

KEY_VERSION = "fit-v2"  # bump when fitting code changes in a way that invalidates cached results
NO_EXTERNAL = "rest pose: no NLF / WiLoR / Pixel3DMM outputs beside the media"


def _digest(*parts: object) -> str:
    h = hashlib.sha256()
    for part in parts:
        h.update(part if isinstance(part, bytes) else json.dumps(part, sort_keys=True, default=str).encode())
        h.update(b"\0")
    return h.hexdigest()[:16]


def _file_digest(path: Path) -> bytes:
    return hashlib.sha256(path.read_bytes()).digest()


# ------------------------------------------------------------------------------------------ listing
def list_corpus(job: FitJob) -> Listing:
    """The adapter's listing (clips cut to ``max_clips``, its quarantined rows all kept)."""
    listing = open_corpus(job.corpus, job.source.root, **job.source.options).listing()
    clips = listing.clips[: job.run.max_clips] if job.run.max_clips > 0 else listing.clips
    return Listing(tuple(clips), listing.quarantined)


def listing_outcomes(listing: Listing) -> list[ClipOutcome]:
    """The rows the adapter refused, as quarantined outcomes (file + row + reason)."""
    return [ClipOutcome(q.clip_id or "", "", "quarantined", reason=q.reason, file=q.file, row=q.row,
                        group="listing: " + q.reason.split(":")[0].split(";")[0][:60], from_listing=True)
            for q in listing.quarantined]


# ------------------------------------------------------------------------------------ worker context
class FitContext:
    """What every clip of a job needs, built lazily and once per process: the body model, the corpus
    adapter, the synthetic ground truth reader."""

    def __init__(self, job: FitJob, body: BodyModel | None = None):
        self.job = job
        self._body = body
        self._corpus: CorpusAdapter | None = None
        self._synthetic = None
        self._body_key: object | None = None
        self._import_settings: ImportSettings | None = None

    @property
    def body(self) -> BodyModel:
        if self._body is None:
            self._body = load_body_model(self.job.body)
        return self._body

    @property
    def body_key(self) -> object:
        if self._body_key is None:  # hashing licensed model files once per process, not once per clip
            self._body_key = body_cache_key(self.job.body)
        return self._body_key

    @property
    def corpus(self) -> CorpusAdapter:
        if self._corpus is None:
            self._corpus = open_corpus(self.job.corpus, self.job.source.root, **self.job.source.options)
        return self._corpus

    @property
    def import_settings(self) -> ImportSettings:
        """What importing this job's clips depends on (reads SMPL-X's mean hand once per process if needed)."""
        if self._import_settings is None:
            self._import_settings = import_settings(self.job, self.corpus.config)
        return self._import_settings

    def ground_truth(self, clip: Clip):
        """(params, identity, camera) of a synthetic clip."""
        if self._synthetic is None:
            from m3t.corpora.synthetic import SyntheticCorpus

            self._synthetic = SyntheticCorpus(self.job.source.root)
        return self._synthetic.ground_truth(clip)


_CONTEXTS: dict[str, FitContext] = {}
_CONTEXTS_LOCK = threading.Lock()


def worker_context(job: FitJob) -> FitContext:
    """This process' context for ``job`` (one body model per process and job, shared by its threads)."""
    key = job.key()
    with _CONTEXTS_LOCK:
        if key not in _CONTEXTS:
            _CONTEXTS.clear()  # one job at a time per process: drop the previous job's model
            _CONTEXTS[key] = FitContext(job)
        return _CONTEXTS[key]


# ---------------------------------------------------------------------------------------- one clip
def track_clip(clip: Clip, ctx: FitContext) -> Path:
    """The clip's cached track: simulated for synthetic clips, else by media kind; keyed by media content."""
    kind = media_kind(clip)
    root = ctx.corpus.root
    if kind == "synthetic":
        media = root / clip.media
        if not media.exists():
            raise FileNotFoundError(f"media file {media} of clip {clip.id} is missing")
        key = _digest(KEY_VERSION, _file_digest(media), ctx.job.tracker, ctx.body_key)
    else:
        key = _digest(KEY_VERSION, media_key(clip, root, ctx.job.mediapipe))
    path = Path(ctx.job.run.cache_dir) / "tracks" / f"{clip.id.replace('/', '_')}-{key}.npz"
    if not path.exists():
        if kind == "synthetic":
            params, identity, camera = ctx.ground_truth(clip)
            track = simulate_track(clip.id, as_tensors(params), torch.as_tensor(identity), camera, clip.fps,
                                   ctx.body, ctx.job.tracker)
        else:
            track = track_real_clip(clip, root, ctx.job.mediapipe)
        save_track(track, path)
    return path


def external_outputs(clip: Clip, ctx: FitContext) -> TrackerOutputs | None:
    """The NLF / WiLoR / Pixel3DMM outputs beside a real clip's media, None for synthetic clips or when
    ``fusion.use_external`` is off."""
    if media_kind(clip) == "synthetic" or not ctx.job.fusion.use_external:
        return None
    return find_tracker_outputs(ctx.corpus.root / clip.media)


def fit_key(track_path: Path, outputs: TrackerOutputs | None, ctx: FitContext) -> str:
    """Content address of a fit: the track's bytes, the fitting config, the body model, and the external
    tracker outputs with the fusion settings when the clip has any (clips without keep their old key)."""
    parts: list[object] = [KEY_VERSION, _file_digest(track_path), ctx.job.fitting, ctx.body_key]
    if outputs is not None and outputs.any():
        parts += [outputs.digest(), ctx.job.fusion]
    return _digest(*parts)


def _fit(clip: Clip, track: Track, outputs: TrackerOutputs | None, ctx: FitContext):
    """(FitResult, initialisation record) for one clip."""
    if media_kind(clip) == "synthetic":
        return fit_track(track, ctx.body, ctx.job.fitting), {"init_source": "simulated tracker initialisation"}
    if outputs is None:
        return fit_track(track, ctx.body, ctx.job.fitting), {"init_source": "rest pose: fusion.use_external is off"}
    if not outputs.any():
        return fit_track(track, ctx.body, ctx.job.fitting), {"init_source": NO_EXTERNAL}
    try:
        fused = initialise_from_trackers(ctx.body, outputs, track.num_frames, ctx.job.fusion)
    except FusionUnsupported as exc:
        note = f"rest pose: external outputs ({', '.join(outputs.names())}) present but not usable: {exc}"
        return fit_track(track, ctx.body, ctx.job.fitting), {"init_source": note}
    return refine(track, fused, ctx.body, ctx.job.fitting), describe(fused)


def fit_clip(clip: Clip, track_path: Path, outputs: TrackerOutputs | None, key: str,
             ctx: FitContext) -> tuple[FittedClip, dict[str, Any]]:
    track = load_track(track_path)
    result, init = _fit(clip, track, outputs, ctx)
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
    fitted = FittedClip(clip=clip, key=key, params=result.params, identity=result.identity, camera=result.camera,
                        metrics=metrics, body_model=ctx.body.name)
    return fitted, init


def part_path(clip: Clip, key: str, ctx: FitContext) -> Path:
    return Path(ctx.job.run.cache_dir) / "parts" / f"{clip.id.replace('/', '_')}-{key}.parquet"


def _part_outcome(clip: Clip, part: Path, make: Callable[[], tuple[FittedClip, dict[str, Any]]],
                  layout: ModalityLayout, start: float, seen: dict[str, Any]) -> ClipOutcome:
    """The clip's part file from the cache when it and its record exist, else ``make()`` written atomically."""
    init_file = part.with_suffix(".init.json")
    if part.exists() and init_file.exists():
        fitted = read_shard(part).clips[0]
        return ClipOutcome(clip.id, clip.split, "cached", str(part), metrics=fitted.metrics,
                           frames=fitted.num_frames, init=json.loads(init_file.read_text()), **seen)
    fitted, init = make()
    part.parent.mkdir(parents=True, exist_ok=True)
    write_json(init_file, init)  # before the part: a part on disk always has its record
    write_shard(part, [fitted], layout)
    return ClipOutcome(clip.id, clip.split, "fitted", str(part), metrics=fitted.metrics,
                       frames=fitted.num_frames, seconds=time.perf_counter() - start, init=init, **seen)


def _import_part(clip: Clip, kind: str, ctx: FitContext, start: float) -> ClipOutcome:
    """An already-fitted clip's part: keyed by its source arrays and the conversion settings."""
    settings = ctx.import_settings
    check_importable(clip, kind, settings)
    arrays = sorted(read_source(clip, kind, ctx.corpus).items())
    key = _digest(KEY_VERSION, kind, settings.key(), [[name, list(a.shape), str(a.dtype)] for name, a in arrays],
                  *[np.ascontiguousarray(a).tobytes() for _, a in arrays])
    layout = settings.layout(kind, dims=arrays[0][1].shape[1])  # dims: the width of slt's one array
    return _part_outcome(clip, part_path(clip, key, ctx), lambda: import_clip(clip, kind, dict(arrays), key, settings),
                         layout, start, {})


def process_clip(clip: Clip, ctx: FitContext) -> ClipOutcome:
    """Track + fit (or import) + write one clip's part file; never raises for a bad clip (quarantines it)."""
    start = time.perf_counter()
    seen: dict[str, Any] = {}
    try:
        kind = media_kind(clip)
        if kind in IMPORTERS:
            return _import_part(clip, kind, ctx, start)
        track_path = track_clip(clip, ctx)
        track = load_track(track_path)
        seen = {"coverage": track_coverage(track), "track_frames": track.num_frames}
        outputs = external_outputs(clip, ctx)
        key = fit_key(track_path, outputs, ctx)
        return _part_outcome(clip, part_path(clip, key, ctx), lambda: fit_clip(clip, track_path, outputs, key, ctx),
                             ctx.body.layout, start, seen)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # noqa: BLE001 - any failure of one clip quarantines that clip only
        reason = f"{type(exc).__name__}: {exc}"
        group = exc.group if isinstance(exc, ClipRefused) else type(exc).__name__
        return ClipOutcome(clip.id, clip.split, "quarantined", reason=reason, seconds=time.perf_counter() - start,
                           group=group, file=clip.media, **seen)


def fit_one(job: FitJob, clip: Clip) -> ClipOutcome:
    """The unit sent to an executor: a picklable job and one clip, processed with this process' context."""
    return process_clip(clip, worker_context(job))


# ------------------------------------------------------------------------------------ the whole run
def _single_thread() -> None:
    torch.set_num_threads(1)  # one process per core; intra-op threads would oversubscribe


def default_executor(workers: int) -> Executor | None:
    """``workers`` spawned processes (None for one: clips then run in this process)."""
    if workers <= 1:
        return None
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    return ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_single_thread)


def _outcomes(job: FitJob, clips: list[Clip], executor: Executor | None,
              ctx: FitContext | None) -> Iterator[ClipOutcome]:
    """Outcomes in completion order."""
    if executor is None:
        ctx = ctx or worker_context(job)
        yield from (process_clip(c, ctx) for c in clips)
        return
    from concurrent.futures import as_completed
    from concurrent.futures.process import BrokenProcessPool

    futures = [executor.submit(fit_one, job, c) for c in clips]
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
    job: FitJob,
    executor: Executor | None = None,
    clips: Iterable[Clip] | None = None,
    progress: bool = True,
    on_outcome: Callable[[ClipOutcome], None] | None = None,
    ctx: FitContext | None = None,
) -> FitCorpusReport:
    """List the corpus (unless ``clips`` are given), process every clip on ``executor`` (default: a pool of
    ``fit_corpus.workers`` processes, or this process for one worker) and consolidate the shards; the rows
    the listing refused are reported as quarantined. ``ctx`` (in-process runs only) reuses a built model."""
    from tqdm.auto import tqdm

    start = time.perf_counter()
    outcomes: list[ClipOutcome] = []
    if clips is None:
        listing = list_corpus(job)
        clips, outcomes = listing.clips, listing_outcomes(listing)
    clips = list(clips)
    layout = None
    kind = imported_kind(job.corpus)
    if kind is not None:  # already-fitted clips: the import's layout, clips it cannot shard together refused now
        layout, clips, refused = plan_import(kind, (ctx or worker_context(job)).import_settings, clips)
        outcomes += refused
    own = executor is None and ctx is None
    executor = default_executor(job.run.workers) if own else executor
    try:
        with tqdm(total=len(clips), desc=f"fit-corpus {job.corpus}", unit="clip", disable=not progress) as bar:
            for outcome in _outcomes(job, clips, executor, ctx):
                outcomes.append(outcome)
                bar.update(1)
                bar.set_postfix(status=outcome.status,
                                quarantined=sum(o.status == "quarantined" for o in outcomes))
                if on_outcome is not None:
                    on_outcome(outcome)
    finally:
        if own and executor is not None:
            executor.shutdown(cancel_futures=True)
    layout = layout or (ctx or worker_context(job)).body.layout
    return consolidate(outcomes, layout, job.shards_dir, job.corpus, time.perf_counter() - start)


def fit_and_log(job: FitJob, experiment, executor: Executor | None = None, progress: bool = True,
                on_outcome: Callable[[ClipOutcome], None] | None = None, log: bool = True) -> FitCorpusReport:
    """:func:`run_fit_corpus`, then the MLflow run of the corpus (params, results, quality, pictures)."""
    from m3t.experiment import section_params
    from m3t.fitting.report import log_fit_corpus

    report = run_fit_corpus(job, executor, progress=progress, on_outcome=on_outcome)
    if log:
        ctx = worker_context(job)
        kind = imported_kind(job.corpus)
        # pictures need the body model and full-body streams: none for face-only or slt feature shards
        render = job.run.render_clips if kind in (None, "smplx_params") else 0
        sections = {"body": job.body, "fitting": job.fitting, "fit_corpus": job.run,
                    **({"tracker": job.tracker} if job.corpus == "synthetic" else {"fusion": job.fusion})}
        logged = {**section_params(**sections), "corpus": job.corpus,
                  f"corpora.{job.corpus}": {"root": job.source.root, "options": job.source.options},
                  "shards_dir": job.shards_dir}
        truth = ctx.ground_truth if job.corpus == "synthetic" else None
        log_fit_corpus(experiment, logged, report, ctx.body if render else None, job.corpus, job.shards_dir,
                       job.run.cache_dir, render, truth)
    return report
