"""params.yaml ``baselines``: the copy baselines scored beside the models (evaluate-baselines)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

BASELINE_SYSTEMS = ("retrieval", "lexicon")


@dataclass(frozen=True)
class BaselinesConfig:
    """params.yaml ``baselines``: which baselines evaluate-baselines produces and scores, and the lexicon's two
    settings (:mod:`m3t.production.lexicon`). Nothing here is fitted to any data."""

    systems: tuple[str, ...] = BASELINE_SYSTEMS
    lexicon_input: Literal["gloss", "words"] = "gloss"  # gloss: the corpus's gloss annotation (oracle text-to-gloss,
    # the Gloss2Pose setting); words: the text's words (every clip without glosses falls back to them)
    transition_frames: int = 6  # interpolated frames between two stored signs

    def __post_init__(self) -> None:
        unknown = [s for s in self.systems if s not in BASELINE_SYSTEMS]
        if unknown or not self.systems:
            raise ValueError(f"baselines.systems {list(self.systems)}: expected a non-empty subset of "
                             f"{', '.join(BASELINE_SYSTEMS)}")
        if self.lexicon_input not in ("gloss", "words"):
            raise ValueError(f"baselines.lexicon_input {self.lexicon_input!r} unknown; allowed: gloss, words")
        if self.transition_frames < 0:
            raise ValueError(f"baselines.transition_frames must be >= 0, got {self.transition_frames}")
