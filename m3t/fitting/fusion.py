"""Fuse per-modality 3D tracker streams into one body-model initialisation, then refine (M3T App. 0.C).

The paper extracts each modality with a dedicated tracker (NLF: body, WiLoR: hands, Pixel3DMM: face),
fuses them and refines everything jointly against 2D keypoints (:func:`m3t.fitting.fit.fit_track`).
Fusion is per modality and per frame:

1. every candidate :class:`Stream` (values in the body's modality layout, a confidence per frame) is
   tried in priority order (hands: WiLoR, then NLF's hands); the
   first one whose confidence reaches ``min_confidence`` gives the frame;
2. frames that no stream covers are filled: gaps of at most ``max_gap`` frames between two covered
   frames are interpolated (rotations joint by joint along the geodesic, scalars linearly), longer gaps
   and the clip ends hold the nearest covered value, and a modality no stream covers at all stays at the
   rest pose; :attr:`FusedInit.source` flags every frame (stream index, or ``INTERPOLATED`` / ``HELD`` / ``REST``);
3. the identity is the per-signer median: SMPL-X betas from NLF, FLAME shape from Pixel3DMM.

The fused parameters become ``Track.init`` (what ``L_reg`` pulls toward) and the identity the starting
identity of the refinement. Converters from tracker estimates need a layout whose rotation labels are
SMPL-X joint names (SMPL-FX's); other body models must supply their own streams.

Axis legend: T frames, D modality dim, n joints of a stream.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import roma
import torch

from m3t.body.protocol import BodyModel, ModalityLayout
from m3t.body.smplfx_build import SMPLX_JOINTS
from m3t.fitting.fit import FitResult, FittingConfig, fit_track
from m3t.trackers.external import BodyEstimates, FaceEstimates, HandEstimates, rotmat_to_6d
from m3t.trackers.track import Track

INTERPOLATED, HELD, REST = -1, -2, -3


@dataclass(frozen=True)
class Stream:
    """One tracker's estimate of one modality: values (T, D) in the layout, confidence (T,), 0 = missing."""

    source: str
    values: np.ndarray
    confidence: np.ndarray


@dataclass(frozen=True)
class FusionConfig:
    min_confidence: float = 0.3
    max_gap: int = 12  # frames; longer gaps hold the nearest covered value instead of interpolating


@dataclass(frozen=True)
class FusedInit:
    init: dict[str, np.ndarray]  # modality -> (T, D) float32, usable as Track.init
    source: dict[str, np.ndarray]  # modality -> (T,) int: stream index, INTERPOLATED, HELD or REST
    stream_names: dict[str, tuple[str, ...]]
    identity: np.ndarray | None  # (P,) or None when no tracker gave one


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


def fuse_modality(streams: list[Stream], rest: np.ndarray, rotation: bool, cfg: FusionConfig) -> tuple[np.ndarray, np.ndarray]:
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


def fuse(layout: ModalityLayout, streams: dict[str, list[Stream]], rest: dict[str, np.ndarray], num_frames: int,
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
def _scatter(frames: np.ndarray, values: np.ndarray, conf: np.ndarray, T: int, source: str) -> Stream:
    full = np.full((T, values.shape[1]), np.nan)
    c = np.zeros(T)
    inside = (frames >= 0) & (frames < T)
    full[frames[inside]] = values[inside]
    c[frames[inside]] = conf[inside]
    return Stream(source, full, c)


def _joint_columns(layout: ModalityLayout, name: str) -> list[int]:
    try:
        return [SMPLX_JOINTS.index(label) for label in layout[name].labels]
    except ValueError as exc:
        raise ValueError(f"modality {name!r} is not labelled with SMPL-X joints ({exc}); the tracker converters "
                         "need the smplfx body model") from exc


def nlf_streams(body: BodyEstimates, layout: ModalityLayout, T: int) -> dict[str, Stream]:
    """NLF body (and, as a fallback, hand) streams. Global orient and spine rotations are left to the
    camera (SMPL-FX's root and torso are rigid); the face comes from Pixel3DMM only."""
    out = {}
    for name in ("body", "left_hand", "right_hand"):
        cols = _joint_columns(layout, name)
        out[name] = _scatter(body.frame, rot_to_flat6d(body.rotations[:, cols]), body.confidence, T, f"nlf:{name}")
    return out


def wilor_streams(hands: dict[str, HandEstimates], layout: ModalityLayout, T: int) -> dict[str, Stream]:
    return {f"{side}_hand": _scatter(h.frame, rot_to_flat6d(h.hand_pose), h.confidence, T, f"wilor:{side}")
            for side, h in hands.items()}


def pixel3dmm_stream(face: FaceEstimates, layout: ModalityLayout, T: int) -> Stream:
    values = np.concatenate([face.expression, face.eyelids, rot_to_flat6d(face.jaw[:, None])], axis=1)
    if values.shape[1] != layout["face"].dim:
        raise ValueError(f"Pixel3DMM gives {values.shape[1]} face values; the layout's face has {layout['face'].dim}")
    return _scatter(face.frame, values, np.ones(len(face.frame)), T, "pixel3dmm")


def tracker_identity(layout: ModalityLayout, body: BodyEstimates | None, face: FaceEstimates | None) -> np.ndarray | None:
    """10 SMPL-X betas (median over NLF frames) + FLAME shape (Pixel3DMM), cut to the layout's identity."""
    if body is None and face is None:
        return None
    ident = np.zeros(layout.identity_dim)
    if body is not None and len(body.betas):
        ident[:10] = np.median(body.betas, axis=0)[:10]
    if face is not None:
        n = min(layout.identity_dim - 10, face.shape.shape[0])
        ident[10:10 + n] = face.shape[:n]
    return ident.astype(np.float32)


def fuse_trackers(body_model: BodyModel, num_frames: int, nlf: BodyEstimates | None = None,
                  wilor: dict[str, HandEstimates] | None = None, pixel3dmm: FaceEstimates | None = None,
                  cfg: FusionConfig = FusionConfig()) -> FusedInit:
    """The paper's combination: body from NLF, hands from WiLoR (NLF as fallback), face from Pixel3DMM."""
    layout = body_model.layout
    streams: dict[str, list[Stream]] = {m.name: [] for m in layout.modalities}
    if wilor is not None:
        for name, s in wilor_streams(wilor, layout, num_frames).items():
            streams[name].append(s)
    if pixel3dmm is not None:
        streams["face"].append(pixel3dmm_stream(pixel3dmm, layout, num_frames))
    if nlf is not None:
        for name, s in nlf_streams(nlf, layout, num_frames).items():
            streams[name].append(s)
    rest = {k: v[0].detach().cpu().numpy() for k, v in body_model.rest_params(1).items()}
    return fuse(layout, streams, rest, num_frames, cfg, tracker_identity(layout, nlf, pixel3dmm))


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
    """Joint refinement (L_kp + L_acc + L_reg) of a 2D track from the fused initialisation."""
    if any(v.shape[0] != track.num_frames for v in fused.init.values()):
        raise ValueError(f"fused initialisation and track disagree on the number of frames ({track.num_frames})")
    model = body if fused.identity is None else _WithIdentity(body, fused.identity)
    return fit_track(dataclasses.replace(track, init=fused.init), model, cfg)
