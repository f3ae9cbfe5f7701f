"""The house points one way: the import graph of m3t/, flows/ and dashboards/ has no cycle, no upward import
and no stage -> stage import, and every DVC stage declares the code it runs.

Every import counts, including those inside functions (they run too). Failures name the file and line.
"""
from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("m3t", "flows", "dashboards")

# Lowest first; a module may import from its own layer and the layers below it. The body model is the
# foundation every other component computes with; shards (the data contract) sit below fitting, which writes
# them; metrics and render depend only on the body model and shards, so trainers can select checkpoints by
# them; models (smlm, slr, backtranslation and the coming sgsa) sit above tokenizers; the claims read every
# model's runs.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base", ("m3t", "m3t.atomic", "m3t.runtime", "m3t.training", "m3t.camera", "m3t.experiment")),
    ("body", ("m3t.body",)),
    ("corpora", ("m3t.corpora",)),
    ("trackers", ("m3t.trackers",)),
    ("shards", ("m3t.shards",)),
    ("metrics", ("m3t.metrics",)),
    ("render", ("m3t.render",)),
    ("fitting", ("m3t.fitting",)),
    ("tokenizers", ("m3t.tokenizers",)),
    ("models", ("m3t.smlm", "m3t.sgsa", "m3t.slr", "m3t.backtranslation")),
    ("claims", ("m3t.claims",)),
    ("config", ("m3t.config",)),
    ("stages", ("m3t.stages",)),
    ("dashboards", ("dashboards",)),
    ("flows", ("flows",)),
    ("surfaces", ("flows.cli", "flows.services")),
)


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def layer_of(module: str) -> int:
    best, rank = "", -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".") or prefix == "m3t" and module == "m3t") \
                    and len(prefix) > len(best):
                best, rank = prefix, i
    if rank < 0:
        raise AssertionError(f"module {module} is in no layer of tests/project/test_architecture.py; "
                             "add its package there")
    return rank


@cache
def imports(module: str) -> tuple[tuple[str, int], ...]:
    """(imported project module, line) of every import statement in ``module``."""
    known = modules()
    path = known[module]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            # `from pkg import sub` imports the module pkg.sub when it is one
            names = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in known else node.module
                     for a in node.names]
        else:
            continue
        for name in names:
            while name and name not in known:
                name = name.rpartition(".")[0]
            if name and name.split(".")[0] in PACKAGES and name != module:
                out.append((name, node.lineno))
    return tuple(sorted(set(out)))


def where(module: str, line: int) -> str:
    return f"{modules()[module].relative_to(ROOT)}:{line}"


def test_no_upward_import():
    bad = [f"{where(m, line)} imports {target} ({LAYERS[layer_of(target)][0]}) from {LAYERS[layer_of(m)][0]}"
           for m in modules() for target, line in imports(m) if layer_of(target) > layer_of(m)]
    assert not bad, "upward imports (move the code down, or the importer up):\n" + "\n".join(bad)


def test_no_stage_imports_another_stage():
    stage = re.compile(r"^m3t\.stages\.\w+$")
    bad = [f"{where(m, line)} imports {target}" for m in modules() if stage.match(m)
           for target, line in imports(m) if stage.match(target)]
    assert not bad, "a stage imports another stage (move the shared code into the library):\n" + "\n".join(bad)


def test_no_import_cycle():
    graph = {m: [t for t, _ in imports(m)] for m in modules()}
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for t in graph[m]:
            if state.get(t) == 1:
                cycles.append(stack[stack.index(t):] + [t])
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m)
    lines = []
    for cycle in cycles:
        steps = [f"{where(a, dict(imports(a))[b])} -> {b}" for a, b in zip(cycle, cycle[1:])]
        lines.append("  " + "; ".join(steps))
    assert not cycles, "import cycles:\n" + "\n".join(lines)


def closure(module: str) -> set[str]:
    seen, todo = set(), [module]
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        todo.extend(t for t, _ in imports(m))
    return seen


def stage_modules() -> dict[str, str]:
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    out = {}
    for name, stage in stages.items():
        found = re.search(r"-m ((?:m3t\.stages|dashboards)\.\w+)", stage["cmd"])
        assert found, f"dvc.yaml stage {name}: cmd {stage['cmd']!r} does not run a m3t.stages (or dashboards) module"
        out[name] = found.group(1)
    return out


@pytest.mark.parametrize("stage", sorted(stage_modules()))
def test_dvc_deps_cover_the_code_a_stage_runs(stage):
    """A stage's deps cover every project module its entry point imports (transitively), so that a code
    change reruns exactly the stages it can affect; deps on code it never imports would rerun it for nothing."""
    spec = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"][stage]
    deps = [str(d) for d in spec.get("deps", [])]
    code_deps = [d.rstrip("/") for d in deps if d.split("/")[0] in PACKAGES]
    files = sorted(str(modules()[m].relative_to(ROOT)) for m in closure(stage_modules()[stage]))

    def covered(file: str) -> bool:
        return any(file == d or file.startswith(d + "/") for d in code_deps)

    missing = [f for f in files if not covered(f)]
    assert not missing, f"dvc.yaml stage {stage} runs code it does not declare; add to its deps:\n" + "\n".join(missing)
    unused = [d for d in code_deps if not any(f == d or f.startswith(d + "/") for f in files)]
    assert not unused, f"dvc.yaml stage {stage} declares code it never imports: {unused}"


def test_training_stages_depend_on_every_training_corpus():
    """``data.train_corpora`` is one key in params.yaml; DVC must see each corpus' shards as a dep."""
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    data = params["data"]
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    missing = []
    for name, root in (("train-tokenizers", "shards_root"), ("tokenize", "shards_root"), ("train-smlm", "tokens_root"),
                       ("train-backtranslation", "shards_root"), ("train-backtranslation-skeleton", "shards_root"),
                       ("train-sgsa", "shards_root"), ("evaluate-sgsa", "shards_root")):
        deps = [str(d) for d in stages[name]["deps"]]
        for corpus in data["train_corpora"]:
            split = "test" if name.startswith("evaluate") else "train"
            shard = f"{data[root]}/{corpus}/{split}.parquet"
            if shard not in deps:
                missing.append(f"{name}: {shard}")
    for name in ("train-slr", "evaluate-slr"):  # the probe reads the isolated clips of slr.corpus
        for split in ("train", "dev", "test"):
            shard = f"{data['shards_root']}/{params['slr']['corpus']}/{split}.parquet"
            if shard not in [str(d) for d in stages[name]["deps"]]:
                missing.append(f"{name}: {shard}")
    assert not missing, "dvc.yaml deps miss the shards of data.train_corpora / slr.corpus:\n" + "\n".join(missing)


def test_no_flow_module_shadows_an_installed_package():
    """Prefect runs a served flow with its file's folder on sys.path: a ``flows/tokenizers.py`` there hides
    Hugging Face's ``tokenizers`` from transformers, and every served flow that loads the SMLM fails on import."""
    import importlib.util
    import sys

    saved = list(sys.path)
    try:
        # installed packages only: the repository's root, flows/ and tests/ (whose component folders import as
        # namespace packages) are not what a served flow would shadow; a .venv inside the checkout stays
        def ours(entry: str) -> bool:
            path = Path(entry or ".").resolve()
            return path == ROOT or path.is_relative_to(ROOT / "flows") or path.is_relative_to(ROOT / "tests")
        sys.path[:] = [p for p in sys.path if not ours(p)]
        clashes = [p.stem for p in sorted((ROOT / "flows").glob("*.py"))
                   if p.stem != "__init__" and importlib.util.find_spec(p.stem) is not None]
    finally:
        sys.path[:] = saved
    assert not clashes, f"flows/ modules named like installed packages (rename them): {clashes}"
