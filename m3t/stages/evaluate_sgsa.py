"""evaluate-sgsa: PT, SGSA and the M3T SMLM on the same splits with the same judges (SGSA Tab. 1-3 and the
cross-paper table): DTW-JPE / DTW-PA-JPE on the skeleton, back-translation BLEU-1..4 / ROUGE-L by the skeleton
judge, side-by-side videos, in ``<metrics>/sgsa`` (:func:`m3t.sgsa.pipeline.evaluate_and_log`).
"""
from __future__ import annotations

from m3t.sgsa.pipeline import evaluate_and_log
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: evaluate_and_log(p.sgsa, p.sgsa_evaluate, p.body, p.data,
                                                                p.experiment, p.backtranslation),
                      argv, show=lambda summary: {k: v for k, v in summary.items()
                                                  if k.count("/") == 2 and k.endswith(("dtw_jpe_mean_m", "slt_bleu4"))
                                                  or k.endswith("/bt/slt_bleu4")})


if __name__ == "__main__":
    main()
