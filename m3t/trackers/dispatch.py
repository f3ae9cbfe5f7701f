"""A listed clip's media -> Track, chosen by the clip's ``media_kind``, and what that track depends on.

fit-corpus addresses a clip's track in its cache by :func:`track_key` (the media's content and the tracker
settings, never only its path) and calls :func:`track_media` on a cache miss; every corpus goes this way. The
inputs beyond the media (:class:`TrackingInputs`) are the 2D trackers' settings and, for the simulated tracker,
the body model that projects ground-truth motion.

=================  =====================================================================================
media kind         tracking
=================  =====================================================================================
synthetic          ground-truth motion (the synthetic corpus' ``.npz``) -> the simulated tracker
                   (:mod:`m3t.trackers.simulated`): a noisy 2D track with its own 3D initialisation;
                   :func:`ground_truth` gives the motion back for scoring the fit
pose               the ``.pose`` file -> track (:mod:`m3t.trackers.posefile`)
spelled            the word's letter ``.pose`` files concatenated -> track (same conversion)
video, frames      MediaPipe Holistic (:mod:`m3t.trackers.mediapipe_holistic`), world landmarks kept
smplx_params       never tracked (:data:`REFUSED`, :class:`ClipRefused` here): fit-corpus imports them
flame_params       (:mod:`m3t.fitting.imports`): SMPL-X fits -> SMPL-FX shards, FLAME fits -> face-only
keypoints          shards, slt ``sign`` arrays -> feature shards as stored, no invented joint mapping
=================  =====================================================================================
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from m3t.corpora.clip import Clip
from m3t.digest import file_digest, file_digest_bytes
from m3t.trackers.config import MediaPipeConfig, SimulatedTrackerConfig
from m3t.trackers.track import Track

if TYPE_CHECKING:
    from m3t.body.protocol import BodyModel
    from m3t.camera import Camera

SIMULATED_CORPUS = "synthetic"  # its clips are ground-truth motion, tracked by the simulated tracker
POSEFILE_VERSION = "posefile-v1"  # bump when the .pose -> track conversion changes its output
REFUSED = {  # media kinds fit-corpus imports instead of tracking (m3t.fitting.imports.IMPORTERS)
    "smplx_params": "already-fitted SMPL-X parameters are imported into SMPL-FX shards (body.model: smplfx), "
                    "not tracked",
    "flame_params": "already-fitted FLAME parameters are imported into face-only shards (body.model: smplfx), "
                    "not tracked",
    "keypoints": "pre-extracted per-frame arrays without a documented landmark layout are imported as stored, "
                 "not tracked; to fit a body model to keypoints, export them as .pose files",
}


class ClipRefused(ValueError):
    """A clip this pipeline cannot track; ``group`` is the short reason the quality report counts."""

    def __init__(self, group: str, message: str):
        super().__init__(message)
        self.group = group


def media_kind(clip: Clip) -> str:
    """The clip's media kind; clips of the synthetic corpus listed without one are ``synthetic``."""
    kind = clip.get("media_kind")
    if kind is None and clip.corpus == SIMULATED_CORPUS:
        return "synthetic"
    if kind is None:
        raise ClipRefused("no media kind", f"clip {clip.id} carries no media_kind; list it through its corpus adapter")
    return kind


def media_digest(path: Path) -> str:
    """Hex SHA-256 of a media file's bytes; a missing file names the fix."""
    if not path.is_file():
        raise FileNotFoundError(f"media file {path} is missing; check the corpus root")
    return file_digest(path)


def _folder_stamp(folder: Path) -> list[tuple[str, int, int]]:
    """Names, sizes and mtimes of a frame folder's images: cheap, and changes whenever a frame does."""
    from m3t.trackers.media import list_frame_files

    return [(p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in list_frame_files(folder)]


def media_key(clip: Clip, root: Path, mediapipe_cfg: object | None = None) -> object:
    """What a clip's track depends on: its media content and the tracker's settings (JSON-able)."""
    kind = media_kind(clip)
    media = root / clip.media
    if kind == "pose":
        return [kind, POSEFILE_VERSION, media_digest(media)]
    if kind == "spelled":
        from m3t.corpora.fingerspelling import spelled_paths

        return [kind, POSEFILE_VERSION, clip.fps, [media_digest(p) for p in spelled_paths(clip, root)]]
    if kind in ("video", "frames"):
        content = _folder_stamp(media) if media.is_dir() else media_digest(media)
        return [kind, dataclasses.asdict(mediapipe_cfg) if mediapipe_cfg is not None else None, clip.fps, content]
    if kind in REFUSED:
        raise ClipRefused(f"{kind} not trackable", f"clip {clip.id} ({clip.media}): {REFUSED[kind]}")
    raise ClipRefused(f"media kind {kind}", f"clip {clip.id}: media kind {kind!r} has no tracker here")


def _holistic(media: Path, fps: float, cfg) -> Track:
    from m3t.trackers.mediapipe_holistic import import_mediapipe, run_holistic

    try:
        import_mediapipe()
    except ImportError as exc:  # its message names `bash .ci/install-tracking`
        raise ClipRefused("mediapipe not installed", str(exc)) from exc
    out = run_holistic(media, cfg, fps=fps)
    return dataclasses.replace(out.track, extras={"pose_world": out.pose_world})


def track_real_clip(clip: Clip, root: Path, mediapipe_cfg=None) -> Track:
    """Track one listed clip of a real corpus; raises (the stage quarantines) when it cannot."""
    from m3t.trackers.posefile import load_pose_track, posedata_to_track

    kind = media_kind(clip)
    media = root / clip.media
    if kind == "pose":
        track = load_pose_track(media).track
    elif kind == "spelled":
        from m3t.corpora.fingerspelling import spell_files, spelled_paths

        track = posedata_to_track(spell_files(spelled_paths(clip, root)), f"spelled word {clip.text!r}").track
    elif kind in ("video", "frames"):
        from m3t.trackers.mediapipe_holistic import MediaPipeConfig

        track = _holistic(media, clip.fps, mediapipe_cfg or MediaPipeConfig())
    else:
        media_key(clip, root)  # raises the refusal with its reason
        raise AssertionError(kind)
    if not (track.confidence > 0).any():
        raise ClipRefused("no person detected", f"no person detected in any of the {track.num_frames} frames of "
                          f"{clip.media}; check that the media shows a signer (blank, tiny or cropped frames)")
    return track


class TrackingInputs(Protocol):
    """What tracking needs beyond a clip's media: the 2D trackers' settings and, for the simulated tracker, the
    body model (built on first use) and its cache key (:class:`m3t.fitting.context.FitContext` is one)."""

    @property
    def mediapipe(self) -> MediaPipeConfig: ...

    @property
    def simulated(self) -> SimulatedTrackerConfig: ...

    @property
    def body(self) -> BodyModel: ...

    @property
    def body_key(self) -> object: ...


def simulated_corpus(corpus: str) -> bool:
    """Whether a corpus' clips are ground-truth motion tracked by the simulated tracker: its runs are configured
    by params.yaml ``tracker`` (never by external tracker outputs) and pictured against the ground truth."""
    return corpus == SIMULATED_CORPUS


def track_key(clip: Clip, root: Path, inputs: TrackingInputs) -> tuple[object, ...]:
    """What a clip's track depends on, as the parts of its cache key: ``(media_key,)`` for real media; for
    ground-truth motion the motion file's bytes, the simulated tracker's settings and the body model's key, three
    parts rather than one list, because that is the address of every cached synthetic track."""
    if media_kind(clip) == "synthetic":
        media = root / clip.media
        if not media.exists():
            raise FileNotFoundError(f"media file {media} of clip {clip.id} is missing")
        return file_digest_bytes(media), inputs.simulated, inputs.body_key
    return (media_key(clip, root, inputs.mediapipe),)


def ground_truth(clip: Clip, root: Path) -> tuple[dict, object, Camera] | None:
    """(params per modality (T, D), identity (P,), camera) a clip's media holds when it is ground-truth motion
    (media kind ``synthetic``); None for every other media."""
    if media_kind(clip) != "synthetic":
        return None
    from m3t.corpora.synthetic_storage import SyntheticCorpus

    return SyntheticCorpus(root).ground_truth(clip)


def track_media(clip: Clip, root: Path, inputs: TrackingInputs) -> Track:
    """Track one listed clip by its media kind; raises (fit-corpus quarantines) when it cannot."""
    if media_kind(clip) != "synthetic":
        return track_real_clip(clip, root, inputs.mediapipe)
    import torch

    from m3t.body.protocol import as_tensors
    from m3t.trackers.simulated import simulate_track

    params, identity, camera = ground_truth(clip, root)
    return simulate_track(clip.id, as_tensors(params), torch.as_tensor(identity), camera, clip.fps, inputs.body,
                          inputs.simulated)
