"""The videos page: the newest evaluation videos of each production model beside the reference, per test clip."""
from __future__ import annotations

import shutil
from collections import defaultdict
from pathlib import Path

from dashboards import html as h
from dashboards.sections.common import run_name, stage_runs
from m3t.experiment import RunRecord


def videos(runs: list[RunRecord], media: Path) -> str:
    """The newest evaluation videos of each production model, grouped by test clip, copied under ``media``."""
    clips: dict[str, list[tuple[str, str]]] = defaultdict(list)
    for stage, label in (("evaluate-smlm", "SMLM, body surface"), ("evaluate-sgsa", "PT / SGSA / SMLM, skeletons")):
        record = next((r for r in stage_runs(runs, stage) if r.status == "FINISHED" and r.artifact_dir
                       and any(r.artifact_dir.rglob("*.mp4"))), None)
        if record is None:
            continue
        for video in sorted(record.artifact_dir.rglob("*.mp4")):
            target = media / stage / video.name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(video, target)
            clip = video.stem.removesuffix("_skeleton")  # the SMLM's skeleton overlay beside its mesh video
            kind = "SMLM, skeleton" if clip != video.stem else label
            clips[clip].append((f"{kind} ({run_name(record)})", f"media/{stage}/{video.name}"))
    if not clips:
        return h.empty("No rendered video yet: <code>dvc repro generate-smlm evaluate-smlm evaluate-sgsa</code> "
                       "renders the first test clips (<code>smlm_generate.render_clips</code>, "
                       "<code>sgsa_evaluate.render_clips</code>).")
    out = ["<p class=note>Each video shows the reference beside the model's output for the same test clip.</p>"]
    for clip, items in sorted(clips.items()):
        figures = "".join(f'<figure><video controls muted preload=metadata src="{h.esc(src)}"></video>'
                          f"<figcaption>{h.esc(label)}</figcaption></figure>" for label, src in items)
        out.append(f"<h2>{h.esc(clip)}</h2>{figures}")
    return "".join(out)
