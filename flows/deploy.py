"""Serve the deployments against the Prefect server in PREFECT_API_URL (see ``m3t serve``).

    fit-corpus/embedded         the embedded corpus with params.yaml (prefect deployment run fit-corpus/embedded)
    train-tokenizers/embedded   tokenizers + token shards (prefect deployment run train-tokenizers/embedded)
"""
from __future__ import annotations

import argparse

from prefect import serve

from flows.fit_corpus import fit_corpus
from flows.tokenizers import train_tokenizers_flow


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    args = parser.parse_args()
    embedded = fit_corpus.to_deployment(name="embedded", parameters={"params_path": args.params})
    tokenizers = train_tokenizers_flow.to_deployment(name="embedded", parameters={"params_path": args.params})
    serve(embedded, tokenizers)


if __name__ == "__main__":
    main()
