"""DVC stage entry points: each module is a thin ``main`` over one library call (``python -m m3t.stages.<stage>``).

:func:`stage_main` is the one copy of what every stage's ``main`` does: parse ``--params`` / ``--preset``
(and the stage's own options), load and validate params.yaml, call the library, print the result as JSON.
Every MLflow run a stage opens is tagged ``data_version``: the digest of the training corpora's shards as the
stage found them (:func:`m3t.shards.io.data_version`), so that runs are compared only on the same data
(:mod:`m3t.claims`). No stage imports another stage.
"""
from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import Any

from m3t.config import Params, load_params
from m3t.shards.io import data_version


def shards_version(params: Params) -> dict[str, str]:
    """``{"data_version": digest}`` of the training corpora's shard files (train, dev, test) present now; ``{}``
    when there are none yet (the stages that write them)."""
    data = params.data
    files = [folder / f"{split}.parquet" for folder in data.shards_dirs for split in ("train", "dev", "test")]
    files = [f for f in files if f.is_file()]
    return {"data_version": data_version(files)} if files else {}


def stage_main(description: str, run: Callable[[Params, argparse.Namespace], Any], argv: list[str] | None = None,
               options: Callable[[argparse.ArgumentParser], None] | None = None,
               show: Callable[[Any], Any] = lambda result: result) -> Any:
    """Parse the command line, load params (``--params``, ``--preset``), return ``run(params, args)``; what
    ``show(result)`` gives is printed as JSON."""
    from m3t.experiment import disable_telemetry, extra_tags

    disable_telemetry()
    parser = argparse.ArgumentParser(description=description.strip().splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--preset", default="default")
    if options is not None:
        options(parser)
    args = parser.parse_args(argv)
    params = load_params(args.params, preset=args.preset)
    with extra_tags(shards_version(params)):
        result = run(params, args)
    print(json.dumps(show(result), indent=2, sort_keys=True, ensure_ascii=False, default=str))
    return result
