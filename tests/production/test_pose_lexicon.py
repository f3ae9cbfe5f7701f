"""The lexicon baseline over a folder in spoken-to-signed's layout (``m3t.production.pose_lexicon``).

The table follows spoken-to-signed's lexicon (``gloss_to_pose/lookup/csv_lookup.py`` reads ``index.csv``; the
wheel's ``assets/fingerspelling_lexicon/data.csv``): columns ``path, spoken_language, signed_language, start, end,
words, glosses, priority``, e.g. the real row ``ase/fs-stse28e9ac023b0e29ca0a3acc12dc46540.pose,en,ase,0,2720,A,A,0``.
The ``.pose`` files are written here in pose-format's holistic layout with points chosen by hand.
"""
from __future__ import annotations

import numpy as np
import pytest

from m3t.metrics.pose_eval import signing_span
from m3t.production.pose_lexicon import LexiconError, PoseLexicon, write_holistic_pose
from m3t.scoring.poses import holistic_array

J = 33 + 468 + 21 + 21
HEADER = "path,spoken_language,signed_language,start,end,words,glosses,priority\n"


def sign(frames: int, shift: float, raised: slice | None = None) -> np.ndarray:
    """(T, J, 3) points in shoulder widths: shoulders at x = +-0.5 (width 1, midpoint 0), every other point at
    (shift, 1) (low: below the elbows at y = 0.5), wrists at y = 0 (above the elbows) in the ``raised`` frames."""
    points = np.zeros((frames, J, 3))
    points[:, :, 0], points[:, :, 1] = shift, 1.0
    points[:, 11], points[:, 12] = (0.5, 0.0, 0.0), (-0.5, 0.0, 0.0)  # LEFT_ / RIGHT_SHOULDER
    points[:, 13, 1] = points[:, 14, 1] = 0.5  # elbows
    if raised is not None:
        points[raised, 15, 1] = 0.0  # LEFT_WRIST above its elbow
    return points


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "ase").mkdir()
    write_holistic_pose(tmp_path / "ase" / "rain.pose", sign(20, 0.1, slice(8, 12)), 25.0)
    write_holistic_pose(tmp_path / "ase" / "rain-b.pose", sign(20, 0.9, slice(0, 20)), 25.0)
    write_holistic_pose(tmp_path / "ase" / "a.pose", sign(6, 0.2, slice(0, 6)), 25.0)
    write_holistic_pose(tmp_path / "ase" / "b.pose", sign(6, 0.3, slice(0, 6)), 25.0)
    (tmp_path / "index.csv").write_text(
        HEADER + "ase/rain-b.pose,en,ase,0,0,rain,RAIN,1\n"  # a later priority: not chosen
        "ase/rain.pose,en,ase,0,0,Rain,RAIN,0\n"
        "ase/a.pose,en,ase,0,0,A,A,0\n"
        "ase/b.pose,en,ase,0,0,B,B,0\n"
        "ase/a.pose,en,gsg,0,0,A,A,0\n", encoding="utf-8")
    return tmp_path


def test_words_by_priority_unknown_words_fingerspelled_and_the_rest_listed(folder):
    made = PoseLexicon(folder).lookup("Rain, abba! x", "ase", transition_frames=2)
    assert made.used[0] == ("rain", "ase/rain.pose")
    assert [w for w, _ in made.used[1:]] == ["a", "b", "b", "a"] and made.fingerspelled == ["abba"]
    assert made.missing == ["x"] and made.fps == 25.0
    # rain: raised frames 8..11, 5 frames either side -> 3..16 (14 frames); letters whole (6 each); 4 joins of 2
    assert made.frames == 14 + 4 * 6 + 4 * 2
    # each sign centred on its shoulders and in shoulder widths: the low points keep their x shift, y 1
    np.testing.assert_allclose(made.points[0, 0, :2], [0.1, 1.0], atol=1e-6)
    np.testing.assert_allclose(made.points[14 + 2, 0, :2], [0.2, 1.0], atol=1e-6)  # "a" after the first join
    np.testing.assert_allclose(made.points[14, 0, 0], 0.1 + (0.2 - 0.1) / 3, atol=1e-6)  # interpolated
    with pytest.raises(LexiconError, match=r"\(missing: \['x', 'abba'\]\)"):  # no letters asked for
        PoseLexicon(folder).lookup("x abba", "ase", fingerspelling="off")


def test_the_written_file_reads_back_as_holistic(folder, tmp_path):
    made = PoseLexicon(folder).lookup("rain", "ase", transition_frames=0)
    write_holistic_pose(tmp_path / "out.pose", made.points, made.fps)
    from m3t.corpora.posefile import read_pose

    back = holistic_array(read_pose(tmp_path / "out.pose"))
    assert back.shape == (made.frames, J, 3)
    np.testing.assert_allclose((back - [512, 512, 0]) / (1024 / 3), made.points, atol=1e-3)  # canvas scale, centre


def test_signing_span():
    """The lexicon trims with pose-evaluation's span (spoken-to-signed's rule), on these holistic points."""
    def span(points):
        return signing_span(points, ~np.isfinite(points))

    assert span(sign(30, 0.0, slice(10, 21))) == (5, 26)
    assert span(sign(30, 0.0, slice(2, 4))) == (0, 9)  # clipped at the first frame
    assert span(sign(30, 0.0)) == (0, 30)  # never raised: the whole clip
    hidden = sign(30, 0.0, slice(10, 21))
    hidden[25:, 15] = np.nan  # the wrist unseen from frame 25: the span ends there
    assert span(hidden) == (5, 25)


def test_refusals_name_the_table_row_and_column(folder, tmp_path):
    with pytest.raises(LexiconError, match="no entry of signed language 'bfi'; it holds \\['ase', 'gsg'\\]"):
        PoseLexicon(folder).lookup("rain", "bfi")
    with pytest.raises(LexiconError, match="no entry of 'gsg' for any word of 'rain'"):
        PoseLexicon(folder).lookup("rain", "gsg", fingerspelling="off")
    bad = tmp_path / "bad"
    bad.mkdir()
    with pytest.raises(LexiconError, match="no lexicon table; spoken-to-signed's layout has one of index.csv"):
        PoseLexicon(bad)
    (bad / "lexicon.csv").write_text(HEADER + "../../etc/passwd,en,ase,0,0,x,X,0\n", encoding="utf-8")
    with pytest.raises(LexiconError, match=r"lexicon.csv, row 2, column path: '../../etc/passwd' is not a file "
                                           r"inside"):
        PoseLexicon(bad)
    (bad / "lexicon.csv").write_text(HEADER + "a.pose,en,ase,soon,0,x,X,0\n", encoding="utf-8")
    with pytest.raises(LexiconError, match="row 2, column start: 'soon' is not a number"):
        PoseLexicon(bad)
    (bad / "lexicon.csv").write_text("file,words\na.pose,x\n", encoding="utf-8")
    with pytest.raises(LexiconError, match=r"columns \['path', 'signed_language'\] missing"):
        PoseLexicon(bad)
    (bad / "lexicon.csv").write_text(HEADER + "gone.pose,en,ase,0,0,x,X,0\n", encoding="utf-8")
    with pytest.raises(LexiconError, match="row 2: .*gone.pose not found"):
        PoseLexicon(bad).lookup("x", "ase")
