"""The shared reader machinery of the corpora (:mod:`m3t.corpora.base`, :mod:`~m3t.corpora.listing`,
:mod:`~m3t.corpora.annotation_files`, :mod:`~m3t.corpora.splits`): what a missing or unreadable pickle's error
names, every field of a quarantine record, media paths checked against the resolved root (links leaving it refused
with the fix), how text files split into lines and what their errors name, the media kind a clip's extra starts
with, Python-2 corpus pickles, model-file classes refused, split fractions and unknown corpus names. Written to pin
behaviours that mutation testing found unchecked.
"""
from __future__ import annotations

import os
import pickle
from pathlib import Path

import corpus_fixtures as fx
import numpy as np
import pytest

from m3t.corpora.annotation_files import load_data_pickle, read_lines
from m3t.corpora.base import CORPORA, adapter_class
from m3t.corpora.listing import (
    Collector,
    CorpusError,
    Quarantined,
    media_path_problem,
    with_kind,
)
from m3t.corpora.phoenix14t import Phoenix14TCorpus
from m3t.corpora.splits import check_fractions


# ----------------------------------------------------------------------------------------- safe pickles
def test_missing_pickle_error_names_the_file_and_what_to_check(tmp_path):
    path = tmp_path / "train" / "clip.pkl"
    with pytest.raises(CorpusError) as err:
        load_data_pickle(path, allow_numpy=True)
    assert str(path) in str(err.value) and "not found" in str(err.value) and "corpus root" in str(err.value)


def test_unreadable_pickle_error_names_the_file(tmp_path):
    path = tmp_path / "frame.pkl"
    path.write_bytes(b"not a pickle at all")
    with pytest.raises(CorpusError, match="not a readable pickle") as err:
        load_data_pickle(path, allow_numpy=True)
    assert str(path) in str(err.value)
    with open(path, "wb") as fh:
        pickle.dump({"a": np.zeros(2, np.float32)}, fh)
    with pytest.raises(CorpusError, match="numpy.*refused") as err:
        load_data_pickle(path, allow_numpy=False)
    assert str(path) in str(err.value) and "Re-save it" in str(err.value)
    assert set(load_data_pickle(path, allow_numpy=True)) == {"a"}


# ----------------------------------------------------------------------------------------- shared reader pieces
def test_quarantine_record_names_files_inside_the_root_relatively_and_others_in_full(tmp_path):
    out = Collector(tmp_path / "corpus")
    out.quarantine(tmp_path / "corpus" / "lists" / "train.txt", 4, "clip-4", "missing media")
    elsewhere = tmp_path / "shared" / "annotations.csv"
    out.quarantine(elsewhere, 2, None, "empty name")
    assert out.listing().quarantined == (Quarantined("lists/train.txt", 4, "clip-4", "missing media"),
                                         Quarantined(str(elsewhere), 2, None, "empty name"))
    assert out.listing().clips == ()


def test_media_leaving_the_root_through_a_link_is_refused_with_the_fix(tmp_path):
    root, outside = tmp_path / "corpus", tmp_path / "elsewhere"
    (outside / "clip").mkdir(parents=True)
    root.mkdir()
    (root / "inside").mkdir()
    (root / "link").symlink_to(outside, target_is_directory=True)
    reason = media_path_problem(root, "link/clip/0.png")
    assert reason.startswith("unsafe media path: 'link/clip/0.png' resolves outside the corpus root")
    assert str(outside.resolve() / "clip" / "0.png") in reason
    assert reason.endswith("through a symbolic link; move the media under the root, or point the root at a folder "
                           "that holds it")
    assert media_path_problem(root, "inside/0.png") is None
    out = Collector(root)
    assert out.media_problem("link/clip/0.png") == reason and out.media_problem("inside/0.png") is None


def test_read_lines_splits_at_newlines_only_and_drops_one_final_newline(tmp_path):
    path = tmp_path / "list.txt"
    cases = {b"": [], b"a": ["a"], b"a\n": ["a"], b"a\n\n": ["a", ""], b"a\n\nb": ["a", "", "b"],
             b"\xef\xbb\xbfa\r\nb\r\n": ["a", "b"], "x\u2028y\u0085z\nw\n".encode(): ["x\u2028y\u0085z", "w"],
             b"\n": [""]}
    for data, expected in cases.items():
        path.write_bytes(data)
        assert read_lines(path, "hint") == expected, data


def test_read_lines_errors_name_the_file_the_line_the_bytes_and_the_fix(tmp_path):
    path = tmp_path / "split_1.txt"
    with pytest.raises(CorpusError) as err:
        read_lines(path, "Point the root at the corpus.")
    assert str(err.value) == f"{path} not found. Point the root at the corpus."
    path.write_bytes(b"\xef\xbb\xbfname|split\nS1|tr\xe9in\n")  # one Latin-1 byte on line 2
    with pytest.raises(CorpusError) as err:
        read_lines(path, "Point the root at the corpus.")
    message = str(err.value)
    assert message.startswith(f"{path} line 2 (byte 19): not UTF-8 text (")
    bad = repr(b"\xe9in\n")  # the first bad byte and the three after it
    assert f"{bad}); re-save the file as UTF-8. Point the root at the corpus." in message


def test_media_paths_are_checked_against_the_resolved_root_the_caller_gives(tmp_path):
    real = tmp_path / "corpus"
    (real / "clips").mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    os.symlink(tmp_path / "elsewhere", real / "out")
    unresolved = Path("not-a-folder-here")  # its own resolve() would accept every name
    assert media_path_problem(unresolved, "clips/a.mp4", real.resolve()) is None
    problem = media_path_problem(unresolved, "out/a.mp4", real.resolve())
    assert problem.startswith("unsafe media path: 'out/a.mp4' resolves outside the corpus root (to ")
    assert media_path_problem(real, "out/a.mp4") == problem


def test_clip_extra_starts_with_the_media_kind_and_an_unknown_kind_is_named():
    assert with_kind("pose", clip_type="letter", frames=12, gloss=None) == (
        ("media_kind", "pose"), ("clip_type", "letter"), ("frames", "12"))
    assert with_kind("synthetic") == (("media_kind", "synthetic"),)
    with pytest.raises(ValueError) as err:
        with_kind("audio", start_s=1.0)
    assert str(err.value) == ("media kind 'audio' unknown; expected one of video, frames, pose, smplx_params, "
                              "flame_params, keypoints, spelled, synthetic")


def test_python2_corpus_pickles_decode_text_as_utf8_and_array_buffers_as_latin1(tmp_path):
    """Without numpy, 8-bit strings are text (UTF-8: a Chinese gloss survives); with numpy, they are decoded as
    latin-1 so that an array's raw buffer (any byte values) rebuilds the array exactly (``numpy.load``'s
    documentation names ``encoding='latin1'`` as the one that reads Python 2 pickles holding numpy arrays)."""
    path = tmp_path / "info.pkl"
    fx.write_python2_pickle(path, {"name": "S000000_P0000_T00", "label_word": ["谢谢", "你好"]}, "utf-8")
    assert pickle.SHORT_BINSTRING + b"\x04name" in path.read_bytes()  # a Python 2 str, not unicode
    assert load_data_pickle(path, allow_numpy=False) == {"name": "S000000_P0000_T00", "label_word": ["谢谢", "你好"]}

    array = np.array([[0.5, -1.25, 3.0], [1e-3, 255.0, -7.5]], np.float32)  # buffer bytes above 0x7f
    assert max(array.tobytes()) > 0x7F
    fx.write_python2_pickle(path, {"sign": array}, "utf-8")
    loaded = load_data_pickle(path, allow_numpy=True)
    assert loaded["sign"].dtype == np.float32
    np.testing.assert_array_equal(loaded["sign"], array)
    with pytest.raises(CorpusError) as err:
        load_data_pickle(path, allow_numpy=False)
    message = str(err.value)
    assert message.startswith(f"{path}: the pickle references numpy.")
    assert "a non-data class, and was refused" in message
    assert "Re-save it holding only builtin containers, numbers, strings." in message


@pytest.mark.parametrize("module, name", [("chumpy.ch", "Ch"), ("scipy.sparse._csr", "csr_matrix"),
                                          ("torch._utils", "_rebuild_tensor_v2")])
def test_corpus_pickles_refuse_model_file_classes_naming_the_class_and_the_file(tmp_path, module, name):
    """Body-model files may hold chumpy / scipy objects (read as inert records there); a corpus file that
    references them, in a submodule too, is refused before anything is built."""
    path = tmp_path / "clip.pkl"
    path.write_bytes(b"\x80\x02}q\x00X\x01\x00\x00\x00xq\x01c" + f"{module}\n{name}\n".encode() + b")Rq\x02s.")
    for allow_numpy in (True, False):
        with pytest.raises(CorpusError) as err:
            load_data_pickle(path, allow_numpy=allow_numpy)
        message = str(err.value)
        assert message.startswith(f"{path}: the pickle references {module}.{name}, a non-data class, and was "
                                  "refused (nothing was run).")
        assert ("torch tensors are refused" in message) == (module == "torch._utils")


def test_fractions_may_leave_a_split_empty_but_must_be_three_non_negative_summing_to_one():
    for fractions in ((1.0, 0.0, 0.0), (0.9, 0.1, 0.0), (0.0, 0.5, 0.5), (0.8, 0.1, 0.1)):
        check_fractions(fractions, "corpora.x.split_fractions")
    for bad in ((0.8, 0.3, -0.1), (0.8, 0.1), (0.5, 0.3, 0.1), (0.25, 0.25, 0.25, 0.25)):
        with pytest.raises(ValueError) as err:
            check_fractions(bad, "corpora.x.split_fractions")
        assert str(err.value) == ("option corpora.x.split_fractions: expected three non-negative train/dev/test "
                                  f"fractions summing to 1, got {bad}")


def test_an_unknown_corpus_name_is_refused_listing_the_known_ones():
    with pytest.raises(ValueError) as err:
        adapter_class("phoenix")
    assert str(err.value) == f"corpus 'phoenix' unknown; expected one of {', '.join(CORPORA)}"
    assert "phoenix14t, " in str(err.value) and adapter_class("phoenix14t") is Phoenix14TCorpus
