"""The one way variants x seeds run: each variant is a DVC experiment, ``dvc exp run --temp -n NAME -S KEY=VALUE ...
STAGE...``, in a temporary copy of the workspace. ``m3t study``, ``m3t ablate-tokenizers`` and ``m3t sgsa-sweep``
only choose the variants.

DVC decides what a variant runs: ``dvc.yaml``'s graph, and its run cache, which restores a stage that already ran
with the same commands, deps and params instead of running it again (so the stages variants share run once, and
a finished sweep rerun restores everything). ``dvc exp show`` compares the experiments; the stages' MLflow runs go
to the workspace's store (``MLFLOW_TRACKING_URI``), where the tables and ``m3t claims`` read them.

Two settings go into every variant besides its own:

- the caches (every ``*.cache_dir`` of the params) point at the workspace's own folders: they are
  content-addressed, so the experiments share the fits and a killed training resumes from its last checkpoint;
- a preset's keys, when a preset is asked for (``+KEY=VALUE`` for a key ``params.yaml`` lacks).

Besides the experiments it writes ``<log_dir>/<variant>.log`` (each variant's ``dvc exp run`` output).
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from m3t.config import preset_overlay, read_yaml
from m3t.experiment import ExperimentConfig, absolute_uri, ensure_experiment, tracking_uri

Runner = Callable[[Sequence[str], Mapping[str, str], Path, Path], int]  # (argv, extra env, log, cwd) -> exit code
_PLAIN = re.compile(r"[A-Za-z_][A-Za-z0-9_.\-]*")


class VariantError(ValueError):
    """Variants that cannot run as asked; the message names the stage, file or key."""


@dataclass(frozen=True)
class Variant:
    """One experiment: its name, its ``-S`` settings (dotted key -> value) and the ``dvc.yaml`` stages it asks for
    (DVC adds whatever they read)."""

    name: str
    settings: Mapping[str, object]
    targets: tuple[str, ...]


@dataclass
class SweepSummary:
    ran: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)  # variant -> why
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.failed


def flatten(tree: Mapping, prefix: str = "") -> dict[str, object]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (lists are values)."""
    out: dict[str, object] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, name + "."))
        else:
            out[name] = value
    return out


def unflatten(settings: Mapping[str, object]) -> dict:
    """``{"a.b": 1}`` -> ``{"a": {"b": 1}}``: settings as a params overlay."""
    tree: dict = {}
    for key, value in settings.items():
        node = tree
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return tree


def override_value(value: object) -> str:
    """A value in the override grammar of ``dvc exp run -S`` (Hydra's): strings quoted unless plainly a name."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(override_value(v) for v in value) + "]"
    text = str(value)
    if _PLAIN.fullmatch(text) and text.lower() not in ("true", "false", "null", "none", "nan", "inf"):
        return text
    return "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"


def _has(tree: Mapping, dotted: str) -> bool:
    node: object = tree
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return False
        node = node[part]
    return True


def exp_argv(variant: Variant, base: Mapping[str, object], params_tree: Mapping) -> list[str]:
    """``dvc exp run --temp -n NAME -S ... STAGES``: ``base`` then the variant's own settings (a key in both takes
    the variant's); ``+KEY`` for a key ``params_tree`` (the workspace's ``params.yaml``) does not hold."""
    argv = ["dvc", "exp", "run", "--temp", "-n", variant.name]
    for key, value in {**base, **variant.settings}.items():
        argv += ["-S", f"{'' if _has(params_tree, key) else '+'}{key}={override_value(value)}"]
    return argv + list(variant.targets)


def shared_settings(workspace: Path, params_tree: Mapping, preset: str | None = None) -> dict[str, object]:
    """The settings of every variant: the preset's keys, then every ``*.cache_dir`` made absolute in ``workspace``."""
    out = flatten(preset_overlay(preset)) if preset else {}
    for key, value in flatten(params_tree).items():
        if key.endswith(".cache_dir") and isinstance(value, str) and not Path(value).is_absolute():
            out[key] = str((workspace / value).resolve())
    return out


def workspace_of(params_path: str | Path) -> Path:
    """The DVC workspace whose ``params.yaml`` the experiments change: the folder of ``params_path``, which must be
    that file (the experiments read no other)."""
    path = Path(params_path).resolve()
    if path.name != "params.yaml" or not (path.parent / "dvc.yaml").is_file():
        raise VariantError(f"{params_path}: m3t runs DVC experiments on a workspace's params.yaml (beside "
                           "its dvc.yaml); change that file, or give settings with --set KEY=VALUE")
    return path.parent


def dvc_stages(workspace: Path) -> set[str]:
    return set(yaml.safe_load((workspace / "dvc.yaml").read_text(encoding="utf-8"))["stages"])


def _git(*args: str, cwd: Path) -> str:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True,  # noqa: S603, S607 - fixed git query
                          check=True).stdout.strip()


def experiment_names(workspace: Path) -> set[str]:
    """Names of the experiments on the workspace's current commit (none when it is no git repository)."""
    try:
        head = _git("rev-parse", "HEAD", cwd=workspace)
        refs = _git("for-each-ref", "--format=%(refname:lstrip=4)", f"refs/exps/{head[:2]}/{head[2:]}/", cwd=workspace)
    except (OSError, subprocess.CalledProcessError):
        return set()
    return set(refs.split())


def run_logged(argv: Sequence[str], env: Mapping[str, str], log: Path, cwd: Path) -> int:
    """``argv`` in ``cwd`` (a leading ``dvc`` is this interpreter's DVC), its output into ``log``."""
    argv = [sys.executable, "-m", "dvc", *argv[1:]] if argv[0] == "dvc" else list(argv)
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w", encoding="utf-8") as handle:
        return subprocess.call(argv, env={**os.environ, **env}, stdout=handle,  # noqa: S603 - argv list, no shell
                               stderr=subprocess.STDOUT, cwd=cwd)


def tracking_env(cfg: ExperimentConfig, workspace: Path) -> dict[str, str]:
    """``MLFLOW_TRACKING_URI`` of the workspace's store for the experiments' stages, with the MLflow experiment
    created there first (its artifacts in the workspace, not in a temporary copy that DVC deletes)."""
    ensure_experiment(cfg, workspace)
    return {"MLFLOW_TRACKING_URI": absolute_uri(tracking_uri(cfg, workspace), workspace)}


def run_variants(variants: Sequence[Variant], workspace: str | Path, log_dir: str | Path, *,
                 preset: str | None = None, env: Mapping[str, str] | None = None, dry_run: bool = False,
                 runner: Runner = run_logged) -> SweepSummary:
    """Run every variant as a DVC experiment, in order; a failed one is reported and the rest still run."""
    workspace, log_dir = Path(workspace), Path(log_dir)
    tree = read_yaml(workspace / "params.yaml")
    known = dvc_stages(workspace)
    unknown = sorted({t for v in variants for t in v.targets} - known)
    if unknown:
        raise VariantError(f"stages {', '.join(unknown)} are not in {workspace / 'dvc.yaml'}; a variant runs dvc.yaml's "
                         "stages only")
    base = shared_settings(workspace, tree, preset)
    existing = set() if dry_run else experiment_names(workspace)
    summary = SweepSummary()
    for k, variant in enumerate(variants, 1):
        argv = exp_argv(variant, base, tree)
        if dry_run:
            print(f"[{k}/{len(variants)}] {shlex.join(argv)}")
            continue
        print(f"[{k}/{len(variants)}] {variant.name}: {' '.join(variant.targets)} ...", end=" ", flush=True)
        log = log_dir / f"{variant.name}.log"
        start = time.monotonic()
        code = 0
        if variant.name in existing:  # a rerun replaces the experiment of that name (its stages come from the cache)
            code = runner(["dvc", "exp", "remove", variant.name], dict(env or {}), log, workspace)
        code = code or runner(argv, dict(env or {}), log, workspace)
        summary.seconds[variant.name] = seconds = time.monotonic() - start
        if code == 0:
            summary.ran.append(variant.name)
            print(f"ok ({seconds:.1f} s)")
        else:
            summary.failed[variant.name] = f"exit {code}; log {log}"
            print(f"FAILED ({seconds:.1f} s): exit {code}; log {log}")
    if not dry_run:
        print(f"{len(summary.ran)} variants ran, {len(summary.failed)} failed; compare them: dvc exp show")
    return summary
