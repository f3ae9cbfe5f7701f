"""Serve the deployments against the Prefect server in PREFECT_API_URL (see ``m3t serve``).

    fit-corpus/embedded         the embedded corpus with params.yaml (prefect deployment run fit-corpus/embedded)
    train-tokenizers/embedded   tokenizers + token shards (prefect deployment run train-tokenizers/embedded)
    backtranslation/embedded    train the back-translation judges + score the GT motion (before smlm/embedded)
    smlm/embedded               train + generate + evaluate the SMLM (prefect deployment run smlm/embedded)
    slr/embedded                train + evaluate the recognition probes (full and face-less)
    sgsa/embedded               skeleton judge + train PT and SGSA + score them beside the SMLM (after smlm/embedded)
    evaluate-smlm/nightly       re-evaluates the current SMLM checkpoint every night at 03:00 (cron)
"""
from __future__ import annotations

import argparse

from prefect import serve

from flows.backtranslation import backtranslation_flow
from flows.fit_corpus import fit_corpus
from flows.sgsa import sgsa_flow
from flows.slr import slr_flow
from flows.smlm import evaluate_smlm_flow, smlm_flow
from flows.tokenizers import train_tokenizers_flow


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--cron", default="0 3 * * *", help="schedule of evaluate-smlm/nightly")
    args = parser.parse_args()
    embedded = fit_corpus.to_deployment(name="embedded", parameters={"params_path": args.params})
    tokenizers = train_tokenizers_flow.to_deployment(name="embedded", parameters={"params_path": args.params})
    smlm = smlm_flow.to_deployment(name="embedded", parameters={"params_path": args.params})
    nightly = evaluate_smlm_flow.to_deployment(name="nightly", parameters={"params_path": args.params},
                                               cron=args.cron)
    judge = backtranslation_flow.to_deployment(name="embedded", parameters={"params_path": args.params})
    slr = slr_flow.to_deployment(name="embedded", parameters={"params_path": args.params})
    sgsa = sgsa_flow.to_deployment(name="embedded", parameters={"params_path": args.params})
    serve(embedded, tokenizers, judge, smlm, slr, sgsa, nightly)


if __name__ == "__main__":
    main()
