"""evaluate-smlm: generated motion + translations -> M3T Tab. 1 metrics (DTW-JPE / DTW-PA-JPE, face DTW-VPE,
BLEU-4 / ROUGE-L) and the back-translation of the generated motion (Tab. 2, SL-T definition) in
``<metrics>/smlm``, logged to MLflow (:func:`m3t.smlm.evaluate_run.evaluate_and_log`); the scoring on fit-corpus's
Dask cluster with ``fit_corpus.executor: dask``.
"""
from __future__ import annotations

from m3t.smlm.evaluate_run import evaluate_and_log
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: evaluate_and_log(p.smlm_generate, p.data, p.body, p.experiment,
                                                                p.backtranslation, p.fit_corpus),
                      argv, show=lambda summary: {k: v for k, v in summary.items() if "/" not in k})


if __name__ == "__main__":
    main()
