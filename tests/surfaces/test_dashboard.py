"""The static dashboard: on an empty store it says what to run; on a tiny pipeline's store its tables hold the
MLflow metrics, its plots and videos are there, and the run picker compares runs."""
from __future__ import annotations

import json
import re
from pathlib import Path

from dashboards.build import build_dashboard
from dashboards.html import PAGES, markdown
from m3t.claims.definitions import CLAIMS
from m3t.config import load_params
from m3t.experiment import fetch_runs

ROOT = Path(__file__).resolve().parents[2]


def test_an_empty_store_shows_what_to_run(tmp_path):
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "experiment": {"tracking_uri": f"sqlite:///{tmp_path / 'empty.db'}", "artifact_dir": str(tmp_path / "a")},
        "data": {"shards_root": str(tmp_path / "shards")}})
    index = build_dashboard(params, tmp_path / "site")
    pages = {name: (index.parent / name).read_text() for name, _ in PAGES}
    assert "No runs in the MLflow store yet" in pages["index.html"] and "dvc repro" in pages["index.html"]
    assert "no finished evaluate-smlm runs yet" in pages["tables.html"]
    assert "Not fitted yet" in pages["quality.html"] and "No rendered video yet" in pages["videos.html"]
    assert pages["claims.html"].count("not run: no ") == len(CLAIMS)  # each claim says which stage to run
    assert all("Traceback" not in text for text in pages.values())
    assert (index.parent / "assets" / "plotly.min.js").stat().st_size > 1_000_000  # from the wheel, no CDN
    assert not list(tmp_path.glob("site.*"))  # built aside and renamed: no leftover folder


def test_markdown_tables_become_html_tables():
    text = "Title line\n\n| a | b |\n|---|---|\n| x | 1.50 |\n\n- a note"
    out = markdown(text, "t")
    assert '<table id="t">' in out and "<th>a</th>" in out and "<td class=num>1.50</td>" in out
    assert "<p class=note>Title line</p>" in out and "<li>a note</li>" in out


def _table(page: str, table_id: str) -> list[list[str]]:
    """Rows (header first) of the table with ``table_id``: cell texts."""
    found = re.search(rf'<table id="{table_id}">(.*?)</table>', page, re.S)
    assert found, f"no table {table_id}"
    rows = re.findall(r"<tr>(.*?)</tr>", found.group(1), re.S)
    return [[re.sub(r"<[^>]+>", "", c) for c in re.findall(r"<t[hd][^>]*>(.*?)</t[hd]>", r, re.S)] for r in rows]


def test_a_tiny_pipeline_fills_the_pages(tiny_workspace, tmp_path):
    params = tiny_workspace.params
    index = build_dashboard(params, tmp_path / "site")
    site = index.parent
    runs = fetch_runs(params.experiment)
    smlm = next(r for r in runs if r.stage == "evaluate-smlm")
    rows = _table((site / "tables.html").read_text(), "m3t-tab1-measured")
    header, values = rows[0], {r[0]: r for r in rows[1:]}
    row = values[smlm.tags["variant"]]
    column = header.index("synthetic/ASL-SYN PA body")
    assert row[column] == f"{smlm.metrics['synthetic/ASL-SYN/dtw_pa_jpe_body_m']:.3f}"
    tokenizers = next(r for r in runs if r.stage == "train-tokenizers")
    tab3 = _table((site / "tables.html").read_text(), "m3t-tab3-measured")
    assert tab3[1][tab3[0].index("util face %")] == f"{tokenizers.metrics['face/utilisation_pct']:.1f}"
    curves = (site / "curves.html").read_text()
    assert "train_loss" in curves and 'src="assets/plotly.min.js"' in curves
    codebooks = (site / "codebooks.html").read_text()
    assert 'id="utilisation"' in codebooks and 'id="tokens-face"' in codebooks
    quality = (site / "quality.html").read_text()
    assert "Not fitted yet" in quality  # the workspace's shards were written directly, without fit-corpus
    picker = json.loads(re.search(r'<script type="application/json" id="run-data">(.*?)</script>',
                                  (site / "runs.html").read_text(), re.S).group(1))
    assert set(picker) == {r.run_id for r in runs} and picker[smlm.run_id]["metrics"] == smlm.metrics


def test_the_repeatability_table_counts_the_digits_two_arithmetics_share(tmp_path):
    from dashboards.sections.claims import repeatability
    from m3t.metrics.stats import agreeing_digits

    assert agreeing_digits(1.23456, 1.23457) == 5 and agreeing_digits(2.0, 3.0) == 0
    assert agreeing_digits(0.5, 0.5) == 15 and agreeing_digits(float("nan"), 1.0) is None
    path = tmp_path / "reproducible.json"
    assert "bench_reproducible.py" in repeatability(path)  # nothing measured: says what to run
    path.write_text(json.dumps({"machine": "x86_64", "cpu_count": 2, "cost": 1.4, "stages": {"train-slr": {
        "figures": {"full/best_dev_loss": {"old": 1.27664, "new": 1.27671}, "face/best_vpe": {"old": 3.0, "new": 3.0}}}}}))
    page = repeatability(path)
    assert ("<td>full/best_dev_loss</td><td class=num>1.27664</td><td class=num>1.27671</td><td class=num>4</td>"
            in page)
    assert "<td>face/best_vpe</td><td class=num>3</td><td class=num>3</td><td>all</td>" in page and "1.40x" in page


def test_a_saved_study_shows_its_judged_claims_with_the_seed_halves_that_flip(tmp_path):
    from dashboards.sections.claims import saved_claims

    row = {"key": "k", "claim": "FSQ uses more codes", "source": "M3T Tab. 3", "paper": "67 -> 96", "metric": "util",
           "a": "VQ", "b": "FSQ", "mean_a": 97.4, "std_a": 1.6, "mean_b": 93.6, "std_b": 2.4, "compared": "B - A",
           "value": -3.8, "interval95": [-7.0, 0.0], "verdict": "inconclusive", "note": "", "seeds": ["0", "1", "2"],
           "runs_a": ["aaaaaaaaaa"], "runs_b": ["bbbbbbbbbb"],
           "halves": {"seeds": [["0"], ["1", "2"]], "verdicts": ["not reproduced", "inconclusive"]}}
    missing = {**row, "key": "m", "claim": "the SMLM claim", "verdict": "not run", "note": "run it", "seeds": []}
    path = tmp_path / "claims.json"
    path.write_text(json.dumps({"claims": [row, missing]}))
    page = saved_claims(path, "Tab. 3 study", "m3t study")
    assert "FSQ uses more codes" in page and "the SMLM claim" not in page  # judged rows only
    assert "seed halves: not reproduced / inconclusive" in page and "1 of 1 claims flip" in page
    assert "m3t study" in saved_claims(tmp_path / "none.json", "Tab. 3 study", "m3t study")
