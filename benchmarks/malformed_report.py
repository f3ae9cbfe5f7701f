"""Malformed-input report: run every case of ``tests/malformed_cases.py`` and write the case -> outcome table.

Each case breaks one input of one adapter or reader (wrong header or separator, non-UTF-8 bytes, truncated
files, NaN / inf, wrong shapes or dtypes, empty text, unknown language, duplicate ids, paths leaving the corpus
root through ``..`` or a link, zero- and one-frame clips, pickles whose payload would run code) and records
whether the reader quarantined it (file + row + reason, the other clips listed), stopped with a clear error
(file or key + reason), read a legal edge case correctly, accepted it silently, or raised a traceback.

    python benchmarks/malformed_report.py [--out benchmarks/results/malformed_inputs.md]

Exits 1 when a case ends in another outcome than the one the table expects.
"""
from __future__ import annotations

import argparse
import collections
import sys
import sysconfig
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the case table and the fixture builders it uses live with the tests

from malformed_cases import CASES, classify  # noqa: E402


def cell(text: str, limit: int = 240) -> str:
    """``text`` as one markdown table cell: one line, pipes escaped, capped; this machine's folders written as
    ``<site-packages>`` and ``<repo>`` (``classify`` already wrote the case's temporary folder as ``<tmp>``), so the
    committed report names no path of the machine that wrote it."""
    text = " ".join(str(text).split()).replace("|", "\\|")
    for folder, name in ((sysconfig.get_paths()["purelib"], "<site-packages>"), (str(ROOT), "<repo>")):
        text = text.replace(folder, name)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "malformed_inputs.md")
    args = parser.parse_args(argv)
    rows, outcomes, unexpected = [], collections.Counter(), []
    for case in CASES:
        with tempfile.TemporaryDirectory() as tmp:
            outcome, message = classify(case, Path(tmp))
        outcomes[outcome] += 1
        mark = "" if outcome == case.expect else f" (expected {case.expect}{'; ' + case.gap if case.gap else ''})"
        if outcome != case.expect:
            unexpected.append(case.id)
        rows.append(f"| {case.id} | {case.reader} | {cell(case.input)} | {outcome}{mark} | {cell(message)} |")
    summary = ", ".join(f"{n} {k}" for k, n in sorted(outcomes.items()))
    lines = ["# Malformed inputs", "",
             f"{len(CASES)} cases ({summary}); written by `python benchmarks/malformed_report.py`, cases in "
             "`tests/malformed_cases.py`.", "",
             "| case | reader | input | outcome | message |", "|---|---|---|---|---|", *rows, ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines), encoding="utf-8")
    print(f"{len(CASES)} cases: {summary}; table in {args.out}")
    if unexpected:
        print(f"not as expected: {', '.join(unexpected)}")
    return 1 if unexpected else 0


if __name__ == "__main__":
    sys.exit(main())
