"""A signer's clips fitted together (:func:`process_batch`): one batch of
:func:`m3t.fitting.corpus.plan_batches`, its clips fitted from their 2D tracks in one solver run.

With ``fitting.solver: lbfgs`` a batch is one problem with one identity, the paper's static per-signer shape; with
``lbfgs_batched`` / ``lbfgs_lockstep`` every clip is its own problem (its own identity), solved at a batch's speed.
A batch's part files are addressed by the tracks of all its members, so a clip's fit is redone when a batch mate
changes.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from m3t.corpora.clip import Clip
from m3t.digest import file_digest_bytes
from m3t.fitting.cache import cache_key, part_outcome, part_path
from m3t.fitting.context import FitContext
from m3t.fitting.fit import FitResult, fit_tracks
from m3t.fitting.imports import IMPORTERS
from m3t.fitting.per_clip import (
    external_outputs,
    fitted_record,
    init_source,
    process_clip,
    track_clip,
)
from m3t.fitting.quality import track_coverage
from m3t.fitting.report import ClipOutcome
from m3t.shards.schema import FittedClip
from m3t.trackers.dispatch import media_kind
from m3t.trackers.external import TrackerOutputs
from m3t.trackers.track import Track, load_track


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
    """Several clips of one signer: those fitted from their 2D track alone (clips whose tracker gives its own
    initialisation, real clips without external tracker outputs) are fitted together (:func:`fit_signer_batch`);
    imports, clips with external outputs (their own fused identity) and clips that fail to track go through
    :func:`m3t.fitting.per_clip.process_clip` one by one. When the batch fit fails, its clips are fitted one by
    one. Never raises for a bad clip."""
    if len(clips) == 1:
        return [process_clip(clips[0], ctx)]
    outcomes: list[ClipOutcome] = []
    members: list[tuple[Clip, Path, Track, TrackerOutputs | None, float]] = []
    for clip in clips:
        start = time.perf_counter()
        try:
            if media_kind(clip) in IMPORTERS:
                outcomes.append(process_clip(clip, ctx))
                continue
            track_file = track_clip(clip, ctx)
            track = load_track(track_file)
            outputs = external_outputs(clip, track, ctx)
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception:  # noqa: BLE001 - process_clip quarantines it with its reason
            outcomes.append(process_clip(clip, ctx))
            continue
        if outputs is not None and outputs.any():
            outcomes.append(process_clip(clip, ctx))
        else:
            members.append((clip, track_file, track, outputs, start))
    if len(members) <= 1:
        return outcomes + [process_clip(m[0], ctx) for m in members]
    key = cache_key("signer batch", [file_digest_bytes(m[1]) for m in members], ctx.job.fitting, ctx.body_key,
                    ctx.job.run.batch_frames)
    tracks = [m[2] for m in members]
    fitted: list[FitResult] = []

    def make(i: int) -> tuple[FittedClip, dict[str, Any]]:
        if not fitted:
            fitted.extend(fit_signer_batch(tracks, ctx))
        clip, _, track, outputs, _ = members[i]
        shared = f"one per batch: {len(members)} clips of signer {clip.signer!r}"
        init = {"init_source": init_source(track, outputs),
                "identity": f"one per clip ({ctx.job.fitting.solver})" if ctx.job.fitting.per_clip_problems else shared}
        return fitted_record(clip, track, fitted[i], key, ctx), init

    try:
        for i, (clip, _, track, _, start) in enumerate(members):
            seen = {"coverage": track_coverage(track), "track_frames": track.num_frames}
            outcomes.append(part_outcome(clip, part_path(clip, key, ctx), lambda i=i: make(i), ctx.body.layout,
                                         start, seen))
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception:  # noqa: BLE001 - one clip may spoil the batch: fit them one by one instead
        done = {o.clip_id for o in outcomes}
        outcomes += [process_clip(m[0], ctx) for m in members if m[0].id not in done]
    return outcomes
