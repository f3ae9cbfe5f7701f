"""Scoring the probe like M3T Tab. 4: Top-1 / Top-5 overall and on the *confusing* and *normal* subsets, each
with its number of clips and classes, a percentile bootstrap confidence interval over clips and its chance level.

- **Subsets** come from the clips: ``subset`` (NMFs-CSL, from the official confusing list) or ``group``
  (the embedded synthetic corpus). When any scored clip has neither, the subsets are reported unavailable
  with the reason, never guessed (NMFs-CSL: set ``corpora.nmfs_csl.options.confusing_list``).
- **Chance.** ``chance_top1`` / ``chance_top5``: a uniform guess over the probe's C classes, 1/C and min(5, C)/C.
  On the confusing subset the telling number is another one: a probe that gets the manual form right but reads
  nothing from the face picks among the k signs sharing that form, chance 1/k (50% for pairs). Where clips carry
  a ``pair`` id (synthetic corpus), ``pair_top1`` measures exactly that: the argmax over the pair's two classes
  only (chance 50%).
- **Bootstrap**: ``resamples`` draws of the scored clips with replacement (seeded); the interval is the
  central ``confidence`` share of the resampled accuracies (percentile method). It narrows as 1/sqrt(clips).

Axis legend: n clips, C classes.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from m3t.atomic import atomic_path
from m3t.corpora.clip import Clip
from m3t.metrics.stats import bootstrap_interval

SUBSETS = ("confusing", "normal")
PAIR_CHANCE_TOP1 = 50.0


def clip_subset(clip: Clip) -> str:
    """``confusing`` / ``normal`` from the clip's ``subset`` (NMFs-CSL) or ``group`` (synthetic), else ``unknown``."""
    value = clip.get("subset") or clip.get("group")
    return value if value in SUBSETS else "unknown"


def clip_pair(clip: Clip) -> str | None:
    """The id of the manual-identical pair a confusing clip belongs to (synthetic corpus), else None."""
    value = clip.get("pair")
    return None if value in (None, "", "-1") else value


def topk_hits(logits: torch.Tensor, targets: torch.Tensor, k: int) -> np.ndarray:
    """(n,) bool: the target is among the ``k`` highest logits (k capped at C). logits (n, C), targets (n,)."""
    if logits.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    top = logits.topk(min(k, logits.shape[1]), dim=-1).indices  # (n, k)
    return (top == targets[:, None]).any(-1).numpy()


def bootstrap_ci(hits: np.ndarray, resamples: int = 1000, confidence: float = 0.95,
                 seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval (in %) of the mean of ``hits`` (n,) over resampled clips; NaNs for n = 0."""
    low, high = bootstrap_interval(np.asarray(hits, dtype=np.float64), np.random.default_rng(seed), resamples,
                                   confidence)
    return 100.0 * low, 100.0 * high


@dataclass(frozen=True)
class Score:
    """An accuracy in % with its bootstrap interval and chance level."""

    value: float
    ci_low: float
    ci_high: float
    chance: float

    @classmethod
    def of(cls, hits: np.ndarray, chance: float, resamples: int, confidence: float, seed: int) -> Score:
        value = 100.0 * float(np.mean(hits)) if len(hits) else math.nan
        return cls(value, *bootstrap_ci(hits, resamples, confidence, seed), chance)


@dataclass(frozen=True)
class SubsetScore:
    """Top-1 / Top-5 on one subset (``overall``, ``confusing``, ``normal``); ``pair_top1`` on confusing only."""

    name: str
    clips: int
    classes: int
    top1: Score
    top5: Score
    pair_top1: Score | None = None
    pair_clips: int = 0

    def to_dict(self) -> dict[str, float]:
        out = {"clips": float(self.clips), "classes": float(self.classes)}
        scores = {"top1": self.top1, "top5": self.top5, "pair_top1": self.pair_top1}
        for key, score in scores.items():
            if score is not None:
                out.update({key: score.value, f"{key}_ci_low": score.ci_low, f"{key}_ci_high": score.ci_high,
                            f"{key}_chance": score.chance})
        if self.pair_top1 is not None:
            out["pair_clips"] = float(self.pair_clips)
        return out


@dataclass(frozen=True)
class Evaluation:
    """Scores of one probe on one split: ``overall`` always; the subsets when every clip has one."""

    scores: dict[str, SubsetScore]
    subsets_available: bool
    subsets_reason: str  # why the subsets are missing ("" when available)

    def to_dict(self) -> dict:
        out: dict = {name: s.to_dict() for name, s in self.scores.items()}
        out["subsets"] = {"available": self.subsets_available, "reason": self.subsets_reason}
        return out


def evaluations_from_flat(metrics: dict[str, float], reason: str = "") -> dict[str, Evaluation]:
    """Rebuild the evaluations from flat ``<variant>/<subset>/<key>`` numbers (an MLflow run's metrics)."""
    tree: dict[str, dict[str, dict[str, float]]] = {}
    for key, value in metrics.items():
        parts = key.split("/")
        if len(parts) == 3:
            tree.setdefault(parts[0], {}).setdefault(parts[1], {})[parts[2]] = value

    def score(d: dict[str, float], key: str) -> Score | None:
        if key not in d:
            return None
        return Score(d[key], d.get(f"{key}_ci_low", math.nan), d.get(f"{key}_ci_high", math.nan),
                     d.get(f"{key}_chance", math.nan))

    out = {}
    for variant, subsets in tree.items():
        scores = {name: SubsetScore(name, int(d.get("clips", 0)), int(d.get("classes", 0)), score(d, "top1"),
                                    score(d, "top5"), score(d, "pair_top1"), int(d.get("pair_clips", 0)))
                  for name, d in subsets.items() if "top1" in d}
        if "overall" in scores:
            available = all(name in scores for name in SUBSETS)
            out[variant] = Evaluation(scores, available, "" if available else reason or "subsets not reported")
    return out


def pair_hits(logits: torch.Tensor, targets: torch.Tensor, pairs: Sequence[str | None],
               pair_classes: dict[str, tuple[int, ...]]) -> np.ndarray:
    """(m,) bool over the clips whose pair has exactly two classes: the target beats its pair partner."""
    hits = []
    for i, pair in enumerate(pairs):
        members = pair_classes.get(pair) if pair is not None else None
        if members is None or len(members) != 2 or int(targets[i]) not in members:
            continue
        best = max(members, key=lambda c: float(logits[i, c]))
        hits.append(best == int(targets[i]))
    return np.asarray(hits, dtype=bool)


def evaluate_logits(logits: torch.Tensor, targets: torch.Tensor, clips: Sequence[Clip],
                    pair_classes: dict[str, tuple[int, ...]] | None = None, resamples: int = 1000,
                    confidence: float = 0.95, seed: int = 0, subset_hint: str = "") -> Evaluation:
    """Score logits (n, C) against targets (n,) of ``clips``; ``pair_classes``: pair id -> its two class
    indices (for ``pair_top1``); ``subset_hint``: what the user can do when the subsets are unknown."""
    num_classes = logits.shape[1]
    hits1, hits5 = topk_hits(logits, targets, 1), topk_hits(logits, targets, 5)
    chance1, chance5 = 100.0 / num_classes, 100.0 * min(5, num_classes) / num_classes

    def score(name: str, rows: np.ndarray) -> SubsetScore:
        return SubsetScore(name, int(rows.size), len(set(targets[rows].tolist())),
                           Score.of(hits1[rows], chance1, resamples, confidence, seed),
                           Score.of(hits5[rows], chance5, resamples, confidence, seed))

    scores = {"overall": score("overall", np.arange(len(clips)))}
    subsets = np.array([clip_subset(c) for c in clips])
    unknown = int((subsets == "unknown").sum())
    if unknown:
        reason = (f"{unknown} of {len(clips)} clips carry no confusing / normal subset (clip extra 'subset' or "
                  f"'group'); subset scores are not reported. {subset_hint}".strip())
        return Evaluation(scores, False, reason)
    for name in SUBSETS:
        scores[name] = score(name, np.flatnonzero(subsets == name))
    confusing = np.flatnonzero(subsets == "confusing")
    pairs = [clip_pair(clips[i]) for i in confusing]
    if pair_classes and confusing.size and all(p is not None for p in pairs):
        hits = pair_hits(logits[confusing], targets[confusing], pairs, pair_classes)
        if hits.size:
            scores["confusing"] = dataclasses.replace(
                scores["confusing"], pair_top1=Score.of(hits, PAIR_CHANCE_TOP1, resamples, confidence, seed),
                pair_clips=int(hits.size))
    return Evaluation(scores, True, "")


def plot_confusion(targets: np.ndarray, predictions: np.ndarray, class_names: Sequence[str], path: str | Path,
                   title: str) -> Path:
    """Row-normalised confusion matrix (true class per row) as a PNG; class names shown up to 60 classes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(class_names)
    counts = np.zeros((n, n))
    np.add.at(counts, (np.asarray(targets, dtype=int), np.asarray(predictions, dtype=int)), 1)
    rates = counts / np.maximum(counts.sum(1, keepdims=True), 1)
    size = min(12.0, 3.0 + 0.18 * n)
    fig, ax = plt.subplots(figsize=(size, size))
    image = ax.imshow(rates, cmap="Blues", vmin=0, vmax=1, interpolation="nearest")
    if n <= 60:
        ax.set_xticks(range(n), class_names, rotation=90, fontsize=6)
        ax.set_yticks(range(n), class_names, fontsize=6)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(title, fontsize=9)
    fig.colorbar(image, ax=ax, fraction=0.046, pad=0.04)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=100, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)
    return Path(path)
