"""generate-corpus: the embedded synthetic sign corpus with ground truth (DVC stage).

``python -m m3t.stages.generate_corpus --out data/corpus/synthetic`` reads the ``corpus`` and ``body``
sections of params.yaml, generates the clips deterministically from the seed and writes them atomically.
"""
from __future__ import annotations

import argparse
import json
import time

from m3t.body.factory import load_body_model
from m3t.corpora.synthetic import generate_corpus, write_corpus


def main(argv: list[str] | None = None) -> None:
    from m3t.config import load_params

    parser = argparse.ArgumentParser(description="generate the embedded synthetic sign corpus")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--preset", default="default")
    parser.add_argument("--out", default="data/corpus/synthetic")
    args = parser.parse_args(argv)
    params = load_params(args.params, preset=args.preset)
    body = load_body_model(params.body)
    start = time.perf_counter()
    clips = generate_corpus(params.corpus, body)
    write_corpus(clips, args.out)
    splits: dict[str, int] = {}
    for c in clips:
        splits[c.clip.split] = splits.get(c.clip.split, 0) + 1
    print(json.dumps({"clips": len(clips), "splits": splits, "seconds": round(time.perf_counter() - start, 1)}))


if __name__ == "__main__":
    main()
