"""train-backtranslation-skeleton: the skeleton judge. Fitted shards of ``data.train_corpora`` posed into the
skeleton of ``sgsa.skeleton`` -> one sign-to-text model per sign language reading normalised skeleton coordinates,
in ``<models>/backtranslation-skeleton`` (:func:`m3t.backtranslation.pipeline.train_and_log` with a
:class:`~m3t.backtranslation.pipeline.SkeletonInput`). It judges PT, SGSA and, posed into the same skeleton, the
SMLM and the ground truth.
"""
from __future__ import annotations

from m3t.backtranslation.pipeline import SkeletonInput, train_and_log
from m3t.body.factory import load_body_model
from m3t.body.skeleton import graph_for
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: train_and_log(
        p.backtranslation, p.backtranslation_train, p.data, p.experiment,
        skeleton=SkeletonInput(load_body_model(p.body), graph_for(p.sgsa.skeleton, p.sgsa.face_points))), argv)


if __name__ == "__main__":
    main()
