"""tokenize: fitted shards + trained tokenizers -> token shards, one folder per training corpus
(:func:`m3t.tokenizers.tokenize.run_tokenize`), here or on fit-corpus's Dask cluster (``fit_corpus.executor``).
"""
from __future__ import annotations

from m3t.stages import stage_main
from m3t.tokenizers.tokenize import run_tokenize


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: run_tokenize(p.data, p.fit_corpus), argv)


if __name__ == "__main__":
    main()
