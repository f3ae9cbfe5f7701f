"""What a corpus run leaves behind: one shard per split, ``quarantine.jsonl``, ``summary.json``, the
data-quality report (``quality.csv`` / ``quality.json``), and the MLflow run that shows them.

The files beside the shards are DVC outputs, so they hold results only: how many clips have a fit, the fit
quality, what was quarantined and why. Whether a clip was fitted now or taken from the cache, and how long
the run took, change from run to run on identical inputs; they go to MLflow (:attr:`FitCorpusReport.run_stats`)
and never into a tracked file. Every file is written only when its bytes change (:mod:`m3t.atomic`).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from m3t.atomic import write_json, write_jsonl, write_text
from m3t.body.protocol import ModalityLayout
from m3t.corpora.splits import SPLITS
from m3t.fitting.quality import plot_quality, quality_report, write_quality
from m3t.shards.io import read_shard, write_shard
from m3t.shards.schema import FittedClip


@dataclass(frozen=True)
class ClipOutcome:
    clip_id: str
    split: str
    status: Literal["fitted", "cached", "quarantined"]
    part: str | None = None
    reason: str | None = None
    metrics: dict[str, float] = field(default_factory=dict)
    frames: int = 0
    seconds: float = 0.0
    group: str | None = None  # the short reason the quality report counts
    file: str | None = None  # quarantined: the listing file (or the clip's media) ...
    row: int | None = None  # ... and its row, when the adapter refused the row
    from_listing: bool = False
    coverage: dict[str, float] = field(default_factory=dict)  # missing_<part> ratios of the track
    track_frames: int = 0
    init: dict[str, Any] = field(default_factory=dict)  # where the initialisation came from (init_source, shares)


@dataclass(frozen=True)
class FitCorpusReport:
    shards: dict[str, str]
    outcomes: list[ClipOutcome]
    summary: dict[str, float]  # results (summary.json)
    quality: dict[str, Any] = field(default_factory=dict)  # quality.json
    run_stats: dict[str, float] = field(default_factory=dict)  # this run only (MLflow): cache hits, timing


def summarise(outcomes: list[ClipOutcome]) -> dict[str, float]:
    """Results of a run: clip counts and the mean / median of every per-clip fit metric."""
    done = [o for o in outcomes if o.status != "quarantined"]
    # metrics summarised by the quality report (per-part reprojection) stay out of the MLflow means
    done = [dataclasses.replace(o, metrics={k: v for k, v in o.metrics.items() if not k.startswith("reproj_px_")
                                            and k != "reproj_shoulder_frac"}) for o in done]
    summary: dict[str, float] = {
        "clips_total": len(outcomes),
        "clips_fitted": len(done),
        "clips_quarantined": sum(o.status == "quarantined" for o in outcomes),
        "frames": sum(o.frames for o in done),
    }
    keys = sorted({k for o in done for k in o.metrics})
    for key in keys:
        values = [o.metrics[key] for o in done if key in o.metrics and o.metrics[key] == o.metrics[key]]
        if values:
            summary[f"{key}_mean"] = float(np.mean(values))
            summary[f"{key}_median"] = float(np.median(values))
    return summary


def run_stats(outcomes: list[ClipOutcome], wall_seconds: float) -> dict[str, float]:
    """What differs between two runs on the same inputs: fitted now vs from the cache, throughput."""
    fitted = [o for o in outcomes if o.status == "fitted"]
    frames = sum(o.frames for o in fitted)
    return {
        "clips_fitted_now": len(fitted),
        "clips_cached": sum(o.status == "cached" for o in outcomes),
        "wall_seconds": wall_seconds,
        # per worker (frames / seconds spent fitting) and for the whole run (frames / wall time)
        "fit_frames_per_s_per_worker": frames / sum(o.seconds for o in fitted) if fitted else math.nan,
        "fit_frames_per_s_wall": frames / wall_seconds if fitted and wall_seconds > 0 else math.nan,
    }


def consolidate(outcomes: list[ClipOutcome], layout: ModalityLayout, shards_dir: str | Path, corpus: str,
                wall_seconds: float) -> FitCorpusReport:
    """Gather part files into one shard per split; write the quarantine report, summary and quality report."""
    out_dir = Path(shards_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # completion order varies (workers, a resumed run's cached clips first): every output is built in clip order,
    # so a float mean sums in the same order and a resumed run writes the same bytes as an uninterrupted one
    outcomes = sorted(outcomes, key=lambda o: (o.clip_id, o.file or "", o.row or 0))
    # Every standard split gets a shard (possibly empty), so downstream stages and DVC outputs always exist.
    by_split: dict[str, list[FittedClip]] = {split: [] for split in SPLITS}
    for o in outcomes:
        if o.part is not None:
            by_split.setdefault(o.split, []).extend(read_shard(o.part).clips)
    shards = {split: str(write_shard(out_dir / f"{split}.parquet", clips, layout)) for split, clips in by_split.items()}
    for stale in out_dir.glob("*.parquet"):
        if str(stale) not in shards.values():
            stale.unlink()
    quarantine = [{"clip_id": o.clip_id, "split": o.split, "file": o.file, "row": o.row, "reason": o.reason,
                   "group": o.group} for o in outcomes if o.status == "quarantined"]
    write_jsonl(out_dir / "quarantine.jsonl", quarantine)
    summary = summarise(outcomes)
    write_json(out_dir / "summary.json", {k: _finite_or_none(v) for k, v in summary.items()})
    quality = quality_report(outcomes, corpus)
    quality = dataclasses.replace(quality, summary={**quality.summary, **import_summary(outcomes)})
    write_quality(quality, out_dir, write_text)
    return FitCorpusReport(shards=shards, outcomes=outcomes, summary=summary, quality=quality.summary,
                           run_stats=run_stats(outcomes, wall_seconds))


def import_summary(outcomes: list[ClipOutcome]) -> dict[str, float]:
    """Over the imported clips (:mod:`m3t.fitting.imports`): their count, the frame-weighted fraction of frames
    that held NaN / inf (replaced by the nearest finite frame) and each source array's range over every clip."""
    done = [o for o in outcomes if o.status != "quarantined" and o.init.get("init_source", "").startswith("imported")]
    if not done:
        return {}
    frames = sum(o.frames for o in done)
    out: dict[str, float] = {
        "imported_clips": len(done),
        "imported_nonfinite_frame_frac": sum(o.metrics.get("src_nonfinite_frame_frac", 0.0) * o.frames
                                             for o in done) / frames if frames else math.nan,
    }
    for key in sorted({k for o in done for k in o.metrics if k.startswith("src_") and k.endswith(("_min", "_max"))}):
        values = [o.metrics[key] for o in done if key in o.metrics]
        out[f"imported_{key.removeprefix('src_')}"] = float(min(values) if key.endswith("_min") else max(values))
    return out


def _finite_or_none(value: Any) -> Any:
    return None if isinstance(value, float) and not math.isfinite(value) else value


def log_fit_corpus(experiment, logged_params: dict[str, Any], report: FitCorpusReport, body, corpus: str,
                   shards_dir: str | Path, cache_dir: str | Path, render_clips: int, ground_truth=None) -> str | None:
    """Log a corpus run to MLflow: params, results and run statistics, quarantine and quality reports,
    fitted-vs-truth pictures and the fitted mesh of the first ``render_clips`` clips.

    ``ground_truth(clip) -> (params, identity, camera)`` for synthetic clips (None: no truth to draw). Imported
    clips have no camera: only their mesh is pictured. ``body`` may be None when ``render_clips`` is 0."""
    from m3t.experiment import start_run
    from m3t.render.mesh import log_fitted_frame
    from m3t.render.skeleton import render_fit_comparison

    tags = {"corpus": corpus, "body_model": getattr(body, "name", "") if body is not None else ""}
    with start_run(experiment, "fit-corpus", tags=tags, variant=corpus) as run:
        run.log_params(logged_params)
        run.log_metrics(report.summary)
        run.log_metrics(report.run_stats)
        run.log_metrics({f"quality_{k}": v for k, v in report.quality.items() if isinstance(v, (int, float))})
        out_dir, render_dir = Path(shards_dir), Path(cache_dir) / "render"
        for name in ("quarantine.jsonl", "summary.json", "quality.json"):
            run.log_artifact(out_dir / name)
        run.log_table(out_dir / "quality.csv", "quality/quality.json")
        quality = quality_report(report.outcomes, corpus)
        run.log_artifact(plot_quality(quality, render_dir / f"quality-{corpus}.png"), "quality")
        for outcome in [o for o in report.outcomes if o.part is not None][:render_clips]:
            fitted = read_shard(outcome.part).clips[0]
            if fitted.camera:  # a fit's camera; imported clips have none
                truth = ground_truth(fitted.clip) if ground_truth is not None else None
                image = render_dir / f"{fitted.clip.id}.png"
                run.log_artifact(render_fit_comparison(body, fitted, truth, image), "fit_vs_ground_truth")
            # the fitted mesh of the middle frame: PLY + a rendered picture
            log_fitted_frame(run, body, fitted.params, fitted.identity, fitted.num_frames // 2, render_dir,
                             fitted.camera or None, stem=fitted.clip.id)
        return run.run_id
