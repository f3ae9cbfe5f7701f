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
    assert index == tmp_path / "site" / "index.html"  # the folder asked for, not experiment.dashboard_dir
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


def test_consecutive_markdown_items_make_one_list():
    """The notes under a table (``m3t ...-table`` output) are one list, however many; a paragraph or a table row
    between items starts a new one."""
    assert markdown("- a\n- b\n- c") == "<ul class=note><li>a</li><li>b</li><li>c</li></ul>"
    assert markdown("- a\ntext\n- b\n| x |\n|---|\n| 1 |\n- c", "t") == (
        "<ul class=note><li>a</li></ul><p class=note>text</p><ul class=note><li>b</li></ul>"
        '<table id="t"><thead><tr><th>x</th></tr></thead><tbody><tr><td class=num>1</td></tr></tbody></table>'
        "<ul class=note><li>c</li></ul>")


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
    assert '<table id="claims">' in page  # the judged rows' table, by its id
    assert saved_claims(tmp_path / "none.json", "Tab. 3 study", "m3t study").startswith(
        "<h2>Tab. 3 study</h2>") and "Not run yet: <code>m3t study</code>" in saved_claims(
        tmp_path / "none.json", "Tab. 3 study", "m3t study")


# ---- the documentation's generated pages (dashboards.docs_pages) from hand-made metrics files: each cell below is
# the metrics value written as the page writes it (3 significant digits, "-" when missing), worked out by hand.
# tests/project/test_docs.py checks the committed pages against the repository's own files.
def _write_json(root: Path, rel: str, data: dict) -> None:
    (root / rel).parent.mkdir(parents=True, exist_ok=True)
    (root / rel).write_text(json.dumps(data), encoding="utf-8")


def _rows(text: str, first: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith(f"| {first}")]


def test_docs_pages_small_helpers():
    from dashboards import docs_pages

    assert docs_pages.pct(None) == "-" and docs_pages.pct(0.1234) == "12.3 %" and docs_pages.pct(1) == "100.0 %"
    assert docs_pages.page_table(["a", "b"], [["x|y", 1]]) == "| a | b |\n|---|---|\n| x\\|y | 1 |\n"
    assert docs_pages._halves({"halves": None}) == "-"
    assert docs_pages._halves({"halves": {"seeds": [["0", "1"], ["2"]], "verdicts": ["reproduced"] * 2}}) == (
        "same ({0, 1} / {2})")
    assert docs_pages._halves({"halves": {"seeds": [["0"], ["1"]], "verdicts": ["reproduced", "inconclusive"]}}) == (
        "**flips**: reproduced / inconclusive ({0} / {1})")


def test_an_empty_root_names_the_stage_of_every_missing_figure(tmp_path):
    from dashboards import docs_pages

    page = docs_pages.embedded_page(tmp_path)
    for rel, stage in (("data/shards/synthetic/summary.json", "fit-corpus"),
                       ("data/shards/fingerspelling/summary.json", "fit-corpus"),
                       ("models/tokenizers/metrics.json", "train-tokenizers"), ("metrics/smlm/metrics.json", "evaluate-smlm"),
                       ("metrics/backtranslation/metrics.json", "evaluate-backtranslation"),
                       ("metrics/sgsa/metrics.json", "evaluate-sgsa"), ("metrics/slr/table.md", "evaluate-slr")):
        assert f"*Not measured yet: `{rel}` is missing; run `dvc repro {stage}`.*" in page
    assert "the synthetic corpus (its test split, one seed)" in page
    assert "from an uncommitted `dvc.lock` (no git history here); do not edit by hand. Sources: ." in page
    claims = docs_pages.claims_page(tmp_path)
    assert "*Not run yet: `metrics/study/claims.json` is missing. Command: `m3t study`" in claims
    assert "*Not run yet: `metrics/tab3/table.md` is missing;" in claims


def test_the_fitting_and_tokenizer_sections_by_hand(tmp_path):
    from dashboards import docs_pages

    _write_json(tmp_path, "data/shards/synthetic/summary.json", {
        "clips_fitted": 3, "clips_total": 4, "frames": 120, "reproj_px_mean": 1.5, "reproj_px_median": 1.25,
        "joint_mm_mean": 12.345, "pa_joint_mm_mean": 8.0, "init_pa_joint_mm_mean": 20.0, "body_deg_mean": 3.0,
        "right_hand_deg_mean": 4.5, "face_abs_mean": 0.1})
    _write_json(tmp_path, "data/shards/fingerspelling/summary.json", {
        "clips_fitted": 2, "clips_total": 2, "frames": 50, "reproj_px_mean": 2.0, "reproj_px_median": 1.0})
    fitting = docs_pages.fitting_section(tmp_path)
    assert _rows(fitting, "synthetic") == [
        "| synthetic (ground truth) | 3 / 4 | 120 | 1.5 / 1.25 | 12.3 | 8 | 20 | 3 / 4.5 | 0.1 |"]
    assert _rows(fitting, "fingerspelling") == [
        "| fingerspelling (real `.pose`) | 2 / 2 | 50 | 2 / 1 | - | - | - | - / - | - |"]
    assert "| corpus | clips fitted / listed | frames |" in fitting and "Not measured" not in fitting
    _write_json(tmp_path, "models/tokenizers/metrics.json", {"hand": {
        "codebook_size": 512, "test_pa_vpe_mm": 10.0, "test_vpe_mm": 20.5, "utilisation_pct": 50.0,
        "perplexity_per_code": 0.5, "tokens_per_code": 2.0, "count_sd": 3.0, "all_splits_utilisation_pct": 60.25,
        "all_splits_tokens_per_code": 4.0}})
    tokenizers = docs_pages.tokenizer_section(tmp_path)
    assert _rows(tokenizers, "hand") == ["| hand | 512 | 10 | 20.5 | 50.0 % | 0.5 | 2 | 3 | 60.2 % | 4 |"]
    assert not _rows(tokenizers, "body") and not _rows(tokenizers, "face")  # only the groups trained


def test_the_smlm_backtranslation_sgsa_and_slr_sections_by_hand(tmp_path):
    from dashboards import docs_pages

    _write_json(tmp_path, "metrics/smlm/metrics.json", {
        "dtw_jpe_body_m": 1.5, "dtw_pa_jpe_body_m": 0.75, "dtw_jpe_body_pathnorm_m": 0.01,
        "dtw_pa_jpe_body_pathnorm_m": 0.005, "dtw_jpe_hand_m": 2.0, "dtw_vpe_face_m": 0.25,
        "clips_scored": 7, "clips_cut": 1, "empty_rate": 0.0, "stopped_rate": 0.5,
        "translation/ASL-SYN/bleu4": 12.5, "bt/slt/ASL-SYN/rouge_l": 30.0, "bt/slt/ASL-SYN/bleu4": 4.0,
        "bt/slt/ASL-SYN/sentences": 3})
    smlm = docs_pages.smlm_section(tmp_path)
    assert _rows(smlm, "body") == ["| body | 1.5 | 0.75 | 0.01 | 0.005 |"]
    assert _rows(smlm, "hands") == ["| hands | 2 | - | - | - |"] and _rows(smlm, "face") == ["| face (DTW-VPE) | 0.25 | - | - | - |"]
    assert "Clips scored: 7 (cut to the model's limits: 1; empty generations: 0.0 %; ended by EOS: 50.0 %)." in smlm
    assert _rows(smlm, "ASL-SYN") == ["| ASL-SYN | 12.5 | 30 | 4 | 3 |"] and _rows(smlm, "DGS-SYN") == [
        "| DGS-SYN | - | - | - | - |"]
    _write_json(tmp_path, "metrics/backtranslation/metrics.json", {
        "slt/CSL-SYN/rouge_l": 41.0, "slt/CSL-SYN/bleu1": 33.3333, "slt/CSL-SYN/bleu4": 9.0, "slt/CSL-SYN/sentences": 1})
    bt = docs_pages.backtranslation_section(tmp_path)
    assert _rows(bt, "CSL-SYN") == ["| CSL-SYN | 41 | 33.3 | 9 | 1 |"] and _rows(bt, "ASL-SYN") == [
        "| ASL-SYN | - | - | - | - |"]
    _write_json(tmp_path, "metrics/sgsa/metrics.json", {
        "pt/test/dtw_jpe_mean_m": 0.012, "pt/test/dtw_jpe_body_pathnorm_m": 0.0005,
        "pt/test/dtw_jpe_hand_pathnorm_m": 0.00025, "pt/test/length_ratio_median": 1.05,
        "pt/test/length_within_25": 0.75, "pt/test/stopped_rate": 1.0, "pt/test/bt/slt_rouge_l": 22.0,
        "pt/test/bt/slt_bleu4": 3.0, "pt/dev/dtw_jpe_mean_m": 9.0,
        "smlm/test/dtw_jpe_mean_m": 0.02, "ground_truth/test/bt/slt_rouge_l": 50.0})
    sgsa = docs_pages.sgsa_section(tmp_path)
    assert _rows(sgsa, "Progressive") == ["| Progressive Transformers | 12 | 0.5 / 0.25 | 1.05 / 75.0 % / 100.0 % | 22 | 3 |"]
    assert _rows(sgsa, "M3T SMLM") == ["| M3T SMLM | 20 | - | ends by EOS | - | - |"]
    assert _rows(sgsa, "ground-truth") == ["| ground-truth motion | - | - | - | 50 | - |"]
    assert not _rows(sgsa, "SGSA")  # a system without test figures has no row
    (tmp_path / "metrics" / "slr").mkdir(parents=True)
    (tmp_path / "metrics" / "slr" / "table.md").write_text("| Method | T-1 |\n", encoding="utf-8")
    assert docs_pages.slr_section(tmp_path) == "## Recognition probe (`evaluate-slr`, M3T Tab. 4)\n\n| Method | T-1 |\n"
    page = docs_pages.embedded_page(tmp_path)
    assert "the synthetic corpus (7 test clips, one seed)" in page
    assert ("Sources: `metrics/smlm/metrics.json`, `metrics/backtranslation/metrics.json`, `metrics/sgsa/metrics.json`, "
            "`metrics/slr/table.md`.") in page


def test_the_claims_page_counts_verdicts_and_tab3_is_copied(tmp_path):
    from dashboards import docs_pages

    row = {"claim": "B beats A", "source": "S", "paper": "5 -> 4", "metric": "m", "a": "A", "b": "B", "mean_a": 5.0,
           "std_a": 0.5, "mean_b": 4.0, "std_b": 0.25, "value": -1.0, "interval95": [-1.5, -0.5], "band": None,
           "verdict": "not reproduced", "note": "2 seed(s) < 3", "seeds": ["0", "1"], "halves": None}
    _write_json(tmp_path, "metrics/study/claims.json", {"min_seeds": 3, "claims": [row, {**row, "verdict": "reproduced",
                                                                                        "note": ""}]})
    text = docs_pages.claims_page(tmp_path)
    assert "2 claims judged: 1 reproduced, 1 not reproduced, 0 inconclusive. Verdicts need at least 3 seeds." in text
    assert "| A 5 +- 0.5 -> B 4 +- 0.25 | -1 [-1.5, -0.5] | not reproduced (2 seed(s) < 3) | 2 | - |" in text
    (tmp_path / "metrics" / "tab3").mkdir(parents=True)
    (tmp_path / "metrics" / "tab3" / "table.md").write_text("| Q | BS |\n", encoding="utf-8")
    text = docs_pages.claims_page(tmp_path)
    assert text.endswith("(utilisation can be read where it is well above 1).\n\n| Q | BS |\n")
    assert "Sources: `metrics/study/claims.json`, `metrics/tab3/table.md`." in text
    (tmp_path / "README.md").write_text("# M: 3D sign language production, reproduced end to end\n\nSee "
                                        "[a](docs/a.md).\n\n## Documentation\n\nx\n", encoding="utf-8")
    written = docs_pages.write_pages(tmp_path, tmp_path / "out")
    assert sorted(p.relative_to(tmp_path / "out").as_posix() for p in written) == [
        "index.md", "results/claims.md", "results/embedded.md"]
    assert (tmp_path / "out" / "index.md").read_text(encoding="utf-8") == "# M\n\nSee [a](a.md).\n\n"


def test_the_docs_pages_command_writes_the_pages_where_asked(tmp_path, capsys):
    from dashboards import docs_pages

    (tmp_path / "README.md").write_text("# R\n", encoding="utf-8")
    docs_pages.main(["--root", str(tmp_path), "--out", str(tmp_path / "site-docs")])
    printed = capsys.readouterr().out.splitlines()
    assert sorted(Path(p).relative_to(tmp_path / "site-docs").as_posix() for p in printed) == [
        "index.md", "results/claims.md", "results/embedded.md"]
    assert (tmp_path / "site-docs" / "index.md").read_text(encoding="utf-8") == "# R\n"


def test_a_figure_becomes_an_html_fragment_of_the_dashboards_size():
    import plotly.graph_objects as go

    from dashboards.sections.common import figure_html

    fig = go.Figure(go.Scatter(x=[0, 1], y=[1, 2]))
    html = figure_html(fig, "curve-1", width=300)
    assert 'id="curve-1"' in html and "<html" not in html and "plotly.min.js" not in html
    assert (fig.layout.width, fig.layout.height) == (300, 320)
    assert (fig.layout.margin.l, fig.layout.margin.r, fig.layout.margin.t, fig.layout.margin.b) == (50, 20, 40, 40)
    assert fig.layout.template.layout.plot_bgcolor == "white"  # plotly_white


def test_a_claim_not_run_shows_no_figures_and_the_pages_go_to_docs_by_default(tmp_path):
    from dashboards import docs_pages

    row = {"claim": "C", "source": "S", "paper": "p", "metric": "m", "a": "A", "b": "B", "verdict": "not run",
           "note": "run `m3t study`", "seeds": []}
    _write_json(tmp_path, "metrics/study/claims.json", {"min_seeds": 3, "claims": [row]})
    text = docs_pages.claims_section(tmp_path, "metrics/study/claims.json", "Study", "`m3t study`")
    assert "| C | S | p | m | - | - | not run (run `m3t study`) | 0 | - |" in text
    assert "0 claims judged: 0 reproduced, 0 not reproduced, 0 inconclusive. Verdicts need at least 3 seeds." in text
    (tmp_path / "README.md").write_text("# R\n", encoding="utf-8")
    written = docs_pages.write_pages(tmp_path)
    assert sorted(p.relative_to(tmp_path / "docs").as_posix() for p in written) == [
        "index.md", "results/claims.md", "results/embedded.md"]


def test_the_videos_page_shows_the_newest_finished_runs_videos_grouped_by_clip(tmp_path):
    from dashboards.sections.videos import videos
    from m3t.experiment import RunRecord

    def run(run_id, stage, status, files):
        folder = tmp_path / run_id
        for name in files:
            (folder / "renders").mkdir(parents=True, exist_ok=True)
            (folder / "renders" / name).write_bytes(run_id.encode())
        return RunRecord(run_id, stage, 0, status, {}, {}, folder, {"mlflow.runName": f"{stage} {run_id}"})

    runs = [run("failed", "evaluate-smlm", "FAILED", ["c1.mp4"]), run("none", "evaluate-smlm", "FINISHED", []),
            run("new", "evaluate-smlm", "FINISHED", ["c1.mp4", "c1_skeleton.mp4"]),
            run("old", "evaluate-smlm", "FINISHED", ["c0.mp4"]), run("sg", "evaluate-sgsa", "FINISHED", ["c1.mp4"])]
    page = videos(runs, tmp_path / "site" / "media")
    assert page.count("<h2>") == 1 and "<h2>c1</h2>" in page  # the old run's clip is not shown
    assert ('src="media/evaluate-smlm/c1.mp4"></video><figcaption>SMLM, body surface (evaluate-smlm new)'
            '</figcaption>') in page
    assert 'src="media/evaluate-smlm/c1_skeleton.mp4"></video><figcaption>SMLM, skeleton (evaluate-smlm new)' in page
    assert 'src="media/evaluate-sgsa/c1.mp4"></video><figcaption>PT / SGSA / SMLM, skeletons (evaluate-sgsa sg)' in page
    assert (tmp_path / "site" / "media" / "evaluate-smlm" / "c1.mp4").read_bytes() == b"new"  # copied beside the page
    assert "No rendered video yet" in videos([], tmp_path / "m")


def test_the_codebooks_page_compares_the_newest_run_of_each_quantizer(tmp_path):
    """Stored runs made by hand: two quantizers (an older FSQ run that must not show), their utilisation
    bars, the statistics table and a token-frequency figure per group that has token counts."""
    from dashboards.sections.codebooks import codebooks
    from m3t.experiment import RunRecord

    def run(run_id, quantizer, start, util, groups=("body", "hand")):
        folder = tmp_path / run_id / "plots"
        folder.mkdir(parents=True)
        for i, group in enumerate(groups):
            (folder / f"tokens_{group}.json").write_text(json.dumps(
                {"group": group, "counts": [5, 1, 0, 3 + i], "codebook_size": 4}))
        metrics = {f"{g}/utilisation_pct": util for g in ("body", "hand", "face")} | {"body/tokens_per_code": 2.25}
        return RunRecord(run_id, "train-tokenizers", start, "FINISHED", {}, metrics, folder.parent,
                         {"quantizer": quantizer})

    params = load_params(ROOT / "params.yaml")
    page = codebooks([run("new-fsq", "fsq", 3, 75.0), run("vq", "vq", 2, 50.0, ("body",)),
                      run("old-fsq", "fsq", 1, 10.0)], params)
    assert 'id="utilisation"' in page and 'id="tokens-body"' in page and 'id="tokens-hand"' in page
    assert 'id="tokens-face"' not in page  # no run counted face tokens
    rows = _table(page, "codebook-stats")
    assert rows[0] == ["quantizer", "group", "util %", "perplexity / K", "count SD", "tokens / K"]
    assert [r[:3] for r in rows[1:]] == [["FSQ", "body", "75.0"], ["FSQ", "hand", "75.0"], ["FSQ", "face", "75.0"],
                                         ["VQ", "body", "50.0"], ["VQ", "hand", "50.0"], ["VQ", "face", "50.0"]]
    assert rows[1][5] == "2.2" or rows[1][5] == "2.3"  # tokens per code at one digit (2.25: either rounding)
    assert "Only one quantizer" not in page
    alone = codebooks([run("single", "fsq", 4, 60.0)], params)
    assert "Only one quantizer" in alone and "FSQ (4 codes)" in alone
    assert "No tokenizer run yet" in codebooks([], params)


def test_every_paper_table_has_its_anchor_and_the_measured_tables_their_ids():
    from dashboards.sections.tables import paper_tables

    page = paper_tables([])
    anchors = re.findall(r'<h2 id="([^"]+)">', page)
    assert anchors == ["m3t-tab1", "m3t-tab2", "m3t-tab3", "m3t-tab4", "sgsa-tab1", "sgsa-tab2", "sgsa-tab3"]
    # with no runs, the tables whose layout is fixed still show it, under <anchor>-measured
    assert re.findall(r'<table id="([^"]+)"', page) == ["m3t-tab3-measured", "sgsa-tab1-measured",
                                                        "sgsa-tab2-measured"]


def _record(run_id: str, stage: str, start: int, status: str = "FINISHED", **tags):
    from m3t.experiment import RunRecord

    return RunRecord(run_id, stage, start, status, {"p": run_id}, {"m": 1.0}, None,
                     {"mlflow.runName": f"{stage} {run_id}", **tags})


def test_the_overview_counts_runs_per_stage_and_names_the_newest():
    from dashboards.sections.runs import overview

    params = load_params(ROOT / "params.yaml")
    runs = [_record("c3", "train-smlm", 3_000_000, "FAILED"), _record("b2", "train-smlm", 2_000_000, scheduled="true"),
            _record("a1", "fit-corpus", 1_000_000)]  # newest first, as fetch_runs gives them
    page = overview(runs, params, ROOT)
    assert page.startswith(f"<p>3 runs in experiment <code>{params.experiment.experiment}</code>")
    rows = _table(page, "stages")
    assert rows[0] == ["stage", "runs", "finished", "scheduled", "newest run", "started", "status"]
    assert [r[:5] + r[6:] for r in rows[1:]] == [["fit-corpus", "1", "1", "0", "fit-corpus a1", "FINISHED"],
                                               ["train-smlm", "2", "1", "1", "train-smlm c3", "FAILED"]]
    assert "No runs in the MLflow store yet" in overview([], params, ROOT)


def test_the_runs_page_lists_every_run_with_its_tags_and_the_data_the_comparison_reads():
    from dashboards.sections.runs import runs_page

    runs = [_record("b2</script>", "train-smlm", 2_000_000, variant="fsq"), _record("a1", "fit-corpus", 1_000_000)]
    page = runs_page(runs)
    options = re.findall(r"<option>([^<]+)</option>", page)
    assert options == ["fit-corpus", "train-smlm"]  # the stage filter, sorted
    rows = [re.findall(r"<td>(.*?)</td>", row) for row in re.findall(r"<tr data-stage[^>]*>(.*?)</tr>", page)]
    assert rows[0][0] == '<input type=checkbox class=pick value="b2&lt;/script&gt;">'
    assert rows[0][1:] == ["train-smlm b2&lt;/script&gt;", "train-smlm", "FINISHED", rows[0][4], "b2&lt;/scri",
                           "variant=fsq", "1"]
    assert 'data-stage="fit-corpus" data-tags=""' in page and "<span id=shown>2</span>" in page
    payload = json.loads(re.search(r'<script type="application/json" id="run-data">(.*?)</script>', page,
                                   re.S).group(1))
    assert payload["a1"] == {"name": "fit-corpus a1", "params": {"p": "a1"}, "metrics": {"m": 1.0}}
    assert payload["b2</script>"]["name"] == "train-smlm b2</script>"  # escaped in the page, whole in the data
    assert "No runs yet" in runs_page([])


def test_the_quality_page_shows_each_corpus_report_its_quarantine_and_per_clip_figures(tmp_path):
    from dashboards.sections.quality import quality

    params = load_params(ROOT / "params.yaml", overrides={"data": {"shards_root": str(tmp_path)}})
    corpora = list(params.corpora)
    folder = params.data.shards_dir(corpora[0])
    folder.mkdir(parents=True)
    (folder / "quality.json").write_text(json.dumps({"clips_fitted": 3, "reproj_px_mean": 2.345678, "corpus": "x",
                                                     "quarantine_reasons": {"no person detected": 2}}))
    (folder / "quality.csv").write_text("clip_id,status,reproj_px,missing_left_hand,missing_right_hand,missing_face\n"
                                        "a,fitted,2.0,0.1,0.0,0.5\nb,quarantined,,,,\nc,fitted,3.0,0.0,0.2,\n")
    page = quality(params)
    assert _table(page, f"quality-{corpora[0]}")[1:] == [["clips_fitted", "3"], ["reproj_px_mean", "2.346"]]
    assert "no person detected" in page and "no clip quarantined" not in page
    assert f'id="reproj-{corpora[0]}"' in page and f'id="missing-{corpora[0]}"' in page
    for corpus in corpora[1:]:  # the others: not fitted yet, and no figure
        assert f'id="reproj-{corpus}"' not in page
    assert page.count("Not fitted yet") == len(corpora) - 1
    (folder / "quality.json").write_text(json.dumps({"clips_fitted": 3, "quarantine_reasons": {}}))
    clean = quality(params)
    assert "no clip quarantined" in clean and "quarantine reason" not in clean


def test_the_curves_page_draws_one_figure_per_metric_of_each_training_runs_history(tmp_path):
    from dashboards.sections.common import run_name
    from dashboards.sections.curves import curves
    from m3t.experiment import ExperimentConfig, fetch_runs, start_run

    experiment = ExperimentConfig(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}",
                                  artifact_dir=str(tmp_path / "mlruns"))
    with start_run(experiment, "train-slr", tmp_path, variant="full") as run:
        for epoch in (1, 2, 3):
            run.log_metrics({"full/train_loss": 1.0 / epoch, "no_face/train_loss": 2.0 / epoch,
                             "full/val_top1": 10.0 * epoch, "full/epoch": float(epoch)}, step=epoch)
        run.log_metrics({"train_clips": 12.0})  # one point: not a curve
    with start_run(experiment, "evaluate-slr", tmp_path) as run:  # not a training stage
        for epoch in (1, 2):
            run.log_metrics({"loss": 1.0}, step=epoch)
    runs = fetch_runs(experiment, tmp_path)
    page = curves(runs, experiment, tmp_path)
    slr = next(r for r in runs if r.stage == "train-slr")
    assert re.findall(r"<h2>([^<]+)</h2>", page) == [run_name(slr)]
    ids = re.findall(r'id="(curve-[^"]+)"', page)
    assert ids == [f"curve-{slr.run_id[:8]}-0", f"curve-{slr.run_id[:8]}-1"]  # train_loss, val_top1: no epoch
    assert page.count('"name":"full"') == 2 and page.count('"name":"no_face"') == 1
    assert len(re.findall(r'id="curve-', curves(runs, experiment, tmp_path, max_figures=1))) == 1
    assert "No training run with per-epoch metrics yet" in curves([], experiment, tmp_path)



def test_the_newest_finished_run_of_each_variant_is_shown():
    from dashboards.sections.common import newest_per_variant

    runs = [_record("c", "train-smlm", 3, "FAILED", variant="a"), _record("b", "train-smlm", 2, variant="b"),
            _record("a2", "train-smlm", 2, variant="a"), _record("a1", "train-smlm", 1, variant="a"),
            _record("x", "train-slr", 4, variant="a")]
    assert [r.run_id for r in newest_per_variant(runs, "train-smlm")] == ["b", "a2"]
    assert [r.run_id for r in newest_per_variant(runs, "train-smlm", limit=1)] == ["b"]


# ---- the pages' exact text from hand-made runs: headings, table ids and cells, the commands each empty section
# names, which runs each section picks. Every expected string below is what a researcher reads on the page.
def _run(run_id: str, stage: str, start: int = 1_000_000, metrics: dict | None = None, status: str = "FINISHED",
         artifact_dir: Path | None = None, **tags):
    """A stored run made by hand (no MLflow): ``metrics`` as logged, ``tags`` besides its run name."""
    from m3t.experiment import RunRecord

    return RunRecord(run_id, stage, start, status, {}, dict(metrics or {}), artifact_dir,
                     {"mlflow.runName": f"{stage} {run_id}", **tags})


def _plot(page: str, div_id: str) -> tuple[list, dict]:
    """The data and layout of the plotly figure drawn into ``div_id``."""
    decoder = json.JSONDecoder()
    found = re.search(rf'Plotly\.newPlot\(\s*"{div_id}",\s*', page)
    assert found, f"no figure {div_id}"
    data, end = decoder.raw_decode(page, found.end())
    layout, _ = decoder.raw_decode(page, re.compile(r"\s*,\s*").match(page, end).end())
    return data, layout


# a judged claim as claims.json stores it: VQ -> FSQ utilisation, its seed halves disagreeing
_JUDGED = {"key": "k", "claim": "FSQ uses more codes", "source": "M3T Tab. 3", "paper": "67 -> 96", "metric": "util",
           "a": "VQ", "b": "FSQ", "mean_a": 97.46, "std_a": 1.66, "mean_b": 93.64, "std_b": 2.44, "compared": "B - A",
           "value": -3.82, "interval95": [-7.0, 0.0], "verdict": "inconclusive", "note": "", "seeds": ["0", "1", "2"],
           "runs_a": ["aaaaaaaa11", "cccccccc33"], "runs_b": ["bbbbbbbb22", "aaaaaaaa99"],
           "halves": {"seeds": [["0"], ["1", "2"]], "verdicts": ["not reproduced", "inconclusive"]}}


def test_the_claims_table_rows_show_means_intervals_verdicts_and_run_ids():
    """One judged row (means at 3 significant digits, SDs at 2, the interval, the flipping seed halves, the runs'
    8-character ids, deduplicated and sorted), one with a note and agreeing halves, one claim not run yet."""
    from dashboards.sections.claims import _claim_rows

    noted = {**_JUDGED, "claim": "noted", "verdict": "reproduced", "note": "2 seed(s) < 3",
             "halves": {"seeds": [["0"], ["1"]], "verdicts": ["reproduced", "reproduced"]}}
    missing = {"claim": "the SMLM claim", "source": "M3T Tab. 1", "paper": "p", "metric": "dtw", "verdict": "not run",
               "note": "no evaluate-smlm runs"}
    rows = _table(_claim_rows([_JUDGED, noted, missing]), "claims")
    assert rows[0] == ["claim", "source", "paper", "metric", "ours: A -&gt; B", "compared [95 % interval]",
                       "verdict", "seeds", "runs"]
    assert rows[1] == ["FSQ uses more codes", "M3T Tab. 3", "67 -&gt; 96", "util",
                       "VQ 97.5 +- 1.7 -&gt; FSQ 93.6 +- 2.4", "B - A -3.82 [-7, 0]",
                       "inconclusive; seed halves: not reproduced / inconclusive", "3", "aaaaaaaa, bbbbbbbb, cccccccc"]
    assert rows[2][6] == "reproduced (2 seed(s) &lt; 3)"  # halves agree: no seed-half note
    assert rows[3] == ["the SMLM claim", "M3T Tab. 1", "p", "dtw", "-", "-", "not run: no evaluate-smlm runs", "0", "-"]
    no_halves = _table(_claim_rows([{**_JUDGED, "halves": None}]), "claims")
    assert no_halves[1][6] == "inconclusive"


def test_the_live_claims_section_and_a_saved_study_say_how_they_were_judged(tmp_path):
    from dashboards import html as h
    from dashboards.sections.claims import CLAIMS_NOTE, claims, saved_claims

    live = claims([])
    assert live.startswith("<p class=note>" + CLAIMS_NOTE + "A claim with no runs says which command makes them. "
                           "<code>m3t claims</code> writes the same table to claims.json / claims.md. Stability: ")
    assert len(_table(live, "claims")) == len(CLAIMS) + 1  # every claim, each saying what to run
    path = tmp_path / "claims.json"
    path.write_text(json.dumps({"claims": [_JUDGED, {**_JUDGED, "claim": "not judged", "verdict": "not run"}]}))
    page = saved_claims(path, "Tab. 3 <study>", "m3t study")
    assert [r[0] for r in _table(page, "claims")[1:]] == ["FSQ uses more codes"]  # the judged rows only
    assert page.startswith("<h2>Tab. 3 &lt;study&gt;</h2><p class=note>" + h.esc(CLAIMS_NOTE) + "Stability: ")
    assert f" ({h.esc(str(path))}, from m3t study)</p><table id=\"claims\">" in page
    assert saved_claims(tmp_path / "none.json", "Tab. 3 <study>", "m3t <study>") == (
        "<h2>Tab. 3 &lt;study&gt;</h2><div class=empty>Not run yet: <code>m3t &lt;study&gt;</code>.</div>")
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({}))  # no claims key: an empty table, not an error
    assert _table(saved_claims(empty, "T", "c"), "claims")[1:] == []


def test_the_repeatability_section_names_the_machine_and_the_digits(tmp_path):
    from dashboards.sections.claims import repeatability

    path = tmp_path / "reproducible.json"
    assert repeatability(path) == ("<h2>Which digits repeat</h2><div class=empty>Not measured here yet: run <code>"
                                   "python benchmarks/bench_reproducible.py</code>.</div>")
    path.write_text(json.dumps({"machine": "arm64", "cpu_count": 8, "cost": 2.0, "stages": {
        "train-smlm": {"figures": {"loss": {"old": 1.0, "new": 1.0 + 3e-14}, "gone": {"old": 2.5, "new": None}}},
        "fit": {}}}))
    page = repeatability(path)
    assert page.startswith("<h2>Which digits repeat</h2><p class=note>Each training stage run twice on the same data "
                           "and seeds, on arm64 (8 cores): with the machine&#x27;s own arithmetic and with the pinned "
                           "one (M3T_REPRODUCIBLE=1, 2.00x the time). Only the float order differs, so the digits the "
                           "two share are those another machine can be expected to repeat. Under the mode every digit "
                           "repeated across thread counts and kernel settings on one machine "
                           "(tests/base/test_arithmetic.py). Seeds move the figures as much or more: see each "
                           "claim&#x27;s std over seeds.</p>")
    assert _table(page, "repeatability") == [
        ["stage", "figure", "machine arithmetic", "pinned arithmetic", "digits that agree"],
        ["train-smlm", "loss", "1", "1", "13"], ["train-smlm", "gone", "2.5", "-", "-"]]
    path.write_text(json.dumps({}))  # nothing recorded: unknown machine, no rows
    bare = repeatability(path)
    assert "on ? (? cores)" in bare and "(M3T_REPRODUCIBLE=1, nanx the time)" in bare
    assert _table(bare, "repeatability")[1:] == []


def test_the_paper_tables_each_read_their_own_stage():
    """Each measured table from the runs of its stage only: Tab. 2 the evaluate-backtranslation run (the ground
    truth) and the evaluate-smlm run, Tab. 3 the train-tokenizers run, Tab. 4 the evaluate-slr run, SGSA Tab. 1/3 the
    evaluate-sgsa run; beside each, the paper's own table."""
    from dashboards import html as h
    from dashboards.paper import M3T, SGSA
    from dashboards.sections.tables import paper_tables

    runs = [_run("bt", "evaluate-backtranslation", metrics={"slt/ASL-SYN/rouge_l": 40.0, "slt/ASL-SYN/bleu4": 10.0}),
            _run("sm", "evaluate-smlm", metrics={"bt/slt/ASL-SYN/rouge_l": 30.0, "bt/slt/ASL-SYN/bleu4": 5.0},
                 variant="production only"),
            _run("sg", "evaluate-sgsa", metrics={"pt/test/dtw_jpe_mean_m": 0.5}),
            _run("tk", "train-tokenizers", metrics={"face/utilisation_pct": 42.0}, quantizer="fsq"),
            _run("sl", "evaluate-slr")]
    page = paper_tables(runs)
    assert page.startswith("<p class=note>Measured tables come from the newest finished runs of each variant, by the "
                           "definitions each table names (SL-T text metrics, SOKE DTW motion metrics). Rows "
                           "<i>baseline</i> are the copy baselines of evaluate-baselines (retrieval: the nearest "
                           "training text's motion; lexicon: one stored sign per annotated gloss), scored on the same "
                           "clips by the same scorers and judges. The papers' numbers are on their own corpora: "
                           "comparable in layout, not in value.</p><h2 id=\"m3t-tab1\">"
                           "M3T Tab. 1</h2><div class=pair><div><h4>This platform (measured)</h4>")
    assert _table(page, "m3t-tab1-measured")[1:] == [["production only", "-"]]
    assert _table(page, "m3t-tab2-measured") == [["motion", "ASL-SYN R", "ASL-SYN B4"],
                                                 ["GT motion (upper bound)", "40.00", "10.00"],
                                                 ["SMLM, production only", "30.00", "5.00"]]
    tab3 = _table(page, "m3t-tab3-measured")
    assert tab3[1][tab3[0].index("util face %")] == "42.0"
    assert "no probe evaluated yet: run `dvc repro evaluate-slr`" in page  # a run, with nothing probed
    assert "no finished evaluate-slr runs yet" not in page
    for key in ("sgsa-tab1", "sgsa-tab3"):
        assert _table(page, f"{key}-measured")[1][-2:] == ["500.00", "1"]  # 0.5 m in mm, one seed
    for key, paper in (M3T | SGSA).items():
        reference = ("<h4>Paper (reference)</h4><p class=note>" + h.esc(paper.caption) + "</p>"
                     + h.table(paper.header, paper.rows))
        ident = key.lower().replace(". ", "").replace(" ", "-")
        section = page[page.index(f'<h2 id="{ident}">'):]
        assert section.startswith(f'<h2 id="{ident}">{key}</h2>') and f"<div>{reference}</div></div>" in section
    assert ("<div><h4>Paper (reference)</h4><p class=note>Back-translation, ROUGE-L (R) and BLEU-4 (B4)</p><table>"
            "<thead><tr><th>method</th><th>H2S R</th>") in page


def test_the_newest_finished_run_of_each_variant_keeps_up_to_four_variants():
    from dashboards.sections.common import (
        newest_per_variant,
        run_name,
        stage_runs,
        started,
    )

    runs = [_run(f"r{i}", "train-smlm", 10 - i, variant=f"v{i}") for i in range(6)] + [
        _run("plain", "train-smlm", 1), _run("plain-old", "train-smlm", 0)]
    assert [r.run_id for r in newest_per_variant(runs, "train-smlm")] == ["r0", "r1", "r2", "r3"]
    assert [r.run_id for r in newest_per_variant(runs[6:], "train-smlm")] == ["plain"]  # no variant tag: one key
    assert [r.run_id for r in newest_per_variant(runs, "train-smlm", limit=8)] == [
        "r0", "r1", "r2", "r3", "r4", "r5", "plain"]
    assert newest_per_variant(runs, "train-slr") == [] and stage_runs(runs, "train-slr") == []
    assert run_name(runs[0]) == "train-smlm r0"
    untagged = _run("x", "fit-corpus")
    untagged.tags.clear()
    assert run_name(untagged) == "fit-corpus"  # no run name: the stage
    import datetime as dt

    assert started(_run("t", "s", 1_700_000_000_000)) == dt.datetime.fromtimestamp(1_700_000_000).strftime(
        "%Y-%m-%d %H:%M")


_PAGE_TITLES = {"index.html": ("M3T platform", False), "tables.html": ("Paper tables", False),
                "curves.html": ("Training curves", True), "claims.html": ("The papers' claims on these runs", False),
                "codebooks.html": ("Codebooks: utilisation and token histograms", True),
                "quality.html": ("Data quality per corpus", True),
                "videos.html": ("Videos: reference vs each model, per test clip", False), "runs.html": ("Runs", False)}


def test_the_site_is_built_into_the_configured_folder_from_the_stores_runs(tmp_path, monkeypatch):
    """The whole site from hand-made runs (MLflow replaced by a list): written to experiment.dashboard_dir when
    no folder is given, each page with its title, navigation and plot script, the study's saved claims and the
    repeatability table on the claims page, the videos copied, the run list as runs.json, no leftover folder."""
    import html

    import plotly.offline

    import dashboards.sections.curves as curves_section
    from dashboards import build

    params = load_params(ROOT / "params.yaml", overrides={
        "experiment": {"dashboard_dir": str(tmp_path / "site")},
        "data": {"metrics_dir": str(tmp_path / "metrics"), "shards_root": str(tmp_path / "shards")}})
    renders = tmp_path / "artifacts" / "renders"
    renders.mkdir(parents=True)
    (renders / "c1.mp4").write_bytes(b"video")
    runs = [_run("smlm-run-1", "evaluate-smlm", 3_000_000, artifact_dir=renders.parent, variant="production only"),
            _run("train-run-2", "train-smlm", 2_000_000, metrics={"full/train_loss": 0.5}, scheduled="true")]
    fetched, histories = [], []
    monkeypatch.setattr(build, "fetch_runs", lambda cfg, root: fetched.append((cfg, root)) or runs)

    def metric_histories(experiment, run_id, keys, root):
        histories.append((experiment, run_id, keys, root))
        return {"full/train_loss": [(1, 1.0), (2, 0.5)]}

    monkeypatch.setattr(curves_section, "metric_histories", metric_histories)
    monkeypatch.setattr(plotly.offline, "get_plotlyjs", lambda: "/* plotly */")
    _write_json(tmp_path, "metrics/study/claims.json", {"claims": [_JUDGED]})
    root = tmp_path / "repo"
    _write_json(root, "benchmarks/results/reproducible.json", {"machine": "m", "cpu_count": 1, "cost": 1.0, "stages": {
        "train-smlm": {"figures": {"loss": {"old": 1.5, "new": 1.5}}}}})
    (tmp_path / "site.tmp" / "stale").mkdir(parents=True)  # an interrupted build's folder: replaced
    index = build_dashboard(params, root=root)
    site = tmp_path / "site"
    assert index == site / "index.html" and fetched == [(params.experiment, root)]
    assert histories == [(params.experiment, "train-run-2", ["full/train_loss"], root)]
    assert sorted(p.name for p in site.glob("*.html")) == sorted(_PAGE_TITLES)
    for name, (title, plots) in _PAGE_TITLES.items():
        text = (site / name).read_text(encoding="utf-8")
        assert f"<title>{html.escape(title)} · M3T platform</title>" in text and f"<h1>{html.escape(title)}</h1>" in text
        assert f'<a href="{name}" class=here>' in text and text.count(" class=here>") == 1
        assert ('<script src="assets/plotly.min.js"></script>' in text) == plots
        assert re.search(r"<p class=note>Generated \d{4}-\d\d-\d\d \d\d:\d\d by <code>python -m dashboards.build"
                         r"</code>.</p></main></body></html>$", text)
    assert (site / "assets" / "plotly.min.js").read_text(encoding="utf-8") == "/* plotly */"
    assert "2 runs in experiment" in (site / "index.html").read_text(encoding="utf-8")
    assert _table((site / "tables.html").read_text(encoding="utf-8"), "m3t-tab1-measured")[1] == ["production only", "-"]
    assert 'id="curve-train-ru-0"' in (site / "curves.html").read_text(encoding="utf-8")
    claims_page = (site / "claims.html").read_text(encoding="utf-8")
    assert claims_page.count('<table id="claims">') == 2  # the live claims, then the study's
    assert "<h2>The claims study: every claim over 5 seeds on the study corpus</h2>" in claims_page
    assert f"({tmp_path / 'metrics' / 'study' / 'claims.json'}, from m3t study)" in claims_page
    assert _table(claims_page, "repeatability")[1] == ["train-smlm", "loss", "1.5", "1.5", "all"]
    assert "No tokenizer run yet" in (site / "codebooks.html").read_text(encoding="utf-8")
    assert (site / "quality.html").read_text(encoding="utf-8").count("Not fitted yet") == len(params.corpora)
    assert 'src="media/evaluate-smlm/c1.mp4"' in (site / "videos.html").read_text(encoding="utf-8")
    assert (site / "media" / "evaluate-smlm" / "c1.mp4").read_bytes() == b"video"
    assert '<table id=runs>' in (site / "runs.html").read_text(encoding="utf-8")
    listed = [{"run_id": r.run_id, "stage": r.stage, "status": r.status, "tags": r.tags} for r in runs]
    assert (site / "runs.json").read_text(encoding="utf-8") == json.dumps(listed, indent=1)
    assert not (tmp_path / "site.tmp").exists() and not (site / "stale").exists()
    # without a study, no study section; the store is read from the current folder by default
    (tmp_path / "metrics" / "study" / "claims.json").unlink()
    monkeypatch.chdir(root)
    build_dashboard(params, tmp_path / "other")
    assert fetched[-1] == (params.experiment, ".")
    other = (tmp_path / "other" / "claims.html").read_text(encoding="utf-8")
    assert "The claims study" not in other and other.count('<table id="claims">') == 1
    assert _table(other, "repeatability")[1][0] == "train-smlm"  # ./benchmarks/results/reproducible.json


def test_the_build_command_reads_the_params_and_prints_where_the_site_is(tmp_path, monkeypatch, capsys):
    import sys

    import pytest

    from dashboards import build

    params = load_params(ROOT / "params.yaml")
    calls = []
    index = tmp_path / "site" / "index.html"
    index.parent.mkdir()
    for name in ("index.html", "runs.html"):
        (index.parent / name).write_text("x")

    def fake_build(p, out):
        calls.append((p, out))
        return index

    monkeypatch.setattr(build, "load_params", lambda path: calls.append(path) or params)
    monkeypatch.setattr(build, "build_dashboard", fake_build)
    monkeypatch.setattr(sys, "argv", ["dashboards.build"])
    build.main()
    assert calls == ["params.yaml", (params, params.experiment.dashboard_dir)]
    assert capsys.readouterr().out == f"wrote {index} (2 pages); open it in a browser\n"
    monkeypatch.setattr(sys, "argv", ["dashboards.build", "--params", "p.yaml", "--out", "elsewhere"])
    build.main()
    assert calls[2:] == ["p.yaml", (params, "elsewhere")]
    capsys.readouterr()
    monkeypatch.setenv("COLUMNS", "250")
    monkeypatch.setattr(sys, "argv", ["dashboards.build", "--help"])
    with pytest.raises(SystemExit):
        build.main()
    text = capsys.readouterr().out
    assert ("Static dashboard over the MLflow store and the DVC metrics: the pages a researcher opens after a run."
            in text)
    assert "--out OUT" in text and "folder of the site (default: experiment.dashboard_dir)" in text


def test_the_quality_section_states_each_corpus_exactly(tmp_path):
    """The measures table (floats at 4 significant digits, texts left out), the quarantine reasons sorted, the
    note when none, the per-clip figures from the fitted clips only, and what to run when nothing is fitted."""
    from types import SimpleNamespace

    from dashboards.sections.quality import quality

    folders = {"a": tmp_path / "a", "b": tmp_path / "b"}
    params = SimpleNamespace(corpora={"a": None, "b": None}, data=SimpleNamespace(shards_dir=folders.get))
    folders["a"].mkdir()
    (folders["a"] / "quality.json").write_text(json.dumps({
        "clips_fitted": 3, "reproj_px_mean": 12.34567, "corpus": "x", "quarantine_reasons": {"z late": 1, "a early": 4}}))
    (folders["a"] / "quality.csv").write_text(
        "clip_id,status,reproj_px,missing_left_hand,missing_right_hand,missing_face\n"
        "a,fitted,2.0,0.5,0.0,0.25\nb,quarantined,9.0,1.0,1.0,1.0\nc,fitted,3.0,0.0,0.75,\nd,fitted,,,,\n")
    page = quality(params)
    assert page.startswith('<h2>a</h2><div class=pair><div><table id="quality-a"><thead><tr><th>measure</th>'
                           "<th>value</th></tr></thead><tbody><tr><td>clips_fitted</td><td class=num>3</td></tr>"
                           "<tr><td>reproj_px_mean</td><td class=num>12.35</td></tr></tbody></table><table><thead><tr>"
                           "<th>quarantine reason</th><th>clips</th></tr></thead><tbody><tr><td>a early</td><td "
                           "class=num>4</td></tr><tr><td>z late</td><td class=num>1</td></tr></tbody></table></div>"
                           "<div><figure>")
    assert page.endswith("</figure></div></div><h2>b</h2><div class=empty>Not fitted yet: no "
                         f"{folders['b'] / 'quality.json'}. Run <code>m3t fit-corpus</code> or <code>dvc repro</code>."
                         "</div>")
    data, layout = _plot(page, "reproj-a")
    assert data == [{"nbinsx": 30, "x": [2.0, 3.0], "type": "histogram"}]
    assert (layout["title"]["text"], layout["xaxis"]["title"]["text"], layout["yaxis"]["title"]["text"]) == (
        "reprojection error per clip (px)", "px", "clips")
    data, layout = _plot(page, "missing-a")
    assert [(d["name"], d["y"], d["type"]) for d in data] == [
        ("left_hand", [0.5, 0.0], "box"), ("right_hand", [0.0, 0.75], "box"), ("face", [0.25], "box")]
    assert layout["title"]["text"] == "share of frames without the part, per clip"
    (folders["a"] / "quality.json").write_text(json.dumps({"clips_fitted": 3}))
    (folders["a"] / "quality.csv").unlink()
    assert quality(params).startswith('<h2>a</h2><div class=pair><div><table id="quality-a">') and (
        "</tbody></table><p class=note>no clip quarantined</p></div></div><h2>b</h2>") in quality(params)
    assert quality(SimpleNamespace(corpora={})) == (
        "<div class=empty>No corpus configured in params.yaml <code>corpora</code>.</div>")


def test_the_codebooks_page_figures_and_statistics_exactly(tmp_path):
    """Utilisation bars per quantizer (newest finished train- or evaluate-tokenizers run per quantizer tag, "?"
    without one), the statistics at their decimals, token shares by rank (an all-zero count stays zero), and the
    hint naming the commands that add a quantizer when only one is stored."""
    from dashboards.sections.codebooks import codebooks

    def counts(run_id, **groups):
        folder = tmp_path / run_id
        (folder / "plots").mkdir(parents=True)
        for group, values in groups.items():
            (folder / "plots" / f"tokens_{group}.json").write_text(json.dumps(
                {"group": group, "counts": values, "codebook_size": len(values)}))
        return folder

    stats = {"body/utilisation_pct": 87.64, "body/perplexity_per_code": 0.876, "body/count_sd": 12.34,
             "body/tokens_per_code": 2.74, "hand/utilisation_pct": 50.0}
    runs = [_run("fsq", "train-tokenizers", 5, metrics=stats, artifact_dir=counts("fsq", body=[1, 5, 0, 2],
                                                                                 hand=[3, 1]), quantizer="fsq"),
            _run("untagged", "evaluate-tokenizers", 4, metrics={"face/utilisation_pct": 10.0}),
            _run("fsq-failed", "train-tokenizers", 6, status="FAILED", quantizer="vq_plain"),
            _run("vq", "train-tokenizers", 3, metrics={"body/utilisation_pct": 25.0},
                 artifact_dir=counts("vq", body=[0, 0]), quantizer="vq"),
            _run("other", "train-smlm", 7, quantizer="x")]
    page = codebooks(runs, None)
    data, layout = _plot(page, "utilisation")
    assert [(d["name"], d["x"], d["y"], d["type"]) for d in data] == [
        ("FSQ", ["body", "hand", "face"], [87.64, 50.0, None], "bar"), ("VQ", ["body", "hand", "face"], [25.0, None, None], "bar"),
        ("?", ["body", "hand", "face"], [None, None, 10.0], "bar")]
    assert (layout["title"]["text"], layout["barmode"], layout["yaxis"]["range"]) == (
        "codebook utilisation on the test split (%)", "group", [0, 100])
    assert ('<table id="codebook-stats"><caption>test split; a uniform code distribution has perplexity / K = 1, and '
            "at 10 tokens per code leaves under 0.005 % of the codes unused</caption>") in page
    rows = _table(page, "codebook-stats")
    assert rows[:3] == [["quantizer", "group", "util %", "perplexity / K", "count SD", "tokens / K"],
                        ["FSQ", "body", "87.6", "0.88", "12.3", "2.7"], ["FSQ", "hand", "50.0", "-", "-", "-"]]
    assert [r[:3] for r in rows[3:]] == [["FSQ", "face", "-"], ["VQ", "body", "25.0"], ["VQ", "hand", "-"],
                                         ["VQ", "face", "-"], ["?", "body", "-"], ["?", "hand", "-"], ["?", "face", "10.0"]]
    data, layout = _plot(page, "tokens-body")
    assert [(d["name"], d["x"], d["y"], d["opacity"]) for d in data] == [
        ("FSQ (4 codes)", [1, 2, 3, 4], [0.625, 0.25, 0.125, 0.0], 0.6), ("VQ (2 codes)", [1, 2], [0.0, 0.0], 0.6)]
    assert (layout["title"]["text"], layout["xaxis"]["title"]["text"], layout["yaxis"]["title"]["text"],
            layout["barmode"]) == ("body token frequencies by rank (test split; cf. M3T Fig. 5)", "code rank",
                                   "share of tokens", "overlay")
    assert [d["name"] for d in _plot(page, "tokens-hand")[0]] == ["FSQ (2 codes)"]
    assert 'id="tokens-face"' not in page and "Only one quantizer" not in page
    assert page.index('id="utilisation"') < page.index('id="codebook-stats"') < page.index('id="tokens-body"') < (
        page.index('id="tokens-hand"'))
    alone = codebooks(runs[3:], None)
    assert ("</table><p class=note>Only one quantizer in the store; add the others with <code>m3t ablate-tokenizers"
            "</code> or <code>dvc exp run -S tokenizer.quantizer=vq</code> (<code>vq_ema</code>, <code>vq_plain</code>, "
            "<code>fsq</code>) to compare them.</p><figure>") in alone
    assert "Only one quantizer" not in codebooks(runs[:1] + runs[3:], None)  # two quantizers
    assert codebooks(runs[2:3] + runs[4:], None) == (
        "<div class=empty>No tokenizer run yet: run <code>dvc repro train-tokenizers</code>.</div>")


def test_the_curves_page_groups_each_runs_histories_into_figures(monkeypatch):
    """Histories replaced by hand-made ones: one figure per metric name (sorted, epoch / step counters left out,
    at most max_figures), one line per prefix; runs in the order of the training stages, newest per variant; a
    run with no history gets no heading."""
    import dashboards.sections.curves as curves_section
    from dashboards.sections.common import started
    from dashboards.sections.curves import curves

    histories = {"tok-run-1": {"body/loss": [(1, 2.0), (2, 1.0)], "hand/loss": [(1, 3.0)], "body/epoch": [(1, 1.0)],
                               "step": [(1, 1.0)], "lr": [(1, 0.5), (2, 0.25)]},
                 "slr-run-2": {f"m{i}": [(1, float(i))] for i in range(10)}, "slr-run-3": {}}
    asked = []

    def metric_histories(experiment, run_id, keys, root):
        asked.append((experiment, run_id, keys, root))
        return histories[run_id]

    monkeypatch.setattr(curves_section, "metric_histories", metric_histories)
    runs = [_run("slr-run-3", "train-slr", 9, variant="c"), _run("slr-run-2", "train-slr", 8, metrics={"b": 1, "a": 2},
                                                                variant="b"),
            _run("slr-old", "train-slr", 7, variant="b"), _run("eval", "evaluate-slr", 6),
            _run("tok-run-1", "train-tokenizers", 5)]
    page = curves(runs, "cfg", "root")
    assert asked == [("cfg", "tok-run-1", [], "root"), ("cfg", "slr-run-3", [], "root"),
                     ("cfg", "slr-run-2", ["a", "b"], "root")]
    assert re.findall(r"<h2>(.*?)</h2><p class=note>(.*?)</p>", page) == [
        ("train-tokenizers tok-run-1", f"run tok-run-, {started(runs[4])}"),
        ("train-slr slr-run-2", f"run slr-run-, {started(runs[1])}")]
    data, layout = _plot(page, "curve-tok-run--0")
    assert [(d["name"], d["x"], d["y"], d["mode"]) for d in data] == [
        ("body", [1, 2], [2.0, 1.0], "lines+markers"), ("hand", [1], [3.0], "lines+markers")]
    assert (layout["title"]["text"], layout["xaxis"]["title"]["text"]) == ("loss", "epoch")
    data, layout = _plot(page, "curve-tok-run--1")
    assert [(d["name"], d["y"]) for d in data] == [("lr", [0.5, 0.25])] and layout["title"]["text"] == "lr"
    assert 'id="curve-tok-run--2"' not in page
    slr = re.findall(r'id="(curve-slr-run--\d+)"', page)
    assert slr == [f"curve-slr-run--{i}" for i in range(8)]  # at most 8 figures per run
    assert _plot(page, "curve-slr-run--7")[1]["title"]["text"] == "m7"
    assert page.count("<figure>") == 10 and page.startswith("<h2>train-tokenizers tok-run-1</h2>")
    assert curves(runs[3:4], "cfg", "root") == (
        "<div class=empty>No training run with per-epoch metrics yet: run <code>dvc repro</code> (or <code>m3t up"
        "</code>, then <code>prefect deployment run ...</code>).</div>")


def test_the_videos_page_text_and_which_runs_it_skips(tmp_path):
    from dashboards.sections.videos import videos

    def folder(name, *files):
        for file in files:
            (tmp_path / name / "a" / "b").mkdir(parents=True, exist_ok=True)
            (tmp_path / name / "a" / "b" / file).write_bytes(name.encode())
        return tmp_path / name

    runs = [_run("none", "evaluate-smlm", 9),  # finished, no artifacts
            _run("running", "evaluate-smlm", 8, status="RUNNING", artifact_dir=folder("running", "z.mp4")),
            _run("new", "evaluate-smlm", 7, artifact_dir=folder("new", "b2.mp4", "a1.mp4", "notes.txt")),
            _run("sg", "evaluate-sgsa", 6, artifact_dir=folder("sg", "a1.mp4")),
            _run("other", "train-smlm", 5, artifact_dir=folder("other", "a1.mp4"))]
    page = videos(runs, tmp_path / "media")
    assert page == (
        "<p class=note>Each video shows the reference beside the model's output for the same test clip.</p>"
        '<h2>a1</h2><figure><video controls muted preload=metadata src="media/evaluate-smlm/a1.mp4"></video>'
        "<figcaption>SMLM, body surface (evaluate-smlm new)</figcaption></figure>"
        '<figure><video controls muted preload=metadata src="media/evaluate-sgsa/a1.mp4"></video>'
        "<figcaption>PT / SGSA / SMLM, skeletons (evaluate-sgsa sg)</figcaption></figure>"
        '<h2>b2</h2><figure><video controls muted preload=metadata src="media/evaluate-smlm/b2.mp4"></video>'
        "<figcaption>SMLM, body surface (evaluate-smlm new)</figcaption></figure>")
    assert sorted(p.relative_to(tmp_path / "media").as_posix() for p in (tmp_path / "media").rglob("*")
                  if p.is_file()) == ["evaluate-sgsa/a1.mp4", "evaluate-smlm/a1.mp4", "evaluate-smlm/b2.mp4"]
    assert videos(runs[:2], tmp_path / "m") == (
        "<div class=empty>No rendered video yet: <code>dvc repro generate-smlm evaluate-smlm evaluate-sgsa</code> "
        "renders the first test clips (<code>smlm_generate.render_clips</code>, <code>sgsa_evaluate.render_clips"
        "</code>).</div>")


def test_the_overview_and_runs_page_text():
    from dashboards.sections.runs import FILTER_JS, overview, runs_page

    params = load_params(ROOT / "params.yaml", overrides={"experiment": {"tracking_uri": "sqlite:///a<b>.db",
                                                                          "experiment": "exp<1>"}})
    assert overview([], params, ROOT) == (
        "<div class=empty>No runs in the MLflow store yet (<code>sqlite:///a&lt;b&gt;.db</code>, experiment <code>"
        "exp&lt;1&gt;</code>). Run the embedded pipeline with <code>dvc repro</code> (or <code>m3t up</code>, then "
        "<code>prefect deployment run ...</code>), then rebuild this page with <code>python -m dashboards.build"
        "</code>.</div>")
    runs = [_run("b2", "train-smlm", 2_000_000, scheduled="true", variant="fsq", **{"mlflow.user": "me"}),
            _run("a1", "fit-corpus", 1_000_000, scheduled="false")]
    page = overview(runs, params, ROOT)
    assert page.startswith("<p>2 runs in experiment <code>exp&lt;1&gt;</code>. Pages: the paper tables filled from "
                           "the newest runs, training curves, codebooks, data quality, videos, and every run with a "
                           'filter.</p><table id="stages">')
    assert [r[3] for r in _table(page, "stages")[1:]] == ["0", "1"]  # scheduled="true" only
    page = runs_page(runs)
    assert page.startswith(
        FILTER_JS + "<div class=filters><label>stage <select id=stage onchange=filterRuns()><option value=''>all"
        "</option><option>fit-corpus</option><option>train-smlm</option></select></label><label>tag contains "
        "<input id=tag oninput=filterRuns() placeholder='quantizer=fsq'></label><label><input type=checkbox "
        "id=scheduled onchange=filterRuns()> scheduled only</label> <span id=shown>2</span> shown <button "
        "id=compare-button onclick=compareRuns()>compare ticked runs</button></div><div id=compare></div>"
        '<script type="application/json" id="run-data">')
    assert ("</script><table id=runs><thead><tr><th></th><th>run</th><th>stage</th><th>status</th><th>started</th>"
            "<th>id</th><th>tags</th><th>metrics</th></tr></thead><tbody>") in page
    assert '<tr data-stage="train-smlm" data-tags="scheduled=true variant=fsq"><td><input' in page  # no mlflow.*
    assert page.endswith("<td>scheduled=false</td><td>0</td></tr></tbody></table>")
    assert "function filterRuns()" in FILTER_JS and "getElementById('run-data')" in FILTER_JS
    assert runs_page([]) == ("<div class=empty>No runs yet: run <code>dvc repro</code> (or <code>m3t up</code>, "
                             "then <code>prefect deployment run ...</code>).</div>")


def test_the_html_pieces():
    """The page shell (navigation with the current page marked, the plot script only when asked), table cells
    (numbers right-aligned, header cells never), ids and captions, markdown tables and notes, empty states."""
    from dashboards import html as h

    page = h.page("curves.html", "A <b>", "<p>body</p>", "2024-01-02 03:04", plots=True)
    assert page.startswith("<!doctype html><html lang=en><head><meta charset=utf-8><title>A &lt;b&gt; · M3T platform"
                           "</title><style>" + h.STYLE + '</style><script src="assets/plotly.min.js"></script></head>'
                           '<body><nav><a href="index.html">Overview</a><a href="tables.html">Paper tables</a>'
                           '<a href="curves.html" class=here>Training curves</a><a href="claims.html">Claims</a>')
    assert page.endswith('<a href="runs.html">Runs</a></nav><main><h1>A &lt;b&gt;</h1><p>body</p><p class=note>'
                         "Generated 2024-01-02 03:04 by <code>python -m dashboards.build</code>.</p></main></body>"
                         "</html>")
    assert "<script" not in h.page("x.html", "T", "", "g") and " class=here" not in h.page("x.html", "T", "", "g")
    assert [h._cell(v) for v in ("12", "-3.5", "12.5%", "1.2.3", "a1", "-", " 7 ")] == [
        "<td class=num>12</td>", "<td class=num>-3.5</td>", "<td class=num>12.5%</td>", "<td>1.2.3</td>",
        "<td>a1</td>", "<td>-</td>", "<td class=num> 7 </td>"]
    assert h._cell(3, "th") == "<th>3</th>" and h._cell("<", "th") == "<th>&lt;</th>"
    assert h.table(["a"], [[1], ["x"]], "t<1>", "cap & c") == (
        '<table id="t&lt;1&gt;"><caption>cap &amp; c</caption><thead><tr><th>a</th></tr></thead><tbody><tr><td '
        "class=num>1</td></tr><tr><td>x</td></tr></tbody></table>")
    assert h.table([], []) == "<table><thead><tr></tr></thead><tbody></tbody></table>"
    text = "| a | b |\n|:--|--:|\n| 1 | x |\n- n1\nafter\n| c |\n| 2 |"
    assert h.markdown(text, "m") == (
        '<table id="m"><thead><tr><th>a</th><th>b</th></tr></thead><tbody><tr><td class=num>1</td><td>x</td></tr>'
        "</tbody></table><ul class=note><li>n1</li></ul><p class=note>after</p>"
        '<table id="m"><thead><tr><th>c</th></tr></thead><tbody><tr><td class=num>2</td></tr></tbody></table>')
    assert h.markdown("") == "" and h.markdown("-x\n  \n<a>") == "<p class=note>-x</p><p class=note>&lt;a&gt;</p>"
    assert h.empty("run <code>x</code>") == "<div class=empty>run <code>x</code></div>"
    assert h.esc("<&>") == "&lt;&amp;&gt;"


# ---- the documentation pages' fixed text: each section's heading and paragraph, which the committed pages carry
_FITTING_HEAD = (
    "## Fitting (`fit-corpus`, `fit-corpus-fingerspelling`)\n\n"
    "Means over fitted clips. `joint_mm`: joints in the camera frame after centring (includes the depth ambiguity of "
    "one view); `pa_joint_mm`: after per-frame similarity Procrustes; `init_pa_joint_mm`: the tracker initialisation, "
    "before refinement. The real fingerspelling clips have no ground truth, so only the reprojection error against "
    "MediaPipe's keypoints is shown.\n\n")
_TOKENIZER_HEAD = (
    "## Tokenizers (`train-tokenizers`)\n\nTest split unless marked. Utilisation needs many tokens per code to mean "
    "anything: N tokens spread uniformly over K codes leave (1 - 1/K)^N unused, so read it with tokens / K (the "
    "embedded test split is small; the study corpus is where Tab. 3 is judged).\n\n")
_SMLM_HEAD = (
    "## Sign Motion Language Model (`evaluate-smlm`)\n\nTest split, `m3t` motion definition: raw accumulated DTW cost "
    "in metres (SOKE's convention; it grows with length) and per aligned frame. Own translation: the SMLM translating "
    "ground-truth tokens (sacreBLEU 13a BLEU-4). Back-translation: the generated motion through the frozen judge "
    "(SL-T definition; CSL per character).\n\n")
_BT_HEAD = (
    "## Back-translation judge, ground-truth upper bound (`evaluate-backtranslation`)\n\nThe test split's fitted "
    "motion through the judge (SL-T definition). The embedded corpus has one test sentence per language, so these "
    "figures cannot rank systems; the claims study's corpus can.\n\n")
_SGSA_HEAD = (
    "## SGSA and Progressive Transformers (`evaluate-sgsa`)\n\nTest split, on the normalised skeleton; lengths decided "
    "by each model's own counter. DTW-JPE: raw cost (mean of body and hands, mm) and per aligned frame; ROUGE-L: the "
    "skeleton judge (SL-T definition). The SMLM's motion is posed into the same skeleton; the ground truth through "
    "the same judge is its ceiling.\n\n")


def test_each_docs_section_opens_with_its_heading_and_paragraph(tmp_path):
    """Missing files: each section's exact heading and paragraph, then the command that makes its file."""
    from dashboards import docs_pages

    def missing(rel, stage):
        return f"*Not measured yet: `{rel}` is missing; run `dvc repro {stage}`.*\n"

    assert docs_pages.fitting_section(tmp_path) == (
        _FITTING_HEAD + missing("data/shards/synthetic/summary.json", "fit-corpus") + "\n"
        + missing("data/shards/fingerspelling/summary.json", "fit-corpus"))
    assert docs_pages.tokenizer_section(tmp_path) == _TOKENIZER_HEAD + missing("models/tokenizers/metrics.json",
                                                                               "train-tokenizers")
    assert docs_pages.smlm_section(tmp_path) == _SMLM_HEAD + missing("metrics/smlm/metrics.json", "evaluate-smlm")
    assert docs_pages.backtranslation_section(tmp_path) == _BT_HEAD + missing(
        "metrics/backtranslation/metrics.json", "evaluate-backtranslation")
    assert docs_pages.sgsa_section(tmp_path) == _SGSA_HEAD + missing("metrics/sgsa/metrics.json", "evaluate-sgsa")
    assert docs_pages.slr_section(tmp_path) == ("## Recognition probe (`evaluate-slr`, M3T Tab. 4)\n\n"
                                                + missing("metrics/slr/table.md", "evaluate-slr"))
    page = docs_pages.embedded_page(tmp_path)
    assert page.startswith(
        "# Embedded pipeline results\n\nGenerated by `m3t docs-pages` from an uncommitted `dvc.lock` (no git history "
        "here); do not edit by hand. Sources: .\n\nWhat `dvc repro` measures on the embedded default: the synthetic "
        "corpus (its test split, one seed) and the real fingerspelling clips, with the Anny body model. One seed on a "
        "small test split: these figures check that every system runs and scores; which paper claims hold is judged "
        "on the study corpus over seeds ([claims](claims.md)). Float rounding differs between CPUs, so the last "
        "digits move from machine to machine unless `M3T_REPRODUCIBLE=1` ([reproducibility](../reproducibility.md))."
        "\n\n" + _FITTING_HEAD)
    assert docs_pages.baselines_section(tmp_path).endswith(missing("metrics/baselines/metrics.json",
                                                                   "evaluate-baselines"))
    assert docs_pages.baselines_section(tmp_path).startswith(
        "## Baselines beside the models (`evaluate-baselines`)\n\nThe copy baselines of the field, scored exactly as "
        "the models: ")
    assert page.endswith("\n" + docs_pages.sgsa_section(tmp_path) + "\n" + docs_pages.baselines_section(tmp_path)
                         + "\n" + docs_pages.slr_section(tmp_path))
    assert "\n" + _TOKENIZER_HEAD in page and "\n" + _SMLM_HEAD in page and "\n" + _BT_HEAD in page


def test_the_docs_tables_headers_and_their_missing_cells(tmp_path):
    """The measured tables' exact headers, and rows whose optional figures are absent."""
    from dashboards import docs_pages

    _write_json(tmp_path, "data/shards/synthetic/summary.json", {
        "clips_fitted": 2.4, "clips_total": 3.6, "frames": 10.5, "reproj_px_mean": 1.23456, "reproj_px_median": 2})
    assert docs_pages.fitting_section(tmp_path).endswith(
        "\n| corpus | clips fitted / listed | frames | reprojection px, mean / median | joint mm | PA joint mm | "
        "init PA joint mm | body / right-hand deg | facial-action error |\n|---|---|---|---|---|---|---|---|---|\n"
        "| synthetic (ground truth) | 2 / 4 | 10 | 1.23 / 2 | - | - | - | - / - | - |\n")
    _write_json(tmp_path, "models/tokenizers/metrics.json", {group: {
        "codebook_size": 64, "test_pa_vpe_mm": 1.0, "test_vpe_mm": 2.0, "utilisation_pct": 12.34,
        "all_splits_utilisation_pct": 99.99, "perplexity_per_code": 0.123456, "tokens_per_code": 1.23456}
        for group in ("face", "body")})
    tokenizers = docs_pages.tokenizer_section(tmp_path)
    assert tokenizers.endswith(
        "| group | codes K | PA-VPE mm | VPE mm | utilisation | perplexity / K | tokens / K | count SD | "
        "utilisation, all splits | tokens / K, all splits |\n|---|---|---|---|---|---|---|---|---|---|\n"
        "| body | 64 | 1 | 2 | 12.3 % | 0.12 | 1.23 | - | 100.0 % | - |\n"
        "| face | 64 | 1 | 2 | 12.3 % | 0.12 | 1.23 | - | 100.0 % | - |\n")  # body before face, whatever the file order
    _write_json(tmp_path, "metrics/smlm/metrics.json", {"dtw_vpe_face_pathnorm_m": 0.5})
    smlm = docs_pages.smlm_section(tmp_path)
    assert ("| region | DTW-JPE (m) | DTW-PA-JPE (m) | DTW-JPE per frame (m) | DTW-PA-JPE per frame (m) |\n"
            "|---|---|---|---|---|\n| body | - | - | - | - |\n| hands | - | - | - | - |\n"
            "| face (DTW-VPE) | - | - | 0.5 | - |\n\n"
            "Clips scored: 0 (cut to the model's limits: 0; empty generations: -; ended by EOS: -).\n\n"
            "| language | own translation BLEU-4 | back-translation ROUGE-L | back-translation BLEU-4 | sentences |\n"
            "|---|---|---|---|---|\n| ASL-SYN | - | - | - | - |\n| CSL-SYN | - | - | - | - |\n"
            "| DGS-SYN | - | - | - | - |\n") in smlm
    assert smlm.startswith(_SMLM_HEAD + "| region |")
    _write_json(tmp_path, "metrics/backtranslation/metrics.json", {})
    assert docs_pages.backtranslation_section(tmp_path) == _BT_HEAD + (
        "| language | ROUGE-L | BLEU-1 | BLEU-4 | sentences |\n|---|---|---|---|---|\n| ASL-SYN | - | - | - | - |\n"
        "| CSL-SYN | - | - | - | - |\n| DGS-SYN | - | - | - | - |\n")
    _write_json(tmp_path, "metrics/sgsa/metrics.json", {
        "sgsa/test/length_ratio_median": 0.9, "ground_truth/test/dtw_jpe_mean_m": 0.001, "pt/dev/dtw_jpe_mean_m": 1.0,
        "smlm/test/dtw_jpe_body_pathnorm_m": 0.002, "smlm/test/dtw_jpe_hand_pathnorm_m": 0.003})
    assert docs_pages.sgsa_section(tmp_path) == _SGSA_HEAD + (
        "| system | DTW-JPE raw (mm) | DTW-JPE per frame (mm), body / hands | length: median ratio / within +-25 % / "
        "stopped by counter | ROUGE-L | BLEU-4 |\n|---|---|---|---|---|---|\n"
        "| SGSA | - | - | 0.9 / - / - | - | - |\n| M3T SMLM | - | 2 / 3 | ends by EOS | - | - |\n"
        "| ground-truth motion | 1 | - | - | - | - |\n")
    assert docs_pages.embedded_page(tmp_path).count("Sources: `data/shards/synthetic/summary.json`, "
                                                    "`models/tokenizers/metrics.json`, `metrics/smlm/metrics.json`, "
                                                    "`metrics/backtranslation/metrics.json`, "
                                                    "`metrics/sgsa/metrics.json`.\n") == 1


def test_the_claims_docs_page_text(tmp_path):
    """The claims page's intro, each study's heading, source and summary (with the seed-half count when the study
    compared halves), the table header, and the Tab. 3 section in both states."""
    from dashboards import docs_pages

    intro = ("# The papers' claims: verdicts\n\nGenerated by `m3t docs-pages` from an uncommitted `dvc.lock` (no git "
             "history here); do not edit by hand. Sources: .\n\nHow a claim is judged (pairing on one data version, "
             "the hierarchical bootstrap over seeds and clips, the verdict rules, the seed-half check) is described "
             "on the [method page](../claims.md). Motion: SOKE's raw DTW cost in metres; text: SL-T's metrics "
             "(ROUGE-L with beta 1.2 per sentence, Chinese per character); PA-VPE in mm; recognition in %.\n")
    tab3_missing = ("## M3T Tab. 3 over seeds (`m3t tokenizer-table`)\n\n*Not run yet: `metrics/tab3/table.md` is "
                    "missing; write it with `m3t params --preset study > study.yaml && m3t --params study.yaml "
                    "tokenizer-table > metrics/tab3/table.md`.*\n")
    study = ("## The claims study (`m3t study`)\n\n*Not run yet: `metrics/study/claims.json` is missing. Command: "
             "`m3t study` (5 seeds per variant on the study corpus, preset `study`; its `claims.json`, `claims.md` and "
             "`timings.json` copied from `studies/study/`).*\n")
    assert docs_pages.claims_page(tmp_path) == f"{intro}\n{study}\n{tab3_missing}"
    (tmp_path / "metrics" / "tab3").mkdir(parents=True)
    (tmp_path / "metrics" / "tab3" / "table.md").write_text("| Q |\n", encoding="utf-8")
    assert docs_pages.tab3_section(tmp_path) == (
        "## M3T Tab. 3 over seeds (`m3t tokenizer-table`)\n\nSource: `metrics/tab3/table.md`. The study's tokenizers "
        "on its test split, mean +- SD over seeds: Q the quantizer (VQ: EMA with dead-code reset; VQ_EMA: EMA without "
        "reset; VQ_PLAIN: the VQ-VAE's learned codebook), BS the batch size, HS the hidden width; ppl/K the perplexity "
        "over the codebook size; tokens/K the test tokens per code (utilisation can be read where it is well above 1)."
        "\n\n| Q |\n")
    row = {"claim": "C", "source": "S", "paper": "p", "metric": "m", "a": "A", "b": "B", "mean_a": 5.0, "std_a": 0.5,
           "mean_b": 4.0, "std_b": 0.25, "value": -1.0, "interval95": [-1.5, -0.5], "band": None, "verdict": "inconclusive",
           "note": "", "seeds": ["0", "1", "2"], "halves": None}
    _write_json(tmp_path, "s/claims.json", {"min_seeds": 2, "stability": {"flipped": 1, "compared": 2},
                                            "claims": [row, {**row, "verdict": "reproduced"},
                                                       {**row, "verdict": "not run", "note": "later"}]})
    text = docs_pages.claims_section(tmp_path, "s/claims.json", "My study", "`cmd`")
    assert text.startswith(
        "## My study\n\nSource: `s/claims.json`, from `cmd`\n\n2 claims judged: 1 reproduced, 0 not reproduced, "
        "1 inconclusive; 1 of 2 flip between the two seed halves. Verdicts need at least 2 seeds.\n\n"
        "| claim | source | paper | metric | ours: A -> B (mean +- SD over seeds) | B - A [95 %] | verdict | seeds | "
        "seed halves |\n|---|---|---|---|---|---|---|---|---|\n| C | S | p | m | A 5 +- 0.5 -> B 4 +- 0.25 | "
        "-1 [-1.5, -0.5] | inconclusive | 3 | - |\n")
    assert text.endswith("| C | S | p | m | - | - | not run (later) | 3 | - |\n")
    _write_json(tmp_path, "s/claims.json", {"min_seeds": 2, "stability": {"flipped": 0, "compared": 0}, "claims": []})
    assert "0 inconclusive. Verdicts need at least 2 seeds.\n" in docs_pages.claims_section(
        tmp_path, "s/claims.json", "T", "c")


def test_the_home_page_drops_the_repository_only_sections_and_fixes_links(tmp_path):
    from dashboards import docs_pages

    (tmp_path / "README.md").write_text(
        "# M3T: 3D sign language production, reproduced end to end\n\nRead [x](docs/x.md) and "
        "[CONTRIBUTING](CONTRIBUTING.md).\n\n## Repository map\n\nm3t/ ...\n\n## Use\n\nrun it: 3D sign language "
        "production, reproduced end to end\n\n## Documentation\n\nthe list\n", encoding="utf-8")
    assert docs_pages.home_page(tmp_path) == (
        "# M3T\n\nRead [x](x.md) and `CONTRIBUTING.md`.\n\n## Use\n\nrun it: 3D sign language production, reproduced "
        "end to end\n\n")
    (tmp_path / "README.md").write_text("# R\n\n## Documentation\n\nx\n\n## After\n\ny\n", encoding="utf-8")
    assert docs_pages.home_page(tmp_path) == "# R\n\n## After\n\ny\n"


def test_the_docs_provenance_names_the_lock_commit_and_local_changes(tmp_path):
    import subprocess

    from dashboards import docs_pages

    def git(*args):
        subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@example.org", *args], cwd=tmp_path,
                       check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "dvc.lock").write_text("a\n")
    (tmp_path / "other").write_text("o\n")
    git("add", "dvc.lock", "other")
    git("commit", "-q", "-m", "lock")
    short = subprocess.run(["git", "log", "-1", "--format=%h (%cs)"], cwd=tmp_path, capture_output=True, text=True,
                           check=True).stdout.strip()
    assert docs_pages.lock_commit(tmp_path) == f"`dvc.lock` of commit {short}"
    (tmp_path / "other").write_text("changed\n")  # another file's change does not count
    assert docs_pages.lock_commit(tmp_path) == f"`dvc.lock` of commit {short}"
    (tmp_path / "dvc.lock").write_text("b\n")
    assert docs_pages.lock_commit(tmp_path) == f"`dvc.lock` of commit {short}, with uncommitted changes"
    assert docs_pages.provenance(tmp_path, ["dvc.lock", "missing.json", "other"]) == (
        f"Generated by `m3t docs-pages` from `dvc.lock` of commit {short}, with uncommitted changes; do not edit by "
        "hand. Sources: `dvc.lock`, `other`.\n")
