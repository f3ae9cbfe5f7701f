"""Intervals and verdicts for the papers' claims: a two-level bootstrap over training seeds and test clips.

A claim compares two variants A and B on one metric, measured per test clip for each of R seeds (independent
trainings). The compared quantity is the mean over clips of B - A, each side averaged over its seeds. Its interval
is a percentile **hierarchical bootstrap**: each resample draws A's R seeds and B's R seeds with replacement
(independently: seed s of A and seed s of B are different models) and C clips with replacement (jointly: the clips
are paired), and takes the same mean. The clips alone (the interval this module gave first) ignore how much a
retrained model moves: two runs of the study read SGSA vs PT back-translation +1.4 [-1.3, 4.2] and then
+5.0 [1.9, 8.5], PT's mean alone moving 37.1 -> 33.6 from a retrain on fits 0.02 mm apart. With one seed only
the clips are resampled, and nothing in the interval speaks for training noise (claims ask for several seeds).
Verdicts read only that interval:

- :func:`verdict_better` ("B beats A"): **reproduced** when the whole interval lies on B's side of 0, **not
  reproduced** when it lies on A's side, **inconclusive** when it straddles 0;
- :func:`verdict_within` ("B stays at A", "falls to chance"): **reproduced** when the whole interval lies
  within +-margin of the target, **not reproduced** when it lies wholly outside that band, **inconclusive**
  otherwise. The margin is part of the claim and is reported beside it.

Axis legend: R seeds, C clips.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

REPRODUCED, NOT_REPRODUCED, INCONCLUSIVE = "reproduced", "not reproduced", "inconclusive"
_CHUNK = 256  # resamples drawn at a time (memory 256 x C)


def bootstrap_interval(values: np.ndarray, rng: np.random.Generator, resamples: int = 2000,
                       confidence: float = 0.95) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean of ``values`` (C,) over resampled clips; NaNs for C = 0."""
    values = np.asarray(values, dtype=np.float64)
    n = values.size
    if n == 0:
        return math.nan, math.nan
    if resamples < 1 or not 0.0 < confidence < 1.0:
        raise ValueError(f"need resamples >= 1 and 0 < confidence < 1, got {resamples}, {confidence}")
    means = np.concatenate([values[rng.integers(0, n, size=(min(_CHUNK, resamples - i), n))].mean(1)
                            for i in range(0, resamples, _CHUNK)])
    alpha = (1.0 - confidence) / 2
    low, high = np.quantile(means, [alpha, 1.0 - alpha])
    return float(low), float(high)


@dataclass(frozen=True)
class Paired:
    """B - A on one metric over seeds and clips: means, the seeds' spread, the difference and its interval."""

    mean_a: float  # over seeds and clips
    mean_b: float
    std_a: float  # of the per-seed means over seeds (0 for one seed)
    std_b: float
    difference: float  # mean over clips of the seed-averaged B - A
    interval: tuple[float, float]
    seeds: int
    clips: int

    def as_dict(self) -> dict:
        return asdict(self)


def _per_seed(values: np.ndarray, name: str) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[None]
    if values.ndim != 2:
        raise ValueError(f"{name}: expected (seeds, clips) values, got shape {values.shape}")
    return values


def _mean(values: np.ndarray, axis: int) -> np.ndarray:
    """Mean over ``axis`` of the finite entries (NaN where there is none), without warnings."""
    finite = np.isfinite(values)
    count = finite.sum(axis)
    total = np.where(finite, values, 0.0).sum(axis)
    return np.divide(total, count, out=np.full(total.shape, np.nan), where=count > 0)


def hierarchical_interval(a: np.ndarray, b: np.ndarray, rng: np.random.Generator, resamples: int = 2000,
                          confidence: float = 0.95) -> tuple[float, float]:
    """Percentile interval of mean over clips of (mean over B's seeds - mean over A's seeds), with A's seeds, B's
    seeds and the (shared) clips resampled with replacement (module docstring). a, b (R, C), NaN where a seed did
    not score a clip; NaNs for C = 0."""
    if resamples < 1 or not 0.0 < confidence < 1.0:
        raise ValueError(f"need resamples >= 1 and 0 < confidence < 1, got {resamples}, {confidence}")
    r, c = a.shape
    if c == 0:
        return math.nan, math.nan
    means = []
    for start in range(0, resamples, _CHUNK):
        k = min(_CHUNK, resamples - start)
        clips = rng.integers(0, c, size=(k, 1, c))
        seed_a, seed_b = rng.integers(0, r, size=(k, r, 1)), rng.integers(0, r, size=(k, r, 1))
        drawn_a, drawn_b = a[seed_a, clips], b[seed_b, clips]  # (k, R, C)
        means.append(_mean(_mean(drawn_b, 1) - _mean(drawn_a, 1), 1))  # (k,)
    means = np.concatenate(means)
    means = means[np.isfinite(means)]
    if not means.size:
        return math.nan, math.nan
    alpha = (1.0 - confidence) / 2
    low, high = np.quantile(means, [alpha, 1.0 - alpha])
    return float(low), float(high)


def paired(a: np.ndarray, b: np.ndarray, rng: np.random.Generator, resamples: int = 2000,
           confidence: float = 0.95) -> Paired:
    """Compare B with A from per-clip values (R, C) or (C,) on the same clips in the same order, with the
    :func:`hierarchical_interval`. A clip a seed did not score is NaN there (that seed leaves the clip's average);
    a clip no seed scored on both sides is left out of everything."""
    a, b = _per_seed(a, "A"), _per_seed(b, "B")
    if a.shape != b.shape:
        raise ValueError(f"A and B must be scored by the same seeds on the same clips: {a.shape} vs {b.shape}")
    both = np.isfinite(a) & np.isfinite(b)
    a, b = np.where(both, a, np.nan), np.where(both, b, np.nan)
    diff = _mean(b - a, 0)
    kept = np.isfinite(diff)
    a, b, diff = a[:, kept], b[:, kept], diff[kept]
    seed_a, seed_b = _mean(a, 1), _mean(b, 1)
    return Paired(mean_a=float(_mean(a.reshape(-1), 0)), mean_b=float(_mean(b.reshape(-1), 0)),
                  std_a=float(np.nanstd(seed_a)) if np.isfinite(seed_a).any() else math.nan,
                  std_b=float(np.nanstd(seed_b)) if np.isfinite(seed_b).any() else math.nan,
                  difference=float(diff.mean()) if diff.size else math.nan,
                  interval=hierarchical_interval(a, b, rng, resamples, confidence),
                  seeds=int(a.shape[0]), clips=int(diff.size))


def verdict_better(interval: tuple[float, float], lower_is_better: bool) -> str:
    """"B beats A" from the interval of B - A: reproduced / not reproduced / inconclusive (straddles 0)."""
    low, high = interval
    if not (math.isfinite(low) and math.isfinite(high)):
        return INCONCLUSIVE
    b_side = high < 0 if lower_is_better else low > 0
    a_side = low > 0 if lower_is_better else high < 0
    return REPRODUCED if b_side else NOT_REPRODUCED if a_side else INCONCLUSIVE


def verdict_within(interval: tuple[float, float], target: float, margin: float) -> str:
    """"The value stays within +-``margin`` of ``target``" from its interval: reproduced when the interval lies
    inside the band, not reproduced when it lies wholly outside, inconclusive when it overlaps an edge."""
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    low, high = interval
    if not (math.isfinite(low) and math.isfinite(high)):
        return INCONCLUSIVE
    if target - margin <= low and high <= target + margin:
        return REPRODUCED
    if high < target - margin or low > target + margin:
        return NOT_REPRODUCED
    return INCONCLUSIVE


def agreeing_digits(a: float, b: float) -> int | None:
    """How many leading significant digits two measurements of one figure share: floor(-log10(|a - b| / max(|a|,
    |b|))), capped at 15 (float64); None when either is not finite. 0 when they differ in the first digit."""
    if not (math.isfinite(a) and math.isfinite(b)):
        return None
    scale = max(abs(a), abs(b))
    if a == b or scale == 0.0:
        return 15
    return max(0, min(15, math.floor(-math.log10(abs(a - b) / scale))))
