"""Property-based fuzz of the readers of files that come from elsewhere: any input ends in a clear error or a
quarantine line, never another exception.

The outcomes are those of :mod:`malformed_cases` (``quarantined``, ``clear error``), plus ``listed`` for a
mutation that left the row valid. A listing must name, for every quarantined row, its file and the reason, keep
every clip of the files left alone (or name it in a quarantine entry: the mutated row may take its id or its
media), and account for every non-blank row of the mutated file (a clip or a quarantine entry, nothing silently
dropped). A whole-file problem must be a ``CorpusError`` (``ConfigError`` for params) whose message names the file
(or the key).

Inputs start from the fixture trees of :mod:`corpus_fixtures`, which build each corpus in its published layout
and cite the layout's source (PHOENIX-2014-T: the ``sign-language-datasets`` dummy release; How2Sign: the official
``download_how2sign.sh`` and issue 9's realigned row; CSL-Daily: hsuzjx/SLRT's ``CSLDailyDataset.py``; NMFs-CSL:
MASA's ``NMFs_CSL.py`` list rows; SOKE: 2000ZRL/SOKE ``load_data.py``), from real ``.pose`` files and the
``data.csv`` of the spoken-to-signed wheel's fingerspelling lexicon, and from the repository's ``params.yaml``;
the strategies then change fields, separators, quoting, column counts, encodings, numbers and paths. Every test is
bounded (``max_examples``) and derandomized: the same examples run on every host.
"""
from __future__ import annotations

import csv
import math
import re
import shutil
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import corpus_fixtures as fx
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from malformed_cases import CLEAR, QUARANTINED

from m3t.config import SECTIONS, ConfigError, load_params
from m3t.corpora.annotation_files import read_lines
from m3t.corpora.base import open_corpus
from m3t.corpora.clip import Clip
from m3t.corpora.fingerspelling import lexicon_root
from m3t.corpora.listing import CorpusError, Listing
from m3t.corpora.posefile import MAX_FPS, read_pose, read_pose_info

ROOT = Path(__file__).resolve().parents[2]
LISTED = "listed"  # the mutated row is still a valid row


def fuzz(n: int) -> settings:
    """Bounded and reproducible: ``n`` examples, no per-example deadline (a shared 2-core CI host is slow at
    times), derandomized so that every host runs the same examples. The trees are module fixtures, reused by
    every example (each example restores the file it mutated): hypothesis warns about that; it is intended."""
    return settings(max_examples=n, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


# ----------------------------------------------------------------------------------------- mutations of text tables
NASTY = ("", " ", "..", "../..", "../../etc/passwd", "a/../../b", "/etc/passwd", "C:\\Windows", "\\\\server\\share",
         "nan", "NaN", "inf", "-inf", "1e400", "-1", "0", "-0", "1_0", "0x10", "²", "١٢", "--5", "9" * 5000,
         "x" * 300, "\x00", "\u2028", "\u0085", "\r", "\t", "|", ",", "\"", "'", "\"\"", "\ufeff", "é", "\U0001f600",
         "train", "dev", "val", "test", "holdout", "*.png", "1/*.png", "video/", "video/../x.mp4", "a\\b")
SEPARATORS = ("|", "\t", ",", ";", " ", "")
INVALID_UTF8 = (b"\xff", b"\xc3", b"\xe9", b"\xed\xa0\x80", b"\xf8\x88\x80\x80\x80")

field_values = st.one_of(st.sampled_from(NASTY), st.text(max_size=12), st.integers().map(str),
                         st.floats().map(repr), st.text(alphabet="x/.\\ -", max_size=300))


@st.composite
def mutated_table(draw, text: str, sep: str, header: bool = True) -> bytes:
    """``text`` (a valid annotation file whose rows are ``sep``-separated) with one to three of its rows
    changed, then possibly its bytes: a field replaced or edited, a field dropped or added, the separator
    changed, quotes added, rows duplicated, dropped or blanked (the header too, rarely), and then non-UTF-8
    bytes, another encoding, CRLF, a BOM, a cut or appended bytes."""
    lines = text.split("\n")[:-1]
    first = 1 if header else 0
    for _ in range(draw(st.integers(1, 3))):
        lines = lines or [""]
        i = draw(st.integers(0 if draw(st.integers(0, 9)) == 0 else min(first, len(lines) - 1), len(lines) - 1))
        fields = lines[i].split(sep) if sep else [lines[i]]
        j = draw(st.integers(0, len(fields) - 1))
        op = draw(st.sampled_from(("replace", "replace", "edit", "drop", "add", "separator", "quote", "duplicate",
                                   "delete", "blank")))
        if op == "replace":
            fields[j] = draw(field_values)
        elif op == "edit":  # a valid prefix, a nasty middle, a valid suffix
            k = draw(st.integers(0, len(fields[j])))
            fields[j] = fields[j][:k] + draw(field_values) + fields[j][k:]
        elif op == "drop" and len(fields) > 1:
            del fields[j]
        elif op == "add":
            fields.insert(j, draw(field_values))
        elif op == "quote":
            fields[j] = draw(st.sampled_from(("\"{}\"", "\"{}", "{}\"", "\"{}\"\"x\""))).format(fields[j])
        line = (draw(st.sampled_from(SEPARATORS)) if op == "separator" else sep).join(fields)
        if op == "duplicate":
            lines.insert(i, lines[i])
        elif op == "delete" and len(lines) > 1:
            del lines[i]
        elif op == "blank":
            lines[i] = draw(st.sampled_from(("", " ", "\t", "\r")))
        else:
            lines[i] = line
    data = ("\n".join(lines) + "\n").encode("utf-8", "surrogatepass")
    return draw(mutated_bytes(data))


@st.composite
def mutated_bytes(draw, data: bytes) -> bytes:
    """``data`` as it is (mostly) or with one file-level change."""
    op = draw(st.sampled_from(("none", "none", "none", "invalid", "latin-1", "utf-16", "crlf", "bom", "no-newline",
                               "cut", "append")))
    at = draw(st.integers(0, len(data)))
    if op == "invalid":
        return data[:at] + draw(st.sampled_from(INVALID_UTF8)) + data[at:]
    if op in ("latin-1", "utf-16"):
        return data.decode("utf-8", "replace").encode(op, "replace")
    if op == "crlf":
        return data.replace(b"\n", b"\r\n")
    if op == "bom":
        return b"\xef\xbb\xbf" + data
    if op == "no-newline":
        return data.rstrip(b"\n")
    if op == "cut":
        return data[:at]
    if op == "append":
        return data + draw(st.binary(max_size=64))
    return data


# ----------------------------------------------------------------------------------------- judging a listing
@dataclass(frozen=True)
class Target:
    """One annotation file of a fixture tree: ``rel`` (from the root), its separator, whether line 1 is a
    header, ``line_of(clip, lines)``: the line of the unmutated file a clip was listed from (``None``: the clip
    comes from another file, so it must stay listed), and for line-based files ``row_of(clip)``: the row of a
    listed clip when it came from this file (``None`` otherwise); its rows are then all accounted for."""

    rel: str
    sep: str
    header: bool = True
    line_of: Callable[[Clip, list[str]], str | None] = lambda clip, lines: None
    row_of: Callable[[Clip], int | None] | None = None
    csv: bool = False


def judge(list_it: Callable[[], Listing], root: Path, target: Target, before: Listing, original: list[str]) -> str:
    """The outcome of a listing of ``root`` whose ``target`` file was mutated (``original``: its lines before);
    an assertion error when it is none of clear error, quarantine or a valid row listed (any other exception
    propagates: that is the failure the fuzz looks for)."""
    try:
        listing = list_it()
    except CorpusError as exc:
        assert Path(target.rel).name in str(exc), f"the error does not name {target.rel}: {exc}"
        return CLEAR
    for q in listing.quarantined:
        assert q.file and q.reason.strip(), q
    mine = [q for q in listing.quarantined if q.file == target.rel]
    lines = read_lines(root / target.rel, "")  # the listing read it: it decodes
    quoted = target.csv and any("\"" in line for line in lines)  # a quote may run a field over later lines
    if target.header and lines[:1] != original[:1]:
        return QUARANTINED if mine else LISTED  # another header gives every row another meaning
    ids, named = {c.id for c in listing.clips}, {q.clip_id for q in listing.quarantined}
    for clip in before.clips:  # a clip of an untouched row: listed, or named by an entry (its id or its row)
        line = target.line_of(clip, original)
        if line is None or (line in lines and not quoted):
            rows = {n for n, x in enumerate(lines, start=1) if x == line}
            assert clip.id in ids or clip.id in named or any(q.row in rows for q in mine), (
                f"clip {clip.id} of an untouched row dropped without a quarantine entry")
    if target.row_of is not None:  # every non-blank row of the mutated file: a clip or a quarantine entry
        rows = [n for n, line in enumerate(lines, start=1) if line.strip() and n > int(target.header)]
        accounted = sorted([r for r in map(target.row_of, listing.clips) if r is not None] + [q.row for q in mine])
        assert accounted == rows, f"rows {rows}, accounted for {accounted}: {mine}"
    return QUARANTINED if mine else LISTED


def fuzz_listing(root: Path, target: Target, data: bytes, list_it: Callable[[], Listing], before: Listing) -> str:
    """Write ``data`` over the target file, judge the listing, put the file back."""
    path = root / target.rel
    original = path.read_bytes()
    try:
        path.write_bytes(data)
        return judge(list_it, root, target, before, original.decode("utf-8").split("\n"))
    finally:
        path.write_bytes(original)


# ----------------------------------------------------------------------------------------- fixture trees
@pytest.fixture(scope="module")
def trees(tmp_path_factory) -> Path:
    """One tree per corpus in its published layout (:mod:`corpus_fixtures`), reused by every example."""
    base = tmp_path_factory.mktemp("fuzz")
    fx.build_phoenix14t(base / "phoenix")
    fx.build_how2sign(base / "how2sign")
    fx.build_csl_daily(base / "csl")
    fx.build_nmfs_csl(base / "nmfs")
    fx.build_soke(base / "soke", "how2sign")
    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    fx.build_pose_collection(base / "pose", lexicon_root(), rows)
    letters = [r for r in rows if r["signed_language"] == "ase"][:4]
    (base / "spell" / "ase").mkdir(parents=True)
    for r in letters:
        shutil.copyfile(lexicon_root() / r["path"], base / "spell" / r["path"])
    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        header = fh.readline()
    (base / "spell" / "data.csv").write_text(header + "".join(
        ",".join(r[c] for c in header.strip().split(",")) + "\n" for r in letters), encoding="utf-8")
    return base


def text_of(root: Path, rel: str) -> str:
    return (root / rel).read_text(encoding="utf-8")


@st.composite
def table_case(draw, root: Path, targets: list[Target]) -> tuple[Target, bytes]:
    target = draw(st.sampled_from(targets))
    return target, draw(mutated_table(text_of(root, target.rel), target.sep, target.header))


def annotated(rel: str) -> Target:
    """A file whose clips carry ``annotation`` = ``<file>:<row>`` (PHOENIX-2014-T, How2Sign)."""

    def row_of(clip: Clip) -> int | None:
        file, row = clip.get("annotation").rsplit(":", 1)
        return int(row) if file == rel else None

    def line_of(clip: Clip, lines: list[str]) -> str | None:
        row = row_of(clip)
        return None if row is None else lines[row - 1]

    return Target(rel, "|" if rel.startswith("annotations") else "\t", True, line_of, row_of)


def starting(prefix: Callable[[Clip], str]) -> Callable[[Clip, list[str]], str | None]:
    """``line_of`` for a file whose rows start with a clip's key (an id, a path): every clip comes from it."""
    return lambda clip, lines: next((x for x in lines if x.startswith(prefix(clip))), "<no such row>")


def listing_of(name: str, root: Path, **options) -> Callable[[], Listing]:
    return lambda: open_corpus(name, root, **options).listing()


def run_table(root: Path, name: str, targets: list[Target], data, before: Listing, **options) -> str:
    target, raw = data.draw(table_case(root, targets))
    return fuzz_listing(root, target, raw, listing_of(name, root, **options), before)


@pytest.fixture(scope="module")
def phoenix(trees):
    return trees / "phoenix", open_corpus("phoenix14t", trees / "phoenix").listing()


@given(data=st.data())
@fuzz(80)
def test_phoenix14t_annotation_rows(phoenix, data):
    """PHOENIX-2014-T's ``|``-separated ``corpus.csv`` files, rows mutated (fields, separators, quoting, column
    counts, paths, encodings): a ``CorpusError`` naming the file, or a listing that accounts for every row (clip
    or quarantine entry naming the file and row) and keeps every clip of an untouched row."""
    root, before = phoenix
    run_table(root, "phoenix14t", [annotated(f"annotations/manual/PHOENIX-2014-T.{s}.corpus.csv")
                                   for s in ("train", "dev", "test")], data, before)


@pytest.fixture(scope="module")
def how2sign(trees):
    return trees / "how2sign", open_corpus("how2sign", trees / "how2sign").listing()


@given(data=st.data())
@fuzz(80)
def test_how2sign_realigned_rows(how2sign, data):
    """How2Sign's tab-separated realigned CSVs, rows mutated (times NaN / huge / not numbers, names with ``..`` or
    300 characters, tabs in the sentence, encodings): a ``CorpusError`` naming the file, or every row a clip or a
    quarantine entry and every clip of an untouched row kept."""
    root, before = how2sign
    run_table(root, "how2sign", [annotated(f"sentence_level/{s}/text/en/raw_text/re_aligned/how2sign_realigned_{s}.csv")
                                 for s in ("train", "val", "test")], data, before)


@pytest.fixture(scope="module")
def csl(trees):
    return trees / "csl", open_corpus("csl_daily", trees / "csl").listing()


@given(data=st.data())
@fuzz(50)
def test_csl_daily_split_file(csl, data):
    """CSL-Daily's ``split_1.txt`` (``name|split``), rows mutated: a ``CorpusError`` naming the file, or a
    listing in which every clip is listed or named by a quarantine entry (a name the split file lost is
    reported as missing from it, never dropped)."""
    root, before = csl
    run_table(root, "csl_daily", [Target("sentence_label/split_1.txt", "|")], data, before)


@pytest.fixture(scope="module")
def nmfs(trees):
    return trees / "nmfs", open_corpus("nmfs_csl", trees / "nmfs", confusing_list="confusing.txt").listing()


def nmfs_list(rel: str) -> Target:
    """A train / test list: its clips are those whose ``source_split`` is the list's; rows are counted."""
    split = rel.removesuffix(".txt")

    def line_of(clip: Clip, lines: list[str]) -> str | None:
        if clip.get("source_split") != split:
            return None
        key = clip.id.replace("__", "/").removeprefix("video/")
        return next(x for x in lines if x.strip() and x.split()[0].rsplit(".", 1)[0].removeprefix("video/") == key)

    return Target(rel, " ", False, line_of)


@given(data=st.data())
@fuzz(80)
def test_nmfs_csl_lists_and_dictionary(nmfs, data):
    """NMFs-CSL's train / test lists (``<path> <class>`` or ``<class folder>/<file>``), dictionary and confusing
    list, rows mutated (classes such as ``²``, ``--5`` or 5,000 digits, paths with ``..`` or 300 characters): a
    ``CorpusError`` naming the file, or every list row a clip or a quarantine entry, and every clip of an
    untouched row listed or named."""
    root, before = nmfs
    targets = [nmfs_list("train.txt"), nmfs_list("test.txt"), Target("dictionary.txt", "\t", False),
               Target("confusing.txt", "", False)]
    target, raw = data.draw(table_case(root, targets))
    listing = listing_of("nmfs_csl", root, confusing_list="confusing.txt")
    if fuzz_listing(root, target, raw, listing, before) == CLEAR or target.sep != " ":
        return
    path = root / target.rel  # a list: its non-blank rows are its clips and its quarantine lines, counted
    original = path.read_bytes()
    try:
        path.write_bytes(raw)
        got = listing()
        rows = [x for x in read_lines(path, "") if x.strip()]
        clips = [c for c in got.clips if c.get("source_split") == target.rel.removesuffix(".txt")]
        entries = [q for q in got.quarantined if q.file == target.rel]
        assert len(clips) + len(entries) == len(rows), (rows, clips, entries)
    finally:
        path.write_bytes(original)


# ----------------------------------------------------------------------------------------- CSV readers
@pytest.fixture(scope="module")
def pose_index(trees):
    return trees / "pose", open_corpus("posefile", trees / "pose", index="index.csv").listing()


# rows the fuzz found raising csv.Error, ValueError and OSError from the index readers, kept as fixed examples
POSE_INDEX_REPRODUCTIONS = {
    "lone carriage return (csv.Error)": "z,poses/a\rb.pose,train,A,ase,s0,1",
    "field over 128 KiB (csv.Error)": "z,poses/" + "x" * 131072 + ".pose,train,A,ase,s0,1",
    "label --5 (ValueError)": "z,poses/ase_0.pose,train,A,ase,s0,--5",
    "label \u00b2 (ValueError)": "z,poses/ase_0.pose,train,A,ase,s0,\u00b2",
    "300-character path (OSError)": "z," + "x" * 300 + ".pose,train,A,ase,s0,1",
}


@pytest.mark.parametrize("row", list(POSE_INDEX_REPRODUCTIONS.values()), ids=list(POSE_INDEX_REPRODUCTIONS))
def test_pose_index_rows_the_fuzz_found_are_quarantined(pose_index, row):
    """Each row once found raising from the index reader is now one quarantine line naming ``index.csv``, and
    every clip listed before is still listed."""
    root, before = pose_index
    path = root / "index.csv"
    original = path.read_bytes()
    try:
        path.write_bytes(original.rstrip(b"\n") + b"\n" + row.encode("utf-8") + b"\n")
        got = open_corpus("posefile", root, index="index.csv").listing()
    finally:
        path.write_bytes(original)
    assert [c.id for c in got.clips] == [c.id for c in before.clips]
    new = [q for q in got.quarantined if q not in before.quarantined]
    assert len(new) == 1 and new[0].file == "index.csv" and new[0].reason, new


@pytest.mark.parametrize("row", ["q1,a\rb,G,s0", "q1," + "x" * 200_000 + ",G,s0"], ids=["carriage-return", "huge-field"])
def test_soke_annotation_rows_the_csv_module_cannot_parse_are_quarantined(soke, row):
    """SOKE's annotation CSV with a row the csv module refuses: one quarantine line naming the file, the rest
    read (the same reader as the index's and the fingerspelling table's)."""
    root, before = soke
    path = root / "annotation.csv"
    original = path.read_bytes()
    try:
        path.write_bytes(original.rstrip(b"\n") + b"\n" + row.encode("utf-8") + b"\n")
        got = open_corpus("soke_smplx", root, annotation="annotation.csv").listing()
    finally:
        path.write_bytes(original)
    assert [c.id for c in got.clips] == [c.id for c in before.clips]
    new = [q for q in got.quarantined if q not in before.quarantined]
    assert len(new) == 1 and new[0].file == "annotation.csv" and "not CSV" in new[0].reason, new


@given(data=st.data())
@fuzz(60)
def test_pose_index_csv(pose_index, data):
    """The ``.pose`` collection's index CSV (``id,path,split,text,language,signer[,label]``), rows mutated
    (labels, splits, ``..`` / absolute paths, quoting, column counts, encodings): a ``CorpusError`` naming the
    index, or quarantine entries naming it and every clip of an untouched row listed or named."""
    root, before = pose_index
    target = Target("index.csv", ",", True, starting(lambda clip: f"{clip.id},"), csv=True)
    run_table(root, "posefile", [target], data, before, index="index.csv")


@pytest.fixture(scope="module")
def spelling(trees):
    return trees / "spell", open_corpus("fingerspelling", trees / "spell", words_per_language=2).listing()


@given(data=st.data())
@fuzz(50)
def test_fingerspelling_table(spelling, data):
    """The fingerspelling lexicon's ``data.csv`` (``path,spoken_language,signed_language,start,end,words,glosses,
    priority``; four real ASL rows of the spoken-to-signed wheel), rows mutated: a ``CorpusError`` naming the
    table, or quarantine entries naming it and every letter of an untouched row listed or named."""
    root, before = spelling
    letters = Listing(tuple(c for c in before.clips if c.get("clip_type") == "letter"), ())
    target = Target("data.csv", ",", True, starting(lambda clip: f"{clip.media},"), csv=True)
    run_table(root, "fingerspelling", [target], data, letters, words_per_language=2)


@pytest.fixture(scope="module")
def soke(trees):
    return trees / "soke", open_corpus("soke_smplx", trees / "soke", annotation="annotation.csv").listing()


@given(data=st.data())
@fuzz(40)
def test_soke_annotation_csv(soke, data):
    """SOKE's optional annotation CSV (``id,text,gloss,signer``), rows mutated: a ``CorpusError`` naming the file,
    or every clip of an untouched row listed or named."""
    root, before = soke
    target = Target("annotation.csv", ",", True, starting(lambda clip: f"{clip.id},"), csv=True)
    run_table(root, "soke_smplx", [target], data, before, annotation="annotation.csv")


# ----------------------------------------------------------------------------------------- params.yaml
PARAMS_TEXT = (ROOT / "params.yaml").read_text(encoding="utf-8")
scalars = st.one_of(st.none(), st.booleans(), st.integers(), st.integers(min_value=2**63), st.floats(),
                    st.text(max_size=10), st.sampled_from(NASTY[:24]), st.dates())
yaml_values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(
    st.one_of(st.text(max_size=8), st.integers(), st.none(), st.booleans()), inner, max_size=3), max_leaves=8)


@st.composite
def params_document(draw) -> str:
    """``params.yaml`` with one to three values changed somewhere in its tree: a value of another type (numbers
    huge or NaN, dates, nested lists and mappings), an unknown key (text, number, null), a key deleted, or a
    subtree shared with another place (written as an anchor and its alias)."""
    doc = yaml.safe_load(PARAMS_TEXT)
    for _ in range(draw(st.integers(1, 3))):
        parent = doc
        key = draw(st.sampled_from(sorted(parent, key=str)))
        while isinstance(parent[key], dict) and parent[key] and draw(st.booleans()):
            parent = parent[key]
            key = draw(st.sampled_from(sorted(parent, key=str)))
        op = draw(st.sampled_from(("value", "value", "unknown", "delete", "alias")))
        if op == "value":
            parent[key] = draw(yaml_values)
        elif op == "unknown":
            parent[draw(st.one_of(st.text(max_size=8), st.integers(), st.none()))] = draw(yaml_values)
        elif op == "delete":
            del parent[key]
        else:
            parent[key] = doc[draw(st.sampled_from(sorted(doc, key=str)))]
        if not doc:
            break
    return yaml.safe_dump(doc, allow_unicode=True, sort_keys=False)


def check_params(path: Path, data: bytes) -> str:
    """``load_params`` of ``data``: the params, or a ``ConfigError`` naming the file or a section / key."""
    path.write_bytes(data)
    try:
        load_params(path)
    except ConfigError as exc:
        message = str(exc)
        assert str(path) in message or re.search(r"\b(" + "|".join(SECTIONS) + r")\b", message), message
        return CLEAR
    return LISTED


@given(text=params_document())
@fuzz(100)
def test_params_yaml_structure(tmp_path_factory, text):
    """``params.yaml`` through ``load_params``, structure-aware (wrong types, unknown keys of any type, deleted
    keys, aliases, nesting): the params, or a ``ConfigError`` naming the file or the key."""
    check_params(tmp_path_factory.mktemp("params") / "params.yaml", text.encode("utf-8"))


@given(data=st.data())
@fuzz(60)
def test_params_yaml_text(tmp_path_factory, data):
    """``params.yaml`` as text and bytes: lines changed, split, quoted, dropped, then non-UTF-8 bytes, other
    encodings, cuts: the params, or a ``ConfigError`` naming the file or the key."""
    raw = data.draw(mutated_table(PARAMS_TEXT, ": ", header=False))
    check_params(tmp_path_factory.mktemp("params") / "params.yaml", raw)


# ----------------------------------------------------------------------------------------- .pose files
def pose_fields(data: bytes) -> dict[str, tuple[int, str]]:
    """name -> (offset, struct format) of every header field of a ``.pose`` v0.2 file (pose-format's layout:
    version, width / height / depth, components each with name, point format, point / limb / colour counts,
    point names, limbs, colours; then fps, frames, people)."""
    fields = {"version": (0, "<f"), "width": (4, "<H"), "height": (6, "<H"), "depth": (8, "<H"),
              "components": (10, "<H")}
    off = 12
    for c in range(struct.unpack_from("<H", data, 10)[0]):
        for name in ("name", "format"):
            (n,) = struct.unpack_from("<H", data, off)
            fields[f"{c}.{name}.length"], fields[f"{c}.{name}"] = (off, "<H"), (off + 2, f"{n}s")
            off += 2 + n
        points, limbs, colours = struct.unpack_from("<HHH", data, off)
        fields.update({f"{c}.points": (off, "<H"), f"{c}.limbs": (off + 2, "<H"), f"{c}.colours": (off + 4, "<H")})
        off += 6
        for p in range(points):
            (n,) = struct.unpack_from("<H", data, off)
            fields[f"{c}.point{p}"] = (off + 2, f"{n}s")
            off += 2 + n
        if limbs:
            fields[f"{c}.limb0"] = (off, "<H")
        off += 4 * limbs + 6 * colours
    fields.update({"fps": (off, "<f"), "frames": (off + 4, "<I"), "people": (off + 8, "<H")})
    return fields


def smallest_lexicon_pose() -> bytes:
    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        paths = [lexicon_root() / r["path"] for r in csv.DictReader(fh)]
    return min(paths, key=lambda p: p.stat().st_size).read_bytes()


POSE = smallest_lexicon_pose()  # a real MediaPipe Holistic .pose file of the spoken-to-signed wheel
POSE_FIELDS = pose_fields(POSE)
FIELD_VALUES = {"<f": st.one_of(st.floats(width=32), st.sampled_from([0.0, 0.1, 0.2, 0.3, 25.0, 1e30])),
                "<H": st.one_of(st.integers(0, 65535), st.sampled_from([0, 1, 2, 3, 65535])),
                "<I": st.one_of(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 2, 2**31]))}


@st.composite
def mutated_pose(draw) -> bytes:
    """The real ``.pose`` file with header fields set to arbitrary values (version, dimensions, component and
    point counts, names and point formats as other bytes of the same length, fps, frames, people), then maybe
    bit flips, a cut or appended bytes."""
    data = bytearray(POSE)
    for _ in range(draw(st.integers(0, 3))):
        offset, fmt = POSE_FIELDS[draw(st.sampled_from(sorted(POSE_FIELDS)))]
        if fmt.endswith("s"):
            value = draw(st.one_of(st.binary(min_size=int(fmt[:-1]), max_size=int(fmt[:-1])),
                                   st.sampled_from([b"XYC", b"XYZC", b"XY", b"C", b""]).filter(
                                       lambda b, n=int(fmt[:-1]): len(b) == n)))
            data[offset:offset + len(value)] = value
        else:
            struct.pack_into(fmt, data, offset, draw(FIELD_VALUES[fmt]))
    for _ in range(draw(st.integers(0, 2))):
        at = draw(st.integers(0, len(data) - 1))
        data[at] ^= 1 << draw(st.integers(0, 7))
    op = draw(st.sampled_from(("none", "cut", "cut-header", "append")))
    if op == "cut":
        return bytes(data[:draw(st.integers(0, len(data)))])
    if op == "cut-header":
        return bytes(data[:draw(st.integers(0, POSE_FIELDS["people"][0] + 10))])
    return bytes(data) + (draw(st.binary(min_size=1, max_size=64)) if op == "append" else b"")


@given(data=mutated_pose())
@fuzz(150)
def test_pose_header_and_body(tmp_path_factory, data):
    """``read_pose_info`` and ``read_pose`` on a real ``.pose`` file with header fields replaced, bits flipped,
    cuts and appended bytes: a ``CorpusError`` naming the file, or a header / body that is usable (fps in
    (0, MAX_FPS], a person, points (T, K, 3) with confidence (T, K))."""
    path = tmp_path_factory.mktemp("pose") / "clip.pose"
    path.write_bytes(data)
    try:
        info = read_pose_info(path)
    except CorpusError as exc:
        assert str(path) in str(exc), exc
    else:
        assert 0 < info.fps <= MAX_FPS and info.people >= 1 and info.frames >= 0, info
    try:
        pose = read_pose(path)
    except CorpusError as exc:
        assert str(path) in str(exc), exc
    else:
        assert pose.points.ndim == 3 and pose.points.shape[-1] == 3, pose.points.shape
        assert pose.confidence.shape == pose.points.shape[:2] and 0 < pose.fps <= MAX_FPS
        assert math.isfinite(pose.fps)


def test_pose_fields_parse_the_real_file():
    """The field table reads the real file to its end: frames x people x points x (dims + 1) float32 follow."""
    frames, people = (struct.unpack_from(POSE_FIELDS[k][1], POSE, POSE_FIELDS[k][0])[0] for k in ("frames", "people"))
    info = read_pose_info_of(POSE)
    points = sum(n for _, n in info.components)
    assert POSE_FIELDS["people"][0] + 2 + 4 * frames * people * points * 4 == len(POSE)


def read_pose_info_of(data: bytes):
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "clip.pose"
        path.write_bytes(data)
        return read_pose_info(path)
