"""The codebook statistics (:mod:`m3t.metrics.codebook`): the token histogram's bars, one unit bar per code in rank
order.
"""
from __future__ import annotations

import numpy as np
import pytest


def test_token_histogram_draws_one_unit_bar_per_code_and_its_rank_order(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    from m3t.metrics.codebook import plot_token_histogram

    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # keep the figure to look at
    counts = np.array([3, 0, 7, 1, 0])
    path = plot_token_histogram(counts, "face (fsq, 5 codes)", tmp_path / "plots" / "face.png")
    assert path == tmp_path / "plots" / "face.png" and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (fig,) = figures
    by_index, by_rank = fig.axes
    for axis, heights in ((by_index, counts), (by_rank, [7, 3, 1, 0, 0])):
        bars = axis.patches
        assert [b.get_height() for b in bars] == list(heights)
        assert [b.get_x() + b.get_width() / 2 for b in bars] == pytest.approx(range(5))
        assert [b.get_width() for b in bars] == pytest.approx([1.0] * 5), "adjacent codes' bars must not overlap"
    assert by_index.get_xlabel() == "code index" and by_rank.get_xlabel() == "code rank"
    title = fig.get_suptitle()
    assert title.startswith("face (fsq, 5 codes)") and "60.0% used" in title and f"{np.std(counts):.1f}" in title
    monkeypatch.undo()
    plt.close(fig)
