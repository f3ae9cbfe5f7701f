"""Malformed inputs of every adapter and reader end in a quarantine line or a clear error, never a traceback.

The case table is :data:`malformed_cases.CASES` (each case builds a published layout from :mod:`corpus_fixtures`
and breaks one thing) plus :data:`hostile_cases.CASES` (files declaring more than they hold, bombs, wrong column
types, hostile headers); ``benchmarks/malformed_report.py`` writes the same table as markdown, with each case's
time and peak memory.
"""
from __future__ import annotations

import collections

import pytest
import torch
from hostile_cases import CASES as HOSTILE
from malformed_cases import CASES, CLEAR, QUARANTINED, READ, classify


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("case", [
    pytest.param(c, id=c.id, marks=[pytest.mark.xfail(strict=True, reason=c.gap)] if c.gap else [])
    for c in CASES + HOSTILE])
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


def test_the_hostile_table_covers_the_issue():
    """>= 25 hostile cases: bombs by declaration, compression and aliasing in every container the readers open
    (zip / npz / npy, torch checkpoints, HDF5, gzip and plain pickles, params.yaml), a wrong Arrow type in every
    column of both table formats, and hostile ``.pose`` headers; ids unique across both tables."""
    import malformed_cases

    from m3t.shards.schema import arrow_schema
    from m3t.shards.tokens import TokenInfo, token_schema

    assert len(HOSTILE) >= 25 and len({c.id for c in CASES + HOSTILE}) == len(CASES) + len(HOSTILE)
    ids = " ".join(c.id for c in HOSTILE)
    for kind in ("declares", "zip-bomb", "npz-bomb", "gzip-bomb", "fill-bomb", "compressed-bomb", "alias-bomb",
                 "forged", "pose-header", "wrong-type"):
        assert kind in ids, kind
    for reader in ("track", "load_model_arrays", "read_checkpoint", "NLF", "slt_pickle", "mead", "load_params",
                   "posefile", "read_shard", "read_token_shard", "read_image_rgb"):
        assert any(c.reader.startswith(reader) for c in HOSTILE), reader
    for name in arrow_schema(malformed_cases._layout()).names:
        assert f"shard-wrong-type-{name}" in ids, name
    for name in token_schema(TokenInfo({"body": 16, "face": 8}, 4, {})).names:
        assert f"tokens-wrong-type-{name}" in ids, name


@pytest.mark.parametrize("case", [c for c in HOSTILE if "wrong-type" not in c.id], ids=lambda c: c.id)
def test_a_hostile_file_is_refused_without_allocating_what_it_declares(case, tmp_path):
    """What a case declares is 64 MB to 400 GB; its refusal allocates under 48 MB (Python and numpy allocations,
    traced from after the input is written; the modules a reader imports are imported first, since importing them
    allocates tens of MB once)."""
    import tracemalloc

    import h5py  # noqa: F401
    import pose_format  # noqa: F401
    import pyarrow.parquet  # noqa: F401

    import m3t.config
    import m3t.corpora.base
    import m3t.shards.tokens
    import m3t.trackers.nlf_reader  # noqa: F401

    case.build(tmp_path)
    tracemalloc.start()
    try:
        outcome, message = classify(case, tmp_path, built=True)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert outcome == case.expect, message
    assert peak < 48 * 2**20, f"{case.id}: {peak / 2**20:.1f} MB traced"


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
    monkeypatch.setattr(report, "HOSTILE", tuple(c for c in HOSTILE if c.id == "track-npy-declares-4gb"))
    assert malformed_cases.CASES is CASES
    code = report.main(["--out", str(tmp_path / "table.md")])
    text = (tmp_path / "table.md").read_text(encoding="utf-8")
    assert "| case | reader | input | outcome | s | traced MB | RSS MB | message |" in text
    assert "| phoenix-wrong-header | phoenix14t |" in text and "| clear error |" in text
    assert "| params-bad-yaml | " in text and "TRACEBACK" not in text
    assert code == 0 and str(tmp_path) not in text.replace(str(tmp_path / "table.md"), "")
    row = next(line for line in text.splitlines() if line.startswith("| track-npy-declares-4gb |"))
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[3] == "clear error" and float(cells[4]) >= 0 and float(cells[5]) < 48  # declared: 4.3 GB
    assert "4 cases (4 clear error)" in text
