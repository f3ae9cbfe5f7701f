"""What every benchmark shares: write the result JSON and log it as an MLflow run; run one arm in a fresh
process and read its peak memory; name the CPU."""
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


def cpu_model() -> str:
    """This machine's CPU model, as ``/proc/cpuinfo`` names it."""
    import platform

    return next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                 if line.startswith("model name")), platform.processor())


def run_measured(command: list[str], log: Path, timeout: float, cwd: Path,
                 poll: float = 0.5) -> tuple[int, float, float, bool]:
    """Run ``command`` in a fresh process (output to ``log``), killed after ``timeout`` seconds: its exit status,
    peak resident memory in MB (the kernel's ``ru_maxrss`` of that process, ``os.wait4``), wall seconds and
    whether it was killed."""
    import os
    import subprocess
    import time

    started = time.perf_counter()
    with open(log, "w") as out:
        proc = subprocess.Popen(command, cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
        killed = False
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() > started + timeout:
                proc.kill()
                _, status, usage = os.wait4(proc.pid, 0)
                killed = True
                break
            time.sleep(poll)
    return os.waitstatus_to_exitcode(status), usage.ru_maxrss / 1024, time.perf_counter() - started, killed
