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
4. *Splits*: sentences cycle through :data:`SPLIT_CYCLE` (80 / 10 / 10); the isolated clips of each sign
   through :data:`ISOLATED_SPLITS` (4 / 1 / 1, the cycle shifted by the sign's label so that the held-out
   signer varies), so every sign with six clips (``num_signers * isolated_per_sign``) is in every split and
   recognition is scored on every class.

Rotations of the generator are rotation vectors applied on top of the template pose:
``R = exp(rotvec) @ R_rest`` (world-aligned axes, Anny's ``local-ref`` parameterisation).
Axis legend: T frames, n bones of a stream, F facial actions.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import roma
import torch

from m3t.body.protocol import BodyModel, Correspondence
from m3t.body.rotations import matrix_to_6d, mirror_rotations, sixd_to_matrix
from m3t.camera import Camera, look_at
from m3t.corpora.clip import Clip
from m3t.corpora.config import SyntheticCorpusConfig
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
)

SPLIT_CYCLE = ("train", "dev", "test") + ("train",) * 7  # 80 / 10 / 10, every split non-empty from 3 clips
ISOLATED_SPLITS = ("train", "train", "train", "train", "dev", "test")  # per sign: 4 / 1 / 1 of every 6 clips
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
        bump = np.clip(np.cos(np.clip((s - c) / width, -0.5, 0.5) * np.pi), 0, 1)
        for action, w in VISEMES[viseme].items():
            face[:, index[action]] += w * bump
    plateau = _smoothstep(np.clip(np.minimum(s, 1 - s) * 5, 0, 1))
    blink = np.exp(-((s - 0.5) / 0.08) ** 2)
    for action, w in {**BROWS[sign.brows], **EYES[sign.eyes]}.items():
        face[:, index[action]] += w * (blink if sign.eyes == "blink" and action.startswith("eyeBlink") else plateau)
    return np.clip(face, 0.0, 1.0)


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

    def _sign_segment(self, sign: SignForm, frames: int, signer: Signer) -> dict[str, np.ndarray]:
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
        state["face"] = _face_curve(sign, frames, self.body.layout["face"].labels)
        return state

    def synthesise(self, signs: list[SignForm], signer: Signer) -> dict[str, np.ndarray]:
        """Rest -> signs (co-articulated) -> rest, as params (T, D) float32 per modality."""
        cfg = self.cfg
        per_sign = max(4, int(round(cfg.frames_per_sign / signer.speed)))
        transition = max(2, int(round(cfg.transition_frames / signer.speed)))
        segments = [self._rest_segment(cfg.hold_frames)]
        segments += [self._sign_segment(s, per_sign, signer) for s in signs]
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


def generate_corpus(cfg: SyntheticCorpusConfig, body: BodyModel) -> list[SyntheticClip]:
    """All clips of the corpus (isolated signs first, then sentences per language), deterministic from the seed."""
    unknown = [lang for lang in cfg.languages if lang not in LANGUAGES]
    if unknown:
        raise ValueError(f"synthetic_corpus.languages: {unknown} unknown; allowed: {', '.join(LANGUAGES)}")
    rng = np.random.default_rng(cfg.seed)
    lexicon = build_lexicon(cfg.num_signs, cfg.confusing_pairs, rng)
    signers = _signers(cfg, rng)
    synth = Synthesiser(body, calibrate(body), cfg)
    clips: list[SyntheticClip] = []

    def add(clip_id, signs, signer, performance, language, text, label, extra, split, part_rng):
        clip = Clip(id=clip_id, corpus="synthetic", split=split, language=language, signer=signer.id, text=text,
                    gloss=" ".join(s.gloss for s in signs), media=f"motion/{clip_id}.npz", fps=cfg.fps, label=label,
                    extra=tuple(extra))
        clips.append(SyntheticClip(clip, synth.synthesise(signs, performance), signer.identity.astype(np.float32),
                                   _camera(part_rng, cfg.image_size)))

    isolated_rng, sentence_rng = np.random.default_rng([cfg.seed, 1]), np.random.default_rng([cfg.seed, 2])
    # the rep-th isolated recording session of each signer: one performance for every sign, so the two signs
    # of a confusing pair stay manually identical within a session
    sessions = {(s.id, rep): _performance(s, isolated_rng, cfg.performance_jitter)
                for rep in range(cfg.isolated_per_sign) for s in signers}
    for label, sign in enumerate(lexicon):
        k = 0
        for rep in range(cfg.isolated_per_sign):
            for signer in signers:
                extra = [("kind", "isolated"), ("group", sign.group), ("pair", str(sign.pair))]
                split = ISOLATED_SPLITS[(k + label) % len(ISOLATED_SPLITS)]
                add(f"iso-{sign.gloss.lower()}-{signer.id}-{rep}", [sign], signer, sessions[(signer.id, rep)], "ISO-SYN",
                    CONCEPTS[sign.gloss][1], label, extra, split, isolated_rng)
                k += 1
    by_gloss = {s.gloss: s for s in lexicon}
    for language in cfg.languages:
        for i in range(cfg.sentences_per_language):
            length = int(sentence_rng.integers(cfg.min_glosses, cfg.max_glosses + 1))
            text, glosses = make_sentence(lexicon, language, length, sentence_rng)
            signer = signers[int(sentence_rng.integers(len(signers)))]
            performance = _performance(signer, sentence_rng, cfg.performance_jitter)
            add(f"{language.lower()}-{i:04d}", [by_gloss[g] for g in glosses], signer, performance, language, text,
                None, [("kind", "sentence")], SPLIT_CYCLE[i % len(SPLIT_CYCLE)], sentence_rng)
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
        old = root.with_name(f".{root.name}.old")
        if root.exists():
            os.replace(root, old)
        os.replace(tmp, root)
        shutil.rmtree(old, ignore_errors=True)
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
                out.append(Clip(**{**d, "extra": tuple(tuple(x) for x in d.get("extra", ()))}))
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
