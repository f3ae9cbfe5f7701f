"""What an adapter's listing is made of: the records, the errors, the row collector and the media checks.

An adapter turns a corpus root in its documented layout into a :class:`Listing`: the clips it could list and,
for every row it could not, a :class:`Quarantined` record naming the file, the row and the reason. A whole file
that is unusable (missing, wrong header, refused pickle) raises :class:`CorpusError` instead. Listing never
decodes media; it only checks that each clip's media path exists.

Annotation files come from elsewhere, so a media path read from one is never trusted: :func:`media_path_problem`
refuses absolute paths, ``..`` components and paths that leave the corpus root through a symbolic link, and
:meth:`Collector.add` applies it to every clip of every adapter before anything under that path is touched.

Each clip carries ``("media_kind", kind)`` in ``Clip.extra`` so the tracking stage can dispatch on it; see
:data:`MEDIA_KINDS`.
"""
from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

from m3t.corpora.clip import Clip

Check = Callable[[Path], "str | None"]  # media path -> quarantine reason, None when fine
MEDIA_KINDS = ("video", "frames", "pose", "smplx_params", "flame_params", "keypoints", "spelled", "synthetic")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


class CorpusError(ValueError):
    """A corpus file that is unusable as a whole; the message names the file, what was expected and what to do."""


@dataclass(frozen=True)
class Quarantined:
    """A row that could not be listed. ``row``: 1-based line number (header = line 1) or 0-based list index."""

    file: str
    row: int | None
    clip_id: str | None
    reason: str


@dataclass(frozen=True)
class Listing:
    clips: tuple[Clip, ...]
    quarantined: tuple[Quarantined, ...]


# ----------------------------------------------------------------------------------------- collecting rows
class Collector:
    """Accumulates clips and quarantine records of one listing; refuses unsafe media paths, duplicate ids, media
    listed twice (where the corpus lists each video once) and missing media."""

    def __init__(self, root: Path):
        self.root = root
        self.clips: list[Clip] = []
        self.quarantined: list[Quarantined] = []
        self._seen: dict[str, str] = {}
        self._media: dict[str, str] = {}  # media -> "clip <id> (<file> row <n>)", for unique_media
        self._resolved_root: Path | None = None

    def media_problem(self, media: str) -> str | None:
        """:func:`media_path_problem` under this listing's root (resolved once per listing)."""
        if self._resolved_root is None:
            self._resolved_root = self.root.resolve()
        return media_path_problem(self.root, media, self._resolved_root)

    def rel(self, path: Path) -> str:
        """``path`` relative to the root when inside it (portable in reports), else as given."""
        try:
            return path.relative_to(self.root).as_posix()
        except ValueError:
            return str(path)

    def quarantine(self, file: Path | str, row: int | None, clip_id: str | None, reason: str) -> None:
        self.quarantined.append(Quarantined(self.rel(Path(file)), row, clip_id, reason))

    def add(self, clip: Clip, file: Path | str, row: int | None, check: Check | None = None,
            unique_media: bool = False) -> bool:
        """Keep ``clip`` unless (in this order) its media path is unsafe (:func:`media_path_problem`), its id
        repeats, ``unique_media`` is set and an earlier clip has the same media, or ``check(root / media)`` names a
        problem; otherwise quarantine it with the reason. Returns whether the clip was kept."""
        where = f"{self.rel(Path(file))} row {row}"
        unsafe = self.media_problem(clip.media)
        if unsafe is not None:
            self.quarantine(file, row, clip.id, unsafe)
            return False
        if clip.id in self._seen:
            self.quarantine(file, row, clip.id, f"duplicate clip id (first listed at {self._seen[clip.id]})")
            return False
        media_key = PurePosixPath(clip.media).as_posix()
        if unique_media and media_key in self._media:
            self.quarantine(file, row, clip.id, f"duplicate media: {clip.media} is already the media of "
                                                f"{self._media[media_key]}; listed once, under the first name")
            return False
        try:
            problem = check(self.root / clip.media) if check is not None else None
        except OSError as exc:  # a name the file system refuses (longer than it allows), an unreadable folder
            problem = f"unreadable media path ({exc.strerror or type(exc).__name__})"
        if problem is not None:
            self.quarantine(file, row, clip.id, f"{problem}: {clip.media}")
            return False
        self._seen[clip.id] = where
        if unique_media:
            self._media[media_key] = f"clip {clip.id} ({where})"
        self.clips.append(clip)
        return True

    def listing(self) -> Listing:
        return Listing(tuple(self.clips), tuple(self.quarantined))


def media_path_problem(root: Path, media: str, resolved_root: Path | None = None) -> str | None:
    """Why the annotation path ``media`` (meant relative to the corpus ``root``) must not be used; ``None`` when
    it names a place inside ``root``.

    Refused: an empty path; an absolute one (``/etc/passwd``, ``C:\\x``, ``\\\\server\\x``); one with a ``..``
    component (``/`` or ``\\`` separated); one that resolves outside the resolved root once symbolic links are
    followed. Only names are inspected and links resolved: nothing under ``media`` is opened. The reason starts
    with ``unsafe media path:`` so reports group these rows together. ``resolved_root``: ``root.resolve()`` when
    the caller already has it (a listing checks thousands of rows against one root).
    """
    text = str(media)
    if not text.strip():
        return "unsafe media path: empty path"
    if PurePosixPath(text).is_absolute() or PureWindowsPath(text).anchor:
        return f"unsafe media path: {text!r} is absolute; annotation paths must be relative to the corpus root"
    if ".." in PurePosixPath(text).parts or ".." in PureWindowsPath(text).parts:
        return f"unsafe media path: {text!r} has a '..' component, which could leave the corpus root"
    try:
        base = resolved_root if resolved_root is not None else root.resolve()
        target = (base / text).resolve()
    except (OSError, ValueError, RuntimeError) as exc:  # NUL bytes, symlink loops
        return f"unsafe media path: {text!r} cannot be resolved ({type(exc).__name__}: {exc})"
    if not target.is_relative_to(base):
        return (f"unsafe media path: {text!r} resolves outside the corpus root (to {target}) through a symbolic "
                "link; move the media under the root, or point the root at a folder that holds it")
    return None


def media_file(path: Path) -> str | None:
    """``None`` when ``path`` is an existing file, else the quarantine reason."""
    return None if path.is_file() else "missing media"


def media_folder(suffixes: tuple[str, ...] = IMAGE_SUFFIXES) -> Check:
    """A check for a frame folder: it must exist and hold at least one file ending in one of ``suffixes``."""

    def check(path: Path) -> str | None:
        if not path.is_dir():
            return "missing media"
        with os.scandir(path) as entries:  # stops at the first frame: no full listing of big folders
            if any(e.is_file() and e.name.lower().endswith(suffixes) for e in entries):
                return None
        return f"empty frame folder (no {'/'.join(suffixes)} files)"

    return check


def with_kind(kind: str, /, **more: Any) -> tuple[tuple[str, str], ...]:
    """``Clip.extra`` with the media kind first and ``more`` as strings (``None`` values left out)."""
    if kind not in MEDIA_KINDS:
        raise ValueError(f"media kind {kind!r} unknown; expected one of {', '.join(MEDIA_KINDS)}")
    return (("media_kind", kind),) + tuple((k, str(v)) for k, v in more.items() if v is not None)
