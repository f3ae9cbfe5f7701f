"""Readers for the outputs of the paper's 3D trackers (M3T App. 0.C): NLF (body), WiLoR (hands),
Pixel3DMM (face). They return per-frame estimates in the trackers' own conventions (SMPL-X / MANO /
FLAME); :mod:`m3t.fitting.fusion` turns them into one SMPL-FX initialisation.

Loading never executes code from a file: ``.npz`` / ``.npy`` with ``allow_pickle=False``; torch files
(``.pt``, ``.pth``, ``.frame``) with ``torch.load(weights_only=True)`` and only numpy's array / dtype
reconstruction allow-listed; ``.pkl`` with :class:`m3t.body.model_files.SafeModelUnpickler`.

Formats (field names checked against the trackers' public code: WiLoR / HaMeR ``demo.py`` and model
forward, Pixel3DMM ``tracking/tracker.py::save_checkpoint``, NLF ``detect_smpl_batched``):

**WiLoR** — one file per clip (``.npz`` or a torch-saved dict), one row per detected hand:
``frame_index`` (N,) int; ``is_right`` (N,) 0/1 (WiLoR's ``batch['right']``); ``global_orient``
(N, 1, 3, 3) and ``hand_pose`` (N, 15, 3, 3) rotation matrices and ``betas`` (N, 10), i.e. the model's
``out['pred_mano_params']`` (also accepted nested under that key); optional ``confidence`` (N,) detector
score. Rotations are MANO's, relative to the flat hand (``MANOLayer`` with rotation matrices adds no hand
mean). WiLoR runs left hands as flipped right hands: their parameters are mirrored back here
(``R -> M R M``, M = diag(-1, 1, 1)), giving left-hand MANO / SMPL-X rotations. Several hands of one side
in a frame: the most confident is kept.

**Pixel3DMM** — a folder of ``{frame:05d}.frame`` files, each ``torch.save`` of a dict:
``flame``: ``exp`` (1, 100), ``shape`` (1, 300), ``eyes`` (1, 12) (two 6D), ``eyelids`` (1, 2),
``jaw`` (1, 6), ``neck`` (1, 6), ``R`` (1, 6) head rotation, ``t`` (1, 3) (plus ``R_rotation_matrix``);
``camera``: ``R_base_0``, ``t_base_0``, ``fl``, ``pp``; ``img_size``; ``frame_id``; ``global_step``.
All rotations are 6D in PyTorch3D's layout (the first two *rows* of the matrix); they are converted
here to this project's layout (first two columns, :mod:`m3t.body.rotations`).

**NLF** — one file per clip (``.npz`` or torch-saved dict) for the signer, with SMPL-X parameters of
``detect_smpl_batched(..., model_name='smplx')``: ``pose`` (T, 165) axis-angle of the 55 SMPL-X joints
(global orient, 21 body, jaw, two eyes, 15 + 15 finger joints), ``betas`` (T, 10), ``trans`` (T, 3);
optional ``frame_index`` (T,) and ``confidence`` (T,) (the detection score, ``boxes[..., 4]``). The
per-frame lists that ``detect_smpl_batched`` returns (``pose[t]`` of shape (people, 165)) are accepted
too: the first (most confident) person is taken; frames without a person are missing. NaN rows are
missing frames.

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

Axis legend: N detections, T frames.
"""
from __future__ import annotations

import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import roma
import torch

from m3t.body.model_files import ModelFileError, load_pickle_safely
from m3t.body.rotations import matrix_to_6d
from m3t.digest import chunks_digest, file_digest

REFLECT_X = np.diag([-1.0, 1.0, 1.0])


class TrackerFileError(ValueError):
    """A tracker output that cannot be used; the message names the file, the field and the fix."""


def _numpy_safe_globals() -> list:
    core = getattr(np, "_core", None) or np.core
    names = [(core.multiarray._reconstruct, "numpy.core.multiarray._reconstruct"),
             (core.multiarray.scalar, "numpy.core.multiarray.scalar")]
    allowed: list = [core.multiarray._reconstruct, core.multiarray.scalar, np.ndarray, np.dtype, *names]
    allowed += [getattr(np.dtypes, n) for n in dir(np.dtypes) if n.endswith("DType")]
    return allowed


def load_tracker_file(path: str | Path) -> dict[str, Any]:
    """A tracker output as a dict, without executing code from the file (see the module docstring)."""
    path = Path(path)
    if not path.exists():
        raise TrackerFileError(f"tracker output {path} does not exist")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                return {k: data[k] for k in data.files}
        if suffix in (".pt", ".pth", ".frame"):
            with torch.serialization.safe_globals(_numpy_safe_globals()):
                out = torch.load(path, map_location="cpu", weights_only=True)
        elif suffix == ".pkl":
            out = load_pickle_safely(path)
        else:
            raise TrackerFileError(f"{path}: unsupported tracker output type {suffix!r}; expected .npz, .pt, .frame or .pkl")
    except ModelFileError as exc:
        raise TrackerFileError(str(exc)) from exc
    except (pickle.UnpicklingError, OSError, RuntimeError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise TrackerFileError(f"{path}: refused or unreadable ({type(exc).__name__}: {exc}). Tracker outputs are "
                               "loaded without executing code; save plain tensors / numpy arrays.") from exc
    if not isinstance(out, dict):
        raise TrackerFileError(f"{path}: expected a dict of arrays, found {type(out).__name__}")
    return out


def _array(data: dict, key: str, path: Path, shape_tail: tuple[int, ...] | None = None) -> np.ndarray:
    if key not in data:
        raise TrackerFileError(f"{path}: field {key!r} missing; found {sorted(data)}")
    value = data[key]
    value = value.detach().cpu().numpy() if torch.is_tensor(value) else np.asarray(value)
    value = value.astype(np.float64) if value.dtype.kind in "fc" else value
    if shape_tail is not None and tuple(value.shape[-len(shape_tail):]) != shape_tail:
        raise TrackerFileError(f"{path}: field {key!r} has shape {value.shape}, expected (..., {', '.join(map(str, shape_tail))})")
    return value


def pytorch3d_6d_to_matrix(sixd: np.ndarray) -> np.ndarray:
    """PyTorch3D 6D (first two rows, Gram-Schmidt on rows) -> rotation matrices (..., 3, 3)."""
    rows = torch.as_tensor(sixd, dtype=torch.float64).reshape(*np.shape(sixd)[:-1], 2, 3)
    return roma.special_gramschmidt(rows.transpose(-1, -2)).transpose(-1, -2).numpy()


def rotmat_to_6d(rot: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> this project's 6D (..., 6)."""
    return matrix_to_6d(torch.as_tensor(rot, dtype=torch.float64)).numpy()


def axis_angle_to_matrix(aa: np.ndarray) -> np.ndarray:
    return roma.rotvec_to_rotmat(torch.as_tensor(aa, dtype=torch.float64)).numpy()


# ---------------------------------------------------------------------------------------------- WiLoR
@dataclass(frozen=True)
class HandEstimates:
    """One side's hands over frames (only frames where the hand was found)."""

    frame: np.ndarray  # (N,) int
    hand_pose: np.ndarray  # (N, 15, 3, 3) MANO rotations of this side
    global_orient: np.ndarray  # (N, 3, 3) camera-frame wrist orientation of this side
    betas: np.ndarray  # (N, 10)
    confidence: np.ndarray  # (N,)


def _mirror_matrices(rot: np.ndarray) -> np.ndarray:
    return REFLECT_X @ rot @ REFLECT_X


def read_wilor(path: str | Path) -> dict[str, HandEstimates]:
    """``{"left": ..., "right": ...}`` from a WiLoR output file (format in the module docstring)."""
    path = Path(path)
    data = load_tracker_file(path)
    if isinstance(data.get("pred_mano_params"), dict):
        data = {**data, **data["pred_mano_params"]}
    go = _array(data, "global_orient", path, (3, 3)).reshape(-1, 3, 3)
    hp = _array(data, "hand_pose", path, (3, 3)).reshape(go.shape[0], 15, 3, 3)
    betas = _array(data, "betas", path).reshape(go.shape[0], -1)
    frame = _array(data, "frame_index", path).astype(np.int64).reshape(-1)
    right = _array(data, "is_right", path).reshape(-1) > 0.5
    conf = _array(data, "confidence", path).reshape(-1) if "confidence" in data else np.ones(go.shape[0])
    if not (len(frame) == len(right) == len(conf) == go.shape[0]):
        raise TrackerFileError(f"{path}: fields disagree on the number of detections")
    out = {}
    for side, mask in (("right", right), ("left", ~right)):
        rows = np.flatnonzero(mask)
        best: dict[int, int] = {}
        for r in rows:  # the most confident detection per frame
            if frame[r] not in best or conf[r] > conf[best[frame[r]]]:
                best[int(frame[r])] = int(r)
        keep = np.array([best[f] for f in sorted(best)], dtype=np.int64)
        h, g = hp[keep], go[keep]
        if side == "left":  # WiLoR ran these as flipped right hands
            h, g = _mirror_matrices(h), _mirror_matrices(g)
        out[side] = HandEstimates(frame[keep], h, g, betas[keep], conf[keep])
    return out


# ------------------------------------------------------------------------------------------ Pixel3DMM
@dataclass(frozen=True)
class FaceEstimates:
    frame: np.ndarray  # (N,) int
    expression: np.ndarray  # (N, 100)
    eyelids: np.ndarray  # (N, 2)
    jaw: np.ndarray  # (N, 3, 3)
    neck: np.ndarray  # (N, 3, 3)
    head_rotation: np.ndarray  # (N, 3, 3) FLAME's R
    head_translation: np.ndarray  # (N, 3)
    shape: np.ndarray  # (300,) FLAME shape (the tracker's per-clip identity; median over frames)


def _frames_folder(folder: Path) -> Path:
    """Pixel3DMM's per-clip output folder -> its ``checkpoint`` subfolder, unless the frames lie directly in it."""
    sub = folder / "checkpoint"
    if folder.is_dir() and sub.is_dir() and not any(folder.glob("*.frame")):
        return sub
    return folder


def read_pixel3dmm(folder: str | Path) -> FaceEstimates:
    """Every ``*.frame`` file of a Pixel3DMM ``checkpoint`` folder, or of the clip's output folder holding it
    (format in the module docstring)."""
    folder = _frames_folder(Path(folder))
    files = sorted(folder.glob("*.frame")) if folder.is_dir() else [folder]
    if not files or not files[0].exists():
        raise TrackerFileError(f"{folder}: no Pixel3DMM '*.frame' files (expected <output>/checkpoint/00000.frame ...)")
    rows: dict[str, list] = {k: [] for k in ("frame", "exp", "eyelids", "jaw", "neck", "R", "t", "shape")}
    for f in files:
        data = load_tracker_file(f)
        flame = data.get("flame")
        if not isinstance(flame, dict):
            raise TrackerFileError(f"{f}: field 'flame' missing or not a dict; found {sorted(data)}")
        rows["frame"].append(int(np.asarray(data.get("frame_id", f.stem)).reshape(-1)[0]))
        rows["exp"].append(_array(flame, "exp", f).reshape(-1)[:100])
        rows["eyelids"].append(_array(flame, "eyelids", f, (2,)).reshape(2))
        for key in ("jaw", "neck", "R"):
            rows[key].append(_array(flame, key, f, (6,)).reshape(6) if key in flame else np.array([1.0, 0, 0, 0, 1, 0]))
        rows["t"].append(_array(flame, "t", f, (3,)).reshape(3) if "t" in flame else np.zeros(3))
        rows["shape"].append(_array(flame, "shape", f).reshape(-1))
    exp = np.stack(rows["exp"])
    if exp.shape[1] < 100:
        exp = np.pad(exp, ((0, 0), (0, 100 - exp.shape[1])))
    order = np.argsort(rows["frame"])
    return FaceEstimates(
        frame=np.asarray(rows["frame"], dtype=np.int64)[order],
        expression=exp[order],
        eyelids=np.stack(rows["eyelids"])[order],
        jaw=pytorch3d_6d_to_matrix(np.stack(rows["jaw"]))[order],
        neck=pytorch3d_6d_to_matrix(np.stack(rows["neck"]))[order],
        head_rotation=pytorch3d_6d_to_matrix(np.stack(rows["R"]))[order],
        head_translation=np.stack(rows["t"])[order],
        shape=np.median(np.stack(rows["shape"]), axis=0),
    )


# ------------------------------------------------------------------------------------------------ NLF
@dataclass(frozen=True)
class BodyEstimates:
    frame: np.ndarray  # (N,) int
    rotations: np.ndarray  # (N, 55, 3, 3) SMPL-X joint rotations (global orient first)
    betas: np.ndarray  # (N, 10)
    translation: np.ndarray  # (N, 3)
    confidence: np.ndarray  # (N,)


def read_nlf(path: str | Path) -> BodyEstimates:
    """NLF SMPL-X estimates of one signer (format in the module docstring)."""
    path = Path(path)
    data = load_tracker_file(path)
    if isinstance(data.get("pose"), (list, tuple)):  # per-frame lists straight from detect_smpl_batched
        frames, pose, betas, trans, conf = [], [], [], [], []
        for t, p in enumerate(data["pose"]):
            p = np.asarray(p.detach().cpu() if torch.is_tensor(p) else p, dtype=np.float64).reshape(-1, 165)
            if p.shape[0] == 0:
                continue
            frames.append(t)
            pose.append(p[0])
            betas.append(np.asarray(data["betas"][t], dtype=np.float64).reshape(-1, 10)[0])
            trans.append(np.asarray(data["trans"][t], dtype=np.float64).reshape(-1, 3)[0])
            boxes = data.get("boxes")
            conf.append(float(np.asarray(boxes[t]).reshape(-1, 5)[0, 4]) if boxes is not None else 1.0)
        pose_a, betas_a, trans_a = np.array(pose).reshape(-1, 165), np.array(betas).reshape(-1, 10), np.array(trans).reshape(-1, 3)
        frame_a, conf_a = np.array(frames, dtype=np.int64), np.array(conf)
    else:
        pose_a = _array(data, "pose", path, (165,)).reshape(-1, 165)
        betas_a = _array(data, "betas", path).reshape(pose_a.shape[0], -1)[:, :10]
        trans_a = _array(data, "trans", path, (3,)).reshape(-1, 3)
        frame_a = (_array(data, "frame_index", path).astype(np.int64).reshape(-1) if "frame_index" in data
                   else np.arange(pose_a.shape[0]))
        conf_a = _array(data, "confidence", path).reshape(-1) if "confidence" in data else np.ones(pose_a.shape[0])
        found = np.isfinite(pose_a).all(1) & np.isfinite(betas_a).all(1)
        pose_a, betas_a, trans_a, frame_a, conf_a = (a[found] for a in (pose_a, betas_a, trans_a, frame_a, conf_a))
    rot = axis_angle_to_matrix(pose_a.reshape(-1, 55, 3)) if len(pose_a) else np.zeros((0, 55, 3, 3))
    return BodyEstimates(frame_a, rot, betas_a, trans_a, conf_a)


# ---------------------------------------------------------------------------------- layout beside the media
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
        frames = checked(_frames_folder(p3), "pixel3dmm")
        for f in frames.glob("*.frame"):
            checked(f, "pixel3dmm")
        found["pixel3dmm"] = frames
    return TrackerOutputs(**found)
