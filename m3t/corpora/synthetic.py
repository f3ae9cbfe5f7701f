"""The embedded synthetic sign corpus: procedural signing with ground-truth body-model parameters.

Deterministic from a seed and scalable from a handful of clips to thousands. Motion is built in the
body model's own parameter space (it stands in for a real signer in front of a camera):

1. *Calibration* (once per corpus, with the body model): the flexion axis of every finger bone (the
   direction that moves the fingertip toward the palm) and, by inverse kinematics, arm postures that put
   the dominant hand at each sign location (neutral space, chin, forehead, cheek, chest, shoulder) and
   both hands at rest.
2. *Signs* (:mod:`m3t.corpora.synthetic_lexicon`): handshape = per-finger curl, location = calibrated arm
   posture, movement = shoulder/elbow rotation pattern (straight, arc, circle, repeat, tap, hold),
   non-manual = mouthing visemes + brows + eyes as facial-action curves. Two-handed signs mirror the
   dominant arm and hand with the project's one mirroring function.
3. *Clips*: rest -> signs with smooth co-articulated transitions -> rest, per-signer identity (Anny
   phenotypes), speed, amplitude and posture, jittered per sentence and per isolated recording session
   (``performance_jitter``: nobody signs the same sign twice alike; within a session both signs of a
   confusing pair stay manually identical); isolated clips (one sign, ``label``) for recognition and sentence clips for
   production; a camera per clip. Isolated clips and sentences draw from separate random streams, so growing
   one part leaves the other unchanged.
4. *Splits*: sentences cycle through ``sentence_splits`` (default :data:`SPLIT_CYCLE`, 80 / 10 / 10);
   the isolated clips of each sign through ``isolated_splits`` (default 4 / 1 / 1, the cycle shifted by the
   sign's label so that the held-out signer varies), so every sign with six clips
   (``num_signers * isolated_per_sign``) is in every split and recognition is scored on every class.

The study design (``synthetic_corpus`` options, all off by default; the ``study`` preset turns them on). Its
constants (:data:`NATURAL_FACE`) were set from the priors below before any study was run and are not tuned
toward any claim's outcome:

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
  variable events, not in a whole-sign plateau per sign.
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

Rotations of the generator are rotation vectors applied on top of the template pose:
``R = exp(rotvec) @ R_rest`` (world-aligned axes, Anny's ``local-ref`` parameterisation).
Axis legend: T frames, n bones of a stream, F facial actions.
"""
from __future__ import annotations

import json
import shutil
import tempfile
import zipfile
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import roma
import torch

from m3t.atomic import replace_dir
from m3t.body.protocol import BodyModel, Correspondence
from m3t.body.rotations import matrix_to_6d, mirror_rotations, sixd_to_matrix
from m3t.camera import Camera, look_at
from m3t.corpora.clip import Clip
from m3t.corpora.config import SPLIT_CYCLE, SyntheticCorpusConfig
from m3t.corpora.synthetic_lexicon import (
    BROWS,
    CONCEPTS,
    EYES,
    HANDSHAPES,
    LANGUAGES,
    VISEMES,
    SignForm,
    build_lexicon,
    make_sentence,
    zipf_weights,
)
from m3t.dataclass_io import build_dataclass

SENTENCE_SPLITS = ("cycle", "held_out")
FACE_MODELS = ("lexical", "natural")
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
ARM = ("clavicle", "upperarm01", "lowerarm01", "wrist")


@dataclass(frozen=True)
class SyntheticClip:
    clip: Clip
    params: dict[str, np.ndarray]  # modality -> (T, D) float32
    identity: np.ndarray  # (P,)
    camera: Camera


# ----------------------------------------------------------------------------------------- calibration
def _stream_rest(body: BodyModel) -> dict[str, torch.Tensor]:
    return {k: sixd_to_matrix(v[0].reshape(-1, 6)) for k, v in body.rest_params(1).items()
            if body.layout[k].kind == "rotation6d"}


def _to_params(rotvecs: dict[str, torch.Tensor], face: torch.Tensor, rest: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rotation vectors (T, n, 3) on top of the rest rotations -> 6D params (T, n*6), plus the face."""
    out = {k: matrix_to_6d(roma.rotvec_to_rotmat(v) @ rest[k]).reshape(v.shape[0], -1) for k, v in rotvecs.items()}
    out["face"] = face
    return out


def _joint(body: BodyModel, name: str) -> int:
    return body.joint_names.index(name)


@dataclass(frozen=True)
class Calibration:
    finger_axes: np.ndarray  # (15, 3) right-hand flexion axes
    locations: dict[str, np.ndarray]  # location -> (4, 3) right-arm rotvecs
    rest_arm: np.ndarray  # (4, 3) right-arm rotvecs of the resting posture


@torch.no_grad()
def _finger_axes(body: BodyModel, rest: dict[str, torch.Tensor]) -> np.ndarray:
    joints = body.forward(body.rest_params(1), body.default_identity()).joints[0]
    p = lambda n: joints[_joint(body, n)]  # noqa: E731
    toward_thumb = p("finger2-1.R") - p("finger5-1.R")
    axes = []
    for f in range(1, 6):
        direction = p(f"finger{f}-3.R") - p(f"finger{f}-1.R")
        direction = direction / direction.norm()
        palm = torch.linalg.cross(toward_thumb, direction)  # right hand: palm side = thumb x fingers
        palm = palm / palm.norm()
        axis = torch.linalg.cross(direction, palm)
        axes += [axis / axis.norm()] * 3
    axes = torch.stack(axes)
    # The sign of the axis depends on frame conventions: keep the one that curls the fingertip toward the palm.
    probe = {k: torch.zeros(1, len(body.layout[k].labels), 3) for k in rest}
    probe["right_hand"] = 1.2 * axes[None]
    face = torch.zeros(1, body.layout["face"].dim)
    curled = body.forward(_to_params(probe, face, rest), body.default_identity()).joints[0]
    tip_before = p("finger3-3.R") - p("wrist.R")
    tip_after = curled[_joint(body, "finger3-3.R")] - curled[_joint(body, "wrist.R")]
    if float(torch.dot(tip_after - tip_before, palm)) < 0:
        axes = -axes
    return axes.numpy()


def _targets(body: BodyModel) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """3D targets of the right hand's middle knuckle per location (body faces -y, z up), and the rest target."""
    with torch.no_grad():
        out = body.forward(body.rest_params(1), body.default_identity())
    j = lambda n: out.joints[0, _joint(body, n)].numpy()  # noqa: E731
    head, neck = j("head"), j("neck01")
    shoulders = (j("upperarm01.L") + j("upperarm01.R")) / 2
    fwd, right, up = np.array([0, -1.0, 0]), np.array([-1.0, 0, 0]), np.array([0, 0, 1.0])
    chest = shoulders - 0.15 * up + 0.14 * fwd
    face_front = head + 0.13 * fwd
    targets = {
        "neutral": chest + 0.25 * fwd + 0.1 * right - 0.05 * up,
        "neutral_high": chest + 0.25 * fwd + 0.12 * right + 0.12 * up,
        "chest": chest + 0.06 * fwd,
        "chin": (neck + head) / 2 + 0.14 * fwd,
        "forehead": face_front + 0.12 * up + 0.04 * fwd,
        "cheek": face_front + 0.07 * right - 0.02 * up,
        "shoulder": j("upperarm01.L") + 0.1 * fwd + 0.02 * up,
    }
    rest_target = chest - 0.3 * up + 0.12 * fwd + 0.12 * right
    return targets, rest_target


def _arm_ik(body: BodyModel, rest: dict[str, torch.Tensor], targets: np.ndarray, steps: int = 250) -> np.ndarray:
    """Right-arm rotvecs (N, 4, 3) placing the middle knuckle at each target (N, 3); elbow kept low."""
    n = targets.shape[0]
    arm_idx = [body.layout["body"].labels.index(f"{b}.R") for b in ARM]
    # Only two joints matter: a joint-only sparse forward keeps the IK cheap.
    points = body.keypoint_set(Correspondence(("knuckle", "elbow"), np.ones(2, dtype=np.int64),
                                              np.array([_joint(body, "finger3-1.R"), _joint(body, "lowerarm01.R")])))
    rot = torch.zeros(n, 4, 3, requires_grad=True)
    goal = torch.as_tensor(targets, dtype=torch.float32)
    opt = torch.optim.Adam([rot], lr=0.05)
    zeros = {k: torch.zeros(n, len(body.layout[k].labels), 3) for k in rest}
    face = torch.zeros(n, body.layout["face"].dim)
    for _ in range(steps):
        opt.zero_grad()
        body_rv = zeros["body"].clone()
        body_rv[:, arm_idx] = rot
        joints = body.forward_keypoints(_to_params({**zeros, "body": body_rv}, face, rest), body.default_identity(), points)
        loss = ((joints[:, 0] - goal) ** 2).sum(-1).mean() * 100
        loss = loss + 0.002 * (rot ** 2).sum((-1, -2)).mean() + 0.5 * torch.relu(joints[:, 1, 1] - 0.05).mean()
        loss.backward()
        opt.step()
    return rot.detach().numpy()


def calibrate(body: BodyModel) -> Calibration:
    rest = _stream_rest(body)
    targets, rest_target = _targets(body)
    names = list(targets)
    solved = _arm_ik(body, rest, np.stack([targets[k] for k in names] + [rest_target]))
    return Calibration(_finger_axes(body, rest), {k: solved[i] for i, k in enumerate(names)}, solved[-1])


# ----------------------------------------------------------------------------------------- synthesis
@dataclass(frozen=True)
class Signer:
    id: str
    identity: np.ndarray  # (6,) phenotypes
    speed: float
    amplitude: float
    posture: np.ndarray  # (3,) spine rotvec offset


def _smoothstep(x: np.ndarray) -> np.ndarray:
    return x * x * (3 - 2 * x)


def _face_curve(sign: SignForm, frames: int, labels: tuple[str, ...]) -> np.ndarray:
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
    plateau = _smoothstep(np.clip(np.minimum(s, 1 - s) * 5, 0, 1))
    blink = np.exp(-((s - 0.5) / 0.08) ** 2)
    for action, w in {**BROWS[sign.brows], **EYES[sign.eyes]}.items():
        curve = blink if sign.eyes == "blink" and action.startswith("eyeBlink") else plateau
        face[:, index[action]] += amp * w * curve


def _amplitude(rng: np.random.Generator) -> float:
    return float(np.exp(rng.normal(0.0, NATURAL_FACE["amplitude_sigma"])))


def _natural_face_curve(sign: SignForm, frames: int, labels: tuple[str, ...], rng: np.random.Generator) -> np.ndarray:
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
        self.rest = _stream_rest(body)
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
        state["face"] = (_face_curve(sign, frames, labels) if face_rng is None
                         else _natural_face_curve(sign, frames, labels, face_rng))
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
            w = _smoothstep(np.linspace(0, 1, transition + 2)[1:-1])
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
        params = _to_params(rotvecs, torch.as_tensor(state["face"], dtype=torch.float32), self.rest)
        return {k: v.numpy().astype(np.float32) for k, v in params.items()}


def _mirror_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Mirror rotation vectors across the sagittal plane through the project's one mirroring function."""
    r = torch.as_tensor(rotvec, dtype=torch.float32)
    mirrored = sixd_to_matrix(mirror_rotations(matrix_to_6d(roma.rotvec_to_rotmat(r))))
    return roma.rotmat_to_rotvec(mirrored).numpy()


# ----------------------------------------------------------------------------------------- corpus
def _camera(rng: np.random.Generator, size: int) -> Camera:
    """Front-ish view of the upper body: small random yaw / pitch, 2.2-2.8 m away."""
    yaw, pitch = np.deg2rad(rng.uniform(-12, 12)), np.deg2rad(rng.uniform(-6, 10))
    dist = rng.uniform(2.2, 2.8)
    target = np.array([0.0, 0.0, 0.32]) + rng.normal(0, 0.02, 3)
    eye = target + dist * np.array([np.sin(yaw) * np.cos(pitch), -np.cos(yaw) * np.cos(pitch), np.sin(pitch)])
    rot = look_at(eye, target, np.array([0.0, 0.0, 1.0]))
    f = 1.9 * size  # about 0.6 m of body across half the image at 2.5 m
    return Camera(f, f, size / 2, size / 2, tuple(map(tuple, rot)), tuple((-rot @ eye).tolist()), size, size)


def _signers(cfg: SyntheticCorpusConfig, rng: np.random.Generator) -> list[Signer]:
    return [Signer(f"signer{i:02d}", rng.uniform(0.2, 0.8, 6), float(rng.uniform(0.8, 1.25)),
                   float(rng.uniform(0.8, 1.2)), rng.normal(0, np.deg2rad(3), 3)) for i in range(cfg.num_signers)]


def _performance(signer: Signer, rng: np.random.Generator, jitter: float) -> Signer:
    """One performance of ``signer``: speed and amplitude scaled by up to +-``jitter``, posture moved by ~1 deg."""
    if jitter <= 0:
        return signer
    return Signer(signer.id, signer.identity, signer.speed * float(rng.uniform(1 - jitter, 1 + jitter)),
                  signer.amplitude * float(rng.uniform(1 - jitter, 1 + jitter)),
                  signer.posture + rng.normal(0, np.deg2rad(1.0), 3))


def _check(cfg: SyntheticCorpusConfig) -> None:
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


def generate_corpus(cfg: SyntheticCorpusConfig, body: BodyModel) -> list[SyntheticClip]:
    """All clips of the corpus (isolated signs first, then sentences per language), deterministic from the seed."""
    _check(cfg)
    rng = np.random.default_rng(cfg.seed)
    lexicon = build_lexicon(cfg.num_signs, cfg.confusing_pairs, rng)
    signers = _signers(cfg, rng)
    unseen = {s.id for s in signers[len(signers) - cfg.held_out_signers:]} if cfg.held_out_signers else set()
    seen_signers = [s for s in signers if s.id not in unseen]
    synth = Synthesiser(body, calibrate(body), cfg)
    face = (FaceStyle.draw(body.layout["face"].labels, [s.id for s in signers], np.random.default_rng([cfg.seed, 4]))
            if cfg.face_model == "natural" else None)
    clips: list[SyntheticClip] = []

    def add(clip_id, signs, signer, performance, language, text, label, extra, split, part_rng):
        if unseen:
            extra = [*extra, ("signer_seen", "false" if signer.id in unseen else "true")]
        clip = Clip(id=clip_id, corpus="synthetic", split=split, language=language, signer=signer.id, text=text,
                    gloss=" ".join(s.gloss for s in signs), media=f"motion/{clip_id}.npz", fps=cfg.fps, label=label,
                    extra=tuple(extra))
        face_rng = np.random.default_rng([cfg.seed, 5, zlib.crc32(clip_id.encode())]) if face is not None else None
        clips.append(SyntheticClip(clip, synth.synthesise(signs, performance, face, face_rng),
                                   signer.identity.astype(np.float32), _camera(part_rng, cfg.image_size)))

    isolated_rng, sentence_rng = np.random.default_rng([cfg.seed, 1]), np.random.default_rng([cfg.seed, 2])
    # the rep-th isolated recording session of each signer: one performance for every sign, so the two signs
    # of a confusing pair stay manually identical within a session
    sessions = {(s.id, rep): _performance(s, isolated_rng, cfg.performance_jitter)
                for rep in range(cfg.isolated_per_sign) for s in signers}
    cycle = cfg.isolated_splits
    first_of_pair: dict[int, int] = {}
    for label, sign in enumerate(lexicon):
        k = 0
        shift = first_of_pair.setdefault(sign.pair, label) if cfg.twins_share_split and sign.pair >= 0 else label
        for rep in range(cfg.isolated_per_sign):
            for signer in signers:
                extra = [("kind", "isolated"), ("group", sign.group), ("pair", str(sign.pair))]
                split = "test" if signer.id in unseen else cycle[(k + shift) % len(cycle)]
                add(f"iso-{sign.gloss.lower()}-{signer.id}-{rep}", [sign], signer, sessions[(signer.id, rep)], "ISO-SYN",
                    CONCEPTS[sign.gloss][1], label, extra, split, isolated_rng)
                k += 1
    by_gloss = {s.gloss: s for s in lexicon}
    weights = zipf_weights(lexicon, cfg.gloss_zipf, np.random.default_rng([cfg.seed, 3])) if cfg.gloss_zipf else None
    if cfg.sentence_split == "cycle":
        for language in cfg.languages:
            for i in range(cfg.sentences_per_language):
                length = int(sentence_rng.integers(cfg.min_glosses, cfg.max_glosses + 1))
                text, glosses = make_sentence(lexicon, language, length, sentence_rng, weights)
                signer = signers[int(sentence_rng.integers(len(signers)))]
                performance = _performance(signer, sentence_rng, cfg.performance_jitter)
                split = "test" if signer.id in unseen else cfg.sentence_splits[i % len(cfg.sentence_splits)]
                add(f"{language.lower()}-{i:04d}", [by_gloss[g] for g in glosses], signer, performance, language, text,
                    None, [("kind", "sentence")], split, sentence_rng)
        return clips
    drafts = []  # held_out: draw every sentence, split by composition, then cast the signers
    for language in cfg.languages:
        for i in range(cfg.sentences_per_language):
            length = int(sentence_rng.integers(cfg.min_glosses, cfg.max_glosses + 1))
            drafts.append((language, i, *make_sentence(lexicon, language, length, sentence_rng, weights)))
    splits = held_out_splits([d[3] for d in drafts], np.random.default_rng([cfg.seed, 6]), cfg.sentence_splits)
    for (language, i, text, glosses), split in zip(drafts, splits):
        pool = signers if split == "test" else seen_signers
        signer = pool[int(sentence_rng.integers(len(pool)))]
        performance = _performance(signer, sentence_rng, cfg.performance_jitter)
        add(f"{language.lower()}-{i:04d}", [by_gloss[g] for g in glosses], signer, performance, language, text,
            None, [("kind", "sentence")], split, sentence_rng)
    return clips


def write_corpus(clips: list[SyntheticClip], root: str | Path) -> Path:
    """Write clips.jsonl + motion/<id>.npz into a temp dir, then swap it in (never a half-written corpus)."""
    root = Path(root)
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=root.parent, prefix=f".{root.name}."))
    try:
        (tmp / "motion").mkdir()
        with open(tmp / "clips.jsonl", "w", encoding="utf-8") as fh:
            for c in clips:
                fh.write(json.dumps(asdict(c.clip), ensure_ascii=False) + "\n")
                np.savez(tmp / c.clip.media, identity=c.identity, camera=np.array(json.dumps(c.camera.as_dict())),
                         **{f"param__{k}": v for k, v in c.params.items()})
        replace_dir(tmp, root)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return root


def make_corpus(cfg: SyntheticCorpusConfig, body_cfg, root: str | Path) -> dict:
    """Generate the corpus with the body model of ``body_cfg`` and write it to ``root``; returns the clip counts."""
    from m3t.body.factory import load_body_model

    clips = generate_corpus(cfg, load_body_model(body_cfg))
    write_corpus(clips, root)
    splits: dict[str, int] = {}
    for c in clips:
        splits[c.clip.split] = splits.get(c.clip.split, 0) + 1
    return {"clips": len(clips), "splits": splits}


class SyntheticCorpus:
    """Reader of a written synthetic corpus."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def clips(self) -> list[Clip]:
        index = self.root / "clips.jsonl"
        if not index.exists():
            raise FileNotFoundError(f"{index} not found; generate the corpus first (dvc repro generate-corpus)")
        out = []
        for n, line in enumerate(index.read_text(encoding="utf-8").splitlines(), 1):
            try:
                d = json.loads(line)
                out.append(build_dataclass(Clip, d, "clip"))
            except (ValueError, TypeError) as exc:
                raise ValueError(f"{index} line {n}: not a clip record ({exc})") from exc
        return out

    def ground_truth(self, clip: Clip) -> tuple[dict[str, np.ndarray], np.ndarray, Camera]:
        """(params per modality (T, D), identity (P,), camera) of a clip."""
        path = self.root / clip.media
        if not path.exists():
            raise FileNotFoundError(f"motion file {path} of clip {clip.id} is missing; regenerate the corpus")
        try:
            with np.load(path, allow_pickle=False) as data:
                params = {k.removeprefix("param__"): data[k] for k in data.files if k.startswith("param__")}
                identity, camera = data["identity"], Camera.from_dict(json.loads(str(data["camera"])))
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as exc:
            raise ValueError(f"motion file {path} of clip {clip.id} is corrupt ({exc}); regenerate the corpus") from exc
        return params, identity, camera
