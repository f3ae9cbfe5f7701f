"""Variants x seeds as DVC experiments (cli/variants.py) and the claims study's plan (cli/study_plan.py,
cli/study.py): every (variant, seed) the claims read exactly once, with the settings that make DVC's run cache
share what variants have in common; the ``-S`` arguments in DVC's override grammar; a real ``dvc exp run`` on a
two-stage workspace (the shared stage runs once, a failed variant leaves the rest, the workspace's params.yaml is
left alone); a fake runner for the study's command line.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
import yaml

from cli.main import main as cli_main
from cli.study import study
from cli.study_plan import StudyError, parse_settings, plan, select, with_settings
from cli.variants import (
    Variant,
    exp_argv,
    flatten,
    override_value,
    run_logged,
    run_variants,
    shared_settings,
    unflatten,
)
from m3t.config import load_params, merge, preset_overlay

ROOT = Path(__file__).resolve().parents[2]
GIT_ID = {"GIT_AUTHOR_NAME": "m3t tests", "GIT_AUTHOR_EMAIL": "tests@m3t.invalid", "GIT_COMMITTER_NAME": "m3t tests",
          "GIT_COMMITTER_EMAIL": "tests@m3t.invalid"}


def effective(variant: Variant, preset: str = "study"):
    """What the variant's stages read: params.yaml, the preset, the variant's settings (as ``-S`` writes them)."""
    return load_params(ROOT / "params.yaml", preset=preset, overrides=unflatten(dict(variant.settings)))


class FakeRunner:
    """Records the variants it was asked to run (by log name) and fails those in ``fail``."""

    def __init__(self, fail: tuple[str, ...] = ()):
        self.calls: list[str] = []
        self.argvs: list[list[str]] = []
        self.envs: list[dict] = []
        self.fail = set(fail)

    def __call__(self, argv, env, log: Path, cwd: Path) -> int:
        assert argv[:4] == ["dvc", "exp", "run", "--temp"] and log.suffix == ".log"
        self.calls.append(log.stem)
        self.argvs.append(list(argv))
        self.envs.append(dict(env))
        return 1 if log.stem in self.fail else 0


def test_plan_has_every_variant_the_claims_need_once_with_settings_that_share_the_common_stages():
    seeds = [0, 1, 2]
    base = load_params(ROOT / "params.yaml", preset="study")
    variants = plan(base, seeds)
    names = [v.name for v in variants]
    assert len(names) == len(set(names)) and names[0] == "shared"
    of = {stage: [effective(v) for v in variants if stage in v.targets]
          for stage in ("train-tokenizers", "evaluate-smlm", "evaluate-slr", "evaluate-sgsa")}
    tokenizers = Counter((p.tokenizer.quantizer, p.tokenizer_train.batch_size, p.tokenizer_train.seed)
                         for p in of["train-tokenizers"])
    shared = ("fsq", 16, base.tokenizer_train.seed)
    assert tokenizers + Counter([shared]) == Counter((q, b, s) for s in seeds for q, b in (
        ("fsq", 16), ("vq", 16), ("vq_ema", 16), ("vq_plain", 16), ("fsq", 128)))
    smlm = Counter((p.smlm_train.translation_objective, p.smlm_train.translation_steps, p.smlm_train.seed)
                   for p in of["evaluate-smlm"])
    assert smlm == Counter((o, st, s) for s in seeds for o, st in ((True, "shared"), (False, "shared"),
                                                                   (True, "added")))
    assert Counter(p.slr_train.seed for p in of["evaluate-slr"]) == Counter(seeds)
    sgsa = Counter((p.sgsa.temporal_adjacency, p.sgsa_train.systems, p.sgsa_train.seed) for p in of["evaluate-sgsa"])
    assert sgsa == Counter([(0, ("sgsa",), s) for s in seeds] + [(1, ("pt", "sgsa"), s) for s in seeds])

    # every model reads the shared tokenizers, and a SGSA variant the SMLM of its seed's smlm-translation variant:
    # the same settings of the stages they share, so DVC's run cache restores them instead of training again
    by_name = {v.name: effective(v) for v in variants}
    for name, p in by_name.items():
        if not name.startswith("tokenizer-"):
            assert (p.tokenizer.quantizer, p.tokenizer_train.batch_size, p.tokenizer_train.seed) == shared, name
        if name.startswith("sgsa-"):
            assert p.smlm_train == by_name[f"smlm-translation-s{p.sgsa_train.seed}"].smlm_train, name
            assert p.smlm == by_name[f"smlm-translation-s{p.sgsa_train.seed}"].smlm


def test_select_by_family_stage_or_name_and_bad_requests_name_what_is_wrong(tmp_path, capsys):
    variants = plan(load_params(ROOT / "params.yaml", preset="tiny"), [0, 1])
    assert [v.name for v in select(variants, ["sgsa"])] == ["sgsa-ninf-s0", "sgsa-ninf-s1", "sgsa-n1-s0",
                                                            "sgsa-n1-s1"]
    assert [v.name for v in select(variants, ["evaluate-slr", "smlm-production-s1"])] == [
        "smlm-production-s1", "slr-s0", "slr-s1"]
    with pytest.raises(StudyError, match="--only evaluate-nothing"):
        select(variants, ["evaluate-nothing"])
    with pytest.raises(StudyError, match="each once"):
        plan(load_params(ROOT / "params.yaml", preset="tiny"), [1, 1])
    with pytest.raises(StudyError, match="KEY=VALUE"):
        parse_settings(["sgsa_evaluate.counter"])
    assert with_settings(variants[:1], parse_settings(["tokenizer.quantizer=vq", "a.b=[1, 2]"]))[0].settings == {
        "tokenizer.quantizer": "fsq", "a.b": [1, 2], "tokenizer_train.batch_size": 16, "tokenizer_train.seed": 0}

    work = tmp_path / "work"
    work.mkdir()
    tree = yaml.safe_load((ROOT / "params.yaml").read_text())
    tree["sgsa"]["temporal_adjacency"] = 0
    (work / "params.yaml").write_text(yaml.safe_dump(tree))
    shutil.copyfile(ROOT / "dvc.yaml", work / "dvc.yaml")
    assert cli_main(["--params", str(work / "params.yaml"), "study", "--preset", "tiny"]) == 1
    assert "sgsa.temporal_adjacency is 0" in capsys.readouterr().err
    other = work / "other.yaml"
    shutil.copyfile(ROOT / "params.yaml", other)
    assert cli_main(["--params", str(other), "study", "--preset", "tiny", "--dry-run"]) == 1
    assert "runs DVC experiments on a workspace's params.yaml" in capsys.readouterr().err


def test_override_values_parse_back_to_the_same_value_in_dvcs_grammar():
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    values = [0, 7, -3, 0.25, 1e-4, True, False, None, "fsq", "vq_ema", "/abs/.cache/fit", "a b", "it's", "true",
              "1.5", "", ["pt", "sgsa"], [], [1, 2.5], "sqlite:////abs/mlflow.db", "x=y", "[x]"]
    for value in values:
        parsed = parser.parse_overrides([f"key={override_value(value)}"])[0].value()
        assert parsed == value and type(parsed) is type(value) or (isinstance(value, tuple)), (value, parsed)


def test_exp_argv_sets_known_keys_appends_new_ones_and_the_variant_wins():
    tree = {"tokenizer": {"quantizer": "fsq", "width": 64}, "fit_corpus": {"cache_dir": ".cache/fit"}}
    base = {"tokenizer.width": 16, "tokenizer.quantizer": "fsq", "slr.trim.min_frames": 8}
    argv = exp_argv(Variant("tok-vq", {"tokenizer.quantizer": "vq"}, ("train-tokenizers",)), base, tree)
    assert argv == ["dvc", "exp", "run", "--temp", "-n", "tok-vq", "-S", "tokenizer.width=16", "-S",
                    "tokenizer.quantizer=vq", "-S", "+slr.trim.min_frames=8", "train-tokenizers"]
    settings = shared_settings(Path("/ws"), tree, "tiny")
    assert settings["fit_corpus.cache_dir"] == str(Path("/ws/.cache/fit").resolve())  # one content-addressed cache
    assert {k: v for k, v in settings.items() if k != "fit_corpus.cache_dir"} == flatten(preset_overlay("tiny"))


def _workspace(tmp_path: Path) -> Path:
    """A DVC workspace of two stages: ``shared`` (param a.x) writes one.txt, ``leaf`` (param a.y) reads it; each
    appends its name to ``calls`` outside the workspace, so the test sees which stage really ran."""
    ws = tmp_path / "ws"
    ws.mkdir()
    calls = tmp_path / "calls"
    (ws / "params.yaml").write_text("a:\n  x: 1\n  y: 2\n")
    step = (f"{sys.executable} -c \"import sys, yaml; p = yaml.safe_load(open('params.yaml'))['a']; "
            f"open(r'{calls}', 'a').write('{{0}}\\n'); {{1}}\"")
    (ws / "dvc.yaml").write_text(yaml.safe_dump({"stages": {
        "shared": {"cmd": step.format("shared", "open('one.txt', 'w').write(str(p['x']))"),
                   "params": ["a.x"], "outs": ["one.txt"]},
        "leaf": {"cmd": step.format("leaf", "sys.exit(3) if p['y'] == 13 else open('two.txt', 'w').write("
                                            "open('one.txt').read() + str(p['y']))"),
                 "deps": ["one.txt"], "params": ["a.y"], "outs": ["two.txt"]}}}))
    env = {**os.environ, **GIT_ID}
    for argv in (["git", "init", "-q"], [sys.executable, "-m", "dvc", "init", "-q"], ["git", "add", "-A"],
                 ["git", "commit", "-qm", "workspace"]):
        subprocess.run(argv, cwd=ws, env=env, check=True)  # noqa: S603 - fixed argv
    return ws


@pytest.mark.slow
def test_variants_run_as_dvc_experiments_sharing_the_stages_they_have_in_common(tmp_path, monkeypatch, capsys):
    for key, value in GIT_ID.items():
        monkeypatch.setenv(key, value)
    ws = _workspace(tmp_path)
    before = (ws / "params.yaml").read_bytes()
    variants = [Variant(f"leaf-{y}", {"a.y": y}, ("leaf",)) for y in (5, 13, 6)]
    summary = run_variants(variants, ws, tmp_path / "logs", runner=run_logged)
    assert summary.ran == ["leaf-5", "leaf-6"] and list(summary.failed) == ["leaf-13"]
    assert str(tmp_path / "logs" / "leaf-13.log") in summary.failed["leaf-13"]
    calls = (tmp_path / "calls").read_text().split()
    assert calls.count("shared") == 1 and calls.count("leaf") == 3  # the run cache restored `shared` twice
    assert (ws / "params.yaml").read_bytes() == before and not (ws / "two.txt").exists()  # the workspace is left alone
    shown = subprocess.run([sys.executable, "-m", "dvc", "exp", "show", "--json"], cwd=ws, capture_output=True,
                           text=True, check=True).stdout  # noqa: S603 - fixed argv
    assert '"leaf-5"' in shown and '"leaf-6"' in shown and '"leaf-13"' not in shown
    assert "2 variants ran, 1 failed" in capsys.readouterr().out

    again = run_variants(variants[:1], ws, tmp_path / "logs", runner=run_logged)  # a rerun: restored, not run
    assert again.ok and (tmp_path / "calls").read_text().split() == calls


def test_the_study_runs_its_variants_in_order_and_a_failure_leaves_the_rest(tmp_path, capsys, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    shutil.copyfile(ROOT / "params.yaml", work / "params.yaml")
    shutil.copyfile(ROOT / "dvc.yaml", work / "dvc.yaml")
    monkeypatch.chdir(work)
    out = tmp_path / "study"
    runner = FakeRunner(fail=("slr-s0",))
    assert study(work / "params.yaml", "tiny", [0, 1], out, claims=False, runner=runner,
                 settings=["sgsa_evaluate.counter=ground_truth"]) == 1
    assert runner.calls == [v.name for v in plan(load_params(work / "params.yaml", preset="tiny"), [0, 1])]
    sgsa = runner.argvs[runner.calls.index("sgsa-n1-s1")]
    assert sgsa[-1] == "evaluate-sgsa" and "sgsa_evaluate.counter=ground_truth" in sgsa
    assert "sgsa_train.seed=1" in sgsa and "smlm_train.seed=1" in sgsa and "synthetic_corpus.num_signs=8" in sgsa
    timings = yaml.safe_load((out / "timings.json").read_text())
    assert [t["variant"] for t in timings["variants"] if t["status"] == "failed"] == ["slr-s0"]
    assert "failed: slr-s0: exit 1; log " in capsys.readouterr().out

    assert cli_main(["--params", str(work / "params.yaml"), "study", "--dry-run", "--preset", "tiny", "--only",
                     "sgsa", "--seeds", "0"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("[")]
    assert [line.split()[0] for line in lines] == ["[1/2]", "[2/2]"]
    assert lines[0].startswith("[1/2] dvc exp run --temp -n sgsa-ninf-s0 ") and lines[1].endswith(" evaluate-sgsa")
    assert not (work / "studies").exists()  # a dry run writes nothing


def test_preset_and_cache_settings_reach_the_stages_as_the_config_reads_them():
    """The ``-S`` arguments of a study variant, applied to params.yaml as DVC applies them, give the params the
    plan meant (the preset's values, the variant's, every cache in the workspace)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    tree = yaml.safe_load((ROOT / "params.yaml").read_text())
    variant = next(v for v in plan(load_params(ROOT / "params.yaml", preset="study"), [3]) if v.name == "slr-s3")
    argv = exp_argv(variant, shared_settings(ROOT, tree, "study"), tree)
    pairs = [argv[i + 1] for i, a in enumerate(argv) if a == "-S"]
    applied = {o.key_or_group: o.value() for o in OverridesParser.create().parse_overrides(pairs)}
    params = load_params(ROOT / "params.yaml", overrides=unflatten(applied))
    assert params == load_params(ROOT / "params.yaml", preset="study", overrides=merge(unflatten(dict(
        variant.settings)), unflatten({k: v for k, v in applied.items() if k.endswith("cache_dir")})))
    assert params.slr_train.seed == 3 and Path(params.fit_corpus.cache_dir).is_absolute()
