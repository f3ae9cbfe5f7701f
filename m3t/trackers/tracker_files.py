"""Tracker output files read without executing code from them, and the field checks the readers share.

Loading never executes code from a file: ``.npz`` / ``.npy`` with ``allow_pickle=False``; torch files
(``.pt``, ``.pth``, ``.frame``) with ``torch.load(weights_only=True)`` and only numpy's array / dtype
reconstruction allow-listed; ``.pkl`` with :class:`m3t.body.model_files.SafeModelUnpickler`. The readers of
each tracker (:mod:`m3t.trackers.nlf_reader`, :mod:`m3t.trackers.wilor_reader`,
:mod:`m3t.trackers.pixel3dmm_reader`) build on :func:`load_tracker_file` and :func:`tracker_array`.
"""
from __future__ import annotations

import pickle
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from m3t.body.model_files import ModelFileError, load_pickle_safely
from m3t.body.rotations import matrix_to_6d
from m3t.declared import check_zip, open_npz


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
            with open_npz(path) as data:
                return {k: data[k] for k in data.files}
        if suffix in (".pt", ".pth", ".frame"):
            check_zip(path)  # torch's reader allocates each record's declared size
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


def tracker_array(data: dict, key: str, path: Path, shape_tail: tuple[int, ...] | None = None) -> np.ndarray:
    """Field ``key`` of a loaded tracker output as numpy (floats as float64), its trailing shape checked."""
    if key not in data:
        raise TrackerFileError(f"{path}: field {key!r} missing; found {sorted(data)}")
    value = data[key]
    value = value.detach().cpu().numpy() if torch.is_tensor(value) else np.asarray(value)
    value = value.astype(np.float64) if value.dtype.kind in "fc" else value
    if shape_tail is not None and tuple(value.shape[-len(shape_tail):]) != shape_tail:
        raise TrackerFileError(f"{path}: field {key!r} has shape {value.shape}, expected (..., {', '.join(map(str, shape_tail))})")
    return value


def rotmat_to_6d(rot: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> this project's 6D (..., 6)."""
    return matrix_to_6d(torch.as_tensor(rot, dtype=torch.float64)).numpy()
