"""Judging the claims: a claim's sample -> its row (means, the seeds' spread, hierarchical bootstrap interval,
verdict), judged again on two disjoint seed halves, and every claim of :data:`~m3t.claims.definitions.CLAIMS` on
a list of runs (:func:`claims_table`).

Axis legend: R seeds, C clips.
"""
from __future__ import annotations

import zlib

import numpy as np

from m3t.claims.collectors import MissingRuns, Sample
from m3t.claims.definitions import CLAIMS, Claim
from m3t.experiment import RunRecord
from m3t.metrics.stats import INCONCLUSIVE, paired, verdict_better, verdict_within


def judge(claim: Claim, sample: Sample, min_seeds: int, rng: np.random.Generator) -> dict:
    """One table row: means, the seeds' spread, the interval and the verdict of ``claim`` on ``sample``."""
    a, b = sample.a, sample.b  # unit "seed": (1, R), so the seeds are what the bootstrap resamples
    pair = paired(a, b, rng)
    if claim.within is not None and claim.of == "b":
        own = paired(np.zeros_like(b), b, rng)  # B's own mean and interval
        interval, shown = own.interval, own.difference
        verdict = verdict_within(interval, *claim.within)
    elif claim.within is not None:
        interval, shown = pair.interval, pair.difference
        verdict = verdict_within(interval, *claim.within)
    else:
        interval, shown = pair.interval, pair.difference
        verdict = verdict_better(interval, claim.lower_is_better)
    seeds = len(sample.seeds)
    note = ""
    if seeds < min_seeds:
        verdict, note = INCONCLUSIVE, f"{seeds} seed(s) < {min_seeds}: the verdict needs the seeds' spread"
    spread = (lambda v: float(np.std(v)) if v.size > 1 else 0.0)
    per_seed_a = np.nanmean(sample.a, axis=1) if sample.unit == "clip" else sample.a.reshape(-1)
    per_seed_b = np.nanmean(sample.b, axis=1) if sample.unit == "clip" else sample.b.reshape(-1)
    return {"key": claim.key, "source": claim.source, "claim": claim.statement, "paper": claim.paper,
            "metric": claim.metric, "a": claim.a, "b": claim.b, "seeds": sample.seeds,
            "units": pair.clips if sample.unit == "clip" else seeds, "unit": sample.unit,
            "mean_a": pair.mean_a, "std_a": spread(per_seed_a), "mean_b": pair.mean_b, "std_b": spread(per_seed_b),
            "compared": "B" if claim.of == "b" else "B - A", "value": shown, "interval95": list(interval),
            "band": list(claim.within) if claim.within is not None else None, "verdict": verdict, "note": note,
            "runs_a": sample.runs_a, "runs_b": sample.runs_b}


def seed_halves(claim: Claim, sample: Sample, rng: np.random.Generator) -> dict | None:
    """The claim judged again on two disjoint halves of its seeds (the first half, the rest), each on its own
    hierarchical interval: ``{"seeds": [first, rest], "verdicts": [..., ...]}``; None under 2 seeds. A verdict
    that one set of retrains gives and the other does not is not a finding. The halves are judged without the
    ``min_seeds`` rule (they hold fewer seeds by construction): what is compared is where each half's interval
    lies."""
    if len(sample.seeds) < 2:
        return None
    half = len(sample.seeds) // 2
    verdicts = []
    for part in (slice(0, half), slice(half, None)):
        if sample.unit == "seed":  # (1, R): the seeds are the columns
            sub = Sample(sample.a[:, part], sample.b[:, part], sample.seeds[part], [], [], sample.unit)
        else:  # (R, C): the seeds are the rows
            sub = Sample(sample.a[part], sample.b[part], sample.seeds[part], [], [], sample.unit)
        verdicts.append(judge(claim, sub, 1, rng)["verdict"])
    return {"seeds": [sample.seeds[:half], sample.seeds[half:]], "verdicts": verdicts}


def stability(rows: list[dict]) -> dict:
    """How many judged claims flip their verdict between the two seed halves (:func:`seed_halves`)."""
    compared = [r for r in rows if r.get("halves")]
    flips = [{"key": r["key"], "claim": r["claim"], "verdicts": r["halves"]["verdicts"],
              "seeds": r["halves"]["seeds"]} for r in compared if len(set(r["halves"]["verdicts"])) > 1]
    return {"compared": len(compared), "flipped": len(flips),
            "share_flipped": len(flips) / len(compared) if compared else None, "flips": flips}


def claims_table(records: list[RunRecord], min_seeds: int = 3, claims: tuple[Claim, ...] = CLAIMS,
                 seed: int = 0) -> list[dict]:
    """Every claim judged on ``records`` (MLflow runs, newest first); a claim without runs says what to run.
    Each claim bootstraps with its own generator, seeded from ``seed`` and its key: its interval does not depend
    on which other claims are judged, nor in which order. Each row also holds its verdicts on two seed halves
    (``halves``, :func:`seed_halves`), drawn after its own interval."""
    rows = []
    for claim in claims:
        rng = np.random.default_rng([seed, zlib.crc32(claim.key.encode())])
        try:
            sample = claim.collect(records)
            row = judge(claim, sample, min_seeds, rng)
            row["halves"] = seed_halves(claim, sample, rng)
            rows.append(row)
        except MissingRuns as missing:
            rows.append({"key": claim.key, "source": claim.source, "claim": claim.statement, "paper": claim.paper,
                         "metric": claim.metric, "a": claim.a, "b": claim.b, "seeds": [], "verdict": "not run",
                         "note": str(missing)})
    return rows
