"""evaluate-baselines: the retrieval and lexicon baselines produced for the evaluation clips and scored like the
models, on the body-model path (M3T Tab. 1-2: evaluate-smlm's clips, scorer and judge) and on the skeleton path
(SGSA Tab. 1-3: evaluate-sgsa's samples, skeleton and judge), in ``<metrics>/baselines``
(:func:`m3t.production.baselines.evaluate_and_log`).
"""
from __future__ import annotations

from m3t.production.baselines import evaluate_and_log
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: evaluate_and_log(p.baselines, p.data, p.body, p.smlm_generate, p.sgsa,
                                                                p.sgsa_evaluate, p.experiment, p.backtranslation),
                      argv, show=lambda summary: {k: v for k, v in summary.items()
                                                  if k.count("/") == 1 or k.endswith("/test/dtw_jpe_mean_m")})


if __name__ == "__main__":
    main()
