"""The 240-d SMPL-X input of the public SignSparK back-translation scorer, from a body model's parameters.

Source: SignSparK_BT (github.com/JianHe0628/SignSparK_BT, ``README.md`` "Data" table and
``signspark_bt/data/lmdb_dataset.py`` ``read_features``: ``body_features[:, 66:]`` + ``left_features[:, :90]`` +
``right_features[:, :90]``), with the feature meaning from SignSparK (github.com/JianHe0628/SignSparK,
``DATA.md`` record schema and ``tools/visualize.py`` ``build_smplx_input`` / ``rot6d_to_matrix``):

- ``body_features`` is SMPL-X ``body_pose`` (21 joints, no global orient) in 6D; the first 11 (hips, spine,
  knees, ankles, feet; ``66 = 11 x 6``) are dropped, leaving 10 joints x 6 = 60, in SMPL-X order: neck,
  left_collar, right_collar, head, left/right shoulder, left/right elbow, left/right wrist;
- each hand: the 15 SMPL-X / MANO finger joints x 6 = 90 (index, middle, pinky, ring, thumb; 3 each), relative
  to the flat hand (``flat_hand_mean=True``), the left hand in SMPL-X's own left-hand axes (not mirrored);
- 6D = the first two **rows** of the rotation matrix, ``(r00, r01, r02, r10, r11, r12)`` (Zhou et al. as in
  pytorch3d; SignSparK's ``rot6d_to_matrix`` stacks the Gram-Schmidt vectors as rows). This project stores the
  first two **columns** (:mod:`m3t.body.rotations`), so every joint goes through its rotation matrix.

The face is not part of it. A layout can be converted when its ``body`` stream has the 10 SMPL-X joints by name
and its hand streams the SMPL-X finger joints (SMPL-FX does: its joints are SMPL-X's, parent-relative in
SMPL-X's axes); anything else (the Anny body) is refused with the missing joints named.

Axis legend: T frames, J joints.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from m3t.body.protocol import ModalityLayout
from m3t.body.rotations import sixd_to_matrix
from m3t.body.smplfx_build import BODY_JOINTS, hand_joint_names

SMPLX_BODY_POSE = BODY_JOINTS[1:22]  # SMPL-X body_pose: 21 joints after the pelvis
SIGNSPARK_BODY = SMPLX_BODY_POSE[11:]  # neck .. right_wrist: the 10 joints SignSparK keeps
SIGNSPARK_STREAMS = (("body", SIGNSPARK_BODY), ("left_hand", hand_joint_names("left")),
                     ("right_hand", hand_joint_names("right")))
SMPLX240_DIM = 6 * sum(len(joints) for _, joints in SIGNSPARK_STREAMS)  # 60 + 90 + 90


def smplx240_slots() -> list[tuple[str, str]]:
    """(stream, joint) of each 6-d slot of the 240-d vector, in order."""
    return [(stream, joint) for stream, joints in SIGNSPARK_STREAMS for joint in joints]


def smplx240_index(layout: ModalityLayout, layout_name: str = "layout") -> dict[str, np.ndarray]:
    """Per stream, the index (in the layout's labels) of each joint SignSparK takes, in SignSparK's order.

    Raises
    ------
    ValueError
        Naming ``layout_name`` and the joints it lacks, when the layout is not SMPL-X based.
    """
    out, missing = {}, []
    for stream, joints in SIGNSPARK_STREAMS:
        if stream not in layout.names or layout[stream].kind != "rotation6d":
            missing.append(f"{stream}: no 6D rotation stream named {stream!r}")
            continue
        labels = {name: i for i, name in enumerate(layout[stream].labels)}
        absent = [j for j in joints if j not in labels]
        if absent:
            missing.append(f"{stream}: {', '.join(absent)}")
            continue
        out[stream] = np.array([labels[j] for j in joints])
    if missing:
        raise ValueError(f"the {layout_name} body layout cannot give SignSparK's 240-d SMPL-X input: it lacks the "
                         f"SMPL-X joints {'; '.join(missing)}. Use backtranslation.input_layout: model, or fit the "
                         "corpus with an SMPL-X based body (body.model: smplfx)")
    return out


def columns_to_rows_6d(sixd: torch.Tensor) -> torch.Tensor:
    """This project's column 6D ``(..., 6)`` -> SignSparK's row 6D ``(..., 6)`` of the same rotation."""
    return sixd_to_matrix(sixd)[..., :2, :].reshape(*sixd.shape[:-1], 6)


def to_smplx240(params: Mapping[str, np.ndarray], layout: ModalityLayout, layout_name: str = "layout") -> np.ndarray:
    """(T, 240) float32 SignSparK input from per-frame parameters ``{stream: (T, D_stream)}`` of ``layout``."""
    index = smplx240_index(layout, layout_name)
    parts = []
    for stream, _ in SIGNSPARK_STREAMS:
        values = torch.as_tensor(np.asarray(params[stream], dtype=np.float32))
        joints = values.reshape(values.shape[0], values.shape[1] // 6, 6)[:, torch.as_tensor(index[stream])]
        parts.append(columns_to_rows_6d(joints).reshape(values.shape[0], len(index[stream]) * 6))  # (T, J*6)
    return torch.cat(parts, dim=-1).numpy().astype(np.float32)
