"""``m3t study``: every variant and seed that the papers' claims (:mod:`m3t.claims`) need, run as stage
subprocesses (``python -m m3t.stages.<stage> --params FILE``) on one data version, then the claims judged.

Where it writes (nothing outside ``root``): ``<root>/params/<variant>.yaml`` (params.yaml + the preset, every output
folder redirected under ``root``); the shared corpus, shards, tokens, models and metrics under ``<root>/data``,
``<root>/models``, ``<root>/metrics``; each variant's own models, generated motion and metrics under
``<root>/variants/<variant>/``, whose models folder holds relative links to the shared models it reads;
``<root>/logs/<variant>.<stage>.log``, ``<root>/timings.json``, ``<root>/metrics/claims.{json,md}``. The caches
(``*.cache_dir``) stay where params.yaml puts them: they are content-addressed and shared.

Resuming: a step that succeeded leaves ``<root>/done/<variant>.<stage>.json`` with the digest of its params file's
bytes, its argv and the stamps of the steps it reads from; a later run skips it while that digest matches, so a
step reruns when its params changed or anything upstream reran. A failed step skips the steps that depend on it;
every other step still runs. Order matters to the claims: :func:`m3t.claims.sgsa_systems` reads the setting of
the newest evaluate-sgsa run, so every SGSA N = inf step comes before the default-adjacency ones, and those are
evaluated again whenever an N = inf evaluation ran.
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

import yaml

from m3t.atomic import write_json, write_text
from m3t.claims import claims_markdown, write_claims
from m3t.config import Params, load_params, merge, params_from_dict, preset_overlay, read_yaml
from m3t.digest import chunks_digest
from m3t.experiment import absolute_uri, fetch_runs, to_dict, tracking_uri

SHARED = "shared"
# (quantizer, batch size) of M3T Tab. 3's claims: FSQ against the three VQs, and FSQ at batch 128
TOKENIZER_SETTINGS = (("fsq", 16), ("vq", 16), ("vq_ema", 16), ("vq_plain", 16), ("fsq", 128))
Runner = Callable[[Sequence[str], Mapping[str, str], Path], int]  # (argv, env, log file) -> exit code


class StudyError(ValueError):
    """A study that cannot be planned or run as asked; the message names the file, key or step."""


@dataclass(frozen=True)
class Step:
    variant: str
    stage: str
    params: Path  # the variant's params file
    argv: tuple[str, ...]
    deps: tuple[str, ...] = ()  # names of the steps whose outputs it reads: their failure skips it
    links: tuple[tuple[Path, Path], ...] = ()  # (link, shared target) made right before it runs
    after: tuple[str, ...] = ()  # it reruns whenever one of these ran (ordering for the claims, not a dependency)

    @property
    def name(self) -> str:
        return f"{self.variant}.{self.stage}"


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


# ------------------------------------------------------------------ the plan
def _argv(module: str, params: Path, *extra: str) -> tuple[str, ...]:
    return ("python", "-m", f"m3t.stages.{module}", "--params", str(params), *extra)


def _folders(root: Path, variant: str) -> dict:
    """The output keys of a variant's params, all under ``root`` (the shared ones for ``shared``)."""
    own = root if variant == SHARED else root / "variants" / variant
    return {"data": {"shards_root": str(root / "data" / "shards"), "tokens_root": str(root / "data" / "tokens"),
                     "models_dir": str(own / "models"),
                     "generated_dir": str(root / "data" / "generated" if variant == SHARED else own / "generated"),
                     "metrics_dir": str(own / "metrics")},
            "corpora": {"synthetic": {"root": str(root / "data" / "corpus" / "synthetic")}},
            "experiment": {"dashboard_dir": str(root / "dashboards")}}


class _Writer:
    """Writes ``<root>/params/<variant>.yaml``: the base tree, the variant's settings, its folders."""

    def __init__(self, raw: dict, root: Path, source: str):
        self.raw, self.root, self.source = raw, root, source

    def write(self, variant: str, settings: dict) -> tuple[Path, Params]:
        tree = merge(merge(self.raw, settings), _folders(self.root, variant))
        params = params_from_dict(tree)
        path = self.root / "params" / f"{variant}.yaml"
        write_text(path, f"# m3t study, variant {variant}: {self.source}; rewritten by `m3t study`\n"
                         + yaml.safe_dump(to_dict(params), sort_keys=False))
        return path, params


def _check(base: Params, where: str, seeds: Sequence[int]) -> None:
    if not seeds or len(set(seeds)) != len(seeds):
        raise StudyError(f"seeds {list(seeds)}: give at least one seed, each once")
    if base.sgsa.decoder_layers == 0:
        raise StudyError(f"{where}: sgsa.decoder_layers is 0 (that is PT); the SGSA claims need SGSA layers")
    if base.sgsa.temporal_adjacency == 0:
        raise StudyError(f"{where}: sgsa.temporal_adjacency is 0 (N = inf); the adjacency claim compares N = inf "
                         "with the configured finite N: set it to 1 (the paper's best)")


class _Planner:
    """Collects the steps in run order, one family of variants at a time; ``shared.*`` names the shared steps."""

    def __init__(self, raw: dict, base: Params, root: Path, where: str):
        self.base, self.root, self.writer = base, root, _Writer(raw, root, where)
        self.steps: list[Step] = []
        self.shared_seed = base.tokenizer_train.seed  # the configured tokenizers: tokenize and every model read them
        self.path, self.shared = self.writer.write(SHARED, {"tokenizer": {"quantizer": "fsq"}, "tokenizer_train": {
            "batch_size": 16, "seed": self.shared_seed}})
        self.fits: tuple[str, ...] = ()
        self.tok = f"{SHARED}.train-tokenizers"

    def add_shared(self) -> None:
        p, s = self.path, f"{SHARED}."
        corpora = list(dict.fromkeys((*self.base.data.train_corpora, self.base.slr.corpus)))
        if "synthetic" in corpora:
            self.steps.append(Step(SHARED, "generate-corpus", p, _argv("generate_corpus", p)))
        for corpus in corpora:
            stage = "fit-corpus" if corpus == "synthetic" else f"fit-corpus-{corpus}"
            deps = (s + "generate-corpus",) if corpus == "synthetic" else ()
            self.steps.append(Step(SHARED, stage, p, _argv("fit_corpus", p, "--corpus", corpus), deps))
        fits = self.fits = tuple(st.name for st in self.steps if st.stage.startswith("fit-corpus"))
        self.steps += [Step(SHARED, "train-tokenizers", p, _argv("train_tokenizers", p), fits),
                       Step(SHARED, "tokenize", p, _argv("tokenize", p), (self.tok, *fits)),
                       Step(SHARED, "train-backtranslation", p, _argv("train_backtranslation", p), fits),
                       Step(SHARED, "evaluate-backtranslation", p, _argv("evaluate_backtranslation", p),
                            (s + "train-backtranslation",)),
                       Step(SHARED, "train-backtranslation-skeleton", p, _argv("train_backtranslation_skeleton", p),
                            fits)]

    def add(self, name: str, settings: dict, stages: Sequence[tuple[str, tuple[str, ...]]],
            shared_dirs: Sequence[str] = (), generated_from: str | None = None,
            after: Mapping[str, tuple[str, ...]] | None = None) -> None:
        """A variant's steps; its models folder links ``shared_dirs`` (DataConfig properties) of the shared models,
        its generated folder is that of the variant ``generated_from``."""
        path, params = self.writer.write(name, settings)
        links = tuple((getattr(params.data, d), getattr(self.shared.data, d)) for d in shared_dirs)
        if generated_from is not None:
            source = _folders(self.root, generated_from)["data"]["generated_dir"]
            links += ((Path(params.data.generated_dir), Path(source)),)
        self.steps.extend(Step(name, stage, path, _argv(stage.replace("-", "_"), path), deps, links,
                               (after or {}).get(stage, ())) for stage, deps in stages)

    def add_tokenizers(self, seed: int) -> None:
        for quantizer, batch in TOKENIZER_SETTINGS:
            if (quantizer, batch, seed) != ("fsq", 16, self.shared_seed):  # that one is the shared run
                self.add(f"tokenizer-{quantizer}-b{batch}-s{seed}", {"tokenizer": {"quantizer": quantizer},
                         "tokenizer_train": {"batch_size": batch, "seed": seed}}, [("train-tokenizers", self.fits)])

    def add_smlm(self, seed: int) -> None:
        tokens = (f"{SHARED}.tokenize", self.tok)
        # the objective's ablation at equal epochs (shared steps) and at equal production updates (added steps)
        for objective, steps, kind in ((True, "shared", "translation"), (False, "shared", "production"),
                                       (True, "added", "translation-added")):
            name = f"smlm-{kind}-s{seed}"
            self.add(name, {"smlm_train": {"translation_objective": objective, "translation_steps": steps,
                                           "seed": seed}},
                     [("train-smlm", tokens), ("generate-smlm", (f"{name}.train-smlm", *tokens)),
                      ("evaluate-smlm", (f"{name}.generate-smlm", f"{SHARED}.train-backtranslation"))],
                     ("tokenizers_dir", "backtranslation_dir"))

    def add_slr(self, seed: int) -> None:
        self.add(f"slr-s{seed}", {"slr_train": {"seed": seed}},
                 [("train-slr", (*self.fits, self.tok)), ("evaluate-slr", (f"slr-s{seed}.train-slr", self.tok))],
                 ("tokenizers_dir",))

    def add_sgsa(self, seed: int, infinite: bool) -> None:
        """N = inf (the SGSA system alone), or the configured N beside PT, judged with the same seed's SMLM."""
        judge, dirs = (f"{SHARED}.train-backtranslation-skeleton", self.tok), ("tokenizers_dir", "skeleton_judge_dir")
        if infinite:
            name = f"sgsa-ninf-s{seed}"
            self.add(name, {"sgsa": {"temporal_adjacency": 0}, "sgsa_train": {"systems": ["sgsa"], "seed": seed}},
                     [("train-sgsa", self.fits), ("evaluate-sgsa", (f"{name}.train-sgsa", *judge))], dirs)
            return
        name, smlm = f"sgsa-n{self.base.sgsa.temporal_adjacency}-s{seed}", f"smlm-translation-s{seed}"
        inf = tuple(st.name for st in self.steps if st.variant.startswith("sgsa-ninf-") and st.stage == "evaluate-sgsa")
        evaluate = ("evaluate-sgsa", (f"{name}.train-sgsa", *judge, f"{smlm}.generate-smlm"))
        self.add(name, {"sgsa_train": {"systems": ["pt", "sgsa"], "seed": seed}}, [("train-sgsa", self.fits), evaluate],
                 dirs, generated_from=smlm, after={"evaluate-sgsa": inf})


def plan(params_path: str | Path, preset: str, seeds: Sequence[int], root: str | Path) -> list[Step]:
    """Every step of the study in run order; writes the variants' params files under ``<root>/params``."""
    where = f"{params_path} + preset {preset}"
    raw = merge(read_yaml(params_path), preset_overlay(preset))
    base = params_from_dict(raw)
    _check(base, where, seeds)
    planner = _Planner(raw, base, Path(root), where)
    planner.add_shared()
    for add in (planner.add_tokenizers, planner.add_smlm, planner.add_slr):
        for seed in seeds:
            add(seed)
    for infinite in (True, False):  # every N = inf run first: the claims read the setting of the newest evaluate-sgsa
        for seed in seeds:
            planner.add_sgsa(seed, infinite)
    return planner.steps


def select(steps: list[Step], only: Sequence[str]) -> list[Step]:
    """The steps named by stage, variant or ``variant.stage`` in ``only`` (all when empty)."""
    unknown = [n for n in only if not any(n in (st.stage, st.variant, st.name) for st in steps)]
    if unknown:
        stages = ", ".join(dict.fromkeys(st.stage for st in steps))
        raise StudyError(f"--only {' '.join(unknown)}: no step of the plan is named so; give stages ({stages}), "
                         "variants (e.g. slr-s0) or variant.stage")
    return [st for st in steps if not only or any(n in (st.stage, st.variant, st.name) for n in only)]


# ------------------------------------------------------------------ running
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
