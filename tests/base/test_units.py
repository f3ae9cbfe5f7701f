"""Small shared pieces of the library on hand-worked values: the vocabularies of the text models, the sinusoidal
positions, the LR schedules and the trainers' process split. Written to pin behaviours that mutation testing found
unchecked (they were exercised only inside model trainings, which pass with many wrong values)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from m3t.optimizer import PlateauSchedule, lr_factor, warmup_cosine
from m3t.positional_encoding import sinusoid_table
from m3t.training_jobs import worker_split
from m3t.vocabulary import BLANK, UNK, Vocabulary, gloss_vocabulary, text_vocabulary


def test_a_vocabulary_orders_specials_then_tokens_by_frequency_then_alphabetically():
    vocab = text_vocabulary([["b", "a", "c"], ["a", "b"], ["a", "d"]])
    assert vocab.itos == ["<pad>", "<unk>", "<bos>", "<eos>", "a", "b", "c", "d"]  # a 3x, b 2x, then c d (ties)
    assert len(vocab) == 8 and vocab.stoi["a"] == 4
    assert vocab.encode(["a", "zzz", "d"]) == [4, 1, 7]  # an unknown word is <unk>
    assert vocab.decode([2, 4, 5, 3, 0]) == ["a", "b"]  # specials are dropped
    rare = text_vocabulary([["b", "a", "c"], ["a", "b"], ["a", "d"]], min_frequency=2)
    assert rare.itos[4:] == ["a", "b"]  # seen once: left out
    assert Vocabulary.from_dict(vocab.to_dict()).itos == vocab.itos
    assert vocab.to_dict() == {"specials": ["<pad>", "<unk>", "<bos>", "<eos>"], "tokens": ["a", "b", "c", "d"]}
    glosses = gloss_vocabulary([["HOUSE", "GO"], ["GO"]])
    assert glosses.itos == [BLANK, UNK, "GO", "HOUSE"] and glosses.stoi[BLANK] == 0
    with pytest.raises(ValueError, match="duplicate"):
        Vocabulary(["a", "a"], ["<pad>"])
    assert Vocabulary(["<pad>", "x"], ["<pad>"]).itos == ["<pad>", "x"]  # a special among the tokens counts once
    assert Vocabulary(["x"], ["<pad>"]).encode(["y"]) == [0]  # no <unk>: id 0


def test_sinusoid_positions_by_hand():
    table = sinusoid_table(3, 4)  # rates 1 and 10000 ** (-2 / 4) = 0.01
    expected = [[math.sin(p), math.cos(p), math.sin(0.01 * p), math.cos(0.01 * p)] for p in range(3)]
    assert table.shape == (3, 4)
    np.testing.assert_allclose(table.numpy(), expected, atol=1e-6)  # float32 rounding
    odd = sinusoid_table(2, 5)  # an odd width: the last channel is a sine
    assert odd.shape == (2, 5) and float(odd[1, 4]) == pytest.approx(math.sin(10000.0 ** (-4 / 5)), abs=1e-6)


def test_the_lr_warms_up_linearly_then_falls_on_a_cosine_to_the_floor():
    assert [lr_factor(s, 4, 12, 0.1) for s in range(4)] == pytest.approx([0.25, 0.5, 0.75, 1.0])
    assert lr_factor(4, 4, 12, 0.1) == pytest.approx(1.0)  # the cosine starts at 1
    assert lr_factor(8, 4, 12, 0.1) == pytest.approx(0.1 + 0.9 * 0.5)  # half-way: the mean of 1 and the floor
    assert lr_factor(12, 4, 12, 0.1) == pytest.approx(0.1) and lr_factor(50, 4, 12, 0.1) == pytest.approx(0.1)
    assert lr_factor(0, 0, 0, 0.5) == pytest.approx(1.0)  # no warm-up, no steps: no division by zero
    model = torch.nn.Linear(1, 1)
    optim = torch.optim.SGD(model.parameters(), lr=0.5)
    schedule = warmup_cosine(optim, epochs=3, steps_per_epoch=2, warmup=1, warmup_unit="epochs", min_lr=0.05)
    lrs = []
    for _ in range(6):
        lrs.append(optim.param_groups[0]["lr"])
        optim.step()
        schedule.step()
    # 2 warm-up steps (1 epoch x 2), then cosine over 4 steps from 0.5 to 0.05 (floor 0.1 of the LR)
    cosine = [0.5 * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * k / 4))) for k in range(4)]
    assert lrs == pytest.approx([0.25, 0.5, *cosine])
    optim = torch.optim.SGD(model.parameters(), lr=0.5)
    steps = warmup_cosine(optim, epochs=3, steps_per_epoch=2, warmup=1, warmup_unit="steps", min_lr=0.05)
    assert optim.param_groups[0]["lr"] == pytest.approx(0.5)  # one warm-up step: full LR at once
    assert steps.lr_lambdas[0](5) == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 4 / 5)))
    with pytest.raises(ValueError, match="warmup_unit"):
        warmup_cosine(optim, 3, 2, 1, "batches", 0.05)


def test_the_plateau_schedule_cuts_the_lr_after_patience_validations_without_improvement():
    model = torch.nn.Linear(1, 1)
    optim = torch.optim.SGD(model.parameters(), lr=1.0)
    schedule = PlateauSchedule(optim, "max", factor=0.5, patience=1, min_lr=0.2)
    schedule.step()  # an optimiser step changes nothing
    for score in (1.0, 2.0, 2.0):  # improving, then one validation without: patience 1 not yet exceeded
        schedule.observe(score)
    assert optim.param_groups[0]["lr"] == 1.0
    schedule.observe(1.5)  # a second one: cut
    assert optim.param_groups[0]["lr"] == 0.5
    for _ in range(6):
        schedule.observe(0.0)
    assert optim.param_groups[0]["lr"] == pytest.approx(0.2)  # never below min_lr
    again = PlateauSchedule(torch.optim.SGD(model.parameters(), lr=1.0), "max", 0.5, 1, 0.2)
    again.load_state_dict(schedule.state_dict())
    assert again.state_dict()["best"] == 2.0
    lower = PlateauSchedule(torch.optim.SGD(model.parameters(), lr=1.0), "min", 0.5, 0, 0.0)
    lower.observe(1.0)
    lower.observe(2.0)  # worse for "min": cut at once with patience 0
    assert lower.plateau.optimizer.param_groups[0]["lr"] == 0.5


def test_worker_split_shares_the_threads_among_at_most_one_process_per_job(monkeypatch):
    monkeypatch.setattr(torch, "get_num_threads", lambda: 8)
    assert worker_split(4, 2, "cpu") == (2, 4)  # two jobs: two processes of 8 / 2 threads
    assert worker_split(3, 5, "cpu") == (3, 2)  # 8 // 3
    assert worker_split(1, 5, "cpu") == (1, 0) and worker_split(4, 1, "cpu") == (1, 0)
    assert worker_split(2, 2, "cpu", world_size=2) == (1, 0)  # DDP: one process per rank already
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    assert worker_split(2, 2, "cpu") == (2, 1)  # at least one thread each


def test_experiment_links_names_and_logged_sections_by_hand(monkeypatch):
    from m3t.experiment import (
        ExperimentConfig,
        run_name,
        saved_view_tag,
        section_params,
        to_dict,
        tracking_uri,
        ui_link,
    )
    from m3t.slr.config import TrimConfig

    assert ui_link("http://h:5000", "7") == ("http://h:5000/#/experiments/7/runs?workflowType=machine_learning"
                                             "&viewStateShareKey=m3t-runs")
    assert ui_link("http://h", "7", view=None) == "http://h/#/experiments/7/runs?workflowType=machine_learning"
    assert ui_link("http://h", "7", run_id="abc") == "http://h/#/experiments/7/runs/abc?workflowType=machine_learning"
    assert run_name("train-slr") == "train-slr" and run_name("train-slr", "full") == "train-slr · full"
    assert run_name("train-slr", "full", {"scheduled": "true"}) == "train-slr · full · scheduled"
    assert run_name("train-slr", None, {"scheduled": "false"}) == "train-slr"
    key, value = saved_view_tag("v1", "my view", ("tags.`stage`",), 123)
    assert key == "mlflow.sharedViewState.v1"
    assert json.loads(value) == {"name": "my view", "createdAt": 123, "updatedAt": 123,
                                 "state": json.dumps({"selectedColumns": ["tags.`stage`"]})}
    assert to_dict({"a": (1, TrimConfig(margin=3))})["a"][1]["margin"] == 3
    assert to_dict((1, 2)) == [1, 2]
    params = section_params(trim=TrimConfig(margin=3))
    assert params["trim.margin"] == 3 and params["trim.reference"] == "clip_rest" and len(params) == 6
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    cfg = ExperimentConfig(tracking_uri="sqlite:///store.db")
    assert tracking_uri(cfg, Path("/r")) == "sqlite:////r/store.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "sqlite:////elsewhere.db")
    assert tracking_uri(cfg, Path("/r")) == "sqlite:////elsewhere.db"  # the environment wins (dvc exp --temp)


def test_a_stage_parses_its_options_loads_the_preset_runs_and_prints_json(capsys):
    from m3t.config import load_params
    from m3t.stages import stage_main

    root = Path(__file__).resolve().parents[2]
    seen = {}

    def run(params, args):
        seen.update(params=params, args=args)
        return {"b": 2, "a": 1}

    argv = ["--params", str(root / "params.yaml"), "--preset", "tiny", "--extra", "7"]
    out = stage_main("The stage.\nMore text.", run, argv, options=lambda p: p.add_argument("--extra", type=int))
    assert out == {"b": 2, "a": 1} and seen["args"].extra == 7
    assert seen["params"] == load_params(root / "params.yaml", preset="tiny")
    assert capsys.readouterr().out == '{\n  "a": 1,\n  "b": 2\n}\n'  # sorted keys, indented
    stage_main("The stage.", run, argv[:4], show=lambda result: result["a"])
    assert capsys.readouterr().out == "1\n"


def test_without_torchrun_the_context_is_one_process(monkeypatch):
    from m3t.runtime import distributed_context

    for world in (None, "1"):
        if world is None:
            monkeypatch.delenv("WORLD_SIZE", raising=False)
        else:
            monkeypatch.setenv("WORLD_SIZE", world)
        ctx = distributed_context("cpu")
        assert (ctx.rank, ctx.world_size, ctx.device.type, ctx.is_main) == (0, 1, "cpu", True)


def test_the_reproducible_modes_shell_lines_quote_values_with_spaces_or_commas():
    from m3t.arithmetic import ENV, PINNED, describe

    lines = describe().splitlines()
    assert lines[0] == f"export {ENV}=1" and len(lines) == 1 + len(PINNED)
    assert "export MKL_CBWR=COMPATIBLE" in lines
    assert f"export NPY_DISABLE_CPU_FEATURES={PINNED['NPY_DISABLE_CPU_FEATURES']!r}" in lines  # spaces: quoted


# --------------------------------------------------------------------------------------------- runtime
def test_device_choice_auto_named_and_a_missing_cuda_named_clearly(monkeypatch):
    from m3t.runtime import choose_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert choose_device() == torch.device("cpu") and choose_device("auto") == torch.device("cpu")
    assert choose_device("cpu") == torch.device("cpu") and choose_device("meta") == torch.device("meta")
    for name in ("cuda", "cuda:1"):
        with pytest.raises(RuntimeError) as err:
            choose_device(name)
        assert str(err.value) == f"device {name!r} requested but no CUDA device is visible; use 'cpu' or 'auto'"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert choose_device("auto") == torch.device("cuda") and choose_device("cuda:1") == torch.device("cuda", 1)


def test_autocast_is_bf16_only_when_asked_and_refuses_unknown_precisions():
    from m3t.runtime import autocast

    cpu = torch.device("cpu")
    on, off = autocast(cpu, "bf16"), autocast(cpu, "fp32")
    assert (on.device, on.fast_dtype, on._enabled) == ("cpu", torch.bfloat16, True)
    assert off._enabled is False
    with autocast(cpu, "bf16"):
        assert torch.nn.functional.linear(torch.ones(1, 2), torch.ones(3, 2)).dtype == torch.bfloat16
    with autocast(cpu, "fp32"):
        assert torch.nn.functional.linear(torch.ones(1, 2), torch.ones(3, 2)).dtype == torch.float32
    with pytest.raises(ValueError) as err:
        autocast(cpu, "fp16")
    assert str(err.value) == "precision 'fp16' unknown; allowed: fp32, bf16"


def test_a_distributed_context_defaults_to_the_main_cpu_process():
    from m3t.runtime import DistributedContext

    ctx = DistributedContext()
    assert (ctx.rank, ctx.world_size, ctx.device, ctx.is_main) == (0, 1, torch.device("cpu"), True)
    other = DistributedContext(2, 4, torch.device("meta"))
    assert (other.rank, other.world_size, other.device, other.is_main) == (2, 4, torch.device("meta"), False)


def test_under_torchrun_the_context_joins_the_group_with_its_rank(monkeypatch):
    """WORLD_SIZE > 1: the process group is joined once (gloo on CPU, NCCL on CUDA with the LOCAL_RANK device)
    and the context carries the group's rank and size (torch.distributed faked: no real group)."""
    import torch.distributed as dist

    from m3t.runtime import distributed_context

    inits = []
    state = {"initialized": False}
    monkeypatch.setattr(dist, "is_initialized", lambda: state["initialized"])
    monkeypatch.setattr(dist, "init_process_group", lambda backend: inits.append(backend))
    monkeypatch.setattr(dist, "get_rank", lambda: 3)
    monkeypatch.setattr(dist, "get_world_size", lambda: 4)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setenv("WORLD_SIZE", "4")
    ctx = distributed_context("cpu")
    assert (ctx.rank, ctx.world_size, ctx.device, ctx.is_main, inits) == (3, 4, torch.device("cpu"), False, ["gloo"])
    state["initialized"] = True
    distributed_context("cpu")
    assert inits == ["gloo"]  # an initialised group is not joined again
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    devices = []
    monkeypatch.setattr(torch.cuda, "set_device", lambda device: devices.append(device))
    monkeypatch.setenv("LOCAL_RANK", "1")
    state["initialized"] = False
    ctx = distributed_context("auto")
    assert ctx.device == torch.device("cuda", 1) and devices == [torch.device("cuda", 1)] and inits[-1] == "nccl"
    monkeypatch.delenv("LOCAL_RANK")
    assert distributed_context("cuda").device == torch.device("cuda", 0)
    monkeypatch.delenv("WORLD_SIZE")
    single = distributed_context("auto")  # one process: the device is still the one chosen
    assert (single.rank, single.world_size, single.device) == (0, 1, torch.device("cuda"))


def test_use_threads_sets_only_a_different_nonzero_count(monkeypatch):
    from m3t.runtime import use_threads

    calls = []
    monkeypatch.setattr(torch, "get_num_threads", lambda: 3)
    monkeypatch.setattr(torch, "set_num_threads", lambda n: calls.append(n))
    use_threads(0)
    use_threads(3)
    assert calls == []
    use_threads(2)
    assert calls == [2]


def test_a_worker_sets_its_threads_and_watches_its_parent(monkeypatch):
    """The initialiser starts a daemon watcher thread on the parent's pid; the watcher polls each second while
    the parent is alive and exits the process (status 1) once it is gone."""
    import os
    import threading
    import time

    from m3t import runtime

    started, threads = [], []

    class FakeThread:
        def __init__(self, target, args, daemon, name):
            started.append((target, args, daemon, name))

        def start(self):
            started.append("started")

    monkeypatch.setattr(threading, "Thread", FakeThread)
    monkeypatch.setattr(runtime, "use_threads", lambda n: threads.append(n))
    runtime._start_worker(1234, 5)
    assert threads == [5]
    assert started == [(runtime._exit_with_parent, (1234,), True, "exit-with-parent"), "started"]

    parents, sleeps = iter([1234, 1234, 1]), []
    monkeypatch.setattr(os, "getppid", lambda: next(parents))
    monkeypatch.setattr(time, "sleep", lambda s: sleeps.append(s))

    def fake_exit(code):
        raise SystemExit(code)

    monkeypatch.setattr(os, "_exit", fake_exit)
    with pytest.raises(SystemExit) as err:
        runtime._exit_with_parent(1234)
    assert err.value.code == 1 and sleeps == [1.0, 1.0]


def test_the_worker_pool_spawns_with_the_initialiser(monkeypatch):
    import os

    from m3t.runtime import _start_worker, spawn_pool

    pool = spawn_pool(2, 3)
    try:
        assert pool._max_workers == 2 and pool._mp_context.get_start_method() == "spawn"
        assert pool._initializer is _start_worker and pool._initargs == (os.getpid(), 3)
    finally:
        pool.shutdown()


def test_jit_caches_on_disk_where_it_can_and_compiles_per_process_otherwise(monkeypatch):
    import numba

    from m3t.runtime import jit

    calls = []

    def fake_njit(**options):
        calls.append(options)
        if options["cache"]:
            raise RuntimeError("no cache directory")
        return lambda func: ("compiled", func)

    monkeypatch.setattr(numba, "njit", fake_njit)
    assert jit(fastmath=True)(len) == ("compiled", len)
    assert calls == [{"cache": True, "error_model": "numpy", "fastmath": True},
                     {"cache": False, "error_model": "numpy", "fastmath": True}]
    monkeypatch.setattr(numba, "njit", lambda **options: calls.append(options) or (lambda func: ("cached", func)))
    assert jit()(len) == ("cached", len) and calls[-1] == {"cache": True, "error_model": "numpy"}


# ---------------------------------------------------------------------------------------------- digests
def test_files_are_hashed_in_blocks_of_block_bytes(monkeypatch, tmp_path):
    """A file is read BLOCK bytes at a time (never whole): every read asks for BLOCK, the hash is the file's."""
    import builtins
    import hashlib

    from m3t import digest

    monkeypatch.setattr(digest, "BLOCK", 4)
    sizes = []
    real_open = builtins.open

    class Recording:
        def __init__(self, fh):
            self.fh = fh

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.fh.close()

        def read(self, size=-1):
            sizes.append(size)
            return self.fh.read(size)

    monkeypatch.setattr(builtins, "open", lambda path, mode="r", *a, **k: Recording(real_open(path, mode, *a, **k)))
    path = tmp_path / "f.bin"
    path.write_bytes(b"0123456789")
    assert digest.file_digest(path) == hashlib.sha256(b"0123456789").hexdigest()
    assert sizes == [4, 4, 4, 4]  # 4 + 4 + 2 bytes, then the empty read that ends it
    assert digest.file_digest(path, 8) == hashlib.sha256(b"0123456789").hexdigest()[:8]
    assert digest.file_digest_bytes(path) == hashlib.sha256(b"0123456789").digest()


def test_digest_block_is_one_mebibyte_and_json_digests_sort_keys():
    import hashlib

    from m3t.digest import (
        BLOCK,
        bytes_digest,
        canonical_json,
        chunks_digest,
        json_digest,
    )

    assert BLOCK == 1048576
    assert canonical_json({"b": 1, "a": Path("x")}) == b'{"a": "x", "b": 1}'
    assert canonical_json({"a": Path("x")}, default=lambda v: 7) == b'{"a": 7}'
    assert json_digest({"b": 1, "a": 2}) == hashlib.sha256(b'{"a": 2, "b": 1}').hexdigest()
    assert json_digest({"a": Path("x")}, 10, default=lambda v: 7) == hashlib.sha256(b'{"a": 7}').hexdigest()[:10]
    assert chunks_digest([b"ab", b"c"], 5) == bytes_digest(b"abc", 5) == hashlib.sha256(b"abc").hexdigest()[:5]
    assert len(chunks_digest([])) == 64 and len(bytes_digest(b"")) == 64


# ------------------------------------------------------------------------------------------- experiment
class _FakeMlflow:
    """The mlflow calls a :class:`m3t.experiment.Run` makes, recorded."""

    def __init__(self):
        self.calls = []

    def active_run(self):
        from types import SimpleNamespace

        return SimpleNamespace(info=SimpleNamespace(run_id="r-1"))

    def __getattr__(self, name):
        return lambda *args, **kwargs: self.calls.append((name, args, kwargs))


def test_a_run_logs_params_cut_metrics_finite_and_existing_artifacts(tmp_path):
    from m3t.experiment import Run

    mlflow = _FakeMlflow()
    run = Run(mlflow)
    assert run.run_id == "r-1"
    run.log_params({"a": "x" * 7000, "b": 3, "c": (1, 2)})
    run.log_metrics({"m": 1, "nan": float("nan"), "none": None, "inf": float("inf")}, step=4)
    run.log_metrics({"n": 2.5})
    present = tmp_path / "here.txt"
    present.write_text("x")
    run.log_artifact(present, "folder")
    run.log_artifact(present)
    run.log_artifact(tmp_path / "absent.txt", "folder")
    run.set_tags({"t": "v"})
    assert mlflow.calls == [
        ("log_params", ({"a": "x" * 6000, "b": "3", "c": "(1, 2)"},), {}),
        ("log_metrics", ({"m": 1.0, "inf": float("inf")},), {"step": 4}),
        ("log_metrics", ({"n": 2.5},), {"step": None}),
        ("log_artifact", (str(present),), {"artifact_path": "folder"}),
        ("log_artifact", (str(present),), {"artifact_path": None}),
        ("set_tags", ({"t": "v"},), {})]
    assert type(mlflow.calls[1][1][0]["m"]) is float


def test_a_run_logs_a_csv_table_by_columns_keeping_newlines_inside_cells(tmp_path):
    """The CSV read back as written (``newline=""``: a quoted cell keeps its ``\\r\\n`` / ``\\n``), one list per
    column in header order, and the file itself as an artifact; an absent file logs nothing, a header-only
    file an empty table."""
    from m3t.experiment import Run

    mlflow = _FakeMlflow()
    table = tmp_path / "t.csv"
    table.write_bytes(b'id,text\r\na,"line one\r\nline two"\r\nb,"x\ny"\r\n')
    Run(mlflow).log_table(table, "tables/t.json")
    assert mlflow.calls == [
        ("log_table", (), {"data": {"id": ["a", "b"], "text": ["line one\r\nline two", "x\ny"]},
                           "artifact_file": "tables/t.json"}),
        ("log_artifact", (str(table),), {})]
    mlflow.calls.clear()
    Run(mlflow).log_table(tmp_path / "absent.csv", "x.json")
    assert mlflow.calls == []
    (tmp_path / "empty.csv").write_text("id,text\n")
    Run(mlflow).log_table(tmp_path / "empty.csv", "e.json")
    assert mlflow.calls[0] == ("log_table", (), {"data": {}, "artifact_file": "e.json"})


def test_a_disabled_run_calls_nothing(tmp_path):
    from m3t.experiment import Run

    run = Run(None)
    (tmp_path / "t.csv").write_text("a\n1\n")
    run.log_params({"a": 1})
    run.log_metrics({"a": 1.0})
    run.log_artifact(tmp_path / "t.csv")
    run.log_table(tmp_path / "t.csv", "t.json")
    run.set_tags({"a": "b"})
    assert run.run_id is None


def test_experiment_tags_name_the_kind_and_the_saved_runs_view(monkeypatch):
    import time

    from m3t.experiment import RUNS_VIEW_COLUMNS, experiment_tags

    monkeypatch.setattr(time, "time", lambda: 12.3456)
    tags = experiment_tags()
    assert list(tags) == ["mlflow.experimentKind", "mlflow.sharedViewState.m3t-runs"]
    assert tags["mlflow.experimentKind"] == "custom_model_development"
    assert json.loads(tags["mlflow.sharedViewState.m3t-runs"]) == {
        "name": "m3t runs: stage, variant, axes", "createdAt": 12345, "updatedAt": 12345,
        "state": json.dumps({"selectedColumns": list(RUNS_VIEW_COLUMNS)})}
    assert RUNS_VIEW_COLUMNS[0] == "tags.`stage`" and RUNS_VIEW_COLUMNS[-1] == "attributes.`Duration`"


def test_telemetry_is_switched_off_without_overriding_the_users_choice(monkeypatch):
    import os

    from m3t.experiment import TELEMETRY_OFF, disable_telemetry

    assert TELEMETRY_OFF == {"DO_NOT_TRACK": "true", "MLFLOW_DISABLE_TELEMETRY": "true",
                             "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DVC_NO_ANALYTICS": "1"}
    for key in TELEMETRY_OFF:
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("DO_NOT_TRACK", "mine")
    disable_telemetry()
    assert os.environ["DO_NOT_TRACK"] == "mine" and os.environ["DVC_NO_ANALYTICS"] == "1"
    assert os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] == "false"


def test_extra_tags_nest_and_end_with_their_block():
    from m3t.experiment import _EXTRA_TAGS, extra_tags

    assert _EXTRA_TAGS.get() == {}
    with extra_tags({"a": "1", "b": "2"}):
        with extra_tags({"b": "3"}):
            assert _EXTRA_TAGS.get() == {"a": "1", "b": "3"}
        assert _EXTRA_TAGS.get() == {"a": "1", "b": "2"}
    assert _EXTRA_TAGS.get() == {}


def test_absolute_uris_by_hand(tmp_path):
    from m3t.experiment import absolute_uri

    assert absolute_uri("sqlite:///sub/x.db", tmp_path) == "sqlite:///" + str((tmp_path / "sub" / "x.db").resolve())
    assert absolute_uri("runs", tmp_path) == (tmp_path / "runs").resolve().as_uri()
    assert absolute_uri("file:///abs", tmp_path) == "file:///abs"
    assert absolute_uri("sqlite:////abs.db", tmp_path) == "sqlite:////abs.db"


# ----------------------------------------------------------------------------------------------- config
def test_config_errors_name_the_key_and_the_fix_exactly(tmp_path):
    """Each refusal of the params loader, word for word: unknown sections and corpora, corpus entries of the
    wrong shape, a ``shards_dir`` key, a training corpus not listed, a section without a class, an unknown
    preset."""
    from m3t.config import (
        SECTIONS,
        ConfigError,
        _check_corpora,
        params_from_dict,
        preset_overlay,
        section_class,
    )
    from m3t.corpora.base import CORPORA

    def error(call, *args):
        with pytest.raises(ConfigError) as err:
            call(*args)
        return str(err.value)

    known = ", ".join(CORPORA)
    assert error(_check_corpora, {"corpora": ["synthetic"]}) == "corpora: expected a mapping of corpus names, got list"
    assert error(_check_corpora, {"corpora": {"nope": {}}}) == f"unknown corpus corpora.nope; allowed corpora: {known}"
    assert error(_check_corpora, {"corpora": {"synthetic": 3}}) == (
        "corpora.synthetic: expected a mapping with root and options; got 3")
    assert error(_check_corpora, {"corpora": {"synthetic": {"shards_dir": "x"}}}) == (
        "corpora.synthetic.shards_dir: shard folders are derived as data.shards_root/synthetic; remove the key "
        "(set data.shards_root to move every corpus' shards)")
    assert error(_check_corpora, {"corpora": {"synthetic": {"options": [1]}}}) == (
        "corpora.synthetic.options: expected a mapping, got list")
    assert error(_check_corpora, {"corpora": {"synthetic": None}, "data": {"train_corpora": ["synthetic", "mead",
                                                                                             "how2sign"]}}) == (
        "data.train_corpora names mead, how2sign, not listed in corpora; add corpora.mead (root, options) or "
        "remove it from data.train_corpora")
    # the default train corpus (synthetic) must be listed too; a malformed list is left to the data section
    assert "data.train_corpora names synthetic," in error(_check_corpora, {})
    assert _check_corpora({"corpora": {"synthetic": None}}) == {"synthetic": {"options": {}}}
    # the options are checked against the adapter's own option class (synthetic has none)
    assert error(_check_corpora, {"corpora": {"synthetic": {"options": {"x": 1}}}}) == (
        "unknown key(s) corpora.synthetic.options.x; allowed keys in 'corpora.synthetic.options': ")
    assert _check_corpora({"corpora": {}, "data": {"train_corpora": "synthetic"}}) == {}
    assert _check_corpora({"corpora": {}, "data": {"train_corpora": [1]}}) == {}
    assert _check_corpora({"corpora": {"synthetic": {"root": "r"}}, "data": {"train_corpora": []}}) == {
        "synthetic": {"root": "r", "options": {}}}
    sections = ", ".join(s for s, p in SECTIONS.items() if p)
    assert error(section_class, "corpora") == f"no config class for section 'corpora'; sections with one: {sections}"
    assert error(section_class, "nope").startswith("no config class for section 'nope'; sections with one: data, ")
    assert error(params_from_dict, {"zz": {}, "aa": {}, 1: {}}) == (
        f"unknown section(s) 1, aa, zz; allowed sections: {', '.join(SECTIONS)}")
    assert error(preset_overlay, "huge") == "unknown preset 'huge'; allowed: default, tiny, paper, study"
    assert preset_overlay("default") == {} and preset_overlay("tiny")


def test_params_files_that_cannot_be_read_are_named(tmp_path, monkeypatch):
    from m3t.config import ConfigError, read_yaml

    def error(path):
        with pytest.raises(ConfigError) as err:
            read_yaml(path)
        return str(err.value)

    path = tmp_path / "p.yaml"
    assert error(path) == f"params file {path} not found; run from the repository root or pass its path"
    path.write_bytes(b"a: 1\nb: \xff\n")
    assert error(path) == f"{path}: not UTF-8 text (byte 8); re-save it as UTF-8"
    path.write_text("a: [1\n")
    assert error(path).startswith(f"{path}: not valid YAML (") and error(path).endswith("); fix the line shown")
    path.write_text("- 1\n")
    assert error(path) == f"{path}: expected a mapping of sections at top level"
    path.write_text("")
    assert read_yaml(path) == {}
    path.write_text("a: 1\n")
    assert read_yaml(path) == {"a": 1}
    monkeypatch.setenv("M3T_YAML_MAX_BYTES", "4")
    assert error(path) == f"{path}: 5 bytes, more than 4 (a params file is tens of kB); a legitimately large file: " \
                          "raise M3T_YAML_MAX_BYTES"
    monkeypatch.setenv("M3T_YAML_MAX_BYTES", "5")
    assert read_yaml(path) == {"a": 1}  # exactly the limit passes


def test_yaml_nesting_and_expansion_limits_are_exact(monkeypatch):
    from m3t.config import MAX_BYTES, MAX_DEPTH, MAX_NODES, ConfigError, safe_yaml

    assert (MAX_NODES, MAX_BYTES, MAX_DEPTH) == (1_000_000, 16 * 2**20, 100)
    assert safe_yaml("", "f") is None and safe_yaml("a: [1, 2]", "f") == {"a": [1, 2]}
    monkeypatch.setenv("M3T_YAML_MAX_DEPTH", "3")
    assert safe_yaml("[[1]]", "f") == [[1]]  # three nested nodes (the scalar counts): allowed
    with pytest.raises(ConfigError) as err:
        safe_yaml("[[[1]]]", "f.yaml")
    assert str(err.value) == ("f.yaml: nested too deeply to read (more than 3 levels); a legitimately deep file: "
                              "raise M3T_YAML_MAX_DEPTH")
    monkeypatch.setenv("M3T_YAML_MAX_NODES", "7")
    assert safe_yaml("a: &x [1, 2]\nb: 3", "f") == {"a": [1, 2], "b": 3}  # 1 + (1 + 3) + 2 = 7 nodes
    with pytest.raises(ConfigError) as err:
        safe_yaml("a: &x [1, 2]\nb: *x", "g")
    assert str(err.value) == ("g: its aliases expand to 9 values, more than 7 (a YAML alias bomb?); a legitimately "
                              "large file: raise M3T_YAML_MAX_NODES")


def test_merge_overlays_nested_mappings_and_replaces_everything_else():
    from m3t.config import merge

    base = {"a": {"x": 1, "y": {"p": 1}}, "b": [1], "c": 3}
    assert merge(base, {"a": {"y": {"q": 2}}, "b": [2], "d": {"z": 1}}) == {
        "a": {"x": 1, "y": {"p": 1, "q": 2}}, "b": [2], "c": 3, "d": {"z": 1}}
    assert merge({"a": 1}, {"a": {"b": 2}}) == {"a": {"b": 2}} and merge({"a": {"b": 2}}, {"a": None}) == {"a": None}
    assert base == {"a": {"x": 1, "y": {"p": 1}}, "b": [1], "c": 3}  # the inputs are not changed


def test_a_fit_job_needs_a_known_corpus_listed_in_params():
    from m3t.config import ConfigError, load_params

    params = load_params(Path(__file__).resolve().parents[2] / "params.yaml", preset="tiny")
    job = params.fit_job()
    assert job is not None
    with pytest.raises(ConfigError) as err:
        params.fit_job("nope")
    assert str(err.value).startswith("corpus 'nope' unknown; expected one of synthetic, ")
    with pytest.raises(ConfigError) as err:
        params.fit_job("mead")
    assert str(err.value) == ("corpora.mead is not in params.yaml; add it with root and options (see the commented "
                              "examples there)")


# -------------------------------------------------------------------------------------- declared sizes
def test_a_zip_member_is_checked_against_the_file_the_cap_and_its_npy_header(tmp_path, monkeypatch):
    """Stored members must hold what they declare, members must lie inside the file, the members' sum is capped,
    and with ``npy_members`` an ``.npy`` member's header may not declare more than the member holds."""
    import io
    import zipfile

    from m3t.declared import MAX_BYTES_ENV, DeclaredSizeError, check_zip, open_npz

    good = tmp_path / "good.npz"
    np.savez(good, a=np.arange(4, dtype=np.int64), b=np.zeros(3))
    check_zip(good, npy_members=True)
    with open_npz(good) as arrays:
        assert arrays["a"].tolist() == [0, 1, 2, 3]
    # a member whose .npy header declares 1,000 int64 items but holds 4
    header = np.lib.format.header_data_from_array_1_0(np.arange(4, dtype=np.int64))
    header["shape"] = (1000,)
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, header)
    forged = tmp_path / "forged.npz"
    with zipfile.ZipFile(forged, "w") as archive:
        archive.writestr("a.npy", buffer.getvalue() + np.arange(4, dtype=np.int64).tobytes())
    check_zip(forged)  # the directory alone is consistent
    with pytest.raises(DeclaredSizeError) as err:
        check_zip(forged, npy_members=True)
    assert str(err.value) == (f"{forged}: member 'a.npy' declares 8,000 bytes but holds 32 (truncated or forged); "
                              "re-export the file")
    with pytest.raises(DeclaredSizeError):
        open_npz(forged)
    # the members' sum is capped even when each member alone fits
    monkeypatch.setenv(MAX_BYTES_ENV, "200")
    two = tmp_path / "two.zip"
    with zipfile.ZipFile(two, "w") as archive:
        archive.writestr("x", b"a" * 150)
        archive.writestr("y", b"b" * 50)
    check_zip(two)  # 200 in all: at the cap
    with zipfile.ZipFile(two, "a") as archive:
        archive.writestr("z", b"c")
    with pytest.raises(DeclaredSizeError) as err:
        check_zip(two)
    assert str(err.value) == (f"{two}: its members declare more than 200 bytes in all; a legitimately huge file: "
                              f"raise {MAX_BYTES_ENV}")


def test_a_zip_member_past_the_end_of_the_file_is_named_with_its_end(tmp_path, monkeypatch):
    """A member whose stored bytes end past the file's size (the file as if cut after its directory was read)."""
    import zipfile
    from types import SimpleNamespace

    from m3t import declared

    path = tmp_path / "t.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("x", b"a" * 100)
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("x")
    end = info.header_offset + info.compress_size

    class Short(type(Path())):
        def stat(self, *args, **kwargs):
            return SimpleNamespace(st_size=end - 1)

    monkeypatch.setattr(declared, "Path", Short)
    with pytest.raises(declared.DeclaredSizeError) as err:
        declared.check_zip(path)
    assert str(err.value) == (f"{path}: member 'x' ends at byte {end:,}, past the end of the file ({end - 1:,} "
                              "bytes): truncated; re-export it")

    class Exact(type(Path())):
        def stat(self, *args, **kwargs):
            return SimpleNamespace(st_size=end)

    monkeypatch.setattr(declared, "Path", Exact)
    declared.check_zip(path)  # ending at the last byte is inside


def test_npy_headers_are_read_and_checked_before_loading(tmp_path):
    import io

    from m3t.declared import DeclaredSizeError, check_npy, check_npy_header, load_npy

    path = tmp_path / "a.npy"
    np.save(path, np.arange(6, dtype=np.float32).reshape(2, 3))
    check_npy(path)
    assert load_npy(path).tolist() == [[0, 1, 2], [3, 4, 5]]
    data = path.read_bytes()
    path.write_bytes(data[:-1])  # one byte short of 24
    with pytest.raises(DeclaredSizeError) as err:
        check_npy(path)
    header = len(data) - 24
    assert str(err.value) == (f"{path} declares 24 bytes but holds 23 (truncated or forged); re-export the file")
    with pytest.raises(DeclaredSizeError):
        load_npy(path)
    with pytest.raises(DeclaredSizeError) as err:
        check_npy_header(io.BytesIO(b"not numpy at all"), 16, "m")
    assert str(err.value).startswith("m: not a readable .npy header (") and str(err.value).endswith(
        "); re-export the file")
    v3 = io.BytesIO()
    np.lib.format.write_array_header_2_0(v3, np.lib.format.header_data_from_array_1_0(np.zeros(2)))
    raw = bytearray(v3.getvalue())
    raw[6] = 3  # format version 3.0
    with pytest.raises(DeclaredSizeError) as err:
        check_npy_header(io.BytesIO(bytes(raw)), 100, "m")
    assert str(err.value) == "m: .npy format version (3, 0) is not read here; save it with numpy.save"
    version2 = io.BytesIO()
    np.lib.format.write_array_header_2_0(version2, np.lib.format.header_data_from_array_1_0(np.zeros(2)))
    size = len(version2.getvalue())
    version2.seek(0)
    check_npy_header(version2, size + 16, "m")  # version 2.0 is read; 2 float64 fit
    version2.seek(0)
    with pytest.raises(DeclaredSizeError):
        check_npy_header(version2, size + 15, "m")
    objects = io.BytesIO()
    np.lib.format.write_array_header_1_0(objects, np.lib.format.header_data_from_array_1_0(
        np.array([None] * 1000, dtype=object)))
    objects.seek(0)
    check_npy_header(objects, 0, "m")  # pickled arrays are left to allow_pickle=False
    assert header > 0


def test_hdf5_datasets_are_checked_against_their_storage():
    from types import SimpleNamespace

    from m3t.declared import MAX_RATIO, DeclaredSizeError, check_hdf5_dataset

    def dataset(size, itemsize, stored, chunks):
        return SimpleNamespace(size=size, dtype=np.dtype(f"f{itemsize}"), chunks=chunks, name="/grp/x",
                               id=SimpleNamespace(get_storage_size=lambda: stored))

    check_hdf5_dataset(dataset(10, 4, 40, None), "f.h5")
    with pytest.raises(DeclaredSizeError) as err:
        check_hdf5_dataset(dataset(10, 4, 39, None), "f.h5")
    assert str(err.value) == "f.h5: dataset 'grp/x' declares 40 bytes but holds 39 (truncated or forged); re-export " \
                             "the file"
    big = 2**21  # above the ratio floor
    check_hdf5_dataset(dataset(big // 8, 8, big // MAX_RATIO + 1, (4,)), "f.h5")  # chunked: within the ratio
    with pytest.raises(DeclaredSizeError, match="compression bomb"):
        check_hdf5_dataset(dataset(big // 8, 8, 1, (4,)), "f.h5")
    check_hdf5_dataset(dataset(None, 8, 0, None), "f.h5")  # an empty dataset declares nothing


def test_bounded_files_plain_and_gzip_carry_their_budgets(tmp_path, monkeypatch):
    import gzip

    from m3t.declared import MAX_RATIO_ENV, RATIO_FLOOR, DeclaredSizeError, open_bounded

    plain = tmp_path / "p.bin"
    plain.write_bytes(b"x" * 10)
    with open_bounded(plain) as stream:
        assert stream._left == 10 and stream._why == "the file has 10 bytes" and stream._where == str(plain)
        assert stream.read(3) == b"xxx" and stream._left == 7
    packed = tmp_path / "p.gz"
    packed.write_bytes(gzip.compress(b"y" * 1000))
    size = packed.stat().st_size
    monkeypatch.setenv(MAX_RATIO_ENV, "300")
    with open_bounded(packed, compressed=True) as stream:
        assert stream.read() == b"y" * 1000
        assert stream._why == (f"300:1 of its {size:,} compressed bytes; a legitimately compressible file: raise "
                               "M3T_MAX_INFLATE_RATIO")
    with open_bounded(packed, compressed=True) as stream:
        assert stream._left == max(RATIO_FLOOR, 300 * size)
    # a gzip trailer declaring far more than the ratio allows is refused before inflating
    bomb = tmp_path / "b.gz"
    bomb.write_bytes(packed.read_bytes()[:-4] + (2**30).to_bytes(4, "little"))
    with pytest.raises(DeclaredSizeError) as err, open_bounded(bomb, compressed=True):
        pass
    assert str(err.value).startswith(f"{bomb}: its gzip trailer declares 1,073,741,824 bytes from {size:,} compressed")
