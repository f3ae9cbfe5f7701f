"""Build the MediaPipe Holistic -> Anny landmark correspondence (``m3t/body/data/anny_mediapipe_holistic.json``).

A one-off build script, not part of the library: the library only reads its output
(:func:`m3t.body.anny_body.load_correspondence`). Run from the repository root::

    python tools/build_correspondence.py --mediapipe-wheel-dir DIR \
        --out m3t/body/data/anny_mediapipe_holistic.json

The output lists the 543 Holistic landmarks in MediaPipe's order -- 33 pose, 21 left-hand, 21 right-hand,
468 face-mesh -- each tied to one Anny vertex, one Anny bone head, or nothing. Everything is measured on
Anny's rest pose with the default (all 0.5) identity; coordinates are metres, Z up, the body faces -Y and
the subject's left is +X (``.L`` bones). MediaPipe's "left" is the subject's left, so it maps to ``.L``.

How it is made
--------------
Hands (21 per side)
    Joints are bone heads: wrist -> ``wrist``; thumb CMC/MCP/IP -> heads of ``finger1-1/1-2/1-3``; index..
    pinky MCP/PIP/DIP -> heads of ``finger{2..5}-1/-2/-3``. A fingertip is a vertex: among the vertices
    skinned mostly to the distal phalanx ``finger{n}-3``, the one reaching farthest along that bone's
    head -> tail direction.

Pose (33)
    Body joints are bone heads, chosen as the Anny bone whose head sits at the anatomical joint centre
    (checked against Anny's own COCO keypoint regressor): shoulder -> ``upperarm01`` (``shoulder01`` sits
    mid-clavicle), elbow -> ``lowerarm01``, wrist -> ``wrist``, hip -> ``upperleg01``, knee -> ``lowerleg01``,
    ankle -> ``foot``. BlazePose documents its hand points as knuckles ("pinky #1 knuckle", "index #1
    knuckle", "thumb #2 knuckle"), so they are the heads of ``finger5-1``, ``finger2-1`` and ``finger1-2``.
    Nose, eyes, ears, heels and foot index (big-toe tip) use the keypoint regressor shipped in the Anny wheel
    (``anny/data/keypoints/coco.pth``): the regressed rest-pose point is snapped to the nearest vertex. (The
    single largest regression weight is not used: those weights are smooth and their argmax can sit off the
    feature, e.g. about 9 mm off the midline for the nose.) The regressed heel lies about 2 cm inside the
    foot, while MediaPipe's heel is on the back of the heel, so the heel is the most posterior (+Y) vertex
    within 3 cm of the regressed point. Eye corners and mouth corners reuse the face-mesh result for
    landmarks 133/33/362/263 and 61/291, so pose and face agree.

Face mesh (468)
    MediaPipe's canonical face model (``canonical_face_model.obj``: 468 points, centimetres, Y up, the face
    looking down +Z) is converted to Anny's frame, ``(x, y, z) -> 0.01 * (x, -z, y)``, and registered to
    the rest-pose head:

    1. Anchors. Eight pairs fix an initial similarity (Umeyama): the four eye corners 33/133/362/263 <->
       the lateral/medial extremes of each eyelid rim (the surface vertices bordering Anny's eye-socket
       cavity); the two mouth corners 61/291 <-> the lateral extremes of the lip seam (surface vertices
       bordering the mouth cavity); the pronasale 4 (MediaPipe's frontmost point; landmark 1 sits just
       below it) <-> Anny's frontmost midline vertex; the menton 152 <-> the midline chin vertex lying
       farthest along the down-and-forward diagonal.
    2. Trimmed similarity ICP. Ten rounds re-pair every canonical point with its nearest front-facing
       head vertex (skinned mostly to ``head``, vertex normal within ~70 degrees of -Y), drop the worst
       20 % of pairs (sides of the face), and re-fit a similarity; the anchors stay in every fit with
       20x weight so the alignment cannot slide along the face.
    3. Assignment. Candidates are the face-surface vertices: skinned mostly to head or neck bones, on the
       main surface (not the eyeballs or the tongue) and not on the inner mouth / eye-socket cavity
       surfaces listed in ``anny/data/template_mesh_internal_cavities.pth``. Every landmark gets a
       *distinct* vertex by one assignment (Hungarian algorithm) minimising the total squared distance, so
       dense MediaPipe rings (lips, eyelids) spread over neighbouring vertices instead of piling onto one.
       Anny's lips meet and its eyelids are thin, so the eyelid-margin and inner-lip contours are
       restricted to the rim vertices of the matching opening, upper contour to the upper half of the rim
       and lower contour to the lower half (split at the height of the corners); this keeps upper and
       lower lip / lid apart.
    4. Rejection. A landmark farther than ``--max-residual-mm`` (default 8 mm) from its vertex gets no
       correspondence (null). Front-of-face mesh edges are 3.5 mm (median) and at most ~8 mm (90th
       percentile), so a point lying on Anny's surface is within ~5 mm of a vertex, and even a second-choice
       vertex from the distinct assignment stays under 8 mm; the threshold only rejects landmarks where
       Anny's face shape departs from the canonical one (default identity: the nose dorsum, 5/195/197).

The canonical face model is not shipped in the ``mediapipe`` 0.10.x wheels (their
``face_geometry/data`` folders are empty); pass ``--canonical-face-model`` to a copy of
``mediapipe/modules/face_geometry/data/canonical_face_model.obj`` from the MediaPipe repository (Apache-2.0)
when the wheel directory does not contain one. Only the ``v`` lines are read.

The build is deterministic (no randomness; ties break by lowest index).
"""
from __future__ import annotations

import argparse
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from m3t.body.anny_body import DATA_DIR
from m3t.body.landmarks import HAND_LANDMARKS, POSE_LANDMARKS
from m3t.body.similarity import SimilarityTransform, similarity_transform

N_FACE = 468

# Pose landmarks tied to a bone head, per side ("{s}" = L/R).
POSE_BONES = {
    "shoulder": "upperarm01.{s}", "elbow": "lowerarm01.{s}", "wrist": "wrist.{s}",
    "pinky": "finger5-1.{s}", "index": "finger2-1.{s}", "thumb": "finger1-2.{s}",
    "hip": "upperleg01.{s}", "knee": "lowerleg01.{s}", "ankle": "foot.{s}",
}
# Pose landmarks taken from Anny's COCO keypoint regressor (pose name -> coco label).
POSE_FROM_COCO = {
    "nose": "nose", "left_eye": "left_eye", "right_eye": "right_eye", "left_ear": "left_ear",
    "right_ear": "right_ear", "left_heel": "left_heel", "right_heel": "right_heel",
    "left_foot_index": "left_big_toe", "right_foot_index": "right_big_toe",
}
HEEL_RADIUS = 0.03  # metres around the regressed heel point searched for the most posterior (+Y) vertex
# Pose landmarks that reuse a face-mesh landmark.
POSE_FROM_FACE = {
    "left_eye_inner": 362, "left_eye_outer": 263, "right_eye_inner": 133, "right_eye_outer": 33,
    "mouth_left": 291, "mouth_right": 61,
}

# Face-mesh contours (MediaPipe's FACEMESH_LIPS / FACEMESH_*_EYE index lists, corner to corner).
INNER_LIP_UPPER = (78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308)
INNER_LIP_LOWER = (78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308)
RIGHT_EYE_UPPER = (33, 246, 161, 160, 159, 158, 157, 173, 133)
RIGHT_EYE_LOWER = (33, 7, 163, 144, 145, 153, 154, 155, 133)
LEFT_EYE_UPPER = (263, 466, 388, 387, 386, 385, 384, 398, 362)
LEFT_EYE_LOWER = (263, 249, 390, 373, 374, 380, 381, 382, 362)

# Anchor pairs for the initial similarity: canonical index -> Anny feature name (see _face_features).
FACE_ANCHORS = {
    33: "right_eye_outer", 133: "right_eye_inner", 362: "left_eye_inner", 263: "left_eye_outer",
    4: "pronasale", 61: "mouth_right", 291: "mouth_left", 152: "menton",
}


# ---------------------------------------------------------------------------------------------- inputs
def find_canonical_face_model(wheel_dir: Path | None) -> bytes | None:
    """Return the bytes of ``canonical_face_model.obj`` found under ``wheel_dir`` (unpacked or in wheels).

    Parameters
    ----------
    wheel_dir
        Folder holding ``mediapipe-*.whl`` files and/or unpacked wheel trees; ``None`` searches nothing.

    Returns
    -------
    bytes or None
        The file contents, or ``None`` when no copy exists there.
    """
    if wheel_dir is None:
        return None
    for path in sorted(Path(wheel_dir).rglob("canonical_face_model.obj")):
        return path.read_bytes()
    for wheel in sorted(Path(wheel_dir).rglob("*.whl")):
        with zipfile.ZipFile(wheel) as archive:
            for name in sorted(archive.namelist()):
                if name.endswith("canonical_face_model.obj"):
                    return archive.read(name)
    return None


def parse_obj_vertices(text: str) -> np.ndarray:
    """The ``v x y z`` lines of an OBJ file as an (N, 3) float64 array."""
    rows = [line.split()[1:4] for line in text.splitlines() if line.startswith("v ")]
    return np.asarray(rows, dtype=np.float64)


def canonical_to_anny(points_cm: np.ndarray) -> np.ndarray:
    """MediaPipe canonical frame (cm, Y up, face towards +Z) -> Anny frame (m, Z up, face towards -Y)."""
    x, y, z = points_cm.T
    return 0.01 * np.stack([x, -z, y], axis=1)


# ---------------------------------------------------------------------------------------------- Anny rest data
@dataclass
class AnnyRest:
    """Rest-pose geometry of Anny at the default identity (all float64 numpy).

    Attributes
    ----------
    vertices : (V, 3) rest vertex positions.
    normals : (V, 3) unit area-weighted vertex normals.
    heads : (J, 3) bone heads.
    axes : (J, 3) unit head -> tail direction of each bone (the rest bone frame's Y axis, Blender style).
    bone_names : the J bone names.
    faces : (F, 3) triangles.
    dominant : (V,) index of the bone with the largest skinning weight.
    bone_weight : (V, J) dense skinning weights.
    component : (V,) connected-component label (0 = the main body surface).
    cavity : (V,) bool, vertices of Anny's internal cavities (mouth, eye sockets).
    coco : label -> (3,) rest position regressed by Anny's COCO keypoint regressor.
    """

    vertices: np.ndarray
    normals: np.ndarray
    heads: np.ndarray
    axes: np.ndarray
    bone_names: tuple[str, ...]
    faces: np.ndarray
    dominant: np.ndarray
    bone_weight: np.ndarray
    component: np.ndarray
    cavity: np.ndarray
    coco: dict[str, np.ndarray]

    def bone(self, name: str) -> int:
        return self.bone_names.index(name)

    def dominated_by(self, names) -> np.ndarray:
        """(V,) bool: vertices whose largest skinning weight belongs to one of ``names``."""
        ids = [self.bone(n) for n in names]
        return np.isin(self.dominant, ids)


def load_anny_rest(body=None) -> AnnyRest:
    """Evaluate Anny's rest pose (default identity) and gather what the builder needs.

    Parameters
    ----------
    body
        An :class:`m3t.body.anny_body.AnnyBody`; built when omitted.
    """
    import anny.paths

    from m3t.body.anny_body import AnnyBody

    body = AnnyBody() if body is None else body
    model = body._anny
    with torch.no_grad():
        identity = body.default_identity()
        out = body.forward(body.rest_params(1), identity)
        rest_bones = body._rest_bones(body._identity_coeffs(identity))[0]  # (J, 4, 4)
    vertices = out.vertices[0].double().numpy()
    heads = out.joints[0].double().numpy()
    faces = np.asarray(body.faces, dtype=np.int64)
    n_vert, n_bone = len(vertices), len(body.joint_names)

    bones = body.skin_bones.numpy()
    weights = body.skin_weights.double().numpy()
    bone_weight = np.zeros((n_vert, n_bone))
    np.add.at(bone_weight, (np.repeat(np.arange(n_vert), bones.shape[1]), bones.ravel()), weights.ravel())

    corner = vertices[faces]
    face_normal = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])  # area-weighted
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normal)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-12)

    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n_vert, n_vert))
    _, component = connected_components(graph, directed=False)
    main = np.bincount(component).argmax()
    component = np.where(component == main, 0, component + 1)

    root = anny.paths.get_anny_root_dir() / "data"
    base_index = model.base_mesh_vertex_indices.cpu().numpy()  # model vertex -> base-mesh vertex
    to_model = {int(b): i for i, b in enumerate(base_index)}
    cavity_base = torch.load(root / "template_mesh_internal_cavities.pth", weights_only=True)["vertex_indices"]
    cavity = np.zeros(n_vert, dtype=bool)
    cavity[[to_model[int(b)] for b in cavity_base if int(b) in to_model]] = True

    coco = {}
    for label, w in torch.load(root / "keypoints" / "coco.pth", weights_only=True).items():
        w = w[model.base_mesh_vertex_indices].double().numpy()
        coco[label] = w @ vertices / w.sum()

    return AnnyRest(
        vertices=vertices, normals=normals, heads=heads, axes=rest_bones[:, :3, 1].double().numpy(),
        bone_names=tuple(body.joint_names), faces=faces, dominant=bone_weight.argmax(1),
        bone_weight=bone_weight, component=component, cavity=cavity, coco=coco,
    )


# ---------------------------------------------------------------------------------------------- geometry helpers
def fit_similarity(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> SimilarityTransform:
    """Weighted least-squares similarity ``dst ~ s * R @ src + t`` (Umeyama 1991) of (K, 3) point sets, solved in
    float64 by the textbook SVD (``method="svd"``)."""
    def as64(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(a, dtype=torch.float64)

    return similarity_transform(as64(src), as64(dst), "svd", None if weights is None else as64(weights))


def apply_similarity(fit: SimilarityTransform, points: np.ndarray) -> np.ndarray:
    """(K, 3) points moved by ``fit``."""
    return fit.apply(torch.as_tensor(points, dtype=torch.float64)).numpy()


def rim_vertices(rest: AnnyRest, cavity_mask: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """Surface vertices sharing an edge with a vertex of ``cavity_mask``: the rim of that opening."""
    faces = rest.faces
    touches = cavity_mask[faces].any(1)
    rim = np.unique(faces[touches])
    return rim[surface[rim] & ~cavity_mask[rim]]


def _face_features(rest: AnnyRest, surface: np.ndarray) -> tuple[dict[str, int], dict[str, np.ndarray]]:
    """Locate Anny's facial anchor vertices and the eyelid / lip rims.

    Parameters
    ----------
    rest
        Anny rest data.
    surface
        (V,) bool, the candidate face-surface vertices.

    Returns
    -------
    anchors
        feature name -> vertex index (see ``FACE_ANCHORS``).
    rims
        ``"right_eye" | "left_eye" | "mouth"`` -> vertex indices of that opening's rim.
    """
    v = rest.vertices
    eye_l, eye_r = rest.heads[rest.bone("eye.L")], rest.heads[rest.bone("eye.R")]
    eye_z = 0.5 * (eye_l[2] + eye_r[2])
    head_cavity = rest.cavity & rest.dominated_by(["head"])
    # Cavity vertices split by height: the eye sockets sit around the eye bones, the mouth well below.
    socket = head_cavity & (v[:, 2] > eye_z - 0.02)
    mouth = head_cavity & (v[:, 2] < eye_z - 0.03)
    rims = {
        "left_eye": rim_vertices(rest, socket & (v[:, 0] > 0), surface),
        "right_eye": rim_vertices(rest, socket & (v[:, 0] < 0), surface),
        "mouth": rim_vertices(rest, mouth, surface),
    }
    anchors = {}
    for side, rim in (("left", rims["left_eye"]), ("right", rims["right_eye"])):
        lateral = np.abs(v[rim, 0])
        anchors[f"{side}_eye_outer"] = int(rim[np.argmax(lateral)])
        anchors[f"{side}_eye_inner"] = int(rim[np.argmin(lateral)])
    anchors["mouth_left"] = int(rims["mouth"][np.argmax(v[rims["mouth"], 0])])
    anchors["mouth_right"] = int(rims["mouth"][np.argmin(v[rims["mouth"], 0])])

    midline = np.where(surface & (np.abs(v[:, 0]) < 0.002) & (v[:, 2] < eye_z))[0]
    anchors["pronasale"] = int(midline[np.argmin(v[midline, 1])])  # frontmost = most -Y
    mouth_z = v[[anchors["mouth_left"], anchors["mouth_right"]], 2].mean()
    chin = midline[v[midline, 2] < mouth_z]
    anchors["menton"] = int(chin[np.argmax(-v[chin, 1] - v[chin, 2])])  # farthest along (0, -1, -1)
    return anchors, rims


def assign_vertices(
    points: np.ndarray, v: np.ndarray, candidates: np.ndarray, allowed: dict[int, np.ndarray], radius: float
) -> np.ndarray:
    """One distinct vertex per point, minimising the total squared distance (Hungarian algorithm).

    Parameters
    ----------
    points
        (K, 3) aligned landmark positions.
    v
        (V, 3) vertex positions.
    candidates
        Vertex indices any landmark may use.
    allowed
        landmark -> the only vertex indices that landmark may use (a subset of ``candidates``).
    radius
        Pairs farther apart than this are not considered (keeps the problem small).

    Returns
    -------
    (K,) vertex index per landmark; a landmark left without any pair within ``radius`` gets its nearest
    candidate (it will fail the residual test).
    """
    near = cKDTree(v[candidates]).query_ball_point(points, r=radius)
    cols = np.unique(np.concatenate([candidates[n] for n in near if n]))
    column_of = {int(c): j for j, c in enumerate(cols)}
    big = 1e6
    cost = np.full((len(points), len(cols)), big)
    for k, n in enumerate(near):
        pool = candidates[n] if k not in allowed else np.intersect1d(allowed[k], candidates[n])
        j = [column_of[int(c)] for c in pool]
        cost[k, j] = ((v[pool] - points[k]) ** 2).sum(1)
    rows, chosen = linear_sum_assignment(cost)
    _, nearest = cKDTree(v[candidates]).query(points)
    vertex = candidates[nearest]
    ok = cost[rows, chosen] < big
    vertex[rows[ok]] = cols[chosen[ok]]
    return vertex


# ---------------------------------------------------------------------------------------------- face
def register_face(rest: AnnyRest, canonical: np.ndarray, max_residual: float, icp_rounds: int = 10) -> dict:
    """Register the 468 canonical face points to Anny's head and assign a vertex (or None) to each.

    Parameters
    ----------
    rest
        Anny rest data.
    canonical
        (468, 3) canonical face model points in Anny's frame (metres).
    max_residual
        Landmarks farther than this (metres) from their vertex get no correspondence.
    icp_rounds
        Rounds of trimmed similarity ICP after the anchor alignment.

    Returns
    -------
    dict with ``vertex`` (list of int | None), ``residual`` (468,) metres, ``anchors``, ``scale``,
    ``anchor_rms`` (metres, after ICP).
    """
    v = rest.vertices
    surface = (rest.component == 0) & ~rest.cavity & rest.dominated_by(["head", "neck01", "neck02", "neck03"])
    anchors, rims = _face_features(rest, surface)
    a_idx = np.array(list(FACE_ANCHORS))
    a_dst = v[[anchors[FACE_ANCHORS[i]] for i in a_idx]]
    fit = fit_similarity(canonical[a_idx], a_dst)

    front = surface & rest.dominated_by(["head"]) & (rest.normals[:, 1] < -0.35)
    front_idx = np.where(front)[0]
    tree = cKDTree(v[front_idx])
    anchor_weight = 20.0
    for _ in range(icp_rounds):
        aligned = apply_similarity(fit, canonical)
        dist, nearest = tree.query(aligned)
        keep = dist <= np.quantile(dist, 0.8)  # trim the worst 20 % (sides of the face, occluded points)
        src = np.concatenate([canonical[keep], canonical[a_idx]])
        dst = np.concatenate([v[front_idx[nearest[keep]]], a_dst])
        w = np.concatenate([np.ones(keep.sum()), np.full(len(a_idx), anchor_weight)])
        fit = fit_similarity(src, dst, w)
    aligned = apply_similarity(fit, canonical)

    # Eyelid margins and inner lips may only use the rim of their opening, upper/lower halves apart.
    allowed = {}
    for upper, lower, rim, (c0, c1) in (
        (INNER_LIP_UPPER, INNER_LIP_LOWER, rims["mouth"], ("mouth_left", "mouth_right")),
        (RIGHT_EYE_UPPER, RIGHT_EYE_LOWER, rims["right_eye"], ("right_eye_outer", "right_eye_inner")),
        (LEFT_EYE_UPPER, LEFT_EYE_LOWER, rims["left_eye"], ("left_eye_outer", "left_eye_inner")),
    ):
        mid_z = v[[anchors[c0], anchors[c1]], 2].mean()
        for landmark in (upper[0], upper[-1]):
            allowed[landmark] = rim
        for landmark in upper[1:-1]:
            allowed[landmark] = rim[v[rim, 2] >= mid_z]
        for landmark in lower[1:-1]:
            allowed[landmark] = rim[v[rim, 2] < mid_z]
    vertex = assign_vertices(aligned, v, np.where(surface)[0], allowed, radius=2.0 * max_residual)
    residual = np.linalg.norm(aligned - v[vertex], axis=1)
    result = [int(vi) if r <= max_residual else None for vi, r in zip(vertex, residual)]
    anchor_rms = float(np.sqrt(((aligned[a_idx] - a_dst) ** 2).sum(1).mean()))
    return {"vertex": result, "residual": residual, "anchors": anchors, "scale": float(fit.scale),
            "anchor_rms": anchor_rms}


# ---------------------------------------------------------------------------------------------- hands / pose
def fingertip_vertex(rest: AnnyRest, bone_name: str) -> int:
    """The vertex at the distal end of ``bone_name``: among vertices skinned mostly to it, the farthest
    along the bone's head -> tail direction."""
    b = rest.bone(bone_name)
    head, axis = rest.heads[b], rest.axes[b]
    cand = np.where(rest.dominant == b)[0]
    return int(cand[np.argmax((rest.vertices[cand] - head) @ axis)])


def hand_entries(rest: AnnyRest, prefix: str, side: str) -> list[dict]:
    entries = [{"name": f"{prefix}:wrist", "vertex": None, "bone": f"wrist.{side}"}]
    for finger, digit in enumerate(("thumb", "index_finger", "middle_finger", "ring_finger", "pinky"), start=1):
        names = ("cmc", "mcp", "ip") if finger == 1 else ("mcp", "pip", "dip")
        for phalanx, joint in enumerate(names, start=1):
            entries.append({"name": f"{prefix}:{digit}_{joint}", "vertex": None, "bone": f"finger{finger}-{phalanx}.{side}"})
        tip = fingertip_vertex(rest, f"finger{finger}-3.{side}")
        entries.append({"name": f"{prefix}:{digit}_tip", "vertex": tip, "bone": None})
    assert [e["name"].split(":")[1] for e in entries] == list(HAND_LANDMARKS)
    return entries


def pose_entries(rest: AnnyRest, face_vertex: list[int | None]) -> tuple[list[dict], dict[str, float]]:
    """The 33 pose entries and, for regressor-based ones, the snap distance (metres) to the chosen vertex."""
    tree = cKDTree(rest.vertices)
    entries, snap = [], {}
    for name in POSE_LANDMARKS:
        entry = {"name": f"pose:{name}", "vertex": None, "bone": None}
        side, _, part = name.partition("_")
        if name in POSE_FROM_COCO:
            point = rest.coco[POSE_FROM_COCO[name]]
            if part == "heel":  # the regressed heel lies inside the foot: take the back of the heel
                near = np.asarray(tree.query_ball_point(point, r=HEEL_RADIUS))
                idx = int(near[np.argmax(rest.vertices[near, 1])])
                dist = float(np.linalg.norm(rest.vertices[idx] - point))
            else:
                dist, idx = tree.query(point)
            entry["vertex"], snap[name] = int(idx), float(dist)
        elif name in POSE_FROM_FACE:
            entry["vertex"] = face_vertex[POSE_FROM_FACE[name]]
        elif part in POSE_BONES:
            entry["bone"] = POSE_BONES[part].format(s="L" if side == "left" else "R")
        else:
            raise KeyError(f"no rule for pose landmark {name!r}")
        entries.append(entry)
    return entries, snap


# ---------------------------------------------------------------------------------------------- main
HOW_MADE = (
    "Built by tools/build_correspondence.py on Anny's rest pose (default identity). Hands: wrist and "
    "finger joints are bone heads (finger{1..5}-{1..3}); fingertips are the vertex farthest along the distal "
    "phalanx. Pose: joints are bone heads (upperarm01, lowerarm01, wrist, upperleg01, lowerleg01, foot; "
    "hand knuckles finger5-1/finger2-1/finger1-2); nose/eyes/ears/foot index snap Anny's COCO keypoint "
    "regressor to the nearest vertex (heels: the most posterior vertex within 3 cm); eye and mouth corners reuse the face result. Face: MediaPipe's canonical "
    "face model is aligned to Anny's head by a similarity from 8 anchors (eye corners, mouth corners, pronasale, "
    "menton), refined by trimmed similarity ICP on front-facing head vertices; landmarks then get distinct "
    "head/neck surface vertices by a minimum-total-squared-distance assignment (eyelid and inner-lip contours "
    "restricted to the upper/lower halves of the eyelid/lip rims), and landmarks farther than the residual "
    "threshold from their vertex are null."
)


def build(canonical_cm: np.ndarray, max_residual_mm: float = 8.0, rest: AnnyRest | None = None) -> dict:
    """Build the correspondence document.

    Parameters
    ----------
    canonical_cm
        (468, 3) vertices of MediaPipe's canonical face model, as stored in the OBJ (cm).
    max_residual_mm
        Face-landmark rejection threshold.
    rest
        Anny rest data (loaded when omitted).
    """
    if canonical_cm.shape != (N_FACE, 3):
        raise ValueError(f"canonical face model must have {N_FACE} vertices, got {canonical_cm.shape}")
    rest = load_anny_rest() if rest is None else rest
    face = register_face(rest, canonical_to_anny(canonical_cm), max_residual_mm / 1000.0)
    pose, snap = pose_entries(rest, face["vertex"])
    landmarks = pose + hand_entries(rest, "left_hand", "L") + hand_entries(rest, "right_hand", "R")
    landmarks += [{"name": f"face:{i}", "vertex": vi, "bone": None} for i, vi in enumerate(face["vertex"])]

    res_mm = face["residual"] * 1000.0
    valid = [vi for vi in face["vertex"] if vi is not None]
    stats = {
        "face_residual_median_mm": round(float(np.median(res_mm)), 2),
        "face_residual_p95_mm": round(float(np.percentile(res_mm, 95)), 2),
        "face_residual_max_mm": round(float(res_mm.max()), 2),
        "face_max_residual_threshold_mm": max_residual_mm,
        "face_scale_canonical_cm_to_anny_m": round(face["scale"] * 0.01, 5),
        "face_anchor_rms_mm": round(face["anchor_rms"] * 1000.0, 2),
        "face_anchor_vertices": face["anchors"],
        "face_null": N_FACE - len(valid),
        "face_distinct_vertices": len(set(valid)),
        "pose_null": sum(e["vertex"] is None and e["bone"] is None for e in pose),
        "hand_null": sum(e["vertex"] is None and e["bone"] is None for e in landmarks[33:75]),
        "pose_regressor_snap_mm": {k: round(d * 1000.0, 2) for k, d in snap.items()},
    }
    return {"landmark_set": "mediapipe_holistic", "how_made": HOW_MADE, "stats": stats, "landmarks": landmarks}


def to_json(doc: dict) -> str:
    """Serialise with one landmark per line (diff-friendly)."""
    head = {k: v for k, v in doc.items() if k != "landmarks"}
    body = ",\n".join("  " + json.dumps(e) for e in doc["landmarks"])
    return json.dumps(head, indent=1)[:-2] + ',\n "landmarks": [\n' + body + "\n ]\n}\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mediapipe-wheel-dir", type=Path, help="folder with the mediapipe wheel (zipped or unpacked)")
    parser.add_argument("--canonical-face-model", type=Path, help="canonical_face_model.obj, if not in the wheel")
    parser.add_argument("--out", type=Path, default=DATA_DIR / "anny_mediapipe_holistic.json")
    parser.add_argument("--max-residual-mm", type=float, default=8.0)
    args = parser.parse_args(argv)

    data = find_canonical_face_model(args.mediapipe_wheel_dir)
    if data is None and args.canonical_face_model is not None:
        data = Path(args.canonical_face_model).read_bytes()
    if data is None:
        raise SystemExit(
            "canonical_face_model.obj not found in --mediapipe-wheel-dir (mediapipe 0.10.x wheels do not ship it); "
            "pass --canonical-face-model PATH to mediapipe/modules/face_geometry/data/canonical_face_model.obj"
        )
    doc = build(parse_obj_vertices(data.decode()), args.max_residual_mm)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(to_json(doc))
    print(json.dumps(doc["stats"], indent=1))


if __name__ == "__main__":
    main()
