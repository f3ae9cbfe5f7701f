"""Shared tail of every benchmark: write the result JSON and log it as an MLflow run."""
from __future__ import annotations

import json
from pathlib import Path


def write_and_log(result: dict, out: str | Path, stage: str) -> Path:
    """Write ``result`` to ``out`` (JSON) and log its numbers + the file to MLflow under ``stage``."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    try:
        from m3t.config import load_params
        from m3t.experiment import start_run

        with start_run(load_params().experiment, stage) as run:
            run.log_metrics({k: v for k, v in result.items() if isinstance(v, (int, float)) and not isinstance(v, bool)})
            run.log_artifact(out)
    except Exception as exc:  # noqa: BLE001 - the result file is the primary output
        print(f"(not logged to MLflow: {exc})")
    print(json.dumps(result, indent=2))
    return out
