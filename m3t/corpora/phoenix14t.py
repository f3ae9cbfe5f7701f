"""RWTH-PHOENIX-Weather 2014 T (German Sign Language weather forecasts) as frame-folder clips.

Layout (as distributed in ``phoenix-2014-T.v3.tar.gz``; the root is its ``PHOENIX-2014-T`` folder)::

    <root>/annotations/manual/PHOENIX-2014-T.{train,dev,test}.corpus.csv   (or directly under <root>)
    <root>/features/fullFrame-210x260px/<split>/<name>/images0001.png ...

Annotation files are ``|``-separated with the header ``name|video|start|end|speaker|orth|translation``, e.g.
``11August_2010_Wednesday_tagesschau-1|11August_2010_Wednesday_tagesschau-1/1/*.png|-1|-1|Signer08|JETZT WETTER
...|und nun die wettervorhersage ...``. The ``video`` column is a glob relative to the split's frame folder
``<frames_dir>/<split>/``; its ``1/`` level is a legacy of PHOENIX-2014, whose ``multisigner`` tree does hold
``<split>/<name>/1/*.png``. The 2014-T release has no ``1/`` folder: the images sit in ``<split>/<name>/``. So the
clip's media is ``<frames_dir>/<split>/<name>/1`` when that folder exists, else ``<frames_dir>/<split>/<name>``.

gloss = ``orth``, text = ``translation``, signer = ``speaker``, 25 fps. A row whose frame folder is already the
media of an earlier row (two names, one video) is quarantined, naming the first; the first stays listed.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from m3t.corpora.annotation_files import check_header, find_file, read_lines
from m3t.corpora.base import CorpusAdapter
from m3t.corpora.clip import Clip
from m3t.corpora.listing import Collector, Listing, media_folder, with_kind
from m3t.corpora.splits import SPLITS

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
            folder = PurePosixPath(video).parent  # "<name>/1" in both releases
            if not video or folder == PurePosixPath("."):
                out.quarantine(path, row, name, f"video column {video!r} names no frame folder; expected "
                                                "'<name>/1/*.png'")
                continue
            media = PurePosixPath(cfg.frames_dir) / split / folder
            unsafe = out.media_problem(media.as_posix())  # before probing the tree for a 1/ folder
            if unsafe is not None:
                out.quarantine(path, row, name, f"{unsafe} (video column {video!r})")
                continue
            if folder.name == "1" and not _is_dir(self.root / media):
                media = media.parent  # 2014-T: the images sit in <split>/<name>/ itself
            clip = Clip(id=name, corpus=self.name, split=split, language=cfg.language, signer=speaker or "unknown",
                        text=translation, gloss=orth, media=media.as_posix(), fps=cfg.fps,
                        extra=with_kind("frames", frame_glob=PurePosixPath(video).name, start=start, end=end,
                                        annotation=f"{out.rel(path)}:{row}"))
            out.add(clip, path, row, check, unique_media=True)


def _is_dir(path: Path) -> bool:
    """``path.is_dir()``, false for a name the file system refuses (a name too long): the media check then
    quarantines the row naming the reason."""
    try:
        return path.is_dir()
    except OSError:
        return False
