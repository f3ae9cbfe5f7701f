"""Loading licensed body-model files (SMPL-X, FLAME) without executing code from them.

- ``.npz``: read with ``allow_pickle=False``; keys holding pickled objects (SMPL-X's ``joint2num`` /
  ``part2num`` dicts) are skipped, never unpickled.
- ``.npy``: ``allow_pickle=False``.
- ``.pkl`` (SMPL v1, FLAME 2020 ``generic_model.pkl``): these are Python-2 pickles whose arrays are
  ``chumpy.ch.Ch`` objects and whose ``J_regressor`` is a ``scipy.sparse`` matrix. chumpy does not
  import on numpy 2, and a plain ``pickle.load`` would run whatever the file names. :class:`SafeModelUnpickler`
  resolves only an allow-list of globals (numpy array reconstruction, ``copyreg._reconstructor``) and
  maps every ``chumpy`` and ``scipy.sparse`` class to an inert record of its pickled state; records are then
  turned into plain arrays (a ``Ch`` keeps its stored value ``x``, a sparse matrix becomes dense). Any other
  global (``os.system``, ``builtins.eval``, ...) is refused with :class:`ModelFileError`.
"""
from __future__ import annotations

import codecs
import copyreg
import pickle
import struct
import zipfile
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from m3t.declared import DeclaredSizeError, load_npy, open_bounded, open_npz

CONVERSION_HINT = (
    "If this file cannot be read safely, convert it once in an environment that has chumpy "
    "(python<=3.10, numpy<1.24): load it with pickle (encoding='latin1'), turn every value into "
    "numpy.asarray(...) (sparse matrices: .toarray()) and save the dict with numpy.savez; then point params.yaml at the .npz."
)


class ModelFileError(ValueError):
    """A model file that is missing, malformed or unsafe; the message names the file and what to do."""


class _PickledRecord:
    """Inert stand-in for a chumpy / scipy.sparse object: keeps the pickled state, runs nothing."""

    kind = "record"
    args: tuple = ()
    state: Any = None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args = args
        self.state: Any = None

    def __setstate__(self, state: Any) -> None:
        self.state = state


class _ChumpyRecord(_PickledRecord):
    kind = "chumpy"


class _SparseRecord(_PickledRecord):
    kind = "sparse"


MAX_DENSE_VALUES = 2**28  # a sparse matrix made dense (SMPL-X's J_regressor: 55 x 10,475 = 576k values)


class _ArrayClass:
    """``numpy.ndarray`` as a pickle names it. A real array pickle only passes the class to ``_reconstruct``,
    which starts from an empty array and then fills it from the bytes the file holds; calling ``ndarray`` itself
    with a shape would allocate what the file merely declares (``ndarray((10**9, 12), float32)``: 48 GB of
    uninitialised memory from ~200 bytes), so that is refused."""

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        raise pickle.UnpicklingError("refused global numpy.ndarray called with a shape: an array of a size the file "
                                     "declares instead of holds")


def _reconstruct(subtype: Any, shape: Any, dtype: Any) -> np.ndarray:
    """numpy's array-pickle entry point, for plain arrays: the empty start array (shape ``(0,)``) that
    ``__setstate__`` then fills from the file's own bytes."""
    core = getattr(np, "_core", None) or np.core  # numpy 2 moved numpy.core to numpy._core
    if subtype is not _ArrayClass or not isinstance(shape, tuple) or int(np.prod(shape, dtype=np.int64)) > 1:
        what = "numpy.ndarray" if subtype is _ArrayClass else getattr(subtype, "__name__", "?")
        raise pickle.UnpicklingError(f"refused numpy array reconstruction of {what} with shape {shape!r}: not a "
                                     "plain array pickle")
    return core.multiarray._reconstruct(np.ndarray, shape, dtype)


def _dtype(*args: Any) -> np.dtype:
    """``numpy.dtype`` without object fields: an object array is sized by its declared shape before its items are
    read (so a short list can claim 10**9 slots), and no body-model or corpus array holds Python objects."""
    dtype = np.dtype(*args)
    if dtype.hasobject:
        raise pickle.UnpicklingError("refused numpy object array: model and corpus arrays hold numbers")
    return dtype


def _numpy_global(name: str) -> Any:
    core = getattr(np, "_core", None) or np.core  # numpy 2 moved numpy.core to numpy._core
    table = {
        "_reconstruct": _reconstruct,
        "scalar": core.multiarray.scalar,
        "ndarray": _ArrayClass,
        "dtype": _dtype,
    }
    return table.get(name)


# what a malformed pickle raises in the pure-Python unpickler (truncated: EOFError / struct.error; a stack or memo
# that the opcodes do not fill: IndexError / KeyError; nesting: RecursionError)
PICKLE_ERRORS = (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError, KeyError,
                 struct.error, RecursionError)


def _load_bytearray8(self) -> None:
    """``BYTEARRAY8`` read through the stream (whose reads refuse a length the file cannot hold) instead of into a
    ``bytearray`` of the declared length allocated first."""
    (size,) = struct.unpack("<Q", self.read(8))
    self.append(bytearray(self.read(size)))


class SafeModelUnpickler(pickle._Unpickler):
    """Allow-list unpickler for body-model pickles (see the module docstring).

    The pure-Python unpickler: the C one allocates each string or bytes object at the length the pickle declares
    before reading it (8 GB from a 20-byte file); this one asks the stream, which a reader opens with
    :func:`m3t.declared.open_bounded` so that a length the file cannot hold is refused first."""

    dispatch: ClassVar[dict] = {**pickle._Unpickler.dispatch, pickle.BYTEARRAY8[0]: _load_bytearray8}

    def __init__(self, file, **kwargs):
        super().__init__(file, **kwargs)
        readline = self._file_readline

        def whole_line() -> bytes:  # every line of a pickle ends in a newline: one without was cut off
            line = readline()
            if not line.endswith(b"\n"):
                raise pickle.UnpicklingError("pickle data was truncated")
            return line

        self._file_readline = whole_line

    def find_class(self, module: str, name: str) -> Any:
        if module in ("copy_reg", "copyreg") and name == "_reconstructor":
            return copyreg._reconstructor
        if module in ("__builtin__", "builtins") and name in ("object", "set", "frozenset"):
            return {"object": object, "set": set, "frozenset": frozenset}[name]
        if module == "_codecs" and name == "encode":  # bytes in protocol-2 pickles written by Python 3
            return codecs.encode
        if module in ("numpy", "numpy.core.multiarray", "numpy._core.multiarray"):
            found = _numpy_global(name)
            if found is not None:
                return found
        if module.startswith("numpy.dtypes") or (module == "numpy" and name.endswith("DType")):
            dtype_cls = getattr(np.dtypes, name, None)
            if dtype_cls is not None:
                return dtype_cls
        if module == "chumpy" or module.startswith("chumpy."):
            return type(f"chumpy_{name}", (_ChumpyRecord,), {})
        if module.startswith("scipy.sparse") and name.endswith("_matrix"):
            return type(f"sparse_{name}", (_SparseRecord,), {"fmt": name[:3]})
        raise pickle.UnpicklingError(f"refused global {module}.{name}: not an array or a known model-file type")


def _state_dict(record: _PickledRecord) -> dict:
    state = record.state
    if isinstance(state, tuple) and state and isinstance(state[-1], dict):
        state = state[-1]
    return state if isinstance(state, dict) else {}


def _to_array(value: Any, key: str, path: Path) -> Any:
    """Turn records into arrays, recursively; leave plain values alone."""
    if isinstance(value, _ChumpyRecord):
        state = _state_dict(value)
        x = state.get("x")
        if isinstance(x, _PickledRecord):
            return _to_array(x, key, path)
        if isinstance(x, np.ndarray):
            return x
        raise ModelFileError(
            f"{path}: key {key!r} is a chumpy expression ({type(value).__name__}) without a stored value; "
            f"it cannot be evaluated without chumpy. {CONVERSION_HINT}"
        )
    if isinstance(value, _SparseRecord):
        state = _state_dict(value)
        try:
            from scipy import sparse

            shape = tuple(int(n) for n in state.get("_shape") or state.get("shape"))
            maker = {"csc": sparse.csc_matrix, "csr": sparse.csr_matrix}.get(getattr(value, "fmt", ""))
            if maker is None or not {"data", "indices", "indptr"} <= set(state):
                raise KeyError(getattr(value, "fmt", "?"))
            if len(shape) != 2 or min(shape) < 0 or shape[0] * shape[1] > MAX_DENSE_VALUES:
                raise ValueError(f"declared shape {shape} would make {shape[0] * shape[1] if len(shape) == 2 else '?'} "
                                 f"dense values, more than a body model holds ({MAX_DENSE_VALUES:,})")
            return maker((state["data"], state["indices"], state["indptr"]), shape=shape).toarray()
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{path}: key {key!r} is a sparse matrix in an unsupported layout ({exc}). "
                                 f"{CONVERSION_HINT}") from exc
    if isinstance(value, dict):
        return {k: _to_array(v, f"{key}.{k}", path) for k, v in value.items()}
    return value


def load_pickle_safely(path: str | Path) -> Any:
    """Unpickle ``path`` with :class:`SafeModelUnpickler` (Python-2 pickles read as latin-1)."""
    path = Path(path)
    try:
        with open_bounded(path) as fh:
            raw = SafeModelUnpickler(fh, encoding="latin1").load()
    except pickle.UnpicklingError as exc:
        raise ModelFileError(f"{path}: {exc}; the file was not loaded. {CONVERSION_HINT}") from exc
    except PICKLE_ERRORS as exc:
        raise ModelFileError(f"{path}: not a readable model pickle ({type(exc).__name__}: {exc}). {CONVERSION_HINT}") from exc
    return _to_array(raw, "<root>", path)


def _numpy_arrays(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` (object arrays, pickled dicts, are skipped: never unpickled, not needed) or of an
    ``.npy`` (as ``array``), their declared sizes checked first."""
    if path.suffix.lower() == ".npy":
        return {"array": load_npy(path)}
    out = {}
    with open_npz(path) as data:
        for key in data.files:
            try:
                out[key] = data[key]
            except ValueError:  # an object array
                continue
    return out


def load_model_arrays(path: str | Path, required: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Arrays of a body-model file (``.npz`` / ``.pkl`` / ``.npy``) as a dict; checks ``required`` keys."""
    path = Path(path)
    if not path.exists():
        raise ModelFileError(f"model file {path} does not exist")
    suffix = path.suffix.lower()
    out: dict[str, np.ndarray] = {}
    if suffix in (".npz", ".npy"):
        try:
            out = _numpy_arrays(path)
        except (DeclaredSizeError, zipfile.BadZipFile, OSError, EOFError) as exc:
            raise ModelFileError(f"{path}: not a readable model file ({exc}). {CONVERSION_HINT}") from exc
    elif suffix == ".pkl":
        raw = load_pickle_safely(path)
        if not isinstance(raw, dict):
            raise ModelFileError(f"{path}: expected a dict of arrays, found {type(raw).__name__}")
        for key, value in raw.items():
            if isinstance(value, np.ndarray):
                out[key] = value
            elif isinstance(value, (int, float, list, tuple)) and not isinstance(value, bool):
                try:
                    out[key] = np.asarray(value)
                except ValueError:
                    continue
    else:
        raise ModelFileError(f"{path}: unsupported model file type {suffix!r}; expected .npz, .pkl or .npy")
    missing = [k for k in required if k not in out]
    if missing:
        raise ModelFileError(f"{path} lacks keys {missing}; found {sorted(out)}. Is this the right model file?")
    return out
