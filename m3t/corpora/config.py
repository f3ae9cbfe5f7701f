"""Config of the embedded synthetic corpus generator (params.yaml ``synthetic_corpus``).

The defaults give the small embedded corpus every embedded-default result was measured on. The ``study`` preset turns on
the design options that make held-out tests honest (:mod:`m3t.corpora.synthetic_design` says how and why):
``sentence_split: held_out`` (no test sentence's concepts in train), ``held_out_signers``, a larger isolated test
share (``isolated_splits``), ``face_model: natural`` and a long-tailed gloss frequency (``gloss_zipf``).
"""
from __future__ import annotations

from dataclasses import dataclass

SPLIT_CYCLE = ("train", "dev", "test") + ("train",) * 7  # 80 / 10 / 10, every split non-empty from 3 clips
ISOLATED_SPLITS = ("train", "train", "train", "train", "dev", "test")  # per sign: 4 / 1 / 1 of every 6 clips


@dataclass(frozen=True)
class SyntheticCorpusConfig:
    seed: int = 0
    num_signs: int = 20
    confusing_pairs: int = 4
    num_signers: int = 3
    sentences_per_language: int = 10
    isolated_per_sign: int = 2  # isolated clips per sign and signer (6 per sign with 3 signers: 4 / 1 / 1 split)
    performance_jitter: float = 0.1  # per clip: speed and amplitude x U(1 -+ jitter), posture + ~1 deg
    languages: tuple[str, ...] = ("ASL-SYN", "DGS-SYN", "CSL-SYN")  # of synthetic_lexicon.LANGUAGES
    fps: float = 25.0
    min_glosses: int = 2
    max_glosses: int = 4
    frames_per_sign: int = 16
    transition_frames: int = 6
    hold_frames: int = 5
    image_size: int = 512
    # --- the study design (defaults: the embedded corpus as it always was)
    sentence_split: str = "cycle"  # cycle: sentence i -> SPLIT_CYCLE[i % 10]; held_out: by concepts (synthetic_design)
    sentence_splits: tuple[str, ...] = SPLIT_CYCLE  # the split cycle of sentences (cycle) or compositions (held_out)
    held_out_signers: int = 0  # the last N signers sign only test clips (tagged ``signer_seen: false``)
    isolated_splits: tuple[str, ...] = ISOLATED_SPLITS  # the split cycle of each sign's isolated clips
    twins_share_split: bool = False  # a confusing pair's two clips of one session go to one split (synthetic_design)
    face_model: str = "lexical"  # lexical: every sign's full non-manual pattern; natural: the statistics of real faces
    gloss_zipf: float = 0.0  # sentence glosses drawn with weight 1 / rank^s (0 = uniform)
