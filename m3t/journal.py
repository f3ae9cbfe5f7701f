"""The one resume mechanic of long evaluations: per-clip results appended to a journal as they are made, so a
killed run continues where it stopped and still writes the outputs an uninterrupted run writes, byte for byte.

A journal is a JSON-lines file beside the run's outputs. Its first line names the run (``{"journal": key}``: a
digest of everything the results depend on); every later line is one finished unit of work (a run of scored
clips, a block of back-translated sentences) under a section name::

    {"journal": "3f2a..."}
    {"section": "dtw", "rows": [{"clip_id": "c1", ...}, ...]}

A unit is appended in one ``write`` and flushed to disk before the run goes on, so a kill loses at most the
unit in progress; a torn last line (the kill landed inside the write) is dropped when the journal is opened.
A journal of another key (the inputs changed) is started afresh. Python floats survive the JSON round trip
exactly (``repr``), so results read back are the values computed. The run removes its journal once its outputs
are written (:meth:`Journal.finish`).
"""
from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from m3t.atomic import write_text


class Journal:
    """Finished rows of one run by section and clip id, read from ``path`` when it holds the same ``key``."""

    def __init__(self, path: str | os.PathLike, key: str):
        self.path, self.key = Path(path), key
        self.rows: dict[str, dict[str, dict[str, Any]]] = {}
        lines = self._read()
        if lines is None:  # absent, another run's, or unreadable: start afresh
            self.path.parent.mkdir(parents=True, exist_ok=True)
            write_text(self.path, json.dumps({"journal": key}) + "\n")
            return
        for entry in lines:
            section = self.rows.setdefault(entry["section"], {})
            for row in entry["rows"]:
                section[row["clip_id"]] = row
        # rewrite without a torn tail, so that the next append starts on a line of its own
        write_text(self.path, "".join(json.dumps(e) + "\n" for e in [{"journal": key}, *lines]))

    def _read(self) -> list[dict] | None:
        """The finished units of this key's journal (None: absent, unreadable or another key's). What follows
        the last newline is a torn line and is dropped, as is everything from a damaged line on."""
        if not self.path.is_file():
            return None
        complete = self.path.read_text(encoding="utf-8", errors="replace").split("\n")[:-1]
        try:
            if not complete or json.loads(complete[0]) != {"journal": self.key}:
                return None
        except json.JSONDecodeError:
            return None
        entries = []
        for line in complete[1:]:
            try:
                entry = json.loads(line)
            except json.JSONDecodeError:
                break
            if not isinstance(entry, dict) or not isinstance(entry.get("rows"), list) or "section" not in entry:
                break
            entries.append(entry)
        return entries

    def done(self, section: str) -> dict[str, dict[str, Any]]:
        """The finished rows of ``section`` by clip id."""
        return self.rows.get(section, {})

    def add(self, section: str, rows: Iterable[dict[str, Any]]) -> None:
        """Append one finished unit of ``section`` (each row has its ``clip_id``) and flush it to disk."""
        rows = list(rows)
        if not rows:
            return
        with open(self.path, "a", encoding="utf-8") as fh:
            fh.write(json.dumps({"section": section, "rows": rows}) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        done = self.rows.setdefault(section, {})
        for row in rows:
            done[row["clip_id"]] = row

    def finish(self) -> None:
        """The run's outputs are written: the journal is no longer needed."""
        self.path.unlink(missing_ok=True)
