"""Where every corpus' shards, tokens and the models trained on them live, derived from one params.yaml
section, ``data``.

``data.train_corpora`` names the corpora that the downstream stages train on **jointly** (one tokenizer
set and one SMLM on all of them, checkpoints selected on all their dev splits, as M3T trains on How2Sign +
CSL-Daily + Phoenix14T); switching or adding a training corpus is that one key (plus, for DVC, the
matching dependency lines in dvc.yaml, which ``tests/project/test_architecture.py`` checks). Each corpus keeps its
own folders (``<shards_root>/<corpus>``, ``<tokens_root>/<corpus>``); models and evaluation outputs have
one folder each.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class DataConfig:
    """params.yaml ``data``."""

    train_corpora: tuple[str, ...] = ("synthetic",)
    shards_root: str = "data/shards"  # fit-corpus writes <shards_root>/<corpus>/{train,dev,test}.parquet
    tokens_root: str = "data/tokens"  # tokenize writes <tokens_root>/<corpus>/{train,dev,test}.parquet
    models_dir: str = "models"  # <models_dir>/{tokenizers,smlm,slr,backtranslation}
    generated_dir: str = "data/generated"  # generate-smlm writes <generated_dir>/<corpora joined by '+'>
    metrics_dir: str = "metrics"  # evaluate-* write <metrics_dir>/<model>
    # clip kinds (a clip's ``kind``, e.g. ``isolated``) left out of the production models' data: the SMLM, SGSA /
    # PT and the back-translation judges, train and test; the tokenizers and the recognition probe keep them
    production_skip_kinds: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.train_corpora:
            raise ValueError("train_corpora is empty; name at least one corpus of `corpora` (e.g. [synthetic])")
        if len(set(self.train_corpora)) != len(self.train_corpora):
            raise ValueError(f"train_corpora {list(self.train_corpora)} names a corpus twice")

    def for_production(self, clips: Sequence[T]) -> list[T]:
        """``clips`` (fitted or token clips, anything with a ``.clip``) without the kinds ``production_skip_kinds``
        names; a clip without a ``kind`` is kept."""
        if not self.production_skip_kinds:
            return list(clips)
        return [c for c in clips if c.clip.get("kind") not in self.production_skip_kinds]

    def production_version(self, version: str) -> str:
        """A trainer's data version: the shards' digest, plus the kinds left out (so a resumable checkpoint is
        never continued on other clips)."""
        if not self.production_skip_kinds:
            return version
        return f"{version}-without-{'+'.join(self.production_skip_kinds)}"

    def shards_dir(self, corpus: str) -> Path:
        return Path(self.shards_root) / corpus

    def tokens_dir(self, corpus: str) -> Path:
        return Path(self.tokens_root) / corpus

    @property
    def shards_dirs(self) -> list[Path]:
        """The training corpora's shard folders, in ``train_corpora`` order."""
        return [self.shards_dir(c) for c in self.train_corpora]

    @property
    def tokens_dirs(self) -> list[Path]:
        return [self.tokens_dir(c) for c in self.train_corpora]

    @property
    def tokenizers_dir(self) -> Path:
        return Path(self.models_dir) / "tokenizers"

    @property
    def smlm_dir(self) -> Path:
        return Path(self.models_dir) / "smlm"

    @property
    def slr_dir(self) -> Path:
        return Path(self.models_dir) / "slr"

    @property
    def backtranslation_dir(self) -> Path:
        return Path(self.models_dir) / "backtranslation"

    @property
    def skeleton_judge_dir(self) -> Path:
        """The back-translation models that read skeletons (the judge of SGSA / PT)."""
        return Path(self.models_dir) / "backtranslation-skeleton"

    @property
    def sgsa_dir(self) -> Path:
        return Path(self.models_dir) / "sgsa"

    @property
    def generated(self) -> Path:
        return Path(self.generated_dir) / "+".join(self.train_corpora)

    def metrics(self, model: str) -> Path:
        return Path(self.metrics_dir) / model

