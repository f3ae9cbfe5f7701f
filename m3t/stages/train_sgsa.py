"""train-sgsa: fitted shards of ``data.train_corpora`` seen as skeletons -> the Progressive Transformers baseline
and the Skeletal Graph Self-Attention model (SGSA Sec. 4-5), each selected by dev DTW-JPE, in ``<models>/sgsa``
(:func:`m3t.sgsa.pipeline.train_and_log`).
"""
from __future__ import annotations

from m3t.sgsa.pipeline import train_and_log
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: train_and_log(p.sgsa, p.sgsa_train, p.body, p.data, p.experiment),
                      argv)


if __name__ == "__main__":
    main()
