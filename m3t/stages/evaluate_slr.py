"""evaluate-slr: the recognition probes on the test clips of ``slr.corpus`` -> M3T Tab. 4 (Top-1 / Top-5 overall,
confusing, normal, with bootstrap intervals) in ``<metrics>/slr``, logged to MLflow
(:func:`m3t.slr.pipeline.evaluate_and_log`).
"""
from __future__ import annotations

from m3t.slr.pipeline import evaluate_and_log
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: evaluate_and_log(p.slr_evaluate, p.body, p.data, p.experiment,
                                                                corpus=p.slr.corpus),
                      argv, show=lambda summary: {k: v for k, v in summary.items() if "/" not in k or
                                                  k.endswith(("/top1", "/top5"))})


if __name__ == "__main__":
    main()
