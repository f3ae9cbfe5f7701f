"""Malformed-input report: run every case of ``tests/malformed_cases.py`` and write the case -> outcome table.

Each case breaks one input of one adapter or reader (wrong header or separator, non-UTF-8 bytes, truncated
files, NaN / inf, wrong shapes or dtypes, empty text, unknown language, duplicate ids, paths leaving the corpus
root through ``..`` or a link, zero- and one-frame clips, pickles whose payload would run code) and records
whether the reader quarantined it (file + row + reason, the other clips listed), stopped with a clear error
(file or key + reason), read a legal edge case correctly, accepted it silently, or raised a traceback. The hostile
cases of ``tests/hostile_cases.py`` (files declaring more than they hold, bombs by compression and by aliasing,
wrong column types, hostile headers) follow.

Each case runs in a child process forked from this one after the readers' modules are imported, so its figures
are its own: the wall time of the case (building its input and reading it), the peak of Python and numpy
allocations while it ran (``tracemalloc``: what a declared size would inflate, touched or not), and the growth of
the process's peak resident memory (Linux's ``VmHWM`` reset through ``/proc/self/clear_refs``; also what torch's
and HDF5's C code allocate).

    python benchmarks/malformed_report.py [--out benchmarks/results/malformed_inputs.md]

Exits 1 when a case ends in another outcome than the one the table expects.
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import sys
import sysconfig
import tempfile
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the case table and the fixture builders it uses live with the tests

from hostile_cases import CASES as HOSTILE  # noqa: E402
from malformed_cases import CASES, classify  # noqa: E402

# imported before any case runs, so that no case is charged for importing a reader's dependencies
READER_MODULES = ("torch", "h5py", "pose_format", "pyarrow.parquet", "m3t.config", "m3t.corpora.base",
                  "m3t.shards.tokens", "m3t.trackers.nlf_reader", "m3t.fitting.imports")


def cell(text: str, limit: int = 240) -> str:
    """``text`` as one markdown table cell: one line, pipes escaped, capped; this machine's folders written as
    ``<site-packages>`` and ``<repo>`` (``classify`` already wrote the case's temporary folder as ``<tmp>``), so the
    committed report names no path of the machine that wrote it."""
    text = " ".join(str(text).split()).replace("|", "\\|")
    for folder, name in ((sysconfig.get_paths()["purelib"], "<site-packages>"), (str(ROOT), "<repo>")):
        text = text.replace(folder, name)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _status_kb(field: str) -> int | None:
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _reset_peak() -> int | None:
    """Reset the resident peak (VmHWM) to the current resident size; that size in kB, None where unsupported."""
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as fh:
            fh.write("5")
    except OSError:
        return None
    return _status_kb("VmRSS")


def measured(case) -> dict:
    """Outcome, message, seconds, traced peak (MB) and resident-peak growth (MB, None where the platform cannot
    say) of one case, run in a temporary folder; a case with a ``build`` is measured from after it."""
    with tempfile.TemporaryDirectory() as tmp:
        if case.build is not None:  # the input is written before the measurement starts
            case.build(Path(tmp))
        resident = _reset_peak()
        tracemalloc.start()
        start = time.perf_counter()
        outcome, message = classify(case, Path(tmp), built=True)
        seconds = time.perf_counter() - start
        traced = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
        peak = _status_kb("VmHWM")
    growth = None if resident is None or peak is None else max(peak - resident, 0) / 1024
    return {"outcome": outcome, "message": message, "seconds": seconds, "traced_mb": traced, "rss_mb": growth}


def run_isolated(case) -> dict:
    """:func:`measured` in a forked child (its memory figures are its own), or here where fork is unavailable."""
    if not hasattr(os, "fork"):
        return measured(case)
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: measure, send, leave without running the parent's exit handlers
        try:
            result = measured(case)
        except BaseException as exc:  # noqa: BLE001 - anything the case raised past classify is reported
            result = {"outcome": "TRACEBACK", "message": f"{type(exc).__name__}: {exc}", "seconds": 0.0,
                      "traced_mb": 0.0, "rss_mb": None}
        with os.fdopen(write, "w", encoding="utf-8") as fh:
            json.dump(result, fh)
        os._exit(0)
    os.close(write)
    with os.fdopen(read, encoding="utf-8") as fh:
        text = fh.read()
    os.waitpid(pid, 0)
    return json.loads(text) if text else {"outcome": "TRACEBACK", "message": "the case's process died",
                                           "seconds": 0.0, "traced_mb": 0.0, "rss_mb": None}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "malformed_inputs.md")
    args = parser.parse_args(argv)
    for module in READER_MODULES:
        __import__(module)
    cases = CASES + HOSTILE
    rows, outcomes, unexpected = [], collections.Counter(), []
    for case in cases:
        got = run_isolated(case)
        outcome, message = got["outcome"], got["message"]
        outcomes[outcome] += 1
        mark = "" if outcome == case.expect else f" (expected {case.expect}{'; ' + case.gap if case.gap else ''})"
        if outcome != case.expect:
            unexpected.append(case.id)
        rss = "-" if got["rss_mb"] is None else f"{got['rss_mb']:.1f}"
        rows.append(f"| {case.id} | {case.reader} | {cell(case.input)} | {outcome}{mark} | {got['seconds']:.2f} | "
                    f"{got['traced_mb']:.1f} | {rss} | {cell(message)} |")
    summary = ", ".join(f"{n} {k}" for k, n in sorted(outcomes.items()))
    intro = (f"{len(cases)} cases ({summary}); written by `python benchmarks/malformed_report.py`, cases in "
             f"`tests/malformed_cases.py` (the first {len(CASES)}) and `tests/hostile_cases.py` (the last "
             f"{len(HOSTILE)}).")
    figures = ("Each case runs in its own forked process: *s* is its wall time, *traced MB* the peak of Python and "
               "numpy allocations, *RSS MB* the growth of the resident peak, all measured after the case's input "
               "is written (the hostile cases write it in a separate step; for the others the figures include "
               "writing it). A hostile case declares 64 MB to 400 GB; the figures are what refusing it cost.")
    lines = ["# Malformed inputs", "", intro, "", figures, "",
             "| case | reader | input | outcome | s | traced MB | RSS MB | message |",
             "|---|---|---|---|---|---|---|---|", *rows, ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines), encoding="utf-8")
    print(f"{len(cases)} cases: {summary}; table in {args.out}")
    if unexpected:
        print(f"not as expected: {', '.join(unexpected)}")
    return 1 if unexpected else 0


if __name__ == "__main__":
    sys.exit(main())
