"""Real media of a listed clip -> Track, chosen by the clip's ``media_kind``, and the content key of that media.

fit-corpus calls :func:`media_key` to address a clip's track in its cache (the media's content and the tracker
settings, never only its path) and :func:`track_real_clip` on a cache miss. Synthetic clips are tracked by the
stage itself (the simulated tracker needs the body model and the ground truth).

=================  =====================================================================================
media kind         tracking
=================  =====================================================================================
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

from m3t.corpora.clip import Clip
from m3t.digest import file_digest
from m3t.trackers.track import Track

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
    if kind is None and clip.corpus == "synthetic":
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

