"""Sign language recognition probe on frozen tokenizer encoder features (M3T Sec. 3.4, Sec. 4.3, App. 0.D.3).

A diagnostic of the motion representation, not a recogniser in its own right: isolated-sign clips are trimmed
to their active signing window (:mod:`~m3t.slr.trim`), encoded by the frozen per-modality FSQ-VAE encoders
(:mod:`~m3t.slr.features`), interleaved per time step and classified by a small transformer
(:mod:`~m3t.slr.model`). The face-less ablation trains the same probe without the face stream; the
confusing / normal subsets of NMFs-CSL (and of the embedded synthetic corpus) tell how much of the accuracy
the face carries (:mod:`~m3t.slr.evaluate`, :mod:`~m3t.slr.table`).

- :mod:`~m3t.slr.config`: ``slr`` (probe + trimming), ``slr_train``, ``slr_evaluate`` sections.
- :mod:`~m3t.slr.train` / :mod:`~m3t.slr.checkpoint`: the trainer and its self-describing checkpoint.
- :mod:`~m3t.slr.pipeline`: the train-slr and evaluate-slr runs behind the stages.
"""
