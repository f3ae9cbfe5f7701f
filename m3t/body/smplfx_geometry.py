"""Mesh pieces of SMPL-FX (:mod:`m3t.body.smplfx_build`, steps 2 and 5): the neck rings along which SMPL-X and
FLAME are blended, grown over FLAME's edges from its open neck boundary, and the two teeth arches placed behind
the inner lips. Pure numpy on vertex / face arrays.

Frames: SMPL-X's (Y up, facing +Z, +X = the subject's left), metres.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from m3t.body.model_files import ModelFileError

TEETH_ARCH_POINTS, TEETH_PROFILE_POINTS = 26, 10


def _boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Vertex sets of the open boundaries (edges used by one face), one array per connected loop."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = uniq[counts == 1]
    adj: dict[int, list[int]] = {}
    for a, b in boundary:
        adj.setdefault(int(a), []).append(int(b))
        adj.setdefault(int(b), []).append(int(a))
    loops, seen = [], set()
    for start in adj:
        if start in seen:
            continue
        comp, stack = [], [start]
        seen.add(start)
        while stack:
            v = stack.pop()
            comp.append(v)
            for w in adj[v]:
                if w not in seen:
                    seen.add(w)
                    stack.append(w)
        loops.append(np.array(sorted(comp)))
    return loops


def neck_rings(flame_vertices: np.ndarray, flame_faces: np.ndarray, n_rings: int) -> list[np.ndarray]:
    """FLAME vertex indices of ``n_rings`` concentric rings, grown over mesh edges from the neck boundary."""
    loops = _boundary_loops(flame_faces)
    if not loops:
        raise ModelFileError("the FLAME mesh has no open boundary: cannot find the neck to blend")
    neck = min(loops, key=lambda loop: float(flame_vertices[loop, 1].mean()))
    n = flame_vertices.shape[0]
    adj = [[] for _ in range(n)]
    for a, b, c in flame_faces:
        adj[a] += [b, c]
        adj[b] += [a, c]
        adj[c] += [a, b]
    dist = np.full(n, -1, dtype=np.int64)
    dist[neck] = 0
    queue = deque(int(v) for v in neck)
    while queue:
        v = queue.popleft()
        if dist[v] >= n_rings - 1:
            continue
        for w in adj[v]:
            if dist[w] < 0:
                dist[w] = dist[v] + 1
                queue.append(w)
    return [np.flatnonzero(dist == k) for k in range(n_rings)]


def teeth_geometry(inner_lips: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two horseshoe arches behind the inner-lip points (8, 3): vertices (520, 3) (upper first), faces (1000, 3)
    int64 wound counter-clockwise seen from outside (outward normals, as the body mesh).

    Each arch is a tube (elliptic profile, 3 mm radial x 5 mm vertical) along a half-ellipse in the horizontal plane:
    its front 6 mm behind the inner lips' centre, its ends ``half`` = 0.55 x the inner mouth width (iBUG 61-65,
    at least 2 cm) to either side and 1.1 ``half`` further back. The arches lie 7 mm above (upper) and below
    (lower) the centre, mirror images of each other about that horizontal (occlusal) plane.
    """
    centre = inner_lips.mean(0)
    width = float(np.linalg.norm(inner_lips[0] - inner_lips[4]))  # iBUG 61 / 65: inner mouth corners
    half = max(width, 0.02) * 0.55
    depth = half * 1.1
    angles = np.linspace(-np.pi / 2, np.pi / 2, TEETH_ARCH_POINTS)
    profile = np.linspace(0, 2 * np.pi, TEETH_PROFILE_POINTS, endpoint=False)
    verts, faces = [], []
    for arch, sign in enumerate((1.0, -1.0)):  # upper, lower
        base = arch * TEETH_ARCH_POINTS * TEETH_PROFILE_POINTS
        ring_pts = []
        for a in angles:
            spine = centre + np.array([half * np.sin(a), sign * 0.007, -0.006 - depth * (1 - np.cos(a))])
            # outward from the arch centre, horizontal: (0, 0, 1) at the front (+Z), (+-1, 0, 0) at the ends; it
            # orients every profile ring the same way, so each face is wound counter-clockwise seen from outside
            radial = np.array([np.sin(a), 0.0, np.cos(a)])
            for p in profile:
                ring_pts.append(spine + 0.003 * np.cos(p) * radial + 0.005 * np.sin(p) * np.array([0, 1.0, 0]))
        verts.append(np.array(ring_pts))
        for i in range(TEETH_ARCH_POINTS - 1):
            for j in range(TEETH_PROFILE_POINTS):
                a0 = base + i * TEETH_PROFILE_POINTS + j
                a1 = base + i * TEETH_PROFILE_POINTS + (j + 1) % TEETH_PROFILE_POINTS
                b0, b1 = a0 + TEETH_PROFILE_POINTS, a1 + TEETH_PROFILE_POINTS
                faces += [(a0, b0, a1), (a1, b0, b1)]
    return np.concatenate(verts), np.asarray(faces, dtype=np.int64)
