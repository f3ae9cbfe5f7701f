"""Intervals and verdicts of the claims (m3t.metrics.stats) on fixed inputs: a clear win, a clear loss, a
straddle, for a lower-is-better and a higher-is-better metric; seed noise in the interval; missing scores."""
from __future__ import annotations

import math

import numpy as np
import pytest

from m3t.metrics.stats import (
    INCONCLUSIVE,
    NOT_REPRODUCED,
    REPRODUCED,
    bootstrap_interval,
    hierarchical_interval,
    paired,
    verdict_better,
    verdict_within,
)

# per-clip DTW-JPE of variant A, 3 seeds x 8 clips
A = np.array([[3.0, 4.0, 5.0, 6.0, 3.5, 4.5, 5.5, 6.5],
              [3.2, 3.9, 5.1, 6.2, 3.4, 4.4, 5.6, 6.4],
              [2.9, 4.1, 4.9, 5.8, 3.6, 4.6, 5.4, 6.6]])


def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def test_a_clear_win_a_clear_loss_and_a_straddle():
    win = paired(A, A - 1.0, rng())  # B lower on every clip and seed
    low, high = win.interval  # A's seeds and B's seeds are resampled independently: A's seed spread (~0.1) shows
    assert win.difference == pytest.approx(-1.0) and -1.2 < low < -1.0 < high < -0.8
    assert verdict_better(win.interval, lower_is_better=True) == REPRODUCED
    assert verdict_better(win.interval, lower_is_better=False) == NOT_REPRODUCED
    loss = paired(A, A + 0.5, rng())
    assert verdict_better(loss.interval, lower_is_better=True) == NOT_REPRODUCED
    # half the clips better by 1, half worse by 1: the interval must straddle 0
    mixed = A + np.array([-1.0, 1.0] * 4)
    straddle = paired(A, mixed, rng())
    low, high = straddle.interval
    assert low < 0 < high and straddle.difference == pytest.approx(0.0)
    assert verdict_better(straddle.interval, lower_is_better=True) == INCONCLUSIVE
    assert verdict_better(straddle.interval, lower_is_better=False) == INCONCLUSIVE


def test_when_seed_noise_dominates_the_interval_says_inconclusive_where_clips_alone_said_reproduced():
    b = A.copy()
    b[0] -= 2.0  # one seed much better, the others equal: the clip averages move by 2/3
    pair = paired(A, b, rng())
    assert pair.seeds == 3 and pair.clips == 8
    assert pair.difference == pytest.approx(-2.0 / 3.0)
    # clips alone: every clip moved alike, so the interval is a point on B's side and B "wins"
    clips_only = bootstrap_interval((b - A).mean(0), rng())
    assert clips_only == pytest.approx((-2.0 / 3.0, -2.0 / 3.0))
    assert verdict_better(clips_only, lower_is_better=True) == REPRODUCED
    # seeds resampled too: B's mean depends on how often its one good seed is drawn (0-3 times of 3)
    low, high = pair.interval
    assert low == pytest.approx(-2.0, abs=0.1) and high >= 0.0
    assert verdict_better(pair.interval, lower_is_better=True) == INCONCLUSIVE
    assert pair.std_a == pytest.approx(float(np.std(A.mean(1))))
    assert pair.std_b > pair.std_a  # seed 0 of B is an outlier
    assert pair.mean_a == pytest.approx(A.mean()) and pair.mean_b == pytest.approx(b.mean())


def test_a_clip_a_seed_missed_is_averaged_over_the_other_seeds_and_unscored_clips_leave():
    b = A - 1.0
    b[1, 0] = np.nan  # seed 1 has no score for clip 0 on side B: that seed leaves clip 0 on both sides
    b[:, 3] = np.nan  # no seed scored clip 3: it leaves everything
    pair = paired(A, b, rng())
    assert pair.clips == 7
    assert pair.difference == pytest.approx(-1.0)
    kept = np.delete(A, 3, axis=1)
    kept_a = kept.copy()
    kept_a[1, 0] = np.nan
    assert pair.mean_a == pytest.approx(np.nanmean(kept_a))
    with pytest.raises(ValueError, match="same seeds on the same clips"):
        paired(A, A[:, :5], rng())


def test_bootstrap_interval_brackets_the_mean_and_narrows_with_more_clips():
    g = np.random.default_rng(1)
    few, many = g.normal(1.0, 1.0, 10), g.normal(1.0, 1.0, 1000)
    lo_few, hi_few = bootstrap_interval(few, rng())
    lo_many, hi_many = bootstrap_interval(many, rng())
    assert lo_few < few.mean() < hi_few and lo_many < many.mean() < hi_many
    assert hi_many - lo_many < (hi_few - lo_few) / 4
    assert bootstrap_interval(np.full(5, 2.0), rng()) == (2.0, 2.0)
    assert all(math.isnan(v) for v in bootstrap_interval(np.array([]), rng()))
    # a narrower confidence gives a narrower interval, and the same generator state gives the same interval
    assert np.subtract(*bootstrap_interval(few, rng(), confidence=0.5)[::-1]) < hi_few - lo_few
    assert bootstrap_interval(few, rng()) == (lo_few, hi_few)


def test_within_a_band_outside_it_and_overlapping_its_edge():
    chance = 50.0
    assert verdict_within((45.0, 58.0), chance, 10.0) == REPRODUCED
    assert verdict_within((65.0, 90.0), chance, 10.0) == NOT_REPRODUCED
    assert verdict_within((10.0, 35.0), chance, 10.0) == NOT_REPRODUCED
    assert verdict_within((55.0, 75.0), chance, 10.0) == INCONCLUSIVE
    assert verdict_within((math.nan, math.nan), chance, 10.0) == INCONCLUSIVE
    assert verdict_better((math.nan, 1.0), lower_is_better=True) == INCONCLUSIVE
    with pytest.raises(ValueError, match="margin"):
        verdict_within((0.0, 1.0), 0.0, -1.0)


def test_one_seed_resamples_only_the_clips():
    one = paired(A[0], A[0] - 1.0, rng())  # (C,): one seed
    assert one.seeds == 1 and one.interval == pytest.approx((-1.0, -1.0))
    mixed = paired(A[0], A[0] + np.array([-1.0, 1.0] * 4), rng())
    assert mixed.interval[0] < 0 < mixed.interval[1]


# ---- the intervals' arithmetic on scripted resamples: the draws are given, the interval follows by hand --------
class ScriptedDraws:
    """A generator whose ``integers`` returns the given index arrays in turn (each checked against the shape and
    range asked for), or, when none are given, seeded draws, recording every shape asked for."""

    def __init__(self, *draws):
        self.draws, self.sizes = [np.asarray(d) for d in draws], []
        self.fallback = np.random.default_rng(0)

    def integers(self, low, high, size):
        self.sizes.append(tuple(size))
        if not self.draws:
            return self.fallback.integers(low, high, size=size)
        out = self.draws.pop(0)
        assert out.shape == tuple(size) and low <= out.min() and out.max() < high
        return out


def test_the_clip_bootstrap_takes_the_percentiles_of_the_resampled_means():
    values = np.array([0.0, 10.0, 20.0, 30.0])
    draws = ScriptedDraws([[0, 0, 0, 0], [1, 1, 1, 1], [2, 2, 2, 2], [3, 3, 3, 3], [0, 1, 2, 3]])
    # resampled means 0, 10, 20, 30, 15; at 50% the 25th and 75th percentiles (linear): 10 and 20
    assert bootstrap_interval(values, draws, resamples=5, confidence=0.5) == pytest.approx((10.0, 20.0))
    draws = ScriptedDraws([[0, 0, 0, 0], [1, 1, 1, 1], [2, 2, 2, 2], [3, 3, 3, 3], [0, 1, 2, 3]])
    # at 90%: the 5th and 95th percentiles of 0, 10, 15, 20, 30: 0 + 0.2 x 10 = 2 and 20 + 0.8 x 10 = 28
    assert bootstrap_interval(values, draws, resamples=5, confidence=0.9) == pytest.approx((2.0, 28.0))
    draws = ScriptedDraws()
    bootstrap_interval(values, draws, resamples=300)  # drawn 256 resamples at a time
    assert draws.sizes == [(256, 4), (44, 4)]
    for bad in ({"resamples": 0}, {"confidence": 0.0}, {"confidence": 1.0}):
        with pytest.raises(ValueError, match="need resamples >= 1"):
            bootstrap_interval(values, rng(), **bad)


def test_the_hierarchical_bootstrap_resamples_clips_jointly_and_each_sides_seeds_independently():
    a = np.array([[0.0, 2.0], [4.0, 6.0]])  # (seeds, clips)
    b = np.array([[10.0, 10.0], [20.0, 20.0]])
    clips = [[[0, 1]], [[0, 0]], [[1, 1]]]  # (k, 1, C): one set of clips per resample, the same for every seed
    seeds_a = [[[0], [1]], [[0], [0]], [[1], [1]]]  # (k, R, 1)
    seeds_b = [[[0], [1]], [[1], [1]], [[0], [0]]]
    # resample 1: B's seeds 10, 20 -> 15 per clip, A's (0 + 4) / 2 = 2 and (2 + 6) / 2 = 4 -> 13, 11 -> 12
    # resample 2: clip 0 twice, B seed 1 (20), A seed 0 (0) -> 20; resample 3: clip 1, B seed 0 (10), A seed 1 (6) -> 4
    interval = hierarchical_interval(a, b, ScriptedDraws(clips, seeds_a, seeds_b), resamples=3, confidence=0.5)
    assert interval == pytest.approx((8.0, 16.0))  # 25th / 75th percentiles of 4, 12, 20
    # a seed that did not score a clip leaves that clip's seed average, not the clip
    holed = a.copy()
    holed[1, 1] = np.nan
    interval = hierarchical_interval(holed, b, ScriptedDraws([[[1, 1]]], [[[0], [1]]], [[[0], [0]]]), resamples=1)
    assert interval == pytest.approx((8.0, 8.0))  # clip 1: A = 2 (seed 1 missing), B = 10
    draws = ScriptedDraws()
    hierarchical_interval(np.zeros((3, 5)), np.ones((3, 5)), draws, resamples=260)
    assert draws.sizes == [(256, 1, 5), (256, 3, 1), (256, 3, 1), (4, 1, 5), (4, 3, 1), (4, 3, 1)]
    assert all(math.isnan(v) for v in hierarchical_interval(np.zeros((2, 0)), np.zeros((2, 0)), rng()))
    with pytest.raises(ValueError, match="need resamples >= 1"):
        hierarchical_interval(a, b, rng(), resamples=0)


def test_paired_means_spreads_and_difference_by_hand():
    a = np.array([[1.0, 3.0], [3.0, 5.0]])  # per-seed means 2, 4
    b = np.array([[2.0, 2.0], [2.0, 4.0]])  # per-seed means 2, 3
    pair = paired(a, b, ScriptedDraws(), resamples=10)
    assert (pair.mean_a, pair.mean_b) == pytest.approx((3.0, 2.5))
    assert (pair.std_a, pair.std_b) == pytest.approx((1.0, 0.5))  # over seeds, population (ddof 0)
    # B - A = [[1, -1], [-1, -1]]: over the seeds 0 for clip 0 and -1 for clip 1, -0.5 over the clips
    assert pair.difference == pytest.approx(-0.5)
    assert (pair.seeds, pair.clips) == (2, 2)
    assert pair.as_dict()["interval"] == pair.interval
    with pytest.raises(ValueError, match=r"expected \(seeds, clips\) values"):
        paired(np.zeros((1, 2, 3)), np.zeros((1, 2, 3)), rng())


@pytest.mark.parametrize(("interval", "lower_is_better", "verdict"), [
    ((-2.0, -0.5), True, REPRODUCED), ((0.5, 2.0), False, REPRODUCED),
    ((0.5, 2.0), True, NOT_REPRODUCED), ((-2.0, -0.5), False, NOT_REPRODUCED),
    ((-2.0, 0.0), True, INCONCLUSIVE), ((0.0, 2.0), False, INCONCLUSIVE),  # touching 0 is not a side of it
    ((0.0, 2.0), True, INCONCLUSIVE), ((-2.0, 0.0), False, INCONCLUSIVE),
])
def test_better_needs_the_whole_interval_strictly_on_one_side(interval, lower_is_better, verdict):
    assert verdict_better(interval, lower_is_better) == verdict


def test_within_counts_the_band_edges_as_inside():
    assert verdict_within((40.0, 60.0), 50.0, 10.0) == REPRODUCED  # both ends on the edges
    assert verdict_within((30.0, 40.0), 50.0, 10.0) == INCONCLUSIVE  # touches the lower edge from outside
    assert verdict_within((60.0, 70.0), 50.0, 10.0) == INCONCLUSIVE
    assert verdict_within((20.0, 39.9), 50.0, 10.0) == NOT_REPRODUCED
    assert verdict_within((60.1, 70.0), 50.0, 10.0) == NOT_REPRODUCED
    assert verdict_within((50.0, 50.0), 50.0, 0.0) == REPRODUCED  # a zero margin is allowed
    assert verdict_within((1.0, math.inf), 50.0, 10.0) == INCONCLUSIVE
