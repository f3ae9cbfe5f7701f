"""train-smlm: token shards of ``data.train_corpora`` -> the Sign Motion Language Model (M3T Sec. 3.3),
checkpoint selected by mean dev DTW-JPE (:func:`m3t.smlm.train_run.train_and_log`).

``python -m m3t.stages.train_smlm``; ``torchrun --nproc_per_node N -m m3t.stages.train_smlm`` for data-parallel training.
"""
from __future__ import annotations

from m3t.smlm.train_run import train_and_log
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: train_and_log(p.smlm, p.smlm_train, p.body, p.data, p.experiment),
                      argv)


if __name__ == "__main__":
    main()
