"""Config of the embedded synthetic corpus generator (params.yaml ``synthetic_corpus``)."""
from __future__ import annotations

from dataclasses import dataclass


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
