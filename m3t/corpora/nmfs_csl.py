"""NMFs-CSL (isolated Chinese Sign Language signs with non-manual features) as labelled video clips.

Layout::

    <root>/dictionary.txt      one class per line: "<index>\\t<gloss>" or "<index> <gloss>"
    <root>/train.txt           one clip per line: "<relative video path> <class index>"
    <root>/test.txt            (a line may give only "<class folder>/<video>": the class is then the folder's
                               number, as in the UCF101-style test lists read by the dataset authors' group)
    <root>/video/...           the videos; list paths are relative to video/ (a path that already starts
                               with "video/" is taken relative to the root)

Every list path goes through :func:`m3t.corpora.listing.media_path_problem`: absolute paths, ``..`` components and
symbolic links out of the root are quarantined.

The corpus has no dev split. ``dev_fraction`` > 0 moves train clips to ``dev`` when
``hash_unit(clip id, salt="nmfs_csl-dev") < dev_fraction``: deterministic, independent of file order, and the
same clip always lands in the same split.

The *confusing* vs *normal* subsets come only from the official subset list the user supplies (option
``confusing_list``: one class index per line, the confusing classes). They are never inferred from label
ranges; without the list every clip's subset is ``"unknown"`` and :meth:`NmfsCslCorpus.subset` raises.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import PurePosixPath

from m3t.corpora.annotation_files import integer_field, read_lines
from m3t.corpora.base import CorpusAdapter
from m3t.corpora.clip import Clip
from m3t.corpora.listing import Collector, CorpusError, Listing, media_file, with_kind
from m3t.corpora.splits import hash_unit

HINT = "Point the corpus root at the NMFs-CSL folder (the one holding dictionary.txt, train.txt, test.txt, video/)."
SUBSET_HINT = ("NMFs-CSL's confusing / normal subsets are defined only by the official list; set option "
               "corpora.nmfs_csl.options.confusing_list to that file (one confusing class index per line).")


@dataclass(frozen=True)
class NmfsCslConfig:
    """Options (params.yaml ``corpora.nmfs_csl``); paths relative to the root unless absolute."""

    dictionary: str = "dictionary.txt"
    train_list: str = "train.txt"
    test_list: str = "test.txt"
    video_dir: str = "video"
    confusing_list: str = ""  # the official confusing-class list; empty = subsets unknown
    fps: float = 30.0
    dev_fraction: float = 0.0
    language: str = "CSL"

    def __post_init__(self) -> None:
        if self.fps <= 0:
            raise ValueError(f"corpora.nmfs_csl.fps must be > 0, got {self.fps}")
        if not 0.0 <= self.dev_fraction < 1.0:
            raise ValueError(f"corpora.nmfs_csl.dev_fraction must be in [0, 1), got {self.dev_fraction}")


class NmfsCslCorpus(CorpusAdapter):
    """Lists NMFs-CSL clips with their class label; subsets only from the official list."""

    name = "nmfs_csl"
    config_type = NmfsCslConfig

    def read_dictionary(self, out: Collector | None = None) -> dict[int, str]:
        """class index -> gloss; bad lines are quarantined into ``out`` (or raise when ``out`` is None)."""
        path = self.root / self.config.dictionary
        classes: dict[int, str] = {}
        for row, line in enumerate(read_lines(path, HINT), start=1):
            if not line.strip():
                continue
            parts = line.strip().split(None, 1)
            index = integer_field(parts[0]) if len(parts) == 2 else None
            problem = None
            if index is None or index < 0:
                problem = f"malformed class line {line!r}: expected '<index><tab or space><gloss>'"
            elif index in classes:
                problem = f"class {parts[0]} defined twice"
            if problem is None:
                classes[index] = parts[1].strip()
            elif out is None:
                raise CorpusError(f"{path} line {row}: {problem}. {HINT}")
            else:
                out.quarantine(path, row, None, problem)
        if not classes:
            raise CorpusError(f"{path} holds no classes; expected '<index>\\t<gloss>' lines. {HINT}")
        return classes

    def confusing_classes(self, classes: dict[int, str], out: Collector | None = None) -> frozenset[int] | None:
        """The official confusing classes, or ``None`` without ``confusing_list``."""
        if not self.config.confusing_list:
            return None
        path = self.root / self.config.confusing_list
        found: set[int] = set()
        for row, line in enumerate(read_lines(path, SUBSET_HINT), start=1):
            text = line.strip()
            if not text:
                continue
            index, problem = integer_field(text), None
            if index is None or index < 0:
                problem = f"{text!r} is not a class index"
            elif index not in classes:
                problem = f"class {text} is not in {self.config.dictionary}"
            if problem is None:
                found.add(index)
            elif out is None:
                raise CorpusError(f"{path} line {row}: {problem}. {SUBSET_HINT}")
            else:
                out.quarantine(path, row, None, problem)
        return frozenset(found)

    def subset(self, label: int) -> str:
        """``"confusing"`` or ``"normal"`` for a class index; raises without the official list."""
        classes = self.read_dictionary()
        confusing = self.confusing_classes(classes)
        if confusing is None:
            raise CorpusError(f"the subset of class {label} is unknown. {SUBSET_HINT}")
        if label not in classes:
            raise CorpusError(f"class {label} is not in {self.root / self.config.dictionary}")
        return "confusing" if label in confusing else "normal"

    def listing(self) -> Listing:
        cfg = self.config
        out = Collector(self.root)
        classes = self.read_dictionary(out)
        confusing = self.confusing_classes(classes, out)
        for list_name, split in ((cfg.train_list, "train"), (cfg.test_list, "test")):
            path = self.root / list_name
            for row, line in enumerate(read_lines(path, HINT), start=1):
                if not line.strip():
                    continue
                parsed = _list_row(line)
                if isinstance(parsed, str):
                    out.quarantine(path, row, None, parsed)
                    continue
                video, label = parsed
                clip_id = video.with_suffix("").as_posix().replace("/", "__")
                if label not in classes:
                    out.quarantine(path, row, clip_id, f"class {label} is not in {cfg.dictionary}")
                    continue
                parts = video.parts
                media = video if parts and parts[0] == cfg.video_dir else PurePosixPath(cfg.video_dir) / video
                subset = "unknown" if confusing is None else ("confusing" if label in confusing else "normal")
                clip_split = split
                if split == "train" and hash_unit(clip_id, salt="nmfs_csl-dev") < cfg.dev_fraction:
                    clip_split = "dev"
                clip = Clip(id=clip_id, corpus=self.name, split=clip_split, language=cfg.language, signer="unknown",
                            text=classes[label], gloss=classes[label], media=media.as_posix(), fps=cfg.fps,
                            label=label, extra=with_kind("video", subset=subset, source_split=split))
                out.add(clip, path, row, media_file)
        return out.listing()


def _list_row(line: str) -> tuple[PurePosixPath, int] | str:
    """(video path, class) of a train / test list line, or the quarantine reason.

    ``"<path> <class>"`` (paths may hold spaces: the class is the last field) or ``"<class folder>/<file>"``
    whose first folder is the class number.
    """
    text = line.strip()
    parts = text.rsplit(None, 1)
    label = integer_field(parts[1]) if len(parts) == 2 else None
    if label is not None:
        return PurePosixPath(parts[0].replace("\\", "/")), label
    video = PurePosixPath(text.replace("\\", "/"))
    folder = integer_field(video.parts[0]) if len(video.parts) >= 2 else None
    if folder is not None and folder >= 0:
        return video, folder
    return (f"malformed row {line!r}: expected '<video path> <class index>' or '<class folder>/<video>' "
            "with a numeric class folder")
