"""Serve the deployments against the Prefect server in PREFECT_API_URL (see ``m3t serve``).

    fit-corpus/embedded   the embedded corpus with params.yaml (trigger: prefect deployment run fit-corpus/embedded)
"""
from __future__ import annotations

import argparse

from prefect import serve

from flows.fit_corpus import fit_corpus


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    args = parser.parse_args()
    embedded = fit_corpus.to_deployment(name="embedded", parameters={"params_path": args.params})
    serve(embedded)


if __name__ == "__main__":
    main()
