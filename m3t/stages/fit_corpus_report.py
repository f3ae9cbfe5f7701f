"""fit-corpus outputs: one shard per split, ``quarantine.jsonl``, ``summary.json``, the data-quality report, and
the MLflow run that shows them (split from :mod:`m3t.stages.fit_corpus`, which re-exports these names).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from m3t.fitting.quality import plot_quality, quality_report, write_quality
from m3t.shards.io import read_shard, write_shard
from m3t.shards.schema import FittedClip
from m3t.trackers.dispatch import media_kind

if TYPE_CHECKING:
    from m3t.stages.fit_corpus import ClipOutcome, FitContext, FitCorpusConfig

STANDARD_SPLITS = ("train", "dev", "test")


def _atomic_write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


@dataclass(frozen=True)
class FitCorpusReport:
    shards: dict[str, str]
    outcomes: list[ClipOutcome]
    summary: dict[str, float]
    quality: dict[str, Any] = field(default_factory=dict)


def summarise(outcomes: list[ClipOutcome], wall_seconds: float) -> dict[str, float]:
    done = [o for o in outcomes if o.status != "quarantined"]
    # metrics summarised by the quality report (per-part reprojection) stay out of the MLflow means
    done = [dataclasses.replace(o, metrics={k: v for k, v in o.metrics.items() if not k.startswith("reproj_px_")
                                            and k != "reproj_shoulder_frac"}) for o in done]
    fitted = [o for o in outcomes if o.status == "fitted"]
    summary: dict[str, float] = {
        "clips_total": len(outcomes),
        "clips_fitted": len(fitted),
        "clips_cached": sum(o.status == "cached" for o in outcomes),
        "clips_quarantined": sum(o.status == "quarantined" for o in outcomes),
        "frames": sum(o.frames for o in done),
        "wall_seconds": wall_seconds,
        # per worker process (frames / seconds spent fitting) and for the whole run (frames / wall time)
        "fit_frames_per_s_per_worker": (sum(o.frames for o in fitted) / sum(o.seconds for o in fitted)) if fitted else math.nan,
        "fit_frames_per_s_wall": sum(o.frames for o in fitted) / wall_seconds if fitted and wall_seconds > 0 else math.nan,
    }
    keys = sorted({k for o in done for k in o.metrics})
    for key in keys:
        values = [o.metrics[key] for o in done if key in o.metrics and o.metrics[key] == o.metrics[key]]
        if values:
            summary[f"{key}_mean"] = float(np.mean(values))
            summary[f"{key}_median"] = float(np.median(values))
    return summary


def consolidate(outcomes: list[ClipOutcome], layout, cfg: FitCorpusConfig, wall_seconds: float) -> FitCorpusReport:
    """Gather part files into one shard per split; write the quarantine report and summary."""
    out_dir = Path(cfg.shards_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # Every standard split gets a shard (possibly empty), so downstream stages and DVC outputs always exist.
    by_split: dict[str, list[FittedClip]] = {split: [] for split in STANDARD_SPLITS}
    for o in sorted(outcomes, key=lambda o: o.clip_id):
        if o.part is not None:
            by_split.setdefault(o.split, []).extend(read_shard(o.part).clips)
    shards = {split: str(write_shard(out_dir / f"{split}.parquet", clips, layout)) for split, clips in by_split.items()}
    for stale in out_dir.glob("*.parquet"):
        if str(stale) not in shards.values():
            stale.unlink()
    quarantine = [{"clip_id": o.clip_id, "split": o.split, "file": o.file, "row": o.row, "reason": o.reason,
                   "group": o.group} for o in outcomes if o.status == "quarantined"]
    _atomic_write_text(out_dir / "quarantine.jsonl", "".join(json.dumps(q) + "\n" for q in quarantine))
    summary = summarise(outcomes, wall_seconds)
    _atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=2, sort_keys=True))
    quality = quality_report(outcomes, cfg.corpus)
    write_quality(quality, out_dir, _atomic_write_text)
    return FitCorpusReport(shards=shards, outcomes=outcomes, summary=summary, quality=quality.summary)


def log_report(params, ctx: FitContext, report: FitCorpusReport) -> str | None:
    """Log a fit-corpus run to MLflow: params, summary metrics, quarantine report, fitted-vs-truth pictures."""
    from m3t.config import flat_params
    from m3t.experiment import start_run
    from m3t.render.mesh import log_fitted_frame
    from m3t.render.skeleton import render_fit_comparison

    with start_run(params.experiment, "fit-corpus", tags={"corpus": ctx.cfg.corpus}) as run:
        sections = ("body", "fitting", "fit_corpus") + (("tracker",) if ctx.cfg.corpus == "synthetic" else ())
        logged = {k: v for k, v in flat_params(params).items() if k.split(".")[0] in sections}
        run.log_params({**logged, "fit_corpus.corpus": ctx.cfg.corpus, f"corpora.{ctx.cfg.corpus}":
                        {"root": ctx.cfg.corpus_dir, "shards_dir": ctx.cfg.shards_dir, "options": ctx.cfg.options}})
        run.log_metrics(report.summary)
        run.log_metrics({f"quality_{k}": v for k, v in report.quality.items() if isinstance(v, (int, float))})
        out_dir = Path(ctx.cfg.shards_dir)
        for name in ("quarantine.jsonl", "summary.json", "quality.json"):
            run.log_artifact(out_dir / name)
        run.log_table(out_dir / "quality.csv", "quality/quality.json")
        quality = quality_report(report.outcomes, ctx.cfg.corpus)
        run.log_artifact(plot_quality(quality, Path(ctx.cfg.cache_dir) / "render" / f"quality-{ctx.cfg.corpus}.png"),
                         "quality")
        for outcome in [o for o in report.outcomes if o.part is not None][: ctx.cfg.render_clips]:
            fitted = read_shard(outcome.part).clips[0]
            truth = ctx.ground_truth(fitted.clip) if media_kind(fitted.clip) == "synthetic" else None
            image = Path(ctx.cfg.cache_dir) / "render" / f"{fitted.clip.id}.png"
            run.log_artifact(render_fit_comparison(ctx.body, fitted, truth, image), "fit_vs_ground_truth")
            # the fitted mesh of the middle frame: PLY + a rendered picture
            log_fitted_frame(run, ctx.body, fitted.params, fitted.identity, fitted.num_frames // 2,
                             Path(ctx.cfg.cache_dir) / "render", fitted.camera, stem=fitted.clip.id)
        return run.run_id
