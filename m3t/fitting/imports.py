"""Already-fitted corpora -> shard rows without tracking or fitting: fit-corpus's path for the media kinds the
trackers refuse (:data:`m3t.trackers.dispatch.REFUSED`).

The engine (:func:`m3t.fitting.per_clip.process_clip`) checks a clip (:func:`check_importable`), reads its source
arrays (:func:`read_source`), addresses the part file by those arrays' bytes and :class:`ImportSettings`, and on a
cache miss builds the row with :func:`import_clip`; part files, cache, quarantine and the quality report are the
engine's, as for fitted clips. What each kind becomes:

==============  ==========================  ==================================================================
media kind      shard layout                conversion (axis-angle -> 6D via rotation matrices)
==============  ==========================  ==================================================================
smplx_params    SMPL-FX                     body: SMPL-X ``body_pose`` of the 10 joints neck .. wrists; hands:
(SOKE)          (:func:`smplfx_layout`),    15 joints each, plus SMPL-X's mean hand unless the corpus says
                needs body.model: smplfx    ``flat_hand_mean``; face: ``expression`` -> the first expression
                                            dims, eyelids 0, ``jaw_pose`` -> the jaw 6D; identity: ``betas``
                                            (first 10, mean over frames) -> ``smplx_beta_*``, FLAME shape 0
flame_params    face only                   face: ``exp`` -> the expression dims, ``eyelids`` (when stored) ->
(MEAD)          (:func:`face_layout`),      the eyelids, ``jaw`` -> the jaw 6D; identity: ``shape`` (first
                needs body.model: smplfx    ``body.flame_shape_dims``, mean over frames) -> ``flame_shape_*``,
                                            SMPL-X betas 0
keypoints       one stream ``sign``         as stored: the format does not say what the D values are (CNN
(slt)           (:func:`sign_layout`)       features in neccam/slt's files), so no joints are made up
==============  ==========================  ==================================================================

Approximations, deliberately: SMPL-X's expression coefficients are copied into FLAME 2020's first expression
dims, but the two bases differ (SMPL-X learned its own 10-100 expression directions), so faces are close, not
equal. Dropped because SMPL-FX has no parameter for them: SMPL-X's global orientation and spine / leg rotations
(SOKE's evaluation zeroes the same joints), translation, eye rotations, betas beyond 10 and SMPL-X's head shape
(SMPL-FX's head is FLAME's); MEAD's ``global_pose`` (head rotation seen from the camera, no body to hang it on),
``cam`` and shape dims beyond ``flame_shape_dims``. Face-only shards are read by the face tokenizer
(``tokenizer_train.extra_face_shards``: their ``face`` column, 108 = SMPL-FX's face); slt feature shards by a
back-translation model with ``input_layout: model`` (it concatenates every stream of the layout), never by SGSA,
which needs a skeleton.

No body model is built: SMPL-FX's layout is fixed by its joint and label names (:func:`smplfx_layout`); only
SOKE's mean hand is read from ``body.smplx_path``.

Frames with a non-finite value take the values of the nearest finite frame (the clip keeps its timing); the
clip's metrics report their fraction (``src_nonfinite_frame_frac``) and every source array's range
(``src_<key>_min`` / ``src_<key>_max``, before conversion: radians, coefficients). A clip with no frames, no
finite frame, or an id that could name a file outside the cache is quarantined with the reason.

Axis legend: T frames, J joints, D per-frame dim.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import roma
import torch

from m3t.body.protocol import Modality, ModalityLayout
from m3t.body.rotations import matrix_to_6d
from m3t.body.smplfx import FACE_LABELS, smplfx_identity_labels, smplfx_layout
from m3t.body.smplfx_build import BODY_JOINTS, BODY_POSE_JOINTS
from m3t.corpora.base import adapter_class
from m3t.corpora.clip import Clip
from m3t.fitting.report import ClipOutcome
from m3t.shards.schema import FittedClip
from m3t.trackers.dispatch import ClipRefused

IMPORT_VERSION = "import-v1"  # bump when a conversion below changes its output
IMPORTERS = {"smplx_params": "SOKE SMPL-X parameters", "flame_params": "MEAD FLAME parameters",
             "keypoints": "slt sign arrays"}  # = the kinds the trackers refuse (m3t.trackers.dispatch.REFUSED)
NEEDS_SMPLFX = ("smplx_params", "flame_params")
SIGN_STREAM = "sign"
EXPRESSION_DIMS, EYELIDS, JAW = 100, slice(100, 102), slice(102, 108)  # SMPL-FX face: 100 expr + 2 lids + jaw 6D
SMPLX_BETAS = 10
# columns of SMPL-X's body_pose (its 21 joints after the pelvis) that SMPL-FX's body stream keeps
BODY_POSE_INDEX = [BODY_JOINTS.index(j) - 1 for j in BODY_POSE_JOINTS]
NO_IDENTITY = ("none",)  # slt arrays carry no identity; a shard row needs a non-empty one


# ------------------------------------------------------------------------------------------ layouts
def face_layout(flame_shape_dims: int) -> ModalityLayout:
    """Face-only shards: SMPL-FX's ``face`` stream and identity (what ``extra_face_shards`` reads)."""
    return ModalityLayout((smplfx_layout(flame_shape_dims)["face"],), smplfx_identity_labels(flame_shape_dims))


def sign_layout(dims: int) -> ModalityLayout:
    """slt ``sign`` arrays: one scalar stream of ``dims`` values per frame, labelled by column."""
    return ModalityLayout((Modality(SIGN_STREAM, "scalar", tuple(f"sign_{i:04d}" for i in range(dims))),),
                          NO_IDENTITY)


def imported_kind(corpus: str) -> str | None:
    """The media kind a corpus' clips are imported as (None: they are tracked and fitted)."""
    return getattr(adapter_class(corpus), "imported_kind", None)


# ------------------------------------------------------------------------------------------ settings
@dataclass(frozen=True, eq=False)
class ImportSettings:
    """What a conversion depends on besides the source arrays (part of the cache key)."""

    body_model: str
    flame_shape_dims: int
    hand_mean: tuple[np.ndarray, np.ndarray] | None = None  # SMPL-X's (left, right) mean hand, (45,) each

    def key(self) -> list:
        mean = None if self.hand_mean is None else [np.asarray(m, np.float64).round(7).tolist() for m in self.hand_mean]
        return [IMPORT_VERSION, self.body_model, self.flame_shape_dims, mean]

    def layout(self, kind: str, dims: int = 0) -> ModalityLayout:
        if kind == "smplx_params":
            return smplfx_layout(self.flame_shape_dims)
        if kind == "flame_params":
            return face_layout(self.flame_shape_dims)
        return sign_layout(dims)


def smplx_hand_mean(smplx_path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``hands_meanl`` / ``hands_meanr`` (45,) of the user's SMPL-X file (``body.smplx_path``)."""
    from m3t.body.model_files import ModelFileError, load_model_arrays

    try:
        arrays = load_model_arrays(smplx_path, required=("hands_meanl", "hands_meanr"))
    except ModelFileError as exc:
        raise ModelFileError(f"{exc}. Importing SMPL-X hand poses stored relative to the mean hand (SMPLer-X / SOKE) "
                             f"needs the SMPL-X file's hands_meanl / hands_meanr (body.smplx_path); if the poses are "
                             f"absolute, set corpora.<corpus>.options.flat_hand_mean: true") from exc
    return (np.asarray(arrays["hands_meanl"], np.float64).reshape(45),
            np.asarray(arrays["hands_meanr"], np.float64).reshape(45))


def import_settings(job, corpus_config: Any) -> ImportSettings:
    """The settings of a fit job (``job``: :class:`m3t.fitting.config.FitJob`); loads the mean hand only when
    an SMPL-X corpus stores poses relative to it and the body model is SMPL-FX (else its clips are refused)."""
    kind = imported_kind(job.corpus)
    needs_mean = (kind == "smplx_params" and job.body.model == "smplfx"
                  and not getattr(corpus_config, "flat_hand_mean", True))
    return ImportSettings(job.body.model, job.body.flame_shape_dims,
                          smplx_hand_mean(job.body.smplx_path) if needs_mean else None)


# ------------------------------------------------------------------------------------------ planning
def plan_import(kind: str, settings: ImportSettings, clips: list[Clip]) -> tuple[ModalityLayout, list[Clip],
                                                                                  list[ClipOutcome]]:
    """The run's shard layout, the clips to import and those refused now (slt clips whose ``sign`` width differs
    from the corpus' most common one: a shard holds one layout)."""
    if kind != "keypoints":
        return settings.layout(kind), clips, []
    widths = Counter(int(c.get("dims", "0")) for c in clips)
    if not widths:
        raise ValueError("no clip of the keypoint corpus was listed (see the listing's quarantine reasons): "
                         "nothing to import, and the width of its 'sign' arrays is unknown")
    dims = min(widths, key=lambda d: (-widths[d], d))
    keep = [c for c in clips if int(c.get("dims", "0")) == dims]
    refused = [ClipOutcome(c.id, c.split, "quarantined", group="other sign width", file=c.media,
                           reason=f"sign has {c.get('dims')} values per frame; {widths[dims]} of the corpus' clips "
                                  f"have {dims} and a shard holds one layout")
               for c in clips if int(c.get("dims", "0")) != dims]
    return settings.layout(kind, dims), keep, refused


def check_importable(clip: Clip, kind: str, settings: ImportSettings) -> None:
    """Refuse (:class:`ClipRefused`) a clip whose id could name a file outside the cache, or whose kind needs
    SMPL-FX under another body model."""
    if clip.id in ("", ".", "..") or any(c in clip.id for c in ("/", "\\", "\0")):
        raise ClipRefused("unsafe clip id", f"clip id {clip.id!r} is empty, '.' or '..', or holds a path separator; "
                          f"it would name a file outside the cache: rename the clip in {clip.media}")
    if kind in NEEDS_SMPLFX and settings.body_model != "smplfx":
        raise ClipRefused("needs body.model: smplfx",
                          f"clip {clip.id}: {IMPORTERS[kind]} are imported into SMPL-FX streams, which needs "
                          f"body.model: smplfx (it is {settings.body_model!r})")


def read_source(clip: Clip, kind: str, corpus) -> dict[str, np.ndarray]:
    """The clip's source arrays, (T, D) each, read by its adapter's ``source(clip)`` (``corpus``: the listing
    adapter; SOKE: SMPL-X keys, MEAD: FLAME keys, slt: ``sign``)."""
    if not hasattr(corpus, "source"):
        raise ClipRefused("no source reader", f"clip {clip.id}: corpus {corpus.name!r} lists {kind} clips but its "
                          f"adapter cannot read them (no source() method)")
    return corpus.source(clip)


# ------------------------------------------------------------------------------------------ conversion
def _held_finite(arrays: dict[str, np.ndarray], clip_id: str) -> tuple[dict[str, np.ndarray], float]:
    """Arrays with every non-finite frame replaced by the nearest finite frame, and the replaced fraction."""
    frames = {a.shape[0] for a in arrays.values()}
    if len(frames) != 1 or 0 in frames:
        raise ClipRefused("no frames", f"clip {clip_id}: source arrays have {sorted(frames)} frames; expected the "
                          f"same T > 0 in every array")
    finite = np.logical_and.reduce([np.isfinite(a).all(axis=1) for a in arrays.values()])  # (T,)
    good = np.flatnonzero(finite)
    if not len(good):
        raise ClipRefused("no finite frame", f"clip {clip_id}: every one of its {len(finite)} frames holds NaN or "
                          f"inf; re-export the clip")
    idx = np.arange(len(finite))
    pos = np.searchsorted(good, idx)
    left, right = good[np.maximum(pos - 1, 0)], good[np.minimum(pos, len(good) - 1)]
    nearest = np.where(np.abs(idx - left) <= np.abs(right - idx), left, right)  # ties: the earlier frame
    return {k: a[nearest] for k, a in arrays.items()}, float(1.0 - finite.mean())


def axis_angle_to_6d(aa: np.ndarray) -> np.ndarray:
    """(T, J*3) axis-angle -> (T, J*6) float32 6D rotations (computed in float64)."""
    rotvec = torch.as_tensor(aa, dtype=torch.float64).reshape(aa.shape[0], -1, 3)  # (T, J, 3)
    return matrix_to_6d(roma.rotvec_to_rotmat(rotvec)).reshape(aa.shape[0], -1).float().numpy()


def _smplx_to_smplfx(src: dict[str, np.ndarray], settings: ImportSettings) -> tuple[dict, np.ndarray]:
    frames = src["body_pose"].shape[0]
    body = src["body_pose"].reshape(frames, 21, 3)[:, BODY_POSE_INDEX].reshape(frames, -1)  # (T, 30)
    mean = settings.hand_mean or (0.0, 0.0)  # smplx adds the mean hand to the pose in axis-angle (flat_hand_mean=False)
    hands = {"left_hand": src["left_hand_pose"].astype(np.float64) + mean[0],
             "right_hand": src["right_hand_pose"].astype(np.float64) + mean[1]}
    face = np.zeros((frames, len(FACE_LABELS)), np.float32)
    expr = min(src["expression"].shape[1], EXPRESSION_DIMS)
    face[:, :expr] = src["expression"][:, :expr]
    face[:, JAW] = axis_angle_to_6d(src["jaw_pose"])
    params = {"body": axis_angle_to_6d(body), **{k: axis_angle_to_6d(v) for k, v in hands.items()}, "face": face}
    identity = np.zeros(SMPLX_BETAS + settings.flame_shape_dims, np.float32)
    betas = src["betas"][:, :SMPLX_BETAS]
    identity[: betas.shape[1]] = betas.mean(0)
    return params, identity


def _flame_to_face(src: dict[str, np.ndarray], settings: ImportSettings, clip_id: str) -> tuple[dict, np.ndarray]:
    frames, expr = src["exp"].shape
    if expr > EXPRESSION_DIMS:
        raise ClipRefused("too many expression dims", f"clip {clip_id}: 'exp' has {expr} columns; FLAME 2020 has "
                          f"{EXPRESSION_DIMS} expression coefficients")
    face = np.zeros((frames, len(FACE_LABELS)), np.float32)
    face[:, :expr] = src["exp"]
    if "eyelids" in src:
        face[:, EYELIDS] = src["eyelids"]
    face[:, JAW] = axis_angle_to_6d(src["jaw"])
    identity = np.zeros(SMPLX_BETAS + settings.flame_shape_dims, np.float32)
    shape = src["shape"][:, : settings.flame_shape_dims]
    identity[SMPLX_BETAS: SMPLX_BETAS + shape.shape[1]] = shape.mean(0)
    return {"face": face}, identity


def import_clip(clip: Clip, kind: str, source: dict[str, np.ndarray], key: str,
                settings: ImportSettings) -> tuple[FittedClip, dict[str, Any]]:
    """The shard row of one clip from its source arrays, and its record (``init_source``: what was imported)."""
    held, nonfinite = _held_finite(source, clip.id)
    metrics = {"src_nonfinite_frame_frac": nonfinite}
    for name, values in sorted(held.items()):
        metrics[f"src_{name}_min"], metrics[f"src_{name}_max"] = float(values.min()), float(values.max())
    if kind == "smplx_params":
        params, identity = _smplx_to_smplfx(held, settings)
        body_model = "smplfx"
        metrics["src_betas_frame_std"] = float(held["betas"].std(axis=0).mean())  # should be ~0: one signer
    elif kind == "flame_params":
        params, identity = _flame_to_face(held, settings, clip.id)
        body_model = "smplfx"
        metrics["src_shape_frame_std"] = float(held["shape"].std(axis=0).mean())
    else:
        params, identity, body_model = {SIGN_STREAM: held[SIGN_STREAM]}, np.zeros(len(NO_IDENTITY), np.float32), "none"
    fitted = FittedClip(clip=clip, key=key, params=params, identity=identity, camera={}, metrics=metrics,
                        body_model=body_model)
    return fitted, {"init_source": f"imported: {IMPORTERS[kind]}, no tracking or fitting"}
