"""The paper's 3D trackers' estimates -> candidate streams in the body's layout, fused into one initialisation
(:func:`fuse_trackers`): body from NLF, hands from WiLoR (NLF's hands as fallback), face from Pixel3DMM.

The identity is the clip's median over its frames (SMPL-X betas from NLF, FLAME shape from Pixel3DMM), placed by
identity label; fused clips are fitted alone, each with its own identity (not pooled per signer). The converters
take SMPL-X / MANO joint rotations and FLAME face parameters as they are, so they need SMPL-FX's layout
(:mod:`m3t.fitting.fusion` says why the other body models cannot take them).

Axis legend: T frames, D modality dim, n joints of a stream.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from m3t.body.protocol import BodyModel, ModalityLayout
from m3t.body.smplfx_build import SMPLX_JOINTS
from m3t.fitting.config import FusionConfig
from m3t.fitting.stream_fusion import FusedInit, TrackerStream, fuse, rot_to_flat6d
from m3t.trackers.external import TRACKERS
from m3t.trackers.nlf_reader import BodyEstimates
from m3t.trackers.pixel3dmm_reader import FaceEstimates
from m3t.trackers.wilor_reader import HandEstimates

SMPLX_BETAS = tuple(f"smplx_beta_{i}" for i in range(10))
FLAME_SHAPE = "flame_shape_{:03d}"
# What each tracker's converter writes: layout modalities, plus the identity.
TRACKER_TARGETS = {"nlf": ("body", "left_hand", "right_hand", "identity"), "wilor": ("left_hand", "right_hand"),
                   "pixel3dmm": ("face", "identity")}


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
