"""Security checks of the library (m3t/, flows/, dashboards/, cli/), run by the README's test command.

1. Lint: ruff's flake8-bandit rules (``--select S``) report nothing. Accepted findings, each suppressed where it
   occurs (``# noqa: S...`` with its reason, or ``[tool.ruff.lint.per-file-ignores]`` in pyproject.toml):

   - S603 / S607 ``cli/variants.py`` ``run_logged`` / ``experiment_names``: ``subprocess`` calls of the
     ``dvc exp run`` argv list that ``exp_argv`` builds and of two fixed ``git`` queries, no shell;
   - S603 ``cli/processes.py`` ``start``: ``subprocess.Popen`` of the argv list that ``plan()`` builds, no shell;
   - S310 ``cli/services.py`` ``_http``: ``urllib.request`` on a health URL; ``_http`` refuses anything but
     ``http://`` / ``https://`` first (the URLs come from ``services.json``, a file on disk);
   - S606 ``m3t/arithmetic.py`` ``_restart``: ``os.execve`` of this process's own interpreter and argv, in the
     pinned environment of ``M3T_REPRODUCIBLE=1``;
   - S104 ``cli/services.py`` ``plan``: the string ``"0.0.0.0"`` is compared with ``--host`` to pick the address
     clients connect to; nothing binds it;
   - S101 ``m3t/body/anny_body.py``, ``tools/build_correspondence.py``, ``m3t/shards/dataset.py``: asserts on
     internal invariants (Anny's bone order and blendshapes, the hand-joint table, a type narrowing), never on
     user input.

   bandit 1.9.4 over the same folders rates none of its findings HIGH; its MEDIUM ones are the S310 / S104 above
   and B615 on the two ``from_pretrained`` calls, which pass ``local_files_only=True`` (checked below).
2. Deserialisation (an AST scan, so aliases such as ``from torch import load`` count): every ``torch.load`` passes
   ``weights_only=True`` and every ``np.load`` ``allow_pickle=False``, literally; ``pickle.load`` / ``loads`` /
   ``Unpickler`` appear only in the restricted unpickler ``m3t.body.model_files.SafeModelUnpickler`` (which
   ``m3t.corpora.annotation_files.CorpusUnpickler`` extends); no ``eval`` / ``exec``, ``yaml.load``, ``joblib`` /
   ``dill`` / ``shelve`` / ``marshal`` / ``pandas.read_pickle``; Hugging Face loads are ``local_files_only=True``
   and never ``trust_remote_code``. :data:`ALLOWED` lists exceptions with their reasons; it is empty (the Anny
   cavity file, once loaded with ``weights_only=False``, holds two lists of ints and loads with
   ``weights_only=True``).
3. Servers bind 127.0.0.1 by default: ``ServicesConfig.host``, ``m3t up`` / ``m3t serve``, ``plan()``'s commands and
   URLs, and every ``dashboard_address`` literal (distributed binds ``":0"`` on all interfaces).
4. Paths from params values: the soke_smplx annotation CSV and the slt_pickle files are refused, unopened, when
   they lead outside the corpus root (``..``, absolute, a symbolic link), like every manifest row
   (``m3t.corpora.listing.media_path_problem``; the per-adapter row tests are in tests/corpora/test_readers.py).
"""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("m3t", "flows", "dashboards", "cli")
LOOPBACK = ("127.0.0.1", "localhost", "::1")

# (file, call) -> why it may break the rule; a new unsafe load fails the scan until it is listed here with a reason.
ALLOWED: dict[tuple[str, str], str] = {}
# classes that may subclass pickle.Unpickler: they allow-list the globals a file may name
RESTRICTED_UNPICKLERS = {("m3t/body/model_files.py", "SafeModelUnpickler")}


# ----------------------------------------------------------------------------------------- 1. lint
def ruff_s(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess:
    pytest.importorskip("ruff", reason="ruff is in the test extra: pip install -e '.[test]'")
    return subprocess.run([sys.executable, "-m", "ruff", "check", "--select", "S", "--no-fix", "--output-format",
                           "concise", *args], cwd=ROOT, input=stdin, capture_output=True, text=True, timeout=120)


def test_ruff_security_rules_find_nothing():
    done = ruff_s(*PACKAGES)
    assert done.returncode == 0, f"ruff --select S findings (fix them, or accept one with a reasoned noqa and list " \
                                 f"it in this module's docstring):\n{done.stdout}{done.stderr}"


def test_ruff_security_lint_catches_a_planted_finding():
    """The lint test above would pass vacuously if the rule set or the config silenced everything."""
    planted = "import subprocess\n\nsubprocess.call(input(), shell=True)\nassert input()\n"
    done = ruff_s("--stdin-filename", "m3t/planted.py", "-", stdin=planted)
    assert done.returncode == 1 and "S602" in done.stdout and "S101" in done.stdout, done.stdout + done.stderr


# ----------------------------------------------------------------------------------------- 2. deserialisation
def _aliases(tree: ast.Module) -> dict[str, str]:
    """Local name -> dotted origin of every import in the module (``np`` -> ``numpy``, ``L`` -> ``torch.load``)."""
    out: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                out[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for a in node.names:
                out[a.asname or a.name] = f"{node.module}.{a.name}"
    return out


def _dotted(node: ast.expr, aliases: dict[str, str]) -> str | None:
    parts: list[str] = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return ".".join([aliases.get(node.id, node.id), *reversed(parts)])


def _keyword(call: ast.Call, name: str):
    """The literal value of keyword ``name`` (``...`` when absent or not a literal)."""
    for kw in call.keywords:
        if kw.arg == name:
            return kw.value.value if isinstance(kw.value, ast.Constant) else ...
    return ...


FORBIDDEN = {"pickle.load", "pickle.loads", "pickle.Unpickler", "_pickle.load", "_pickle.loads", "cPickle.load",
             "cPickle.loads", "yaml.load", "yaml.unsafe_load", "yaml.full_load", "pandas.read_pickle",
             "marshal.load", "marshal.loads", "shelve.open", "eval", "exec", "builtins.eval", "builtins.exec"}
FORBIDDEN_MODULES = ("dill", "joblib", "cloudpickle")


def unsafe_loads(source: str, rel: str) -> list[str]:
    """``"<rel>:<line> <call>: <problem>"`` for every deserialisation of ``source`` that could run code."""
    tree = ast.parse(source)
    aliases = _aliases(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef):
            for base in node.bases:
                if _dotted(base, aliases) in ("pickle.Unpickler", "_pickle.Unpickler") \
                        and (rel, node.name) not in RESTRICTED_UNPICKLERS:
                    found.append(f"{rel}:{node.lineno} class {node.name}: a new pickle.Unpickler (extend "
                                 "m3t.body.model_files.SafeModelUnpickler instead)")
        if not isinstance(node, ast.Call):
            continue
        name = _dotted(node.func, aliases)
        if name is None:
            continue
        where = f"{rel}:{node.lineno} {name}"
        if name == "torch.load" and _keyword(node, "weights_only") is not True:
            found.append(f"{where}: pass weights_only=True")
        elif name == "numpy.load" and _keyword(node, "allow_pickle") is not False:
            found.append(f"{where}: pass allow_pickle=False")
        elif name.endswith(".from_pretrained") and (_keyword(node, "local_files_only") is not True
                                                     or _keyword(node, "trust_remote_code") not in (..., False)):
            found.append(f"{where}: pass local_files_only=True and no trust_remote_code")
        elif name in FORBIDDEN or name.split(".")[0] in FORBIDDEN_MODULES:
            found.append(f"{where}: runs code from the file; use a restricted unpickler or a data format")
    return [f for f in found if (rel, f.split(" ")[1].rstrip(":")) not in ALLOWED]


def library_files() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


@pytest.mark.parametrize("source, problem", [
    ("import torch\ntorch.load(p)", "weights_only=True"),
    ("import torch\ntorch.load(p, weights_only=False)", "weights_only=True"),
    ("import torch\ntorch.load(p, weights_only=flag)", "weights_only=True"),
    ("from torch import load as L\nL(p)", "weights_only=True"),
    ("import numpy as np\nnp.load(p)", "allow_pickle=False"),
    ("import numpy as np\nnp.load(p, allow_pickle=True)", "allow_pickle=False"),
    ("import pickle\npickle.loads(b)", "runs code"),
    ("from pickle import load\nload(fh)", "runs code"),
    ("import pickle\nclass U(pickle.Unpickler):\n    pass", "SafeModelUnpickler"),
    ("import yaml\nyaml.load(s, Loader=yaml.Loader)", "runs code"),
    ("import joblib\njoblib.load(p)", "runs code"),
    ("eval(s)", "runs code"),
    ("from transformers import AutoTokenizer\nAutoTokenizer.from_pretrained(p)", "local_files_only"),
    ("from transformers import M\nM.from_pretrained(p, local_files_only=True, trust_remote_code=True)", "local_files"),
    ("import torch\ntorch.load(p, map_location='cpu', weights_only=True)", None),
    ("import numpy as np\nwith np.load(p, allow_pickle=False) as d:\n    pass", None),
    ("import yaml\nyaml.safe_load(s)", None),
    ("model.eval()", None),
])
def test_scan_flags_unsafe_loads(source, problem):
    found = unsafe_loads(source, "m3t/x.py")
    assert (found == []) if problem is None else (len(found) == 1 and problem in found[0]), found


def test_library_deserialises_only_safely():
    found = [f for p in library_files()
             for f in unsafe_loads(p.read_text(encoding="utf-8"), p.relative_to(ROOT).as_posix())]
    assert not found, "unsafe loads (fix them, or list one in ALLOWED with its reason):\n" + "\n".join(found)


def test_restricted_unpicklers_exist_where_listed():
    """RESTRICTED_UNPICKLERS names real classes (a rename must not leave a stale exception behind)."""
    from m3t.body import model_files
    from m3t.corpora.annotation_files import CorpusUnpickler

    assert all(hasattr(model_files, name) for _, name in RESTRICTED_UNPICKLERS)
    assert issubclass(CorpusUnpickler, model_files.SafeModelUnpickler)


# ----------------------------------------------------------------------------------------- 3. servers
def test_services_bind_loopback_by_default(monkeypatch):
    import cli.services as services
    from cli.main import main
    from cli.processes import ServiceError

    assert services.ServicesConfig().host == "127.0.0.1"
    seen = []

    def fake_up(cfg):
        seen.append(cfg)
        raise ServiceError("not started in this test")

    monkeypatch.setattr(services, "up", fake_up)
    assert main(["up"]) == 1 and main(["serve"]) == 1
    assert [c.host for c in seen] == ["127.0.0.1", "127.0.0.1"]
    for service in services.plan(services.ServicesConfig(params=ROOT / "params.yaml")):
        command = list(service.command)
        if "--host" in command:
            assert command[command.index("--host") + 1] == "127.0.0.1", command
        assert service.url.startswith("http://127.0.0.1:") and service.health_url.startswith("http://127.0.0.1:")


def test_dashboard_addresses_are_loopback():
    """distributed binds a dashboard_address without a host (``":0"``, ``":8787"``) on every interface."""
    found = []
    for path in library_files():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call):
                for kw in node.keywords:
                    if kw.arg in ("dashboard_address", "host", "ip") and isinstance(kw.value, ast.Constant) \
                            and isinstance(kw.value.value, str) and not kw.value.value.startswith(LOOPBACK):
                        found.append(f"{path.relative_to(ROOT)}:{node.lineno} {kw.arg}={kw.value.value!r}")
    assert not found, "binds beyond loopback (use '127.0.0.1:0'):\n" + "\n".join(found)


def test_health_checks_follow_only_http(monkeypatch, tmp_path):
    """services.json is a file on disk: a health URL it names must not make the CLI read local files."""
    import urllib.request

    import cli.services as services

    opened = []
    def urlopen(request, timeout):
        opened.append(request.full_url)
        raise OSError("recorded, not opened")

    monkeypatch.setattr(urllib.request, "urlopen", urlopen)
    secret = tmp_path / "secret"
    secret.write_text("x")
    assert services._http(secret.as_uri()) is None and services._http("ftp://127.0.0.1/x") is None
    assert opened == []


# ----------------------------------------------------------------------------------------- 4. params paths
def outside(tmp_path: Path, root: Path, name: str) -> list[str]:
    """Params values leading from ``root`` to ``tmp_path / "outside" / name``: through ``..``, absolute, and
    through a symbolic link inside the root."""
    target = tmp_path / "outside" / name
    (root / f"link_{name}").symlink_to(target)
    return [f"../outside/{name}", str(target), f"link_{name}"]


def test_soke_annotation_outside_the_root_is_never_read(tmp_path, monkeypatch):
    """Layout: tests/corpus_fixtures.py ``build_soke`` (SOKE's release, 2000ZRL/SOKE ``load_data.py``)."""
    import corpus_fixtures as fx

    import m3t.corpora.soke_smplx as soke
    from m3t.corpora.base import open_corpus
    from m3t.corpora.listing import CorpusError

    root = tmp_path / "corpus"
    fx.build_soke(root)
    (tmp_path / "outside").mkdir()
    (root / "annotation.csv").rename(tmp_path / "outside" / "notes.csv")  # a valid CSV: reading it would list
    read = []
    real = soke.read_lines
    monkeypatch.setattr(soke, "read_lines", lambda path, hint: read.append(Path(path)) or real(path, hint))
    for value in outside(tmp_path, root, "notes.csv"):
        with pytest.raises(CorpusError, match="outside the corpus root|is absolute|'..' component"):
            open_corpus("soke_smplx", root, annotation=value).listing()
    assert read == []


def test_slt_files_outside_the_root_are_never_read(tmp_path, monkeypatch):
    """Layout: tests/corpus_fixtures.py ``build_slt`` (neccam/slt's gzip pickles, ``signjoey/dataset.py``)."""
    import corpus_fixtures as fx

    import m3t.corpora.slt_pickle as slt
    from m3t.corpora.base import open_corpus

    root = tmp_path / "corpus"
    files = fx.build_slt(root).extra["files"]
    (tmp_path / "outside").mkdir()
    (root / files["dev"]).rename(tmp_path / "outside" / files["dev"])  # a valid file: reading it would list it
    read = []
    real = slt.read_slt_pickle
    monkeypatch.setattr(slt, "read_slt_pickle", lambda path: read.append(Path(path)) or real(path))
    values = outside(tmp_path, root, files["dev"])
    listing = open_corpus("slt_pickle", root, files=tuple(values) + (files["train"],)).listing()
    assert all(p.resolve().is_relative_to(root.resolve()) for p in read) and read, read
    assert {c.split for c in listing.clips} == {"train"}
    assert sum("unsafe media path" in q.reason for q in listing.quarantined) == 3, listing.quarantined
    walked = open_corpus("slt_pickle", root).listing()  # discovery finds the link: refused, not read
    assert all(p.resolve().is_relative_to(root.resolve()) for p in read), read
    assert any("unsafe media path" in q.reason for q in walked.quarantined), walked.quarantined
