"""The outputs of the paper's 3D trackers (M3T App. 0.C) beside a clip's media: NLF (body), WiLoR (hands),
Pixel3DMM (face). Each has its reader (:mod:`m3t.trackers.nlf_reader`, :mod:`m3t.trackers.wilor_reader`,
:mod:`m3t.trackers.pixel3dmm_reader`), returning per-frame estimates in the tracker's own conventions (SMPL-X /
MANO / FLAME), loaded without executing code (:mod:`m3t.trackers.tracker_files`); :mod:`m3t.fitting.fusion`
turns them into one SMPL-FX initialisation. This module finds them.

**Layout beside the media.** The outputs of one clip sit next to its media ``M`` (a video file, a
``.pose`` file or a folder of frames), named after ``M`` with its last suffix replaced (a folder's
whole name is kept)::

    clips/abc.mp4                 the media (or clips/abc.pose, or the frame folder clips/abc/)
    clips/abc.nlf.npz             NLF, or clips/abc.nlf.pt
    clips/abc.wilor.npz           WiLoR, or clips/abc.wilor.pt
    clips/abc.pixel3dmm/          Pixel3DMM's output folder of the clip, as its tracker writes it:
        checkpoint/00000.frame    one file per frame (``*.frame`` directly in abc.pixel3dmm/ also works);
        ...                       meshes, renders and other files there are not read

Frame indices (NLF ``frame_index`` or row order, WiLoR ``frame_index``, Pixel3DMM ``frame_id``) count the
media's frames from 0, as the 2D tracker reads them. :func:`find_tracker_outputs` looks only there: an
output that is (or holds) a link leaving the media's folder is refused, and so are two files for one
tracker. :meth:`TrackerOutputs.digest` summarises the bytes the readers will read, for cache keys.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from m3t.digest import chunks_digest, file_digest
from m3t.trackers.pixel3dmm_reader import frames_folder
from m3t.trackers.tracker_files import TrackerFileError

TRACKERS = ("nlf", "wilor", "pixel3dmm")  # the paper's body, hand and face trackers, in that order
FILE_SUFFIXES = {"nlf": (".nlf.npz", ".nlf.pt"), "wilor": (".wilor.npz", ".wilor.pt")}
PIXEL3DMM_SUFFIX = ".pixel3dmm"


@dataclass(frozen=True)
class TrackerOutputs:
    """The external tracker outputs found beside one clip's media; None where a tracker left none.
    ``pixel3dmm`` is the folder that holds the ``*.frame`` files."""

    nlf: Path | None = None
    wilor: Path | None = None
    pixel3dmm: Path | None = None

    def names(self) -> tuple[str, ...]:
        """The trackers present, in :data:`TRACKERS` order."""
        return tuple(name for name in TRACKERS if getattr(self, name) is not None)

    def any(self) -> bool:
        return bool(self.names())

    def files(self) -> dict[str, list[Path]]:
        """Tracker -> the files its reader reads (Pixel3DMM: the ``*.frame`` files in name order)."""
        out = {}
        for name in self.names():
            path = getattr(self, name)
            out[name] = [f for f in sorted(path.glob("*.frame")) if f.is_file()] if name == "pixel3dmm" else [path]
        return out

    def digest(self) -> str:
        """SHA-256 (hex) over each present tracker's name and the names and bytes of the files its reader
        reads, so a changed, added or removed output changes it; ``"none"`` when no output is present.
        Files in the Pixel3DMM folder that are not read (meshes, renders) do not count."""
        if not self.any():
            return "none"
        chunks = [b"m3t tracker outputs v1"]
        for name, files in self.files().items():
            chunks.append(f"\0{name}\0{len(files)}".encode())
            for f in files:
                if not f.is_file():
                    raise TrackerFileError(f"{name} output {f} does not exist (a broken link?)")
                chunks.append(f"\0{f.name}\0{file_digest(f)}".encode())
        return chunks_digest(chunks)


def _inside(path: Path, folder: Path) -> bool:
    return path.resolve().is_relative_to(folder)


def _present(path: Path) -> bool:
    return path.exists() or path.is_symlink()


def find_tracker_outputs(media: str | Path) -> TrackerOutputs:
    """The NLF / WiLoR / Pixel3DMM outputs beside a clip's media (layout in the module docstring).

    Only the media's own folder is looked at. Raises :class:`TrackerFileError` for an output that is, or
    holds, a link leaving that folder, and for two files of one tracker (``abc.nlf.npz`` and ``abc.nlf.pt``).
    """
    media = Path(media).absolute()
    folder = media.parent
    base = folder.resolve()
    stem = media.name if media.is_dir() else media.stem

    def checked(path: Path, tracker: str) -> Path:
        if not _inside(path, base):
            raise TrackerFileError(f"{tracker} output {path} leads outside the clip's folder {folder} (to "
                                   f"{path.resolve()}); tracker outputs are read only beside the media: copy them there")
        return path

    found: dict[str, Path] = {}
    for tracker, suffixes in FILE_SUFFIXES.items():
        hits = [folder / f"{stem}{s}" for s in suffixes if _present(folder / f"{stem}{s}")]
        if len(hits) > 1:
            raise TrackerFileError(f"two {tracker} outputs for {media.name}: {', '.join(p.name for p in hits)}; keep one")
        if hits:
            found[tracker] = checked(hits[0], tracker)
    p3 = folder / f"{stem}{PIXEL3DMM_SUFFIX}"
    if _present(p3):
        checked(p3, "pixel3dmm")
        frames = checked(frames_folder(p3), "pixel3dmm")
        for f in frames.glob("*.frame"):
            checked(f, "pixel3dmm")
        found["pixel3dmm"] = frames
    return TrackerOutputs(**found)
