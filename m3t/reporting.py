"""Text for reports: numbers as table cells, Markdown tables, rows as CSV text.

Every table the stages write and the CLI, dashboard and docs print builds its cells and lines with these, so a
missing value reads the same everywhere and a file's bytes depend only on its rows.
"""
from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Mapping, Sequence

MISSING = "-"


def fixed(value: float | None, digits: int, missing: str = MISSING) -> str:
    """``value`` with ``digits`` decimals; ``missing`` when it is None or NaN (infinity prints as ``inf``)."""
    return missing if value is None or math.isnan(value) else f"{value:.{digits}f}"


def significant(value: object, digits: int = 3, whole_from: float | None = None) -> str:
    """``value`` with ``digits`` significant digits, written whole (no decimals) from ``abs(value) >= whole_from``
    (default ``10 ** digits``) up; "-" when it is None, a string, NaN or infinite."""
    if value is None or isinstance(value, str) or not math.isfinite(float(value)):
        return MISSING
    value = float(value)
    if abs(value) >= (10 ** digits if whole_from is None else whole_from):
        return f"{value:.0f}"
    return f"{value:.{digits}g}"


def markdown_table(header: Sequence[object], rows: Iterable[Sequence[object]], escape: bool = False) -> str:
    """A GitHub-flavoured Markdown table: the header line, the ``|---|`` separator, a line per row, joined by
    newlines with none at the end. Cells are ``str(value)``; with ``escape``, a ``|`` inside a cell becomes
    ``\\|`` and a newline a space, so any text stays in its cell."""
    def cell(value: object) -> str:
        text = str(value)
        return text.replace("|", "\\|").replace("\n", " ") if escape else text

    lines = ["| " + " | ".join(cell(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def csv_text(rows: Iterable[Mapping[str, object]], fieldnames: Sequence[str]) -> str:
    """``rows`` under a header of ``fieldnames`` as :class:`csv.DictWriter` writes them, lines ending in ``\\n``:
    a key the row lacks or a None is an empty cell, a float its ``str`` (``nan`` included); a key outside
    ``fieldnames`` raises ValueError."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=fieldnames, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()


def frame_csv(rows: Sequence[Mapping[str, object]]) -> str:
    """``rows`` as pandas writes them (``DataFrame(rows).to_csv(index=False)``): a column per key in order of first
    appearance, None and NaN empty, integers in a column that also holds floats or holes written as floats
    (``1.0``). For per-clip files that are read back with pandas."""
    import pandas as pd

    buffer = io.StringIO()
    pd.DataFrame(rows).to_csv(buffer, index=False)
    return buffer.getvalue()
