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
