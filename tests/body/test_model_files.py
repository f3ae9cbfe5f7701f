"""The model-file readers of the body models (m3t.body.model_files): Python-2 and protocol-0/1 pickles with sparse regressors, the arrays and numbers they keep, what a reader cannot read named, and landmark vertices from face corners."""
from __future__ import annotations

import pickle

import numpy as np
import pytest
from corpus_fixtures import write_python2_pickle

from m3t.body.model_files import ModelFileError, load_model_arrays, load_pickle_safely


# ------------------------------------------------------------------------------------------------ model files
def test_python2_model_pickle_strings_are_read_as_latin1(tmp_path):
    """The pickle reads like FLAME 2020's ``generic_model.pkl``: a protocol-2 Python-2 pickle whose keys and array
    buffers are 8-bit strings. FLAME's readers (soubhiksanyal/FLAME_PyTorch ``flame.py``, Ribosome-rbx/PBNS
    ``preprocess.py`` for SMPL) load such files with ``pickle.load(f, encoding='latin1')``."""
    rng = np.random.default_rng(0)
    arrays = {"v_template": rng.normal(size=(5, 3)), "f": np.array([[0, 1, 2], [2, 3, 4]], dtype=np.uint32)}
    path = tmp_path / "generic_model.pkl"
    write_python2_pickle(path, {**arrays, "bs_style": "lbs", "author": "Ren\xe9e"}, "latin1")
    assert pickle.SHORT_BINSTRING + b"\x0av_template" in path.read_bytes()  # a Python 2 str, not unicode
    raw = load_pickle_safely(path)
    assert raw["bs_style"] == "lbs" and raw["author"] == "Ren\xe9e"  # 8-bit strings decoded as latin-1
    np.testing.assert_array_equal(raw["v_template"], arrays["v_template"])
    loaded = load_model_arrays(path, required=("v_template", "f"))
    assert sorted(loaded) == ["f", "v_template"]  # text entries are not arrays
    assert loaded["f"].dtype == np.uint32
    np.testing.assert_array_equal(loaded["f"], arrays["f"])
    with pytest.raises(ModelFileError, match=r"generic_model\.pkl lacks keys \['weights'\]"):
        load_model_arrays(path, required=("v_template", "weights"))


def test_model_file_reader_keeps_arrays_and_numbers_and_names_what_it_cannot_read(tmp_path):
    from scipy import sparse

    dense = np.array([[0.0, 0.5, 0.0], [0.25, 0.0, 0.75]])
    path = tmp_path / "model.pkl"
    with open(path, "wb") as fh:
        pickle.dump({"J_regressor": sparse.csr_matrix(dense), "nested": {"J": sparse.csc_matrix(dense)}, "scale": 2.5,
                     "ids": [1, 2, 3], "flag": True, "ragged": [[1], [2, 3]], "name": "x"}, fh, protocol=2)
    loaded = load_model_arrays(path)
    assert sorted(loaded) == ["J_regressor", "ids", "scale"]  # bools, ragged lists, text and dicts are no arrays
    np.testing.assert_array_equal(loaded["J_regressor"], dense)  # sparse -> dense
    assert loaded["scale"] == 2.5 and loaded["ids"].tolist() == [1, 2, 3]
    np.testing.assert_array_equal(load_pickle_safely(path)["nested"]["J"], dense)  # records inside dicts too
    coo = tmp_path / "coo.pkl"
    coo.write_bytes(pickle.dumps({"J_regressor": sparse.coo_matrix(dense)}, protocol=2))
    unsupported = r"coo\.pkl: key '<root>\.J_regressor' is a sparse matrix in an unsupported layout \('coo'\)"
    with pytest.raises(ModelFileError, match=unsupported):
        load_model_arrays(coo)
    listed = tmp_path / "list.pkl"
    listed.write_bytes(pickle.dumps([np.zeros(3)], protocol=2))
    with pytest.raises(ModelFileError, match=r"list\.pkl: expected a dict of arrays, found list"):
        load_model_arrays(listed)
    truncated = tmp_path / "truncated.pkl"
    truncated.write_bytes(path.read_bytes()[:40])
    with pytest.raises(ModelFileError, match=r"truncated\.pkl: pickle data was truncated; the file was not loaded"):
        load_model_arrays(truncated)
    (tmp_path / "empty.pkl").write_bytes(b"")
    with pytest.raises(ModelFileError, match=r"empty\.pkl: not a readable model pickle \(EOFError"):
        load_model_arrays(tmp_path / "empty.pkl")
    np.save(tmp_path / "ids.npy", np.arange(4))
    assert load_model_arrays(tmp_path / "ids.npy")["array"].tolist() == [0, 1, 2, 3]
    np.savez(tmp_path / "mixed.npz", v=np.ones(2), names=np.array([{"a": 1}], dtype=object))
    assert sorted(load_model_arrays(tmp_path / "mixed.npz")) == ["v"]  # object arrays are never unpickled
    with pytest.raises(ModelFileError, match=r"model\.obj: unsupported model file type '\.obj'"):
        (tmp_path / "model.obj").write_text("v 0 0 0\n")
        load_model_arrays(tmp_path / "model.obj")
    with pytest.raises(ModelFileError, match=r"model file .*absent\.npz does not exist"):
        load_model_arrays(tmp_path / "absent.npz")


# ------------------------------------------------------------------------------------------------ older model pickles
def test_protocol_0_and_1_pickles_with_sparse_regressors_keep_their_shape(tmp_path):
    """Pickle protocols 0 and 1 rebuild objects through ``copy_reg._reconstructor`` (what Python 2 wrote for
    them); a sparse regressor whose last rows / columns are empty keeps its stored shape (a vertex that no
    joint uses is still a column)."""
    from scipy import sparse

    dense = np.array([[0.0, 0.5, 0.0, 0.0], [0.25, 0.0, 0.75, 0.0], [0.0, 0.0, 0.0, 0.0]])  # last row, column empty
    model = {"J_regressor": sparse.csr_matrix(dense), "J_csc": sparse.csc_matrix(dense),
             "v_template": np.arange(6.0).reshape(2, 3), "parts": {"head", "neck"}, "fixed": frozenset({"jaw"})}
    for protocol in (0, 1):
        for python2_names in (True, False):  # copy_reg / __builtin__ (as Python 2 wrote) or copyreg / builtins
            path = tmp_path / f"model_p{protocol}_{python2_names}.pkl"
            path.write_bytes(pickle.dumps(model, protocol=protocol, fix_imports=python2_names))
            assert (b"copy_reg\n_reconstructor" if python2_names else b"copyreg\n_reconstructor") in path.read_bytes()
            loaded = load_model_arrays(path, required=("J_regressor", "v_template"))
            assert sorted(loaded) == ["J_csc", "J_regressor", "v_template"]
            for key in ("J_regressor", "J_csc"):
                assert loaded[key].shape == (3, 4), key
                np.testing.assert_array_equal(loaded[key], dense)
            np.testing.assert_array_equal(loaded["v_template"], np.arange(6.0).reshape(2, 3))
            raw = load_pickle_safely(path)
            assert raw["parts"] == {"head", "neck"} and raw["fixed"] == frozenset({"jaw"})
    import os

    evil = tmp_path / "evil.pkl"
    evil.write_bytes(pickle.dumps({"v_template": os.system}, protocol=2))
    with pytest.raises(ModelFileError, match=r"evil\.pkl: refused global (posix|nt)\.system: not an array or a known "
                                             r"model-file type; the file was not loaded"):
        load_model_arrays(evil)


def test_landmark_vertices_take_each_faces_corner_of_largest_weight():
    from m3t.body.smplfx_build import _landmark_vertices

    smplx = {"f": np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]]), "lmk_faces_idx": np.array([2, 0, 1]),
             "lmk_bary_coords": np.array([[0.8, 0.1, 0.1], [0.1, 0.1, 0.8], [0.2, 0.7, 0.1]])}
    assert _landmark_vertices(smplx).tolist() == [6, 2, 4]
    with pytest.raises(ModelFileError) as info:
        _landmark_vertices({"f": smplx["f"], "lmk_faces_idx": smplx["lmk_faces_idx"]})
    assert str(info.value) == ("the SMPL-X file lacks 'lmk_faces_idx' / 'lmk_bary_coords' (the landmark embedding); "
                               "use SMPLX_NEUTRAL.npz from the SMPL-X v1.1 download")


class _Declared:
    """Pickles as a call of ``func`` on ``args``: how a hostile file declares an array it does not hold."""

    def __init__(self, func, *args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


def test_arrays_a_file_declares_but_does_not_hold_are_refused_before_allocating(tmp_path):
    """A ~200-byte pickle calling ``numpy.ndarray((10**9, 12), float32)`` (48 GB uninitialised), an array
    reconstruction started at 10**9 elements, an object array (sized by its declared shape before its items are
    read) and a sparse matrix declaring 10**12 dense values: each refused at once with the file named, in a few
    MB; the arrays real pickles hold (any shape, C or Fortran order, protocol 2 or 4) still load."""
    import time
    import tracemalloc

    from scipy import sparse

    core = getattr(np, "_core", None) or np.core
    regressor = sparse.csr_matrix(np.eye(3))
    regressor._shape = (10**6, 10**6)  # what the file says; it holds three values
    cases = {"ndarray": (_Declared(np.ndarray, (10**9, 12), np.dtype("float32")), "numpy.ndarray called with a shape"),
             "reconstruct": (_Declared(core.multiarray._reconstruct, np.ndarray, (10**9,), b"b"),
                             r"reconstruction of numpy.ndarray with shape \(1000000000,\)"),
             "object": (np.array([1, None], dtype=object), "numpy object array"),
             "sparse": (regressor, r"declared shape \(1000000, 1000000\) would make 1000000000000 dense values")}
    for name, (value, message) in cases.items():
        path = tmp_path / f"{name}.pkl"
        path.write_bytes(pickle.dumps({"J_regressor": value}, protocol=2))
        assert path.stat().st_size < 1000
        tracemalloc.start()
        start = time.monotonic()
        with pytest.raises(ModelFileError, match=message) as err:
            load_model_arrays(path)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert str(path) in str(err.value) and time.monotonic() - start < 1.0 and peak < 5 * 2**20, name
    held = {"c": np.arange(24.0).reshape(2, 3, 4), "f": np.asfortranarray(np.ones((3, 2), np.float32)),
            "i": np.array([[1, 2]], np.int64), "u": np.array([7], np.uint32), "s": np.float64(2.5)}
    for protocol in (2, 4):
        path = tmp_path / f"held{protocol}.pkl"
        path.write_bytes(pickle.dumps(held, protocol=protocol))
        loaded = load_pickle_safely(path)
        for key, value in held.items():
            assert np.array_equal(loaded[key], value) and np.asarray(loaded[key]).dtype == np.asarray(value).dtype
