"""The study design of the synthetic corpus: ``synthetic_corpus`` options, all off by default (the ``study`` preset
turns them on), their checks, and the held-out split of sentences by composition.

- ``sentence_split: held_out``: a sentence's *composition* is its set of concepts, whatever the language. The
  distinct compositions, in a seeded random order, cycle through ``sentence_splits``; a dev or test composition
  with a concept no train sentence has moves to train. So every test sentence is a new composition of glosses
  seen in training sentences, and no test sentence (in any language) is a train sentence. With the default
  ``cycle`` split, sentence ``i`` of a language goes to ``sentence_splits[i % 10]``, which lets the same sentence
  land on both sides.
- ``held_out_signers: N``: the last N signers sign only test clips (sentences and isolated signs); every clip is
  tagged ``signer_seen``. Under ``held_out`` they sign test compositions only.
- ``isolated_splits``: the per-sign cycle of isolated clips, e.g. a 12-clip cycle with 5 test slots gives the
  recognition probe >= 10 test clips per class from 24 clips per sign.
- ``twins_share_split``: the two signs of a confusing pair are manually identical within a recording session.
  With the cycle shifted by label (the default), a test clip's manual twin from the same session lands in train
  under the other label, so a probe without the face recalls the wrong twin (below chance); real corpora record
  the two signs apart. With ``true`` both clips of a session share the split (the cycle shifted by the pair's
  first label).
- ``gloss_zipf: s``: sentence glosses are drawn with weight ``1 / rank^s`` (ranks in a seeded random order of
  the lexicon), as sign frequency in real corpora is long-tailed. Isolated clips stay balanced per class, as in
  NMFs-CSL.
- ``face_model: natural``: the face of real signing is near-neutral most of the time and moves in brief,
  variable events, not in a whole-sign plateau per sign (:mod:`m3t.corpora.synthetic_face` gives the model, its
  constants and the priors they come from).

:mod:`m3t.corpora.synthetic` applies these options while it generates the clips.
"""
from __future__ import annotations

import numpy as np

from m3t.corpora.config import SPLIT_CYCLE, SyntheticCorpusConfig
from m3t.corpora.synthetic_lexicon import LANGUAGES

SENTENCE_SPLITS = ("cycle", "held_out")
FACE_MODELS = ("lexical", "natural")


def check_design(cfg: SyntheticCorpusConfig) -> None:
    """Refuse options outside their allowed values, naming the ``synthetic_corpus`` key and what is allowed."""
    unknown = [lang for lang in cfg.languages if lang not in LANGUAGES]
    if unknown:
        raise ValueError(f"synthetic_corpus.languages: {unknown} unknown; allowed: {', '.join(LANGUAGES)}")
    if cfg.sentence_split not in SENTENCE_SPLITS:
        raise ValueError(f"synthetic_corpus.sentence_split: {cfg.sentence_split!r}; allowed: "
                         f"{', '.join(SENTENCE_SPLITS)}")
    if cfg.face_model not in FACE_MODELS:
        raise ValueError(f"synthetic_corpus.face_model: {cfg.face_model!r}; allowed: {', '.join(FACE_MODELS)}")
    if not 0 <= cfg.held_out_signers < cfg.num_signers:
        raise ValueError(f"synthetic_corpus.held_out_signers={cfg.held_out_signers}: must be >= 0 and leave at least "
                         f"one of the {cfg.num_signers} signers for training")
    for key in ("isolated_splits", "sentence_splits"):
        cycle = getattr(cfg, key)
        if not cycle or any(x not in ("train", "dev", "test") for x in cycle) or "train" not in cycle:
            raise ValueError(f"synthetic_corpus.{key}: {list(cycle)}; give a cycle of train / dev / test with train")
    if cfg.gloss_zipf < 0:
        raise ValueError(f"synthetic_corpus.gloss_zipf={cfg.gloss_zipf}: must be >= 0 (0 = uniform)")


def held_out_splits(glosses: list[list[str]], rng: np.random.Generator,
                    cycle: tuple[str, ...] = SPLIT_CYCLE) -> list[str]:
    """Split sentences by composition (their set of concepts): the distinct compositions in a random order go
    through ``cycle``, then a dev / test composition with a concept no train sentence has moves to
    train. Returns each sentence's split: no test composition is in train, every test concept is."""
    keys = [frozenset(g) for g in glosses]
    distinct = list(dict.fromkeys(keys))
    split_of = {distinct[i]: cycle[j % len(cycle)] for j, i in enumerate(rng.permutation(len(distinct)))}
    seen = frozenset().union(*(k for k in distinct if split_of[k] == "train"))
    moved = True
    while moved:  # moving a composition to train can only add concepts: this ends
        moved = False
        for key in distinct:
            if split_of[key] != "train" and not key <= seen:
                split_of[key], seen, moved = "train", seen | key, True
    return [split_of[k] for k in keys]
