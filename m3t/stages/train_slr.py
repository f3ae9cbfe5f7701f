"""train-slr: isolated-sign clips of ``slr.corpus`` -> the recognition probe on frozen tokenizer encoder features
(M3T Sec. 3.4, App. 0.D.3), full and face-less, each selected by dev Top-1 (:func:`m3t.slr.pipeline.train_and_log`).
"""
from __future__ import annotations

from m3t.slr.pipeline import train_and_log
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: train_and_log(p.slr, p.slr_train, p.body, p.data, p.experiment),
                      argv)


if __name__ == "__main__":
    main()
