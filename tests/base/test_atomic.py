"""Swapping a finished folder in: a reader sees the old folder or the new one, and nothing is left beside it."""
from __future__ import annotations

from m3t.atomic import replace_dir


def _folder(path, text):
    path.mkdir()
    (path / "index.html").write_text(text)
    return path


def test_replace_dir_swaps_the_new_folder_in_and_clears_a_killed_swaps_leftover(tmp_path):
    dest = tmp_path / "site"
    assert replace_dir(_folder(tmp_path / "new1", "one"), dest) == dest  # no previous folder
    assert (dest / "index.html").read_text() == "one"
    _folder(tmp_path / ".site.old", "a swap killed before removing the old folder")
    replace_dir(_folder(tmp_path / "new2", "two"), dest)
    assert (dest / "index.html").read_text() == "two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["site"]
