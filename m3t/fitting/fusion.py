"""Fuse per-modality 3D tracker streams into one body-model initialisation, then refine (M3T App. 0.C).

The paper extracts each modality with a dedicated tracker (NLF: body, WiLoR: hands, Pixel3DMM: face),
fuses them and refines everything jointly against 2D keypoints (:func:`m3t.fitting.fit.fit_track`).
For one clip: :func:`initialise_from_trackers` reads the outputs found beside its media
(:func:`m3t.trackers.external.find_tracker_outputs`) and fuses them, :func:`refine` fits the clip's 2D
track around the result, :func:`describe` summarises where each modality's initialisation came from.
Fusion is per modality and per frame:

1. every candidate :class:`TrackerStream` (values in the body's modality layout, a confidence per frame)
   is tried in priority order (hands: WiLoR, then NLF's hands); the first one whose confidence reaches
   ``min_confidence`` gives the frame;
2. frames that no stream covers are filled: gaps of at most ``max_gap`` frames between two covered
   frames are interpolated (rotations joint by joint along the geodesic, scalars linearly), longer gaps
   and the clip ends hold the nearest covered value, and a modality no stream covers at all stays at the
   rest pose; :attr:`FusedInit.source` flags every frame (stream index, or ``INTERPOLATED`` / ``HELD`` / ``REST``);
3. the identity is the clip's median over its frames (SMPL-X betas from NLF, FLAME shape from Pixel3DMM);
   fused clips are fitted alone, each with its own identity (not pooled per signer).

The fused parameters become ``Track.init`` (what ``L_reg`` pulls toward) and the identity the starting
identity of the refinement.

Body models. The converters take SMPL-X / MANO joint rotations and FLAME face parameters as they are, so
they need a layout labelled with SMPL-X joints, FLAME's 108 face values and SMPL-X / FLAME identity labels:
SMPL-FX's. Anny takes none of the streams: its rotations are relative to an A-pose reference posture
(upper arms ~54 degrees below horizontal, where SMPL-X's zero pose is a T-pose), its arm, spine and neck
chains split SMPL-X's joints into several bones (clavicle + shoulder01, upperarm01 + 02, three neck bones)
and its fingers hang on metacarpals MANO lacks; its face is 52 ARKit-style action weights with no known map
from FLAME's PCA expressions or jaw rotation; its identity is 6 phenotypes (Anny's own SMPL-X bridge is a
separate non-commercial download and maps meshes, not parameters). Copying rotations would be wrong and a
retargeting could not be checked against geometry here, so such body models raise
:class:`FusionUnsupported` and the clip is fitted from its 2D track alone.

Axis legend: T frames, D modality dim, n joints of a stream.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import roma
import torch

from m3t.body.protocol import BodyModel, ModalityLayout
from m3t.body.smplfx import FACE_LABELS
from m3t.body.smplfx_build import SMPLX_JOINTS
from m3t.fitting.config import FittingConfig, FusionConfig
from m3t.fitting.fit import FitResult, fit_track
from m3t.trackers.external import (
    TRACKERS,
    BodyEstimates,
    FaceEstimates,
    HandEstimates,
    TrackerOutputs,
    read_nlf,
    read_pixel3dmm,
    read_wilor,
    rotmat_to_6d,
)
from m3t.trackers.track import Track

INTERPOLATED, HELD, REST = -1, -2, -3
SMPLX_BETAS = tuple(f"smplx_beta_{i}" for i in range(10))
FLAME_SHAPE = "flame_shape_{:03d}"
# What each tracker's converter writes: layout modalities, plus the identity.
TRACKER_TARGETS = {"nlf": ("body", "left_hand", "right_hand", "identity"), "wilor": ("left_hand", "right_hand"),
                   "pixel3dmm": ("face", "identity")}


class FusionUnsupported(ValueError):
    """External tracker outputs that the body model cannot take. ``body_model`` names the model and
    ``unusable`` lists each ``"<tracker> -> <modality>: <reason>"``."""

    def __init__(self, body_model: str, unusable: tuple[str, ...]):
        self.body_model = body_model
        self.unusable = unusable
        super().__init__(f"body model {body_model!r} cannot take " + "; ".join(unusable)
                         + " (the tracker converters need SMPL-FX's SMPL-X / FLAME layout)")


@dataclass(frozen=True)
class TrackerStream:
    """One tracker's estimate of one modality: values (T, D) in the layout, confidence (T,), 0 = missing."""

    source: str
    values: np.ndarray
    confidence: np.ndarray


@dataclass(frozen=True)
class FusedInit:
    init: dict[str, np.ndarray]  # modality -> (T, D) float32, usable as Track.init
    source: dict[str, np.ndarray]  # modality -> (T,) int: stream index, INTERPOLATED, HELD or REST
    stream_names: dict[str, tuple[str, ...]]  # modality -> "<tracker>[:<part>]" per stream, priority order
    identity: np.ndarray | None  # (P,) or None when no tracker gave one
    identity_sources: tuple[str, ...] = ()  # trackers that gave the identity
    outside: dict[str, int] = field(default_factory=dict)  # tracker -> estimates at frames outside the clip


def _interpolate(a: np.ndarray, b: np.ndarray, w: float, rotation: bool) -> np.ndarray:
    if not rotation:
        return (1 - w) * a + w * b
    ra = roma.special_gramschmidt(torch.as_tensor(a, dtype=torch.float64).reshape(-1, 2, 3).transpose(-1, -2))
    rb = roma.special_gramschmidt(torch.as_tensor(b, dtype=torch.float64).reshape(-1, 2, 3).transpose(-1, -2))
    rw = roma.rotmat_slerp(ra, rb, torch.tensor([w], dtype=torch.float64))[0]  # (n, 3, 3)
    return rot_to_flat6d(rw.numpy())


def rot_to_flat6d(rot: np.ndarray) -> np.ndarray:
    """(..., n, 3, 3) -> (..., n * 6) in the project's 6D layout."""
    six = rotmat_to_6d(rot)
    return six.reshape(*six.shape[:-2], -1)


def fuse_modality(streams: list[TrackerStream], rest: np.ndarray, rotation: bool, cfg: FusionConfig) -> tuple[np.ndarray, np.ndarray]:
    """(T, D) values and (T,) source flags of one modality (see the module docstring)."""
    T = streams[0].values.shape[0] if streams else 0
    out = np.tile(rest, (T, 1)).astype(np.float64)
    source = np.full(T, REST, dtype=np.int64)
    for k in reversed(range(len(streams))):  # the highest priority written last
        s = streams[k]
        ok = (s.confidence >= cfg.min_confidence) & np.isfinite(s.values).all(1)
        out[ok] = s.values[ok]
        source[ok] = k
    covered = np.flatnonzero(source >= 0)
    if covered.size == 0:
        return out.astype(np.float32), source
    for t in np.flatnonzero(source < 0):
        after = covered[covered > t]
        before = covered[covered < t]
        if before.size and after.size and after[0] - before[-1] - 1 <= cfg.max_gap:
            a, b = before[-1], after[0]
            out[t] = _interpolate(out[a], out[b], (t - a) / (b - a), rotation)
            source[t] = INTERPOLATED
        else:
            near = before[-1] if (before.size and (not after.size or t - before[-1] <= after[0] - t)) else after[0]
            out[t] = out[near]
            source[t] = HELD
    return out.astype(np.float32), source


def fuse(layout: ModalityLayout, streams: dict[str, list[TrackerStream]], rest: dict[str, np.ndarray], num_frames: int,
         cfg: FusionConfig = FusionConfig(), identity: np.ndarray | None = None) -> FusedInit:
    """Fuse candidate streams per modality; ``rest``: modality -> (D,) rest parameters."""
    init, source, names = {}, {}, {}
    for m in layout.modalities:
        cands = streams.get(m.name, [])
        for s in cands:
            if s.values.shape != (num_frames, m.dim) or s.confidence.shape != (num_frames,):
                raise ValueError(f"stream {s.source!r} for {m.name!r} has shape {s.values.shape} / "
                                 f"{s.confidence.shape}; expected ({num_frames}, {m.dim}) / ({num_frames},)")
        if cands:
            init[m.name], source[m.name] = fuse_modality(cands, rest[m.name], m.kind == "rotation6d", cfg)
        else:
            init[m.name] = np.tile(rest[m.name], (num_frames, 1)).astype(np.float32)
            source[m.name] = np.full(num_frames, REST, dtype=np.int64)
        names[m.name] = tuple(s.source for s in cands)
    return FusedInit(init, source, names, identity)


# ------------------------------------------------------------------------ tracker estimates -> streams
def _scatter(frames: np.ndarray, values: np.ndarray, conf: np.ndarray, T: int, source: str) -> TrackerStream:
    full = np.full((T, values.shape[1]), np.nan)
    c = np.zeros(T)
    inside = (frames >= 0) & (frames < T)
    full[frames[inside]] = values[inside]
    c[frames[inside]] = conf[inside]
    return TrackerStream(source, full, c)


def _joint_columns(layout: ModalityLayout, name: str) -> list[int]:
    try:
        return [SMPLX_JOINTS.index(label) for label in layout[name].labels]
    except ValueError as exc:
        raise ValueError(f"modality {name!r} is not labelled with SMPL-X joints ({exc}); the tracker converters "
                         "need the smplfx body model") from exc


def nlf_streams(body: BodyEstimates, layout: ModalityLayout, T: int) -> dict[str, TrackerStream]:
    """NLF body (and, as a fallback, hand) streams. Global orient and spine rotations are left to the
    camera (SMPL-FX's root and torso are rigid); the face comes from Pixel3DMM only."""
    out = {}
    for name in ("body", "left_hand", "right_hand"):
        cols = _joint_columns(layout, name)
        out[name] = _scatter(body.frame, rot_to_flat6d(body.rotations[:, cols]), body.confidence, T, f"nlf:{name}")
    return out


def wilor_streams(hands: dict[str, HandEstimates], layout: ModalityLayout, T: int) -> dict[str, TrackerStream]:
    return {f"{side}_hand": _scatter(h.frame, rot_to_flat6d(h.hand_pose), h.confidence, T, f"wilor:{side}")
            for side, h in hands.items()}


def pixel3dmm_stream(face: FaceEstimates, layout: ModalityLayout, T: int) -> TrackerStream:
    values = np.concatenate([face.expression, face.eyelids, rot_to_flat6d(face.jaw[:, None])], axis=1)
    if values.shape[1] != layout["face"].dim:
        raise ValueError(f"Pixel3DMM gives {values.shape[1]} face values; the layout's face has {layout['face'].dim}")
    return _scatter(face.frame, values, np.ones(len(face.frame)), T, "pixel3dmm")


def tracker_identity(layout: ModalityLayout, body: BodyEstimates | None, face: FaceEstimates | None) -> np.ndarray | None:
    """SMPL-X betas (median over NLF frames) and FLAME shape (Pixel3DMM) placed by identity label
    (``smplx_beta_<i>``, ``flame_shape_<iii>``); labels no tracker gives stay 0."""
    if body is None and face is None:
        return None
    column = {label: i for i, label in enumerate(layout.identity_labels)}
    given = list(zip(SMPLX_BETAS, np.median(body.betas, axis=0))) if body is not None and len(body.betas) else []
    given += [(FLAME_SHAPE.format(i), v) for i, v in enumerate(face.shape)] if face is not None else []
    ident = np.zeros(layout.identity_dim)
    for label, value in given:
        if label in column:
            ident[column[label]] = value
    return ident.astype(np.float32)


def _outside(frames: np.ndarray, T: int) -> int:
    return int(((frames < 0) | (frames >= T)).sum())


def fuse_trackers(body_model: BodyModel, num_frames: int, nlf: BodyEstimates | None = None,
                  wilor: dict[str, HandEstimates] | None = None, pixel3dmm: FaceEstimates | None = None,
                  cfg: FusionConfig = FusionConfig()) -> FusedInit:
    """The paper's combination: body from NLF, hands from WiLoR (NLF as fallback), face from Pixel3DMM."""
    layout = body_model.layout
    streams: dict[str, list[TrackerStream]] = {m.name: [] for m in layout.modalities}
    outside = {}
    if wilor is not None:
        for name, s in wilor_streams(wilor, layout, num_frames).items():
            streams[name].append(s)
        outside["wilor"] = sum(_outside(h.frame, num_frames) for h in wilor.values())
    if pixel3dmm is not None:
        streams["face"].append(pixel3dmm_stream(pixel3dmm, layout, num_frames))
        outside["pixel3dmm"] = _outside(pixel3dmm.frame, num_frames)
    if nlf is not None:
        for name, s in nlf_streams(nlf, layout, num_frames).items():
            streams[name].append(s)
        outside["nlf"] = _outside(nlf.frame, num_frames)
    rest = {k: v[0].detach().cpu().numpy() for k, v in body_model.rest_params(1).items()}
    fused = fuse(layout, streams, rest, num_frames, cfg, tracker_identity(layout, nlf, pixel3dmm))
    sources = tuple(n for n, e in (("nlf", nlf), ("pixel3dmm", pixel3dmm)) if e is not None)
    return dataclasses.replace(fused, identity_sources=sources, outside={k: outside[k] for k in TRACKERS if k in outside})


# ------------------------------------------------------------------------------------------ one clip
def _target_problem(layout: ModalityLayout, tracker: str, target: str) -> str | None:
    """Why ``tracker``'s converter cannot write ``target`` of this layout (None: it can)."""
    if target == "identity":
        labels = set(layout.identity_labels)
        if tracker == "nlf" and not labels.issuperset(SMPLX_BETAS):
            return f"identity {_few(layout.identity_labels)} lacks the 10 SMPL-X betas 'smplx_beta_<i>'"
        if tracker == "pixel3dmm" and FLAME_SHAPE.format(0) not in labels:
            return f"identity {_few(layout.identity_labels)} has no FLAME shape 'flame_shape_<iii>'"
        return None
    if target not in layout.names:
        return f"the layout has no {target!r} modality"
    m = layout[target]
    if target == "face":
        if m.labels != FACE_LABELS:
            return (f"face is {m.dim} values {_few(m.labels)}, not FLAME's 100 expressions + 2 eyelids + "
                    "jaw rotation")
        return None
    if m.kind != "rotation6d":
        return f"{target} is {m.kind}, the converters write rotations"
    foreign = tuple(label for label in m.labels if label not in SMPLX_JOINTS)
    if foreign:
        return f"{len(foreign)} of its {len(m.labels)} joints are not SMPL-X joints {_few(foreign)}"
    return None


def _few(labels: tuple[str, ...], n: int = 3) -> str:
    return "(" + ", ".join(repr(x) for x in labels[:n]) + (", ...)" if len(labels) > n else ")")


def unusable_outputs(layout: ModalityLayout, trackers: tuple[str, ...]) -> tuple[str, ...]:
    """``"<tracker> -> <modality>: <reason>"`` for every stream of these trackers that the layout cannot take."""
    out = []
    for tracker in trackers:
        for target in TRACKER_TARGETS[tracker]:
            problem = _target_problem(layout, tracker, target)
            if problem is not None:
                out.append(f"{tracker} -> {target}: {problem}")
    return tuple(out)


def initialise_from_trackers(body: BodyModel, outputs: TrackerOutputs, num_frames: int,
                             cfg: FusionConfig = FusionConfig()) -> FusedInit:
    """Read a clip's external tracker outputs and fuse them into an initialisation of ``num_frames`` frames.

    All present outputs are used or none: :class:`FusionUnsupported` when the body model cannot take one of
    their streams (nothing is read then); :class:`m3t.trackers.external.TrackerFileError` for an unreadable
    file. With ``cfg.use_external`` off, or no output present, every modality stays at the rest pose.
    """
    present = outputs.names() if cfg.use_external else ()
    unusable = unusable_outputs(body.layout, present)
    if unusable:
        raise FusionUnsupported(body.name, unusable)
    return fuse_trackers(body, num_frames, nlf=read_nlf(outputs.nlf) if "nlf" in present else None,
                         wilor=read_wilor(outputs.wilor) if "wilor" in present else None,
                         pixel3dmm=read_pixel3dmm(outputs.pixel3dmm) if "pixel3dmm" in present else None, cfg=cfg)


def describe(fused: FusedInit) -> dict[str, float | str]:
    """What a data-quality record shows of a fused initialisation, as flat keys.

    Per modality ``m``: ``init_share_tracker_<m>`` (frames given by a tracker), ``init_share_<tracker>_<m>``
    for each tracker that had a stream for it, ``init_share_interpolated_<m>``, ``init_share_held_<m>``,
    ``init_share_rest_<m>`` (fractions of the clip's frames, summing to 1); ``init_outside_frames_<tracker>``
    (estimates at frame indices outside the clip, not used); ``init_source`` (``"fused: nlf, wilor"``, or
    ``"rest pose: ..."`` when no tracker gave a frame) and ``init_identity``.
    """
    out: dict[str, float | str] = {}
    used: set[str] = set()
    for m, src in fused.source.items():
        T = max(len(src), 1)
        out[f"init_share_tracker_{m}"] = float((src >= 0).sum() / T)
        for k, name in enumerate(fused.stream_names.get(m, ())):
            tracker = name.split(":")[0]
            key = f"init_share_{tracker}_{m}"
            out[key] = float(out.get(key, 0.0)) + float((src == k).sum() / T)
            if (src == k).any():
                used.add(tracker)
        for flag, label in ((INTERPOLATED, "interpolated"), (HELD, "held"), (REST, "rest")):
            out[f"init_share_{label}_{m}"] = float((src == flag).sum() / T)
    for tracker, n in fused.outside.items():
        out[f"init_outside_frames_{tracker}"] = float(n)
    order = [t for t in TRACKERS if t in used]
    if order:
        out["init_source"] = "fused: " + ", ".join(order)
    elif any(fused.stream_names.values()):
        out["init_source"] = "rest pose: no external tracker estimate reached fusion.min_confidence"
    else:
        out["init_source"] = "rest pose: no external tracker outputs"
    out["init_identity"] = ", ".join(fused.identity_sources) if fused.identity is not None else "default"
    return out


class _WithIdentity:
    """A body model whose default identity is the fused one (so refinement starts from it)."""

    def __init__(self, body: BodyModel, identity: np.ndarray):
        self._body = body
        self._identity = torch.as_tensor(identity, dtype=torch.float32)

    def __getattr__(self, name):
        return getattr(self._body, name)

    def default_identity(self) -> torch.Tensor:
        return self._identity.to(self._body.default_identity().device)

    def to(self, device):
        self._body = self._body.to(device)
        return self


def refine(track: Track, fused: FusedInit, body: BodyModel, cfg: FittingConfig) -> FitResult:
    """Joint refinement (L_kp + L_acc + L_reg) of a 2D track around the fused initialisation: the track's own
    ``init`` is replaced by ``fused.init`` and the fit starts from the fused identity. Returns
    :func:`m3t.fitting.fit.fit_track`'s :class:`FitResult`."""
    if any(v.shape[0] != track.num_frames for v in fused.init.values()):
        raise ValueError(f"fused initialisation and track disagree on the number of frames ({track.num_frames})")

    model = body if fused.identity is None else _WithIdentity(body, fused.identity)
    return fit_track(dataclasses.replace(track, init=fused.init), model, cfg)
