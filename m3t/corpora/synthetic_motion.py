"""Motion of the synthetic corpus: gloss sequences -> per-frame body-model parameters for one signer.

A sign is built in the body model's own parameter space (it stands in for a real signer in front of a camera):
handshape = per-finger curl about the calibrated flexion axes, location = calibrated arm posture
(:mod:`m3t.corpora.synthetic_calibration`), movement = shoulder/elbow rotation pattern (straight, arc, circle,
repeat, tap, hold), non-manual = facial-action curves (:mod:`m3t.corpora.synthetic_face`). Two-handed signs
mirror the dominant arm and hand with the project's one mirroring function. A clip is rest -> signs with smooth
co-articulated transitions -> rest, scaled by the signer's speed and amplitude, with the signer's posture and a
slow idle sway.

Axis legend: T frames, n bones of a stream, F facial actions.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import roma
import torch

from m3t.body.protocol import BodyModel
from m3t.body.rotations import matrix_to_6d, mirror_rotations, sixd_to_matrix
from m3t.corpora.config import SyntheticCorpusConfig
from m3t.corpora.synthetic_calibration import ARM, Calibration, stream_rest, to_params
from m3t.corpora.synthetic_face import (
    FaceStyle,
    face_curve,
    natural_face_curve,
    smoothstep,
)
from m3t.corpora.synthetic_lexicon import HANDSHAPES, SignForm


@dataclass(frozen=True)
class Signer:
    """One signer (or one performance of theirs): body identity, speed, movement amplitude and posture."""

    id: str
    identity: np.ndarray  # (6,) phenotypes
    speed: float
    amplitude: float
    posture: np.ndarray  # (3,) spine rotvec offset


def _movement(sign: SignForm, frames: int, amplitude: float) -> tuple[np.ndarray, np.ndarray]:
    """Shoulder and elbow rotvec offsets (frames, 3) of the movement pattern."""
    s = np.linspace(0.0, 1.0, frames)[:, None]
    axis = np.asarray(sign.axis)
    u = np.cross(axis, [0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.cross(axis, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    amp = 0.18 * amplitude
    zero = np.zeros((frames, 3))
    shoulder = {
        "straight": amp * (s - 0.5) * axis,
        "arc": amp * np.sin(np.pi * s) * axis,
        "circle": 0.7 * amp * (np.cos(2 * np.pi * s) * u + np.sin(2 * np.pi * s) * v),
        "repeat": 0.6 * amp * np.sin(4 * np.pi * s) * axis,
        "tap": zero,
        "hold": zero,
    }[sign.movement]
    elbow = amp * np.maximum(0.0, np.sin(6 * np.pi * s)) * np.array([1.0, 0.0, 0.0]) if sign.movement == "tap" else zero
    return shoulder, elbow


class Synthesiser:
    """Turns gloss sequences into per-frame parameters for one body model."""

    def __init__(self, body: BodyModel, calibration: Calibration, cfg: SyntheticCorpusConfig):
        self.body, self.cal, self.cfg = body, calibration, cfg
        self.rest = stream_rest(body)
        labels = body.layout["body"].labels
        self.arm_r = [labels.index(f"{b}.R") for b in ARM]
        self.arm_l = [labels.index(f"{b}.L") for b in ARM]
        self.spine = [labels.index(b) for b in ("spine03", "spine01", "neck01")]
        self.n = {k: len(body.layout[k].labels) for k in body.layout.names}

    def _state(self, frames: int) -> dict[str, np.ndarray]:
        return {k: np.zeros((frames, self.n[k], 3)) for k in self.rest} | {"face": np.zeros((frames, self.n["face"]))}

    def _rest_segment(self, frames: int) -> dict[str, np.ndarray]:
        state = self._state(frames)
        state["body"][:, self.arm_r] = self.cal.rest_arm
        state["body"][:, self.arm_l] = _mirror_rotvec(self.cal.rest_arm)
        state["right_hand"][:] = 0.25 * self.cal.finger_axes  # relaxed, slightly curled
        state["left_hand"][:] = _mirror_rotvec(state["right_hand"][0])
        return state

    def _sign_segment(self, sign: SignForm, frames: int, signer: Signer,
                      face_rng: np.random.Generator | None = None) -> dict[str, np.ndarray]:
        state = self._rest_segment(frames)
        shoulder, elbow = _movement(sign, frames, signer.amplitude)
        arm = np.repeat(self.cal.locations[sign.location][None], frames, axis=0)  # (frames, 4, 3)
        arm[:, 1] += shoulder
        arm[:, 2] += elbow
        state["body"][:, self.arm_r] = arm
        curls = np.repeat(np.asarray(HANDSHAPES[sign.handshape]), 3)  # (15,) per bone
        hand = curls[:, None] * 1.3 * self.cal.finger_axes  # up to ~75 degrees per phalanx
        state["right_hand"][:] = hand
        if sign.two_handed:
            state["body"][:, self.arm_l] = _mirror_rotvec(arm)
            state["left_hand"][:] = _mirror_rotvec(hand)
        labels = self.body.layout["face"].labels
        state["face"] = (face_curve(sign, frames, labels) if face_rng is None
                         else natural_face_curve(sign, frames, labels, face_rng))
        return state

    def synthesise(self, signs: list[SignForm], signer: Signer, face: FaceStyle | None = None,
                   face_rng: np.random.Generator | None = None) -> dict[str, np.ndarray]:
        """Rest -> signs (co-articulated) -> rest, as params (T, D) float32 per modality. With ``face`` (and its
        per-clip ``face_rng``) the face follows ``face_model: natural``."""
        cfg = self.cfg
        if (face is None) != (face_rng is None):
            raise ValueError("synthesise: the natural face needs both its FaceStyle and a per-clip generator")
        per_sign = max(4, int(round(cfg.frames_per_sign / signer.speed)))
        transition = max(2, int(round(cfg.transition_frames / signer.speed)))
        segments = [self._rest_segment(cfg.hold_frames)]
        segments += [self._sign_segment(s, per_sign, signer, face_rng) for s in signs]
        segments.append(self._rest_segment(cfg.hold_frames))
        pieces = [segments[0]]
        for seg in segments[1:]:
            prev_last = {k: v[-1] for k, v in pieces[-1].items()}
            w = smoothstep(np.linspace(0, 1, transition + 2)[1:-1])
            blend = {k: (1 - w.reshape(-1, *[1] * (v.ndim - 1))) * prev_last[k] + w.reshape(-1, *[1] * (v.ndim - 1)) * v[0]
                     for k, v in seg.items()}
            pieces += [blend, seg]
        state = {k: np.concatenate([p[k] for p in pieces]) for k in pieces[0]}
        T = state["face"].shape[0]
        sway = 0.03 * np.sin(np.linspace(0, 2 * np.pi, T))[:, None] * np.array([1.0, 0.0, 0.3])
        state["body"][:, self.spine] += signer.posture + sway[:, None]
        if face is not None:
            labels = self.body.layout["face"].labels
            state["face"] = np.clip(state["face"] + face.background(signer.id, T, cfg.fps, labels, face_rng), 0, 1)
        rotvecs = {k: torch.as_tensor(state[k], dtype=torch.float32) for k in self.rest}
        params = to_params(rotvecs, torch.as_tensor(state["face"], dtype=torch.float32), self.rest)
        return {k: v.numpy().astype(np.float32) for k, v in params.items()}


def _mirror_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Mirror rotation vectors across the sagittal plane through the project's one mirroring function."""
    r = torch.as_tensor(rotvec, dtype=torch.float32)
    mirrored = sixd_to_matrix(mirror_rotations(matrix_to_6d(roma.rotvec_to_rotmat(r))))
    return roma.rotmat_to_rotvec(mirrored).numpy()
