"""The dashboard in headless Chromium, built over a tiny pipeline's MLflow store: every page loads from disk with
no failed request and no console error, the paper tables hold the MLflow metrics, the plots are drawn, the videos
load their metadata, and the run picker compares ticked runs. Screenshots land in the test artifacts folder."""
from __future__ import annotations

import pytest

from browser import browser  # noqa: F401 - the fixture
from dashboards.build import build_dashboard
from dashboards.html import PAGES
from m3t.experiment import fetch_runs

CELL = """(([id, row, column]) => {
  const table = document.getElementById(id);
  const header = [...table.querySelectorAll('thead th')].map(th => th.textContent);
  const tr = [...table.querySelectorAll('tbody tr')].find(tr => tr.cells[0].textContent === row);
  return tr ? tr.cells[header.indexOf(column)].textContent : null;
})"""


@pytest.fixture(scope="module")
def site(tiny_workspace, tmp_path_factory):
    return build_dashboard(tiny_workspace.params, tmp_path_factory.mktemp("dashboard") / "site").parent


def cell(page, table_id: str, row: str, column: str) -> str | None:
    return page.evaluate(f"{CELL}({[table_id, row, column]!r})")


def test_every_page_loads_clean(browser, site):  # noqa: F811
    for name, title in PAGES:
        browser.clear()
        browser.goto((site / name).as_uri())
        assert browser.evaluate("document.querySelector('nav a.here').textContent") == title
        browser.screenshot(f"dashboard-{name.removesuffix('.html')}.png", full_page=True)
        assert browser.console_errors == [], (name, browser.console_errors)
        assert browser.failed_requests == [], (name, browser.failed_requests)


def test_tables_hold_the_mlflow_metrics(browser, site, tiny_workspace):  # noqa: F811
    runs = fetch_runs(tiny_workspace.params.experiment)
    smlm = next(r for r in runs if r.stage == "evaluate-smlm")
    tokenizers = next(r for r in runs if r.stage == "train-tokenizers")
    browser.goto((site / "tables.html").as_uri())
    for key, column in (("dtw_pa_jpe_body_m", "PA body"), ("dtw_jpe_hand_m", "JPE hand")):
        shown = cell(browser, "m3t-tab1-measured", smlm.tags["variant"], f"synthetic/ASL-SYN {column}")
        assert shown == f"{smlm.metrics[f'synthetic/ASL-SYN/{key}']:.3f}"
    for group in ("body", "hand", "face"):
        shown = cell(browser, "m3t-tab3-measured", "FSQ", f"util {group} %")
        assert shown == f"{tokenizers.metrics[f'{group}/utilisation_pct']:.1f}"
    assert browser.console_errors == []


def test_plots_are_drawn_and_videos_load(browser, site):  # noqa: F811
    browser.goto((site / "codebooks.html").as_uri())
    browser.wait_for("document.querySelectorAll('#utilisation .main-svg').length > 0", timeout=20)
    bars = browser.evaluate("document.getElementById('utilisation').data.length")
    assert bars == 1  # one quantizer (FSQ) in the tiny store
    browser.goto((site / "curves.html").as_uri())
    browser.wait_for("document.querySelectorAll('.plotly-graph-div .main-svg').length > 0", timeout=20)
    browser.goto((site / "videos.html").as_uri())
    assert browser.evaluate("document.querySelectorAll('video').length") >= 2  # mesh + skeleton of a test clip
    browser.wait_for("[...document.querySelectorAll('video')].every(v => v.readyState >= 1)", timeout=30)
    sizes = browser.evaluate("[...document.querySelectorAll('video')].map(v => [v.videoWidth, v.duration])")
    assert all(w > 0 and d > 0 for w, d in sizes), sizes
    browser.screenshot("dashboard-videos-loaded.png", full_page=True)
    assert browser.console_errors == [] and browser.failed_requests == []


def test_run_picker_filters_and_compares(browser, site, tiny_workspace):  # noqa: F811
    runs = fetch_runs(tiny_workspace.params.experiment)
    browser.goto((site / "runs.html").as_uri())
    browser.evaluate("(() => { const s = document.getElementById('stage'); s.value = 'evaluate-smlm';"
                     " s.dispatchEvent(new Event('change')); })()")
    assert browser.evaluate("document.getElementById('shown').textContent") == str(
        sum(r.stage == "evaluate-smlm" for r in runs))
    browser.evaluate("(() => { const s = document.getElementById('stage'); s.value = '';"
                     " s.dispatchEvent(new Event('change')); "
                     "[...document.querySelectorAll('#runs input.pick')].slice(0, 2).forEach(b => b.click());"
                     " document.getElementById('compare-button').click(); })()")
    header = browser.evaluate("[...document.querySelectorAll('#compare-table thead th')].map(t => t.textContent)")
    assert header[1:] == [r.tags["mlflow.runName"] for r in runs[:2]]
    first_metric = sorted(runs[0].metrics)[0]
    row = browser.evaluate(f"[...document.querySelectorAll('#compare-table tbody tr')].map(r => r.cells[0].textContent)"
                           f".indexOf({first_metric!r})")
    assert row >= 0
    assert browser.console_errors == []
