"""The paper tables page: each table measured on this store's runs beside the paper's own numbers."""
from __future__ import annotations

from dashboards import html as h
from dashboards.paper import M3T, SGSA, PaperTable
from dashboards.sections.common import stage_runs
from m3t.backtranslation.table import backtranslation_table
from m3t.experiment import RunRecord
from m3t.sgsa.table import adjacency_table, cross_table, layers_table
from m3t.slr.table import recognition_table
from m3t.smlm.table import production_table
from m3t.tokenizers.ablation import ablation_table


def _paper(table: PaperTable) -> str:
    return "<h4>Paper (reference)</h4><p class=note>" + h.esc(table.caption) + "</p>" + h.table(table.header, table.rows)


def paper_tables(runs: list[RunRecord]) -> str:
    """Each paper table: what this store measured (the ``m3t ...-table`` text) beside the paper's numbers."""
    smlm, sgsa = stage_runs(runs, "evaluate-smlm"), stage_runs(runs, "evaluate-sgsa")
    baselines = stage_runs(runs, "evaluate-baselines")
    measured = {
        "M3T Tab. 1": production_table(smlm, baselines=baselines),
        "M3T Tab. 2": backtranslation_table(stage_runs(runs, "evaluate-backtranslation"), smlm, baselines),
        "M3T Tab. 3": ablation_table(stage_runs(runs, "train-tokenizers")),
        "M3T Tab. 4": recognition_table(stage_runs(runs, "evaluate-slr")),
        "SGSA Tab. 1": layers_table(sgsa, baselines),
        "SGSA Tab. 2": adjacency_table(sgsa, baselines=baselines),
        "SGSA Tab. 3": cross_table(sgsa, baselines),
    }
    out = [("<p class=note>Measured tables come from the newest finished runs of each variant, by the definitions "
           "each table names (SL-T text metrics, SOKE DTW motion metrics). Rows <i>baseline</i> are the copy "
           "baselines of evaluate-baselines (retrieval: the nearest training text's motion; lexicon: one stored sign "
           "per annotated gloss), scored on the same clips by the same scorers and judges. The papers' numbers are "
           "on their own corpora: comparable in layout, not in value.</p>")]
    for key, text in measured.items():
        ident = key.lower().replace(". ", "").replace(" ", "-")  # "m3t-tab1"
        paper = (M3T | SGSA)[key]
        out.append(f'<h2 id="{ident}">{h.esc(key)}</h2><div class=pair><div><h4>This platform (measured)</h4>'
                   f"{h.markdown(text, ident + '-measured')}</div><div>{_paper(paper)}</div></div>")
    return "".join(out)
