"""Back-translation (M3T App. 0.D.4): one sign-to-text transformer per sign language, trained on ground-truth
motion, that turns any produced motion back into text scored with SL-T's BLEU / ROUGE-L.

config (dataclasses) -> text (tokenisation, vocabularies, pseudo-glosses) -> smplx240 (SignSparK_BT's input) ->
data (samples, batches) -> model -> decode -> checkpoint -> train -> pipeline (stages' engines, the scorer).
"""
