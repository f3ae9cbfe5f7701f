"""One clip through fit-corpus: track (or import) -> initialisation -> refined fit -> its part file
(:func:`process_clip`, which never raises for a bad clip: it quarantines it with its reason).

Every media kind goes the same way. The track comes from the tracker dispatch
(:func:`m3t.trackers.dispatch.track_media`), cached under the key of what it depends on
(:func:`m3t.trackers.dispatch.track_key`). The initialisation (M3T App. 0.C) is, in this order:

- the track's own 3D initialisation when its tracker gives one (the simulated tracker of the synthetic corpus);
- else the NLF / WiLoR / Pixel3DMM outputs beside the clip's media
  (:func:`m3t.trackers.external.find_tracker_outputs`) with ``fusion.use_external``: those streams fused
  (:mod:`m3t.fitting.fusion`), then refined around them;
- else the rest pose, and the clip's quality record says that no external outputs were found.

A fit is addressed by the track's bytes, the fitting config, the body model and (when the clip has them) the
external outputs with the fusion settings. A clip whose media is ground-truth motion
(:func:`m3t.trackers.dispatch.ground_truth`) also gets its errors against that truth. Clips of already-fitted
corpora (media kinds ``smplx_params``, ``flame_params``, ``keypoints``) are imported instead
(:mod:`m3t.fitting.imports`): no track, no fit; their part files are addressed by the source arrays' bytes and the
conversion settings, and go through the same cache, quarantine and reports.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from m3t.body.metric_sets import joints_for
from m3t.corpora.clip import Clip
from m3t.digest import file_digest_bytes
from m3t.fitting.cache import (
    cache_intact,
    cache_key,
    part_outcome,
    part_path,
    track_path,
    vouch,
)
from m3t.fitting.context import FitContext
from m3t.fitting.evaluate import ground_truth_errors, procrustes_error_mm
from m3t.fitting.fit import FitResult, fit_track
from m3t.fitting.fusion import (
    FusionUnsupported,
    describe,
    initialise_from_trackers,
    refine,
)
from m3t.fitting.imports import IMPORTERS, check_importable, import_clip, read_source
from m3t.fitting.quality import part_reprojection_px, track_coverage
from m3t.fitting.report import ClipOutcome
from m3t.shards.schema import FittedClip
from m3t.trackers.dispatch import (
    ClipRefused,
    ground_truth,
    media_kind,
    track_key,
    track_media,
)
from m3t.trackers.external import TrackerOutputs, find_tracker_outputs
from m3t.trackers.track import Track, load_track, save_track

NO_EXTERNAL = "rest pose: no NLF / WiLoR / Pixel3DMM outputs beside the media"


def track_clip(clip: Clip, ctx: FitContext) -> Path:
    """The clip's cached track, tracked by its media kind on a cache miss; keyed by what the track depends on."""
    root = ctx.corpus.root
    path = track_path(clip, cache_key(*track_key(clip, root, ctx)), ctx)
    if not (path.exists() and cache_intact(path, load_track)):
        save_track(track_media(clip, root, ctx), path)
        vouch(path)
    return path


def external_outputs(clip: Clip, track: Track, ctx: FitContext) -> TrackerOutputs | None:
    """The NLF / WiLoR / Pixel3DMM outputs beside the clip's media; None when its track carries its tracker's own
    3D initialisation (that one is used) or ``fusion.use_external`` is off."""
    if track.init is not None or not ctx.job.fusion.use_external:
        return None
    return find_tracker_outputs(ctx.corpus.root / clip.media)


def fit_key(track_file: Path, outputs: TrackerOutputs | None, ctx: FitContext) -> str:
    """Content address of a fit: the track's bytes, the fitting config, the body model, and the external
    tracker outputs with the fusion settings when the clip has any (clips without keep their old key)."""
    parts: list[object] = [file_digest_bytes(track_file), ctx.job.fitting, ctx.body_key]
    if outputs is not None and outputs.any():
        parts += [outputs.digest(), ctx.job.fusion]
    return cache_key(*parts)


def init_source(track: Track, outputs: TrackerOutputs | None) -> str:
    """Where a clip fitted from its 2D track alone started: its tracker's 3D initialisation, or the rest pose."""
    if track.init is not None:
        return f"{track.tracker} tracker initialisation"
    return "rest pose: fusion.use_external is off" if outputs is None else NO_EXTERNAL


def _fit(track: Track, outputs: TrackerOutputs | None, ctx: FitContext) -> tuple[FitResult, dict[str, Any]]:
    """(FitResult, initialisation record) for one clip."""
    if outputs is None or not outputs.any():
        return fit_track(track, ctx.body, ctx.job.fitting), {"init_source": init_source(track, outputs)}
    try:
        fused = initialise_from_trackers(ctx.body, outputs, track.num_frames, ctx.job.fusion)
    except FusionUnsupported as exc:
        note = f"rest pose: external outputs ({', '.join(outputs.names())}) present but not usable: {exc}"
        return fit_track(track, ctx.body, ctx.job.fitting), {"init_source": note}
    return refine(track, fused, ctx.body, ctx.job.fitting), describe(fused)


def fit_clip(clip: Clip, track_file: Path, outputs: TrackerOutputs | None, key: str,
             ctx: FitContext) -> tuple[FittedClip, dict[str, Any]]:
    track = load_track(track_file)
    result, init = _fit(track, outputs, ctx)
    return fitted_record(clip, track, result, key, ctx), init


def fitted_record(clip: Clip, track: Track, result: FitResult, key: str, ctx: FitContext) -> FittedClip:
    """The part-file record of a fit: its parameters and metrics (per landmark part; against the ground truth
    when the clip's media is ground-truth motion)."""
    metrics = dict(result.metrics)
    metrics.update(part_reprojection_px(ctx.body, result.params, result.identity, result.camera, track))
    truth = ground_truth(clip, ctx.corpus.root)
    if truth is not None:
        gt_params, gt_identity, gt_camera = truth
        metrics.update(ground_truth_errors(ctx.body, result.params, result.identity, result.camera,
                                           gt_params, gt_identity, gt_camera.as_dict()))
        if track.init is not None:  # what refinement gained over the tracker initialisation
            with torch.no_grad():
                truth_joints = joints_for(ctx.body, gt_params, gt_identity)
                init_joints = joints_for(ctx.body, track.init, ctx.body.default_identity().numpy())
            metrics["init_pa_joint_mm"] = procrustes_error_mm(init_joints, truth_joints)
    return FittedClip(clip=clip, key=key, params=result.params, identity=result.identity, camera=result.camera,
                      metrics=metrics, body_model=ctx.body.name)


def _import_part(clip: Clip, kind: str, ctx: FitContext, start: float) -> ClipOutcome:
    """An already-fitted clip's part: keyed by its source arrays and the conversion settings."""
    settings = ctx.import_settings
    check_importable(clip, kind, settings)
    arrays = sorted(read_source(clip, kind, ctx.corpus).items())
    key = cache_key(kind, settings.key(), [[name, list(a.shape), str(a.dtype)] for name, a in arrays],
                    *[np.ascontiguousarray(a).tobytes() for _, a in arrays])
    layout = settings.layout(kind, dims=arrays[0][1].shape[1])  # dims: the width of slt's one array
    return part_outcome(clip, part_path(clip, key, ctx), lambda: import_clip(clip, kind, dict(arrays), key, settings),
                        layout, start, {})


def process_clip(clip: Clip, ctx: FitContext) -> ClipOutcome:
    """Track + fit (or import) + write one clip's part file; never raises for a bad clip (quarantines it)."""
    start = time.perf_counter()
    seen: dict[str, Any] = {}
    try:
        kind = media_kind(clip)
        if kind in IMPORTERS:
            return _import_part(clip, kind, ctx, start)
        track_file = track_clip(clip, ctx)
        track = load_track(track_file)
        seen = {"coverage": track_coverage(track), "track_frames": track.num_frames}
        outputs = external_outputs(clip, track, ctx)
        key = fit_key(track_file, outputs, ctx)
        return part_outcome(clip, part_path(clip, key, ctx), lambda: fit_clip(clip, track_file, outputs, key, ctx),
                            ctx.body.layout, start, seen)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # noqa: BLE001 - any failure of one clip quarantines that clip only
        reason = f"{type(exc).__name__}: {exc}"
        group = exc.group if isinstance(exc, ClipRefused) else type(exc).__name__
        return ClipOutcome(clip.id, clip.split, "quarantined", reason=reason, seconds=time.perf_counter() - start,
                           group=group, file=clip.media, **seen)
