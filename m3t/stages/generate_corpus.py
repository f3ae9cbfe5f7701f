"""generate-corpus: the embedded synthetic sign corpus with ground truth, written to ``corpora.synthetic.root``
(``synthetic_corpus`` and ``body`` sections; deterministic from the seed, written atomically).
"""
from __future__ import annotations

from m3t.corpora.synthetic import make_corpus
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: make_corpus(p.synthetic_corpus, p.body, p.corpora["synthetic"].root),
                      argv)


if __name__ == "__main__":
    main()
