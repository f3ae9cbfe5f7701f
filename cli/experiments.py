"""The ``m3t`` commands of the papers' experiments: the sweeps run by ``dvc exp`` (``ablate-tokenizers``,
``sgsa-sweep``), the tables printed from the MLflow runs, the claims judged on them, and the seeded studies
(``sgsa-study``, ``study``). Each takes the parsed arguments of :func:`cli.main.main` and returns the exit code.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path


def cmd_ablate(args: argparse.Namespace) -> int:
    from m3t.config import load_params
    from m3t.experiment import absolute_uri
    from m3t.tokenizers.ablation import CPU_WIDTHS, dvc_command, sweep_settings

    params = load_params(args.params)
    settings = sweep_settings(params.tokenizer.width, widths=args.widths or CPU_WIDTHS, full=args.full)
    # `--temp` runs in a copy of the workspace: send its MLflow runs to this workspace's store
    env = dict(os.environ, MLFLOW_TRACKING_URI=absolute_uri(params.experiment.tracking_uri, Path.cwd()))
    for i, setting in enumerate(settings, 1):
        command = dvc_command(setting)
        print(f"[{i}/{len(settings)}] {' '.join(command)}", flush=True)
        if not args.dry_run and subprocess.call(command, env=env) != 0:  # noqa: S603 - argv list, no shell
            print(f"setting {setting} failed; the sweep goes on", file=sys.stderr)
    return 0


def cmd_tokenizer_table(args: argparse.Namespace) -> int:
    from m3t.config import load_params
    from m3t.experiment import fetch_runs
    from m3t.tokenizers.ablation import ablation_table

    print(ablation_table(fetch_runs(load_params(args.params).experiment, stage="train-tokenizers")))
    return 0


def cmd_smlm_table(args: argparse.Namespace) -> int:
    from m3t.config import load_params
    from m3t.experiment import fetch_runs
    from m3t.smlm.table import production_table

    print(production_table(fetch_runs(load_params(args.params).experiment, stage="evaluate-smlm")))
    return 0


def cmd_bt_table(args: argparse.Namespace) -> int:
    from m3t.backtranslation.table import backtranslation_table
    from m3t.config import load_params
    from m3t.experiment import fetch_runs

    experiment = load_params(args.params).experiment
    print(backtranslation_table(fetch_runs(experiment, stage="evaluate-backtranslation"),
                                fetch_runs(experiment, stage="evaluate-smlm")))
    return 0


def cmd_slr_table(args: argparse.Namespace) -> int:
    from m3t.config import load_params
    from m3t.experiment import fetch_runs
    from m3t.slr.table import recognition_table

    print(recognition_table(fetch_runs(load_params(args.params).experiment, stage="evaluate-slr")))
    return 0


def cmd_sgsa_sweep(args: argparse.Namespace) -> int:
    from m3t.config import load_params
    from m3t.experiment import absolute_uri
    from m3t.sgsa.table import sweep_settings
    from m3t.tokenizers.ablation import dvc_command

    params = load_params(args.params)
    settings = sweep_settings(args.table, args.seeds, layers=args.layers)
    # `--temp` runs in a copy of the workspace: send its MLflow runs to this workspace's store
    env = dict(os.environ, MLFLOW_TRACKING_URI=absolute_uri(params.experiment.tracking_uri, Path.cwd()))
    for i, setting in enumerate(settings, 1):
        command = dvc_command(setting, stage="evaluate-sgsa")
        print(f"[{i}/{len(settings)}] {' '.join(command)}", flush=True)
        if not args.dry_run and subprocess.call(command, env=env) != 0:  # noqa: S603 - argv list, no shell
            print(f"setting {setting} failed; the sweep goes on", file=sys.stderr)
    return 0 if args.dry_run else cmd_sgsa_table(args)


def cmd_sgsa_table(args: argparse.Namespace) -> int:
    from m3t.config import load_params
    from m3t.experiment import fetch_runs
    from m3t.sgsa.table import adjacency_table, cross_table, layers_table

    records = fetch_runs(load_params(args.params).experiment, stage="evaluate-sgsa")
    tables = {"1": layers_table, "2": adjacency_table, "3": cross_table}
    chosen = [args.table] if getattr(args, "table", "all") != "all" else list(tables)
    print("\n\n".join(tables[t](records) for t in chosen))
    return 0


def cmd_claims(args: argparse.Namespace) -> int:
    from m3t.claims.report import claims_markdown, write_claims
    from m3t.config import load_params
    from m3t.experiment import fetch_runs

    params = load_params(args.params)
    out = args.out or params.data.metrics_dir
    rows = write_claims(fetch_runs(params.experiment), out, args.min_seeds)
    print(claims_markdown(rows, args.min_seeds))
    print(f"written: {out}/claims.json, {out}/claims.md")
    return 0


def cmd_sgsa_study(args: argparse.Namespace) -> int:
    from m3t.body.factory import load_body_model
    from m3t.config import load_params
    from m3t.sgsa.study import run_study

    params = load_params(args.params)
    summary = run_study(params.sgsa, params.sgsa_train, load_body_model(params.body), params.data, args.seeds,
                        args.out, args.split, params.backtranslation)
    print((Path(args.out) / "claims.md").read_text())
    return 0 if summary["comparisons"] else 1


def cmd_study(args: argparse.Namespace) -> int:
    from cli.study import study
    from cli.study_plan import StudyError
    from m3t.config import ConfigError

    try:
        return study(args.params, args.preset, args.seeds, args.root, dry_run=args.dry_run, only=args.only or (),
                     claims=not args.no_claims)
    except (ConfigError, StudyError) as err:
        print(f"m3t study: {err}", file=sys.stderr)
        return 1
