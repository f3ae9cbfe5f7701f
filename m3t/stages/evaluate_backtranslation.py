"""evaluate-backtranslation: the ground-truth upper bound of M3T Tab. 2 - the fitted motion of a split (default
test) back-translated by the trained models and scored with SL-T's BLEU-1..4 / ROUGE-L, in
``<metrics>/backtranslation`` (:func:`m3t.backtranslation.pipeline.evaluate_and_log`).
"""
from __future__ import annotations

from m3t.backtranslation.pipeline import evaluate_and_log
from m3t.stages import stage_main


def main(argv: list[str] | None = None) -> dict:
    return stage_main(
        __doc__, lambda p, args: evaluate_and_log(p.backtranslation, p.data, p.experiment, args.split), argv,
        options=lambda parser: parser.add_argument("--split", default="test", choices=("train", "dev", "test")),
        show=lambda summary: {k: v for k, v in summary.items() if k.count("/") < 2 or k.endswith("/bleu4")})


if __name__ == "__main__":
    main()
