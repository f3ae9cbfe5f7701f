"""The malformed-input table: one case per broken input of every adapter and reader, and how each must end.

A case builds a small tree (from the published layouts of :mod:`corpus_fixtures`, which cite their sources),
breaks one thing in it and calls the reader a pipeline stage would call. :func:`classify` names the outcome:

- ``quarantined``: the listing (or the import's refusal, which fit-corpus writes to ``quarantine.jsonl`` with
  the clip's media as the file) names the file, the row where it has one, and the reason, and every other
  clip of the corpus is still listed;
- ``clear error``: the exception's message names the file (or the params key) and the reason;
- ``read correctly``: a legal edge case (a one-frame clip) read with its values intact;
- ``ACCEPTED-SILENTLY``: the reader returned as if nothing were wrong;
- ``TRACEBACK``: another exception, or one whose message does not say which file and why.

``tests/corpora/test_malformed_inputs.py`` runs every case; ``benchmarks/malformed_report.py`` writes the table.
"""
from __future__ import annotations

import csv
import gzip
import os
import pickle
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import corpus_fixtures as fx

QUARANTINED, CLEAR, READ, SILENT, TRACEBACK = ("quarantined", "clear error", "read correctly", "ACCEPTED-SILENTLY",
                                              "TRACEBACK")
ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Listed:
    """What a listing (or an import) reported: quarantine entries (file, row, reason, clip id), clips kept, clips
    expected."""

    entries: list[tuple[str, int | None, str, str | None]]
    kept: int
    expected_kept: int


@dataclass(frozen=True)
class Read:
    """A legal edge case read back; ``ok``: the values are the ones written."""

    ok: bool
    detail: str


@dataclass(frozen=True)
class Case:
    """``file`` / ``reason``: fragments the quarantine entry or error message must hold; ``row``: the quarantine
    entry's row (``None``: not checked); ``clip``: the clip id the entry names (``None``: not checked). ``gap``: a
    defect in a file this suite may not fix (the test xfails). ``build``: writes the input into the case's folder
    before ``run`` reads it (the report times and measures ``run`` alone); without it ``run`` does both."""

    id: str
    reader: str
    input: str
    run: Callable[[Path], Any]
    expect: str
    file: str = ""
    reason: str = ""
    row: int | None = None
    gap: str = ""
    clip: str | None = None
    build: Callable[[Path], Any] | None = None


def classify(case: Case, tmp: Path, built: bool = False) -> tuple[str, str]:
    """(outcome, message) of running ``case`` in the empty folder ``tmp`` (``built``: its ``build`` has run)."""
    if case.build is not None and not built:
        case.build(tmp)
    outcome, message = _classify(case, tmp)
    return outcome, message.replace(str(tmp), "<tmp>")


def _classify(case: Case, tmp: Path) -> tuple[str, str]:
    try:
        got = case.run(tmp)
    except (ValueError, OSError, LookupError) as exc:  # the library's errors (CorpusError, TrackError, ...) included
        message = f"{type(exc).__name__}: {exc}"
        named = case.file in str(exc) and case.reason in str(exc)
        return (CLEAR if named else TRACEBACK), message
    except Exception as exc:  # noqa: BLE001 - any other exception is what the suite looks for
        return TRACEBACK, f"{type(exc).__name__}: {exc}"
    if isinstance(got, Read):
        return (READ if got.ok else SILENT), got.detail
    if isinstance(got, Listed):
        hits = [e for e in got.entries if case.file in e[0] and case.reason in e[2]
                and (case.row is None or e[1] == case.row) and (case.clip is None or e[3] == case.clip)]
        if hits and got.kept == got.expected_kept:
            return QUARANTINED, f"{hits[0][0]} row {hits[0][1]}: {hits[0][2]}"
        if hits:
            return SILENT, f"quarantined, but {got.kept} of {got.expected_kept} other clips listed"
        return SILENT, f"no quarantine entry naming {case.file!r} / {case.reason!r}; got {got.entries}"
    return SILENT, f"returned {type(got).__name__} without complaint"


# ----------------------------------------------------------------------------------------- helpers
def listed(name: str, root: Path, expected_kept: int, **options) -> Listed:
    from m3t.corpora.base import open_corpus

    listing = open_corpus(name, root, **options).listing()
    entries = [(q.file, q.row, q.reason, q.clip_id) for q in listing.quarantined]
    return Listed(entries, len(listing.clips), expected_kept)


def append(path: Path, text: str) -> None:
    path.write_text(path.read_text(encoding="utf-8") + text, encoding="utf-8")


def imported(name: str, root: Path, expected_kept: int, **options) -> Listed:
    """Run the import of every listed clip of corpus ``name`` (what fit-corpus does per clip); a refusal becomes the
    quarantine entry fit-corpus writes: file = the clip's media, reason = the refusal's message."""
    from m3t.corpora.base import open_corpus
    from m3t.fitting.imports import ImportSettings, import_clip, imported_kind
    from m3t.trackers.dispatch import ClipRefused

    corpus = open_corpus(name, root, **options)
    kind = imported_kind(name)
    entries, kept = [], 0
    for clip in corpus.listing().clips:
        try:
            import_clip(clip, kind, corpus.source(clip), "k", ImportSettings("smplfx", 100))
            kept += 1
        except ClipRefused as exc:
            entries.append((clip.media, None, str(exc), clip.id))
    return Listed(entries, kept, expected_kept)


# ----------------------------------------------------------------------------------------- PHOENIX-2014-T
PHX = "annotations/manual/PHOENIX-2014-T.{}.corpus.csv"


def phoenix(tmp: Path) -> Path:
    fx.build_phoenix14t(tmp / "phx")
    return tmp / "phx"


def phx_header(tmp: Path):
    root = phoenix(tmp)
    path = root / PHX.format("dev")
    path.write_text(path.read_text().replace("speaker", "signer"), encoding="utf-8")
    return listed("phoenix14t", root, 6)


def phx_separator(tmp: Path):
    root = phoenix(tmp)
    path = root / PHX.format("dev")
    path.write_text(path.read_text().replace("|", ","), encoding="utf-8")
    return listed("phoenix14t", root, 6)


def phx_latin1(tmp: Path):
    root = phoenix(tmp)
    path = root / PHX.format("test")
    path.write_bytes(path.read_bytes().replace(b"morgen regnet es", "morgen regnet es über".encode("latin-1")))
    return listed("phoenix14t", root, 6)


def phx_truncated(tmp: Path):
    """The file cut in the middle of its last row (a copy that stopped early): that row has too few columns."""
    root = phoenix(tmp)
    path = root / PHX.format("test")
    append(path, "cut_here|cut_here/1/*.png|-1|-1|Sig")
    return listed("phoenix14t", root, 6)


def phx_row(row: str, split: str = "test", prepare: Callable[[Path, Path], None] | None = None):
    def run(tmp: Path):
        root = phoenix(tmp)
        if prepare is not None:
            prepare(root, tmp)
        append(root / PHX.format(split), row + "\n")
        return listed("phoenix14t", root, 6)

    return run


def phx_symlink(root: Path, tmp: Path) -> None:
    fx.write_phoenix_frames(tmp / "outside" / "leak")
    (root / "features/fullFrame-210x260px/test/leak").symlink_to(tmp / "outside" / "leak")


def phx_one_frame(tmp: Path):
    """A one-frame clip (one image) is a clip: listed, its folder holding that one frame."""
    root = phoenix(tmp)
    fx.write_phoenix_frames(root / "features/fullFrame-210x260px/test/one_frame", n=1)
    append(root / PHX.format("test"), "one_frame|one_frame/1/*.png|-1|-1|Signer01|A|ein bild\n")
    from m3t.corpora.base import open_corpus

    clips = {c.id: c for c in open_corpus("phoenix14t", root).clips()}
    frames = sorted((root / clips["one_frame"].media).iterdir()) if "one_frame" in clips else []
    return Read(len(clips) == 7 and [f.name for f in frames] == ["images0001.png"], f"{len(frames)} frame listed")


# ----------------------------------------------------------------------------------------- How2Sign
H2S = "how2sign_realigned_{}.csv"


def how2sign(tmp: Path) -> Path:
    fx.build_how2sign(tmp / "h2s", "archives")
    return tmp / "h2s"


def h2s_row(row: str):
    def run(tmp: Path):
        root = how2sign(tmp)
        fx.write_video(root / "test_rgb_front_clips/raw_videos/nan_times.mp4")
        append(root / H2S.format("test"), row + "\n")
        return listed("how2sign", root, 7)

    return run


def h2s_comma(tmp: Path):
    root = how2sign(tmp)
    path = root / H2S.format("test")
    path.write_text(path.read_text().replace("\t", ","), encoding="utf-8")
    return listed("how2sign", root, 7)


def h2s_symlink(tmp: Path):
    root = how2sign(tmp)
    fx.write_video(tmp / "outside" / "clip.mp4")
    (root / "test_rgb_front_clips/raw_videos/leak.mp4").symlink_to(tmp / "outside" / "clip.mp4")
    append(root / H2S.format("test"), "v\tv-rgb\tv_9\tleak\t1.0\t2.0\tA linked clip.\n")
    return listed("how2sign", root, 7)


# ----------------------------------------------------------------------------------------- CSL-Daily
CSL_PKL = "sentence_label/csl2020ct_v2.pkl"


def csl(tmp: Path) -> Path:
    fx.build_csl_daily(tmp / "csl")
    return tmp / "csl"


def csl_hostile(tmp: Path):
    root = csl(tmp)
    fx.write_hostile_pickle(root / CSL_PKL)
    return listed("csl_daily", root, 6)


def csl_truncated(tmp: Path):
    root = csl(tmp)
    data = (root / CSL_PKL).read_bytes()
    (root / CSL_PKL).write_bytes(data[: len(data) // 2])
    return listed("csl_daily", root, 6)


def csl_edit(change: Callable[[dict], None], split_row: str | None = None):
    def run(tmp: Path):
        root = csl(tmp)
        with open(root / CSL_PKL, "rb") as fh:
            data = pickle.load(fh)
        change(data)
        with open(root / CSL_PKL, "wb") as fh:
            pickle.dump(data, fh)
        if split_row:
            append(root / "sentence_label/split_1.txt", split_row + "\n")
        return listed("csl_daily", root, 6)

    return run


def _csl_up(data: dict) -> None:
    data["info"].append(dict(fx.CSL_REAL_INFO, name="../../S900000_P0000_T00"))


# ----------------------------------------------------------------------------------------- NMFs-CSL
def nmfs_row(row: str, file: str = "test.txt", raw: bytes | None = None):
    def run(tmp: Path):
        root = tmp / "nmfs"
        fx.build_nmfs_csl(root)
        if raw is not None:
            (root / file).write_bytes((root / file).read_bytes() + raw)
        else:
            append(root / file, row + "\n")
        return listed("nmfs_csl", root, 9)

    return run


# ----------------------------------------------------------------------------------------- MEAD
def mead_clip(change: Callable[[dict], dict] | None = None, raw: bytes | None = None, where: str = "W009/front/x/level_1/001"):
    """The released tree (:func:`corpus_fixtures.build_mead_release`) plus one clip ``where`` broken by ``change``
    (or replaced by ``raw`` bytes); read as fit-corpus reads it (``MeadCorpus.source``)."""

    def run(tmp: Path):
        root = tmp / "mead"
        fx.build_mead_release(root)
        arrays = fx.flame_arrays(4, exp=100, shape=300, batch_axis=True)
        path = root / where / "shape_pose_cam.hdf5"
        if raw is not None:
            path.parent.mkdir(parents=True)
            path.write_bytes(raw)
        else:
            fx.write_hdf5(path, change(arrays) if change else arrays)
        from m3t.corpora.base import open_corpus
        from m3t.trackers.dispatch import ClipRefused

        corpus = open_corpus("mead", root)
        listing = corpus.listing()
        clip = next(c for c in listing.clips if c.media.startswith(where))
        try:
            corpus.source(clip)
        except ClipRefused as exc:
            return Listed([(clip.media, None, str(exc), clip.id)], len(listing.clips), len(listing.clips))
        return Read(False, f"{clip.media} read")

    return run


def mead_all_nan(tmp: Path):
    root = tmp / "mead"
    fx.build_mead_release(root)
    return imported("mead", root, 4)


def mead_stray(tmp: Path):
    root = tmp / "mead"
    fx.build_mead_release(root)
    fx.write_hdf5(root / "M003/front/angry/shape_pose_cam.hdf5", fx.flame_arrays(4, exp=100, shape=300, batch_axis=True))
    return listed("mead", root, 5)


# ----------------------------------------------------------------------------------------- SOKE SMPL-X
SOKE_CLIP = "train/poses/-fZc293MpJk_0-1-rgb_front"


def soke(tmp: Path) -> Path:
    fx.build_soke(tmp / "soke", "how2sign")
    return tmp / "soke"


def soke_frame(frame: Any, raw: bytes | None = None):
    """A good SOKE clip whose frame 2 is replaced by ``frame`` (pickled) or ``raw`` bytes; the listing validates."""

    def run(tmp: Path):
        root = soke(tmp)
        path = root / "train/poses/-fZc293MpJk_0-1-rgb_front/-fZc293MpJk_0-1-rgb_front_2_3D.pkl"
        if raw is not None:
            path.write_bytes(raw)
        else:
            with open(path, "wb") as fh:
                pickle.dump(frame, fh)
        return listed("soke_smplx", root, 3, annotation="annotation.csv", validate=True)

    return run


class _CallsGetcwd:
    """Pickles as a call of os.getcwd: a stand-in for a hostile pickle (harmless even if it ran)."""

    def __reduce__(self):
        return (os.getcwd, ())


def soke_nan_frames(tmp: Path):
    root = soke(tmp)
    folder = root / "train/poses/-fZc293MpJk_0-1-rgb_front"
    for f in folder.glob("*.pkl"):
        with open(f, "rb") as fh:
            frame = pickle.load(fh)
        with open(f, "wb") as fh:
            pickle.dump({k: np.full_like(v, np.nan) for k, v in frame.items()}, fh)
    return imported("soke_smplx", root, 3, annotation="annotation.csv",
                    flat_hand_mean=True, validate=True)


# ----------------------------------------------------------------------------------------- slt pickles
SLT_TRAIN = "phoenix14t.pami0.train"


def slt_entry(tmp: Path, entry: dict | None = None, raw: bytes | None = None, listing: bool = True):
    root = tmp / "slt"
    fx.build_slt(root)
    if raw is not None:
        (root / SLT_TRAIN).write_bytes(raw)
    elif entry is not None:
        with gzip.open(root / SLT_TRAIN, "rb") as fh:
            entries = pickle.load(fh)
        with gzip.open(root / SLT_TRAIN, "wb") as fh:
            pickle.dump(entries + [entry], fh)
    return listed("slt_pickle", root, 7) if listing else root


def slt_sign(sign: Any, name: str = "train/odd"):
    return lambda tmp: slt_entry(tmp, {"name": name, "signer": "s", "gloss": "G", "text": "t", "sign": sign})


def slt_truncated(tmp: Path):
    buf = gzip.compress(pickle.dumps(fx.slt_entries("train", 3, np.random.default_rng(0))))
    return slt_entry(tmp, raw=buf[: len(buf) // 2])


def slt_torch(tmp: Path):
    root = tmp / "slt"
    fx.build_slt(root)
    fx.write_torch_slt(root / SLT_TRAIN)
    return listed("slt_pickle", root, 7)


def slt_hostile(tmp: Path):
    root = tmp / "slt"
    fx.build_slt(root)
    with gzip.open(root / SLT_TRAIN, "wb") as fh:
        pickle.dump([{"name": "train/x", "signer": "s", "gloss": "", "text": "", "sign": _CallsGetcwd()}], fh)
    return listed("slt_pickle", root, 7)


def slt_symlink_out(tmp: Path):
    """A split file in the root that is a link to a pickle outside it (``build_slt``'s layout, plus the link)."""
    root = tmp / "slt"
    fx.build_slt(root)
    (tmp / "outside").mkdir()
    shutil.copyfile(root / SLT_TRAIN, tmp / "outside" / "secret.train")
    (root / "leak.pami0.dev").symlink_to(tmp / "outside" / "secret.train")
    return listed("slt_pickle", root, 7)


def slt_files_escape(tmp: Path):
    """``corpora.slt_pickle.files`` naming a file above the root through ``..``."""
    root = tmp / "slt"
    fx.build_slt(root)
    shutil.copyfile(root / SLT_TRAIN, tmp / "secret.pami0.train")
    return listed("slt_pickle", root, 3, files=[SLT_TRAIN, "../secret.pami0.train"])


def slt_all_nan(tmp: Path):
    sign = np.full((5, 12), np.nan, np.float32)
    root = slt_entry(tmp, {"name": "train/all_nan", "signer": "s", "gloss": "G", "text": "t", "sign": sign},
                     listing=False)
    return imported("slt_pickle", root, 7)


def slt_one_frame(tmp: Path):
    sign = np.arange(12, dtype=np.float32)[None]
    root = slt_entry(tmp, {"name": "train/one", "signer": "s", "gloss": "G", "text": "t", "sign": sign}, listing=False)
    from m3t.corpora.base import open_corpus

    corpus = open_corpus("slt_pickle", root)
    clip = next(c for c in corpus.listing().clips if c.id == "train__one")
    got = corpus.sequence(clip)
    return Read(got.shape == (1, 12) and np.array_equal(got, sign), f"sign {got.shape} read")


# ----------------------------------------------------------------------------------------- .pose files
def pose_collection(tmp: Path) -> Path:
    from m3t.corpora.fingerspelling import lexicon_root

    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    fx.build_pose_collection(tmp / "pose", lexicon_root(), rows)
    return tmp / "pose"


def pose_listing(tmp: Path):
    return listed("posefile", pose_collection(tmp), 4, index="index.csv")


def pose_row(row: str, prepare: Callable[[Path, Path], None] | None = None):
    def run(tmp: Path):
        root = pose_collection(tmp)
        if prepare is not None:
            prepare(root, tmp)
        append(root / "index.csv", row + "\n")
        return listed("posefile", root, 4, index="index.csv")

    return run


def pose_symlink(root: Path, tmp: Path) -> None:
    (tmp / "outside").mkdir()
    shutil.copyfile(root / "poses/ase_0.pose", tmp / "outside/secret.pose")
    (root / "poses/link.pose").symlink_to(tmp / "outside/secret.pose")


def pose_track_truncated(tmp: Path):
    from m3t.trackers.posefile import load_pose_track

    root = pose_collection(tmp)
    return load_pose_track(root / "poses/truncated.pose")


def fingerspell_unknown_language(tmp: Path):
    from m3t.corpora.fingerspelling import FingerspellingCorpus

    return FingerspellingCorpus().spell("abc", "xyz")


def fingerspell_unknown_language_option(tmp: Path):
    from m3t.corpora.base import open_corpus

    return open_corpus("fingerspelling", None, languages=["xyz"], words_per_language=0).listing()


# ----------------------------------------------------------------------------------------- track files
def track_file(tmp: Path, **fields) -> Path:
    """A MediaPipe Holistic track saved by :func:`save_track`, with ``fields`` then overwritten in the file."""
    from m3t.trackers.track import Track, save_track

    k = 543
    track = Track(np.zeros((3, k, 2), np.float32), np.ones((3, k), np.float32), "mediapipe_holistic", (8, 8), 25.0,
                  np.full(4, np.nan, np.float32), "test")
    path = save_track(track, tmp / "clip.track.npz")
    if fields:
        with np.load(path) as data:
            stored = {name: data[name] for name in data.files}
        np.savez(path, **{**stored, **fields})
    return path


def track_case(**fields):
    def run(tmp: Path):
        from m3t.trackers.track import load_track

        return load_track(track_file(tmp, **fields))

    return run


def track_truncated(tmp: Path):
    from m3t.trackers.track import load_track

    path = track_file(tmp)
    path.write_bytes(path.read_bytes()[:200])
    return load_track(path)


def track_one_frame(tmp: Path):
    from m3t.trackers.track import load_track

    kp = np.full((1, 543, 2), 0.5, np.float32)
    got = load_track(track_file(tmp, keypoints=kp, confidence=np.ones((1, 543), np.float32)))
    return Read(got.num_frames == 1 and np.array_equal(got.keypoints, kp), f"{got.num_frames} frame read")


# ----------------------------------------------------------------------------------------- tracker outputs
class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned > /dev/null",))


def nlf_pickle(tmp: Path):
    from m3t.trackers.nlf_reader import read_nlf

    (tmp / "clip.nlf.pkl").write_bytes(pickle.dumps({"pose": _Evil()}, protocol=2))
    return read_nlf(tmp / "clip.nlf.pkl")


def nlf_torch(tmp: Path):
    import torch

    from m3t.trackers.nlf_reader import read_nlf

    torch.save({"pose": _Evil()}, tmp / "clip.nlf.pt")
    return read_nlf(tmp / "clip.nlf.pt")


def wilor_object_array(tmp: Path):
    from m3t.trackers.wilor_reader import read_wilor

    np.savez(tmp / "clip.wilor.npz", global_orient=np.array([_Evil()], dtype=object))
    return read_wilor(tmp / "clip.wilor.npz")


def nlf_shape(tmp: Path):
    """NLF's array layout as :mod:`m3t.trackers.nlf_reader` documents it and ``fusion_fixtures.write_nlf`` writes it
    (``pose`` (N, 165) SMPL-X axis-angles, ``betas`` (N, 10), ``trans`` (N, 3)), with SMPL's 72 pose values."""
    from m3t.trackers.nlf_reader import read_nlf

    np.savez(tmp / "clip.nlf.npz", pose=np.zeros((4, 72), np.float32), betas=np.zeros((4, 10), np.float32),
             trans=np.zeros((4, 3), np.float32))
    return read_nlf(tmp / "clip.nlf.npz")


def nlf_truncated(tmp: Path):
    from m3t.trackers.nlf_reader import read_nlf

    np.savez(tmp / "clip.nlf.npz", pose=np.zeros((4, 165), np.float32), betas=np.zeros((4, 10), np.float32),
             trans=np.zeros((4, 3), np.float32))
    data = (tmp / "clip.nlf.npz").read_bytes()
    (tmp / "clip.nlf.npz").write_bytes(data[: len(data) // 2])
    return read_nlf(tmp / "clip.nlf.npz")


def pixel3dmm_empty(tmp: Path):
    from m3t.trackers.pixel3dmm_reader import read_pixel3dmm

    (tmp / "clip.pixel3dmm" / "checkpoint").mkdir(parents=True)
    return read_pixel3dmm(tmp / "clip.pixel3dmm")


def outputs_symlink(tmp: Path):
    from m3t.trackers.external import find_tracker_outputs

    (tmp / "outside").mkdir()
    np.savez(tmp / "outside" / "x.npz", pose=np.zeros((1, 165)))
    (tmp / "clips").mkdir()
    fx.write_video(tmp / "clips" / "clip.mp4")
    (tmp / "clips" / "clip.nlf.npz").symlink_to(tmp / "outside" / "x.npz")
    return find_tracker_outputs(tmp / "clips" / "clip.mp4")


# ----------------------------------------------------------------------------------------- shards
def _layout():
    from m3t.body.protocol import Modality, ModalityLayout

    return ModalityLayout(modalities=(Modality("face", "scalar", ("jaw_open", "smile")),), identity_labels=("height",))


def _fitted(i: int, frames: int = 4):
    from m3t.corpora.clip import Clip
    from m3t.shards import FittedClip

    clip = Clip(f"clip-{i}", "toy", "train", "DGS", "s0", "es regnet", "REGEN", f"videos/{i}.mp4", 25.0)
    return FittedClip(clip, f"sha256:{i:064x}", {"face": np.full((frames, 2), 0.1 * i, np.float32)},
                      np.zeros(1, np.float32), {}, {}, "anny")


def shard(tmp: Path, n: int = 3) -> Path:
    from m3t.shards import write_shard

    return write_shard(tmp / "train.parquet", [_fitted(i) for i in range(n)], _layout())


def rewrite(path: Path, change: Callable[[Any], Any]) -> None:
    """Rewrite the Parquet file at ``path`` with ``change(table)`` (schema metadata kept unless changed)."""
    import pyarrow.parquet as pq

    pq.write_table(change(pq.read_table(path)), path)


def shard_truncated(tmp: Path):
    from m3t.shards import read_shard

    path = shard(tmp)
    path.write_bytes(path.read_bytes()[:-100])
    return read_shard(path)


def shard_version(tmp: Path):
    from m3t.shards import read_shard

    path = shard(tmp)
    rewrite(path, lambda t: t.replace_schema_metadata({**t.schema.metadata, b"m3t.schema_version": b"99"}))
    return read_shard(path)


def shard_nan(tmp: Path):
    """A shard edited outside the writer (which refuses NaN): one value of clip-1's face stream is NaN."""
    import pyarrow as pa

    from m3t.shards import read_shard

    path = shard(tmp)

    def poison(table):
        i = table.schema.get_field_index("face")
        rows = table.column("face").to_pylist()
        rows[1][2][0] = float("nan")
        return table.set_column(i, table.schema.field(i), pa.array(rows, type=table.schema.field(i).type))

    rewrite(path, poison)
    return read_shard(path)


def shard_duplicate(tmp: Path):
    from m3t.shards import read_shard

    path = shard(tmp)
    rewrite(path, lambda t: t.set_column(t.schema.get_field_index("id"), "id",
                                         __import__("pyarrow").array(["clip-0", "clip-1", "clip-0"])))
    return read_shard(path)


def shard_two_corpora(tmp: Path):
    from m3t.shards.io import read_split
    from m3t.shards import write_shard

    for name in ("a", "b"):
        (tmp / name).mkdir()
        write_shard(tmp / name / "train.parquet", [_fitted(0)], _layout())
    return read_split([tmp / "a", tmp / "b"], "train")


# ----------------------------------------------------------------------------------------- token shards
def token_shard(tmp: Path) -> Path:
    from m3t.shards.tokens import TokenClip, TokenInfo, write_token_shard

    clips = [TokenClip(_fitted(i).clip, 8, {"body": np.array([1, 2]), "face": np.array([3, 0])}) for i in range(2)]
    return write_token_shard(tmp / "train.tokens.parquet", clips, TokenInfo({"body": 16, "face": 8}, 4, {}))


def token_case(change: Callable[[Any], Any] | None = None, cut: bool = False, motion: bool = False):
    def run(tmp: Path):
        from m3t.shards.tokens import read_token_shard

        path = shard(tmp) if motion else token_shard(tmp)
        if cut:
            path.write_bytes(path.read_bytes()[:-64])
        if change is not None:
            rewrite(path, change)
        return read_token_shard(path)

    return run


def _set_stream(table, name: str, rows: list):
    import pyarrow as pa

    i = table.schema.get_field_index(name)
    return table.set_column(i, table.schema.field(i), pa.array(rows, type=table.schema.field(i).type))


# ----------------------------------------------------------------------------------------- checkpoints
def checkpoint_case(kind: str):
    def run(tmp: Path):
        import torch

        from m3t.checkpoints import read_checkpoint

        path = tmp / "tokenizer.pt"
        if kind == "hostile":
            torch.save({"format": "m3t-tokenizer", "state_dict": _Evil()}, path)
        else:
            torch.save({"format": "m3t-tokenizer" if kind == "truncated" else "m3t-smlm", "state_dict": {}}, path)
        if kind == "truncated":
            path.write_bytes(path.read_bytes()[:100])
        return read_checkpoint(path, "m3t-tokenizer", "tokenizer", "train_tokenizer")

    return run


# ----------------------------------------------------------------------------------------- params.yaml
def params_case(old: str, new: str, raw: bytes | None = None):
    def run(tmp: Path):
        from m3t.config import load_params

        text = (ROOT / "params.yaml").read_text(encoding="utf-8")
        assert old in text, f"params.yaml no longer holds {old!r}"
        path = tmp / "params.yaml"
        path.write_bytes(text.replace(old, new, 1).encode("utf-8") + (raw or b""))
        return load_params(path)

    return run


# ----------------------------------------------------------------------------------------- the table
CASES: tuple[Case, ...] = (
    # PHOENIX-2014-T
    Case("phoenix-wrong-header", "phoenix14t", "header 'speaker' renamed 'signer'", phx_header, CLEAR,
         "PHOENIX-2014-T.dev.corpus.csv line 1", "expected exactly"),
    Case("phoenix-wrong-separator", "phoenix14t", "',' instead of '|'", phx_separator, CLEAR,
         "PHOENIX-2014-T.dev.corpus.csv line 1", "expected exactly"),
    Case("phoenix-non-utf8", "phoenix14t", "a Latin-1 'ü' in row 2", phx_latin1, CLEAR,
         "PHOENIX-2014-T.test.corpus.csv line 2", "not UTF-8"),
    Case("phoenix-truncated-file", "phoenix14t", "file cut inside its last row", phx_truncated, QUARANTINED,
         "PHOENIX-2014-T.test.corpus.csv", "malformed row", row=3),
    Case("phoenix-empty-text", "phoenix14t", "empty translation", phx_row("x|x/1/*.png|-1|-1|S|G|"), QUARANTINED,
         "PHOENIX-2014-T.test.corpus.csv", "empty translation", row=3),
    Case("phoenix-path-traversal", "phoenix14t", "video '../../../../outside/1/*.png'",
         phx_row("up|../../../../outside/1/*.png|-1|-1|S|G|t"), QUARANTINED, "PHOENIX-2014-T.test.corpus.csv",
         "'..' component", row=3),
    Case("phoenix-symlink-out", "phoenix14t", "frame folder is a link out of the root",
         phx_row("leak|leak/1/*.png|-1|-1|S|G|t", prepare=phx_symlink), QUARANTINED, "PHOENIX-2014-T.test.corpus.csv",
         "resolves outside the corpus root", row=3),
    Case("phoenix-duplicate-id", "phoenix14t", "a dev name again in dev",
         phx_row("01December_2011_Thursday_dev-100|01December_2011_Thursday_dev-101/1/*.png|-1|-1|S|G|t", "dev"),
         QUARANTINED, "PHOENIX-2014-T.dev.corpus.csv", "duplicate clip id", row=4),
    Case("phoenix-zero-frames", "phoenix14t", "frame folder without images",
         phx_row("none|none/1/*.png|-1|-1|S|G|t",
                 prepare=lambda root, tmp: (root / "features/fullFrame-210x260px/test/none").mkdir()),
         QUARANTINED, "PHOENIX-2014-T.test.corpus.csv", "empty frame folder", row=3),
    Case("phoenix-layout-no-folder", "phoenix14t", "video column '*.png' names no folder",
         phx_row("bare|*.png|-1|-1|S|G|t"), QUARANTINED, "PHOENIX-2014-T.test.corpus.csv", "names no frame folder",
         row=3),
    Case("phoenix-one-frame", "phoenix14t", "frame folder with one image", phx_one_frame, READ),
    # How2Sign
    Case("how2sign-comma-separator", "how2sign", "',' instead of tabs", h2s_comma, CLEAR,
         "how2sign_realigned_test.csv line 1", "expected exactly"),
    Case("how2sign-nan-times", "how2sign", "START_REALIGNED 'nan'",
         h2s_row("v\tv-rgb\tv_7\tnan_times\tnan\t2.0\tNo time."), QUARANTINED, "how2sign_realigned_test.csv",
         "bad times", row=4),
    Case("how2sign-inf-times", "how2sign", "END_REALIGNED 'inf'",
         h2s_row("v\tv-rgb\tv_7\tnan_times\t1.0\tinf\tNo end."), QUARANTINED, "how2sign_realigned_test.csv",
         "bad times", row=4),
    Case("how2sign-extra-column", "how2sign", "a tab inside SENTENCE (8 columns)",
         h2s_row("v\tv-rgb\tv_7\tnan_times\t1.0\t2.0\tA tab\there."), QUARANTINED, "how2sign_realigned_test.csv",
         "8 tab-separated columns", row=4),
    Case("how2sign-path-traversal", "how2sign", "SENTENCE_NAME '../../../outside/clip'",
         h2s_row("v\tv-rgb\tv_7\t../../../outside/clip\t1.0\t2.0\tUp."), QUARANTINED, "how2sign_realigned_test.csv",
         "'..' component", row=4),
    Case("how2sign-symlink-out", "how2sign", "clip file is a link out of the root", h2s_symlink, QUARANTINED,
         "how2sign_realigned_test.csv", "resolves outside the corpus root", row=4),
    # CSL-Daily
    Case("csl-daily-code-pickle", "csl_daily", "pickle calling os.getcwd", csl_hostile, CLEAR, "csl2020ct_v2.pkl",
         "was refused (nothing was run)"),
    Case("csl-daily-truncated-pickle", "csl_daily", "pickle cut in half", csl_truncated, CLEAR, "csl2020ct_v2.pkl",
         "not a readable pickle"),
    Case("csl-daily-empty-text", "csl_daily", "label_word []",
         csl_edit(lambda d: d["info"].append({**d["info"][0], "name": "S200000_P0000_T00", "label_word": []}),
                  "S200000_P0000_T00|train"), QUARANTINED, CSL_PKL, "label_word is empty", clip="S200000_P0000_T00"),
    Case("csl-daily-duplicate-id", "csl_daily", "a name twice in the pickle",
         csl_edit(lambda d: d["info"].append(dict(d["info"][1]))), QUARANTINED, CSL_PKL, "duplicate clip id"),
    Case("csl-daily-path-traversal", "csl_daily", "name '../../S900000_P0000_T00'",
         csl_edit(_csl_up, "../../S900000_P0000_T00|train"), QUARANTINED, CSL_PKL, "'..' component"),
    Case("csl-daily-wrong-type", "csl_daily", "label_gloss a number, not a list",
         csl_edit(lambda d: d["info"].append({**d["info"][0], "name": "S200001_P0000_T00", "label_gloss": 7}),
                  "S200001_P0000_T00|train"), QUARANTINED, CSL_PKL, "label_gloss", clip="S200001_P0000_T00"),
    # NMFs-CSL
    Case("nmfs-csl-malformed-row", "nmfs_csl", "a path without a class", nmfs_row("P07/3_01.mp4"), QUARANTINED,
         "test.txt", "malformed row", row=5),
    Case("nmfs-csl-path-traversal", "nmfs_csl", "'../../outside/x.mp4 1'", nmfs_row("../../outside/x.mp4 1"),
         QUARANTINED, "test.txt", "'..' component", row=5),
    Case("nmfs-csl-non-utf8", "nmfs_csl", "a Latin-1 byte in a row", nmfs_row("", raw="P07/\xe9.mp4 1\n".encode("latin-1")),
         CLEAR, "test.txt line 5", "not UTF-8"),
    # MEAD
    Case("mead-all-nan", "mead import", "every frame NaN (release fixture clip 003)", mead_all_nan, QUARANTINED,
         "W011/front/fear/level_1/003", "clip W011_front_fear_level_1_003: every one of its 4 frames holds NaN or inf"),
    Case("mead-layout-stray", "mead", "a file one level too high", mead_stray, QUARANTINED,
         "M003/front/angry/shape_pose_cam.hdf5", "unexpected location"),
    Case("mead-wrong-shape", "mead source", "'jaw' of shape (2, T, 3)",
         mead_clip(lambda a: {**a, "jaw": np.zeros((2, 4, 3), np.float32)}), CLEAR, "shape_pose_cam.hdf5",
         "expected (T, D)"),
    Case("mead-frame-count", "mead source", "'cam' shorter than 'exp'",
         mead_clip(lambda a: {**a, "cam": a["cam"][:, :2]}), CLEAR, "shape_pose_cam.hdf5", "has 2 frames"),
    Case("mead-wrong-width", "mead source", "'jaw' with 4 columns instead of 3",
         mead_clip(lambda a: {**a, "jaw": np.zeros((1, a["exp"].shape[1], 4), np.float32)}), CLEAR,
         "shape_pose_cam.hdf5", "dataset 'jaw' has 4 columns; expected 3"),
    Case("mead-truncated-hdf5", "mead source", "HDF5 signature only", mead_clip(raw=b"\x89HDF\r\n\x1a\n\0\0"),
         CLEAR, "shape_pose_cam.hdf5", "not a readable HDF5 file"),
    Case("mead-wrong-dtype", "mead source", "'exp' stored as strings",
         mead_clip(lambda a: {**a, "exp": np.full((1, 4, 100), b"x")}), CLEAR, "shape_pose_cam.hdf5", "'exp'"),
    # SOKE SMPL-X
    Case("soke-code-pickle", "soke_smplx", "frame pickle calling os.getcwd", soke_frame(_CallsGetcwd()), QUARANTINED,
         SOKE_CLIP, "_2_3D.pkl: the pickle references posix.getcwd"),
    Case("soke-truncated-pickle", "soke_smplx", "frame pickle cut short", soke_frame(None, raw=b"\x80\x04\x95"),
         QUARANTINED, SOKE_CLIP, "_2_3D.pkl: not a readable pickle"),
    Case("soke-wrong-type", "soke_smplx", "frame pickle holds a list", soke_frame([1, 2, 3]), QUARANTINED,
         SOKE_CLIP + "/-fZc293MpJk_0-1-rgb_front_2_3D.pkl", "expected a dict of SMPL-X arrays, found list"),
    Case("soke-all-nan", "soke_smplx import", "every frame NaN", soke_nan_frames, QUARANTINED,
         SOKE_CLIP, "every one of its 3 frames holds NaN or inf"),
    # slt pickles
    Case("slt-torch-pickle", "slt_pickle", "torch tensors in the records", slt_torch, CLEAR, SLT_TRAIN,
         "tensor.numpy()"),
    Case("slt-code-pickle", "slt_pickle", "record calling os.getcwd", slt_hostile, CLEAR, SLT_TRAIN, "was refused"),
    Case("slt-truncated", "slt_pickle", "gzip stream cut in half", slt_truncated, CLEAR, SLT_TRAIN,
         "not a readable pickle"),
    Case("slt-zero-frames", "slt_pickle", "sign of shape (0, 12)", slt_sign(np.zeros((0, 12), np.float32)),
         QUARANTINED, SLT_TRAIN, "non-empty (T, D) float array", row=5),
    Case("slt-wrong-dtype", "slt_pickle", "sign of strings", slt_sign(np.full((3, 12), "x")), QUARANTINED, SLT_TRAIN,
         "float array", row=5),
    Case("slt-all-nan", "slt_pickle import", "every frame NaN", slt_all_nan, QUARANTINED, SLT_TRAIN,
         "clip train__all_nan: every one of its 5 frames holds NaN or inf"),
    Case("slt-one-frame", "slt_pickle", "sign of shape (1, 12)", slt_one_frame, READ),
    Case("slt-symlink-out", "slt_pickle", "a split file linked to a pickle outside the root", slt_symlink_out,
         QUARANTINED, "leak.pami0.dev", "outside the corpus root"),
    Case("slt-files-escape", "slt_pickle", "corpora.slt_pickle.files = ../secret.pami0.train", slt_files_escape,
         QUARANTINED, "secret.pami0.train", "could leave the corpus root"),
    # .pose files
    Case("pose-truncated", "posefile", "a .pose file cut in half", pose_listing, QUARANTINED, "index.csv",
         "truncated", row=6),
    Case("pose-not-a-pose", "posefile", "CSV bytes named .pose", pose_listing, QUARANTINED, "index.csv",
         "not a .pose file", row=13),
    Case("pose-path-traversal", "posefile", "index path '../outside.pose'", pose_row("up,../outside.pose,train,A,ase,s0,0"),
         QUARANTINED, "index.csv", "'..' component", row=14),
    Case("pose-symlink-out", "posefile", "index path a link out of the root",
         pose_row("link,poses/link.pose,train,A,ase,s0,0", prepare=pose_symlink), QUARANTINED, "index.csv",
         "resolves outside the corpus root", row=14),
    Case("pose-duplicate-id", "posefile", "id 'c0' twice", pose_listing, QUARANTINED, "index.csv", "duplicate clip id",
         row=12),
    Case("pose-track-truncated", "pose tracker", "load_pose_track of a cut file", pose_track_truncated, CLEAR,
         "truncated.pose", "truncated"),
    Case("fingerspelling-unknown-language", "fingerspelling", "spell('abc', 'xyz')", fingerspell_unknown_language,
         CLEAR, "'xyz'", "no letters"),
    Case("fingerspelling-unknown-language-option", "fingerspelling", "languages: [xyz]",
         fingerspell_unknown_language_option, CLEAR, "xyz", "languages"),
    # track files
    Case("track-fps-zero", "track file", "fps 0", track_case(fps=np.array(0.0)), CLEAR, "clip.track.npz",
         "not a positive finite number"),
    Case("track-fps-nan", "track file", "fps NaN", track_case(fps=np.array(np.nan)), CLEAR, "clip.track.npz",
         "not a positive finite number"),
    Case("track-truncated", "track file", "npz cut after 200 bytes", track_truncated, CLEAR, "clip.track.npz",
         "unreadable"),
    Case("track-wrong-shape", "track file", "keypoints (3, 543, 3)",
         track_case(keypoints=np.zeros((3, 543, 3), np.float32)), CLEAR, "clip.track.npz", "are not (T, K, 2)"),
    Case("track-zero-frames", "track file", "keypoints (0, 543, 2)",
         track_case(keypoints=np.zeros((0, 543, 2), np.float32), confidence=np.zeros((0, 543), np.float32)),
         CLEAR, "clip.track.npz", "no frames"),
    Case("track-one-frame", "track file", "keypoints (1, 543, 2)", track_one_frame, READ),
    # tracker outputs
    Case("nlf-code-pickle", "NLF output", ".pkl whose payload calls os.system", nlf_pickle, CLEAR, "clip.nlf.pkl",
         "refused"),
    Case("nlf-code-torch", "NLF output", ".pt whose payload calls os.system", nlf_torch, CLEAR, "clip.nlf.pt",
         "refused"),
    Case("wilor-object-array", "WiLoR output", ".npz holding an object array", wilor_object_array, CLEAR,
         "clip.wilor.npz", "refused"),
    Case("nlf-wrong-shape", "NLF output", "pose (4, 72) instead of (4, 165)", nlf_shape, CLEAR, "clip.nlf.npz",
         "expected (..., 165)"),
    Case("nlf-truncated", "NLF output", "npz cut in half", nlf_truncated, CLEAR, "clip.nlf.npz", "unreadable"),
    Case("pixel3dmm-zero-frames", "Pixel3DMM output", "checkpoint folder without .frame files", pixel3dmm_empty,
         CLEAR, "clip.pixel3dmm", "no Pixel3DMM '*.frame' files"),
    Case("tracker-output-symlink-out", "tracker outputs", "clip.nlf.npz a link out of the clip folder",
         outputs_symlink, CLEAR, "clip.nlf.npz", "leads outside the clip's folder"),
    # shards
    Case("shard-truncated", "read_shard", "Parquet footer cut", shard_truncated, CLEAR, "train.parquet",
         "not a readable Parquet file"),
    Case("shard-wrong-version", "read_shard", "m3t.schema_version 99", shard_version, CLEAR, "train.parquet",
         "version 99"),
    Case("shard-nan", "read_shard", "a NaN written around the shard writer", shard_nan, CLEAR, "train.parquet",
         "NaN or inf"),
    Case("shard-duplicate-id", "read_shard", "clip id 'clip-0' twice in one shard", shard_duplicate, CLEAR,
         "train.parquet", "appear twice"),
    Case("shard-duplicate-across-corpora", "read_split", "clip id in two corpora's shards", shard_two_corpora, CLEAR,
         "train.parquet", "is in both"),
    # token shards
    Case("tokens-truncated", "read_token_shard", "Parquet footer cut", token_case(cut=True), CLEAR,
         "train.tokens.parquet", "not a readable Parquet file"),
    Case("tokens-motion-shard", "read_token_shard", "a motion shard given as tokens", token_case(motion=True), CLEAR,
         "train.parquet", "not an m3t token shard"),
    Case("tokens-out-of-range", "read_token_shard", "token 99 in a 16-code stream",
         token_case(lambda t: _set_stream(t, "body", [[1, 99], [1, 2]])), CLEAR, "train.tokens.parquet",
         "outside [0, 16)"),
    Case("tokens-wrong-length", "read_token_shard", "3 tokens for 8 frames / 4",
         token_case(lambda t: _set_stream(t, "face", [[1, 2, 3], [3, 0]])), CLEAR, "train.tokens.parquet",
         "expected ceil(8 / 4) = 2"),
    Case("tokens-missing-stream", "read_token_shard", "column 'face' dropped",
         token_case(lambda t: t.drop_columns(["face"])), CLEAR, "train.tokens.parquet", "'face'"),
    # checkpoints
    Case("checkpoint-code-pickle", "read_checkpoint", "payload calling os.system", checkpoint_case("hostile"), CLEAR,
         "tokenizer.pt", "not a readable tokenizer checkpoint"),
    Case("checkpoint-truncated", "read_checkpoint", "file cut after 100 bytes", checkpoint_case("truncated"), CLEAR,
         "tokenizer.pt", "not a readable tokenizer checkpoint"),
    Case("checkpoint-other-format", "read_checkpoint", "an SMLM checkpoint given as tokenizer",
         checkpoint_case("other"), CLEAR, "tokenizer.pt", "expected 'm3t-tokenizer'"),
    # params.yaml
    Case("params-unknown-key", "load_params", "fit_corpus.workerz", params_case("\n  workers:", "\n  workerz:"),
         CLEAR, "fit_corpus", "workerz"),
    Case("params-wrong-type", "load_params", "fit_corpus.workers: two",
         params_case("\n  workers: ", "\n  workers: two #"), CLEAR, "fit_corpus.workers", "expected"),
    Case("params-bad-yaml", "load_params", "an unclosed '[' list", params_case("\nfit_corpus:", "\nfit_corpus: [\n"),
         CLEAR, "params.yaml", "YAML"),
    Case("params-non-utf8", "load_params", "a Latin-1 byte in a comment", params_case("", "", raw=b"# \xe9\n"),
         CLEAR, "params.yaml", "UTF-8"),
)
