"""The ``m3t`` commands of the papers' experiments: the sweeps (``ablate-tokenizers``, ``sgsa-sweep``) and the
claims study (``study``), each a list of DVC experiments run by :mod:`cli.variants`; the tables printed from the
MLflow runs and the claims judged on them. Each takes the parsed arguments of :func:`cli.main.main` and returns
the exit code.
"""
from __future__ import annotations

import argparse
import sys


def _sweep(args: argparse.Namespace, variants: list) -> int:
    """Run ``variants`` as DVC experiments in the workspace of ``--params`` (:mod:`cli.variants`)."""
    from cli.variants import VariantError, run_variants, tracking_env, workspace_of
    from m3t.config import load_params

    params = load_params(args.params)
    try:
        workspace = workspace_of(args.params)
        env = {} if args.dry_run else tracking_env(params.experiment, workspace)
        summary = run_variants(variants, workspace, workspace / ".m3t" / "sweeps", env=env, dry_run=args.dry_run)
    except VariantError as err:
        print(f"m3t: {err}", file=sys.stderr)
        return 1
    return 0 if summary.ok else 1


def cmd_ablate(args: argparse.Namespace) -> int:
    from cli.variants import Variant
    from m3t.config import load_params
    from m3t.tokenizers.ablation import CPU_WIDTHS, sweep_settings

    settings = sweep_settings(load_params(args.params).tokenizer.width, widths=args.widths or CPU_WIDTHS,
                              full=args.full)
    return _sweep(args, [Variant(f"tokenizer-{s['tokenizer.quantizer']}-b{s['tokenizer_train.batch_size']}"
                                 f"-w{s['tokenizer.width']}", s, ("train-tokenizers",)) for s in settings])


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

    experiment = load_params(args.params).experiment
    print(production_table(fetch_runs(experiment, stage="evaluate-smlm"),
                           baselines=fetch_runs(experiment, stage="evaluate-baselines")))
    return 0


def cmd_bt_table(args: argparse.Namespace) -> int:
    from m3t.backtranslation.table import backtranslation_table
    from m3t.config import load_params
    from m3t.experiment import fetch_runs

    experiment = load_params(args.params).experiment
    print(backtranslation_table(fetch_runs(experiment, stage="evaluate-backtranslation"),
                                fetch_runs(experiment, stage="evaluate-smlm"),
                                fetch_runs(experiment, stage="evaluate-baselines")))
    return 0


def cmd_slr_table(args: argparse.Namespace) -> int:
    from m3t.config import load_params
    from m3t.experiment import fetch_runs
    from m3t.slr.table import recognition_table

    print(recognition_table(fetch_runs(load_params(args.params).experiment, stage="evaluate-slr")))
    return 0


def cmd_sgsa_sweep(args: argparse.Namespace) -> int:
    from cli.variants import Variant
    from m3t.sgsa.table import sweep_settings

    variants = [Variant(f"sgsa-l{s.get('sgsa.decoder_layers', 'cfg')}-n{s['sgsa.temporal_adjacency']}"
                        f"-s{s['sgsa_train.seed']}", s, ("evaluate-sgsa",))
                for s in sweep_settings(args.table, args.seeds, layers=args.layers)]
    code = _sweep(args, variants)
    return code if args.dry_run else max(code, cmd_sgsa_table(args))


def cmd_sgsa_table(args: argparse.Namespace) -> int:
    from m3t.config import load_params
    from m3t.experiment import fetch_runs
    from m3t.sgsa.table import adjacency_table, cross_table, layers_table

    experiment = load_params(args.params).experiment
    records = fetch_runs(experiment, stage="evaluate-sgsa")
    baselines = fetch_runs(experiment, stage="evaluate-baselines")
    tables = {"1": layers_table, "2": adjacency_table, "3": cross_table}
    chosen = [args.table] if getattr(args, "table", "all") != "all" else list(tables)
    print("\n\n".join(tables[t](records, baselines=baselines) for t in chosen))
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


def cmd_study(args: argparse.Namespace) -> int:
    from cli.study import study
    from cli.variants import VariantError
    from m3t.config import ConfigError

    try:
        return study(args.params, args.preset, args.seeds, args.out, dry_run=args.dry_run, only=args.only or (),
                     claims=not args.no_claims, settings=args.settings)
    except (ConfigError, VariantError) as err:  # StudyError is one
        print(f"m3t study: {err}", file=sys.stderr)
        return 1
