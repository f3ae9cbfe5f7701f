"""The real embedded corpus: fingerspelled letters shipped in the installed ``spoken-to-signed`` wheel.

``spoken_to_signed/assets/fingerspelling_lexicon/`` holds ``data.csv`` (columns ``path, spoken_language,
signed_language, start, end, words, glosses, priority``; one row per letter clip, times in ms), ``index.csv``
(the same rows plus aliases written by the package's ``create_index.py``, e.g. the ASL letters again as ``fsl``)
and one folder per signed-language code (ISO 639-3: ``ase``, ``gsg``, ...) of MediaPipe-Holistic ``.pose``
files. The files are read in place through importlib, never copied.

Two kinds of clips:

- *letters* (media kind ``pose``): one clip per table row; ``label`` = the letter's position among its
  language's rows (stable: a quarantined row keeps its number), text = gloss = the letter, language = the code.
- *spelled words* (media kind ``spelled``): words drawn from each language's letters by a generator seeded with
  ``(seed, language)``; a word's clip is its letters' clips concatenated (:meth:`FingerspellingCorpus.spell`),
  resampled to the highest letter fps when letters differ. Letters may be several characters (``SCH``, ``Dž``):
  words are split by greedy longest match, case-insensitively. Media is the language folder; the letter files
  are listed in extra ``letter_paths``.

Splits are a deterministic hash of the clip id.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path, PurePosixPath

import numpy as np

from m3t.corpora.annotation_files import csv_rows, read_lines
from m3t.corpora.base import CorpusAdapter
from m3t.corpora.clip import Clip
from m3t.corpora.listing import Collector, CorpusError, Listing, with_kind
from m3t.corpora.posefile import PoseData, components_text, read_pose, read_pose_info
from m3t.corpora.splits import check_fractions, hash_split, hash_unit

PACKAGE = "spoken_to_signed"
ASSET_DIR = "assets/fingerspelling_lexicon"
COLUMNS = ("path", "spoken_language", "signed_language", "start", "end", "words", "glosses", "priority")


def lexicon_root() -> Path:
    """The lexicon folder inside the installed wheel (a real folder: the wheel installs unzipped)."""
    from importlib.resources import files

    try:
        root = files(PACKAGE) / ASSET_DIR
    except ModuleNotFoundError as exc:
        raise CorpusError("the fingerspelling corpus ships with spoken-to-signed: "
                          "pip install spoken-to-signed") from exc
    if not isinstance(root, Path) or not root.is_dir():
        raise CorpusError(f"{root} is not a folder on disk; install spoken-to-signed as a regular (unzipped) package")
    return root


@dataclass(frozen=True)
class FingerspellingConfig:
    """Options (params.yaml ``corpora.fingerspelling``)."""

    table: str = "data.csv"  # "index.csv" adds the package's aliased languages (fsl = ase letters)
    languages: tuple[str, ...] = ()  # signed-language codes to keep; empty = all
    words_per_language: int = 20
    min_letters: int = 2
    max_letters: int = 6
    seed: int = 0
    split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)

    def __post_init__(self) -> None:
        check_fractions(self.split_fractions, "corpora.fingerspelling.split_fractions")
        if self.words_per_language < 0 or not 1 <= self.min_letters <= self.max_letters:
            raise ValueError("corpora.fingerspelling: need words_per_language >= 0 and 1 <= min_letters <= max_letters"
                             f", got {self.words_per_language}, {self.min_letters}, {self.max_letters}")


@dataclass(frozen=True)
class Letter:
    letter: str
    language: str
    label: int
    path: str  # relative to the lexicon root
    row: int
    spoken_language: str
    start_ms: str
    end_ms: str


class FingerspellingCorpus(CorpusAdapter):
    """Letter clips and spelled-word clips of the packaged fingerspelling lexicon."""

    name = "fingerspelling"
    config_type = FingerspellingConfig

    def __init__(self, root: str | Path | None = None, config: FingerspellingConfig | None = None):
        super().__init__(root or lexicon_root(), config)

    def table(self, out: Collector | None = None) -> list[Letter]:
        """The letter rows of the table; bad rows go to ``out`` (or are skipped when ``out`` is None)."""
        cfg = self.config
        path = self.root / cfg.table
        lines = read_lines(path, "Reinstall spoken-to-signed.")
        fieldnames, records = csv_rows(lines, path, ",".join(COLUMNS), out)
        missing = [c for c in COLUMNS if c not in fieldnames]
        if missing:
            raise CorpusError(f"{path} line 1: columns {list(fieldnames)} lack {missing}; "
                              f"expected {','.join(COLUMNS)}")
        letters, seen, counts = [], set(), {}
        for row, r in records:
            language = (r.get("signed_language") or "").strip()
            label = counts.get(language, 0)
            counts[language] = label + 1
            if cfg.languages and language not in cfg.languages:
                continue
            letter, rel = (r.get("words") or "").strip(), PurePosixPath((r.get("path") or "").strip())
            problem = None
            if None in r or not language or not letter or not rel.name:
                problem = "malformed row: empty signed_language, words or path, or extra columns"
            elif rel.is_absolute() or ".." in rel.parts:
                problem = f"path {rel} must be relative to the lexicon folder"
            elif (language, letter.upper()) in seen:
                problem = f"letter {letter!r} listed twice for {language}"
            if problem:
                if out is not None:
                    out.quarantine(path, row, None, problem)
                continue
            seen.add((language, letter.upper()))
            letters.append(Letter(letter, language, label, rel.as_posix(), row, r.get("spoken_language") or "",
                                  r.get("start") or "", r.get("end") or ""))
        unknown = [code for code in cfg.languages if code not in counts]
        if unknown:  # a typo in corpora.fingerspelling.options.languages would otherwise list nothing for it
            raise CorpusError(f"corpora.fingerspelling.languages: {unknown} not in {path}; its signed languages are "
                              f"{', '.join(sorted(c for c in counts if c))}")
        return letters

    def letters(self, language: str) -> dict[str, str]:
        """letter -> ``.pose`` path (relative to the root) of one language."""
        found = {x.letter: x.path for x in self.table() if x.language == language}
        if not found:
            raise CorpusError(f"no letters for signed language {language!r} in {self.root / self.config.table}")
        return found

    def tokenize(self, word: str, language: str) -> list[str]:
        """Split ``word`` into the language's letters: greedy longest match, case-insensitive, spaces skipped."""
        return split_letters(word, list(self.letters(language)), language)

    def spell(self, word: str, language: str) -> PoseData:
        """The word's letter clips concatenated in time (T, K, 3); letters resampled to the highest fps."""
        paths = self.letters(language)
        return spell_files([self.root / paths[x] for x in self.tokenize(word, language)])

    def listing(self) -> Listing:
        cfg = self.config
        out = Collector(self.root)
        listed: dict[str, list[tuple[Letter, Clip]]] = {}
        for x in self.table(out):
            clip_id = f"{x.language}-{PurePosixPath(x.path).stem}"
            try:
                info = read_pose_info(self.root / x.path)
            except CorpusError as exc:
                out.quarantine(self.root / cfg.table, x.row, clip_id, str(exc).replace(str(self.root / x.path), x.path))
                continue
            clip = Clip(id=clip_id, corpus=self.name, split=hash_split(clip_id, cfg.split_fractions, "fingerspelling"),
                        language=x.language, signer="unknown", text=x.letter, gloss=x.letter, media=x.path,
                        fps=info.fps, label=x.label,
                        extra=with_kind("pose", clip_type="letter", spoken_language=x.spoken_language,
                                        start_ms=x.start_ms, end_ms=x.end_ms, frames=info.frames,
                                        components=components_text(info.components)))
            if out.add(clip, self.root / cfg.table, x.row):
                listed.setdefault(x.language, []).append((x, clip))
        for language, letters in listed.items():
            for clip in self._spelled(language, letters):
                out.add(clip, self.root / cfg.table, None)
        return out.listing()

    def _spelled(self, language: str, letters: list[tuple[Letter, Clip]]) -> list[Clip]:
        cfg = self.config
        rng = np.random.default_rng([cfg.seed, int(hash_unit(language, "fingerspelling-words") * 2 ** 32)])
        by_letter = {x.letter: clip for x, clip in letters}
        names = sorted(by_letter)
        words: list[str] = []
        for _ in range(20 * cfg.words_per_language):  # bounded: tiny alphabets may have few distinct words
            if len(words) == cfg.words_per_language:
                break
            n = int(rng.integers(cfg.min_letters, cfg.max_letters + 1))
            word = "".join(names[int(i)] for i in rng.integers(len(names), size=n))
            if word not in words:
                words.append(word)
        clips = []
        for i, word in enumerate(words):
            parts = [by_letter[x] for x in split_letters(word, names, language)]
            fps = max(c.fps for c in parts)
            frames = sum(_resampled_length(int(c.get("frames")), c.fps, fps) for c in parts)
            clip_id = f"{language}-spelled-{i:03d}"
            split = hash_split(clip_id, cfg.split_fractions, "fingerspelling")
            clips.append(Clip(id=clip_id, corpus=self.name, split=split, language=language, signer="unknown",
                              text=word, gloss=" ".join(c.text for c in parts),
                              media=PurePosixPath(parts[0].media).parent.as_posix(), fps=fps,
                              extra=with_kind("spelled", clip_type="spelled", frames=frames,
                                              letter_paths="|".join(c.media for c in parts))))
        return clips


def split_letters(word: str, letters: list[str], language: str) -> list[str]:
    """``word`` as a sequence of ``letters`` (greedy longest match, case-insensitive, spaces skipped)."""
    by_upper = {k.upper(): k for k in letters}
    longest = max(map(len, by_upper))
    text, out, i = word.upper(), [], 0
    while i < len(text):
        if text[i].isspace():
            i += 1
            continue
        for n in range(min(longest, len(text) - i), 0, -1):
            if text[i:i + n] in by_upper:
                out.append(by_upper[text[i:i + n]])
                i += n
                break
        else:
            raise CorpusError(f"{word!r}: {word[i]!r} cannot be fingerspelled in {language}; letters: "
                              f"{' '.join(sorted(by_upper.values()))}")
    return out


def _resampled_length(frames: int, fps: float, target: float) -> int:
    return frames if abs(fps - target) < 1e-6 else max(1, int(round(frames * target / fps)))


def resample(data: PoseData, fps: float) -> PoseData:
    """``data`` at ``fps``: linear in time where both neighbouring frames see a point, nearest frame otherwise."""
    T = data.points.shape[0]
    n = _resampled_length(T, data.fps, fps)
    if n == T and abs(data.fps - fps) < 1e-6:
        return data
    src = np.clip(np.arange(n) * (data.fps / fps), 0, T - 1)  # (n,) source frame positions
    lo = np.floor(src).astype(np.int64)
    hi = np.minimum(lo + 1, T - 1)
    w = (src - lo)[:, None]  # (n, 1)
    near = np.where(w[:, 0] >= 0.5, hi, lo)
    both = (data.confidence[lo] > 0) & (data.confidence[hi] > 0)  # (n, K)
    points = np.where(both[..., None], (1 - w[..., None]) * data.points[lo] + w[..., None] * data.points[hi],
                      data.points[near])  # (n, K, 3)
    conf = np.where(both, (1 - w) * data.confidence[lo] + w * data.confidence[hi], data.confidence[near])  # (n, K)
    return replace(data, points=points.astype(np.float32), confidence=conf.astype(np.float32), fps=float(fps))


def concatenate(parts: list[PoseData]) -> PoseData:
    """Clips one after another in time, at the highest fps among them; they must share one point layout."""
    if not parts:
        raise ValueError("nothing to concatenate: the word has no letters")
    layout = parts[0].components
    for p in parts[1:]:
        if p.components != layout:
            raise CorpusError(f"letter clips have different point layouts ({components_text(layout)} vs "
                              f"{components_text(p.components)}); they cannot be concatenated")
    fps = max(p.fps for p in parts)
    same = [resample(p, fps) for p in parts]
    return replace(parts[0], points=np.concatenate([p.points for p in same]),
                   confidence=np.concatenate([p.confidence for p in same]), fps=fps, dims=min(p.dims for p in parts))


def spell_files(paths: list[Path]) -> PoseData:
    """The ``.pose`` files of a word's letters, read and concatenated (what a ``spelled`` clip's media is)."""
    return concatenate([read_pose(p) for p in paths])


def spelled_paths(clip: Clip, root: Path) -> list[Path]:
    """The letter files of a ``spelled`` clip (its extra ``letter_paths``, relative to ``root``)."""
    letters = clip.get("letter_paths") or ""
    if not letters:
        raise CorpusError(f"spelled clip {clip.id} lists no letter_paths; re-list the fingerspelling corpus")
    return [root / p for p in letters.split("|")]


def spell(word: str, language: str) -> PoseData:
    """Fingerspell ``word`` in ``language`` (a signed-language code) from the packaged lexicon."""
    return FingerspellingCorpus().spell(word, language)
