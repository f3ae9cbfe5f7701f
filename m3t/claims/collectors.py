"""Reading a claim's variants from the MLflow runs: :class:`Sample` (per-clip values of A and B over the same seeds
and clips) and the collectors that build one per kind of comparison (SMLM objective, ground-truth ceiling, SLR
face stream, SGSA systems and adjacency, tokenizer settings); :class:`MissingRuns` says which command makes what
is missing.

Axis legend: R seeds, C clips.
"""
from __future__ import annotations

import csv
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from m3t.experiment import RunRecord, newest_finished


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


def _sgsa_runs(records: list[RunRecord]) -> list[RunRecord]:
    """The evaluate-sgsa runs whose lengths came from the models' own counters (the papers' decoding; runs with
    ground-truth lengths are for parity with published numbers and are not judged)."""
    runs = _stage(records, "evaluate-sgsa")
    own = [r for r in runs if r.tags.get("counter", "predicted") == "predicted"]
    if runs and not own:
        raise MissingRuns("every evaluate-sgsa run used ground-truth lengths; the claims judge the models' own "
                          "counters: rerun with sgsa_evaluate.counter: predicted")
    return own


def _sgsa_setting(records: list[RunRecord]) -> dict[str, RunRecord]:
    """Seed -> the evaluate-sgsa run of the setting the claims judge: a finite N (PT and the SMLM beside SGSA)
    where one ran, else the newest run's."""
    runs = _sgsa_runs(records)
    finite = [r for r in runs if r.params.get("sgsa.temporal_adjacency") not in ("0", None)]
    variant = (finite or runs)[0].tags.get("variant")
    return newest_finished([r for r in runs if r.tags.get("variant") == variant], _seed)


def sgsa_systems(a_system: str, b_system: str, file: str, column: str) -> Callable[[list[RunRecord]], Sample]:
    """Two systems of the same evaluate-sgsa runs (``pt``, ``sgsa``, ``smlm``) on the test split, per seed;
    ``column`` of ``file`` (``per_clip.csv`` or ``backtranslation.csv``). The runs are those of one setting: the
    newest run's at a finite temporal adjacency where one ran (the study's runs with PT beside SGSA), whatever
    order the runs finished in."""

    def collect(records: list[RunRecord]) -> Sample:
        by_seed = _sgsa_setting(records)
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
        runs = [r for r in _sgsa_runs(records) if r.params.get("sgsa.decoder_layers", "0") != "0"]
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


def versus_baseline(baseline: str, model: str, column: str) -> Callable[[list[RunRecord]], Sample]:
    """A: a baseline of evaluate-baselines (``retrieval`` / ``lexicon``: deterministic, its newest run on the same
    data for every seed); B: ``model`` per seed, ``smlm`` (evaluate-smlm with the objective, body-model path) or a
    system of evaluate-sgsa (``sgsa`` / ``pt``: the skeleton path, test split). ``column`` of ``per_clip.csv``."""

    def collect(records: list[RunRecord]) -> Sample:
        if model == "smlm":
            generated = [r for r in _stage(records, "evaluate-smlm") if _smlm_variant(r) == "shared"]
            by_seed = newest_finished(generated, _seed)
            model_values = {s: _values(_rows(r, "per_clip.csv"), column) for s, r in by_seed.items()}
            path = "body_model"
        else:
            by_seed = _sgsa_setting(records)
            model_values = {s: _values(_rows(r, "per_clip.csv"), column, system=model, split="test")
                            for s, r in by_seed.items()}
            path = "skeleton"
        if not by_seed:
            raise MissingRuns(f"needs {'evaluate-smlm' if model == 'smlm' else 'evaluate-sgsa'} runs: `dvc repro`")
        version = next(iter(by_seed.values())).tags.get("data_version")
        runs = newest_finished([r for r in _stage(records, "evaluate-baselines", version)
                                if r.tags.get("variant") == baseline], lambda r: 0)
        if not runs:
            raise MissingRuns(f"needs an evaluate-baselines run of {baseline!r} on the same data: "
                              "`dvc repro evaluate-baselines`")
        base = _values(_rows(runs[0], "per_clip.csv"), column, system=baseline, path=path, split="test")
        seeds = sorted(by_seed)
        a, b = _aligned([(base, model_values[s]) for s in seeds])
        return Sample(a, b, seeds, [runs[0].run_id] * len(seeds), [by_seed[s].run_id for s in seeds])

    return collect
