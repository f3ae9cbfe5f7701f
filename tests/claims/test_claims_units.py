"""Judging one claim (:func:`m3t.claims.verdicts.judge`, :func:`~m3t.claims.verdicts.seed_halves`) and its table
cells (:mod:`m3t.claims.report`) on hand-made samples whose means, spreads and verdicts are worked out by hand.
Written to pin behaviours that mutation testing found unchecked."""
from __future__ import annotations

import numpy as np
import pytest

from m3t.claims.collectors import Sample
from m3t.claims.definitions import Claim
from m3t.claims.report import interval_cell, means_cell, stability_line
from m3t.claims.verdicts import judge, seed_halves, stability


def claim(**options) -> Claim:
    return Claim("k", "src", "B beats A", "1 -> 2", "metric (unit)", "A", "B", collect=lambda records: None, **options)


def rng() -> np.random.Generator:
    return np.random.default_rng(0)


# per seed (rows) and clip (columns): A's seed means 12 and 14, B's 1 and 2; seed-averaged, B - A is -10.5 on clip
# 0 and -12.5 on clip 1. Any resample of seeds and clips lies in [1 - 15, 2 - 11] = [-14, -9]
A = np.array([[11.0, 13.0], [13.0, 15.0]])
B = np.array([[1.0, 1.0], [2.0, 2.0]])


def test_a_row_holds_the_means_the_seeds_spread_the_difference_and_its_verdict():
    row = judge(claim(), Sample(A, B, ["0", "1"], ["ra0", "ra1"], ["rb0", "rb1"]), 2, rng())
    assert (row["mean_a"], row["mean_b"]) == pytest.approx((13.0, 1.5))
    assert (row["std_a"], row["std_b"]) == pytest.approx((1.0, 0.5))  # population std of the seeds' means
    assert row["value"] == pytest.approx(-11.5) and row["compared"] == "B - A"
    low, high = row["interval95"]
    assert -14.0 <= low <= -11.5 <= high <= -9.0
    assert row["verdict"] == "reproduced" and row["note"] == "" and row["band"] is None
    assert (row["units"], row["unit"], row["seeds"]) == (2, "clip", ["0", "1"])
    assert (row["runs_a"], row["runs_b"]) == (["ra0", "ra1"], ["rb0", "rb1"])
    higher = judge(claim(lower_is_better=False), Sample(A, B, ["0", "1"], [], []), 2, rng())
    assert higher["verdict"] == "not reproduced"
    few = judge(claim(), Sample(A, B, ["0", "1"], [], []), 3, rng())
    assert few["verdict"] == "inconclusive" and few["note"] == "2 seed(s) < 3: the verdict needs the seeds' spread"


def test_a_band_claim_reads_b_alone_or_the_difference():
    alone = judge(claim(within=(1.5, 1.0), of="b"), Sample(A, B, ["0", "1"], [], []), 2, rng())
    assert alone["compared"] == "B" and alone["value"] == pytest.approx(1.5) and alone["band"] == [1.5, 1.0]
    assert alone["verdict"] == "reproduced"  # B's interval lies within [1, 2] (its values are 1 and 2)
    assert 1.0 <= alone["interval95"][0] <= alone["interval95"][1] <= 2.0
    outside = judge(claim(within=(10.0, 1.0), of="b"), Sample(A, B, ["0", "1"], [], []), 2, rng())
    assert outside["verdict"] == "not reproduced"
    diff = judge(claim(within=(-11.5, 3.0)), Sample(A, B, ["0", "1"], [], []), 2, rng())  # [-14.5, -8.5]
    assert diff["compared"] == "B - A" and diff["value"] == pytest.approx(-11.5) and diff["verdict"] == "reproduced"
    assert judge(claim(within=(0.0, 1.0)), Sample(A, B, ["0", "1"], [], []), 2, rng())["verdict"] == "not reproduced"


def test_per_run_statistics_resample_the_seeds_and_report_their_spread():
    a, b = np.array([[10.0, 12.0, 14.0]]), np.array([[20.0, 20.0, 23.0]])  # unit "seed": (1, R)
    row = judge(claim(lower_is_better=False), Sample(a, b, ["0", "1", "2"], [], [], unit="seed"), 3, rng())
    assert row["units"] == 3 and row["unit"] == "seed"
    assert row["std_a"] == pytest.approx(np.sqrt(8 / 3)) and row["std_b"] == pytest.approx(np.sqrt(2.0))
    assert row["value"] == pytest.approx(9.0) and row["verdict"] == "reproduced"


def test_seed_halves_split_first_half_and_rest_along_the_seed_axis():
    four = np.array([[1.0, 1.0], [1.0, 1.0], [3.0, 3.0], [3.0, 3.0]])
    # the first two seeds: B below A (reproduced); the last two: B above A (not reproduced)
    halves = seed_halves(claim(), Sample(four, np.full((4, 2), 2.0), ["0", "1", "2", "3"], [], []), rng())
    assert halves == {"seeds": [["0", "1"], ["2", "3"]], "verdicts": ["not reproduced", "reproduced"]}
    three = seed_halves(claim(), Sample(np.zeros((3, 2)), np.ones((3, 2)), ["0", "1", "2"], [], []), rng())
    assert three["seeds"] == [["0"], ["1", "2"]]  # an odd count: the rest has one more
    per_run = Sample(np.array([[1.0, 1.0, 3.0, 3.0]]), np.full((1, 4), 2.0), ["0", "1", "2", "3"], [], [], "seed")
    assert seed_halves(claim(), per_run, rng())["verdicts"] == ["not reproduced", "reproduced"]
    assert seed_halves(claim(), Sample(A[:1], B[:1], ["0"], [], []), rng()) is None


def test_stability_counts_the_rows_whose_halves_disagree():
    rows = [{"key": "x", "claim": "X", "halves": {"seeds": [["0"], ["1"]], "verdicts": ["reproduced", "inconclusive"]}},
            {"key": "y", "claim": "Y", "halves": {"seeds": [["0"], ["1"]], "verdicts": ["reproduced", "reproduced"]}},
            {"key": "z", "claim": "Z", "halves": None}, {"key": "n", "claim": "N"}]
    summary = stability(rows)
    assert (summary["compared"], summary["flipped"], summary["share_flipped"]) == (2, 1, 0.5)
    assert summary["flips"] == [{"key": "x", "claim": "X", "verdicts": ["reproduced", "inconclusive"],
                                 "seeds": [["0"], ["1"]]}]
    assert stability_line(summary) == ("Stability: judged again on two disjoint halves of their seeds (first half, "
                                       "rest), 1 of 2 claims flip their verdict (50 %): X (reproduced / inconclusive).")
    steady = stability(rows[1:])
    assert steady["share_flipped"] == 0.0 and stability_line(steady).endswith("flip their verdict (0 %).")
    assert stability([])["share_flipped"] is None


def test_the_table_cells_by_hand():
    row = {"a": "VQ", "b": "FSQ", "mean_a": 1.0, "std_a": 0.25, "mean_b": 2.0, "std_b": 0.5, "value": 1.0,
           "interval95": [0.5, 1.5], "band": [1.0, 0.75]}
    assert means_cell(row, str, lambda v: f"{v:.2f}") == "VQ 1.0 +- 0.25 -> FSQ 2.0 +- 0.50"
    assert interval_cell(row, str) == "1.0 [0.5, 1.5] (band 1 +- 0.75)"
    assert interval_cell({**row, "band": None}, str) == "1.0 [0.5, 1.5]"


def test_write_claims_judges_with_the_seeds_it_is_given(tmp_path, monkeypatch):
    import json

    from m3t.claims import report

    seen = []
    monkeypatch.setattr(report, "claims_table", lambda records, min_seeds: seen.append(min_seeds) or [])
    assert report.write_claims([], tmp_path, min_seeds=5) == [] and seen == [5]
    assert json.loads((tmp_path / "claims.json").read_text())["min_seeds"] == 5
    assert "Verdicts need >= 5 seeds." in (tmp_path / "claims.md").read_text()
