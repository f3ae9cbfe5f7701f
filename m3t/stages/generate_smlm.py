"""generate-smlm: the trained SMLM on ``smlm_generate.split`` -> generated motion tokens, translations, ``.pose``
files, side-by-side body-surface videos (reference / generated) and skeleton videos (MP4) in ``data.generated``
(:func:`m3t.smlm.generate_run.generate`); the decoding on fit-corpus's Dask cluster with ``fit_corpus.executor:
dask``.
"""
from __future__ import annotations

from m3t.smlm.generate_run import generate
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: generate(p.smlm_generate, p.data, p.body, cluster=p.fit_corpus), argv)


if __name__ == "__main__":
    main()
