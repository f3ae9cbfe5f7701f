"""The house points one way: the import graph of m3t/, flows/ and dashboards/ has no cycle, no upward import
and no stage -> stage import, and every DVC stage declares the code it runs.

Every import counts, including those inside functions (they run too). Failures name the file and line.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

import tools.code_deps as code_deps_module
from tools.code_deps import DVC_YAML, ROOT, code_deps, imports, is_code, modules, rewrite, stage_modules

# Lowest first; a module may import from its own layer and the layers below it. The body model is the
# foundation every other component computes with; shards (the data contract) sit below fitting, which writes
# them; metrics and render depend only on the body model and shards, so trainers can select checkpoints by
# them; models (smlm, slr, backtranslation and the coming sgsa) sit above tokenizers; the claims read every
# model's runs; the applications (m3t score / produce / translate) use the trained models through params.yaml.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base", ("m3t", "m3t.atomic", "m3t.runtime", "m3t.training", "m3t.camera", "m3t.experiment", "m3t.dataclass_io",
              "m3t.reporting", "m3t.digest", "m3t.optimizer", "m3t.checkpoints", "m3t.training_jobs",
              "m3t.positional_encoding", "m3t.vocabulary", "m3t.declared")),
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
    ("applications", ("m3t.scoring", "m3t.production")),  # one input at a time, over every trained model
    ("stages", ("m3t.stages",)),
    ("dashboards", ("dashboards",)),
    ("flows", ("flows",)),
    ("cli", ("cli",)),
)


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


@pytest.mark.parametrize("stage", sorted(stage_modules(DVC_YAML.read_text())))
def test_dvc_deps_are_the_code_a_stage_runs(stage):
    """A stage's code deps are exactly the project modules its entry point imports (transitively), as
    ``tools/code_deps.py`` writes them: a code change reruns exactly the stages it can affect."""
    declared = [str(d) for d in yaml.safe_load(DVC_YAML.read_text())["stages"][stage].get("deps", [])]
    code = [d for d in declared if is_code(d)]
    expected = code_deps(stage_modules(DVC_YAML.read_text())[stage])
    missing, unused = sorted(set(expected) - set(code)), sorted(set(code) - set(expected))
    assert not missing and not unused, (
        f"dvc.yaml stage {stage}: code deps out of date (run python tools/code_deps.py)\n"
        f"  runs but does not declare: {missing}\n  declares but never imports: {unused}")


@pytest.mark.parametrize("stage", sorted(stage_modules(DVC_YAML.read_text())))
def test_a_stage_depends_on_the_config_of_each_section_it_reads(stage):
    """``m3t.config`` imports section classes only when params are loaded, so a section's config module is a
    code dep of exactly the stages that import it. A stage declaring a whole section in ``params`` must import
    its config module (its methods and defaults are code the stage runs); a stage declaring single keys reads
    plain values, which DVC tracks in params.yaml. Every stage computes folders with ``data``'s methods."""
    from m3t.config import SECTIONS

    spec = yaml.safe_load(DVC_YAML.read_text())["stages"][stage]
    files = set(code_deps(stage_modules(DVC_YAML.read_text())[stage]))
    whole = {str(k) for k in spec.get("params", []) if "." not in str(k)} | {"data"}
    missing = [f"{s} ({m})" for s in sorted(whole) if SECTIONS.get(s)
               for m in [SECTIONS[s].split(":")[0].replace(".", "/") + ".py"] if m not in files]
    assert not missing, f"dvc.yaml stage {stage} reads sections whose config it never imports: {missing}"


def test_generate_corpus_does_not_depend_on_model_configs():
    """The case that motivated lazy section classes: an SGSA or SMLM default must not rerun the corpus."""
    files = code_deps("m3t.stages.generate_corpus")
    assert not [f for f in files if f.endswith("/config.py") and f.split("/")[1] in
                ("sgsa", "smlm", "slr", "backtranslation", "tokenizers", "fitting")], files


def test_code_deps_follow_imports_inside_functions(tmp_path, monkeypatch):
    """The walk counts every import statement, also one inside a function, and follows it transitively."""
    pkg = tmp_path / "m3t"
    (pkg / "stages").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "stages" / "__init__.py").write_text("")
    (pkg / "stages" / "run.py").write_text("def main():\n    from m3t.lib import f\n    return f()\n")
    (pkg / "lib.py").write_text("import m3t.deep\n\ndef f():\n    return 1\n")
    (pkg / "deep.py").write_text("")
    (pkg / "unused.py").write_text("")
    monkeypatch.setattr(code_deps_module, "ROOT", tmp_path)
    for fn in (code_deps_module.modules, code_deps_module.imports):
        fn.cache_clear()
    try:
        # packages' __init__ files count when imported by name (they hold no code of their own here)
        assert code_deps("m3t.stages.run") == ["m3t/deep.py", "m3t/lib.py", "m3t/stages/run.py"]
        text = ("stages:\n  run:\n    cmd: python -m m3t.stages.run\n    deps:\n    - data/in\n"
                "    - m3t/unused.py\n    outs:\n    - data/out\n")
        assert rewrite(text) == ("stages:\n  run:\n    cmd: python -m m3t.stages.run\n    deps:\n    - data/in\n"
                                 "    - m3t/deep.py\n    - m3t/lib.py\n    - m3t/stages/run.py\n    outs:\n    - data/out\n")
    finally:
        for fn in (code_deps_module.modules, code_deps_module.imports):
            fn.cache_clear()


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
