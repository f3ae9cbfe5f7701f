"""``m3t study``: every variant and seed that the papers' claims (:mod:`m3t.claims`) need, run as stage
subprocesses (``python -m m3t.stages.<stage> --params FILE``) on one data version, then the claims judged. The
steps and the params files are planned by :mod:`cli.study_plan`; this module runs them.

Besides the planned folders it writes ``<root>/logs/<variant>.<stage>.log``, ``<root>/timings.json`` and
``<root>/metrics/claims.{json,md}``.

Resuming: a step that succeeded leaves ``<root>/done/<variant>.<stage>.json`` with the digest of its params file's
bytes, its argv and the stamps of the steps it reads from; a later run skips it while that digest matches, so a
step reruns when its params changed or anything upstream reran. A failed step skips the steps that depend on it;
every other step still runs.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cli.study_plan import SHARED, Step, StudyError, plan, select
from m3t.atomic import write_json
from m3t.claims.report import claims_markdown, write_claims
from m3t.config import load_params
from m3t.digest import chunks_digest
from m3t.experiment import absolute_uri, fetch_runs, tracking_uri

Runner = Callable[[Sequence[str], Mapping[str, str], Path], int]  # (argv, env, log file) -> exit code


@dataclass(frozen=True)
class StepResult:
    name: str
    status: str  # ok | done (an earlier run's, skipped) | failed | skipped (a dependency failed)
    seconds: float
    detail: str = ""


@dataclass
class StudySummary:
    results: list[StepResult] = field(default_factory=list)
    seconds: float = 0.0

    def _of(self, *status: str) -> dict[str, str]:
        return {r.name: r.detail for r in self.results if r.status in status}

    @property
    def ran(self) -> list[str]:
        return list(self._of("ok"))

    @property
    def skipped(self) -> dict[str, str]:
        return self._of("done", "skipped")

    @property
    def failed(self) -> dict[str, str]:
        return self._of("failed")

    @property
    def ok(self) -> bool:
        return not self.failed


def run_subprocess(argv: Sequence[str], env: Mapping[str, str], log: Path) -> int:
    """Run ``argv`` (a leading ``python`` is this interpreter), stdout and stderr into ``log``."""
    argv = [sys.executable, *argv[1:]] if argv[0] == "python" else list(argv)
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w", encoding="utf-8") as handle:
        return subprocess.call(argv, env=dict(env), stdout=handle, stderr=subprocess.STDOUT)  # noqa: S603 - argv list


def _marker(root: Path, name: str) -> Path:
    return root / "done" / f"{name}.json"


def _read_marker(root: Path, name: str) -> dict:
    try:
        return json.loads(_marker(root, name).read_text(encoding="utf-8"))
    except (OSError, ValueError):  # none yet, or a marker cut short: the step simply runs again
        return {}


def step_digest(step: Step, root: Path) -> str:
    """Digest of the step's params file, its argv and the stamps of the steps it reads from."""
    if not step.params.is_file():
        raise StudyError(f"{step.params}: the params file of step {step.name} is missing; plan the study again")
    chunks = [step.params.read_bytes(), "\0".join(step.argv).encode()]
    chunks += [f"\0{name}={_read_marker(root, name).get('stamp', '-')}".encode()
               for name in sorted({*step.deps, *step.after})]
    return chunks_digest(chunks)


def pending(steps: list[Step], root: Path) -> set[str]:
    """Names of the steps a run would run (no matching marker, or something upstream would run)."""
    out: set[str] = set()
    for st in steps:
        if _read_marker(root, st.name).get("digest") != step_digest(st, root) or out & {*st.deps, *st.after}:
            out.add(st.name)
    return out


def _link(link: Path, target: Path) -> None:
    relative = os.path.relpath(target, link.parent)
    if link.is_symlink():
        if os.readlink(link) == relative:
            return
        link.unlink()
    elif link.exists():
        raise StudyError(f"{link}: expected a link to the shared {target}, found a real folder or file; move it "
                         "away and rerun")
    link.parent.mkdir(parents=True, exist_ok=True)
    os.symlink(relative, link, target_is_directory=True)


def _execute(step: Step, root: Path, runner: Runner, env: Mapping[str, str]) -> StepResult:
    digest = step_digest(step, root)
    _marker(root, step.name).unlink(missing_ok=True)  # an interrupted rerun must not count as done
    log = root / "logs" / f"{step.name}.log"
    start = time.monotonic()
    try:
        for link, target in step.links:
            _link(link, target)
        code = runner(step.argv, env, log)
    except (OSError, StudyError) as err:
        return StepResult(step.name, "failed", time.monotonic() - start, f"{err}")
    seconds = time.monotonic() - start
    if code != 0:
        return StepResult(step.name, "failed", seconds, f"exit {code}; log {log}")
    write_json(_marker(root, step.name), {"digest": digest, "stamp": uuid.uuid4().hex, "seconds": round(seconds, 1),
                                          "argv": list(step.argv)})
    return StepResult(step.name, "ok", seconds)


def _check_order(steps: list[Step]) -> None:
    index = {st.name: i for i, st in enumerate(steps)}
    late = [f"{st.name} needs {d}" for i, st in enumerate(steps) for d in (*st.deps, *st.after) if index.get(d, -1) > i]
    if late:
        raise StudyError(f"steps out of order (a step must come after those it reads): {'; '.join(late)}")


def _write_timings(root: Path, summary: StudySummary) -> None:
    write_json(root / "timings.json", {"total_s": round(summary.seconds, 1), "steps": [
        {"step": r.name, "status": r.status, "seconds": round(r.seconds, 1), "detail": r.detail}
        for r in summary.results]})


def run(steps: list[Step], root: str | Path, runner: Runner = run_subprocess,
        env: Mapping[str, str] | None = None) -> StudySummary:
    """Run ``steps`` in order, resumably (module docstring); logs in ``<root>/logs``, ``<root>/timings.json``."""
    root, summary = Path(root), StudySummary()
    cause: dict[str, str] = {}  # failed or blocked step -> the step that failed
    _check_order(steps)
    env = {**os.environ, **(env or {})}
    start = time.monotonic()
    for k, step in enumerate(steps, 1):
        print(f"[{k}/{len(steps)}] {step.variant} {step.stage} ...", end=" ", flush=True)
        blocker = next((d for d in step.deps if d in cause), None)
        marker = _read_marker(root, step.name)
        if blocker is not None:
            cause[step.name] = cause[blocker]
            via = "" if blocker == cause[blocker] else f" (needed through {blocker})"
            result = StepResult(step.name, "skipped", 0.0, f"{cause[blocker]} failed{via}")
            print(f"skipped: {result.detail}")
        elif marker.get("digest") == step_digest(step, root):
            result = StepResult(step.name, "done", float(marker.get("seconds", 0.0)), "done, skipped")
            print("done, skipped")
        else:
            result = _execute(step, root, runner, env)
            if result.status == "failed":
                cause[step.name] = step.name
                print(f"FAILED ({result.seconds:.1f} s): {result.detail}")
            else:
                print(f"ok ({result.seconds:.1f} s)")
        summary.results.append(result)
        summary.seconds = time.monotonic() - start
        _write_timings(root, summary)
    count = {status: sum(r.status == status for r in summary.results) for status in ("ok", "done", "skipped")}
    print(f"study: {count['ok']} ran, {count['done']} done before, {count['skipped']} skipped, "
          f"{len(summary.failed)} failed in {summary.seconds:.1f} s")
    for name, detail in summary.failed.items():
        print(f"  failed: {name}: {detail}")
    return summary


def study(params_path: str | Path, preset: str, seeds: Sequence[int], root: str | Path | None = None,
          dry_run: bool = False, only: Sequence[str] = (), claims: bool = True,
          runner: Runner = run_subprocess) -> int:
    """``m3t study``: plan, run (or with ``dry_run`` print the plan), judge the claims; 1 when a step failed."""
    root = Path(root or Path("studies") / preset)
    steps = select(plan(params_path, preset, seeds, root), only)
    params = load_params(params_path, preset=preset)
    uri = absolute_uri(tracking_uri(params.experiment, Path.cwd()), Path.cwd())
    print(f"study {preset!r}, seeds {' '.join(map(str, seeds))}: {len(steps)} steps under {root}; MLflow {uri}")
    if not params.experiment.enabled:
        print(f"note: experiment.enabled is false in {params_path} + preset {preset}: the stages log no MLflow runs, "
              "so no claim can be judged")
    if dry_run:
        waiting = pending(steps, root)
        for k, st in enumerate(steps, 1):
            print(f"[{k}/{len(steps)}] {st.variant} {st.stage}{'' if st.name in waiting else ' (done)'}: "
                  f"{' '.join(st.argv)}")
        return 0
    summary = run(steps, root, runner, {"MLFLOW_TRACKING_URI": uri})
    if claims and params.experiment.enabled:
        # the verdicts need 3 seeds whatever was asked for: a study with fewer seeds reads inconclusive
        rows = write_claims(fetch_runs(params.experiment), root / "metrics")
        print(claims_markdown(rows, 3))
        print(f"written: {root / 'metrics' / 'claims.json'}, {root / 'metrics' / 'claims.md'}")
        from dashboards.build import build_dashboard

        shared = load_params(root / "params" / f"{SHARED}.yaml")
        index = build_dashboard(shared, shared.experiment.dashboard_dir)
        print(f"dashboard of the study: {index}")
    return 0 if summary.ok else 1
