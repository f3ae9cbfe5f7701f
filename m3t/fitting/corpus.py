"""The corpus-fitting engine: a corpus' clips -> tracks -> (fused) initialisation -> refined body-model
parameters -> one part file per clip -> shards (one per split) and the data-quality report.

One orchestration path for every caller: the DVC stage ``fit-corpus``, the Prefect flow ``fit-corpus`` and
tests all call :func:`run_fit_corpus` with a :class:`FitJob` (everything a worker needs, picklable: configs
only, never a built model) and, by default, the executor of ``fit_corpus.executor``
(:func:`m3t.fitting.cluster.open_executor`: local processes or a Dask cluster), or any
``concurrent.futures.Executor``-like runner passed in. The unit of work is a signer batch (:func:`plan_batches`,
:func:`process_batch`: a signer's clips fitted together with one identity). Each worker process builds its body
model once (:func:`worker_context`) and reuses it for every batch it is sent.

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

import json
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import numpy as np
import torch

from m3t.arithmetic import cache_parts
from m3t.atomic import run_lock, write_json, write_text
from m3t.body.factory import body_cache_key, load_body_model
from m3t.body.metric_sets import joints_for
from m3t.body.protocol import BodyModel, ModalityLayout, as_tensors
from m3t.corpora.base import CorpusAdapter, Listing, open_corpus
from m3t.corpora.clip import Clip
from m3t.digest import canonical_json, chunks_digest, file_digest, file_digest_bytes
from m3t.fitting.config import FitCorpusConfig, FitJob  # noqa: F401 - FitCorpusConfig: the engine's config
from m3t.fitting.evaluate import ground_truth_errors, procrustes_error_mm
from m3t.fitting.fit import FitResult, fit_track, fit_tracks
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
    """16-hex cache key of ``parts``: bytes as they are, anything else as sorted-key JSON, each followed by NUL."""
    chunks: list[bytes] = []
    for part in (*parts, *cache_parts()):
        chunks += [part if isinstance(part, bytes) else canonical_json(part), b"\0"]
    return chunks_digest(chunks, length=16)


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
        key = _digest(KEY_VERSION, file_digest_bytes(media), ctx.job.tracker, ctx.body_key)
    else:
        key = _digest(KEY_VERSION, media_key(clip, root, ctx.job.mediapipe))
    path = Path(ctx.job.run.cache_dir) / "tracks" / f"{clip.id.replace('/', '_')}-{key}.npz"
    if not (path.exists() and _cache_intact(path, load_track)):
        if kind == "synthetic":
            params, identity, camera = ctx.ground_truth(clip)
            track = simulate_track(clip.id, as_tensors(params), torch.as_tensor(identity), camera, clip.fps,
                                   ctx.body, ctx.job.tracker)
        else:
            track = track_real_clip(clip, root, ctx.job.mediapipe)
        save_track(track, path)
        _vouch(path)
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
    parts: list[object] = [KEY_VERSION, file_digest_bytes(track_path), ctx.job.fitting, ctx.body_key]
    if outputs is not None and outputs.any():
        parts += [outputs.digest(), ctx.job.fusion]
    return _digest(*parts)


def _fit(clip: Clip, track: Track, outputs: TrackerOutputs | None, ctx: FitContext):
    """(FitResult, initialisation record) for one clip."""
    if media_kind(clip) == "synthetic" or outputs is None or not outputs.any():
        return fit_track(track, ctx.body, ctx.job.fitting), {"init_source": _init_source(clip, outputs)}
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
    return fitted_record(clip, track, result, key, ctx), init


def fitted_record(clip: Clip, track: Track, result: FitResult, key: str, ctx: FitContext) -> FittedClip:
    """The part-file record of a fit: its parameters and metrics (per landmark part; against the ground truth
    for synthetic clips)."""
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


def part_path(clip: Clip, key: str, ctx: FitContext) -> Path:
    return Path(ctx.job.run.cache_dir) / "parts" / f"{clip.id.replace('/', '_')}-{key}.parquet"


def _checksum_file(cached: Path) -> Path:
    return cached.with_suffix(".sha256")


def _vouch(cached: Path) -> None:
    """Write the SHA-256 of a cached track or part beside it, after the file itself: the digest vouches for it."""
    write_text(_checksum_file(cached), file_digest(cached))


def _cache_intact(cached: Path, read: Callable[[Path], object]) -> bool:
    """Whether a cached track or part file is the one its run wrote: its SHA-256 matches the digest written
    beside it (a flipped byte on disk is redone, never read). A file cached before digests existed is trusted
    once ``read`` reads it back, and gets its digest."""
    digest = file_digest(cached)
    checksum = _checksum_file(cached)
    if checksum.exists():
        return checksum.read_text().strip() == digest
    try:
        read(cached)
    except Exception:  # noqa: BLE001 - unreadable: redo it
        return False
    write_text(checksum, digest)
    return True


def _part_outcome(clip: Clip, part: Path, make: Callable[[], tuple[FittedClip, dict[str, Any]]],
                  layout: ModalityLayout, start: float, seen: dict[str, Any]) -> ClipOutcome:
    """The clip's part file from the cache when it and its record exist, else ``make()`` written atomically."""
    init_file = part.with_suffix(".init.json")
    if part.exists() and init_file.exists() and _cache_intact(part, read_shard):
        fitted = read_shard(part).clips[0]
        return ClipOutcome(clip.id, clip.split, "cached", str(part), metrics=fitted.metrics,
                           frames=fitted.num_frames, init=json.loads(init_file.read_text()), **seen)
    fitted, init = make()
    part.parent.mkdir(parents=True, exist_ok=True)
    write_json(init_file, init)  # before the part: a part on disk always has its record
    write_shard(part, [fitted], layout)
    _vouch(part)
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


def _init_source(clip: Clip, outputs: TrackerOutputs | None) -> str:
    """Where a clip fitted from its 2D track alone started (synthetic, or real without usable outputs)."""
    if media_kind(clip) == "synthetic":
        return "simulated tracker initialisation"
    return "rest pose: fusion.use_external is off" if outputs is None else NO_EXTERNAL


def fit_signer_batch(tracks: list[Track], ctx: FitContext) -> list[FitResult]:
    """One signer's tracks fitted with one identity: in chunks of at most ``fit_corpus.batch_frames`` frames,
    the first chunk fitting the identity and the others holding it. With ``fitting.solver: lbfgs_batched`` or
    ``lbfgs_lockstep`` every clip of a chunk is its own problem, with its own identity."""
    own_identity = ctx.job.fitting.per_clip_problems
    chunks: list[list[int]] = [[]]
    frames = 0
    for i, track in enumerate(tracks):
        if chunks[-1] and frames + track.num_frames > ctx.job.run.batch_frames > 0:
            chunks.append([])
            frames = 0
        chunks[-1].append(i)
        frames += track.num_frames
    results: list[FitResult | None] = [None] * len(tracks)
    identity = None
    for chunk in chunks:
        for i, result in zip(chunk, fit_tracks([tracks[i] for i in chunk], ctx.body, ctx.job.fitting,
                                               identity=identity)):
            results[i] = result
        identity = None if own_identity else results[chunk[0]].identity
    return results  # type: ignore[return-value]


def process_batch(clips: list[Clip], ctx: FitContext) -> list[ClipOutcome]:
    """Several clips of one signer (:func:`plan_batches`): those fitted from their 2D track alone (synthetic
    clips, real clips without external tracker outputs) are fitted together with one shared identity
    (:func:`fit_signer_batch`); imports, clips with external outputs (their own fused identity) and clips that
    fail to track go through :func:`process_clip` one by one. A batch's part files are addressed by the tracks
    of all its members; when the batch fit fails, its clips are fitted one by one. Never raises for a bad clip."""
    if len(clips) == 1:
        return [process_clip(clips[0], ctx)]
    outcomes: list[ClipOutcome] = []
    members: list[tuple[Clip, Path, TrackerOutputs | None, float]] = []
    for clip in clips:
        start = time.perf_counter()
        try:
            if media_kind(clip) in IMPORTERS:
                outcomes.append(process_clip(clip, ctx))
                continue
            track_path = track_clip(clip, ctx)
            outputs = external_outputs(clip, ctx)
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception:  # noqa: BLE001 - process_clip quarantines it with its reason
            outcomes.append(process_clip(clip, ctx))
            continue
        if outputs is not None and outputs.any():
            outcomes.append(process_clip(clip, ctx))
        else:
            members.append((clip, track_path, outputs, start))
    if len(members) <= 1:
        return outcomes + [process_clip(m[0], ctx) for m in members]
    key = _digest(KEY_VERSION, "signer batch", [file_digest_bytes(m[1]) for m in members], ctx.job.fitting,
                  ctx.body_key, ctx.job.run.batch_frames)
    tracks = [load_track(m[1]) for m in members]
    fitted: list[FitResult] = []

    def make(i: int) -> tuple[FittedClip, dict[str, Any]]:
        if not fitted:
            fitted.extend(fit_signer_batch(tracks, ctx))
        clip, _, outputs, _ = members[i]
        shared = f"one per batch: {len(members)} clips of signer {clip.signer!r}"
        init = {"init_source": _init_source(clip, outputs),
                "identity": f"one per clip ({ctx.job.fitting.solver})" if ctx.job.fitting.per_clip_problems else shared}
        return fitted_record(clip, tracks[i], fitted[i], key, ctx), init

    try:
        for i, (clip, _, _, start) in enumerate(members):
            seen = {"coverage": track_coverage(tracks[i]), "track_frames": tracks[i].num_frames}
            outcomes.append(_part_outcome(clip, part_path(clip, key, ctx), lambda i=i: make(i), ctx.body.layout,
                                          start, seen))
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception:  # noqa: BLE001 - one clip may spoil the batch: fit them one by one instead
        done = {o.clip_id for o in outcomes}
        outcomes += [process_clip(m[0], ctx) for m in members if m[0].id not in done]
    return outcomes


def plan_batches(clips: list[Clip], batch_clips: int) -> list[list[Clip]]:
    """Clips grouped by signer (in listing order), at most ``batch_clips`` per batch (1 = a batch per clip)."""
    if batch_clips <= 1:
        return [[c] for c in clips]
    by_signer: dict[str, list[Clip]] = {}
    for clip in clips:
        by_signer.setdefault(clip.signer, []).append(clip)
    return [group[i:i + batch_clips] for group in by_signer.values() for i in range(0, len(group), batch_clips)]


def fit_batch(job: FitJob, clips: list[Clip]) -> list[ClipOutcome]:
    """The unit sent to an executor: a picklable job and one batch of :func:`plan_batches`, processed with this
    process' context."""
    return process_batch(clips, worker_context(job))


# ------------------------------------------------------------------------------------ the whole run
LOCK_NAME = ".fit-corpus.lock"  # in the shards dir while a run writes it: a second run on it is refused
POLL_SECONDS = 10.0  # while no clip finishes, how often an executor is asked whether its cluster is still there


def _outcomes(job: FitJob, clips: list[Clip], executor: Executor | None,
              ctx: FitContext | None) -> Iterator[ClipOutcome]:
    """Outcomes in completion order, batch by batch (:func:`plan_batches`). An executor with ``capacity()``
    (Dask) gets at most that many batches at a time; one with ``check()`` is asked, while no batch finishes,
    whether its cluster is still there (it raises when not). The clips of a batch whose worker died are
    quarantined and the others go on (:mod:`m3t.fitting.cluster`)."""
    batches = plan_batches(clips, job.run.batch_clips)
    if executor is None:
        ctx = ctx or worker_context(job)
        for batch in batches:
            yield from process_batch(batch, ctx)
        return
    from concurrent.futures import FIRST_COMPLETED, CancelledError, Future, wait
    from concurrent.futures.process import BrokenProcessPool
    from itertools import islice

    from m3t.fitting.cluster import worker_died

    capacity = getattr(executor, "capacity", lambda: len(batches))
    check = getattr(executor, "check", lambda: None)
    todo, left = iter(batches), len(batches)
    running: dict[Future, list[Clip]] = {}
    try:
        while True:
            if left:
                sent = list(islice(todo, max(capacity() - len(running), 0)))
                left -= len(sent)
                running.update((executor.submit(fit_batch, job, b), b) for b in sent)
            if not running:
                return
            done, _ = wait(running, timeout=POLL_SECONDS, return_when=FIRST_COMPLETED)
            if not done:
                check()
            for future in done:
                batch = running.pop(future)
                try:
                    outcomes = future.result()
                except CancelledError as exc:  # Dask cancels every task when its scheduler connection drops
                    check()
                    raise RuntimeError(f"clip {batch[0].id}: the executor cancelled its task; finished clips are "
                                       "cached, rerun to resume") from exc
                except Exception as exc:
                    if not worker_died(exc):
                        raise
                    outcomes = [ClipOutcome(clip.id, clip.split, "quarantined", group="worker died", file=clip.media,
                                            reason=f"worker died while fitting this clip: {type(exc).__name__}: "
                                                   f"{exc} (the next run retries it)") for clip in batch]
                yield from outcomes
    except BrokenProcessPool as exc:
        raise RuntimeError("a fit-corpus worker process died (out of memory or killed); finished clips are "
                           "cached, rerun to resume") from exc
    finally:
        for future in running:
            future.cancel()


def run_fit_corpus(
    job: FitJob,
    executor: Executor | None = None,
    clips: Iterable[Clip] | None = None,
    progress: bool = True,
    on_outcome: Callable[[ClipOutcome], None] | None = None,
    ctx: FitContext | None = None,
) -> FitCorpusReport:
    """List the corpus (unless ``clips`` are given), process every clip on ``executor`` (default: the one of
    ``fit_corpus.executor``, :func:`m3t.fitting.cluster.open_executor`: a pool of ``fit_corpus.workers``
    processes, this process for one worker, or a Dask cluster) and consolidate the shards; the rows the listing
    refused are reported as quarantined. ``ctx`` (in-process runs only) reuses a built model."""
    from contextlib import ExitStack

    from tqdm.auto import tqdm

    from m3t.fitting.cluster import open_executor

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
    opened = ExitStack()  # the lock on the shards, then the run's own executor; released when the run ends or stops
    opened.enter_context(run_lock(Path(job.shards_dir) / LOCK_NAME, f"fit-corpus {job.corpus}"))
    try:
        executor = opened.enter_context(open_executor(job.run)) if own else executor
        with tqdm(total=len(clips), desc=f"fit-corpus {job.corpus}", unit="clip", disable=not progress) as bar:
            for outcome in _outcomes(job, clips, executor, ctx):
                outcomes.append(outcome)
                bar.update(1)
                bar.set_postfix(status=outcome.status,
                                quarantined=sum(o.status == "quarantined" for o in outcomes))
                if on_outcome is not None:
                    on_outcome(outcome)
        layout = layout or (ctx or worker_context(job)).body.layout
        return consolidate(outcomes, layout, job.shards_dir, job.corpus, time.perf_counter() - start)
    finally:
        opened.close()


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
