"""The papers' claims read from the pipeline's MLflow runs: claim | paper's figure | ours | verdict, with run ids.

Every claim compares two variants A and B on one metric (:data:`CLAIMS`). Its values come from the artifacts the
evaluate stages log (``per_clip.csv``, ``backtranslation.csv``, ``predictions.csv``) or, for codebook
statistics, the training runs' metrics: per test clip, for every seed both variants were run with (the newest
finished run per variant and seed). :mod:`m3t.metrics.stats` compares the seed-averaged means over clips with a
hierarchical bootstrap over seeds and clips (seeds alone for per-run statistics) and gives the verdict. With fewer than
``min_seeds`` seeds the verdict is ``inconclusive`` whatever the interval: two runs of the embedded pipeline
that differed only by float rounding flipped orderings, so one seed answers nothing.

Variants are run by the pipeline and its sweeps: ``dvc exp run -S smlm_train.seed=N`` (and
``-S smlm_train.translation_objective=false``), ``m3t ablate-tokenizers``, ``m3t sgsa-sweep``; a claim whose
variants have no runs yet says which command makes them.

Axis legend: R seeds, C clips.
"""
from __future__ import annotations

import csv
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from m3t.atomic import write_json, write_text
from m3t.experiment import RunRecord, newest_finished
from m3t.metrics.stats import INCONCLUSIVE, paired, verdict_better, verdict_within
from m3t.reporting import markdown_table, significant

MOTION_DEFINITION = "SOKE DTW (raw cost over aligned frames, m)"
TEXT_DEFINITION = "SL-T (ROUGE-L beta 1.2, per sentence; Chinese per character)"


@dataclass
class Sample:
    """Per-clip values of both variants, (R, C) each, on the same seeds and clips, and where they came from."""

    a: np.ndarray
    b: np.ndarray
    seeds: list[str]
    runs_a: list[str]
    runs_b: list[str]
    unit: str = "clip"  # what the bootstrap resamples: "clip", or "seed" for per-run statistics


class MissingRuns(LookupError):
    """A claim's variants have no comparable runs; the message says which command makes them."""


@dataclass(frozen=True)
class Claim:
    key: str
    source: str  # where the paper states it
    statement: str
    paper: str  # the paper's figure(s)
    metric: str  # what is compared, in which definition
    a: str
    b: str
    collect: Callable[[list[RunRecord]], Sample] = field(repr=False)
    lower_is_better: bool = True
    within: tuple[float, float] | None = None  # (target, margin): the value of ``of`` stays within the band
    of: str = "b-a"  # "b-a": the claim is about B - A; "b": about B alone (``within`` only)


# ------------------------------------------------------------------ reading runs
def _rows(record: RunRecord, name: str) -> list[dict[str, str]]:
    path = record.artifact_dir / name if record.artifact_dir is not None else None
    if path is None or not path.is_file():
        raise MissingRuns(f"run {record.run_id} ({record.stage}) has no artifact {name}; rerun that stage")
    with open(path, newline="", encoding="utf-8") as handle:
        return list(csv.DictReader(handle))


def _values(rows: list[dict[str, str]], column: str, **where: str) -> dict[str, float]:
    out = {}
    for row in rows:
        if all(row.get(k) == v for k, v in where.items()) and row.get(column, "") != "":
            out[row["clip_id"]] = float(row[column])
    return out


def _aligned(pairs: list[tuple[dict[str, float], dict[str, float]]]) -> tuple[np.ndarray, np.ndarray]:
    """Seeds' {clip: value} maps of A and B -> (R, C) arrays over every clip either side scored (NaN gaps)."""
    clips = sorted({c for a, b in pairs for c in (*a, *b)})
    a = np.array([[ma.get(c, np.nan) for c in clips] for ma, _ in pairs], dtype=np.float64).reshape(len(pairs), -1)
    b = np.array([[mb.get(c, np.nan) for c in clips] for _, mb in pairs], dtype=np.float64).reshape(len(pairs), -1)
    return a, b


def _stage(records: list[RunRecord], stage: str, version: str | None = None) -> list[RunRecord]:
    """The finished runs of ``stage`` on one data version (``version``, else that of its newest tagged run):
    runs on other shards are never compared."""
    runs = [r for r in records if r.stage == stage and r.status == "FINISHED"]
    versions = [r.tags["data_version"] for r in runs if r.tags.get("data_version")]
    if version is None and not versions:
        what = f"no {stage} run" if not runs else f"no {stage} run carries a data_version tag (runs of earlier code)"
        raise MissingRuns(f"{what}: run `dvc repro {stage}`")
    version = version or versions[0]
    return [r for r in runs if r.tags.get("data_version") == version]


def _seed(record: RunRecord) -> str:
    return record.tags.get("seed", "?")


# ------------------------------------------------------------------ the collectors
def _smlm_variant(record: RunRecord) -> str:
    """off (no translation objective), shared or added (its translation steps; runs before the setting: shared)."""
    if record.tags.get("translation_objective") == "False":
        return "off"
    return record.tags.get("translation_steps", "shared")


def smlm_objective(file: str, column: str, steps: str = "shared") -> Callable[[list[RunRecord]], Sample]:
    """evaluate-smlm without (A) and with (B) the translation objective, per seed; ``column`` of ``file``. ``steps``:
    B's translation steps, ``shared`` (taken from the epoch: equal epochs) or ``added`` (equal production updates)."""

    def collect(records: list[RunRecord]) -> Sample:
        runs = newest_finished(_stage(records, "evaluate-smlm"), lambda r: (_smlm_variant(r), _seed(r)))
        seeds = sorted({s for o, s in runs if o == "off"} & {s for o, s in runs if o == steps})
        if not seeds:
            how = "" if steps == "shared" else " -S smlm_train.translation_steps=added"
            raise MissingRuns(f"needs evaluate-smlm runs with and without the translation objective ({steps} "
                              "translation steps) for one seed: `dvc exp run -S smlm_train.translation_objective="
                              f"false` and `dvc exp run{how}` (or `m3t study`)")
        a_runs, b_runs = [runs[("off", s)] for s in seeds], [runs[(steps, s)] for s in seeds]
        a, b = _aligned([(_values(_rows(ra, file), column), _values(_rows(rb, file), column))
                         for ra, rb in zip(a_runs, b_runs)])
        return Sample(a, b, seeds, [r.run_id for r in a_runs], [r.run_id for r in b_runs])

    return collect


def ground_truth_ceiling(records: list[RunRecord]) -> Sample:
    """A: back-translation of the generated motion (with the objective), per seed; B: of the ground truth."""
    generated = [r for r in _stage(records, "evaluate-smlm") if _smlm_variant(r) == "shared"]
    runs = newest_finished(generated, _seed)
    version = generated[0].tags["data_version"] if generated else None
    gt = newest_finished([r for r in _stage(records, "evaluate-backtranslation", version)
                          if r.tags.get("source") == "ground-truth" and r.tags.get("split") == "test"], lambda r: 0)
    if not runs or not gt:
        raise MissingRuns("needs evaluate-smlm and evaluate-backtranslation (ground truth, test) runs: `dvc repro`")
    truth = _values(_rows(gt[0], "per_clip.csv"), "rouge_l")
    seeds = sorted(runs)
    a, b = _aligned([(_values(_rows(runs[s], "backtranslation.csv"), "rouge_l"), truth) for s in seeds])
    return Sample(a, b, seeds, [runs[s].run_id for s in seeds], [gt[0].run_id] * len(seeds))


def slr_face(subset: str, column: str, a_variant: str, b_variant: str) -> Callable[[list[RunRecord]], Sample]:
    """evaluate-slr predictions of two probe variants (``full`` / ``no_face``) on one subset, in %, per seed."""

    def collect(records: list[RunRecord]) -> Sample:
        runs = newest_finished(_stage(records, "evaluate-slr"),
                               lambda r: r.params.get(f"{b_variant}.slr_train.seed", r.params.get("slr_train.seed")))
        seeds = sorted(s for s in runs if s is not None)
        if not seeds:
            raise MissingRuns("needs evaluate-slr runs: `dvc repro evaluate-slr`")
        pairs = []
        for s in seeds:
            rows = _rows(runs[s], "predictions.csv")
            if rows and column not in rows[0]:
                raise MissingRuns(f"run {runs[s].run_id} predictions.csv has no {column!r} column; rerun evaluate-slr")
            pairs.append(({k: 100.0 * v for k, v in _values(rows, column, variant=a_variant, subset=subset).items()},
                          {k: 100.0 * v for k, v in _values(rows, column, variant=b_variant, subset=subset).items()}))
        a, b = _aligned(pairs)
        ids = [runs[s].run_id for s in seeds]
        return Sample(a, b, seeds, ids, ids)

    return collect


def sgsa_systems(a_system: str, b_system: str, file: str, column: str) -> Callable[[list[RunRecord]], Sample]:
    """Two systems of the same evaluate-sgsa runs (``pt``, ``sgsa``, ``smlm``) on the test split, per seed;
    ``column`` of ``file`` (``per_clip.csv`` or ``backtranslation.csv``)."""

    def collect(records: list[RunRecord]) -> Sample:
        runs = _stage(records, "evaluate-sgsa")
        variant = runs[0].tags.get("variant")  # the newest run's setting
        by_seed = newest_finished([r for r in runs if r.tags.get("variant") == variant], _seed)
        seeds = sorted(by_seed)
        pairs = []
        for s in seeds:
            rows = _rows(by_seed[s], file)
            pairs.append((_values(rows, column, system=a_system, split="test"),
                          _values(rows, column, system=b_system, split="test")))
        a, b = _aligned(pairs)
        ids = [by_seed[s].run_id for s in seeds]
        return Sample(a, b, seeds, ids, ids)

    return collect


def sgsa_adjacency(file: str, column: str) -> Callable[[list[RunRecord]], Sample]:
    """SGSA at N = inf (A) and at a finite N (B), same layers, per seed (evaluate-sgsa runs of both settings)."""

    def collect(records: list[RunRecord]) -> Sample:
        runs = [r for r in _stage(records, "evaluate-sgsa") if r.params.get("sgsa.decoder_layers", "0") != "0"]
        key = newest_finished(runs, lambda r: (r.params.get("sgsa.decoder_layers"),
                                               r.params.get("sgsa.temporal_adjacency"), _seed(r)))
        found = next(((layers, adjacency) for layers, adjacency, seed in key
                      if adjacency not in ("0", None) and (layers, "0", seed) in key), None)
        if found is None:
            raise MissingRuns("needs evaluate-sgsa runs at N = inf and a finite N with the same layers and seed: "
                              "`m3t sgsa-sweep 2`")
        layers, adjacency = found
        seeds = sorted(s for (l_, n, s) in key if l_ == layers and n == adjacency and (layers, "0", s) in key)
        a_runs, b_runs = [key[(layers, "0", s)] for s in seeds], [key[(layers, adjacency, s)] for s in seeds]
        a, b = _aligned([(_values(_rows(ra, file), column, system="sgsa", split="test"),
                          _values(_rows(rb, file), column, system="sgsa", split="test"))
                         for ra, rb in zip(a_runs, b_runs)])
        return Sample(a, b, seeds, [r.run_id for r in a_runs], [r.run_id for r in b_runs])

    return collect


def tokenizer_runs(metric: str, a: tuple[str, str], b: tuple[str, str]) -> Callable[[list[RunRecord]], Sample]:
    """A train-tokenizers run metric of two (quantizer, batch size) settings at one width (the newest run's),
    paired by seed; one value per run."""

    def collect(records: list[RunRecord]) -> Sample:
        tokenizers = _stage(records, "train-tokenizers")
        width = tokenizers[0].tags.get("width") if tokenizers else None  # the newest run's width, for both sides
        runs = newest_finished([r for r in tokenizers if r.tags.get("width") == width],
                               lambda r: (r.tags.get("quantizer"), r.tags.get("batch_size"), _seed(r)))
        seeds = sorted({s for (q, bs, s) in runs if (q, bs) == a} & {s for (q, bs, s) in runs if (q, bs) == b})
        seeds = [s for s in seeds if metric in runs[(*a, s)].metrics and metric in runs[(*b, s)].metrics]
        if not seeds:
            raise MissingRuns(f"needs train-tokenizers runs of {a[0]} batch {a[1]} and {b[0]} batch {b[1]} with the "
                              "same seed: `m3t ablate-tokenizers`")
        a_runs, b_runs = [runs[(*a, s)] for s in seeds], [runs[(*b, s)] for s in seeds]
        return Sample(np.array([[r.metrics[metric] for r in a_runs]]), np.array([[r.metrics[metric] for r in b_runs]]),
                      seeds, [r.run_id for r in a_runs], [r.run_id for r in b_runs], unit="seed")

    return collect


# the VQ baselines of Tab. 3's FSQ claims: (claim-id suffix, quantizer, label); M3T names its VQ no further
VQ_BASELINES = (("", "vq", "VQ (EMA + reset)"), ("-vq-ema", "vq_ema", "VQ (EMA, no reset)"),
                ("-vq-plain", "vq_plain", "VQ-VAE (plain)"))


def _tokenizer_claims() -> list[Claim]:
    paper_use = {"body": "67.3 -> 96.4 %", "hand": "72.5 -> 98.1 %", "face": "78.8 -> 99.0 %"}
    paper_vpe = {"body": "20.67 -> 16.11", "hand": "5.61 -> 4.94", "face": "1.35 -> 1.18"}
    paper_batch = {"body": "96.4 -> 84.1 %", "hand": "98.1 -> 86.9 %", "face": "99.0 -> 89.3 %"}
    out = []
    for group in ("body", "hand", "face"):
        for suffix, vq, label in VQ_BASELINES:
            out.append(Claim(f"tokenizer-utilisation-{group}{suffix}", "M3T Tab. 3", f"FSQ uses more of its codebook "
                             f"than {label} ({group})", f"VQ -> FSQ {paper_use[group]}",
                             "test-split codebook utilisation (%)", label, "FSQ",
                             tokenizer_runs(f"{group}/utilisation_pct", (vq, "16"), ("fsq", "16")),
                             lower_is_better=False))
        for suffix, vq, label in VQ_BASELINES:
            out.append(Claim(f"tokenizer-pa-vpe-{group}{suffix}", "M3T Tab. 3", f"FSQ reconstructs with lower PA-VPE "
                             f"than {label} ({group})", f"VQ -> FSQ {paper_vpe[group]}",
                             "test PA-VPE (mm, per-frame Procrustes)", label, "FSQ",
                             tokenizer_runs(f"{group}/test_pa_vpe_mm", (vq, "16"), ("fsq", "16"))))
        out.append(Claim(f"tokenizer-batch-{group}", "M3T Tab. 3", f"FSQ utilisation falls as the batch grows 16 -> "
                         f"128 ({group})", f"batch 16 -> 128 {paper_batch[group]}", "test-split codebook utilisation "
                         "(%)", "FSQ batch 128", "FSQ batch 16",
                         tokenizer_runs(f"{group}/utilisation_pct", ("fsq", "128"), ("fsq", "16")),
                         lower_is_better=False))
    return out


CLAIMS: tuple[Claim, ...] = (
    *_tokenizer_claims(),
    Claim("smlm-objective-dtw-body", "M3T Tab. 1", "the auxiliary translation objective lowers body DTW-JPE",
          "How2Sign 5.02 -> 4.86, CSL-Daily 4.77 -> 4.63, Phoenix14T 4.17 -> 4.02",
          f"body DTW-JPE, {MOTION_DEFINITION}", "production only", "production + translation",
          smlm_objective("per_clip.csv", "dtw_jpe_body_m")),
    Claim("smlm-objective-dtw-hand", "M3T Tab. 1", "the auxiliary translation objective lowers hand DTW-JPE",
          "How2Sign 8.94 -> 9.44 (higher), CSL-Daily 9.94 -> 9.28, Phoenix14T 9.14 -> 8.55",
          f"hand DTW-JPE, {MOTION_DEFINITION}", "production only", "production + translation",
          smlm_objective("per_clip.csv", "dtw_jpe_hand_m")),
    Claim("smlm-objective-bt", "M3T Tab. 2", "the auxiliary translation objective raises back-translation",
          "ROUGE-L How2Sign 12.32 -> 13.15, CSL-Daily 17.27 -> 20.23, Phoenix14T 31.14 -> 32.12",
          f"back-translation ROUGE-L, {TEXT_DEFINITION}", "production only", "production + translation",
          smlm_objective("backtranslation.csv", "rouge_l"), lower_is_better=False),
    # the same three at equal production updates: with translation_steps shared the objective takes half of the
    # production run's steps, so "with" also means "half the production training"
    Claim("smlm-objective-dtw-body-equal-updates", "M3T Tab. 1",
          "the auxiliary translation objective lowers body DTW-JPE (at equal production updates)",
          "How2Sign 5.02 -> 4.86, CSL-Daily 4.77 -> 4.63, Phoenix14T 4.17 -> 4.02 (the paper's budget is not given)",
          f"body DTW-JPE, {MOTION_DEFINITION}", "production only", "production + translation (added steps)",
          smlm_objective("per_clip.csv", "dtw_jpe_body_m", "added")),
    Claim("smlm-objective-dtw-hand-equal-updates", "M3T Tab. 1",
          "the auxiliary translation objective lowers hand DTW-JPE (at equal production updates)",
          "How2Sign 8.94 -> 9.44 (higher), CSL-Daily 9.94 -> 9.28, Phoenix14T 9.14 -> 8.55",
          f"hand DTW-JPE, {MOTION_DEFINITION}", "production only", "production + translation (added steps)",
          smlm_objective("per_clip.csv", "dtw_jpe_hand_m", "added")),
    Claim("smlm-objective-bt-equal-updates", "M3T Tab. 2",
          "the auxiliary translation objective raises back-translation (at equal production updates)",
          "ROUGE-L How2Sign 12.32 -> 13.15, CSL-Daily 17.27 -> 20.23, Phoenix14T 31.14 -> 32.12",
          f"back-translation ROUGE-L, {TEXT_DEFINITION}", "production only", "production + translation (added steps)",
          smlm_objective("backtranslation.csv", "rouge_l", "added"), lower_is_better=False),
    Claim("bt-ground-truth-ceiling", "M3T Tab. 2", "back-translation of the ground truth is the upper bound",
          "ROUGE-L GT 18.68 / 27.14 / 35.83 vs M3T 13.15 / 20.23 / 32.12", f"back-translation ROUGE-L, "
          f"{TEXT_DEFINITION}", "generated (with objective)", "ground truth", ground_truth_ceiling,
          lower_is_better=False),
    Claim("slr-face-confusing", "M3T Tab. 4 / Sec. 4.3", "the face stream carries the confusing pairs",
          "confusing Top-1 58.3 % with face (no face-less run reported)", "pair accuracy on confusing signs (%): "
          "the target beats its manual twin", "without face", "with face",
          slr_face("confusing", "correct_pair", "no_face", "full"), lower_is_better=False),
    Claim("slr-face-chance", "M3T Sec. 4.3", "without the face, confusing pairs fall to about chance",
          "'face tokens are the sole source of discriminative information' (no figure)",
          "pair accuracy on confusing signs without face (%), within 10 points of chance (50 %)", "with face",
          "without face", slr_face("confusing", "correct_pair", "full", "no_face"), within=(50.0, 10.0), of="b"),
    Claim("slr-face-normal", "M3T Sec. 4.3", "normal signs stay recognised without the face",
          "'adding face tokens provides no discriminative advantage' on normal signs (no figure)",
          "Top-1 on normal signs (%), without - with face within 10 points", "with face", "without face",
          slr_face("normal", "correct_top1", "full", "no_face"), within=(0.0, 10.0)),
    Claim("sgsa-vs-pt-bt", "SGSA Tab. 1", "SGSA beats Progressive Transformers (back-translation)",
          "test BLEU-4 13.64 -> 14.27, ROUGE 36.59 -> 37.79 (L = 0 with 4 SA layers -> L = 5)",
          f"back-translation ROUGE-L of the skeleton judge, {TEXT_DEFINITION}", "PT", "SGSA",
          sgsa_systems("pt", "sgsa", "backtranslation.csv", "rouge_l"), lower_is_better=False),
    Claim("sgsa-vs-pt-dtw", "SGSA Tab. 1 (our metric)", "SGSA beats Progressive Transformers (motion)",
          "not reported (back-translation only)", f"body DTW-JPE, {MOTION_DEFINITION}, skeleton judge's split",
          "PT", "SGSA", sgsa_systems("pt", "sgsa", "per_clip.csv", "dtw_jpe_body_m")),
    Claim("sgsa-adjacency", "SGSA Tab. 2", "temporal adjacency N = 1 beats N = inf",
          "test BLEU-4 14.27 -> 14.33, ROUGE 37.79 -> 37.96 (dev BLEU-4 14.72 -> 15.15)",
          f"back-translation ROUGE-L of the skeleton judge, {TEXT_DEFINITION}", "SGSA N = inf", "SGSA N = 1",
          sgsa_adjacency("backtranslation.csv", "rouge_l"), lower_is_better=False),
    Claim("smlm-vs-sgsa", "across papers", "M3T's SMLM beats SGSA on the same split",
          "not compared in either paper", f"body DTW-JPE, {MOTION_DEFINITION}", "SGSA", "SMLM",
          sgsa_systems("sgsa", "smlm", "per_clip.csv", "dtw_jpe_body_m")),
    Claim("smlm-vs-pt", "across papers", "M3T's SMLM beats Progressive Transformers on the same split",
          "M3T Tab. 1: PT 14.74 vs M3T 4.86 body DTW-JPE (How2Sign)", f"body DTW-JPE, {MOTION_DEFINITION}", "PT",
          "SMLM", sgsa_systems("pt", "smlm", "per_clip.csv", "dtw_jpe_body_m")),
)


# ------------------------------------------------------------------ the table
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


def stability_line(summary: dict) -> str:
    """One sentence on :func:`stability` for claims.md and the dashboard."""
    if not summary["compared"]:
        return "Stability: no claim has 2 seeds yet, so none could be judged again on two disjoint seed halves."
    return (f"Stability: judged again on two disjoint halves of their seeds (first half, rest), {summary['flipped']} "
            f"of {summary['compared']} claims flip their verdict ({100 * summary['share_flipped']:.0f} %)"
            + (": " + "; ".join(f"{f['claim']} ({' / '.join(f['verdicts'])})" for f in summary["flips"])
               if summary["flips"] else "") + ".")


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


def _fmt(value: float | None) -> str:
    return significant(value, whole_from=100)


def means_cell(row: dict, fmt: Callable[[float], str], fmt_sd: Callable[[float], str]) -> str:
    """A judged row's ``A mean +- SD -> B mean +- SD``, means by ``fmt`` and SDs by ``fmt_sd``."""
    return (f"{row['a']} {fmt(row['mean_a'])} +- {fmt_sd(row['std_a'])} -> {row['b']} {fmt(row['mean_b'])} +- "
            f"{fmt_sd(row['std_b'])}")


def interval_cell(row: dict, fmt: Callable[[float], str]) -> str:
    """A judged row's ``value [low, high]`` by ``fmt``, then its equivalence band when the claim has one."""
    low, high = row["interval95"]
    band = f" (band {row['band'][0]:g} +- {row['band'][1]:g})" if row.get("band") else ""
    return f"{fmt(row['value'])} [{fmt(low)}, {fmt(high)}]{band}"


def claims_markdown(rows: list[dict], min_seeds: int) -> str:
    intro = (f"Claims of M3T and SGSA on this platform's runs. Ours: A -> B as mean +- std over seeds; the 95 % "
             f"interval is a hierarchical bootstrap over training seeds and test clips (over seeds for codebook "
             f"statistics), so it includes how much a retrained model moves. Verdicts need >= {min_seeds} seeds. "
             "Metric definitions in the metric column.")
    body = []
    for r in rows:
        if r["verdict"] == "not run":
            body.append([r["claim"], r["source"], r["paper"], r["metric"], "-", "-", f"not run: {r['note']}", 0, "-"])
            continue
        runs = ", ".join(sorted({i[:8] for i in r["runs_a"] + r["runs_b"]}))
        verdict = r["verdict"] + (f" ({r['note']})" if r["note"] else "")
        body.append([r["claim"], r["source"], r["paper"], r["metric"], means_cell(r, _fmt, _fmt),
                     f"{r['compared']} {interval_cell(r, _fmt)}", verdict, len(r["seeds"]), runs])
    table = markdown_table(["claim", "source", "paper", "metric", "ours: A -> B", "compared [95 % interval]", "verdict",
                            "seeds", "runs"], body)
    return "\n".join([intro, "", table, "", stability_line(stability(rows))]) + "\n"


def write_claims(records: list[RunRecord], out_dir: str | Path, min_seeds: int = 3) -> list[dict]:
    """Judge every claim and write ``claims.json`` and ``claims.md`` into ``out_dir``."""
    rows = claims_table(records, min_seeds)
    out = Path(out_dir)
    write_json(out / "claims.json", {"min_seeds": min_seeds, "motion_definition": MOTION_DEFINITION,
                                     "text_definition": TEXT_DEFINITION, "claims": rows,
                                     "stability": stability(rows)})
    write_text(out / "claims.md", claims_markdown(rows, min_seeds))
    return rows
