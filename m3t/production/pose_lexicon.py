"""The ``lexicon`` baseline over a user's dictionary of ``.pose`` files in spoken-to-signed's layout: words looked
up, unknown words fingerspelled, the signs trimmed to their signing, put at one size and stitched, written as one
MediaPipe Holistic ``.pose`` file (no body model: the points themselves).

**Layout** (spoken-to-signed, ``gloss_to_pose/lookup/csv_lookup.py`` reads ``index.csv``; its shipped lexicon has
``data.csv``): a folder with a table of columns ``path, spoken_language, signed_language, start, end, words, glosses,
priority`` (times in ms; ``end`` 0 = to the file's end) and the ``.pose`` files it names, relative to the folder.
A real row of the lexicon shipped in the spoken-to-signed wheel:
``ase/fs-stse28e9ac023b0e29ca0a3acc12dc46540.pose,en,ase,0,2720,A,A,0``.

**Lookup** (as spoken-to-signed's word lookup, without its lemmatiser): the text's words (normalised: NFKC, lower
case, no punctuation) in order; a word is the entry of the signed language whose ``words`` equals it
(case-insensitively), the lowest ``priority`` first, then the first row. A word without an entry is fingerspelled
when the lexicon has letters (entries of one character, or multi-character letters of the installed
fingerspelling lexicon such as ``SCH``): greedy longest letter first, as spoken-to-signed's
``FingerspellingPoseLookup``; otherwise it is listed as missing. ``fingerspelling=installed`` falls back to the
letters shipped with spoken-to-signed for the signed language.

**Stitching** (the recipe of spoken-to-signed's ``concatenate.py``): each sign is cut to its row's times and
trimmed to its signing span (the frames where a wrist is above its elbow, 5 frames either side, within the frames
where the wrist is seen; the whole clip when a wrist never rises), centred on its mean shoulder midpoint and divided
by its mean shoulder width (pose-format's normalisation, per sign), then the signs are joined by ``transition_frames`` frames interpolated
linearly (:func:`m3t.production.lexicon.concatenate`); a point missing at either end of a transition stays missing.
Signs recorded at other rates are resampled to the first sign's rate as the fingerspelling corpus resamples its
letters (linear where both neighbouring frames see a point). A sign without both shoulders in any frame is refused
with its row.

Every path is resolved inside the folder (a row naming a file outside it is refused with its row number); a
malformed row names the table, the row and the column.

Axis legend: T frames, J holistic points, D coordinates.
"""
from __future__ import annotations

import csv
import io
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from m3t.atomic import write_bytes
from m3t.corpora.listing import CorpusError
from m3t.corpora.posefile import read_pose
from m3t.metrics.pose_eval import normalize_by_shoulders, signing_span
from m3t.production.lexicon import concatenate
from m3t.production.retrieval import normalise
from m3t.scoring.poses import holistic_array

TABLES = ("index.csv", "lexicon.csv", "data.csv")
COLUMNS = ("path", "spoken_language", "signed_language", "start", "end", "words", "glosses", "priority")
POSE_COUNT, HAND_COUNT, FACE_MESH = 33, 21, 468


class LexiconError(ValueError):
    """A lexicon folder or row that cannot be read; the message names the file, row and column."""


@dataclass(frozen=True)
class PoseEntry:
    row: int
    path: Path
    signed_language: str
    words: str
    start_ms: int
    end_ms: int
    priority: int


@dataclass
class PoseLexical:
    """A stitched sentence: (T, J, 3) points in shoulder-width units (NaN missing), the rate, the entries used and what was missing."""

    points: np.ndarray
    fps: float
    used: list[tuple[str, str]]  # (word or letter, file relative to the folder)
    fingerspelled: list[str]
    missing: list[str]

    @property
    def frames(self) -> int:
        return len(self.points)


class PoseLexicon:
    """A spoken-to-signed lexicon folder (module doc)."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder).resolve()
        table = next((self.folder / t for t in TABLES if (self.folder / t).is_file()), None)
        if table is None:
            raise LexiconError(f"{folder}: no lexicon table; spoken-to-signed's layout has one of {', '.join(TABLES)} "
                               f"with columns {', '.join(COLUMNS)}")
        self.table = table
        self.entries: list[PoseEntry] = []
        with open(table, newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            absent = [c for c in ("path", "signed_language", "words") if c not in (reader.fieldnames or ())]
            if absent:
                raise LexiconError(f"{table}: columns {absent} missing; spoken-to-signed's columns are "
                                   f"{', '.join(COLUMNS)}")
            for number, row in enumerate(reader, start=2):
                self.entries.append(self._entry(row, number))

    def _entry(self, row: dict, number: int) -> PoseEntry:
        where = f"{self.table}, row {number}"
        path = (self.folder / (row.get("path") or "")).resolve()
        if not path.is_relative_to(self.folder) or path == self.folder:
            raise LexiconError(f"{where}, column path: {row.get('path')!r} is not a file inside {self.folder}")
        values = {}
        for column in ("start", "end", "priority"):
            text = (row.get(column) or "0").strip() or "0"
            try:
                values[column] = int(float(text))
            except ValueError:
                raise LexiconError(f"{where}, column {column}: {text!r} is not a number") from None
            if values[column] < 0:
                raise LexiconError(f"{where}, column {column}: {text!r} is negative")
        return PoseEntry(number, path, (row.get("signed_language") or "").strip(), (row.get("words") or "").strip(),
                         values["start"], values["end"], values["priority"])

    def _index(self, signed_language: str) -> dict[str, PoseEntry]:
        ranked = sorted((e for e in self.entries if e.signed_language == signed_language and e.words),
                        key=lambda e: (e.priority, e.row))
        out: dict[str, PoseEntry] = {}
        for entry in ranked:
            out.setdefault(entry.words.lower(), entry)
        return out

    def lookup(self, text: str, signed_language: str, transition_frames: int = 6,
               fingerspelling: str = "own") -> PoseLexical:
        """The signs of ``text`` in ``signed_language`` stitched (module doc); ``fingerspelling``: ``own`` (the
        lexicon's letters), ``installed`` (spoken-to-signed's shipped letters when the lexicon has none) or
        ``off``."""
        index = self._index(signed_language)
        if not index:
            languages = sorted({e.signed_language for e in self.entries})
            raise LexiconError(f"{self.table}: no entry of signed language {signed_language!r}; it holds {languages}")
        letters = {w: e for w, e in index.items() if len(w) == 1} if fingerspelling != "off" else {}
        if not letters and fingerspelling == "installed":
            letters = _installed_letters(signed_language)
        pieces, used, spelled, missing = [], [], [], []
        for word in normalise(text).split():
            if word in index:
                pieces.append(index[word])
                used.append((word, str(index[word].path.relative_to(self.folder))))
                continue
            spelling = _spell(word, letters, signed_language)
            if spelling is None:
                missing.append(word)
                continue
            spelled.append(word)
            for letter in spelling:
                pieces.append(letters[letter])
                used.append((letter, letters[letter].path.name))
        if not pieces:
            raise LexiconError(f"no entry of {signed_language!r} for any word of {text!r} (missing: {missing})")
        first, fps = _sign(pieces[0], None)
        points = [first] + [_sign(entry, fps)[0] for entry in pieces[1:]]
        stitched = concatenate([{"points": p} for p in points], transition_frames)["points"]
        return PoseLexical(stitched.astype(np.float64), fps, used, spelled, missing)


def _spell(word: str, letters: dict[str, PoseEntry], signed_language: str) -> list[str] | None:
    """The fingerspelling corpus's greedy longest-letter-first spelling of ``word``
    (:func:`m3t.corpora.fingerspelling.split_letters`), None when a part has no letter."""
    from m3t.corpora.fingerspelling import split_letters

    if not letters:
        return None
    try:
        return split_letters(word, list(letters), signed_language)
    except CorpusError:
        return None


def _installed_letters(signed_language: str) -> dict[str, PoseEntry]:
    from m3t.corpora.fingerspelling import lexicon_root

    try:
        return {w: e for w, e in PoseLexicon(lexicon_root())._index(signed_language).items()}
    except LexiconError:
        return {}


def _sign(entry: PoseEntry, fps: float | None) -> tuple[np.ndarray, float]:
    """(T, J, 3) holistic points of one entry in shoulder widths (pose-format's normalisation,
    :func:`m3t.metrics.pose_eval.normalize_by_shoulders`), cut to its times, at ``fps`` (default: its own; the
    fingerspelling corpus's resampling, :func:`m3t.corpora.fingerspelling.resample`) and trimmed to its signing span
    (:func:`m3t.metrics.pose_eval.signing_span`, spoken-to-signed's rule), and its rate."""
    from m3t.corpora.fingerspelling import resample

    if not entry.path.is_file():
        raise LexiconError(f"row {entry.row}: {entry.path} not found")
    data = read_pose(entry.path)
    first = round(entry.start_ms * data.fps / 1000)
    last = round(entry.end_ms * data.fps / 1000) if entry.end_ms > 0 else len(data.points)
    data = resample(replace(data, points=data.points[first:last], confidence=data.confidence[first:last]),
                    fps or data.fps)
    if not len(data.points):
        raise LexiconError(f"row {entry.row}: {entry.path.name} has no frames between {entry.start_ms} and "
                           f"{entry.end_ms} ms")
    points = holistic_array(data, str(entry.path))
    if points.shape[-1] == 2:
        points = np.concatenate([points, np.zeros_like(points[..., :1])], axis=-1)
    face = points.shape[1] - POSE_COUNT - 2 * HAND_COUNT
    if face != FACE_MESH:  # the refined face's 10 iris points follow the mesh's 468: keep the mesh
        points = np.concatenate([points[:, :POSE_COUNT + FACE_MESH], points[:, POSE_COUNT + face:]], axis=1)
    missing = ~np.isfinite(points)
    start, end = signing_span(points, missing)
    try:
        return normalize_by_shoulders(points[start:end], missing[start:end], entry.path.name), float(data.fps)
    except ValueError as exc:
        raise LexiconError(f"row {entry.row}: {exc}") from exc


def write_holistic_pose(path: str | Path, points: np.ndarray, fps: float, width: int = 1024,
                        height: int = 1024) -> Path:
    """(T, 543, 3) points in shoulder-width units (pose, face mesh, hands; NaN missing) as a pose-format holistic
    ``.pose`` file, centred on a ``width`` x ``height`` canvas at a third of its width per shoulder width; world landmarks absent
    (confidence 0). Written atomically."""
    from pose_format import Pose
    from pose_format.numpy.pose_body import NumPyPoseBody
    from pose_format.pose_header import PoseHeader, PoseHeaderDimensions

    from m3t.render.posefile import holistic_components

    seen = np.isfinite(points).all(-1)
    canvas = np.where(seen[..., None], points * (width / 3) + np.array([width / 2, height / 2, 0.0]), 0.0)
    world = np.zeros((len(points), POSE_COUNT, 3))
    data = np.concatenate([canvas, world], axis=1)[:, None].astype(np.float32)
    conf = np.concatenate([seen, np.zeros((len(points), POSE_COUNT), bool)], axis=1)[:, None].astype(np.float32)
    pose = Pose(PoseHeader(0.2, PoseHeaderDimensions(width, height, 0), holistic_components()),
                NumPyPoseBody(fps=float(fps), data=data, confidence=conf))
    buffer = io.BytesIO()
    pose.write(buffer)
    write_bytes(Path(path), buffer.getvalue())
    return Path(path)
