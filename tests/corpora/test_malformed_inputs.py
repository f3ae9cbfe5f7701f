"""Malformed inputs of every adapter and reader end in a quarantine line or a clear error, never a traceback.

The case table is :data:`malformed_cases.CASES` (each case builds a published layout from :mod:`corpus_fixtures`
and breaks one thing); ``benchmarks/malformed_report.py`` writes the same table as markdown.
"""
from __future__ import annotations

import collections

import pytest
import torch
from malformed_cases import CASES, CLEAR, QUARANTINED, READ, classify


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("case", [
    pytest.param(c, id=c.id, marks=[pytest.mark.xfail(strict=True, reason=c.gap)] if c.gap else [])
    for c in CASES])
def test_malformed_input(case, tmp_path):
    outcome, message = classify(case, tmp_path)
    assert outcome == case.expect, f"{case.id} ({case.reader}, {case.input}): {outcome}: {message}"
    assert str(tmp_path) not in message  # the table shows <tmp>, the same on every machine


def test_the_table_covers_the_issue():
    """>= 30 cases over every reader the issue names, each with a unique id, and every broken kind of input."""
    assert len(CASES) >= 35 and len({c.id for c in CASES}) == len(CASES)
    readers = collections.Counter(c.reader.split()[0] for c in CASES)
    for reader in ("phoenix14t", "how2sign", "csl_daily", "nmfs_csl", "mead", "soke_smplx", "slt_pickle", "posefile",
                   "track", "NLF", "WiLoR", "Pixel3DMM", "read_shard", "read_token_shard", "read_checkpoint",
                   "load_params"):
        assert readers[reader], reader
    ids = " ".join(c.id for c in CASES)
    for kind in ("header", "separator", "non-utf8", "truncated", "nan", "wrong-shape", "wrong-dtype", "empty-text",
                 "unknown-language", "duplicate-id", "path-traversal", "symlink-out", "zero-frames", "one-frame",
                 "code-pickle", "all-nan", "fps-zero", "layout"):
        assert kind in ids, kind
    assert {c.expect for c in CASES} == {QUARANTINED, CLEAR, READ}
    assert all(c.file and c.reason for c in CASES if c.expect != READ)


def test_classify_tells_the_outcomes_apart(tmp_path):
    """The classifier itself: a silent return, an unnamed error and a quarantine missing the file are failures."""
    from malformed_cases import SILENT, TRACEBACK, Case, Listed

    def raise_(exc):
        raise exc

    silent = Case("s", "r", "i", lambda tmp: object(), CLEAR, "a.csv", "bad")
    assert classify(silent, tmp_path)[0] == SILENT
    unnamed = Case("u", "r", "i", lambda tmp: raise_(ValueError("could not convert string to float")), CLEAR,
                   "a.csv", "bad")
    assert classify(unnamed, tmp_path)[0] == TRACEBACK
    assert classify(Case("k", "r", "i", lambda tmp: raise_(ZeroDivisionError("a.csv bad")), CLEAR, "a.csv", "bad"),
                    tmp_path)[0] == TRACEBACK
    named = Case("n", "r", "i", lambda tmp: raise_(ValueError(f"{tmp}/a.csv line 2: bad header")), CLEAR, "a.csv",
                 "bad")
    assert classify(named, tmp_path) == (CLEAR, "ValueError: <tmp>/a.csv line 2: bad header")
    lost = Case("l", "r", "i", lambda tmp: Listed([("a.csv", 3, "bad row", None)], 4, 5), QUARANTINED, "a.csv", "bad",
                row=3)
    assert classify(lost, tmp_path)[0] == SILENT  # quarantined, but another clip went missing
    other_row = Case("o", "r", "i", lambda tmp: Listed([("a.csv", 4, "bad row", None)], 5, 5), QUARANTINED, "a.csv",
                     "bad", row=3)
    assert classify(other_row, tmp_path)[0] == SILENT
    assert classify(Case("q", "r", "i", lambda tmp: Listed([("a.csv", 3, "bad row", None)], 5, 5), QUARANTINED, "a.csv",
                         "bad", row=3), tmp_path)[0] == QUARANTINED
    other_clip = Case("c", "r", "i", lambda tmp: Listed([("a.csv", 3, "bad row", None)], 5, 5), QUARANTINED, "a.csv",
                      "bad", row=3, clip="clip-7")
    assert classify(other_clip, tmp_path)[0] == SILENT  # the entry does not name the clip it refused


def test_report_writes_the_table(tmp_path, monkeypatch):
    import importlib.util
    from pathlib import Path

    import malformed_cases

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "malformed_report.py"
    spec = importlib.util.spec_from_file_location("malformed_report", path)
    report = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(report)
    few = tuple(c for c in CASES if c.id in ("phoenix-wrong-header", "track-fps-zero", "params-bad-yaml"))
    monkeypatch.setattr(report, "CASES", few)
    assert malformed_cases.CASES is CASES
    code = report.main(["--out", str(tmp_path / "table.md")])
    text = (tmp_path / "table.md").read_text(encoding="utf-8")
    assert "| case | reader | input | outcome | message |" in text
    assert "| phoenix-wrong-header | phoenix14t |" in text and "| clear error |" in text
    assert "| params-bad-yaml | " in text and "TRACEBACK" not in text
    assert code == 0 and str(tmp_path) not in text.replace(str(tmp_path / "table.md"), "")
