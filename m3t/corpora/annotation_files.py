"""Reading a corpus's annotation files safely: UTF-8 text lines, headers, files looked up in several places, and
pickles through an allow-list unpickler that admits data only (builtin containers, optionally numpy arrays).

Every problem with a whole file raises :class:`~m3t.corpora.listing.CorpusError` naming the file, what was
expected and what to do.
"""
from __future__ import annotations

import codecs
import csv
import io
import pickle
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from m3t.body.model_files import PICKLE_ERRORS, SafeModelUnpickler
from m3t.corpora.listing import Collector, CorpusError
from m3t.declared import open_bounded


# ----------------------------------------------------------------------------------------- text files
def read_lines(path: Path, hint: str) -> list[str]:
    """Lines of a UTF-8 text file (BOM tolerated); ``CorpusError`` with ``hint`` when missing or undecodable.

    Lines end at ``\\n`` only (a ``\\r`` before it is dropped): ``str.splitlines`` would also split at U+2028 or
    U+0085 inside a sentence and shift every later row number. The error for undecodable bytes names the 1-based
    line and the file's byte offset of the first bad byte, so a single Latin-1 row can be found and fixed.
    """
    if not path.is_file():
        raise CorpusError(f"{path} not found. {hint}")
    data = path.read_bytes()
    start = len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0
    try:
        lines = data[start:].decode("utf-8").split("\n")
        if lines[-1] == "":
            lines.pop()  # the final newline ends the last row; it does not start another
        return [line[:-1] if line.endswith("\r") else line for line in lines]
    except UnicodeDecodeError as exc:
        offset = start + exc.start
        line = data[:offset].count(b"\n") + 1
        raise CorpusError(f"{path} line {line} (byte {offset}): not UTF-8 text ({exc.reason}: "
                          f"{data[offset:offset + 4]!r}); re-save the file as UTF-8. {hint}") from exc


def check_header(path: Path, lines: list[str], expected: str, hint: str) -> None:
    """Raise ``CorpusError`` unless line 1 is exactly ``expected`` (trailing whitespace ignored)."""
    found = lines[0].rstrip() if lines else "<empty file>"
    if found != expected:
        raise CorpusError(f"{path} line 1: header is {found!r}; expected exactly {expected!r}. {hint}")


def find_file(name: str, places: list[Path], hint: str) -> Path:
    """The first ``place / name`` that exists; ``CorpusError`` listing every place looked in otherwise."""
    for place in places:
        if (place / name).is_file():
            return place / name
    looked = ", ".join(str(p / name) for p in places)
    raise CorpusError(f"{name} not found (looked in {looked}). {hint}")


# ----------------------------------------------------------------------------------------- safe pickles
TORCH_HINT = ("torch tensors are refused because unpickling them runs torch's own loading code; convert the "
              "file once where you trust it: load it, replace every tensor by tensor.numpy(), pickle it again.")


class _Refused(pickle.UnpicklingError):
    def __init__(self, module: str, name: str):
        super().__init__(f"{module}.{name}")
        self.qualname = f"{module}.{name}"


class CorpusUnpickler(SafeModelUnpickler):
    """The body-model allow-list narrowed to data: builtin containers and (optionally) numpy arrays.

    :class:`~m3t.body.model_files.SafeModelUnpickler` also maps chumpy / scipy classes to inert records; corpus
    files never hold those, so they are refused here, as are torch classes and, for ``allow_numpy=False``,
    numpy itself.
    """

    allow_numpy = True

    def find_class(self, module: str, name: str) -> Any:
        top = module.split(".")[0]
        if top in ("chumpy", "scipy", "torch") or (top == "numpy" and not self.allow_numpy):
            raise _Refused(module, name)
        try:
            return super().find_class(module, name)
        except pickle.UnpicklingError:
            raise _Refused(module, name) from None


def load_data_pickle(path: Path, allow_numpy: bool, compressed: bool = False) -> Any:
    """Unpickle a corpus file with :class:`CorpusUnpickler`; ``CorpusError`` for refused classes or bad bytes."""
    if not path.is_file():
        raise CorpusError(f"{path} not found; check the corpus root and the adapter's file options")
    allowed = "builtin containers, numbers, strings" + (" and numpy arrays" if allow_numpy else "")
    try:
        with open_bounded(path, compressed) as fh:
            unpickler = CorpusUnpickler(fh, encoding="latin1" if allow_numpy else "utf-8")
            unpickler.allow_numpy = allow_numpy
            return unpickler.load()
    except _Refused as exc:
        hint = TORCH_HINT if exc.qualname.startswith("torch") else f"Re-save it holding only {allowed}."
        raise CorpusError(f"{path}: the pickle references {exc.qualname}, a non-data class, and was refused "
                          f"(nothing was run). Allowed: {allowed}. {hint}") from exc
    except (*PICKLE_ERRORS, OSError) as exc:
        raise CorpusError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc}); re-export the file") from exc


def csv_rows(lines: list[str], path: Path, expected: str,
             out: Collector | None) -> tuple[tuple[str, ...], Iterator[tuple[int, dict]]]:
    """(header, (line, record) of each row) of a CSV file's ``lines``. A header the csv module cannot parse is a
    ``CorpusError`` naming ``path`` and the ``expected`` columns; a row it cannot parse (a lone carriage return in
    an unquoted field, a field over the csv module's size limit) is quarantined into ``out`` and the reading goes
    on with the next line."""
    reader = csv.DictReader(io.StringIO("\n".join(lines)))
    try:
        header = tuple(reader.fieldnames or ())
    except csv.Error as exc:
        raise CorpusError(f"{path} line 1: not a CSV header ({exc}); expected {expected}") from exc
    return header, _records(reader, path, out)


def _records(reader: csv.DictReader, path: Path, out: Collector | None) -> Iterator[tuple[int, dict]]:
    while True:
        try:
            record = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            if out is not None:
                out.quarantine(path, reader.line_num, None, f"malformed row: not CSV ({exc})")
            continue
        yield reader.line_num, record


def integer_field(text: str) -> int | None:
    """The integer ``text`` writes in ASCII digits (``-`` allowed), else ``None``: ``str.isdigit`` also admits
    ``²`` or ``١`` and ``int`` refuses ``--5`` or a number of thousands of digits, which are malformed rows here."""
    if re.fullmatch(r"-?[0-9]{1,18}", text) is None:
        return None
    return int(text)
