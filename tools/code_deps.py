"""The project's import graph, and ``dvc.yaml``'s code deps generated from it.

A DVC stage must declare every project module its entry point imports (transitively), and nothing else: a
missing dep lets a code change go unnoticed, an extra one reruns the stage for nothing. Keeping ~900 such
lines by hand is error-prone, so they are written by this script from the same import walk that
``tests/project/test_architecture.py`` uses to check the layering::

    python tools/code_deps.py          # rewrite dvc.yaml's code deps in place
    python tools/code_deps.py --check  # exit 1 and list the stages whose deps differ

Every import statement counts, including those inside functions (they run too); only those under
``if TYPE_CHECKING:`` do not (they never run). Only the code lines of each
stage's ``deps:`` list are rewritten: data deps keep their order and come first, comments and everything else
in ``dvc.yaml`` stay as they are.
"""
from __future__ import annotations

import argparse
import ast
import re
import sys
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("m3t", "flows", "dashboards", "cli")
DVC_YAML = ROOT / "dvc.yaml"
_STAGE_CMD = re.compile(r"-m ((?:m3t\.stages|dashboards)\.\w+)")


def module_name(path: Path) -> str:
    """``m3t/body/smplfx.py`` -> ``m3t.body.smplfx``; a package's ``__init__.py`` is the package."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def modules() -> dict[str, Path]:
    """Every project module -> its file."""
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


@cache
def imports(module: str) -> tuple[tuple[str, int], ...]:
    """(imported project module, line) of every import statement in ``module``."""
    known = modules()
    path = known[module]
    out = []
    for node in _run_time_nodes(ast.parse(path.read_text(), str(path))):
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


def _type_checking_only(node: ast.AST) -> bool:
    test = getattr(node, "test", None)
    return isinstance(node, ast.If) and (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING"
                                         or isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _run_time_nodes(tree: ast.AST):
    """Every node of ``tree`` except the bodies of ``if TYPE_CHECKING:`` blocks (their ``else`` still runs)."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        if _type_checking_only(node):
            todo.extend(node.orelse)
            todo.append(node.test)
        else:
            todo.extend(ast.iter_child_nodes(node))


def closure(module: str) -> set[str]:
    """``module`` and every project module it imports, transitively."""
    seen, todo = set(), [module]
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        todo.extend(t for t, _ in imports(m))
    return seen


def stage_modules(text: str) -> dict[str, str]:
    """DVC stage name -> the module its ``cmd`` runs (``python -m m3t.stages.X`` or ``dashboards.X``)."""
    import yaml

    out = {}
    for name, stage in yaml.safe_load(text)["stages"].items():
        found = _STAGE_CMD.search(stage["cmd"])
        if not found:
            raise SystemExit(f"dvc.yaml stage {name}: cmd {stage['cmd']!r} does not run a m3t.stages "
                             "(or dashboards) module, so its code deps cannot be derived")
        out[name] = found.group(1)
    return out


def code_deps(module: str) -> list[str]:
    """The files a stage running ``module`` must declare, sorted."""
    return sorted(str(modules()[m].relative_to(ROOT)) for m in closure(module))


def is_code(dep: str) -> bool:
    return dep.split("/")[0] in PACKAGES


def rewrite(text: str) -> str:
    """``dvc.yaml`` text with every stage's code deps replaced by the generated ones."""
    entry = stage_modules(text)
    out: list[str] = []
    stage = None
    in_deps = False
    for line in text.splitlines(keepends=True):
        header = re.match(r"^  ([\w-]+):\s*$", line)
        if header:
            stage, in_deps = header.group(1), False
        if in_deps and re.match(r"^    - ", line):
            if not is_code(line.strip()[2:]):
                out.append(line)
            continue
        if in_deps:  # the deps list ended: the generated code deps go last
            out.extend(f"    - {f}\n" for f in code_deps(entry[stage]))
            in_deps = False
        out.append(line)
        if stage in entry and re.match(r"^    deps:\s*$", line):
            in_deps = True
    if in_deps:
        out.extend(f"    - {f}\n" for f in code_deps(entry[stage]))
    return "".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="report stages whose code deps differ; write nothing")
    args = parser.parse_args(argv)
    text = DVC_YAML.read_text()
    new = rewrite(text)
    if args.check:
        import yaml

        old_stages, new_stages = (yaml.safe_load(t)["stages"] for t in (text, new))
        stale = [s for s in old_stages if old_stages[s].get("deps") != new_stages[s].get("deps")]
        for s in stale:
            print(f"dvc.yaml stage {s}: code deps differ from its imports; run python tools/code_deps.py")
        return 1 if stale else 0
    if new != text:
        DVC_YAML.write_text(new)
        print("dvc.yaml: code deps rewritten")
    return 0


if __name__ == "__main__":
    sys.exit(main())
