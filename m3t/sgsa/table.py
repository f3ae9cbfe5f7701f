"""SGSA Tab. 1-3 from MLflow ``evaluate-sgsa`` runs, in the paper's layouts (dev | test x BLEU-4, BLEU-3, BLEU-2,
BLEU-1, ROUGE), plus the DTW-JPE columns the paper does not have.

- Tab. 1 (:func:`layers_table`): SGSA layers ``L`` at ``N = inf``; ``L = 0`` is the PT baseline ("0 (4 SA)").
- Tab. 2 (:func:`adjacency_table`): temporal adjacency ``N`` at one ``L`` (the ``L`` with most runs).
- Tab. 3 (:func:`cross_table`): PT, SGSA, the M3T SMLM and the ground truth on the same corpus, split and judges
  (the SMLM is scored on the split generate-smlm produced, so its dev cells may be empty).

Text metrics: definition ``slt`` (SL-T: lower-cased whitespace tokens, BLEU unsmoothed, ROUGE-L beta 1.2, Chinese
per character), each the mean over sign languages of the per-language corpus score; DTW-JPE: SOKE's raw DTW cost of
the root-relative mean point distance, mean of body and hands, in millimetres, on the skeleton. A row pools every
finished run of its variant (one per seed): cells are the mean over seeds, with the seed count in the last column.
Each table says how the lengths were decided (the runs' ``counter`` tag): by the model's own counter (the default),
or the ground-truth length (parity with published PT numbers, which were produced so).
"""
from __future__ import annotations

from collections import defaultdict

import numpy as np

from m3t.experiment import RunRecord, newest_finished
from m3t.metrics.text import SLT_DEFINITION
from m3t.reporting import fixed, markdown_table

BLEU_COLUMNS = ("bleu4", "bleu3", "bleu2", "bleu1", "rouge_l")
HEADER_NAMES = ("BLEU-4", "BLEU-3", "BLEU-2", "BLEU-1", "ROUGE")
SPLITS = ("dev", "test")
DEFINITION_LINE = (f"Back-translation by the skeleton judge, text metrics definition {SLT_DEFINITION!r} (SL-T: "
                   "lower-cased whitespace tokens, BLEU unsmoothed, ROUGE-L beta 1.2, Chinese per character; mean over "
                   "sign languages). DTW-JPE: SOKE raw DTW cost, mean of body and hands, mm. Cells: mean over seeds.")


def backtranslation_scores(metrics: dict[str, float], system: str, split: str) -> dict[str, float]:
    """BLEU-1..4 / ROUGE-L of ``system`` on ``split``: the mean over languages of ``<system>/<split>/bt/slt/<lang>/..``."""
    prefix = f"{system}/{split}/bt/{SLT_DEFINITION}/"
    by_language: dict[str, dict[str, float]] = defaultdict(dict)
    for key, value in metrics.items():
        if key.startswith(prefix) and key.count("/") == prefix.count("/") + 1:
            language, name = key[len(prefix):].split("/")
            by_language[language][name] = value
    return {c: float(np.mean([m[c] for m in by_language.values() if c in m])) for c in BLEU_COLUMNS
            if any(c in m for m in by_language.values())}


def row_values(records: list[RunRecord], system: str) -> tuple[dict[str, float], int]:
    """``<split>/<column>`` -> mean over the runs (seeds), and the number of runs."""
    pooled: dict[str, list[float]] = defaultdict(list)
    for record in records:
        for split in SPLITS:
            for k, v in backtranslation_scores(record.metrics, system, split).items():
                pooled[f"{split}/{k}"].append(v)
            jpe = record.metrics.get(f"{system}/{split}/dtw_jpe_mean_m")
            if jpe is not None:
                pooled[f"{split}/dtw_jpe_mm"].append(1000.0 * jpe)
    return {k: float(np.mean(v)) for k, v in pooled.items()}, len(records)


COUNTER_MODES = {"predicted": "lengths decided by each model's own counter (counter decoding)",
                 "ground_truth": "ground-truth lengths (the true counter fed back; parity with published PT numbers)"}


def counter_line(records: list[RunRecord]) -> str:
    """How the runs behind a table decided their lengths (``evaluate-sgsa``'s ``counter`` tag)."""
    modes = sorted({r.tags.get("counter", "predicted") for r in records})
    if not modes:
        return "Lengths: no run."
    return "Lengths: " + "; ".join(f"{COUNTER_MODES.get(m, m)}" for m in modes) + \
        (" (runs of both modes pooled: rerun one mode)" if len(modes) > 1 else "") + "."


def _render(title: str, first: str, rows: list[tuple[str, dict[str, float], int]], records: list[RunRecord]) -> str:
    columns = [f"{split} {name}" for split in SPLITS for name in (*HEADER_NAMES, "DTW-JPE")]
    body = [[name, *(fixed(values.get(f"{split}/{c}"), 2) for split in SPLITS for c in (*BLEU_COLUMNS, "dtw_jpe_mm")),
             seeds] for name, values, seeds in rows]
    return "\n".join([title, DEFINITION_LINE, counter_line(records), "",
                      markdown_table([first, *columns, "seeds"], body)])


def _finished(records: list[RunRecord]) -> list[RunRecord]:
    return [r for r in records if r.status == "FINISHED"]


def _by_variant(records: list[RunRecord]) -> dict[tuple[int, int], list[RunRecord]]:
    """(L, N with 0 = inf) -> the runs of that SGSA variant, newest first, one per seed."""
    def variant(record: RunRecord) -> tuple[int, int] | None:
        layers, adjacency = record.params.get("sgsa.decoder_layers"), record.params.get("sgsa.temporal_adjacency")
        return None if layers is None or adjacency is None else (int(layers), int(adjacency))

    out: dict[tuple[int, int], list[RunRecord]] = defaultdict(list)
    for (key, _seed), record in newest_finished(records, lambda r: (variant(r), _seed_of(r))).items():
        if key is not None:
            out[key].append(record)
    return dict(out)


def _seed_of(record: RunRecord) -> str:
    return record.tags.get("seed", record.run_id)


def _pt_runs(records: list[RunRecord]) -> list[RunRecord]:
    return list(newest_finished([r for r in records if any(k.startswith("pt/") for k in r.metrics)], _seed_of).values())


BASELINE_NAMES = {"retrieval": "Retrieval baseline (nearest training text's motion)",
                  "lexicon": "Lexicon baseline (stored sign per gloss, stitched)"}


def _baselines(records: list[RunRecord]) -> list[tuple[str, dict[str, float], int]]:
    """A row per baseline system: its newest finished evaluate-baselines run, scored on the same samples, skeleton
    and judge as the systems (``<system>/<split>/...``)."""
    from m3t.smlm.table import baseline_rows

    return [(BASELINE_NAMES.get(name, f"baseline: {name}"), *row_values([record], name))
            for name, record in baseline_rows(records)]


def layers_table(records: list[RunRecord], baselines: list[RunRecord] = ()) -> str:
    """SGSA Tab. 1: rows ``0 (4 SA)`` (PT) and each ``L`` evaluated at ``N = inf``; then the baselines."""
    rows = []
    pt = _pt_runs(records)
    if pt:
        rows.append(("0 (PT, standard SA)", *row_values(pt, "pt")))
    for (layers, adjacency), runs in sorted(_by_variant(records).items()):
        if adjacency == 0 and layers > 0:
            rows.append((str(layers), *row_values(runs, "sgsa")))
    rows += _baselines(baselines)
    return _render("SGSA Tab. 1: skeletal graph layers L (N = inf)", "L", rows, _finished(records))


def adjacency_table(records: list[RunRecord], layers: int | None = None, baselines: list[RunRecord] = ()) -> str:
    """SGSA Tab. 2: rows ``N`` in inf, 1, 2, ... at ``layers`` (default: the L with most evaluated variants)."""
    variants = {k: v for k, v in _by_variant(records).items() if k[0] > 0}
    if layers is None and variants:
        counts = defaultdict(int)
        for (lay, _), runs in variants.items():
            counts[lay] += 1
        layers = max(counts, key=lambda lay: (counts[lay], lay))
    rows = [("inf" if n == 0 else str(n), *row_values(runs, "sgsa"))
            for (lay, n), runs in sorted(variants.items(), key=lambda kv: (kv[0][1] != 0, kv[0][1])) if lay == layers]
    rows += _baselines(baselines)
    return _render(f"SGSA Tab. 2: temporal adjacency N (L = {layers})", "N", rows, _finished(records))


def cross_table(records: list[RunRecord], baselines: list[RunRecord] = ()) -> str:
    """SGSA Tab. 3 layout across papers: PT, SGSA (the newest run's variant), the M3T SMLM, the baselines and the
    ground truth."""
    finished = _finished(records)
    if not finished:
        return "no finished evaluate-sgsa run yet: run `dvc repro evaluate-sgsa`"
    newest = finished[0]
    layers, adjacency = newest.params.get("sgsa.decoder_layers"), newest.params.get("sgsa.temporal_adjacency")
    same = _by_variant(finished).get((int(layers), int(adjacency)), [newest]) if layers is not None else [newest]
    n = "inf" if str(adjacency) in ("0", "None") else adjacency
    rows = [("Progressive Transformers", *row_values(_pt_runs(finished), "pt")),
            (f"Skeletal Graph Self-Attention (L={layers}, N={n})", *row_values(same, "sgsa")),
            ("M3T SMLM (posed into the skeleton)", *row_values([newest], "smlm")),
            *_baselines(baselines),
            ("Ground-truth motion (judge upper bound)", *row_values([newest], "ground_truth"))]
    return _render("SGSA Tab. 3 layout, across papers: one corpus, one split, one judge", "approach", rows, finished)


TAB1_LAYERS = (1, 2, 3, 4, 5)  # L = 0 is the PT baseline every run trains alongside
TAB2_ADJACENCY = (0, 1, 2, 3, 5)  # N; 0 = inf


def sweep_settings(table: str, seeds: list[int] | tuple[int, ...] = (0,), layers: int | None = None) -> list[dict]:
    """The ``-S`` settings of one sweep: Tab. 1 (``L`` in 1..5 at ``N = inf``) or Tab. 2 (``N`` in inf, 1, 2, 3, 5
    at ``layers``, default the params' own), once per seed."""
    if table == "1":
        grid = [{"sgsa.decoder_layers": n, "sgsa.temporal_adjacency": 0} for n in TAB1_LAYERS]
    elif table == "2":
        grid = [{"sgsa.temporal_adjacency": n, **({} if layers is None else {"sgsa.decoder_layers": layers})}
                for n in TAB2_ADJACENCY]
    else:
        raise ValueError(f"table {table!r} unknown; the sweeps are 1 (layers) and 2 (temporal adjacency)")
    return [{**setting, "sgsa_train.seed": seed} for seed in seeds for setting in grid]
