"""fit-corpus: a corpus' clips -> tracks -> (fused) initialisation -> refined body-model parameters -> Parquet
shards (one per split), quarantine and data-quality reports, and an MLflow run.

``python -m m3t.stages.fit_corpus --corpus NAME``: any corpus of ``corpora`` in params.yaml (root and adapter
options there; shards to ``data.shards_root/NAME``). The engine is :func:`m3t.fitting.corpus.fit_and_log`; it
fits where ``fit_corpus.executor`` says (:func:`m3t.fitting.cluster.open_executor`: local processes, or a Dask
cluster, the one at ``fit_corpus.dask_address`` or one started for the run). The shards are the same either way,
so neither key is a DVC param of this stage.
"""
from __future__ import annotations

from m3t.fitting.corpus import fit_and_log
from m3t.stages import stage_main


def main(argv: list[str] | None = None):
    return stage_main(
        __doc__, lambda p, args: fit_and_log(p.fit_job(args.corpus), p.experiment), argv,
        options=lambda parser: parser.add_argument("--corpus", default=None,
                                                   help="a name of corpora in params.yaml (default fit_corpus.default_corpus)"),
        show=lambda report: {**report.summary, "quality": report.quality})


if __name__ == "__main__":
    main()
