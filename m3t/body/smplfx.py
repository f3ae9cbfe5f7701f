"""SMPL-FX (M3T Sec. 3.1, App. 0.C) behind the :class:`m3t.body.protocol.BodyModel` protocol.

Built at load time from the user's licensed files (:mod:`m3t.body.smplfx_build`); nothing licensed ships
with the project. One forward serves the full mesh and a sparse set of keypoints:
``T + B_S(beta) + B_E(psi) + eyelids + B_P(theta)`` -> forward kinematics -> linear blend skinning.

Modality layout (paper Eq. 1):
- ``body``: 10 joints x 6D = 60 (neck, head, collars, shoulders, elbows, wrists)
- ``left_hand`` / ``right_hand``: 15 finger joints x 6D = 90 each (SMPL-X / MANO order: index, middle,
  pinky, ring, thumb; 3 each), relative to the flat hand (no PCA, no hand mean)
- ``face``: 108 = 100 FLAME expression + 2 eyelids (left, right) + the jaw rotation in 6D
Identity: 10 SMPL-X + 100 FLAME shape coefficients (110; ``flame_shape_dims`` changes the FLAME part).

Rotations are SMPL-X's parent-relative joint rotations in its own axes (X = the subject's left), so
:func:`m3t.body.rotations.mirror_rotations` maps a left hand to a right hand exactly as SMPL-X / MANO
mirror (axis-angle ``(x, -y, -z)``). Outputs (joints, vertices) are given in the protocol's frame, Z up and
facing -Y like Anny (SMPL-X's Y-up / +Z-forward frame turned +90 degrees about X), with the root joint
(``spine3``) at the origin; the camera carries the global placement.

Axis legend: B frames, V vertices, J joints, K keypoints, N blendshape directions.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from m3t.body.protocol import (
    BodyOutput,
    Correspondence,
    KeypointIndex,
    Modality,
    ModalityLayout,
    Params,
)
from m3t.body.rotations import identity_6d, sixd_to_matrix
from m3t.body.smplfx_build import (
    BODY_POSE_JOINTS,
    POSED_JOINTS,
    ROOT,
    SMPLFXData,
    SMPLFXFiles,
    build_smplfx,
    hand_joint_names,
)

DATA_DIR = Path(__file__).parent / "data"
# SMPL-X (Y up, +Z forward) -> protocol frame (Z up, -Y forward): +90 degrees about X.
TO_PROTOCOL_FRAME = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
FACE_LABELS = tuple(f"expr_{i:03d}" for i in range(100)) + ("eyelid_left", "eyelid_right") + tuple(
    f"jaw_6d_{i}" for i in range(6))


def _depth_levels(parents: np.ndarray) -> list[torch.Tensor]:
    """Joint indices grouped by depth in the tree (level 0 = root), for batched forward kinematics."""
    depth = np.zeros(len(parents), dtype=np.int64)
    for j, p in enumerate(parents):
        depth[j] = 0 if p < 0 else depth[p] + 1  # parents come before children
    return [torch.as_tensor(np.flatnonzero(depth == d)) for d in range(1, int(depth.max()) + 1)]


def smplfx_identity_labels(flame_shape_dims: int) -> tuple[str, ...]:
    """Identity = 10 SMPL-X betas + ``flame_shape_dims`` FLAME shape coefficients (M3T Eq. 1)."""
    return tuple(f"smplx_beta_{i}" for i in range(10)) + tuple(f"flame_shape_{i:03d}" for i in range(flame_shape_dims))


def smplfx_layout(flame_shape_dims: int = 100) -> ModalityLayout:
    """SMPL-FX's modality layout; fixed by joint and label names, so it needs none of the licensed files (imports
    of already-fitted parameters write shards in it without building the model)."""
    return ModalityLayout(
        modalities=(
            Modality("body", "rotation6d", BODY_POSE_JOINTS),
            Modality("left_hand", "rotation6d", hand_joint_names("left"), mirror_of="right_hand"),
            Modality("right_hand", "rotation6d", hand_joint_names("right"), mirror_of="left_hand"),
            Modality("face", "scalar", FACE_LABELS),
        ),
        identity_labels=smplfx_identity_labels(flame_shape_dims),
    )


class SMPLFXBody(torch.nn.Module):
    """The :class:`m3t.body.protocol.BodyModel` implementation for SMPL-FX (float32, any device)."""

    name = "smplfx"

    def __init__(self, files: SMPLFXFiles, flame_shape_dims: int = 100, neck_rings: int = 5, alignment: str = "eyes"):
        super().__init__()
        data = build_smplfx(files, flame_shape_dims=flame_shape_dims, n_rings=neck_rings, alignment=alignment)
        self.data = data
        self.joint_names = data.joint_names
        self.joint_parents = tuple(int(p) for p in data.parents)
        self.faces = data.faces
        self.layout = smplfx_layout(flame_shape_dims)
        t = torch.as_tensor
        self.register_buffer("template", t(data.template), persistent=False)  # (V, 3)
        self.register_buffer("identity_dirs", t(data.identity_dirs), persistent=False)  # (N_id, V, 3)
        self.register_buffer("face_dirs", t(data.face_dirs), persistent=False)  # (102, V, 3)
        self.register_buffer("pose_dirs", t(data.pose_dirs), persistent=False)  # (41*9, V, 3)
        self.register_buffer("joint_template", t(data.joint_template), persistent=False)  # (J, 3)
        self.register_buffer("joint_identity_dirs", t(data.joint_identity_dirs), persistent=False)  # (N_id, J, 3)
        self.register_buffer("weights", t(data.weights), persistent=False)  # (V, J)
        self.register_buffer("parents", t(data.parents).long(), persistent=False)
        self.register_buffer("to_frame", TO_PROTOCOL_FRAME.clone(), persistent=False)
        index = {n: i for i, n in enumerate(self.joint_names)}
        self._stream_joints = {m.name: torch.tensor([index[j] for j in m.labels])
                               for m in self.layout.modalities if m.kind == "rotation6d"}
        self._jaw = index["jaw"]
        self._posed_joints = torch.tensor([index[j] for j in POSED_JOINTS])
        self._root = index[ROOT]
        self._levels = _depth_levels(data.parents)

    # ------------------------------------------------------------------ parameters
    def rest_params(self, batch: int) -> dict[str, torch.Tensor]:
        device = self.template.device
        out = {m.name: identity_6d(batch, len(m.labels), device=device).reshape(batch, m.dim)
               for m in self.layout.modalities if m.kind == "rotation6d"}
        face = torch.zeros(batch, self.layout["face"].dim, device=device)
        face[:, 102:] = identity_6d(batch, device=device)
        out["face"] = face
        return out

    def default_identity(self) -> torch.Tensor:
        return torch.zeros(self.layout.identity_dim, device=self.template.device)

    # ------------------------------------------------------------------ internals
    def _identity(self, identity: torch.Tensor) -> torch.Tensor:
        return identity.reshape(-1, self.layout.identity_dim).to(self.template.dtype)  # (1|B, N_id)

    def _local_rotations(self, params: Params) -> torch.Tensor:
        """(B, J, 3, 3) parent-relative rotations: streams + jaw, identity elsewhere."""
        batch = self.layout.check(params)
        J = len(self.joint_names)
        rot = torch.eye(3, device=self.template.device, dtype=self.template.dtype).expand(batch, J, 3, 3).clone()
        for name, joints in self._stream_joints.items():
            rot[:, joints.to(rot.device)] = sixd_to_matrix(params[name].reshape(batch, -1, 6))
        rot[:, self._jaw] = sixd_to_matrix(params["face"][:, 102:108])
        return rot

    def _rest_joints(self, coeffs: torch.Tensor) -> torch.Tensor:
        return self.joint_template + torch.einsum("bn,njc->bjc", coeffs, self.joint_identity_dirs)  # (1|B, J, 3)

    def _kinematics(self, rot: torch.Tensor, rest_joints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Global rotations (B, J, 3, 3) and posed joint positions (B, J, 3), level by level."""
        batch = rot.shape[0]
        rest_joints = rest_joints.expand(batch, -1, -1)
        glob_rot = torch.empty_like(rot)
        pos = torch.empty_like(rest_joints)
        glob_rot[:, self._root] = rot[:, self._root]
        pos[:, self._root] = rest_joints[:, self._root]
        for level in self._levels:
            parents = self.parents[level]
            offset = rest_joints[:, level] - rest_joints[:, parents]  # (B, n, 3)
            parent_rot = glob_rot[:, parents]
            pos[:, level] = pos[:, parents] + (parent_rot @ offset[..., None])[..., 0]
            glob_rot[:, level] = parent_rot @ rot[:, level]
        return glob_rot, pos

    def _rest_points(self, coeffs, face, pose_feature, vidx=None) -> torch.Tensor:
        """Rest-pose points (B, K|V, 3) with identity, expression / eyelid and pose-corrective offsets."""
        pick = (lambda x: x) if vidx is None else (lambda x: x[:, vidx])
        template = self.template if vidx is None else self.template[vidx]
        points = template + torch.einsum("bn,nvc->bvc", coeffs, pick(self.identity_dirs))
        points = points + torch.einsum("bn,nvc->bvc", face[:, :102], pick(self.face_dirs))
        return points + torch.einsum("bn,nvc->bvc", pose_feature, pick(self.pose_dirs))

    def _skin(self, points, weights, glob_rot, pos, rest_joints) -> torch.Tensor:
        """Linear blend skinning of rest points (B, K, 3) with weights (K, J) -> (B, K, 3)."""
        batch = glob_rot.shape[0]
        trans = pos - (glob_rot @ rest_joints.expand(batch, -1, -1)[..., None])[..., 0]  # (B, J, 3)
        affine = torch.cat([glob_rot.reshape(batch, -1, 9), trans], dim=-1)  # (B, J, 12)
        blended = torch.einsum("kj,bjd->bkd", weights, affine)  # (B, K, 12)
        lin = blended[..., :9].reshape(batch, -1, 3, 3)
        return (lin @ points[..., None])[..., 0] + blended[..., 9:]

    def _posed(self, params: Params, identity: torch.Tensor):
        coeffs = self._identity(identity)
        rot = self._local_rotations(params)
        rest_joints = self._rest_joints(coeffs)
        glob_rot, pos = self._kinematics(rot, rest_joints)
        eye = torch.eye(3, device=rot.device, dtype=rot.dtype)
        pose_feature = (rot[:, self._posed_joints.to(rot.device)] - eye).reshape(rot.shape[0], -1)  # (B, 41*9)
        return coeffs, rest_joints, glob_rot, pos, pose_feature

    def _to_frame(self, points: torch.Tensor, rest_joints: torch.Tensor) -> torch.Tensor:
        root = rest_joints[:, self._root][:, None]  # (1|B, 1, 3)
        return (points - root) @ self.to_frame.T

    # ------------------------------------------------------------------ forwards
    def forward(self, params: Params, identity: torch.Tensor) -> BodyOutput:
        coeffs, rest_joints, glob_rot, pos, pose_feature = self._posed(params, identity)
        rest = self._rest_points(coeffs, params["face"].to(self.template.dtype), pose_feature)
        vertices = self._skin(rest, self.weights, glob_rot, pos, rest_joints)
        return BodyOutput(joints=self._to_frame(pos, rest_joints), vertices=self._to_frame(vertices, rest_joints))

    def keypoint_set(self, correspondence: Correspondence) -> KeypointIndex:
        return KeypointIndex.from_correspondence(correspondence, self.template.device)

    def forward_keypoints(self, params: Params, identity: torch.Tensor, keypoints: KeypointIndex,
                          identity_index: torch.Tensor | None = None) -> torch.Tensor:
        if identity_index is not None:
            identity = identity.reshape(-1, identity.shape[-1])[identity_index]
        coeffs, rest_joints, glob_rot, pos, pose_feature = self._posed(params, identity)
        vidx = keypoints.vertex_index
        rest = self._rest_points(coeffs, params["face"].to(self.template.dtype), pose_feature, vidx)
        skinned = self._skin(rest, self.weights[vidx], glob_rot, pos, rest_joints)
        joints = pos[:, keypoints.joint_index]
        out = torch.where(keypoints.is_vertex[None, :, None], skinned, joints)
        return self._to_frame(out, rest_joints) * keypoints.valid[None, :, None]

    def correspondence(self, landmark_set: str) -> Correspondence:
        path = DATA_DIR / f"smplfx_{landmark_set}.json"
        if not path.exists():
            raise FileNotFoundError(
                f"no landmark correspondence {path.name} for body model 'smplfx'; available: "
                f"{sorted(p.stem.removeprefix('smplfx_') for p in DATA_DIR.glob('smplfx_*.json'))}"
            )
        return resolve_correspondence(json.loads(path.read_text()), self.joint_names, self.data)


def resolve_correspondence(spec: dict, joint_names: tuple[str, ...], data: SMPLFXData) -> Correspondence:
    """Stored spec (``joint`` | ``smplx_vertex`` | ``ibug`` | nothing per landmark) -> indices of this model."""
    joint_of = {n: i for i, n in enumerate(joint_names)}
    names, kind, index = [], [], []
    for entry in spec["landmarks"]:
        names.append(entry["name"])
        if entry.get("joint") is not None:
            kind.append(1)
            index.append(joint_of[entry["joint"]])
        elif entry.get("smplx_vertex") is not None and int(entry["smplx_vertex"]) < data.num_smplx_vertices:
            kind.append(0)
            index.append(int(entry["smplx_vertex"]))
        elif entry.get("ibug") is not None:
            kind.append(0)
            index.append(int(data.landmark_vertices[int(entry["ibug"]) - 18]))
        else:
            kind.append(-1)
            index.append(0)
    return Correspondence(tuple(names), np.asarray(kind, dtype=np.int64), np.asarray(index, dtype=np.int64))
