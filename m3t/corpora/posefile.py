"""Collections of ``.pose`` files (the pose-format library) as keypoint clips; the project's one ``.pose`` reader.

Listing reads headers only (:func:`read_pose_info`: fps, frame count, components) and checks that the file is
as long as its header says, so a truncated file is quarantined without decoding its frames. Clips come from an
optional index CSV (columns ``id,path,split,text,language,signer`` and optional ``label``; ``path`` relative to
the root) or, without one, one clip per ``*.pose`` under the root with a deterministic hash split. A ``path`` that
is absolute, has a ``..`` component or leaves the root through a symbolic link is quarantined before the file is
opened (:func:`m3t.corpora.listing.media_path_problem`).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from m3t.corpora.annotation_files import csv_rows, integer_field, read_lines
from m3t.corpora.base import CorpusAdapter
from m3t.corpora.clip import Clip
from m3t.corpora.listing import Collector, CorpusError, Listing, with_kind
from m3t.corpora.splits import SPLITS, check_fractions, hash_split

INDEX_COLUMNS = ("id", "path", "split", "text", "language", "signer")
# ZeroDivisionError: pose-format's v0.1 reader divides by the people count its body declares
READ_ERRORS = (struct.error, ValueError, TypeError, EOFError, IndexError, NotImplementedError, UnicodeDecodeError,
               ZeroDivisionError)


@dataclass(frozen=True)
class PoseInfo:
    """What a ``.pose`` header says; ``components`` = ((name, n_points), ...) in point order."""

    fps: float
    frames: int
    people: int
    components: tuple[tuple[str, int], ...]
    width: int
    height: int
    version: float


@dataclass(frozen=True)
class PoseData:
    """One person of a ``.pose`` file; the form every ``.pose`` consumer (listing, spelling, tracks) reads.

    points (T, K, 3) float32 in the file's units (z = 0 for 2D files, see ``dims``); confidence (T, K) float32,
    0 where pose-format masked the point; ``components`` = ((name, n_points), ...) in point order and
    ``point_names`` the names of each component's points (what tracks match landmarks by).
    """

    points: np.ndarray
    confidence: np.ndarray
    fps: float
    components: tuple[tuple[str, int], ...]
    width: int
    height: int
    point_names: tuple[tuple[str, ...], ...] = ()
    dims: int = 3  # coordinates the file stores (2 or 3)


def _header(path: Path, chunk: int = 1 << 16):
    """(PoseHeader, reader positioned after it): the first ``chunk`` bytes, grown until the header fits."""
    from pose_format.pose_header import PoseHeader
    from pose_format.utils.reader import BufferReader

    size = path.stat().st_size
    with open(path, "rb") as fh:
        while True:
            fh.seek(0)
            buffer = fh.read(chunk)
            try:
                reader = BufferReader(buffer)
                header = PoseHeader.read(reader)
                if len(buffer) >= reader.read_offset + 10 or chunk >= size:  # 10: fps, frames, people of v0.2
                    return header, reader
            except struct.error:
                if chunk >= size:
                    raise
            chunk *= 4


MAX_FPS = 1000.0  # a camera's frame rate; a header above it (or 0, negative, NaN) was not written by a recorder


def checked_fps(fps: float, source: str) -> float:
    """The header's frame rate, refused unless finite and in (0, :data:`MAX_FPS`]: every duration, resampling
    and DTW window derives from it."""
    fps = float(fps)
    if not (0.0 < fps <= MAX_FPS):  # also false for NaN
        raise CorpusError(f"{source}: the header's frame rate is {fps}, not a camera's (0 < fps <= {MAX_FPS:g}); "
                          "re-export the file with its real fps")
    return fps


def checked_header(header, source: str):
    """The header, refused unless it declares components with points of 2 or 3 coordinates (``XYC`` / ``XYZC``):
    pose-format sizes the body from them, and a header without points or coordinates fails there with a division
    by zero or a reshape that names no file."""
    components = list(header.components)
    if not components or not sum(len(c.points) for c in components):
        raise CorpusError(f"{source}: the header declares no points; re-export the file")
    formats = sorted({c.format for c in components})
    if not 2 <= header.num_dims() <= 3 or any(len(f) - 1 != header.num_dims() for f in formats):
        raise CorpusError(f"{source}: the header's point formats {formats} are not XYC or XYZC (2 or 3 coordinates "
                          "and a confidence, the same in every component); re-export the file")
    return header


def read_pose_info(path: str | Path) -> PoseInfo:
    """Header-only read of a ``.pose`` file; ``CorpusError`` naming the file when unreadable or truncated."""
    path = Path(path)
    if not path.is_file():
        raise CorpusError(f"{path} not found")
    try:
        header, reader = _header(path)
        checked_header(header, str(path))
        components = tuple((c.name, len(c.points)) for c in header.components)
        if round(header.version, 3) != 0.2:  # older layouts store no frame count: decode the body to learn it
            data = read_pose(path)
            return PoseInfo(data.fps, data.points.shape[0], 1, components, header.dimensions.width,
                            header.dimensions.height, header.version)
        fps, frames, people = struct.unpack_from("<fIH", reader.buffer, reader.read_offset)
        points, dims = sum(n for _, n in components), header.num_dims()
        expected = reader.read_offset + 10 + 4 * frames * people * points * (dims + 1)  # data + confidence, float32
    except CorpusError:
        raise
    except (*READ_ERRORS, OSError) as exc:
        raise CorpusError(f"{path}: unreadable .pose header, truncated or not a .pose file "
                          f"({type(exc).__name__}: {exc})") from exc
    if people == 0:
        raise CorpusError(f"{path}: the header declares no person; re-export the file")
    checked_fps(fps, str(path))
    actual = path.stat().st_size
    if actual < expected:
        raise CorpusError(f"{path}: truncated .pose file ({actual} bytes, the header promises {expected}: {frames} "
                          f"frames x {people} people x {points} points); re-export it")
    return PoseInfo(float(fps), int(frames), int(people), components, header.dimensions.width,
                    header.dimensions.height, header.version)


def pose_data(pose, source: str = "<pose>", person: int = 0) -> PoseData:
    """A decoded ``pose_format.Pose`` -> :class:`PoseData` of one person. Masked points get confidence 0.

    Parameters
    ----------
    pose : pose_format.Pose; body data (T, P, K, D) with D = 2 or 3, confidence (T, P, K)
    source : the file name, for error messages
    person : which person of the P axis to take
    """
    data, conf = pose.body.data, pose.body.confidence  # (T, P, K, D), (T, P, K)
    if data.ndim != 4 or data.shape[0] == 0 or data.shape[1] == 0:
        raise CorpusError(f"{source}: no frames or no person in the pose body (shape {data.shape})")
    if not 0 <= person < data.shape[1]:
        raise CorpusError(f"{source} has {data.shape[1]} person(s); person={person} does not exist")
    points = np.ma.getdata(data)[:, person].astype(np.float32)  # (T, K, D)
    confidence = np.asarray(conf, dtype=np.float32)[:, person]  # (T, K)
    mask = np.ma.getmaskarray(data)[:, person].any(-1)
    confidence = np.where(mask, 0.0, confidence).astype(np.float32)
    dims = int(points.shape[-1])
    if dims < 3:  # 2D files: z = 0 so every reader sees (T, K, 3)
        points = np.concatenate([points, np.zeros((*points.shape[:2], 3 - dims), np.float32)], -1)
    header = pose.header
    return PoseData(points[..., :3], confidence, checked_fps(pose.body.fps, source),
                    tuple((c.name, len(c.points)) for c in header.components),
                    int(header.dimensions.width), int(header.dimensions.height),
                    tuple(tuple(str(p) for p in c.points) for c in header.components), min(dims, 3))


def read_pose(path: str | Path, person: int = 0) -> PoseData:
    """Decode a ``.pose`` file (one person); ``CorpusError`` naming the file when missing or unreadable."""
    from pose_format import Pose

    path = Path(path)
    if not path.is_file():
        raise CorpusError(f"{path} does not exist; check the corpus root")
    try:
        checked_header(_header(path)[0], str(path))  # the body is sized from it; the body's reads are bounded
        pose = Pose.read(path.read_bytes())
    except CorpusError:
        raise
    except OSError as exc:
        raise CorpusError(f"{path}: cannot read ({exc})") from exc
    except (*READ_ERRORS, AssertionError, KeyError) as exc:
        raise CorpusError(f"{path}: unreadable or truncated .pose file ({type(exc).__name__}: {exc}); "
                          "re-export it") from exc
    return pose_data(pose, str(path), person)


def component_offsets(data: PoseData) -> dict[str, tuple[int, tuple[str, ...]]] | None:
    """Component name -> (index of its first point on the data's point axis, its point names), in file order; None
    when the data carry no point names (read them with :func:`read_pose` / :func:`pose_data`)."""
    if len(data.point_names) != len(data.components):
        return None
    offsets, start = {}, 0
    for (name, _), names in zip(data.components, data.point_names):
        offsets[name] = (start, tuple(names))
        start += len(names)
    return offsets


def matched_points(offsets: dict[str, tuple[int, tuple[str, ...]]], component: str, names: tuple[str, ...],
                   first_target: int) -> tuple[list[int], list[int]]:
    """(point indices in the data, indices in a target layout whose ``component`` points are ``names`` from
    ``first_target`` on) of the points of ``component`` the target names; ([], []) when the data lack it."""
    if component not in offsets:
        return [], []
    first, points = offsets[component]
    position = {name: i for i, name in enumerate(names)}
    pairs = [(first + i, first_target + position[p]) for i, p in enumerate(points) if p in position]
    return [a for a, _ in pairs], [b for _, b in pairs]


def components_text(components: tuple[tuple[str, int], ...]) -> str:
    return ",".join(f"{name}:{n}" for name, n in components)


@dataclass(frozen=True)
class PoseFileConfig:
    """Options (params.yaml ``corpora.posefile``)."""

    index: str = ""  # CSV relative to the root; empty = every *.pose under the root
    language: str = "unknown"  # without an index
    split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)  # without an index

    def __post_init__(self) -> None:
        check_fractions(self.split_fractions, "corpora.posefile.split_fractions")


class PoseFileCorpus(CorpusAdapter):
    """Lists a ``.pose`` collection (media kind ``pose``); fps comes from each file's header."""

    name = "posefile"
    config_type = PoseFileConfig

    def _rows(self, out: Collector) -> list[tuple[Path, int | None, dict[str, str]]]:
        cfg = self.config
        if not cfg.index:
            files = sorted(self.root.rglob("*.pose"))
            if not files:
                raise CorpusError(f"no .pose files under {self.root}; check the root or set corpora.posefile.index")
            rows = []
            for f in files:
                rel = PurePosixPath(f.relative_to(self.root).as_posix())
                clip_id = rel.with_suffix("").as_posix().replace("/", "__")
                rows.append((f, None, {"id": clip_id, "path": rel.as_posix(), "language": cfg.language,
                                       "split": hash_split(clip_id, cfg.split_fractions, salt="posefile")}))
            return rows
        path = self.root / cfg.index
        lines = read_lines(path, "Set corpora.posefile.index to the index CSV (relative to the root).")
        header, records = csv_rows(lines, path, f"{','.join(INDEX_COLUMNS)} and optional label", out)
        missing = [c for c in INDEX_COLUMNS if c not in header]
        if missing:
            raise CorpusError(f"{path} line 1: columns {list(header)} lack {missing}; expected "
                              f"{','.join(INDEX_COLUMNS)} and optional label")
        rows = []
        for row, record in records:
            if None in record or any(record.get(c) is None for c in INDEX_COLUMNS):
                out.quarantine(path, row, record.get("id") or None, "malformed row: wrong number of columns")
                continue
            rows.append((path, row, {k: (v or "").strip() for k, v in record.items()}))
        return rows

    def listing(self) -> Listing:
        out = Collector(self.root)
        for file, row, r in self._rows(out):
            clip_id = r["id"]
            if not clip_id or not r["path"]:
                out.quarantine(file, row, clip_id or None, "empty id or path")
                continue
            if r["split"] not in SPLITS:
                out.quarantine(file, row, clip_id, f"split {r['split']!r} unknown; expected one of {', '.join(SPLITS)}")
                continue
            label = r.get("label") or None
            if label is not None and integer_field(label) is None:
                out.quarantine(file, row, clip_id, f"label {label!r} is not an integer")
                continue
            unsafe = out.media_problem(r["path"])
            if unsafe is not None:  # before the header is read: never parse a file outside the collection
                out.quarantine(file, row, clip_id, unsafe)
                continue
            media = self.root / r["path"]
            try:
                if not media.is_file():
                    out.quarantine(file, row, clip_id, f"missing media: {r['path']}")
                    continue
                info = read_pose_info(media)
            except OSError as exc:  # a name the file system refuses (longer than it allows)
                out.quarantine(file, row, clip_id, f"unreadable media path ({exc.strerror or exc})")
                continue
            except CorpusError as exc:
                out.quarantine(file, row, clip_id, str(exc).replace(str(media), r["path"]))
                continue
            clip = Clip(id=clip_id, corpus=self.name, split=r["split"], language=r.get("language") or "unknown",
                        signer=r.get("signer") or "unknown", text=r.get("text", ""), gloss=r.get("gloss", ""),
                        media=r["path"], fps=info.fps, label=None if label is None else int(label),
                        extra=with_kind("pose", frames=info.frames, people=info.people,
                                        components=components_text(info.components)))
            out.add(clip, file, row)
        return out.listing()
