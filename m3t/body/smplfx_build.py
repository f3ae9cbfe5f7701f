"""Build SMPL-FX (M3T App. 0.C) from the user's SMPL-X, FLAME 2020 and SMPL-X <-> FLAME files.

Everything here is numpy and runs once per process at model load; :mod:`m3t.body.smplfx` turns the result
into a torch module. The construction follows the paper:

1. The SMPL-X template vertices that correspond to FLAME vertices are replaced by FLAME's template, moved
   by the displacement that aligns the two models (default: the mean of the two eye joints, as GUAVA does;
   ``alignment="mean"``: the mean displacement over all corresponding vertices).
2. Neck blending: concentric rings are grown over FLAME's edges from its open neck boundary (the boundary
   loop with the lowest mean height). Ring k of n gets the ratio ``linspace(0.9, 0.1, n)[k]``: the weight of
   SMPL-X there (0.9 next to the body, 0.1 next to the jaw); every other FLAME vertex has ratio 0.
   Template, shape, expression and pose correctives are blended with that ratio.
3. FLAME shape (first ``flame_shape_dims`` of 300) and expression (100) directions are retargeted into
   full-mesh buffers that are non-zero only on FLAME-corresponding vertices; SMPL-X's 10 shape directions
   are multiplied by the ratio (zero on the head). Identity = 10 SMPL-X + ``flame_shape_dims`` FLAME
   coefficients (110 by default, paper Eq. 1; Table A.1's 310 counts all 300 FLAME shape directions).
4. Two eyelid buffers (FLAME vertex offsets of Pixel3DMM / VHAP's ``l_eyelid.npy`` / ``r_eyelid.npy``)
   are retargeted the same way; without that file a procedural lid-closing displacement is used.
5. Teeth: 520 vertices (two arches of 26 x 10) placed behind the inner-lip landmarks of SMPL-X's landmark
   embedding, rigidly skinned to the head (upper) and jaw (lower) joints. With the real SMPL-X mesh
   (10,475 vertices) this gives the paper's 10,995 vertices. The arch size is our choice: the paper gives
   only the total.
6. Joints: the 11 lower-body joints (pelvis, spine1, spine2, hips, knees, ankles, feet) are discarded and
   their skinning weights merged into ``spine3``, the new root; 44 joints remain (root + 43, keeping the
   jaw and both eye joints; the eye joints come from FLAME's regressor). The paper's Table A.1 says 42
   pose joints while its text says 11 (App. C) or 12 (Sec. 3.1) removed joints, which cannot all hold.
   Pose correctives are kept for the joints that have parameters (10 body, 30 finger, jaw); on the head
   they come from FLAME (its neck and jaw blocks), blended with the ratio.

The neck rings (step 2) and the teeth arches (step 5) are built by :mod:`m3t.body.smplfx_geometry`.

Frames: everything here is in SMPL-X's frame (Y up, facing +Z, +X = the subject's left), metres.
Axis legend: V vertices, J joints, N blendshape directions, F faces.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.body.model_files import ModelFileError, load_model_arrays
from m3t.body.smplfx_geometry import neck_rings, teeth_geometry
from m3t.declared import load_npy

BODY_JOINTS = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "jaw",
    "left_eye", "right_eye",
)
FINGERS = ("index", "middle", "pinky", "ring", "thumb")  # SMPL-X / MANO order


def hand_joint_names(side: str) -> tuple[str, ...]:
    return tuple(f"{side}_{finger}{k}" for finger in FINGERS for k in (1, 2, 3))


SMPLX_JOINTS = BODY_JOINTS + hand_joint_names("left") + hand_joint_names("right")  # 55
DISCARDED = ("pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
             "left_ankle", "right_ankle", "left_foot", "right_foot")
ROOT = "spine3"
BODY_POSE_JOINTS = ("neck", "head", "left_collar", "right_collar", "left_shoulder", "right_shoulder",
                    "left_elbow", "right_elbow", "left_wrist", "right_wrist")
POSED_JOINTS = BODY_POSE_JOINTS + hand_joint_names("left") + hand_joint_names("right") + ("jaw",)
FLAME_NECK, FLAME_JAW, FLAME_LEFT_EYE, FLAME_RIGHT_EYE = 1, 2, 3, 4
SMPLX_REQUIRED = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
FLAME_REQUIRED = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
INNER_LIP_LANDMARKS = slice(43, 51)  # iBUG 61-68 in SMPL-X's 51-landmark embedding (iBUG 18-68)

SOURCES = {
    "smplx": "SMPL-X 'SMPLX_NEUTRAL.npz' (SMPL-X v1.1 model download) from https://smpl-x.is.tue.mpg.de",
    "flame": "FLAME 2020 'generic_model.pkl' (or an .npz conversion) from https://flame.is.tue.mpg.de",
    "correspondence": "'SMPL-X__FLAME_vertex_ids.npy' from the SMPL-X downloads (https://smpl-x.is.tue.mpg.de, "
                      "'MANO and FLAME vertex indices')",
    "eyelids": "optional: a folder with Pixel3DMM / VHAP's 'l_eyelid.npy' and 'r_eyelid.npy' (or an .npz with those keys)",
}
CONFIG_KEYS = {"smplx": "body.smplx_path", "flame": "body.flame_path",
               "correspondence": "body.flame_correspondence_path", "eyelids": "body.eyelids_path"}


class SMPLFXFilesMissing(FileNotFoundError):
    """Raised when licensed files are absent; the message lists each missing file and where to get it."""


@dataclass(frozen=True)
class SMPLFXFiles:
    smplx: Path
    flame: Path
    correspondence: Path
    eyelids: Path | None = None

    def check(self) -> None:
        missing = [(k, getattr(self, k)) for k in ("smplx", "flame", "correspondence") if not Path(getattr(self, k)).exists()]
        if self.eyelids is not None and not Path(self.eyelids).exists():
            missing.append(("eyelids", self.eyelids))
        if missing:
            lines = "\n".join(f"  - {CONFIG_KEYS[k]} = {p}: not found. Get {SOURCES[k]}" for k, p in missing)
            raise SMPLFXFilesMissing(
                f"body.model 'smplfx' is built from licensed model files; missing:\n{lines}\n"
                "Register and accept each licence on those sites, place the files there (or change the paths in "
                "the body section of params.yaml), or use body.model: anny (embedded, open)."
            )


@dataclass(frozen=True)
class SMPLFXData:
    joint_names: tuple[str, ...]
    parents: np.ndarray  # (J,) int, -1 for the root
    template: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    identity_dirs: np.ndarray  # (N_id, V, 3)
    face_dirs: np.ndarray  # (102, V, 3): 100 expression + 2 eyelids
    pose_dirs: np.ndarray  # (41 * 9, V, 3) over POSED_JOINTS
    joint_template: np.ndarray  # (J, 3)
    joint_identity_dirs: np.ndarray  # (N_id, J, 3)
    weights: np.ndarray  # (V, J)
    head_vertices: np.ndarray  # (V_flame,) SMPL-X indices of the FLAME vertices
    smplx_ratio: np.ndarray  # (V,) 1 = pure SMPL-X, 0 = pure FLAME
    neck_rings: tuple[np.ndarray, ...]  # SMPL-X indices of each ring, body side first
    landmark_vertices: np.ndarray  # (51,) dominant vertex of each SMPL-X landmark (iBUG 18-68)
    num_smplx_vertices: int


def _eyelid_dirs(flame: dict, path: Path | None, eyes: np.ndarray) -> np.ndarray:
    """(2, V_flame, 3) eyelid offsets: the user's buffers, else a procedural downward lid sweep."""
    v = flame["v_template"]
    if path is not None:
        path = Path(path)
        if path.is_dir():
            arrays = [load_npy(path / f"{side}_eyelid.npy") for side in ("l", "r")]
        else:
            data = load_model_arrays(path, required=("l_eyelid", "r_eyelid"))
            arrays = [data["l_eyelid"], data["r_eyelid"]]
        out = np.stack([np.asarray(a, dtype=np.float64).reshape(v.shape) for a in arrays])
        return out
    out = np.zeros((2, *v.shape))
    radius = 0.02
    for k, eye in enumerate(eyes):  # left, right
        d = np.linalg.norm(v - eye, axis=1)
        lid = (d < radius) & (v[:, 1] > eye[1]) & (v[:, 2] > eye[2])
        falloff = (1.0 - d[lid] / radius) ** 2
        out[k, lid, 1] = -(v[lid, 1] - eye[1]) * falloff  # param 1 brings the upper lid to eye height
    return out


def _landmark_vertices(smplx: dict) -> np.ndarray:
    if "lmk_faces_idx" not in smplx or "lmk_bary_coords" not in smplx:
        raise ModelFileError("the SMPL-X file lacks 'lmk_faces_idx' / 'lmk_bary_coords' (the landmark embedding); "
                             "use SMPLX_NEUTRAL.npz from the SMPL-X v1.1 download")
    faces = smplx["f"].astype(np.int64)[smplx["lmk_faces_idx"].astype(np.int64)]  # (51, 3)
    bary = smplx["lmk_bary_coords"]
    return faces[np.arange(len(faces)), np.argmax(bary, axis=1)]


def build_smplfx(files: SMPLFXFiles, flame_shape_dims: int = 100, n_rings: int = 5,
                 alignment: str = "eyes") -> SMPLFXData:
    """Load the three (four) files and assemble SMPL-FX; see the module docstring for each step."""
    files.check()
    sx = load_model_arrays(files.smplx, SMPLX_REQUIRED)
    fl = load_model_arrays(files.flame, FLAME_REQUIRED)
    corr = np.asarray(load_model_arrays(files.correspondence)["array"]).astype(np.int64).reshape(-1)
    V, Vf = sx["v_template"].shape[0], fl["v_template"].shape[0]
    if corr.shape[0] != Vf or corr.min() < 0 or corr.max() >= V:
        raise ModelFileError(f"{files.correspondence}: expected {Vf} SMPL-X vertex indices in [0, {V}) "
                             f"(one per FLAME vertex), found shape {corr.shape} with range [{corr.min()}, {corr.max()}]")
    if sx["J_regressor"].shape[0] != 55 or fl["J_regressor"].shape[0] != 5:
        raise ModelFileError("expected SMPL-X with 55 joints and FLAME with 5 joints; check the model files")
    if fl["shapedirs"].shape[-1] < 400 or not 0 <= flame_shape_dims <= 300:
        raise ModelFileError(f"{files.flame}: FLAME 2020 has 300 shape + 100 expression directions; "
                             f"found {fl['shapedirs'].shape[-1]} (flame_shape_dims={flame_shape_dims})")
    f64 = np.float64
    v_sx, v_fl = sx["v_template"].astype(f64), fl["v_template"].astype(f64)
    jreg_sx, jreg_fl = sx["J_regressor"].astype(f64), fl["J_regressor"].astype(f64)
    joints_sx, joints_fl = jreg_sx @ v_sx, jreg_fl @ v_fl

    rings = neck_rings(v_fl, fl["f"].astype(np.int64), n_rings)
    ratio_fl = np.zeros(Vf)
    for k, ratio in enumerate(np.linspace(0.9, 0.1, n_rings)):
        ratio_fl[rings[k]] = ratio
    ratio = np.ones(V)
    ratio[corr] = ratio_fl
    if alignment == "eyes":
        offset = joints_sx[[23, 24]].mean(0) - joints_fl[[FLAME_LEFT_EYE, FLAME_RIGHT_EYE]].mean(0)
    elif alignment == "mean":
        offset = (v_sx[corr] - v_fl).mean(0)
    else:
        raise ValueError(f"alignment {alignment!r} unknown; use 'eyes' or 'mean'")
    template = v_sx.copy()
    template[corr] = ratio_fl[:, None] * v_sx[corr] + (1 - ratio_fl[:, None]) * (v_fl + offset)

    def retarget(dirs_fl: np.ndarray) -> np.ndarray:  # (V_flame, 3, N) -> (N, V, 3), FLAME share only
        out = np.zeros((dirs_fl.shape[-1], V, 3))
        out[:, corr] = np.moveaxis(dirs_fl, -1, 0) * (1 - ratio_fl)[None, :, None]
        return out

    body_shape = np.moveaxis(sx["shapedirs"][:, :, :10].astype(f64), -1, 0) * ratio[None, :, None]
    identity_dirs = np.concatenate([body_shape, retarget(fl["shapedirs"][:, :, :flame_shape_dims].astype(f64))])
    eyes_fl = joints_fl[[FLAME_LEFT_EYE, FLAME_RIGHT_EYE]]
    eyelids = _eyelid_dirs({"v_template": v_fl}, files.eyelids, eyes_fl)  # (2, Vf, 3)
    face_dirs = np.concatenate([retarget(fl["shapedirs"][:, :, 300:400].astype(f64)),
                                retarget(np.moveaxis(eyelids, 0, -1))])

    # Joints: SMPL-X's regressor on the new template, FLAME's eye rows (moved onto SMPL-X indices).
    jreg = jreg_sx.copy()
    for row, fl_row in ((23, FLAME_LEFT_EYE), (24, FLAME_RIGHT_EYE)):
        jreg[row] = 0.0
        np.add.at(jreg[row], corr, jreg_fl[fl_row])
    keep = [i for i, n in enumerate(SMPLX_JOINTS) if n not in DISCARDED]
    new_index = {old: new for new, old in enumerate(keep)}
    parents_sx = sx["kintree_table"][0].astype(np.int64)
    parents_sx[0] = -1

    def kept_ancestor(j: int) -> int:
        while j >= 0 and j not in new_index:
            j = int(parents_sx[j])
        return new_index[j] if j >= 0 else new_index[SMPLX_JOINTS.index(ROOT)]

    parents = np.array([-1 if SMPLX_JOINTS[j] == ROOT else kept_ancestor(int(parents_sx[j])) for j in keep])
    target = np.array([kept_ancestor(j) for j in range(55)])
    weights = np.zeros((V, len(keep)))
    np.add.at(weights.T, target, sx["weights"].astype(f64).T)

    # Pose correctives over the posed joints; FLAME's neck/jaw blocks drive the head.
    posedirs_sx = sx["posedirs"].astype(f64)
    posedirs_fl = fl["posedirs"].astype(f64)
    blocks = []
    for name in POSED_JOINTS:
        j = SMPLX_JOINTS.index(name)
        block = np.moveaxis(posedirs_sx[:, :, (j - 1) * 9: j * 9], -1, 0) * ratio[None, :, None]  # (9, V, 3)
        flame_joint = {"head": FLAME_NECK, "jaw": FLAME_JAW}.get(name)
        if flame_joint is not None:
            block = block + retarget(posedirs_fl[:, :, (flame_joint - 1) * 9: flame_joint * 9])
        blocks.append(block)
    pose_dirs = np.concatenate(blocks)

    # Teeth: rigid, appended after the SMPL-X vertices.
    lmk = _landmark_vertices(sx)
    teeth, teeth_faces = teeth_geometry(template[lmk[INNER_LIP_LANDMARKS]])
    n_teeth = teeth.shape[0]
    teeth_weights = np.zeros((n_teeth, len(keep)))
    teeth_weights[: n_teeth // 2, new_index[SMPLX_JOINTS.index("head")]] = 1.0
    teeth_weights[n_teeth // 2:, new_index[SMPLX_JOINTS.index("jaw")]] = 1.0

    def pad(dirs: np.ndarray) -> np.ndarray:
        return np.concatenate([dirs, np.zeros((dirs.shape[0], n_teeth, 3))], axis=1)

    f32 = np.float32
    full_template = np.concatenate([template, teeth])
    return SMPLFXData(
        joint_names=tuple(SMPLX_JOINTS[j] for j in keep),
        parents=parents,
        template=full_template.astype(f32),
        faces=np.concatenate([sx["f"].astype(np.int64), teeth_faces + V]),
        identity_dirs=pad(identity_dirs).astype(f32),
        face_dirs=pad(face_dirs).astype(f32),
        pose_dirs=pad(pose_dirs).astype(f32),
        joint_template=(jreg[keep] @ template).astype(f32),
        joint_identity_dirs=np.einsum("jv,nvc->njc", jreg[keep], identity_dirs).astype(f32),
        weights=np.concatenate([weights, teeth_weights]).astype(f32),
        head_vertices=corr,
        smplx_ratio=np.concatenate([ratio, np.ones(n_teeth)]).astype(f32),
        neck_rings=tuple(corr[r] for r in rings),
        landmark_vertices=lmk,
        num_smplx_vertices=V,
    )
