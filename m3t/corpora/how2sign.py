"""How2Sign (American Sign Language instructional videos) as sentence-level video clips.

Layout, either as the official ``download_how2sign.sh`` builds it (``rgb_front_clips``,
``english_translation_re-aligned``)::

    <root>/sentence_level/{train,val,test}/text/en/raw_text/re_aligned/how2sign_realigned_{split}.csv
    <root>/sentence_level/{train,val,test}/rgb_front/raw_videos/<SENTENCE_NAME>.mp4

or as the website's archives unpack by hand, next to the three CSVs::

    <root>/how2sign_realigned_{train,val,test}.csv
    <root>/{train,val,test}_rgb_front_clips/raw_videos/<SENTENCE_NAME>.mp4

The realigned CSVs are tab-separated with the header
``VIDEO_ID  VIDEO_NAME  SENTENCE_ID  SENTENCE_NAME  START_REALIGNED  END_REALIGNED  SENTENCE``, e.g.
``--7E2sU6zP4  --7E2sU6zP4-5-rgb_front  --7E2sU6zP4_10  --7E2sU6zP4_10-5-rgb_front  129.06  142.48  And I call
them decorative elements ...``. The times are seconds in the full video ``VIDEO_NAME`` (How2Sign's answer in
how2sign.github.io issue 9), not in the sentence clip, so they are kept in ``extra`` (``start_s``, ``end_s``) and
never used to cut the clip. ``val`` becomes split ``dev``. How2Sign has no signer column, so signer is
``"unknown"`` (nothing is inferred).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from m3t.corpora.annotation_files import check_header, find_file, read_lines
from m3t.corpora.base import CorpusAdapter
from m3t.corpora.clip import Clip
from m3t.corpora.listing import Collector, CorpusError, Listing, media_file, with_kind

COLUMNS = ("VIDEO_ID", "VIDEO_NAME", "SENTENCE_ID", "SENTENCE_NAME", "START_REALIGNED", "END_REALIGNED", "SENTENCE")
HEADER = "\t".join(COLUMNS)
SPLIT_NAMES = {"train": "train", "val": "dev", "test": "test"}  # How2Sign name -> project split
CLIP_DIRS = ("sentence_level/{split}/rgb_front/raw_videos", "{split}_rgb_front_clips/raw_videos")
HINT = ("Point the corpus root at the How2Sign folder, or set option annotations_dir to the folder holding "
        "how2sign_realigned_<split>.csv and clips_dir to the sentence clip folders.")


@dataclass(frozen=True)
class How2SignConfig:
    """Options (params.yaml ``corpora.how2sign``); ``{split}`` in paths is How2Sign's name (train / val / test)."""

    annotations_dir: str = ""  # default: the root, then sentence_level/{split}/text/en/raw_text/re_aligned
    clips_dir: str = ""  # "" = the first of CLIP_DIRS that exists, per split
    video_suffix: str = ".mp4"
    fps: float = 24.0  # the front-camera videos of How2Sign
    language: str = "ASL"

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ValueError(f"corpora.how2sign.fps must be > 0, got {self.fps}")


class How2SignCorpus(CorpusAdapter):
    """Lists How2Sign sentence clips; bad rows (columns, times, empty sentence, missing video) are quarantined."""

    name = "how2sign"
    config_type = How2SignConfig

    def annotation_file(self, split_name: str) -> Path:
        cfg = self.config
        places = ([self.root / cfg.annotations_dir.format(split=split_name)] if cfg.annotations_dir else
                  [self.root, self.root / "sentence_level" / split_name / "text/en/raw_text/re_aligned"])
        return find_file(f"how2sign_realigned_{split_name}.csv", places, HINT)

    def clips_dir(self, split_name: str) -> PurePosixPath:
        """The sentence-clip folder of one split: option ``clips_dir``, else the first of :data:`CLIP_DIRS`."""
        if self.config.clips_dir:
            return PurePosixPath(self.config.clips_dir.format(split=split_name))
        candidates = [c.format(split=split_name) for c in CLIP_DIRS]
        for candidate in candidates:
            if (self.root / candidate).is_dir():
                return PurePosixPath(candidate)
        looked = ", ".join(str(self.root / c) for c in candidates)
        raise CorpusError(f"no How2Sign clip folder for split {split_name} (looked in {looked}); unpack "
                          f"{split_name}_rgb_front_clips.zip there or set corpora.how2sign.options.clips_dir. {HINT}")

    def listing(self) -> Listing:
        out = Collector(self.root)
        for split_name, split in SPLIT_NAMES.items():
            self._list_split(split_name, split, self.annotation_file(split_name), out)
        return out.listing()

    def _list_split(self, split_name: str, split: str, path: Path, out: Collector) -> None:
        cfg = self.config
        lines = read_lines(path, HINT)
        check_header(path, lines, HEADER, f"Is this a How2Sign realigned CSV (tab-separated)? {HINT}")
        clips_dir = self.clips_dir(split_name)
        for row, line in enumerate(lines[1:], start=2):
            if not line.strip():
                continue
            cols = line.split("\t")
            if len(cols) != len(COLUMNS):
                out.quarantine(path, row, None, f"malformed row: {len(cols)} tab-separated columns, expected "
                                                f"{len(COLUMNS)} ({' '.join(COLUMNS)})")
                continue
            video_id, video_name, sentence_id, sentence_name, start, end, sentence = (c.strip() for c in cols)
            if not sentence_name:
                out.quarantine(path, row, None, "empty SENTENCE_NAME")
                continue
            times = _times(start, end)
            if isinstance(times, str):
                out.quarantine(path, row, sentence_name, times)
                continue
            if not sentence:
                out.quarantine(path, row, sentence_name, "empty SENTENCE")
                continue
            clip = Clip(id=sentence_name, corpus=self.name, split=split, language=cfg.language, signer="unknown",
                        text=sentence, gloss="", media=(clips_dir / f"{sentence_name}{cfg.video_suffix}").as_posix(),
                        fps=cfg.fps,
                        extra=with_kind("video", start_s=times[0], end_s=times[1], video_id=video_id,
                                        video_name=video_name, sentence_id=sentence_id,
                                        annotation=f"{out.rel(path)}:{row}"))
            out.add(clip, path, row, media_file)


def _times(start: str, end: str) -> tuple[float, float] | str:
    """(start, end) seconds, or the quarantine reason."""
    try:
        s, e = float(start), float(end)
    except ValueError:
        return f"bad times: START_REALIGNED={start!r}, END_REALIGNED={end!r} are not numbers"
    if not (math.isfinite(s) and math.isfinite(e)) or s < 0:
        return f"bad times: start {start} / end {end} must be finite and start >= 0"
    if e <= s:
        return f"bad times: end {end} s <= start {start} s"
    return s, e
