"""Data-quality report of one fit-corpus run: what was listed, fitted and quarantined (and why), where each
clip's initialisation came from, how much of each body part the tracks saw, and how well the fits explain
the tracks. A clip taken from the fit cache counts as fitted: the report describes results, not one run.

Written next to the shards as ``quality.csv`` (one row per clip, quarantined ones included) and
``quality.json`` (the summary), plus a picture (``quality.png``: fit-error histogram, missing-part bars).

Fit error: per landmark part (pose, hands, face), the median reprojection error in pixels over confidently
tracked landmarks (confidence >= 0.5) that the body model has a correspondence for; a clip's error is the mean
of its parts' medians (``reproj_px_parts``) and, scale-free, that over the clip's median shoulder width in
pixels (``reproj_shoulder_frac``). Not the raw mean over all landmarks, which off-canvas legs and missing
correspondences dominate. Missing ratios: the fraction of a clip's frames in which no landmark of the part
was tracked.

Axis legend: T frames, K landmarks.
"""
from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from m3t.reporting import csv_text
from m3t.trackers.track import Track, landmark_slices

CONFIDENT = 0.5  # MediaPipe's own visibility threshold for "the landmark is in view"
LEFT_SHOULDER, RIGHT_SHOULDER = 11, 12
MISSING_PARTS = ("left_hand", "right_hand", "face")
COLUMNS = ("clip_id", "split", "status", "frames", "missing_left_hand", "missing_right_hand", "missing_face",
           "reproj_px_parts", "reproj_px_pose", "reproj_px_left_hand", "reproj_px_right_hand", "reproj_px_face",
           "reproj_shoulder_frac", "reproj_px", "init_source", "group", "file", "row", "reason")


def track_coverage(track: Track) -> dict[str, float]:
    """``missing_<part>``: fraction of frames in which no landmark of the part was tracked (0 = always seen)."""
    parts = landmark_slices(track.landmark_set)
    seen = track.confidence > 0  # (T, K)
    return {f"missing_{p}": float(1.0 - seen[:, parts[p]].any(-1).mean()) for p in MISSING_PARTS}


def part_reprojection_px(body, params: dict[str, np.ndarray], identity: np.ndarray, camera: dict,
                         track: Track) -> dict[str, float]:
    """Per-part median reprojection errors (px) of a fit, their mean, and that mean over the shoulder width.

    Parameters
    ----------
    body : BodyModel the fit used
    params : per-frame body-model parameters, each (T, D)
    identity : (S,) identity coefficients
    camera : the fit's camera (fx, fy, cx, cy, rotation (3, 3), translation (3,))
    track : the fitted track, keypoints (T, K, 2)
    """
    from m3t.body.protocol import as_tensors
    from m3t.camera import project

    correspondence = body.correspondence(track.landmark_set)
    with torch.no_grad():
        points = body.forward_keypoints(as_tensors(params), torch.as_tensor(identity),
                                        body.keypoint_set(correspondence))  # (T, K, 3)
        intrinsics = torch.tensor([camera["fx"], camera["fy"], camera["cx"], camera["cy"]], dtype=torch.float32)
        uv = project(points, torch.tensor(camera["rotation"], dtype=torch.float32),
                     torch.tensor(camera["translation"], dtype=torch.float32), intrinsics).numpy()  # (T, K, 2)
    err = np.linalg.norm(uv - track.keypoints, axis=-1)  # (T, K), NaN where untracked
    confident = (track.confidence >= CONFIDENT) & np.asarray(correspondence.valid, dtype=bool)  # (T, K)
    out = {f"reproj_px_{p}": float(np.median(err[:, s][confident[:, s]]))
           for p, s in landmark_slices(track.landmark_set).items() if confident[:, s].any()}
    parts = list(out.values())
    out["reproj_px_parts"] = float(np.mean(parts)) if parts else math.nan
    shoulders = track.keypoints[:, LEFT_SHOULDER] - track.keypoints[:, RIGHT_SHOULDER]  # (T, 2)
    width = np.linalg.norm(shoulders, axis=-1)
    width = float(np.nanmedian(width)) if np.isfinite(width).any() else math.nan
    out["reproj_shoulder_frac"] = out["reproj_px_parts"] / width if width > 0 else math.nan
    return out


@dataclass(frozen=True)
class QualityReport:
    rows: list[dict[str, Any]]  # one per clip, keys COLUMNS
    summary: dict[str, Any]


def _spread(values: list[float], name: str) -> dict[str, float]:
    finite = [v for v in values if not math.isnan(v)]
    if not finite:
        return {f"{name}_median": math.nan, f"{name}_p90": math.nan, f"{name}_max": math.nan}
    return {f"{name}_median": float(np.median(finite)), f"{name}_p90": float(np.percentile(finite, 90)),
            f"{name}_max": float(np.max(finite))}


def quality_report(outcomes: Iterable, corpus: str) -> QualityReport:
    """Rows and summary from the run's clip outcomes (:class:`m3t.fitting.report.ClipOutcome`)."""
    outcomes = sorted(outcomes, key=lambda o: (o.status == "quarantined", o.clip_id or "", o.row or 0))
    rows = []
    for o in outcomes:
        row = {c: "" for c in COLUMNS}
        status = "fitted" if o.status == "cached" else o.status
        row.update({"clip_id": o.clip_id or "", "split": o.split, "status": status, "frames": o.frames,
                    "init_source": o.init.get("init_source", ""),
                    "group": o.group or "", "file": o.file or "", "row": "" if o.row is None else o.row,
                    "reason": o.reason or ""})
        row.update({k: v for k, v in {**o.coverage, **o.metrics}.items() if k in COLUMNS})
        rows.append(row)
    done = [o for o in outcomes if o.status != "quarantined"]
    tracked = [o for o in outcomes if o.coverage]
    frames = sum(o.frames for o in done)
    summary: dict[str, Any] = {
        "corpus": corpus,
        "clips_listed": sum(not o.from_listing for o in outcomes),
        "clips_fitted": len(done),
        "clips_quarantined": sum(o.status == "quarantined" for o in outcomes),
        "clips_quarantined_at_listing": sum(o.from_listing for o in outcomes),
        "quarantine_reasons": dict(Counter(o.group or "unknown" for o in outcomes if o.status == "quarantined")
                                   .most_common()),
        "frames": frames,
        "init_sources": dict(Counter(o.init.get("init_source", "unknown").split(":")[0] for o in done).most_common()),
    }
    tracked_frames = sum(o.track_frames for o in tracked)
    for part in MISSING_PARTS:
        key = f"missing_{part}"
        # overall: frame-weighted over every tracked clip; per clip: the mean of the clips' ratios
        summary[f"{key}_ratio"] = (sum(o.coverage[key] * o.track_frames for o in tracked) / tracked_frames
                                   if tracked_frames else math.nan)
        summary[f"{key}_ratio_clip_mean"] = float(np.mean([o.coverage[key] for o in tracked])) if tracked else math.nan
    summary.update(_spread([o.metrics.get("reproj_px_parts", math.nan) for o in done], "reproj_px_parts"))
    summary.update(_spread([o.metrics.get("reproj_shoulder_frac", math.nan) for o in done], "reproj_shoulder_frac"))
    return QualityReport(rows, summary)


def _finite_or_none(value: Any) -> Any:
    return None if isinstance(value, float) and not math.isfinite(value) else value


def write_quality(report: QualityReport, out_dir: str | Path, write_text) -> tuple[Path, Path]:
    """``quality.csv`` + ``quality.json`` in ``out_dir``, each written whole by ``write_text(path, text)``."""
    out_dir = Path(out_dir)
    rows = ({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in row.items()} for row in report.rows)
    write_text(out_dir / "quality.csv", csv_text(rows, COLUMNS))
    summary = {k: _finite_or_none(v) for k, v in report.summary.items()}  # JSON has no NaN
    write_text(out_dir / "quality.json", json.dumps(summary, indent=2, sort_keys=True) + "\n")
    return out_dir / "quality.csv", out_dir / "quality.json"


def plot_quality(report: QualityReport, path: str | Path) -> Path:
    """PNG: histogram of per-clip fit errors (px) and bars of the missing-part ratios."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    errors = [r["reproj_px_parts"] for r in report.rows if isinstance(r["reproj_px_parts"], float)
              and math.isfinite(r["reproj_px_parts"])]
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    left.hist(errors, bins=min(30, max(5, len(errors))), color="tab:blue")
    left.set(title=f"{report.summary['corpus']}: fit error per clip", xlabel="mean of part-median reprojection (px)",
             ylabel="clips")
    ratios = [report.summary[f"missing_{p}_ratio"] for p in MISSING_PARTS]
    right.bar(list(MISSING_PARTS), [0.0 if math.isnan(r) else r for r in ratios], color="tab:orange")
    right.set(title="frames with the part missing", ylim=(0, 1), ylabel="ratio")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
