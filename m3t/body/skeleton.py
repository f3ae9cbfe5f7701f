"""Skeleton graphs as data: the joints, limb connections and coordinate-level adjacency of SGSA's skeletal graph.

SGSA (Saunders et al. 2022) Sec. 4.2 represents a frame as the flat coordinates of a skeleton's joints (plus one
counter value) and masks its decoder's self-attention values with an adjacency matrix over those coordinates:
every coordinate of a joint is adjacent to every coordinate of the joints it is connected to by a limb, and to
the coordinates of its own joint (self-loops), rows normalised by their degree; the counter is adjacent to every
coordinate (Sec. 5 "Dataset"). This module defines the skeletons and that matrix; the temporal band (Eq. 5) is
the attention's business, not the graph's.

Two skeletons, each optionally with a small face subset (:data:`FACE_POINTS`):

- :func:`body_graph`: the body model's evaluation keypoints of :mod:`m3t.body.metric_sets` (12 upper-body points,
  neck first; 21 points per hand, wrist first), so that generated skeletons are scored on exactly the points
  :class:`m3t.metrics.scorer.MotionScorer` measures;
- :func:`holistic_graph`: MediaPipe-Holistic keypoints of ``.pose`` corpora (upper-body pose landmarks with a
  mid-shoulder neck, 21 points per hand).

Joints are named ``"<region>:<point>"`` with a region of :data:`REGIONS`; the first joint of ``body`` is the neck
and the first of each hand its wrist, the roots that the root-relative metrics of :mod:`m3t.metrics.motion` use.
Posing a graph's joints (on a body model, from holistic points) and normalising them live in
:mod:`m3t.body.skeleton_points`.

Axis legend: J joints of a graph, S = 3 J (+ 1 counter) coordinates.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from m3t.body.landmarks import POSE_LANDMARKS
from m3t.body.metric_sets import BODY_POINTS, HAND_POINTS
from m3t.dataclass_io import build_dataclass

REGIONS = ("body", "left_hand", "right_hand", "face")
HANDS = ("left_hand", "right_hand")

HOLISTIC_BODY_POINTS = ("neck",) + POSE_LANDMARKS[:17]
"""The holistic graph's body region: a mid-shoulder neck (MediaPipe has none), then pose landmarks 0-16."""

# mediapipe/python/solutions/pose_connections.py POSE_CONNECTIONS (pose landmark indices).
POSE_CONNECTIONS = (
    (0, 1), (1, 2), (2, 3), (3, 7), (0, 4), (4, 5), (5, 6), (6, 8), (9, 10), (11, 12), (11, 13), (13, 15),
    (15, 17), (15, 19), (15, 21), (17, 19), (12, 14), (14, 16), (16, 18), (16, 20), (16, 22), (18, 20), (11, 23),
    (12, 24), (23, 24), (23, 25), (24, 26), (25, 27), (26, 28), (27, 29), (28, 30), (29, 31), (30, 32), (27, 31),
    (28, 32),
)

# mediapipe/python/solutions/hands_connections.py HAND_CONNECTIONS over the "hand_landmark" index map (0 wrist;
# 1-4 thumb CMC, MCP, IP, tip; 5-8 index MCP, PIP, DIP, tip; 9-12 middle; 13-16 ring; 17-20 pinky), which is
# OpenPose's hand order and :data:`m3t.body.metric_sets.HAND_POINTS`.
HAND_CONNECTIONS = (
    (0, 1), (1, 2), (2, 3), (3, 4), (0, 5), (5, 6), (6, 7), (7, 8), (5, 9), (9, 10), (10, 11), (11, 12), (9, 13),
    (13, 14), (14, 15), (15, 16), (13, 17), (0, 17), (17, 18), (18, 19), (19, 20),
)

# The face subset: MediaPipe face-mesh indices (canonical 468-point mesh; "face:<index>" in the holistic layout
# and in a .pose file's FACE_LANDMARKS) of the sign-language non-manual articulators: brows, eye apertures, nose
# and mouth. Every one is a landmark of the iBUG-68 annotation under the usual MediaPipe-to-iBUG table, because
# those are the face points every body model here has a correspondence for (SMPL-FX's face correspondence is
# iBUG-68 only; Anny lacks mesh points 5, 195 and 197, none of them used). "right" is the subject's right.
FACE_POINTS: tuple[tuple[str, str], ...] = (
    ("70", "right brow, outer end (iBUG 18)"), ("63", "right brow (iBUG 19)"), ("105", "right brow, middle (iBUG 20)"),
    ("66", "right brow (iBUG 21)"), ("107", "right brow, inner end (iBUG 22)"),
    ("336", "left brow, inner end (iBUG 23)"), ("296", "left brow (iBUG 24)"), ("334", "left brow, middle (iBUG 25)"),
    ("293", "left brow (iBUG 26)"), ("300", "left brow, outer end (iBUG 27)"),
    ("168", "nose bridge between the brows (iBUG 28)"), ("4", "nose tip (iBUG 31)"),
    ("158", "right upper eyelid (iBUG 39)"), ("153", "right lower eyelid (iBUG 41)"),
    ("385", "left upper eyelid (iBUG 44)"), ("380", "left lower eyelid (iBUG 48)"),
    ("61", "right mouth corner (iBUG 49)"), ("39", "upper lip, right (iBUG 50)"), ("0", "upper lip, middle (iBUG 52)"),
    ("269", "upper lip, left (iBUG 54)"), ("291", "left mouth corner (iBUG 55)"), ("405", "lower lip, left (iBUG 56)"),
    ("17", "lower lip, middle (iBUG 58)"), ("181", "lower lip, right (iBUG 60)"),
    ("13", "upper lip, inner middle (iBUG 63)"), ("14", "lower lip, inner middle (iBUG 67)"),
)
FACE_CONNECTIONS = (
    ("70", "63"), ("63", "105"), ("105", "66"), ("66", "107"),  # right brow
    ("336", "296"), ("296", "334"), ("334", "293"), ("293", "300"),  # left brow
    ("107", "168"), ("336", "168"), ("168", "4"),  # brows to the nose bridge and tip
    ("105", "158"), ("158", "153"), ("334", "385"), ("385", "380"),  # each eye's lids under its brow
    ("61", "39"), ("39", "0"), ("0", "269"), ("269", "291"),  # outer lips ring: upper lip
    ("291", "405"), ("405", "17"), ("17", "181"), ("181", "61"),  # lower lip
    ("61", "13"), ("13", "291"), ("61", "14"), ("14", "291"),  # inner lips through the corners
    ("4", "0"),  # nose tip to the upper lip
)
FACE_ROOT = "4"
"""The face point linked to the body's nose (the face region's tie to the rest of the skeleton)."""


@dataclass(frozen=True)
class SkeletonGraph:
    """A skeleton: named joints and undirected limb connections between them.

    ``joints``: ``"<region>:<point>"`` with a region of :data:`REGIONS`; ``edges``: joint index pairs ``(i, j)``
    with ``i < j``, each once. A frame of the graph is ``width = 3 J`` coordinates: x, y, z of joint 0, then of
    joint 1, ...
    """

    name: str
    joints: tuple[str, ...]
    edges: tuple[tuple[int, int], ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "joints", tuple(str(j) for j in self.joints))
        object.__setattr__(self, "edges", tuple((int(i), int(j)) for i, j in self.edges))
        bad = [j for j in self.joints if j.split(":", 1)[0] not in REGIONS or ":" not in j]
        if bad:
            raise ValueError(f"skeleton {self.name!r}: joints {bad} are not '<region>:<point>' with a region of "
                             f"{REGIONS}")
        if len(set(self.joints)) != len(self.joints):
            raise ValueError(f"skeleton {self.name!r}: duplicate joints "
                             f"{sorted({j for j in self.joints if self.joints.count(j) > 1})}")
        n = len(self.joints)
        wrong = [e for e in self.edges if not 0 <= e[0] < e[1] < n]
        if wrong:
            raise ValueError(f"skeleton {self.name!r}: edges {wrong} are not (i, j) with 0 <= i < j < {n}")
        if len(set(self.edges)) != len(self.edges):
            raise ValueError(f"skeleton {self.name!r}: duplicate edges")

    @property
    def width(self) -> int:
        """3 J: the coordinates of a frame (without SGSA's counter)."""
        return 3 * len(self.joints)

    def region_index(self) -> dict[str, np.ndarray]:
        """Region -> (K,) joint indices in graph order, for the regions present, in :data:`REGIONS` order."""
        region_of = np.array([j.split(":", 1)[0] for j in self.joints])
        out = {r: np.flatnonzero(region_of == r) for r in REGIONS}
        return {r: idx for r, idx in out.items() if len(idx)}

    def coordinate_names(self) -> tuple[str, ...]:
        """``"body:neck.x"``, ``"body:neck.y"``, ...: the names of the ``width`` coordinates."""
        return tuple(f"{j}.{axis}" for j in self.joints for axis in "xyz")

    def index(self, joint: str) -> int:
        """Position of a joint by name; ``KeyError`` naming the graph when absent."""
        try:
            return self.joints.index(joint)
        except ValueError:
            raise KeyError(f"skeleton {self.name!r} has no joint {joint!r}") from None

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able form (stored in checkpoints)."""
        return {"name": self.name, "joints": list(self.joints), "edges": [list(e) for e in self.edges]}

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any]) -> SkeletonGraph:
        missing = {"name", "joints", "edges"} - set(raw)
        if missing:
            raise ValueError(f"skeleton graph dict lacks {sorted(missing)}")
        return build_dataclass(cls, dict(raw), "graph", ignore_unknown=True)


def _build(name: str, joints: list[str], named_edges: list[tuple[str, str]], face_points: bool) -> SkeletonGraph:
    """A body region (``joints``, ``named_edges``) completed with both hands (MediaPipe's HAND_CONNECTIONS) and,
    with ``face_points``, the face chains rooted at the body's nose (the graph is then named ``<name>+face``)."""
    joints = joints + [f"{side}:{p}" for side in HANDS for p in HAND_POINTS]
    named_edges = named_edges + [(f"{side}:{HAND_POINTS[a]}", f"{side}:{HAND_POINTS[b]}")
                                 for side in HANDS for a, b in HAND_CONNECTIONS]
    if face_points:
        name, joints = f"{name}+face", joints + [f"face:{i}" for i, _ in FACE_POINTS]
        named_edges = (named_edges + [(f"face:{a}", f"face:{b}") for a, b in FACE_CONNECTIONS]
                       + [("body:nose", f"face:{FACE_ROOT}")])
    position = {j: i for i, j in enumerate(joints)}
    edges = sorted({(min(position[a], position[b]), max(position[a], position[b])) for a, b in named_edges})
    return SkeletonGraph(name, tuple(joints), tuple(edges))


def body_graph(face_points: bool = False) -> SkeletonGraph:
    """The body model's metric keypoints (:mod:`m3t.body.metric_sets`) as a graph.

    Joints: the 12 upper-body points of ``BODY_POINTS`` (neck first), 21 left-hand and 21 right-hand points of
    ``HAND_POINTS`` (wrist first) = 54 joints, width 162; with ``face_points`` the 26 face points of
    :data:`FACE_POINTS` after them (80 joints, width 240). Edges: neck-shoulders, shoulder-elbow, elbow-wrist,
    neck-nose, nose-eyes, eye-ear (both sides); each body wrist to its hand's wrist point (the same model point,
    kept in both regions as the metrics have it); MediaPipe's HAND_CONNECTIONS within each hand; the face chains of
    :data:`FACE_CONNECTIONS` and the face's nose tip to the body's nose.
    """
    joints = [f"body:{p}" for p in BODY_POINTS]
    edges = [("body:neck", "body:left_shoulder"), ("body:neck", "body:right_shoulder"), ("body:neck", "body:nose")]
    for side in ("left", "right"):
        edges += [(f"body:{side}_shoulder", f"body:{side}_elbow"), (f"body:{side}_elbow", f"body:{side}_wrist"),
                  ("body:nose", f"body:{side}_eye"), (f"body:{side}_eye", f"body:{side}_ear"),
                  (f"body:{side}_wrist", f"{side}_hand:wrist")]
    return _build("body", joints, edges, face_points)


def holistic_graph(face_points: bool = False) -> SkeletonGraph:
    """MediaPipe-Holistic keypoints of ``.pose`` corpora as a graph.

    Layout (MediaPipe's ``pose_landmark`` and ``hand_landmark`` index maps, :data:`POSE_LANDMARKS`,
    :data:`HAND_POINTS`): body = a neck (the mid-shoulder point, first so that the region is neck-rooted as the
    metric's) then pose landmarks 0-16 (nose, eyes inner / centre / outer, ears, mouth corners, shoulders, elbows,
    wrists; the coarse hand points 17-22 and the lower body 23-32 are left out) = 18 joints; 21 + 21 hand points
    (wrist first) = 60 joints, width 180; with ``face_points`` the 26 of :data:`FACE_POINTS` (86 joints, width 258).

    Edges: MediaPipe's POSE_CONNECTIONS between the kept pose landmarks (eye chains to the ears, mouth corners,
    shoulders, arms); neck-shoulders and neck-nose (the neck's place in :func:`body_graph`); the nose to each mouth
    corner (POSE_CONNECTIONS leaves the mouth unconnected); each pose wrist to its hand's wrist; HAND_CONNECTIONS
    within each hand; the face chains and the face's nose tip to the pose nose.
    """
    kept = range(17)
    joints = [f"body:{p}" for p in HOLISTIC_BODY_POINTS]
    edges = [(f"body:{POSE_LANDMARKS[a]}", f"body:{POSE_LANDMARKS[b]}") for a, b in POSE_CONNECTIONS
             if a in kept and b in kept]
    edges += [("body:neck", "body:left_shoulder"), ("body:neck", "body:right_shoulder"), ("body:neck", "body:nose"),
              ("body:nose", "body:mouth_left"), ("body:nose", "body:mouth_right"),
              ("body:left_wrist", "left_hand:wrist"), ("body:right_wrist", "right_hand:wrist")]
    return _build("holistic", joints, edges, face_points)


def graph_for(kind: str, face_points: bool = False) -> SkeletonGraph:
    """``"body"`` -> :func:`body_graph`, ``"holistic"`` -> :func:`holistic_graph`."""
    builders = {"body": body_graph, "holistic": holistic_graph}
    if kind not in builders:
        raise ValueError(f"unknown skeleton {kind!r}; known: {sorted(builders)}")
    return builders[kind](face_points)


def adjacency(graph: SkeletonGraph, counter: bool = True) -> np.ndarray:
    """SGSA's normalised coordinate-level adjacency A* (Eq. 4-6, Sec. 5), (S, S) float32 with
    S = ``graph.width`` + ``counter``; coordinate 3 i + c is coordinate c (x, y, z) of joint i, the counter last.

    - A (Eq. 4): A[a, b] = 1 when a is a coordinate of joint i, b one of joint j and (i, j) is an edge (both ways:
      the graph is undirected). The counter has global adjacency: A[counter, b] = A[b, counter] = 1 for every
      coordinate b; A[counter, counter] = 0. A's diagonal is 0 (edges join different joints).
    - I* (self-loops): I*[a, b] = 1 when a and b are coordinates of the same joint (each coordinate to itself and
      to the other coordinates of its joint); I*[counter, counter] = 1.
    - D: the degree of each coordinate in A, its row sum (the number of its edges: 3 x the joint's limb edges,
      + 1 for the counter's edge when there is a counter; the counter's own degree is ``graph.width``).
    - A* = D^-1 A + I* (Eq. 6): row a of A divided by D[a]; a row of degree 0 (an isolated joint without
      counter) keeps only its I* entries.

    Eq. 5's temporal band (adjacency across the N previous frames) is applied by the attention, not here.
    """
    n, width = len(graph.joints), graph.width
    size = width + int(counter)
    joint_adj = np.zeros((n, n), dtype=np.float64)
    for i, j in graph.edges:
        joint_adj[i, j] = joint_adj[j, i] = 1.0
    a = np.zeros((size, size), dtype=np.float64)
    a[:width, :width] = np.kron(joint_adj, np.ones((3, 3)))
    self_loops = np.zeros((size, size), dtype=np.float64)
    self_loops[:width, :width] = np.kron(np.eye(n), np.ones((3, 3)))
    if counter:
        a[-1, :width] = a[:width, -1] = 1.0
        self_loops[-1, -1] = 1.0
    degree = a.sum(axis=1)
    inverse = np.divide(1.0, degree, out=np.zeros_like(degree), where=degree > 0)
    return (inverse[:, None] * a + self_loops).astype(np.float32)
