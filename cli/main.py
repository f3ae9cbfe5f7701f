"""``m3t`` command line: the few things users should not have to remember Prefect's syntax for.

    m3t params --preset paper [--write]   print (or write to params.yaml) a preset merged over params.yaml
    m3t fit-corpus [--max-clips N]        run the fit-corpus flow once, locally (temporary Prefect server)
    m3t up [--prefect-port 4200] [--mlflow-port 5000] [--no-serve] [--host 127.0.0.1] [--run-dir .m3t/run]
                                          in the background: Prefect server + every deployment served + MLflow UI,
                                          logs and PIDs in the run directory
    m3t status                            their URLs and health (non-zero exit when one is down)
    m3t down                              stop exactly the processes `m3t up` started
    m3t serve [--port 4200]               the foreground variant of `m3t up`, stopped on Ctrl-C;
                                          then: prefect deployment run fit-corpus/embedded
    m3t ablate-tokenizers [--full] [--dry-run] [--widths ...]
                                          the Tab. 3 sweep: one `dvc exp run --temp -S ...` per setting
    m3t tokenizer-table                   print the Tab. 3-style comparison from MLflow
    m3t smlm-table                        print the Tab. 1-style SMLM comparison (one row per variant)
    m3t bt-table                          print Tab. 2: back-translation of GT and generated motion (SL-T metrics)
    m3t sgsa-sweep 1|2 [--seeds 0 1 2]    SGSA Tab. 1 / 2 sweeps by dvc exp (opt-in: minutes per setting), then the table
    m3t sgsa-table [--table 1|2|3]        print SGSA Tab. 1-3 (Tab. 3: PT, SGSA, SMLM, baselines, ground truth; same judges)
    m3t claims [--min-seeds 3]            the papers' claims on the runs: paper vs ours, interval, verdict, run ids
    m3t study [--preset study] [--seeds 0 1 2 3 4] [--dry-run] [--only sgsa ...] [--set KEY=VALUE ...]
                                          every variant and seed the claims need as DVC experiments, then judged
    m3t slr-table                         print Tab. 4: recognition probe, full vs face-less, with intervals
    m3t dashboard [--out DIR]             build the static dashboard (default: experiment.dashboard_dir)
    m3t docs-pages [--out docs]           regenerate the docs' generated pages (results from metrics/, home from README)
    m3t produce "TEXT" --language L [--system smlm|retrieval|lexicon|pt|sgsa] [--gloss G] [--lexicon DIR] [--out DIR]
                                          one sentence -> .pose, parameters (.npz) and an MP4 with a trained system
    m3t translate INPUT --language L       a video, frame folder, .pose or .npz -> tracking, fitting, tokens ->
                                          the SMLM's translation (and the judge's), with each step's time
    m3t score PRED REF [--definitions ...] [--language en] [--out DIR] [--format table|csv|json] [--any-fps]
                                          score anyone's output (.pose / SMPL-X folders, shards, sentences) under the
                                          field's definitions; clips that cannot be scored are listed with a reason

This module parses the command line and holds the workspace and service commands; the experiment commands (sweeps,
tables, claims, studies) are in :mod:`cli.experiments`; every sweep and study runs its variants as DVC experiments
through :mod:`cli.variants`.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import yaml

from cli import experiments
from m3t.atomic import write_text
from m3t.experiment import disable_telemetry


def _cmd_params(args: argparse.Namespace) -> int:
    from m3t.config import load_params
    from m3t.experiment import to_dict

    text = yaml.safe_dump(to_dict(load_params(args.params, preset=args.preset)), sort_keys=False)
    if args.write:
        write_text(args.params, f"# preset: {args.preset}\n" + text)
        print(f"wrote preset {args.preset!r} to {args.params}")
    else:
        print(text)
    return 0


def _cmd_fit_corpus(args: argparse.Namespace) -> int:
    from flows.fit_corpus import fit_corpus

    summary = fit_corpus(params_path=args.params, preset=args.preset, max_clips=args.max_clips)
    print(summary)
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
    """``m3t up`` in the foreground: the same services, stopped together on Ctrl-C."""
    from cli.processes import ServiceError
    from cli.services import ServicesConfig, down, up

    cfg = ServicesConfig(run_dir=Path(args.run_dir), params=Path(args.params), prefect_port=args.port,
                         mlflow_port=args.mlflow_port)
    try:
        up(cfg)
    except ServiceError as err:
        print(f"m3t serve: {err}", file=sys.stderr)
        return 1
    print(f"Prefect UI http://127.0.0.1:{args.port}, MLflow UI http://127.0.0.1:{args.mlflow_port}; Ctrl-C stops "
          f"them. Run: PREFECT_API_URL=http://127.0.0.1:{args.port}/api prefect deployment run fit-corpus/embedded")
    try:
        while True:
            time.sleep(1)
    except KeyboardInterrupt:
        pass
    finally:
        down(cfg.run_dir)
    return 0


def _print_status(healths: list) -> None:
    rows = [("service", "pid", "alive", "healthy", "url", "log")]
    rows += [(h.name, str(h.pid), "yes" if h.alive else "no", "yes" if h.healthy else f"no ({h.detail})", h.url,
              os.path.relpath(h.log) if h.log.startswith(os.getcwd() + os.sep) else h.log) for h in healths]
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)) + "  " + row[-1])


def _cmd_up(args: argparse.Namespace) -> int:
    from cli.processes import ServiceError
    from cli.services import ServicesConfig, status, up

    cfg = ServicesConfig(run_dir=Path(args.run_dir), params=Path(args.params), host=args.host,
                         prefect_port=args.prefect_port, mlflow_port=args.mlflow_port, serve=not args.no_serve,
                         start_timeout_s=args.timeout)
    t0 = time.monotonic()
    try:
        records = up(cfg)
    except ServiceError as err:
        print(f"m3t up: {err}", file=sys.stderr)
        return 1
    print(f"up in {time.monotonic() - t0:.1f} s")
    _print_status(status(cfg.run_dir))
    prefect = next((r for r in records if r.name == "prefect"), None)
    if prefect is not None:
        print(f"run a deployment: PREFECT_API_URL={prefect.url}/api prefect deployment run fit-corpus/embedded")
    mlflow = next((r for r in records if r.name == "mlflow"), None)
    if mlflow is not None:
        print(f"MLflow runs: {_mlflow_link(args.params, mlflow.url)}")
    return 0


def _mlflow_link(params: str, base_url: str) -> str:
    """The link that opens the experiment on its runs table (MLflow 3.17's UI otherwise lands on GenAI pages)."""
    from m3t.config import load_params
    from m3t.experiment import experiment_ui_link

    return experiment_ui_link(load_params(params).experiment, base_url) or (
        f"{base_url} (no experiment yet; once a stage has run, choose 'Model training' in the side bar)")


def _cmd_status(args: argparse.Namespace) -> int:
    from cli.processes import ServiceError
    from cli.services import status

    try:
        healths = status(Path(args.run_dir))
    except ServiceError as err:
        print(f"m3t status: {err}", file=sys.stderr)
        return 1
    if not healths:
        print(f"no services recorded in {args.run_dir}; start them with `m3t up`")
        return 1
    _print_status(healths)
    return 0 if all(h.healthy for h in healths) else 1


def _cmd_down(args: argparse.Namespace) -> int:
    from cli.processes import ServiceError
    from cli.services import down

    try:
        stopped = down(Path(args.run_dir), timeout_s=args.timeout)
    except ServiceError as err:
        print(f"m3t down: {err}", file=sys.stderr)
        return 1
    if not stopped:
        print(f"nothing was running (run directory {args.run_dir})")
    return 0


def _cmd_docs_results(args: argparse.Namespace) -> int:
    from dashboards.docs_pages import write_pages

    for path in write_pages(".", args.out):
        print(f"wrote {path}")
    return 0


def _cmd_dashboard(args: argparse.Namespace) -> int:
    from dashboards.build import build_dashboard
    from m3t.config import load_params

    index = build_dashboard(load_params(args.params), args.out)
    print(f"wrote {index}; open it in a browser")
    return 0


def _workspace_body(params_path: str):
    from m3t.body.factory import load_body_model
    from m3t.config import load_params

    return load_body_model(load_params(params_path).body)


def _workspace_judge(args: argparse.Namespace) -> dict:
    """For shards: the workspace's tokenizers (a token shard is decoded by them) and the back-translation judge
    (``--judge``, else the workspace's when it has checkpoints) with the decoding settings of params.yaml."""
    from m3t.config import load_params

    if not str(args.prediction).endswith(".parquet"):
        return {}
    params = load_params(args.params)
    found = {"tokenizers_dir": params.data.tokenizers_dir}
    judge = Path(args.judge) if args.judge else params.data.backtranslation_dir
    if args.judge or any(judge.glob("*.pt")):
        found.update(judge=judge, beam_size=params.backtranslation.beam_size,
                     length_penalty=params.backtranslation.length_penalty)
    return found


def _cmd_produce(args: argparse.Namespace) -> int:
    from m3t.config import load_params
    from m3t.production.produce import ProductionError, produce

    try:
        result = produce(args.text, args.language, load_params(args.params), args.system, args.out, args.name,
                         video=not args.no_video, progress=True, gloss=args.gloss, lexicon_dir=args.lexicon)
    except ProductionError as exc:
        print(f"m3t produce: {exc}", file=sys.stderr)
        return 2
    print(f"{result.system}: {result.frames} frames at {result.fps:g} fps for {result.text!r} ({result.language})")
    for key in ("retrieved_clip", "retrieved_text", "match", "chrf", "steps", "stopped", "input", "signs", "entries", "skeleton", "fingerspelled"):
        if key in result.details:
            print(f"  {key}: {result.details[key]}")
    if result.unhandled_words:
        print(f"  words not handled ({len(result.unhandled_words)}): {' '.join(result.unhandled_words)}")
    for path in result.files.values():
        print(f"wrote {path}")
    return 0


def _cmd_translate(args: argparse.Namespace) -> int:
    from m3t.config import load_params
    from m3t.production.produce import ProductionError
    from m3t.production.translate import translate_input

    try:
        result = translate_input(args.input, args.language, load_params(args.params), judge=not args.no_judge,
                                 progress=True)
    except ProductionError as exc:
        print(f"m3t translate: {exc}", file=sys.stderr)
        return 2
    print(f"{result.input} ({result.kind}, {result.frames} frames, {result.language})")
    print(f"  SMLM:  {result.smlm}")
    if result.judge is not None:
        print(f"  judge: {result.judge}")
    print("  time: " + ", ".join(f"{step} {s:.1f} s" for step, s in result.seconds.items()))
    for note in result.notes:
        print(f"  note: {note}")
    return 0


def _workspace_smplx(params_path: str) -> str | None:
    """body.smplx_path of the workspace's params (the mean hand of SMPL-X parameter folders), None without one."""
    from m3t.config import load_params

    try:
        return str(load_params(params_path).body.smplx_path)
    except (OSError, ValueError):
        return None


def _cmd_score(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from m3t.scoring.poses import ScoreInputError
    from m3t.scoring.score import score

    definitions = [d for part in args.definitions for d in part.split(",") if d] if args.definitions else None
    try:
        report = score(args.prediction, args.reference, definitions, args.language, any_fps=args.any_fps,
                       progress=lambda ids: tqdm(ids, desc="scoring", unit="clip", disable=None),
                       body=lambda: _workspace_body(args.params), smplx_path=_workspace_smplx(args.params),
                       **_workspace_judge(args))
    except ScoreInputError as exc:
        print(f"m3t score: {exc}", file=sys.stderr)
        return 2
    if args.format == "json":
        from m3t.atomic import dumps

        print(dumps(report.as_json()), end="")
    elif args.format == "csv":
        print(report.csv(), end="")
    else:
        print(report.table())
    if args.out:
        for path in report.write(args.out):
            print(f"wrote {path}", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    disable_telemetry()
    parser = argparse.ArgumentParser(prog="m3t", description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("params", help="show or write a params preset")
    p.add_argument("--preset", default="default")
    p.add_argument("--write", action="store_true")
    p.set_defaults(func=_cmd_params)
    p = sub.add_parser("fit-corpus", help="run the fit-corpus flow once")
    p.add_argument("--preset", default="default")
    p.add_argument("--max-clips", type=int, default=-1)
    p.set_defaults(func=_cmd_fit_corpus)
    p = sub.add_parser("up", help="start the Prefect server, the deployments and the MLflow UI in the background")
    p.add_argument("--params", default=argparse.SUPPRESS, help="params.yaml of the MLflow store and the deployments")
    p.add_argument("--prefect-port", type=int, default=4200)
    p.add_argument("--mlflow-port", type=int, default=5000)
    p.add_argument("--host", default="127.0.0.1", help="interface to bind; anything but loopback exposes both "
                                                         "servers to other machines, without authentication")
    p.add_argument("--no-serve", action="store_true", help="no deployments, only the two servers")
    p.add_argument("--run-dir", default=".m3t/run", help="services.json, logs and Prefect's home")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds each service may take to answer")
    p.set_defaults(func=_cmd_up)
    p = sub.add_parser("status", help="URLs and health of what `m3t up` started (exit 1 if one is down)")
    p.add_argument("--run-dir", default=".m3t/run")
    p.set_defaults(func=_cmd_status)
    p = sub.add_parser("down", help="stop every process `m3t up` started")
    p.add_argument("--run-dir", default=".m3t/run")
    p.add_argument("--timeout", type=float, default=20.0, help="seconds between SIGTERM and SIGKILL")
    p.set_defaults(func=_cmd_down)
    p = sub.add_parser("serve", help="`m3t up` in the foreground, stopped on Ctrl-C")
    p.add_argument("--port", type=int, default=4200)
    p.add_argument("--mlflow-port", type=int, default=5000)
    p.add_argument("--run-dir", default=".m3t/run")
    p.set_defaults(func=_cmd_serve)
    p = sub.add_parser("ablate-tokenizers", help="run the quantisation ablation sweep (dvc exp run --temp)")
    p.add_argument("--full", action="store_true", help="the whole quantizer x batch x width grid")
    p.add_argument("--widths", type=int, nargs="*", help="widths to sweep (default 32 64 128; paper: 512 1024 2048)")
    p.add_argument("--dry-run", action="store_true")
    p.set_defaults(func=experiments.cmd_ablate)
    p = sub.add_parser("tokenizer-table", help="print the Tab. 3-style tokenizer comparison from MLflow")
    p.set_defaults(func=experiments.cmd_tokenizer_table)
    p = sub.add_parser("smlm-table", help="print the Tab. 1-style SMLM comparison from MLflow")
    p.set_defaults(func=experiments.cmd_smlm_table)
    p = sub.add_parser("bt-table", help="print Tab. 2 (back-translation, SL-T definition) from MLflow")
    p.set_defaults(func=experiments.cmd_bt_table)
    p = sub.add_parser("dashboard", help="build the static dashboard over the MLflow store and the DVC metrics")
    p.add_argument("--out", default=None, help="folder of the site (default: experiment.dashboard_dir)")
    p.set_defaults(func=_cmd_dashboard)
    p = sub.add_parser("docs-pages", help="regenerate the docs' generated pages (results from the metrics files, home from the README)")
    p.add_argument("--out", default=None, help="documentation folder (default: docs)")
    p.set_defaults(func=_cmd_docs_results)
    p = sub.add_parser("slr-table", help="print Tab. 4 (recognition probe with intervals) from MLflow")
    p.set_defaults(func=experiments.cmd_slr_table)
    p = sub.add_parser("sgsa-sweep", help="SGSA Tab. 1 (L = 0..5) or Tab. 2 (N = inf, 1, 2, 3, 5) by dvc exp, then "
                                          "the table")
    p.add_argument("table", choices=("1", "2"))
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="sgsa_train.seed values (one run each)")
    p.add_argument("--layers", type=int, default=None, help="L of the Tab. 2 sweep (default: params' sgsa layers)")
    p.add_argument("--dry-run", action="store_true")
    p.set_defaults(func=experiments.cmd_sgsa_sweep)
    p = sub.add_parser("claims", help="judge the papers' claims on the MLflow runs: claims.json / claims.md")
    p.add_argument("--min-seeds", type=int, default=3, help="fewer seeds per variant: inconclusive")
    p.add_argument("--out", default=None, help="folder of claims.json / claims.md (default: data.metrics_dir)")
    p.set_defaults(func=experiments.cmd_claims)
    p = sub.add_parser("study", help="every variant and seed the claims need, as DVC experiments; then the claims")
    p.add_argument("--preset", default="study")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4],
                   help="training seeds of every variant (default 5: the seed-half check splits them 2 + 3)")
    p.add_argument("--out", default=None, help="folder of the logs, timings and verdicts (default studies/<preset>)")
    p.add_argument("--dry-run", action="store_true", help="print the dvc exp run commands, run nothing")
    p.add_argument("--only", nargs="+", default=None, metavar="NAME",
                   help="only these variants: families (sgsa, smlm, slr, tokenizer, shared), stages or variant names")
    p.add_argument("--set", nargs="+", default=(), metavar="KEY=VALUE", dest="settings",
                   help="settings of every variant, e.g. sgsa_evaluate.counter=ground_truth")
    p.add_argument("--no-claims", action="store_true", help="do not judge the claims at the end")
    p.set_defaults(func=experiments.cmd_study)
    p = sub.add_parser("sgsa-table", help="print SGSA Tab. 1, 2, 3 (PT, SGSA, SMLM, same judges) from MLflow")
    p.add_argument("--table", choices=("1", "2", "3", "all"), default="all")
    p.set_defaults(func=experiments.cmd_sgsa_table)
    p = sub.add_parser("produce", help="one sentence -> signing (.pose, parameters, MP4) with a trained system")
    p.add_argument("text", help="the sentence, in the spoken language of the corpus")
    p.add_argument("--language", required=True, help="the sign language, as the corpus names it (e.g. ASL-SYN)")
    p.add_argument("--system", choices=("smlm", "retrieval", "lexicon", "pt", "sgsa"), default="smlm",
                   help="smlm: the trained SMLM; retrieval: the nearest training clip's motion; lexicon: stored "
                        "isolated signs stitched (the two baselines); pt / sgsa: the skeletal systems (a skeleton)")
    p.add_argument("--gloss", default=None, help="lexicon: the gloss sequence to sign (default: the text's words)")
    p.add_argument("--lexicon", default=None, help="lexicon: a folder in spoken-to-signed's layout (lexicon.csv / "
                                                   "index.csv + .pose files); --language is its signed-language code")
    p.add_argument("--out", default="produced", help="folder of the outputs (default: produced/)")
    p.add_argument("--name", default=None, help="file name stem (default: a slug of the sentence)")
    p.add_argument("--no-video", action="store_true", help="skip the MP4")
    p.set_defaults(func=_cmd_produce)
    p = sub.add_parser("translate", help="one signing input (video, frame folder, .pose, .npz) -> text with the "
                                         "trained SMLM and the judge")
    p.add_argument("input", help="a video file, a frame folder, a .pose file or a .npz of parameters")
    p.add_argument("--language", required=True, help="the sign language, as the corpus names it (e.g. ASL-SYN)")
    p.add_argument("--no-judge", action="store_true", help="skip the back-translation judge")
    p.set_defaults(func=_cmd_translate)
    p = sub.add_parser("score", help="score predictions against references (.pose folders, SMPL-X parameter folders, "
                                     "shards or sentence files) under the field's named definitions (docs/scoring.md)")
    p.add_argument("prediction", help="folder of .pose files, folder of SMPL-X parameter files in SOKE's layout "
                                      "(.pkl / .npz; scored on SMPL-FX), a parameter shard (.parquet; the body model "
                                      "of params.yaml), or a .txt / .tsv file of sentences")
    p.add_argument("reference", help="the references, same kind; clips pair by relative path / line / id")
    p.add_argument("--definitions", nargs="+", default=None, metavar="NAME",
                   help="pose: pose_eval slrtp; parameters and SMPL-X folders: m3t soke_exact; text: slt soke "
                        "slrtp (default: every one that applies)")
    p.add_argument("--language", default="en", help="language of sentence files (zh: Chinese tokenisation)")
    p.add_argument("--judge", default=None, help="back-translation checkpoints for shards (default: the workspace's "
                                                 "models/backtranslation when trained)")
    p.add_argument("--out", default=None, help="also write score.json, score.csv, clips.csv, unscored.csv here")
    p.add_argument("--format", choices=("table", "csv", "json"), default="table", help="what to print")
    p.add_argument("--any-fps", action="store_true", help="score pairs whose two sides differ in frame rate, as "
                                                          "pose-evaluation and the SLRTP scripts do")
    p.set_defaults(func=_cmd_score)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
