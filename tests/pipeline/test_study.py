"""``m3t study`` (cli/study.py, cli/study_plan.py) without training: the plan holds every (variant, seed) the claims read exactly once,
on paths under the study's root; a fake runner (the injectable ``(argv, env, log) -> exit code``) stands in for the
stage subprocesses to check resuming, failures and the command line.
"""
from __future__ import annotations

import os
import shutil
from collections import Counter
from pathlib import Path

import pytest
import yaml

from cli.main import main as cli_main
from cli.study import run, study
from cli.study_plan import StudyError, plan, select, stage_graph
from m3t.config import load_params

ROOT = Path(__file__).resolve().parents[2]
SHARED_ONLY = ("generate-corpus", "fit-corpus", "tokenize", "train-backtranslation", "evaluate-backtranslation",
               "train-backtranslation-skeleton")


class FakeRunner:
    """Records the steps it was asked to run (by log name) and fails those in ``fail``."""

    def __init__(self, fail: tuple[str, ...] = ()):
        self.calls: list[str] = []
        self.envs: list[dict] = []
        self.fail = set(fail)

    def __call__(self, argv, env, log: Path) -> int:
        assert log.name.endswith(".log") and argv[:2] == ("python", "-m")
        self.calls.append(log.stem)
        self.envs.append(dict(env))
        return 1 if log.stem in self.fail else 0


@pytest.fixture
def params(tmp_path) -> Path:
    path = tmp_path / "params.yaml"
    shutil.copyfile(ROOT / "params.yaml", path)
    return path


def _under(path: str | Path, root: Path) -> bool:
    return Path(path).resolve().is_relative_to(root.resolve())


def test_plan_has_every_variant_the_claims_need_once_in_order_under_root(params, tmp_path):
    root = tmp_path / "study"
    seeds = [0, 1, 2]
    steps = plan(params, "tiny", seeds, root)
    names = [s.name for s in steps]
    assert len(names) == len(set(names))
    index = {n: i for i, n in enumerate(names)}
    assert all(index[d] < index[s.name] for s in steps for d in (*s.deps, *s.after)), "a step before what it reads"
    for stage in SHARED_ONLY:  # once, and only in the shared variant
        assert [s.variant for s in steps if s.stage == stage] == ["shared"], stage

    loaded = {s.params: load_params(s.params) for s in steps}  # what each stage will read
    of = {stage: [(s, loaded[s.params]) for s in steps if s.stage == stage]
          for stage in ("train-tokenizers", "evaluate-smlm", "evaluate-slr", "evaluate-sgsa")}
    tokenizers = Counter((p.tokenizer.quantizer, p.tokenizer_train.batch_size, p.tokenizer_train.seed)
                         for _, p in of["train-tokenizers"])
    assert tokenizers == Counter((q, b, s) for s in seeds for q, b in (("fsq", 16), ("vq", 16), ("vq_ema", 16),
                                                                              ("vq_plain", 16), ("fsq", 128)))
    smlm = Counter((p.smlm_train.translation_objective, p.smlm_train.translation_steps, p.smlm_train.seed)
                   for _, p in of["evaluate-smlm"])
    assert smlm == Counter((o, steps, s) for s in seeds for o, steps in ((True, "shared"), (False, "shared"),
                                                                         (True, "added")))
    assert Counter(p.slr_train.seed for _, p in of["evaluate-slr"]) == Counter(seeds)
    sgsa = Counter((p.sgsa.temporal_adjacency, p.sgsa_train.systems, p.sgsa_train.seed) for _, p in of["evaluate-sgsa"])
    assert sgsa == Counter([(0, ("sgsa",), s) for s in seeds] + [(1, ("pt", "sgsa"), s) for s in seeds])
    for stage in ("train-smlm", "generate-smlm", "train-slr", "train-sgsa"):  # each evaluated variant is trained
        assert Counter(s.variant for s in steps if s.stage == stage) == Counter(
            s.variant for s in steps if s.stage == stage.replace("train", "evaluate").replace("generate", "evaluate"))

    inf = [index[s.name] for s, p in of["evaluate-sgsa"] if p.sgsa.temporal_adjacency == 0]
    finite = [index[s.name] for s in steps if s.stage.endswith("-sgsa") and not s.variant.startswith("sgsa-ninf")]
    assert max(inf) < min(finite), "every N = inf run must come before the default-adjacency runs"

    for path, p in loaded.items():
        assert _under(path, root / "params")
        folders = (p.data.shards_root, p.data.tokens_root, p.data.generated_dir, p.data.metrics_dir, p.data.models_dir,
                   p.corpora["synthetic"].root, p.experiment.dashboard_dir)
        assert all(_under(f, root) for f in folders), (path, folders)
    assert all(_under(link, root) and _under(target, root) for s in steps for link, target in s.links)
    assert sorted(p.name for p in root.rglob("*")) == sorted({"params", *(p.name for p in loaded)})


def test_a_finished_study_reruns_nothing_and_a_changed_variant_only_its_steps(params, tmp_path, capsys):
    root = tmp_path / "study"
    steps = plan(params, "tiny", [0, 1], root)
    first = FakeRunner()
    summary = run(steps, root, first, {"MLFLOW_TRACKING_URI": "sqlite:////abs/mlflow.db"})
    assert summary.ok and first.calls == [s.name for s in steps] and summary.ran == first.calls
    assert first.envs[0]["MLFLOW_TRACKING_URI"] == "sqlite:////abs/mlflow.db"
    assert f"[1/{len(steps)}] shared generate-corpus ... ok (" in capsys.readouterr().out
    link = root / "variants" / "slr-s0" / "models" / "tokenizers"
    assert link.is_symlink() and os.readlink(link) == os.path.join("..", "..", "..", "models", "tokenizers")
    generated = root / "variants" / "sgsa-n1-s1" / "generated"
    assert generated.resolve() == (root / "variants" / "smlm-translation-s1" / "generated").resolve()
    timings = yaml.safe_load((root / "timings.json").read_text())
    assert [t["status"] for t in timings["steps"]] == ["ok"] * len(steps)

    again = FakeRunner()
    summary = run(plan(params, "tiny", [0, 1], root), root, again)
    assert again.calls == [] and set(summary.skipped.values()) == {"done, skipped"}
    assert "done, skipped" in capsys.readouterr().out

    changed = root / "params" / "slr-s1.yaml"
    tree = yaml.safe_load(changed.read_text())
    tree["slr_train"]["seed"] = 7
    changed.write_text(yaml.safe_dump(tree, sort_keys=False))
    third = FakeRunner()
    run(steps, root, third)
    assert third.calls == ["slr-s1.train-slr", "slr-s1.evaluate-slr"]

    # a new seed: its steps; the default-adjacency SGSA evaluations again, so that they stay the newest; and slr-s1,
    # whose params file planning wrote back
    fourth = FakeRunner()
    run(plan(params, "tiny", [0, 1, 2], root), root, fourth)
    assert {c for c in fourth.calls if not c.split(".")[0].endswith("-s2")} == {
        "sgsa-n1-s0.evaluate-sgsa", "sgsa-n1-s1.evaluate-sgsa", "slr-s1.train-slr", "slr-s1.evaluate-slr"}
    assert "sgsa-n1-s2.evaluate-sgsa" in fourth.calls and fourth.calls[-1].startswith("sgsa-n1-")


def test_a_failed_step_skips_its_dependents_and_the_rest_still_runs(params, tmp_path, capsys):
    root = tmp_path / "study"
    judge = "shared.train-backtranslation-skeleton"
    runner = FakeRunner(fail=(judge,))
    code = study(params, "tiny", [0, 1], root, claims=False, runner=runner)
    assert code == 1
    assert runner.envs[0]["MLFLOW_TRACKING_URI"].startswith("sqlite:////")  # absolute: any cwd, one store
    steps = plan(params, "tiny", [0, 1], root)
    timings = {t["step"]: t for t in yaml.safe_load((root / "timings.json").read_text())["steps"]}
    evaluations = [s.name for s in steps if s.stage == "evaluate-sgsa"]
    assert all(timings[e]["status"] == "skipped" and judge in timings[e]["detail"] for e in evaluations)
    assert timings[judge]["status"] == "failed" and str(root / "logs" / f"{judge}.log") in timings[judge]["detail"]
    independent = [s.name for s in steps if s.name not in (judge, *evaluations)]
    assert [c for c in runner.calls if c != judge] == independent
    out = capsys.readouterr().out
    assert f"{judge}: exit 1; log " in out and "failed: " in out and "skipped: " + judge in out

    fixed = FakeRunner()
    assert study(params, "tiny", [0, 1], root, claims=False, runner=fixed) == 0
    assert fixed.calls == [judge, *evaluations]


def test_dry_run_prints_the_plan_and_writes_only_the_params_files(params, tmp_path, capsys, monkeypatch):
    """``--dry-run`` writes the variants' params files (the plan is made of them) and nothing else."""
    monkeypatch.chdir(tmp_path)
    root = tmp_path / "study"
    assert cli_main(["--params", str(params), "study", "--dry-run", "--preset", "tiny", "--root", str(root)]) == 0
    out = capsys.readouterr().out
    lines = [line for line in out.splitlines() if line.startswith("[")]
    assert len(lines) == len(plan(params, "tiny", [0, 1, 2, 3, 4], root))  # 5 seeds by default
    assert lines[0].startswith(f"[1/{len(lines)}] shared generate-corpus: python -m m3t.stages.generate_corpus")
    assert "experiment.enabled is false" in out
    written = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()}
    assert written - {"params.yaml"} == {f"study/params/{p.name}" for p in (root / "params").iterdir()}

    assert cli_main(["--params", str(params), "study", "--dry-run", "--preset", "tiny", "--root", str(root),
                     "--only", "evaluate-slr", "sgsa-n1-s0"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("[")]
    assert [line.split(":")[0] for line in lines] == [
        "[1/7] slr-s0 evaluate-slr", "[2/7] slr-s1 evaluate-slr", "[3/7] slr-s2 evaluate-slr",
        "[4/7] slr-s3 evaluate-slr", "[5/7] slr-s4 evaluate-slr",
        "[6/7] sgsa-n1-s0 train-sgsa", "[7/7] sgsa-n1-s0 evaluate-sgsa"]


def test_bad_requests_are_refused_with_the_key_or_name(params, tmp_path, capsys):
    root = tmp_path / "study"
    with pytest.raises(StudyError, match="--only evaluate-nothing"):
        select(plan(params, "tiny", [0], root), ["evaluate-nothing"])
    with pytest.raises(StudyError, match="each once"):
        plan(params, "tiny", [1, 1], root)
    tree = yaml.safe_load(params.read_text())
    tree["sgsa"]["temporal_adjacency"] = 0
    params.write_text(yaml.safe_dump(tree))
    assert cli_main(["--params", str(params), "study", "--preset", "tiny", "--root", str(root)]) == 1
    assert "sgsa.temporal_adjacency is 0" in capsys.readouterr().err


def test_on_real_corpora_the_study_fits_them_and_generates_nothing(params, tmp_path):
    # the same command on real data: train_corpora names downloaded corpora (their roots stay where they are)
    raw = yaml.safe_load(params.read_text(encoding="utf-8"))
    raw["data"]["train_corpora"] = ["phoenix14t"]
    raw["corpora"]["phoenix14t"] = {"root": str(tmp_path / "raw" / "phoenix14t")}
    raw["slr"]["corpus"] = "phoenix14t"
    params.write_text(yaml.safe_dump(raw), encoding="utf-8")
    steps = plan(params, "study", [0, 1, 2], tmp_path / "study")
    shared = [s.stage for s in steps if s.variant == "shared"]
    assert "generate-corpus" not in shared and "fit-corpus-phoenix14t" in shared
    fit = next(s for s in steps if s.stage == "fit-corpus-phoenix14t")
    assert fit.argv[-2:] == ("--corpus", "phoenix14t")
    written = load_params(fit.params)
    assert written.corpora["phoenix14t"].root == str(tmp_path / "raw" / "phoenix14t")  # the data is read in place
    assert _under(written.data.shards_root, tmp_path / "study") and written.experiment.experiment == "m3t-study"


def test_stage_graph_reads_outputs_from_dvc_yaml(tmp_path):
    """A stage reads another when a dep equals, lies inside, or holds one of the other's outs / metrics."""
    path = tmp_path / "dvc.yaml"
    path.write_text(yaml.safe_dump({"stages": {
        "make": {"cmd": "python -m m3t.stages.make", "outs": ["data/corpus"], "metrics": [{"data/m.json": {}}]},
        "fit": {"cmd": "python -m m3t.stages.fit --corpus x", "deps": ["data/corpus/x", "m3t/fit.py"],
                "outs": ["data/shards/x/train.parquet"]},
        "train": {"cmd": "python -m m3t.stages.train", "deps": ["data/shards", "data/m.json"]},
        "other": {"cmd": "python -m m3t.stages.other", "deps": ["data/corpus2"]}}}, sort_keys=False))
    graph = stage_graph(path)
    assert graph.reads == {"make": (), "fit": ("make",), "train": ("make", "fit"), "other": ()}
    assert graph.cmd["fit"] == ("python", "-m", "m3t.stages.fit", "--corpus", "x")


def test_each_step_reads_what_dvc_yaml_says_from_the_variant_that_makes_it(params, tmp_path):
    steps = {s.name: s for s in plan(params, "tiny", [0], tmp_path / "study")}
    graph = stage_graph()
    assert set(graph.reads["evaluate-smlm"]) >= {"generate-smlm", "train-backtranslation"}
    evaluate = steps["smlm-translation-s0.evaluate-smlm"]
    assert {"smlm-translation-s0.generate-smlm", "shared.train-backtranslation"} <= set(evaluate.deps)
    assert not [d for d in evaluate.deps if d.startswith("smlm-production")]
    # the default-adjacency SGSA judges the same seed's SMLM motion, which it links; N = inf reads no SMLM
    assert "smlm-translation-s0.generate-smlm" in steps["sgsa-n1-s0.evaluate-sgsa"].deps
    assert not [d for d in steps["sgsa-ninf-s0.evaluate-sgsa"].deps if "smlm" in d]
    for step in steps.values():  # every step runs its dvc.yaml command with its variant's params
        if not step.stage.startswith("fit-corpus"):
            assert step.argv == (*graph.cmd[step.stage], "--params", str(step.params))
