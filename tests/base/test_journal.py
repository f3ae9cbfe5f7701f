"""The resume journal of long evaluations (m3t/journal.py): finished units survive a kill, a torn last line is
dropped, another run's journal is started afresh, floats come back exactly."""
from __future__ import annotations

import json
import math

from m3t.journal import Journal


def test_rows_come_back_by_section_and_clip_with_exact_floats(tmp_path):
    path = tmp_path / "out" / ".run.journal"
    first = Journal(path, "k1")
    assert first.done("dtw") == {} and path.read_text() == '{"journal": "k1"}\n'
    first.add("dtw", [{"clip_id": "a", "v": 0.1 + 0.2}, {"clip_id": "b", "v": float("nan")}])
    first.add("bt", [{"clip_id": "a", "hypothesis": "the cat"}])
    first.add("bt", [])  # nothing finished: nothing written
    again = Journal(path, "k1")
    assert again.done("dtw")["a"]["v"] == 0.1 + 0.2  # the computed value, bit for bit (repr round trip)
    assert math.isnan(again.done("dtw")["b"]["v"])
    assert again.done("bt") == {"a": {"clip_id": "a", "hypothesis": "the cat"}}
    assert len(path.read_text().splitlines()) == 3


def test_a_torn_last_line_is_dropped_and_appends_start_on_a_line_of_their_own(tmp_path):
    path = tmp_path / ".run.journal"
    journal = Journal(path, "k")
    journal.add("dtw", [{"clip_id": "a", "v": 1.0}])
    with open(path, "a") as fh:  # a kill inside the write of the second unit
        fh.write('{"section": "dtw", "rows": [{"clip_id": "b", "v"')
    resumed = Journal(path, "k")
    assert sorted(resumed.done("dtw")) == ["a"]
    resumed.add("dtw", [{"clip_id": "b", "v": 2.0}])
    assert sorted(Journal(path, "k").done("dtw")) == ["a", "b"]
    assert all(json.loads(line) for line in path.read_text().splitlines())


def test_another_runs_or_a_damaged_journal_starts_afresh_and_finish_removes_it(tmp_path):
    path = tmp_path / ".run.journal"
    Journal(path, "old").add("dtw", [{"clip_id": "a", "v": 1.0}])
    assert Journal(path, "new").done("dtw") == {}, "the inputs changed: nothing of the old run is reused"
    path.write_text("not json\n")
    assert Journal(path, "new").done("dtw") == {}
    journal = Journal(path, "new")
    journal.add("dtw", [{"clip_id": "a", "v": 1.0}])
    with open(path, "a") as fh:  # a damaged line in the middle: what came before it is kept
        fh.write('["not a unit"]\n{"section": "dtw", "rows": [{"clip_id": "c", "v": 3.0}]}\n')
    assert sorted(Journal(path, "new").done("dtw")) == ["a"]
    journal.finish()
    assert not path.exists()
    journal.finish()  # twice: nothing to remove
