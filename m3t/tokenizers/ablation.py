"""The quantisation ablation (M3T Tab. 3): a ``dvc exp`` sweep and the table printed from MLflow.

The sweep follows the paper's design around a base setting (batch 16, the configured width): the three VQs
(strong ``vq``, ``vq_ema``, ``vq_plain``: :mod:`m3t.tokenizers.vq`) vs FSQ, then FSQ over batch sizes, then FSQ
over widths (``full=True``: the whole grid). ``m3t ablate-tokenizers`` runs each setting as one DVC experiment
(``cli.variants``: ``dvc exp run --temp -S ...``, so ``params.yaml`` is left alone); the runs log to the MLflow
store of the workspace.
"""
from __future__ import annotations

import itertools
import math
from typing import Iterable

from m3t.experiment import RunRecord, newest_finished
from m3t.reporting import fixed, markdown_table
from m3t.tokenizers.config import QUANTIZERS

CPU_WIDTHS = (32, 64, 128)
PAPER_WIDTHS = (512, 1024, 2048)
BATCH_SIZES = (16, 32, 64, 128)
GROUPS = ("body", "hand", "face")


def sweep_settings(base_width: int, widths: Iterable[int] = CPU_WIDTHS, batch_sizes: Iterable[int] = BATCH_SIZES,
                   quantizers: Iterable[str] = tuple(QUANTIZERS), base_batch: int = 16, full: bool = False) -> list[dict]:
    """Settings as ``{"tokenizer.quantizer": ..., "tokenizer_train.batch_size": ..., "tokenizer.width": ...}``."""
    def setting(q: str, bs: int, w: int) -> dict:
        return {"tokenizer.quantizer": q, "tokenizer_train.batch_size": bs, "tokenizer.width": w}

    if full:
        return [setting(q, b, w) for q, b, w in itertools.product(quantizers, batch_sizes, widths)]
    out = [setting(q, base_batch, base_width) for q in quantizers]
    out += [setting("fsq", b, base_width) for b in batch_sizes if b != base_batch]
    out += [setting("fsq", base_batch, w) for w in widths if w != base_width]
    return out


def _cell(values: list[float], digits: int) -> str:
    """One seed's value, or mean +- population SD over the seeds."""
    values = [v for v in values if v is not None and not math.isnan(v)]
    if len(values) < 2:
        return fixed(values[0] if values else None, digits)
    mean = sum(values) / len(values)
    sd = math.sqrt(sum((v - mean) ** 2 for v in values) / len(values))
    return f"{mean:.{digits}f} +- {sd:.{digits}f}"


def ablation_table(records: list[RunRecord]) -> str:
    """Markdown table: one row per (quantizer, batch size, width), the VQs first, over the newest finished run of
    each seed (mean +- SD when there are several); columns per group: test PA-VPE (mm), codebook utilisation (%),
    perplexity / K, token-count SD, tokens per code (the last says how far utilisation can be read:
    :func:`m3t.metrics.codebook.codebook_stats`)."""
    runs = newest_finished(records, lambda r: (r.params.get("tokenizer.quantizer", "?"),
                                               int(r.params.get("tokenizer_train.batch_size", 0)),
                                               int(r.params.get("tokenizer.width", 0)),
                                               r.params.get("tokenizer_train.seed", r.tags.get("seed", "?"))))
    rows: dict[tuple, list[RunRecord]] = {}
    for (q, bs, hs, _), record in runs.items():
        rows.setdefault((q, bs, hs), []).append(record)
    columns = (("PA-VPE {} (mm)", "test_pa_vpe_mm", 2), ("util {} %", "utilisation_pct", 1),
               ("ppl/K {}", "perplexity_per_code", 2), ("count SD {}", "count_sd", 1),
               ("tokens/K {}", "tokens_per_code", 1))
    header = ["Q", "BS", "HS", "seeds", *(name.format(g) for name, _, _ in columns for g in GROUPS)]
    body = []
    order = list(QUANTIZERS)
    for (q, bs, hs), group_runs in sorted(rows.items(), key=lambda kv: (
            (kv[0][0] == "fsq", order.index(kv[0][0]) if kv[0][0] in order else len(order)), kv[0][1], kv[0][2])):
        cells = [q.upper(), str(bs), str(hs), str(len(group_runs))]
        cells += [_cell([r.metrics.get(f"{g}/{key}") for r in group_runs], digits)
                  for _, key, digits in columns for g in GROUPS]
        body.append(cells)
    return markdown_table(header, body)
