"""Mutation testing of the library: how many small, plausible code changes the tests notice.

mutmut (configured in ``pyproject.toml`` ``[tool.mutmut]``) copies ``m3t/`` and ``dashboards/`` to ``mutants/``,
plants every mutant of every package (the core ``body``, ``fitting``, ``metrics``, ``tokenizers``, ``smlm``,
``shards``, ``corpora``; ``sgsa``, ``slr``, ``backtranslation``, ``claims``, ``render``, ``trackers``, the top-level
modules, the dashboard builder): a flipped comparison or operator, a changed constant or string, a dropped
argument, ``None`` for a value. For each mutant it runs the tests of the selection that call the mutated function
(forked, so imports are paid once). A mutant is *killed* when a test fails, *timeout* when its tests run past
2 x (the clean run's time + 20 s) (an endless loop), *crashed* when the test process dies by a signal; all three
are detected. It *survived* when every test passes, and has *no tests* when no selected test calls the function.

    python benchmarks/mutation.py --sample 1000    # a seeded random sample (what a 2-core machine does in ~1 h)
    python benchmarks/mutation.py                  # every mutant (~19,000: hours; use --max-children 16)
    python benchmarks/mutation.py --sample 1000 --retest survived   # after adding tests: the survivors again
    python benchmarks/mutation.py --report-only    # rewrite the report from the verdicts in mutants/
    python benchmarks/mutation.py --sample 200 --seed 4 --modules sgsa,slr,dashboards \
        --exclude-sample benchmarks/results/mutation_first_sample.json   # a fresh draw from some modules

A module is a package of ``m3t`` (``sgsa``), a top-level module of ``m3t`` by its name (``experiment``) or
``dashboards``. A draw from some modules keeps, in the report, the last figures of the others (an earlier run's,
with its commit); ``--exclude-sample`` (repeatable) leaves out the mutants of an earlier draw (its
``mutants/sample.json``, copied aside), so the new draw holds none that tests were written against after reading
an earlier one.

The mutants whose survival new tests were written against are listed in ``benchmarks/mutation_targeted.json``;
the report also rates the sample without any mutant of their functions (the estimate no test was tuned to: the
test writers read those functions and tried neighbouring mutants too).

Writes ``benchmarks/results/mutation.md`` (per module: counts, the detection rate with its Wilson 95% interval
when sampled; then every survivor with its diff and every untested function, grouped by function) and
``mutation.json``, and logs the numbers to MLflow. Runs resume: finished mutants keep their verdict, and after a
code change mutmut retests only the mutants of changed functions.
"""
from __future__ import annotations

import argparse
import collections
import datetime as dt
import json
import math
import hashlib
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# a test run that crashed (mutmut's "segfault": the process died by a signal, e.g. killed after its CPU-time limit
# or for memory) failed too: detected
DETECTED = ("killed", "timeout", "segfault", "caught by type check")
SURVIVED = ("survived",)
UNTESTED = ("no tests",)


# mutmut 3.8's first steps of `mutmut run` (copy the package, plant the mutants), without running any test: the
# sample is drawn from the mutants it plants
GENERATE = """
from pathlib import Path
import mutmut.__main__ as m
m.set_mutant_under_test("mutant_generation")
Path("mutants").mkdir(exist_ok=True)
m.copy_src_dir(); m.copy_also_copy_files(); m.setup_source_paths(); m.store_lines_covered_by_tests()
m.create_mutants({children})
"""
SAMPLE_FILE = ROOT / "mutants" / "sample.json"
# survivors a reader has looked at: mutant name -> why it may stay (an equivalent mutant, or only an error
# message's wording); the report prints the reason beside the survivor, and counts the others as unexplained
JUSTIFIED_FILE = ROOT / "benchmarks" / "mutation_justified.json"
# mutants whose survival (or lack of tests) new tests were written against: a rate over a sample holding them is
# flattered, so the report also rates the sample without them
TARGETED_FILE = ROOT / "benchmarks" / "mutation_targeted.json"


def equivalents(justified: dict[str, str]) -> set[str]:
    """The justified mutants that change no behaviour (their reason says *equivalent* or *unreachable*), as
    opposed to those that change only a message's wording or a figure's look, which stay in every rate."""
    return {name for name, why in justified.items() if why.startswith(("equivalent", "unreachable"))}


def wilson(hits: int, n: int, z: float = 1.96) -> tuple[float, float] | None:
    """Wilson score 95% interval of a proportion, in percent."""
    if n == 0:
        return None
    p = hits / n
    centre, half = p + z * z / (2 * n), z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return (round(100 * (centre - half) / (1 + z * z / n), 1), round(100 * (centre + half) / (1 + z * z / n), 1))


def draw(population: list[str], n: int, seed: int) -> list[str]:
    """The ``n`` mutants whose ``sha256(seed:name)`` rank lowest, sorted by name.

    Each mutant's rank depends on its name alone, so the draw is stable: a smaller sample is a subset of a larger
    one, and a code change that adds or removes k mutants changes at most k members of the sample (a shuffle of the
    whole population would redraw all of it, and every stored verdict would be lost to the rate).
    """
    def rank(name: str) -> str:
        return hashlib.sha256(f"{seed}:{name}".encode()).hexdigest()
    return sorted(sorted(population, key=rank)[:n])


# the mutated source trees under mutants/ (pyproject's source_paths)
SOURCES = ("m3t", "dashboards")


def module_of(path: Path) -> str:
    """The report's module of a mutated file: ``m3t/fitting/corpus.py`` -> ``fitting`` (a package of the
    library), ``m3t/experiment.py`` -> ``experiment`` (a top-level module), ``dashboards/sections/runs.py`` ->
    ``dashboards`` (the dashboard builder, one module). ``path`` is relative to ``mutants/`` or the repository."""
    parts = path.parts
    if parts[0] == "mutants" or path.is_absolute():
        parts = path.relative_to(ROOT / "mutants").parts if path.is_absolute() else parts[1:]
    if parts[0] != "m3t":
        return parts[0]
    return parts[1] if len(parts) > 2 else Path(parts[1]).stem


def verdicts() -> list[dict]:
    """One row per mutant from mutmut's ``.meta`` files: name, source file, module, function, status."""
    from mutmut.stats import status_by_exit_code

    rows = []
    metas = [meta for source in SOURCES for meta in sorted((ROOT / "mutants" / source).rglob("*.py.meta"))]
    for meta in metas:
        data = json.loads(meta.read_text())
        source = meta.with_suffix("")  # mutants/m3t/x/y.py
        for name, code in data["exit_code_by_key"].items():
            function = name.rsplit("__mutmut_", 1)[0]
            rows.append({"name": name, "file": str(source.relative_to(ROOT / "mutants")), "module": module_of(source),
                         "function": function, "status": status_by_exit_code[code],
                         "seconds": data.get("durations_by_key", {}).get(name)})
    if not rows:
        raise SystemExit("no mutmut results under mutants/: run `python benchmarks/mutation.py` first")
    return rows


def summary(rows: list[dict], targeted: set[str] = frozenset(), equivalent: set[str] = frozenset()) -> dict:
    """Counts per module and overall; ``detection_pct`` = (killed + timeout) / every checked mutant. With
    ``targeted`` (mutants whose survival tests were written against), also ``untargeted``: the counts over the
    mutants of the other functions, and ``targeted``: how many of ``rows`` that leaves out. ``equivalent``: the
    mutants justified as equivalent (no behaviour differs); ``score_pct`` leaves the surviving ones out of the
    rate, the mutation score as the literature defines it (detected / non-equivalent mutants)."""
    def counts(subset: list[dict]) -> dict:
        c = collections.Counter(r["status"] for r in subset)
        checked = sum(v for k, v in c.items() if k not in ("not checked", "skipped"))
        detected = sum(c[k] for k in DETECTED)
        same = sum(r["status"] in SURVIVED and r["name"] in equivalent for r in subset)
        return {"mutants": len(subset), "checked": checked, "killed": c["killed"], "timeout": c["timeout"],
                "crashed": c["segfault"], "equivalent": same,
                "score_pct": round(100.0 * detected / (checked - same), 1) if checked - same else None,
                "score_ci95": wilson(detected, checked - same),
                "detection_ci95": wilson(detected, checked),
                "survived": c["survived"], "no_tests": c["no tests"],
                "other": checked - detected - c["survived"] - c["no tests"],
                "not_checked": c["not checked"],
                "detection_pct": round(100.0 * detected / checked, 1) if checked else None,
                "detection_of_tested_pct": round(100.0 * detected / (checked - c["no tests"]), 1)
                if checked - c["no tests"] else None}

    modules = sorted({r["module"] for r in rows})
    result = {"modules": {m: counts([r for r in rows if r["module"] == m]) for m in modules}, "total": counts(rows)}
    if targeted:
        functions = {name.rsplit("__mutmut_", 1)[0] for name in targeted}
        rest = [r for r in rows if r["name"].rsplit("__mutmut_", 1)[0] not in functions]
        result.update(targeted=len(rows) - len(rest), untargeted=counts(rest))
    return result


def diff_lines(name: str, file: str) -> list[str]:
    """The changed lines of one mutant (``-`` original, ``+`` mutant), from mutmut's own diff."""
    from mutmut.mutation.diff_apply import get_diff_for_mutant

    try:
        diff = get_diff_for_mutant(name, path=Path(file))
    except Exception as exc:  # noqa: BLE001 - a report line, not a reason to stop the report
        return [f"(diff unavailable: {exc})"]
    return [line for line in diff.splitlines()
            if line[:1] in "-+" and not line.startswith(("---", "+++"))]


def earlier_runs(result: dict, out: Path) -> list[dict]:
    """The runs in ``out`` (the previous result file: its run and the earlier ones it kept) over modules the new
    ``result`` did not measure: a run drawn from some modules (``--modules``) keeps the last figures of the
    others, each with the commit, date and sample it was made on (they are not rerun)."""
    if not out.exists():
        return []
    previous = json.loads(out.read_text()).get("detail", {})
    runs = [{k: v for k, v in previous.items() if k != "earlier"}, *previous.get("earlier", [])]
    measured = set(result["modules"])
    return [run for run in runs if run.get("modules") and not set(run["modules"]) & measured]


TABLE_HEADER = ("| module | mutants | killed | timeout | crashed | survived | no tests | other | detection % (95% CI) "
                "| of tested % | equivalent | score % (95% CI) |")
# the full report (survivors with their diffs) of an earlier run whose rows a later, restricted run keeps
EARLIER_REPORTS = {"45b77c4": "Its survivors and their reasons: [mutation_core.md](mutation_core.md)."}


def drawn_from(result: dict) -> str:
    """How a sample's population was restricted, for the report: '' when it was every mutant."""
    parts = []
    if result.get("modules_drawn"):
        parts.append(f"drawn from {', '.join(result['modules_drawn'])} only")
    if result.get("excluded"):
        parts.append(f"leaving out the {result['excluded']} mutants of earlier draws (a fresh draw)")
    return f", {'; '.join(parts)}" if parts else ""


def write_report(rows: list[dict], result: dict, out_md: Path, justified: dict[str, str]) -> None:
    total = result["total"]
    lines = [
        "# Mutation testing of the library",
        "",
        f"mutmut {result['mutmut']} on commit `{result['commit']}`, {result['date']}; command: "
        "`python benchmarks/mutation.py` (configuration: `pyproject.toml` `[tool.mutmut]`).",
        f"Run time of the last run: {result['run_seconds'] / 60:.0f} min with {result['max_children']} workers"
        if result.get("run_seconds") else "Run time: not measured (report rewritten from stored verdicts).",
        "",
        "*Detected* = killed + timeout + crashed. *Detection* is over every checked mutant; *of tested* leaves out "
        "the mutants of functions no selected test calls (listed below); *score* leaves out the *equivalent* "
        "survivors, those justified below as changing no behaviour (the mutation score as the literature defines "
        "it: detected / non-equivalent mutants). Survivors that change only a message's wording or a figure's look "
        "count as undetected in both rates.",
        "",
        (f"**A seeded random sample** of {result['sample']} of the {result['population']} mutants (seed "
         f"{result['seed']}: the mutants of lowest sha256(seed:name)){drawn_from(result)}; each rate carries its "
         "Wilson 95% interval."
         if result.get("sample") else
         f"Every one of the {result['population']} mutants."),
        "",
        "| module | mutants | killed | timeout | crashed | survived | no tests | other | detection % (95% CI) "
        "| of tested % | equivalent | score % (95% CI) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    untargeted = [(f"*untargeted*: all but the {result['targeted']} mutants of functions whose survivors got new "
                   "tests", result["untargeted"])] if result.get("targeted") else []
    def rate(pct: float | None, interval: tuple[float, float] | None) -> str:
        """A rate, with its interval when the figures come from a sample."""
        return f"{pct} ({interval[0]}-{interval[1]})" if interval and result.get("sample") else f"{pct}"

    for name, c in [*result["modules"].items(), ("**all**", total), *untargeted]:
        lines.append(f"| {name} | {c['mutants']} | {c['killed']} | {c['timeout']} | {c['crashed']} | {c['survived']} "
                     f"| {c['no_tests']} "
                     f"| {c['other']} | {rate(c['detection_pct'], c['detection_ci95'])} "
                     f"| {c['detection_of_tested_pct']} "
                     f"| {c['equivalent']} | {rate(c['score_pct'], c['score_ci95'])} |")
    for run in result.get("earlier", []):
        lines += ["", (f"**Earlier run, not rerun here**: {', '.join(run['modules'])}, measured on commit "
                       f"`{run.get('commit')}` ({run.get('date')}), a sample of {run.get('sample')} of "
                       f"{run.get('population')} mutants (seed {run.get('seed')}){drawn_from(run)}; the code of those "
                       f"modules may have changed since. {EARLIER_REPORTS.get(run.get('commit'), '')}"), "",
                  TABLE_HEADER, "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for name, c in [*run["modules"].items(), ("**all**", run["total"])]:
            lines.append(f"| {name} | {c['mutants']} | {c['killed']} | {c['timeout']} | {c['crashed']} "
                         f"| {c['survived']} | {c['no_tests']} | {c['other']} "
                         f"| {c['detection_pct']} ({c['detection_ci95'][0]}-{c['detection_ci95'][1]}) "
                         f"| {c['detection_of_tested_pct']} | {c['equivalent']} "
                         f"| {c['score_pct']} ({c['score_ci95'][0]}-{c['score_ci95'][1]}) |")
    if total["not_checked"]:
        lines += ["", f"**{total['not_checked']} mutants are not checked yet** (the run was stopped): rerun the "
                  "command to finish; the numbers above count checked mutants only."]
    notes = result.get("notes", [])
    if notes:
        lines += ["", *notes]
    survivors = [r for r in rows if r["status"] in SURVIVED]
    explained = sum(r["name"] in justified for r in survivors)
    lines += ["", f"Survivors: {len(survivors)}, of which {explained} are justified below (equivalent mutants, or "
              f"only the wording of a message no test reads) and {len(survivors) - explained} are not yet: each of "
              "those is a behaviour no test checks."]
    for title, statuses in (("Survivors", SURVIVED), ("Functions no selected test calls", UNTESTED),
                            ("Other outcomes (suspicious)", None)):
        chosen = [r for r in rows if (r["status"] in statuses if statuses else
                                      r["status"] not in (*DETECTED, *SURVIVED, *UNTESTED, "not checked"))]
        lines += ["", f"## {title} ({len(chosen)})", ""]
        by_function: dict[tuple[str, str], list[dict]] = collections.defaultdict(list)
        for r in chosen:
            by_function[(r["file"], r["function"])].append(r)
        for (file, function), group in sorted(by_function.items(), key=lambda kv: (-len(kv[1]), kv[0])):
            lines.append(f"- `{file}` `{function.rsplit('.', 1)[-1].removeprefix('x_').replace('__mutmut_', '')}`: "
                         f"{len(group)}")
            if statuses == UNTESTED:
                continue
            for r in group:
                changed = [line.strip() for line in diff_lines(r["name"], r["file"])]
                text = " / ".join(changed)[:300].replace("`", "'")
                why = f" — justified: {justified[r['name']]}" if r["name"] in justified else ""
                lines.append(f"  - `{r['name'].rsplit('__mutmut_', 1)[-1]}` ({r['status']}): `{text}`{why}")
    out_md.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_md.with_suffix(".md.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, out_md)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-children", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--sample", type=int, default=0, help="test a seeded random sample of this many mutants "
                        "(0: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--modules", default="", help="draw the sample from these modules only, comma separated "
                        "(e.g. 'sgsa,slr,experiment,dashboards'; a package of m3t, a top-level module of m3t by its "
                        "name, or 'dashboards'); the report keeps an earlier run's rows of the other modules")
    parser.add_argument("--exclude-sample", action="append", default=[], help="a sample file (mutants/sample.json "
                        "of an earlier draw, copied aside) whose mutants are left out of the population: a fresh "
                        "draw, none of whose mutants a test was written against after reading the earlier draw's "
                        "survivors (repeatable: every earlier draw)")
    parser.add_argument("--retest", default="", help="also retest the sample's mutants of these statuses, comma "
                        "separated (e.g. 'survived' after adding tests, 'timeout' after changing the timeout)")
    parser.add_argument("--report-only", action="store_true", help="write the report from the stored verdicts")
    parser.add_argument("--note", action="append", default=[], help="a paragraph for the report, under the table "
                        "(repeatable; --report-only keeps the previous report's notes when none is given)")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "mutation.json"))
    args = parser.parse_args(argv)
    os.chdir(ROOT)  # mutmut works in the repository root (mutants/ beside m3t/)
    import mutmut

    seconds = None
    if not args.report_only:
        log = ROOT / "mutants" / "run.log"
        log.parent.mkdir(exist_ok=True)
        names: list[str] = []
        if args.sample:
            subprocess.run([sys.executable, "-c", GENERATE.format(children=args.max_children)], cwd=ROOT, check=True,
                           stdout=subprocess.DEVNULL)
            stored = verdicts()
            modules = sorted(m.strip() for m in args.modules.split(",") if m.strip())
            unknown = set(modules) - {r["module"] for r in stored}
            if unknown:  # a module without a function to mutate (or a misspelt one): said, not fatal
                print(f"--modules: no mutants in {sorted(unknown)}", flush=True)
            excluded = {name for file in args.exclude_sample for name in json.loads(Path(file).read_text())["names"]}
            population = sorted(r["name"] for r in stored if (not modules or r["module"] in modules)
                                and r["name"] not in excluded)
            chosen = draw(population, args.sample, args.seed)
            SAMPLE_FILE.write_text(json.dumps({"seed": args.seed, "population": len(population), "names": chosen,
                                               "modules": modules, "excluded": len(excluded)}))
            # mutmut retests every mutant it is given by name: give it the sampled ones without a verdict (new, or
            # changed since) and those of the statuses asked for
            status = {r["name"]: r["status"] for r in stored}
            again = {"not checked", *(s.strip() for s in args.retest.split(",") if s.strip())}
            names = [n for n in chosen if status[n] in again]
            if not names:
                print("every sampled mutant has a verdict; writing the report", flush=True)
        else:
            SAMPLE_FILE.unlink(missing_ok=True)
        began = time.perf_counter()
        rc = 0
        if names or not args.sample:
            print(f"mutmut run --max-children {args.max_children}"
                  f"{f' on {len(names)} sampled mutants' if names else ''} (progress in {log}) ...", flush=True)
            with open(log, "w") as fh:
                rc = subprocess.call([str(Path(sys.executable).with_name("mutmut")), "run", "--max-children",
                                      str(args.max_children), *names], stdout=fh, stderr=subprocess.STDOUT)
        seconds = round(time.perf_counter() - began, 1)
        if rc != 0:
            tail = log.read_text(errors="replace")[-3000:]
            raise SystemExit(f"mutmut run failed (exit {rc}); the end of {log}:\n{tail}")
    rows = verdicts()
    sample = json.loads(SAMPLE_FILE.read_text()) if SAMPLE_FILE.exists() else None
    population = len(rows)
    if sample:
        chosen = set(sample["names"])
        rows = [r for r in rows if r["name"] in chosen]
    targeted = set(json.loads(TARGETED_FILE.read_text())) if TARGETED_FILE.exists() else set()
    justified = json.loads(JUSTIFIED_FILE.read_text()) if JUSTIFIED_FILE.exists() else {}
    result = summary(rows, targeted, equivalents(justified))
    result.update({"population": sample["population"] if sample else population,
                   "sample": len(rows) if sample else None, "seed": sample["seed"] if sample else None,
                   "modules_drawn": sample.get("modules", []) if sample else [],
                   "excluded": sample.get("excluded", 0) if sample else 0})
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    result.update({"mutmut": mutmut.__version__, "commit": commit or "?", "date": dt.date.today().isoformat(),
                   "run_seconds": seconds, "max_children": args.max_children})
    out = Path(args.out)
    previous = json.loads(out.read_text()).get("detail", {}) if out.exists() else {}
    if seconds is None and (previous.get("seed"), previous.get("population"), previous.get("modules_drawn", [])) == (
            result["seed"], result["population"], result["modules_drawn"]):
        # --report-only over the draw the previous report measured: keep the commit, date and time of that run
        kept = ("run_seconds", "max_children", "commit", "date", "notes")
        result.update({k: previous.get(k) for k in kept if previous.get(k)})
    if args.note:
        result["notes"] = list(args.note)
    result["earlier"] = earlier_runs(result, out)
    write_report(rows, result, out.with_suffix(".md"), justified)
    from report import write_and_log

    flat = {"detection_pct": result["total"]["detection_pct"], "score_pct": result["total"]["score_pct"],
            "mutants": result["total"]["mutants"],
            "survived": result["total"]["survived"], "no_tests": result["total"]["no_tests"],
            "run_seconds": result["run_seconds"]}
    flat.update({f"{m}_detection_pct": c["detection_pct"] for m, c in result["modules"].items()})
    if result.get("targeted"):
        flat["untargeted_detection_pct"] = result["untargeted"]["detection_pct"]
    write_and_log({**flat, "detail": result}, out, "bench-mutation")
    return result


if __name__ == "__main__":
    main()
