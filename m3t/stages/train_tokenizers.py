"""train-tokenizers: fitted shards of ``data.train_corpora`` -> one FSQ-VAE (or VQ-VAE baseline) per modality
group -> checkpoints, codebook statistics, token histograms, reconstruction videos (MP4), an MLflow run
(:func:`m3t.tokenizers.pipeline.train_and_log`).

``python -m m3t.stages.train_tokenizers``, or ``torchrun --nproc_per_node N -m m3t.stages.train_tokenizers`` for DDP.
"""
from __future__ import annotations

from m3t.stages import stage_main
from m3t.tokenizers.pipeline import train_and_log


def main(argv: list[str] | None = None) -> dict:
    return stage_main(__doc__, lambda p, args: train_and_log(p.tokenizer, p.tokenizer_train, p.body, p.data,
                                                             p.experiment), argv)


if __name__ == "__main__":
    main()
