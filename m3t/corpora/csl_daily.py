"""CSL-Daily (Chinese Sign Language, daily-life sentences) as frame-folder clips.

Layout (as distributed)::

    <root>/sentence_label/csl2020ct_v2.pkl     pickle dict; "info": list of dicts {name, length, label_gloss,
                                              label_char, label_word, label_postag, signer, time}, plus
                                              "gloss_map", "char_map", "word_map", "postag_map"
    <root>/sentence_label/split_1.txt          header "name|split", rows "<name>|train|dev|test"
    <root>/sentence/frames_512x512/<name>/000000.jpg ...
        (or <root>/sentence_frames-512x512/frames_512x512/<name>/, the frame archive unpacked under its own name)

An ``info`` entry looks like ``{'name': 'S000007_P0003_T00', 'length': 55, 'label_gloss': ['他', '谁'],
'label_char': ['他', '是', '谁', '？'], 'label_word': ['他', '是', '谁', '？'], 'label_postag': ['r', 'v', 'v', 'w'],
'signer': 3, 'time': 0}``. text = ``"".join(label_word)``, gloss = ``" ".join(label_gloss)``,
``"".join(label_char)`` kept in extra as ``chars``. The pickle is read with an allow-list unpickler that accepts
builtin containers only (the ``*_map`` keys are ignored). A name in the split file but not in the pickle, or the
reverse, is quarantined: the release has one such pair (split row ``S000005_P0004_T00``, pickle entry
``S000007_P0003_T00``), which some loaders silently rename; here both are reported and nothing is guessed.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import PurePosixPath
from typing import Any

from m3t.corpora.annotation_files import check_header, load_data_pickle, read_lines
from m3t.corpora.base import CorpusAdapter
from m3t.corpora.clip import Clip
from m3t.corpora.listing import Collector, CorpusError, Listing, media_folder, with_kind
from m3t.corpora.splits import SPLITS

SPLIT_HEADER = "name|split"
INFO_KEYS = ("name", "length", "label_gloss", "label_char", "label_word", "signer")
FRAME_DIRS = ("sentence/frames_512x512", "sentence_frames-512x512/frames_512x512")
HINT = "Point the corpus root at the CSL-Daily folder (the one holding sentence_label/ and sentence/)."


@dataclass(frozen=True)
class CslDailyConfig:
    """Options (params.yaml ``corpora.csl_daily``); paths relative to the root."""

    annotation: str = "sentence_label/csl2020ct_v2.pkl"
    split_file: str = "sentence_label/split_1.txt"
    frames_dir: str = ""  # "" = the first of FRAME_DIRS that exists
    fps: float = 30.0
    language: str = "CSL"

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ValueError(f"corpora.csl_daily.fps must be > 0, got {self.fps}")


class CslDailyCorpus(CorpusAdapter):
    """Lists CSL-Daily clips by joining the annotation pickle with the split file."""

    name = "csl_daily"
    config_type = CslDailyConfig

    def read_info(self) -> list[Any]:
        """The ``info`` list of the annotation pickle (builtin containers only; anything else is refused)."""
        path = self.root / self.config.annotation
        data = load_data_pickle(path, allow_numpy=False)
        if not isinstance(data, dict) or not isinstance(data.get("info"), list):
            found = sorted(map(str, data)) if isinstance(data, dict) else type(data).__name__
            raise CorpusError(f"{path}: expected a dict with an 'info' list of clip records, found {found}. {HINT}")
        return data["info"]

    def read_splits(self, out: Collector) -> dict[str, tuple[str, int]]:
        """name -> (split, row) from the split file; bad rows quarantined."""
        path = self.root / self.config.split_file
        lines = read_lines(path, HINT)
        check_header(path, lines, SPLIT_HEADER, f"Is this CSL-Daily's split_1.txt? {HINT}")
        splits: dict[str, tuple[str, int]] = {}
        for row, line in enumerate(lines[1:], start=2):
            if not line.strip():
                continue
            cols = [c.strip() for c in line.split("|")]
            if len(cols) != 2 or not cols[0]:
                out.quarantine(path, row, None, f"malformed row: expected '<name>|<split>', found {line!r}")
            elif cols[1] not in SPLITS:
                out.quarantine(path, row, cols[0], f"split {cols[1]!r} unknown; expected one of {', '.join(SPLITS)}")
            elif cols[0] in splits:
                out.quarantine(path, row, cols[0], f"name listed twice (first at row {splits[cols[0]][1]})")
            else:
                splits[cols[0]] = (cols[1], row)
        return splits

    def frames_dir(self) -> str:
        """The frame folder: option ``frames_dir``, else the first of :data:`FRAME_DIRS` under the root."""
        if self.config.frames_dir:
            return self.config.frames_dir
        for candidate in FRAME_DIRS:
            if (self.root / candidate).is_dir():
                return candidate
        looked = ", ".join(str(self.root / c) for c in FRAME_DIRS)
        raise CorpusError(f"no CSL-Daily frame folder (looked in {looked}); unpack the sentence frames there or "
                          f"set corpora.csl_daily.options.frames_dir. {HINT}")

    def listing(self) -> Listing:
        cfg = self.config
        out = Collector(self.root)
        info = self.read_info()
        splits = self.read_splits(out)
        frames_dir = PurePosixPath(self.frames_dir())
        pkl, split_path = self.root / cfg.annotation, self.root / cfg.split_file
        check = media_folder()
        listed: set[str] = set()
        for index, entry in enumerate(info):
            record = _record(entry)
            if isinstance(record, str):
                name = entry.get("name") if isinstance(entry, dict) else None
                name = name if isinstance(name, str) and name else None
                listed.add(name or "")  # its split row is then not reported a second time
                out.quarantine(pkl, index, name, record)
                continue
            name = record["name"]
            listed.add(name)
            if name not in splits:
                out.quarantine(pkl, index, name, f"name not in the split file {cfg.split_file}")
                continue
            clip = Clip(id=name, corpus=self.name, split=splits[name][0], language=cfg.language,
                        signer=str(record["signer"]), text="".join(record["label_word"]),
                        gloss=" ".join(record["label_gloss"]), media=(frames_dir / name).as_posix(),
                        fps=cfg.fps, extra=with_kind("frames", chars="".join(record["label_char"]),
                                                     length=record["length"]))
            out.add(clip, pkl, index, check)
        for name, (_, row) in splits.items():
            if name not in listed:
                out.quarantine(split_path, row, name, f"name not in the annotation pickle {cfg.annotation}")
        return out.listing()


def _record(entry: Any) -> dict[str, Any] | str:
    """The entry when it has every key with the right type, else the quarantine reason."""
    if not isinstance(entry, dict):
        return f"info entry is a {type(entry).__name__}, expected a dict with keys {', '.join(INFO_KEYS)}"
    missing = [k for k in INFO_KEYS if k not in entry]
    if missing:
        return f"info entry lacks keys {missing}"
    if not isinstance(entry["name"], str) or not entry["name"]:
        return f"name {entry['name']!r} is not a non-empty string"
    for key in ("label_gloss", "label_char", "label_word"):
        value = entry[key]
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            return f"{key} is not a list of strings"
    if not entry["label_word"]:
        return "label_word is empty (no sentence text)"
    return entry
