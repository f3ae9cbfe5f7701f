"""The documentation site: it builds under ``mkdocs build --strict`` and its generated pages are current.

The results pages and the home page are generated (``m3t docs-pages``, :mod:`dashboards.docs_pages`) from the
tracked metrics files and the README; a committed page that differs from what the generator writes now means a
figure was typed by hand or a metrics file changed without the pages being regenerated.
"""
from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from dashboards import docs_pages

ROOT = Path(__file__).resolve().parents[2]


def _without_provenance(text: str) -> str:
    """The page minus its provenance line, which names the current dvc.lock commit (it moves with every commit
    that changes the lock, not with the figures)."""
    return "\n".join(line for line in text.splitlines() if not line.startswith(docs_pages.PROVENANCE_PREFIX))


@pytest.mark.parametrize("page", sorted(docs_pages.pages(ROOT)))
def test_generated_pages_are_current(page):
    committed = ROOT / "docs" / page
    assert committed.exists(), f"docs/{page} is missing: run `m3t docs-pages`"
    expected = docs_pages.pages(ROOT)[page]
    assert _without_provenance(committed.read_text(encoding="utf-8")) == _without_provenance(expected), (
        f"docs/{page} differs from what `m3t docs-pages` generates from the metrics files and the README now: "
        "run `m3t docs-pages` and commit the result (never edit a generated page by hand)")


def test_every_results_page_names_the_dvc_lock_commit_it_comes_from():
    for page in ("results/embedded.md", "results/claims.md"):
        text = (ROOT / "docs" / page).read_text(encoding="utf-8")
        line = next(line for line in text.splitlines() if line.startswith(docs_pages.PROVENANCE_PREFIX))
        assert "`dvc.lock`" in line and "do not edit by hand" in line


def test_a_missing_metrics_file_names_the_stage_that_makes_it(tmp_path):
    (tmp_path / "README.md").write_text("# t\n", encoding="utf-8")
    pages = docs_pages.pages(tmp_path)
    assert "`metrics/smlm/metrics.json` is missing; run `dvc repro evaluate-smlm`" in pages["results/embedded.md"]
    assert "`models/tokenizers/metrics.json` is missing; run `dvc repro train-tokenizers`" in pages[
        "results/embedded.md"]
    assert "Not run yet: `metrics/study/claims.json` is missing" in pages["results/claims.md"]


def _claim(verdict: str, halves: list[str] | None, **extra) -> dict:
    row = {"claim": "B beats A", "source": "M3T Tab. 1", "paper": "5 -> 4", "metric": "DTW-JPE (m)", "a": "A",
           "b": "B", "mean_a": 5.0, "std_a": 0.5, "mean_b": 4.0, "std_b": 0.25, "value": -1.0,
           "interval95": [-1.5, -0.5], "band": None, "verdict": verdict, "note": "", "seeds": ["0", "1", "2", "3"],
           "halves": None if halves is None else {"seeds": [["0", "1"], ["2", "3"]], "verdicts": halves}}
    row.update(extra)
    return row


def test_the_claims_section_counts_verdicts_and_marks_the_flipped_ones(tmp_path):
    rows = [_claim("reproduced", ["reproduced", "reproduced"]),
            _claim("inconclusive", ["reproduced", "inconclusive"], claim="C | D"),
            _claim("not run", None, note="run `m3t study`", seeds=[])]
    (tmp_path / "metrics" / "study").mkdir(parents=True)
    (tmp_path / "metrics" / "study" / "claims.json").write_text(json.dumps(
        {"min_seeds": 3, "claims": rows, "stability": {"compared": 2, "flipped": 1}}), encoding="utf-8")
    text = docs_pages.claims_section(tmp_path, "metrics/study/claims.json", "Study", "`m3t study`")
    assert "2 claims judged: 1 reproduced, 0 not reproduced, 1 inconclusive; 1 of 2 flip" in text
    assert "| -1 [-1.5, -0.5] | reproduced | 4 | same ({0, 1} / {2, 3}) |" in text
    assert "**flips**: reproduced / inconclusive" in text
    assert "C \\| D" in text  # a "|" inside a cell cannot split the row
    assert "| not run (run `m3t study`) | 0 | - |" in text


def test_the_home_page_is_the_readme_with_links_relative_to_docs(tmp_path):
    (tmp_path / "README.md").write_text(
        "# X: 3D sign language production, reproduced end to end\n\nSee [Install](docs/install.md) and "
        "[CONTRIBUTING](CONTRIBUTING.md).\n\n## Repository map\n\nm3t/ ...\n\n## Documentation\n\nlist\n\n"
        "## Licences\n\nApache\n", encoding="utf-8")
    home = docs_pages.home_page(tmp_path)
    assert home.startswith("# X\n")
    assert "[Install](install.md)" in home and "`CONTRIBUTING.md`" in home
    assert "Repository map" not in home and "## Documentation" not in home and "## Licences\n\nApache" in home


@pytest.mark.slow
def test_the_site_builds_in_strict_mode(tmp_path):
    """Every page in the navigation exists, every link and anchor resolves, every API page's module is found."""
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocstrings") is None:
        pytest.skip("MkDocs is not installed: `pip install -e '.[docs]'` (`bash .ci/install` does it)")
    mkdocs = shutil.which("mkdocs", path=str(Path(sys.executable).parent)) or "mkdocs"
    env = {"NO_MKDOCS_2_WARNING": "1", "PATH": str(Path(sys.executable).parent) + ":/usr/bin:/bin"}
    done = subprocess.run([mkdocs, "build", "--strict", "-d", str(tmp_path / "site")],  # noqa: S603
                          cwd=ROOT, check=False, capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-6000:]
    assert (tmp_path / "site" / "results" / "claims" / "index.html").exists()
    assert (tmp_path / "site" / "api" / "scoring" / "index.html").exists()
