"""RWTH-PHOENIX-Weather 2014 T (German Sign Language weather forecasts) as frame-folder clips.

Layout (as distributed)::

    <root>/annotations/manual/PHOENIX-2014-T.{train,dev,test}.corpus.csv   (or directly under <root>)
    <root>/features/fullFrame-210x260px/<split>/<name>/1/*.png

Annotation files are ``|``-separated with the header ``name|video|start|end|speaker|orth|translation``; the
``video`` column is a glob relative to the frame root (``train/<name>/1/*.png``) and the clip's media is the
folder of that glob. gloss = ``orth``, text = ``translation``, signer = ``speaker``, 25 fps.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from m3t.corpora.base import (
    SPLITS,
    Collector,
    CorpusAdapter,
    Listing,
    check_header,
    find_file,
    media_folder,
    read_lines,
    with_kind,
)
from m3t.corpora.clip import Clip

HEADER = "name|video|start|end|speaker|orth|translation"
FILE_PATTERN = "PHOENIX-2014-T.{split}.corpus.csv"
HINT = ("Point the corpus root at the PHOENIX-2014-T release folder (the one holding annotations/ and features/) "
        "or set option annotations_dir.")


@dataclass(frozen=True)
class Phoenix14TConfig:
    """Options (params.yaml ``corpora.phoenix14t``); empty ``annotations_dir`` = the release locations."""

    annotations_dir: str = ""  # relative to the root; default: annotations/manual, then the root itself
    frames_dir: str = "features/fullFrame-210x260px"
    fps: float = 25.0
    language: str = "DGS"

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ValueError(f"corpora.phoenix14t.fps must be > 0, got {self.fps}")


class Phoenix14TCorpus(CorpusAdapter):
    """Lists PHOENIX-2014-T clips; bad rows are quarantined with file, row and reason."""

    name = "phoenix14t"
    config_type = Phoenix14TConfig

    def annotation_file(self, split: str) -> Path:
        cfg = self.config
        places = [self.root / cfg.annotations_dir] if cfg.annotations_dir else [
            self.root / "annotations" / "manual", self.root]
        return find_file(FILE_PATTERN.format(split=split), places, HINT)

    def listing(self) -> Listing:
        out = Collector(self.root)
        for split in SPLITS:
            self._list_split(split, self.annotation_file(split), out)
        return out.listing()

    def _list_split(self, split: str, path: Path, out: Collector) -> None:
        cfg = self.config
        lines = read_lines(path, HINT)
        check_header(path, lines, HEADER, f"Is this a PHOENIX-2014-T corpus.csv file? {HINT}")
        check = media_folder((".png",))
        for row, line in enumerate(lines[1:], start=2):
            if not line.strip():
                continue  # blank trailing lines carry nothing
            cols = line.split("|")
            if len(cols) != 7:
                out.quarantine(path, row, cols[0] or None,
                               f"malformed row: {len(cols)} '|'-separated columns, expected 7 ({HEADER})")
                continue
            name, video, start, end, speaker, orth, translation = (c.strip() for c in cols)
            if not name:
                out.quarantine(path, row, None, "empty name")
                continue
            if not translation:
                out.quarantine(path, row, name, "empty translation")
                continue
            glob = PurePosixPath(video)
            if not video or glob.is_absolute() or ".." in glob.parts:
                out.quarantine(path, row, name, f"video column {video!r} is not a relative frame glob")
                continue
            media = (PurePosixPath(cfg.frames_dir) / glob.parent).as_posix()
            clip = Clip(id=name, corpus=self.name, split=split, language=cfg.language, signer=speaker or "unknown",
                        text=translation, gloss=orth, media=media, fps=cfg.fps,
                        extra=with_kind("frames", frame_glob=glob.name, start=start, end=end,
                                        annotation=f"{out.rel(path)}:{row}"))
            out.add(clip, path, row, check)
