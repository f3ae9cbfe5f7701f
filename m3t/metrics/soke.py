"""SOKE's motion evaluation protocol (2000ZRL/SOKE ``mGPT/metrics/t2m.py``, ``dtw.py``, ``mGPT/data/H2S.py``,
``mGPT/utils/human_models.py``), the ``soke_exact`` mode of :class:`m3t.metrics.motion.MotionMetricsConfig`.

What SOKE does, read from its released code:

- **Posing.** Its data loader drops the global orient and the first 11 body-pose joints of every SMPL-X frame
  (``clip_poses[:, 3 + 3 * 11:]``) and ``feats2joints`` puts zeros back in their place: the pelvis, hips,
  spine1-3, knees, ankles and feet (:data:`SOKE_ZEROED_JOINTS`) never move, so the pelvis and the neck are
  fixed points and the shape is one fixed vector on both sides.
- **Points.** ``joints`` are the SMPL-X layer's ``output.joints`` (144: 55 skeleton joints, 21 vertex points
  of smplx's ``vertex_ids`` - nose, eyes, ears, feet, fingertips - and 68 face landmarks). The body is the 12
  points ``joint_part2idx['upper_body']`` (neck, shoulders, elbows, wrists, ears, eyes, nose: the order of
  :data:`m3t.body.metric_sets.BODY_POINTS`); a hand is 21 points in OpenPose order.
- **Distance.** ``l2_dist_align(x, y, wanted, align_idx=0)``: translate the prediction so that its point 0
  coincides with the reference's, take the ``wanted`` subset, mean point distance. For the body point 0 is
  the pelvis (outside the 12 measured points), for a hand the wrist (inside the 21).
- **Names.** Every region is reported as ``<dataset>_DTW_MPJPE_PA_<body|lhand|rhand>`` although
  ``align_idx=0`` makes it DTW-JPE (a comment in ``t2m.py`` says so). The Procrustes variant
  (``align_idx=None``) is dormant: ``rigid_align`` on *all* 144 points, then the subset. The values are the
  raw accumulated DTW costs in metres, averaged over clips per dataset, with no scaling.

On SMPL-FX (M3T App. C) the zeroing is the model itself: the 11 joints are discarded at build
(:mod:`m3t.body.smplfx_build`, step 6) and the global orient has no stream, so ``spine3``, the root, is a
fixed point rigidly tied to where SMPL-X's pelvis would be. Translating by the root or by the pelvis gives
the same numbers when both sides share the identity, as both :class:`m3t.metrics.scorer.MotionScorer` and SOKE
ensure. :func:`soke_keypoints` lays the body region out as SOKE's arithmetic needs it: the root first,
then the 12 measured points (:data:`BODY_MEASURED`), then the other points its Procrustes also fits.
:func:`zero_soke_joints` zeroes the listed joints of any layout that names them (none on SMPL-FX).

Where this stays apart from SOKE's SMPL-X numbers (the geometry, not the arithmetic):
- the head is FLAME's (SMPL-FX), so nose, eyes and ears are where SMPL-FX puts SMPL-X's vertex ids;
- hand joints are forward-kinematics joints, whereas SOKE regresses the wrist and finger joints from the
  posed vertices with SMPL-X's ``J_regressor`` rows (``make_hand_regressor``); fingertips are the same vertices;
- the Procrustes set has 116 points, not 144: SMPL-FX keeps no position for the pelvis and the 10 other
  discarded joints, and no dynamic face contour; its 51 static landmarks are the dominant vertex of each
  barycentric SMPL-X landmark.

Axis legend: T frames, K points.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from m3t.body.metric_sets import BODY_POINTS, metric_keypoints
from m3t.body.protocol import BodyModel, Correspondence, ModalityLayout
from m3t.body.rotations import identity_6d

SOKE_ZEROED_JOINTS = ("pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
                      "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot")
"""SMPL-X joints 0-11: the global orient (the pelvis' rotation) and the 11 joints of ``body_pose[:33]``."""
SMPLX_VERTEX_JOINTS = (("nose", 9120), ("reye", 9929), ("leye", 9448), ("rear", 616), ("lear", 6),
                       ("LBigToe", 5770), ("LSmallToe", 5780), ("LHeel", 8846),
                       ("RBigToe", 8463), ("RSmallToe", 8474), ("RHeel", 8635),
                       ("lthumb", 5361), ("lindex", 4933), ("lmiddle", 5058), ("lring", 5169), ("lpinky", 5286),
                       ("rthumb", 8079), ("rindex", 7669), ("rmiddle", 7794), ("rring", 7905), ("rpinky", 8022))
"""The 21 vertex points smplx appends to SMPL-X's joints (``vertex_ids['smplx']``, VertexJointSelector order)."""
BODY_MEASURED = slice(1, 1 + len(BODY_POINTS))
"""The 12 measured points of the body region in ``soke_exact`` mode; point 0 is the root."""
SOKE_NAMES = {"dtw_jpe_body_m": "DTW_MPJPE_PA_body", "dtw_jpe_left_hand_m": "DTW_MPJPE_PA_lhand",
              "dtw_jpe_right_hand_m": "DTW_MPJPE_PA_rhand"}
"""Our metric -> the name SOKE's released code reports the same value under (DTW-JPE, despite ``_PA``)."""


class SokeModeError(ValueError):
    """``soke_exact`` asked of a body model that has no SMPL-X joint convention."""


def soke_names(metrics: Mapping[str, float]) -> dict[str, float]:
    """SOKE's names for the metrics of ``metrics`` that SOKE reports (see :data:`SOKE_NAMES`)."""
    return {soke: metrics[ours] for ours, soke in SOKE_NAMES.items() if ours in metrics}


def zero_soke_joints(layout: ModalityLayout, params: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``params`` (B, D_m) with every rotation of :data:`SOKE_ZEROED_JOINTS` set to the identity (a copy).

    A no-op on SMPL-FX, which has no stream for any of them.
    """
    out = dict(params)
    for modality in layout.modalities:
        rows = [i for i, label in enumerate(modality.labels) if label in SOKE_ZEROED_JOINTS]
        if modality.kind != "rotation6d" or not rows or modality.name not in out:
            continue
        value = out[modality.name].clone()
        view = value.reshape(value.shape[0], len(modality.labels), 6)  # (B, joints, 6)
        view[:, rows] = identity_6d(value.shape[0], len(rows), dtype=value.dtype, device=value.device)
        out[modality.name] = value
    return out


def _check_smplfx(body: BodyModel) -> None:
    if body.name != "smplfx":
        raise SokeModeError(
            f"motion metric mode 'soke_exact' reproduces SOKE's SMPL-X evaluation and needs body.model: smplfx; "
            f"body model {body.name!r} has no SMPL-X pelvis, spine or vertex ids to root and measure by. SMPL-FX is "
            "built from the licensed SMPL-X and FLAME files (body.smplx_path, body.flame_path, "
            "body.flame_correspondence_path; see docs/body-models.md), or score with mode 'm3t'")


def soke_keypoints(body: BodyModel) -> dict[str, Correspondence]:
    """:func:`m3t.body.metric_sets.metric_keypoints` with SOKE's body region: the root joint, the 12 measured
    points, then every other point of SOKE's ``output.joints`` that SMPL-FX defines (see the module docstring).
    Raises :class:`SokeModeError` for a body model other than SMPL-FX."""
    _check_smplfx(body)
    sets = metric_keypoints(body)
    measured = sets["body"]
    root = body.joint_parents.index(-1)
    data = body.data  # SMPL-FX's build data (SMPLFXData)
    beyond = [name for name, v in SMPLX_VERTEX_JOINTS if v >= data.num_smplx_vertices]
    if beyond:
        raise SokeModeError(f"SMPL-X vertex points {beyond} lie beyond the model's {data.num_smplx_vertices} SMPL-X "
                            "vertices; build SMPL-FX from SMPLX_NEUTRAL.npz of the SMPL-X v1.1 download")
    # Skeleton joints and smplx's vertex points, less the root and the measured points (in SOKE those are
    # members of the 144), then the landmarks.
    taken = set(zip(measured.kind.tolist(), measured.index.tolist())) | {(1, root)}
    rest = [(name, 1, j) for j, name in enumerate(body.joint_names)] + [(name, 0, v) for name, v in SMPLX_VERTEX_JOINTS]
    rest = [(name, kind, index) for name, kind, index in rest if (kind, index) not in taken]
    rest += [(f"ibug_{18 + k}", 0, int(v)) for k, v in enumerate(data.landmark_vertices)]
    names, kind, index = zip(*rest)
    sets["body"] = Correspondence(
        (body.joint_names[root], *measured.names, *names),
        np.concatenate([[1], measured.kind, kind]).astype(np.int64),
        np.concatenate([[root], measured.index, index]).astype(np.int64))
    return sets
