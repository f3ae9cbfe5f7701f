"""Synthetic stand-ins for the licensed SMPL-X / FLAME files, with the real files' key structure.

Nothing here is derived from SMPL-X or FLAME data: a coarse humanoid made of tubes (torso, arms, hands
with 3-segment fingers, legs) plus an ellipsoid head with a neck. The head has one topology shared by
the "FLAME" file and the head region of the "SMPL-X" file (as in the real models, linked by the
correspondence file), in different frames and scales so that the eye alignment is exercised.

- ``SMPLX_NEUTRAL.npz``: v_template (V, 3) with V >= 9930 (the smplx package hard-codes vertex ids up to
  9929; nose / eyes / ears / fingertips sit at those ids), f, shapedirs (V, 3, 400: 300 shape + 100
  expression), posedirs (V, 3, 486), J_regressor (55, V), weights (V, 55), kintree_table (2, 55), hand
  PCA (hands_componentsl/r (45, 45), hands_meanl/r (45,)), lmk_faces_idx (51,), lmk_bary_coords (51, 3),
  dynamic_lmk_faces_idx (79, 17), dynamic_lmk_bary_coords (79, 17, 3).
- FLAME ``generic_model.pkl``: a Python-2-style pickle (protocol 2) whose ``shapedirs`` is a
  ``chumpy.ch.Ch`` object and ``J_regressor`` a ``scipy.sparse.csc_matrix``, like FLAME 2020; or the
  same keys as ``.npz``: v_template, f, shapedirs (Vf, 3, 400), posedirs (Vf, 3, 36), J_regressor (5, Vf),
  weights (Vf, 5), kintree_table (2, 5).
- ``SMPL-X__FLAME_vertex_ids.npy``: (Vf,) SMPL-X index of every FLAME vertex.

Frames: SMPL-X's (Y up, facing +Z, +X = the subject's left), metres.
"""
from __future__ import annotations

import functools
import pickle
import sys
import types
from dataclasses import dataclass
from pathlib import Path

import numpy as np

SMPLX_IDS = {"nose": 9120, "reye": 9929, "leye": 9448, "rear": 616, "lear": 6,
             "rthumb": 8079, "rindex": 7669, "rmiddle": 7794, "rring": 7905, "rpinky": 8022,
             "lthumb": 5361, "lindex": 4933, "lmiddle": 5058, "lring": 5169, "lpinky": 5286}
JOINTS = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "jaw",
    "left_eye", "right_eye",
) + tuple(f"{s}_{f}{k}" for s in ("left", "right") for f in ("index", "middle", "pinky", "ring", "thumb") for k in (1, 2, 3))
J = {n: i for i, n in enumerate(JOINTS)}
PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15] + [
    parent for wrist in (20, 21) for base in range(5) for parent in (wrist, 0, 0)]
for _i in range(25, 55):  # finger chains: joint k>1 hangs on the previous one
    if (_i - 25) % 3:
        PARENTS[_i] = _i - 1

# Left-side joint positions (the right side mirrors x); centre joints have x = 0.
LEFT = {
    "hip": (0.06, -0.08, 0.0), "knee": (0.10, -0.45, 0.0), "ankle": (0.10, -0.85, -0.03), "foot": (0.11, -0.90, 0.09),
    "collar": (0.07, 0.42, -0.01), "shoulder": (0.18, 0.44, -0.02), "elbow": (0.44, 0.44, -0.03), "wrist": (0.69, 0.44, -0.03),
}
FINGER_POINTS = {  # joint 1, 2, 3, tip
    "index": [(0.78, 0.44, 0.0), (0.815, 0.44, 0.0), (0.84, 0.44, 0.0), (0.862, 0.44, 0.0)],
    "middle": [(0.785, 0.44, -0.022), (0.825, 0.44, -0.022), (0.853, 0.44, -0.022), (0.877, 0.44, -0.022)],
    "ring": [(0.78, 0.44, -0.043), (0.815, 0.44, -0.043), (0.842, 0.44, -0.043), (0.862, 0.44, -0.043)],
    "pinky": [(0.77, 0.44, -0.062), (0.797, 0.44, -0.062), (0.815, 0.44, -0.062), (0.832, 0.44, -0.062)],
    "thumb": [(0.72, 0.43, 0.02), (0.745, 0.425, 0.042), (0.77, 0.42, 0.058), (0.79, 0.415, 0.07)],
}
CENTRE = {"pelvis": (0, 0.0, 0.0), "spine1": (0, 0.10, -0.01), "spine2": (0, 0.22, -0.01), "spine3": (0, 0.30, 0.0)}
HEAD_SCALE, HEAD_OFFSET = 0.97, np.array([0.0, 0.64, 0.012])  # FLAME frame -> SMPL-X frame for the head
RX, RY, RZ = 0.078, 0.105, 0.095  # head ellipsoid radii (FLAME frame, centred at the origin)


def ibug_points() -> dict[int, tuple[float, float]]:
    """(x, y) on the face front (FLAME frame) of iBUG landmarks 18-68."""
    pts = {18: (-0.05, 0.032), 19: (-0.042, 0.037), 20: (-0.033, 0.039), 21: (-0.024, 0.038), 22: (-0.013, 0.035),
           28: (0, 0.022), 29: (0, 0.008), 30: (0, -0.006), 31: (0, -0.02),
           32: (-0.016, -0.032), 33: (-0.008, -0.034), 34: (0, -0.035),
           37: (-0.046, 0.016), 38: (-0.038, 0.021), 39: (-0.027, 0.021), 40: (-0.019, 0.015), 41: (-0.027, 0.01), 42: (-0.038, 0.01),
           49: (-0.026, -0.056), 50: (-0.017, -0.048), 51: (-0.007, -0.045), 52: (0, -0.046),
           59: (-0.007, -0.068), 58: (0, -0.069), 60: (-0.017, -0.064),
           61: (-0.019, -0.056), 62: (-0.008, -0.052), 63: (0, -0.052), 68: (-0.008, -0.06), 67: (0, -0.06)}
    mirror = {22: 23, 21: 24, 20: 25, 19: 26, 18: 27, 33: 35, 32: 36, 40: 43, 39: 44, 38: 45, 37: 46, 42: 47, 41: 48,
              49: 55, 50: 54, 51: 53, 60: 56, 59: 57, 61: 65, 62: 64, 68: 66}
    for a, b in mirror.items():
        pts[b] = (-pts[a][0], pts[a][1])
    return dict(sorted(pts.items()))


# ------------------------------------------------------------------------------------------ geometry
class Mesh:
    """Accumulates vertices, faces and per-vertex skinning (joint -> weight) for the humanoid."""

    def __init__(self):
        self.v: list[np.ndarray] = []
        self.f: list[np.ndarray] = []
        self.skin: list[dict[int, float]] = []

    @property
    def n(self) -> int:
        return sum(len(v) for v in self.v)

    def add(self, verts: np.ndarray, faces: np.ndarray, skin: list[dict[int, float]]) -> np.ndarray:
        base = self.n
        self.v.append(np.asarray(verts, dtype=np.float64))
        self.f.append(np.asarray(faces, dtype=np.int64) + base)
        self.skin += skin
        return np.arange(base, base + len(verts))


def _frame(axis: np.ndarray, flat_up: bool) -> tuple[np.ndarray, np.ndarray]:
    axis = axis / np.linalg.norm(axis)
    ref = np.array([0.0, 1.0, 0.0]) if (flat_up or abs(axis[1]) < 0.9) else np.array([1.0, 0.0, 0.0])
    u = np.cross(axis, ref)
    u /= np.linalg.norm(u)
    return u, np.cross(u, axis)


def tube(a, b, radii_a, radii_b, n_around=16, n_rings=6, cap_start=True, cap_end=True, flat_up=False):
    """A generalised cylinder from a to b with elliptical rings; returns vertices, faces, t (0..1) per vertex."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    u, w = _frame(b - a, flat_up)
    theta = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    verts, ts = [], []
    for t in np.linspace(0, 1, n_rings):
        ru, rw = (1 - t) * np.asarray(radii_a) + t * np.asarray(radii_b)
        centre = a + t * (b - a)
        verts += [centre + ru * np.cos(th) * u + rw * np.sin(th) * w for th in theta]
        ts += [t] * n_around
    faces = []
    for r in range(n_rings - 1):
        for k in range(n_around):
            p0, p1 = r * n_around + k, r * n_around + (k + 1) % n_around
            faces += [(p0, p0 + n_around, p1), (p1, p0 + n_around, p1 + n_around)]
    if cap_start:
        verts.append(a - 0.3 * np.mean(radii_a) * (b - a) / np.linalg.norm(b - a))
        ts.append(0.0)
        apex = len(verts) - 1
        faces += [(apex, (k + 1) % n_around, k) for k in range(n_around)]
    if cap_end:
        verts.append(b.copy())
        ts.append(1.0)
        apex, last = len(verts) - 1, (n_rings - 1) * n_around
        faces += [(apex, last + k, last + (k + 1) % n_around) for k in range(n_around)]
    return np.array(verts), np.array(faces), np.array(ts)


def limb(mesh: Mesh, a, b, radii_a, radii_b, joint: int, parent: int, blend: float = 0.25, **kw) -> np.ndarray:
    verts, faces, ts = tube(a, b, radii_a, radii_b, **kw)
    skin = []
    for t in ts:
        wp = 0.5 * max(0.0, 1 - t / blend) if parent >= 0 else 0.0
        skin.append({joint: 1 - wp, parent: wp} if wp > 0 else {joint: 1.0})
    return mesh.add(verts, faces, skin)


def head_mesh(n_around: int = 64, n_lat: int = 36) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """FLAME-frame head + neck: an open neck tube (5 rings) under an ellipsoid; region masks per vertex."""
    theta = np.linspace(0, 2 * np.pi, n_around, endpoint=False)  # 0 = front (+z); symmetric in x
    verts, region = [], []
    for y in np.linspace(-0.165, -0.105, 5):
        verts += [(0.042 * np.sin(th), y, -0.012 + 0.042 * np.cos(th)) for th in theta]
        region += ["neck"] * n_around
    for lat in np.deg2rad(np.linspace(-62, 82, n_lat)):
        verts += [(RX * np.cos(lat) * np.sin(th), RY * np.sin(lat), RZ * np.cos(lat) * np.cos(th)) for th in theta]
        region += ["head"] * n_around
    verts.append((0.0, RY, 0.0))
    region.append("head")
    verts = np.array(verts)
    rings = 5 + n_lat
    faces = []
    for r in range(rings - 1):
        for k in range(n_around):
            p0, p1 = r * n_around + k, r * n_around + (k + 1) % n_around
            faces += [(p0, p0 + n_around, p1), (p1, p0 + n_around, p1 + n_around)]
    apex, last = len(verts) - 1, (rings - 1) * n_around
    faces += [(apex, last + (k + 1) % n_around, last + k) for k in range(n_around)]
    # A nose: push the front-centre strip forward.
    bump = np.exp(-((verts[:, 0] / 0.012) ** 2 + ((verts[:, 1] + 0.008) / 0.02) ** 2)) * (verts[:, 2] > 0)
    verts[:, 2] += 0.018 * bump
    region = np.array(region)
    jaw = (region == "head") & (verts[:, 1] < -0.05) & (verts[:, 2] > 0.02)
    return verts, np.array(faces), {"neck": region == "neck", "jaw": jaw, "head": (region == "head") & ~jaw}


def _assign_points(verts: np.ndarray, candidates: np.ndarray, targets: list[np.ndarray]) -> list[int]:
    """Nearest still-unused candidate vertex for each target point, in order."""
    used, out = set(), []
    for p in targets:
        order = candidates[np.argsort(np.linalg.norm(verts[candidates] - p, axis=1))]
        pick = next(int(i) for i in order if int(i) not in used)
        used.add(pick)
        out.append(pick)
    return out


def _surface(x: float, y: float, verts: np.ndarray) -> np.ndarray:
    z = RZ * np.sqrt(max(1e-6, 1 - (x / RX) ** 2 - (y / RY) ** 2))
    return np.array([x, y, z])


def _affine_row(verts: np.ndarray, candidates: np.ndarray, point: np.ndarray, k: int = 160) -> np.ndarray:
    """Weights over the k nearest candidates that reproduce ``point`` exactly (rows sum to 1)."""
    near = candidates[np.argsort(np.linalg.norm(verts[candidates] - point, axis=1))[:k]]
    A = np.vstack([verts[near].T, np.ones(len(near))])  # (4, k)
    w = np.linalg.pinv(A) @ np.append(point, 1.0)
    assert np.allclose(verts[near].T @ w, point, atol=1e-9), "joint regressor row is not exact"
    row = np.zeros(len(verts))
    row[near] = w
    return row


@dataclass(frozen=True)
class FixturePaths:
    smplx: Path
    flame: Path
    flame_npz: Path
    correspondence: Path
    eyelids: Path


def _smooth_dirs(verts: np.ndarray, n: int, scale: float, rng: np.random.Generator, rank: int = 12) -> np.ndarray:
    """(V, 3, n) smooth displacement fields: a low-rank mix of sinusoids of the position."""
    freq = rng.normal(0, 6.0, size=(rank, 3))
    phase = rng.uniform(0, 2 * np.pi, size=rank)
    basis = np.sin(verts @ freq.T + phase)  # (V, rank)
    mix = rng.normal(0, scale, size=(rank, 3, n))
    return np.einsum("vr,rcn->vcn", basis, mix)


def make_fixture_files(root: Path, seed: int = 0) -> FixturePaths:
    """Write synthetic SMPLX_NEUTRAL.npz, FLAME (pkl + npz), the correspondence and eyelid files."""
    rng = np.random.default_rng(seed)
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    mesh = Mesh()
    P = {n: np.array(p, float) for n, p in CENTRE.items()}
    for side, sx in (("left", 1.0), ("right", -1.0)):
        for name, p in LEFT.items():
            P[f"{side}_{name}"] = np.array(p) * (sx, 1, 1)
        for finger, pts in FINGER_POINTS.items():
            for k, p in enumerate(pts):
                P[f"{side}_{finger}{k + 1}" if k < 3 else f"{side}_{finger}_tip"] = np.array(p) * (sx, 1, 1)

    # Torso: one tube skinned by height to pelvis / spine1 / spine2 / spine3.
    verts, faces, _ = tube((0, -0.06, 0), (0, 0.49, -0.01), (0.15, 0.10), (0.13, 0.09), n_around=48, n_rings=40)
    bands = [(J["pelvis"], -1.0), (J["spine1"], 0.10), (J["spine2"], 0.22), (J["spine3"], 0.30)]
    skin = []
    for y in verts[:, 1]:
        j = max((b for b in bands if y >= b[1]), key=lambda b: b[1])[0]
        skin.append({j: 1.0})
    mesh.add(verts, faces, skin)
    fingertip_nat = {}
    for side, sx in (("left", 1.0), ("right", -1.0)):
        s = side
        limb(mesh, P[f"{s}_collar"], P[f"{s}_shoulder"], (0.05, 0.05), (0.05, 0.05), J[f"{s}_collar"], J["spine3"], n_around=24, n_rings=10)
        limb(mesh, P[f"{s}_shoulder"], P[f"{s}_elbow"], (0.05, 0.05), (0.04, 0.04), J[f"{s}_shoulder"], J[f"{s}_collar"], n_around=32, n_rings=24)
        limb(mesh, P[f"{s}_elbow"], P[f"{s}_wrist"], (0.04, 0.04), (0.03, 0.025), J[f"{s}_elbow"], J[f"{s}_shoulder"], n_around=32, n_rings=24)
        palm_end = P[f"{s}_middle1"] + np.array([0.0, 0.0, 0.0])
        limb(mesh, P[f"{s}_wrist"], palm_end, (0.045, 0.012), (0.045, 0.012), J[f"{s}_wrist"], J[f"{s}_elbow"],
             n_around=24, n_rings=10, flat_up=True)
        for finger in ("index", "middle", "pinky", "ring", "thumb"):
            chain = [P[f"{s}_{finger}{k}"] for k in (1, 2, 3)] + [P[f"{s}_{finger}_tip"]]
            parents = [J[f"{s}_wrist"]] + [J[f"{s}_{finger}{k}"] for k in (1, 2)]
            for k in range(3):
                ids = limb(mesh, chain[k], chain[k + 1], (0.009, 0.008), (0.008, 0.007), J[f"{s}_{finger}{k + 1}"],
                           parents[k], n_around=12, n_rings=5, cap_end=(k == 2))
            fingertip_nat[f"{s[0]}{finger}"] = int(ids[-1])  # the apex of the last segment's end cap
        limb(mesh, P[f"{s}_hip"], P[f"{s}_knee"], (0.07, 0.07), (0.05, 0.05), J[f"{s}_hip"], J["pelvis"], n_around=32, n_rings=20)
        limb(mesh, P[f"{s}_knee"], P[f"{s}_ankle"], (0.05, 0.05), (0.04, 0.04), J[f"{s}_knee"], J[f"{s}_hip"], n_around=32, n_rings=20)
        limb(mesh, P[f"{s}_ankle"], P[f"{s}_foot"], (0.04, 0.035), (0.035, 0.02), J[f"{s}_ankle"], J[f"{s}_knee"], n_around=16, n_rings=8)
        limb(mesh, P[f"{s}_foot"], P[f"{s}_foot"] + (0, 0, 0.06), (0.035, 0.02), (0.02, 0.015), J[f"{s}_foot"], J[f"{s}_ankle"], n_around=16, n_rings=6)

    # Head: FLAME topology; SMPL-X's head is a scaled, moved and slightly reshaped copy.
    head_fl, head_faces, region = head_mesh()
    head_sx = HEAD_SCALE * head_fl + HEAD_OFFSET
    head_sx[:, 2] += 0.003 * np.exp(-((head_fl[:, 1] + 0.06) / 0.02) ** 2)  # a different chin
    head_skin = []
    for i in range(len(head_fl)):
        if region["neck"][i]:
            t = (head_fl[i, 1] + 0.165) / 0.06
            head_skin.append({J["neck"]: 0.5 + 0.5 * t, J["spine3"]: 0.5 - 0.5 * t} if t < 1 else {J["neck"]: 1.0})
        elif region["jaw"][i]:
            head_skin.append({J["jaw"]: 1.0})
        else:
            head_skin.append({J["head"]: 1.0})
    head_ids = mesh.add(head_sx, head_faces, head_skin)

    # Filler under the pelvis up to V >= 10,000 (smplx's hard-coded vertex ids reach 9929).
    deficit = 10_000 - mesh.n
    if deficit > 0:
        rings = int(np.ceil((deficit - 1) / 40)) + 1
        limb(mesh, (0, -0.05, 0), (0, -0.16, 0), (0.12, 0.08), (0.10, 0.07), J["pelvis"], -1, n_around=40, n_rings=rings, cap_start=False)
    nat_v = np.concatenate(mesh.v)
    nat_f = np.concatenate(mesh.f)
    V = len(nat_v)

    # Face points on the head (FLAME frame), assigned to distinct head vertices.
    ib = ibug_points()
    ib_targets = [_surface(x, y, head_fl) for x, y in ib.values()]
    named = {"nose": _surface(0.0, -0.012, head_fl) + (0, 0, 0.018), "leye": _surface(0.032, 0.016, head_fl),
             "reye": _surface(-0.032, 0.016, head_fl), "lear": np.array([RX, 0.0, 0.0]), "rear": np.array([-RX, 0.0, 0.0])}
    picks = _assign_points(head_fl, np.arange(len(head_fl)), list(named.values()) + ib_targets)
    face_nat = {k: int(head_ids[i]) for k, i in zip(named, picks[: len(named)])}
    ibug_local = dict(zip(ib, picks[len(named):]))
    ibug_nat = {k: int(head_ids[i]) for k, i in ibug_local.items()}

    # Permutation: designated natural vertices land on smplx's hard-coded ids.
    order = np.arange(V)
    position = np.arange(V)  # natural vertex -> current index
    for key, nat in {**fingertip_nat, **face_nat}.items():
        req, cur = SMPLX_IDS[key], position[nat]
        other = order[req]
        order[req], order[cur] = nat, other
        position[nat], position[other] = req, cur
    inv = position
    v_template = nat_v[order]
    faces = inv[nat_f]
    weights = np.zeros((V, 55))
    for nat, skin in enumerate(mesh.skin):
        for j, w in skin.items():
            weights[inv[nat], j] += w
    corr = inv[head_ids]

    # Joint regressor: exact affine combinations of nearby vertices.
    P.update({"neck": HEAD_SCALE * np.array([0, -0.15, -0.012]) + HEAD_OFFSET,
              "head": HEAD_SCALE * np.array([0, -0.07, -0.01]) + HEAD_OFFSET,
              "jaw": HEAD_SCALE * np.array([0, -0.045, 0.03]) + HEAD_OFFSET,
              "left_eye": HEAD_SCALE * np.array([0.032, 0.016, 0.06]) + HEAD_OFFSET,
              "right_eye": HEAD_SCALE * np.array([-0.032, 0.016, 0.06]) + HEAD_OFFSET})
    body_cands = np.setdiff1d(np.arange(V), corr)
    jreg = np.stack([_affine_row(v_template, corr if n in ("neck", "head", "jaw", "left_eye", "right_eye") else body_cands, P[n])
                     for n in JOINTS])
    flame_jreg = np.stack([_affine_row(head_fl, np.arange(len(head_fl)), p) for p in (
        np.array([0, -0.165, -0.012]), np.array([0, -0.07, -0.01]), np.array([0, -0.045, 0.03]),
        np.array([0.032, 0.016, 0.06]), np.array([-0.032, 0.016, 0.06]))])

    # Landmark embedding: a face containing each iBUG vertex, with all weight on that vertex.
    def face_with(vertex: int, faces_: np.ndarray) -> tuple[int, np.ndarray]:
        fi = int(np.flatnonzero((faces_ == vertex).any(1))[0])
        bary = (faces_[fi] == vertex).astype(np.float64)
        return fi, bary

    lmk = [face_with(int(inv[ibug_nat[k]]), faces) for k in range(18, 69)]
    head_face_ids = np.flatnonzero(np.isin(faces, corr).all(1))

    # Blendshapes.
    sx_shapedirs = _smooth_dirs(v_template, 400, 0.004, rng).astype(np.float32)
    sx_shapedirs[:, :, 300:] = 0.0
    sx_shapedirs[corr, :, 300:] = _smooth_dirs(v_template[corr], 100, 0.002, rng)
    fl_shape = _smooth_dirs(head_fl, 300, 0.003, rng)
    centres = head_fl[list(ibug_local.values())]
    fl_expr = np.zeros((len(head_fl), 3, 100))
    for e in range(100):  # localised bumps around face landmarks, moving along a random direction
        c = centres[rng.integers(len(centres))]
        fall = np.exp(-np.sum((head_fl - c) ** 2, axis=1) / (2 * 0.015 ** 2))
        fl_expr[:, :, e] = fall[:, None] * rng.normal(0, 0.004, size=3)
    fl_expr[region["neck"]] = 0.0
    flame = {
        "v_template": head_fl, "f": head_faces.astype(np.uint32),
        "shapedirs": np.concatenate([fl_shape, fl_expr], axis=2),
        "posedirs": _smooth_dirs(head_fl, 36, 0.0005, rng),
        "J_regressor": flame_jreg,
        "weights": np.stack([region["neck"], region["head"], region["jaw"], 0 * region["jaw"], 0 * region["jaw"]], 1).astype(np.float64),
        "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.uint32),
    }
    posedirs = _smooth_dirs(v_template, 486, 0.0005, rng).astype(np.float32)
    for j in range(1, 55):  # like the real model: a joint's correctives live where it and its parent skin
        region = (weights[:, j] + weights[:, PARENTS[j]]) > 0
        posedirs[~region, :, (j - 1) * 9: j * 9] = 0.0
    q = np.linalg.qr(rng.normal(size=(45, 45)))[0]
    smplx = {
        "v_template": v_template, "f": faces.astype(np.uint32), "shapedirs": sx_shapedirs,
        "posedirs": posedirs,
        "J_regressor": jreg, "weights": weights,
        "kintree_table": np.stack([np.array(PARENTS, dtype=np.int64) % 4294967296, np.arange(55)]).astype(np.uint32),
        "hands_componentsl": q, "hands_componentsr": q.copy(), "hands_meanl": 0.1 * rng.normal(size=45),
        "hands_meanr": 0.1 * rng.normal(size=45),
        "lmk_faces_idx": np.array([f for f, _ in lmk], dtype=np.int64),
        "lmk_bary_coords": np.array([b for _, b in lmk]),
        "dynamic_lmk_faces_idx": rng.choice(head_face_ids, size=(79, 17)).astype(np.int64),
        "dynamic_lmk_bary_coords": np.full((79, 17, 3), 1.0 / 3.0),
    }
    paths = FixturePaths(root / "SMPLX_NEUTRAL.npz", root / "generic_model.pkl", root / "flame2020.npz",
                         root / "SMPL-X__FLAME_vertex_ids.npy", root / "eyelids")
    np.savez(paths.smplx, **smplx)
    np.savez(paths.flame_npz, **flame)
    write_chumpy_style_pickle(paths.flame, flame)
    paths.eyelids.mkdir(exist_ok=True)
    for k, eye_x in (("l", 0.032), ("r", -0.032)):
        near = np.exp(-np.sum((head_fl - (eye_x, 0.022, RZ * 0.8)) ** 2, axis=1) / (2 * 0.008 ** 2))
        np.save(paths.eyelids / f"{k}_eyelid.npy", near[:, None] * np.array([0.0, -0.006, 0.0]))
    np.save(paths.correspondence, corr.astype(np.int64))  # written last: marks a complete fixture
    return paths


def write_chumpy_style_pickle(path: Path, arrays: dict[str, np.ndarray], extra: dict | None = None,
                              value_key: str = "x") -> None:
    """Pickle like FLAME 2020: ``shapedirs`` as a ``chumpy.ch.Ch`` object, ``J_regressor`` sparse (csc).
    ``value_key`` other than ``"x"`` imitates a chumpy expression that has no stored value."""
    from scipy import sparse

    chumpy, chumpy_ch = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")

    class Ch:  # stands in for chumpy.ch.Ch only while pickling; the reader never imports chumpy
        pass

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    chumpy_ch.Ch = Ch
    chumpy.ch = chumpy_ch
    saved = {k: sys.modules.get(k) for k in ("chumpy", "chumpy.ch")}
    sys.modules.update({"chumpy": chumpy, "chumpy.ch": chumpy_ch})
    try:
        payload = dict(arrays)
        ch = Ch()
        ch.__dict__.update({value_key: np.asarray(arrays["shapedirs"]), "_dirty_vars": set(), "_itr": None})
        payload["shapedirs"] = ch
        payload["J_regressor"] = sparse.csc_matrix(np.asarray(arrays["J_regressor"]))
        payload["bs_style"], payload["bs_type"] = "lbs", "lrotmin"
        payload.update(extra or {})
        with open(path, "wb") as fh:
            pickle.dump(payload, fh, protocol=2)
    finally:
        for k, mod in saved.items():
            if mod is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = mod


# ------------------------------------------------------------------------------------ pytest fixtures' builders
def fixture_paths(root: Path) -> FixturePaths:
    root = Path(root)
    return FixturePaths(root / "SMPLX_NEUTRAL.npz", root / "generic_model.pkl", root / "flame2020.npz",
                        root / "SMPL-X__FLAME_vertex_ids.npy", root / "eyelids")


def ensure_fixture_files(tmp_path_factory) -> FixturePaths:
    """Write the synthetic files once per test run (shared by every test module)."""
    root = tmp_path_factory.getbasetemp() / "smplfx_files"
    paths = fixture_paths(root)
    if not paths.correspondence.exists():  # written last
        make_fixture_files(root)
    return paths


@functools.lru_cache(maxsize=4)
def _load_body(smplx: str, flame: str, correspondence: str, eyelids: str):
    from m3t.body.smplfx import SMPLFXBody
    from m3t.body.smplfx_build import SMPLFXFiles

    return SMPLFXBody(SMPLFXFiles(Path(smplx), Path(flame), Path(correspondence), Path(eyelids)))


def fixture_body(paths: FixturePaths):
    """The SMPL-FX model built from the synthetic files (built once per process)."""
    return _load_body(str(paths.smplx), str(paths.flame), str(paths.correspondence), str(paths.eyelids))


def smplfx_motion(body, frames: int = 16, seed: int = 0) -> dict:
    """Smooth SMPL-FX motion: sinusoidal joint rotations, expressions, eyelids and a little jaw opening."""
    import roma
    import torch

    from m3t.body.rotations import matrix_to_6d

    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 1, frames)[:, None, None]
    params = body.rest_params(frames)
    for m in body.layout.modalities:
        if m.kind == "rotation6d":
            n = len(m.labels)
            amp, phase = 0.3 * torch.randn(1, n, 3, generator=g), 6 * torch.rand(1, n, 1, generator=g)
            params[m.name] = matrix_to_6d(roma.rotvec_to_rotmat(amp * torch.sin(3 * t + phase))).reshape(frames, -1)
    tt = t[..., 0]
    face = params["face"]
    face[:, :100] = 1.2 * torch.sin(4 * tt + 6 * torch.rand(1, 100, generator=g)) * torch.rand(1, 100, generator=g)
    face[:, 100:102] = 0.4 * (1 + torch.sin(5 * tt + torch.rand(1, 2, generator=g)))
    jaw = torch.zeros(frames, 3)
    jaw[:, 0] = 0.15 * (1 + torch.sin(6 * tt[:, 0]))
    face[:, 102:] = matrix_to_6d(roma.rotvec_to_rotmat(jaw))
    return params


def front_camera_fx():
    """A frontal camera that sees the whole T-posed synthetic body (Z up, body facing -Y)."""
    from m3t.camera import Camera, look_at

    eye = np.array([0.1, -3.0, 0.2])
    rot = look_at(eye, np.array([0.0, 0.0, 0.12]), np.array([0.0, 0.0, 1.0]))
    return Camera(600.0, 600.0, 256.0, 256.0, tuple(map(tuple, rot)), tuple((-rot @ eye).tolist()), 512, 512)
