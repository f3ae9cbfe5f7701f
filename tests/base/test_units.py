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
