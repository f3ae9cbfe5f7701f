"""train-backtranslation: fitted shards of ``data.train_corpora`` -> one sign-to-text model per sign language
(M3T App. 0.D.4), each selected by its dev-split BLEU-4, in ``<models>/backtranslation``
(:func:`m3t.backtranslation.pipeline.train_and_log`).
"""
from __future__ import annotations

from m3t.backtranslation.pipeline import train_and_log
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: train_and_log(p.backtranslation, p.backtranslation_train, p.data,
                                                             p.experiment), argv)


if __name__ == "__main__":
    main()
