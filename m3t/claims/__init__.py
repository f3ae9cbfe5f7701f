"""The papers' claims read from the pipeline's MLflow runs: claim | paper's figure | ours | verdict, with run ids.

Every claim compares two variants A and B on one metric (:data:`CLAIMS`). Its values come from the artifacts the
evaluate stages log (``per_clip.csv``, ``backtranslation.csv``, ``predictions.csv``) or, for codebook
statistics, the training runs' metrics: per test clip, for every seed both variants were run with (the newest
finished run per variant and seed). :mod:`m3t.metrics.stats` compares the seed-averaged means over clips with a
hierarchical bootstrap over seeds and clips (seeds alone for per-run statistics) and gives the verdict. With fewer than
``min_seeds`` seeds the verdict is ``inconclusive`` whatever the interval: two runs of the embedded pipeline
that differed only by float rounding flipped orderings, so one seed answers nothing.

Variants are run by the pipeline and its sweeps: ``dvc exp run -S smlm_train.seed=N`` (and
``-S smlm_train.translation_objective=false``), ``m3t ablate-tokenizers``, ``m3t sgsa-sweep``; a claim whose
variants have no runs yet says which command makes them.

The package: :mod:`~m3t.claims.definitions` (the claims as data), :mod:`~m3t.claims.collectors` (reading the
runs into per-clip samples), :mod:`~m3t.claims.verdicts` (samples -> judged rows),
:mod:`~m3t.claims.report` (claims.md / claims.json).

Axis legend: R seeds, C clips.
"""
