"""What every real-corpus adapter shares: the listing records, the errors, media checks, splits, safe pickles, registry.

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

import codecs
import dataclasses
import gzip
import hashlib
import importlib
import os
import pickle
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any, ClassVar

from m3t.body.model_files import SafeModelUnpickler
from m3t.corpora.clip import Clip
from m3t.dataclass_io import build_dataclass

Check = Callable[[Path], "str | None"]  # media path -> quarantine reason, None when fine
MEDIA_KINDS = ("video", "frames", "pose", "smplx_params", "flame_params", "keypoints", "spelled", "synthetic")
SPLITS = ("train", "dev", "test")
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
        problem = check(self.root / clip.media) if check is not None else None
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


# ----------------------------------------------------------------------------------------- text files
def read_lines(path: Path, hint: str) -> list[str]:
    """Lines of a UTF-8 text file (BOM tolerated); ``CorpusError`` with ``hint`` when missing or undecodable.

    Lines end at ``\\n`` only (a ``\\r`` before it is dropped): ``str.splitlines`` would also split at U+2028 or
    U+0085 inside a sentence and shift every later row number. The error for undecodable bytes names the 1-based
    line and the file's byte offset of the first bad byte, so a single Latin-1 row can be found and fixed.
    """
    if not path.is_file():
        raise CorpusError(f"{path} not found. {hint}")
    data = path.read_bytes()
    start = len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0
    try:
        lines = data[start:].decode("utf-8").split("\n")
        if lines[-1] == "":
            lines.pop()  # the final newline ends the last row; it does not start another
        return [line[:-1] if line.endswith("\r") else line for line in lines]
    except UnicodeDecodeError as exc:
        offset = start + exc.start
        line = data[:offset].count(b"\n") + 1
        raise CorpusError(f"{path} line {line} (byte {offset}): not UTF-8 text ({exc.reason}: "
                          f"{data[offset:offset + 4]!r}); re-save the file as UTF-8. {hint}") from exc


def check_header(path: Path, lines: list[str], expected: str, hint: str) -> None:
    """Raise ``CorpusError`` unless line 1 is exactly ``expected`` (trailing whitespace ignored)."""
    found = lines[0].rstrip() if lines else "<empty file>"
    if found != expected:
        raise CorpusError(f"{path} line 1: header is {found!r}; expected exactly {expected!r}. {hint}")


def find_file(name: str, places: list[Path], hint: str) -> Path:
    """The first ``place / name`` that exists; ``CorpusError`` listing every place looked in otherwise."""
    for place in places:
        if (place / name).is_file():
            return place / name
    looked = ", ".join(str(p / name) for p in places)
    raise CorpusError(f"{name} not found (looked in {looked}). {hint}")


# ----------------------------------------------------------------------------------------- splits
def hash_unit(key: str, salt: str = "") -> float:
    """A deterministic number in [0, 1) from ``key`` (same on every machine and Python run)."""
    digest = hashlib.blake2b(f"{salt}\x00{key}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big") / 2.0 ** 64


def check_fractions(fractions: tuple[float, float, float], option: str) -> None:
    if len(fractions) != 3 or min(fractions) < 0 or abs(sum(fractions) - 1.0) > 1e-6:
        raise ValueError(f"option {option}: expected three non-negative train/dev/test fractions summing to 1, "
                         f"got {fractions}")


def hash_split(key: str, fractions: tuple[float, float, float] = (0.8, 0.1, 0.1), salt: str = "") -> str:
    """Deterministic train / dev / test assignment of ``key`` with the given fractions."""
    u = hash_unit(key, salt)
    if u < fractions[0]:
        return "train"
    return "dev" if u < fractions[0] + fractions[1] else "test"


# ----------------------------------------------------------------------------------------- safe pickles
TORCH_HINT = ("torch tensors are refused because unpickling them runs torch's own loading code; convert the "
              "file once where you trust it: load it, replace every tensor by tensor.numpy(), pickle it again.")


class _Refused(pickle.UnpicklingError):
    def __init__(self, module: str, name: str):
        super().__init__(f"{module}.{name}")
        self.qualname = f"{module}.{name}"


class CorpusUnpickler(SafeModelUnpickler):
    """The body-model allow-list narrowed to data: builtin containers and (optionally) numpy arrays.

    :class:`~m3t.body.model_files.SafeModelUnpickler` also maps chumpy / scipy classes to inert records; corpus
    files never hold those, so they are refused here, as are torch classes and, for ``allow_numpy=False``,
    numpy itself.
    """

    allow_numpy = True

    def find_class(self, module: str, name: str) -> Any:
        top = module.split(".")[0]
        if top in ("chumpy", "scipy", "torch") or (top == "numpy" and not self.allow_numpy):
            raise _Refused(module, name)
        try:
            return super().find_class(module, name)
        except pickle.UnpicklingError:
            raise _Refused(module, name) from None


def load_data_pickle(path: Path, allow_numpy: bool, compressed: bool = False) -> Any:
    """Unpickle a corpus file with :class:`CorpusUnpickler`; ``CorpusError`` for refused classes or bad bytes."""
    if not path.is_file():
        raise CorpusError(f"{path} not found; check the corpus root and the adapter's file options")
    allowed = "builtin containers, numbers, strings" + (" and numpy arrays" if allow_numpy else "")
    try:
        with (gzip.open(path, "rb") if compressed else open(path, "rb")) as fh:
            unpickler = CorpusUnpickler(fh, encoding="latin1" if allow_numpy else "utf-8")
            unpickler.allow_numpy = allow_numpy
            return unpickler.load()
    except _Refused as exc:
        hint = TORCH_HINT if exc.qualname.startswith("torch") else f"Re-save it holding only {allowed}."
        raise CorpusError(f"{path}: the pickle references {exc.qualname}, a non-data class, and was refused "
                          f"(nothing was run). Allowed: {allowed}. {hint}") from exc
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, OSError) as exc:
        raise CorpusError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc}); re-export the file") from exc


# ----------------------------------------------------------------------------------------- adapters
class CorpusAdapter:
    """Base of every adapter: ``listing()`` does the work, ``clips()`` keeps only the listed clips."""

    name: ClassVar[str] = ""
    config_type: ClassVar[type] = type(None)

    def __init__(self, root: str | Path, config: Any = None):
        self.root = Path(root)
        self.config = config if config is not None else self.config_type()

    def listing(self) -> Listing:
        raise NotImplementedError

    def clips(self) -> tuple[Clip, ...]:
        return self.listing().clips


@dataclass(frozen=True)
class SyntheticOptions:
    """The synthetic corpus is configured where it is generated (``corpus`` in params.yaml); nothing here."""


class SyntheticAdapter(CorpusAdapter):
    """The embedded synthetic corpus behind the adapter interface (media = ground-truth motion ``.npz``)."""

    name = "synthetic"
    config_type = SyntheticOptions

    def listing(self) -> Listing:
        from m3t.corpora.synthetic import SyntheticCorpus

        clips = tuple(dataclasses.replace(c, extra=with_kind("synthetic") + c.extra)
                      for c in SyntheticCorpus(self.root).clips())
        return Listing(clips, ())


_ADAPTERS = {
    "synthetic": "m3t.corpora.base:SyntheticAdapter",
    "phoenix14t": "m3t.corpora.phoenix14t:Phoenix14TCorpus",
    "how2sign": "m3t.corpora.how2sign:How2SignCorpus",
    "csl_daily": "m3t.corpora.csl_daily:CslDailyCorpus",
    "nmfs_csl": "m3t.corpora.nmfs_csl:NmfsCslCorpus",
    "mead": "m3t.corpora.mead:MeadCorpus",
    "soke_smplx": "m3t.corpora.fitted_pickles:SokeSmplxCorpus",
    "slt_pickle": "m3t.corpora.fitted_pickles:SltPickleCorpus",
    "posefile": "m3t.corpora.posefile:PoseFileCorpus",
    "fingerspelling": "m3t.corpora.fingerspelling:FingerspellingCorpus",
}
CORPORA: tuple[str, ...] = tuple(_ADAPTERS)


@dataclass(frozen=True)
class CorpusSource:
    """Where one corpus lives (params.yaml ``corpora.<name>``). ``root`` "" = the adapter's default (the
    fingerspelling lexicon inside its installed package); ``options`` = the adapter's option dataclass fields.
    Its shards go to ``data.shards_root/<name>`` (:class:`m3t.shards.folders.DataConfig`)."""

    root: str = ""
    options: dict[str, Any] = dataclasses.field(default_factory=dict)


def adapter_class(name: str) -> type[CorpusAdapter]:
    if name not in _ADAPTERS:
        raise ValueError(f"corpus {name!r} unknown; expected one of {', '.join(CORPORA)}")
    module, cls = _ADAPTERS[name].split(":")
    return getattr(importlib.import_module(module), cls)  # imported on demand: adapters import this module


def open_corpus(name: str, root: str | Path | None, **options: Any) -> CorpusAdapter:
    """The adapter for corpus ``name`` at ``root``; ``options`` are the fields of its option dataclass.

    Options are type-checked (lists from YAML become tuples where the option is a tuple); unknown or wrongly
    typed options raise ``ValueError`` naming the allowed ones or the option.
    """
    cls = adapter_class(name)
    fields = {f.name: f for f in dataclasses.fields(cls.config_type)}
    unknown = sorted(set(options) - set(fields))
    if unknown:
        raise ValueError(f"corpora.{name}: unknown options {unknown}; allowed: {', '.join(fields) or 'none'}")
    return cls(root if root is not None else "", build_dataclass(cls.config_type, options, f"corpora.{name}.options"))
