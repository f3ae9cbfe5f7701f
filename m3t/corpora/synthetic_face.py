"""The face of the synthetic corpus's signing: facial-action curves per sign performance, in two models.

``face_model: lexical`` (the default): every sign carries its full non-manual pattern, mouthing visemes as
raised-cosine bumps and brows / eyes as a plateau over the sign.

``face_model: natural``: the face of real signing is near-neutral most of the time and moves in brief, variable
events, not in a whole-sign plateau per sign. Its constants (:data:`NATURAL_FACE`) were set from the priors below
before any study was run and are not tuned toward any claim's outcome:

- Mouthings are brief (40-90 % of their viseme's slot) with a log-normal amplitude (sigma 0.3) per
  performance. A normal sign carries its mouthing in half of its performances, its brows / eyes in 30 %:
  mouthing and brow use vary between signers and sign languages. The confusing pairs' non-manual features
  are lexical: always present (they are the only difference between the two signs), still brief and
  variable.
- Idle motion: every facial action follows its own slow random walk (Ornstein-Uhlenbeck, 0.5 s correlation
  time, absolute value since actions are non-negative activations). Standard deviations fall as
  ``0.05 / rank`` over a seeded random order of the actions, the decaying spectrum of PCA expression
  coefficients: a few actions carry most of the idle variance.
- Spontaneous blinks: Poisson, 0.3 per second (adults blink about 15-20 times a minute), 0.2 s each.
- Every signer has a resting face: three actions held at 0.02-0.12.

Axis legend: F facial actions.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from m3t.corpora.synthetic_lexicon import BROWS, EYES, VISEMES, SignForm

NATURAL_FACE = {  # face_model: natural (fixed before any study run; the module docstring gives the reasons)
    "mouthing_prob_normal": 0.5,  # a normal sign's mouthing is present in this share of its performances
    "brows_prob_normal": 0.3,  # ... its brows / eyes
    "mouthing_duration": (0.4, 0.9),  # a viseme's bump, as a share of its slot
    "amplitude_sigma": 0.3,  # log-normal spread of an event's amplitude
    "idle_std": 0.05,  # the idle random walk of the most mobile action; the k-th: idle_std / k
    "idle_tau_s": 0.5,
    "blink_rate_hz": 0.3,
    "blink_s": 0.2,
    "rest_actions": 3,
    "rest_range": (0.02, 0.12),
}


def smoothstep(x: np.ndarray) -> np.ndarray:
    """Smooth 0 -> 1 ease (zero slope at both ends) of ``x`` in [0, 1]."""
    return x * x * (3 - 2 * x)


def face_curve(sign: SignForm, frames: int, labels: tuple[str, ...]) -> np.ndarray:
    """(frames, F) facial actions: visemes as raised-cosine bumps, brows/eyes as a plateau."""
    face = np.zeros((frames, len(labels)), dtype=np.float32)
    index = {name: i for i, name in enumerate(labels)}
    s = np.linspace(0.0, 1.0, frames)
    centres = (np.arange(len(sign.mouthing)) + 0.5) / len(sign.mouthing)
    width = 1.0 / len(sign.mouthing)
    for viseme, c in zip(sign.mouthing, centres):
        bump = _bump(s, c, width)
        for action, w in VISEMES[viseme].items():
            face[:, index[action]] += w * bump
    _add_brows_eyes(face, index, sign, s)
    return np.clip(face, 0.0, 1.0)


def _bump(s: np.ndarray, centre: float, width: float) -> np.ndarray:
    return np.clip(np.cos(np.clip((s - centre) / width, -0.5, 0.5) * np.pi), 0, 1)


def _add_brows_eyes(face: np.ndarray, index: dict[str, int], sign: SignForm, s: np.ndarray, amp: float = 1.0) -> None:
    """Add the sign's brows / eyes pattern (a plateau over the sign; a lexical blink as a bump) to ``face``."""
    plateau = smoothstep(np.clip(np.minimum(s, 1 - s) * 5, 0, 1))
    blink = np.exp(-((s - 0.5) / 0.08) ** 2)
    for action, w in {**BROWS[sign.brows], **EYES[sign.eyes]}.items():
        curve = blink if sign.eyes == "blink" and action.startswith("eyeBlink") else plateau
        face[:, index[action]] += amp * w * curve


def _amplitude(rng: np.random.Generator) -> float:
    return float(np.exp(rng.normal(0.0, NATURAL_FACE["amplitude_sigma"])))


def natural_face_curve(sign: SignForm, frames: int, labels: tuple[str, ...], rng: np.random.Generator) -> np.ndarray:
    """(frames, F) facial actions of one performance under ``face_model: natural``: brief mouthings of variable
    amplitude, present always on confusing signs (lexical) and sometimes on normal ones; brows / eyes likewise."""
    face = np.zeros((frames, len(labels)), dtype=np.float32)
    index = {name: i for i, name in enumerate(labels)}
    s = np.linspace(0.0, 1.0, frames)
    lexical = sign.group == "confusing"
    if lexical or rng.random() < NATURAL_FACE["mouthing_prob_normal"]:
        width = 1.0 / len(sign.mouthing)
        for i, viseme in enumerate(sign.mouthing):
            centre = (i + 0.5 + rng.uniform(-0.1, 0.1)) * width
            bump = _amplitude(rng) * _bump(s, centre, width * rng.uniform(*NATURAL_FACE["mouthing_duration"]))
            for action, w in VISEMES[viseme].items():
                face[:, index[action]] += w * bump
    if lexical or rng.random() < NATURAL_FACE["brows_prob_normal"]:
        _add_brows_eyes(face, index, sign, s, _amplitude(rng))
    return face


@dataclass(frozen=True)
class FaceStyle:
    """The corpus-wide idle spectrum and each signer's resting face (``face_model: natural``)."""

    idle_std: np.ndarray  # (F,)
    rest: dict[str, np.ndarray]  # signer id -> (F,)

    @staticmethod
    def draw(labels: tuple[str, ...], signers: list[str], rng: np.random.Generator) -> FaceStyle:
        f = len(labels)
        idle = NATURAL_FACE["idle_std"] / (1.0 + rng.permutation(f))
        rest = {}
        for signer in signers:
            face = np.zeros(f)
            face[rng.choice(f, NATURAL_FACE["rest_actions"], replace=False)] = rng.uniform(
                *NATURAL_FACE["rest_range"], NATURAL_FACE["rest_actions"])
            rest[signer] = face
        return FaceStyle(idle, rest)

    def background(self, signer: str, frames: int, fps: float, labels: tuple[str, ...],
                   rng: np.random.Generator) -> np.ndarray:
        """(frames, F): the signer's resting face + idle random walks + spontaneous blinks."""
        a = float(np.exp(-1.0 / (NATURAL_FACE["idle_tau_s"] * fps)))
        steps = rng.normal(0.0, 1.0, (frames, len(labels))) * self.idle_std * np.sqrt(1 - a * a)
        walk = np.empty_like(steps)
        walk[0] = rng.normal(0.0, 1.0, len(labels)) * self.idle_std
        for t in range(1, frames):
            walk[t] = a * walk[t - 1] + steps[t]
        face = self.rest[signer] + np.abs(walk)
        t = np.arange(frames)
        length = NATURAL_FACE["blink_s"] * fps
        blinks = np.zeros(frames)
        for start in rng.uniform(0, frames, rng.poisson(NATURAL_FACE["blink_rate_hz"] * frames / fps)):
            blinks = np.maximum(blinks, rng.uniform(0.8, 1.0) * _bump(t, start + length / 2, length))
        for side in ("eyeBlinkLeft", "eyeBlinkRight"):
            if side in labels:
                face[:, labels.index(side)] += blinks
        return face
