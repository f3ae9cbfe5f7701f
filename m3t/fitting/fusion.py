"""Fuse per-modality 3D tracker streams into one body-model initialisation, then refine (M3T App. 0.C).

The paper extracts each modality with a dedicated tracker (NLF: body, WiLoR: hands, Pixel3DMM: face),
fuses them and refines everything jointly against 2D keypoints (:func:`m3t.fitting.fit.fit_track`).
For one clip: :func:`initialise_from_trackers` reads the outputs found beside its media
(:func:`m3t.trackers.external.find_tracker_outputs`) and fuses them, :func:`refine` fits the clip's 2D
track around the result, :func:`describe` summarises where each modality's initialisation came from.
Fusion is per modality and per frame (:mod:`m3t.fitting.stream_fusion`), from the streams the trackers'
estimates convert to (:mod:`m3t.fitting.tracker_streams`).

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

import numpy as np
import torch

from m3t.body.protocol import BodyModel, ModalityLayout
from m3t.body.smplfx import FACE_LABELS
from m3t.body.smplfx_build import SMPLX_JOINTS
from m3t.fitting.config import FittingConfig, FusionConfig
from m3t.fitting.fit import FitResult, fit_track
from m3t.fitting.stream_fusion import HELD, INTERPOLATED, REST, FusedInit
from m3t.fitting.tracker_streams import (
    FLAME_SHAPE,
    SMPLX_BETAS,
    TRACKER_TARGETS,
    fuse_trackers,
)
from m3t.trackers.external import TRACKERS, TrackerOutputs
from m3t.trackers.nlf_reader import read_nlf
from m3t.trackers.pixel3dmm_reader import read_pixel3dmm
from m3t.trackers.track import Track
from m3t.trackers.wilor_reader import read_wilor


class FusionUnsupported(ValueError):
    """External tracker outputs that the body model cannot take. ``body_model`` names the model and
    ``unusable`` lists each ``"<tracker> -> <modality>: <reason>"``."""

    def __init__(self, body_model: str, unusable: tuple[str, ...]):
        self.body_model = body_model
        self.unusable = unusable
        super().__init__(f"body model {body_model!r} cannot take " + "; ".join(unusable)
                         + " (the tracker converters need SMPL-FX's SMPL-X / FLAME layout)")


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
    their streams (nothing is read then); :class:`m3t.trackers.tracker_files.TrackerFileError` for an unreadable
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
