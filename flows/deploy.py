"""Serve every deployment against the Prefect server in PREFECT_API_URL (``m3t up`` starts both).

    fit-corpus/<corpus>         one per corpus configured in params.yaml ``corpora`` (fit-corpus/synthetic, ...)
    fit-corpus/embedded         the default corpus (``fit_corpus.default_corpus``)
    train-tokenizers/embedded   tokenizers + token shards
    backtranslation/embedded    train the back-translation judges + score the GT motion (before smlm/embedded)
    smlm/embedded               train + generate + evaluate the SMLM
    evaluate-smlm/embedded      generate + evaluate with the current SMLM checkpoint only
    slr/embedded                train + evaluate the recognition probes (full and face-less)
    sgsa/embedded               skeleton judge + train PT and SGSA + score them beside the SMLM (after smlm/embedded)
    evaluate/nightly            re-evaluates every current checkpoint (runs tagged ``scheduled``) and rebuilds the
                                dashboard, on a cron schedule (``--cron``, default 03:00 every night)

Run one with ``prefect deployment run <flow>/<deployment>``.
"""
from __future__ import annotations

import argparse

from prefect import serve

from flows.backtranslation import backtranslation_flow
from flows.fit_corpus import fit_corpus
from flows.reevaluate import evaluate_flow
from flows.sgsa import sgsa_flow
from flows.slr import slr_flow
from flows.smlm import evaluate_smlm_flow, smlm_flow
from flows.train_tokenizers import train_tokenizers_flow
from m3t.config import load_params

NIGHTLY_CRON = "0 3 * * *"


def deployments(params_path: str = "params.yaml", cron: str = NIGHTLY_CRON) -> list:
    """Every deployment of the platform over ``params_path`` (not yet served)."""
    params = {"params_path": params_path}
    corpora = load_params(params_path).corpora
    out = [fit_corpus.to_deployment(name="embedded", parameters=params)]
    out += [fit_corpus.to_deployment(name=corpus, parameters={**params, "corpus": corpus}) for corpus in corpora]
    out += [flow_.to_deployment(name="embedded", parameters=params)
            for flow_ in (train_tokenizers_flow, backtranslation_flow, smlm_flow, evaluate_smlm_flow, slr_flow,
                          sgsa_flow)]
    out.append(evaluate_flow.to_deployment(name="nightly", parameters=params, cron=cron))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--cron", default=NIGHTLY_CRON, help="schedule of evaluate/nightly")
    args = parser.parse_args()
    serve(*deployments(args.params, args.cron))


if __name__ == "__main__":
    main()
