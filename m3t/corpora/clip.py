"""The uniform clip record every corpus adapter produces and every later stage consumes."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Clip:
    """One signing clip as listed by a corpus adapter (no media loaded).

    ``media`` is a path relative to the corpus root (video file, frame folder, ``.pose`` file or, for the
    synthetic corpus, the ground-truth motion file). ``label`` is the class for isolated-sign corpora
    (``None`` for sentence clips). ``extra`` carries corpus-specific fields as strings.
    """

    id: str
    corpus: str
    split: str  # "train" | "dev" | "test"
    language: str  # sign language code, e.g. "ASL", "CSL", "DGS"
    signer: str
    text: str
    gloss: str
    media: str
    fps: float
    label: int | None = None
    extra: tuple[tuple[str, str], ...] = field(default_factory=tuple)

    def get(self, key: str, default: str | None = None) -> str | None:
        return dict(self.extra).get(key, default)
