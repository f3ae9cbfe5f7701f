"""Points on a skeleton graph (:mod:`m3t.body.skeleton`) and the coordinates SGSA's models see.

- Where the points come from: :func:`body_points` poses the graph's joints on a body model (through
  :func:`graph_correspondence`), :func:`holistic_points` picks them from named MediaPipe-Holistic points of
  ``.pose`` corpora (the neck being the mid-shoulder point);
- what a model sees: :func:`normalise` centres every frame on the neck and divides by the clip's mean shoulder
  width, :func:`denormalise` brings coordinates back to metres; :func:`regions` splits points by region for the
  metrics of :mod:`m3t.metrics.motion`.

Axis legend: T frames, J joints of a graph, K named input points.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from m3t.body.metric_sets import _neck_index, subset_correspondence
from m3t.body.protocol import BodyModel, Correspondence, as_tensors
from m3t.body.skeleton import SkeletonGraph


def graph_correspondence(body: BodyModel, graph: SkeletonGraph) -> Correspondence:
    """Where each joint of ``graph`` sits on ``body``: ``body:neck`` the model's neck joint (as
    :func:`m3t.body.metric_sets.metric_keypoints`), ``body:<p>`` the holistic ``pose:<p>``, hand and face joints
    their holistic namesakes. A ``ValueError`` names joints the model has no point for."""
    corr = body.correspondence("mediapipe_holistic")
    source = ["pose:" + j.split(":", 1)[1] if j.startswith("body:") else j for j in graph.joints]
    neck = [i for i, j in enumerate(graph.joints) if j == "body:neck"]
    rows = [i for i in range(len(source)) if i not in neck]
    try:
        sub = subset_correspondence(corr, [source[i] for i in rows])
    except KeyError as err:
        raise ValueError(f"skeleton {graph.name!r} on body model {body.name!r}: {err.args[0]}") from None
    kind = np.zeros(len(source), dtype=np.int64)
    index = np.zeros(len(source), dtype=np.int64)
    kind[rows], index[rows] = sub.kind, sub.index
    if neck:
        kind[neck], index[neck] = 1, _neck_index(body)
    lost = [j for j, k in zip(graph.joints, kind) if k < 0]
    if lost:
        raise ValueError(f"body model {body.name!r} has no point for joints {lost} of skeleton {graph.name!r}")
    return Correspondence(graph.joints, kind, index)


@torch.no_grad()
def body_points(body: BodyModel, params: Mapping[str, np.ndarray], identity: np.ndarray,
                graph: SkeletonGraph) -> np.ndarray:
    """(T, J, 3) float64 metres of ``graph``'s joints for a parameter sequence ((T, D_m) per modality, (P,)
    identity): body and hand joints exactly the points of :func:`m3t.body.metric_sets.metric_points`, face
    joints the holistic correspondence's points (see :func:`graph_correspondence`)."""
    keypoints = body.keypoint_set(graph_correspondence(body, graph))
    ident = torch.as_tensor(np.asarray(identity), dtype=torch.float32)
    return body.forward_keypoints(as_tensors(params), ident, keypoints).cpu().numpy().astype(np.float64)


_POSE_ALIASES = {"pose": "pose", "pose_landmarks": "pose", "left_hand": "left_hand",
                 "left_hand_landmarks": "left_hand", "right_hand": "right_hand",
                 "right_hand_landmarks": "right_hand", "face": "face", "face_landmarks": "face"}


def _canonical(name: str) -> str:
    part, _, point = str(name).partition(":")
    return f"{_POSE_ALIASES.get(part.strip().lower(), part.strip().lower())}:{point.strip().lower()}"


def holistic_points(points: np.ndarray, names: Sequence[str], graph: SkeletonGraph) -> np.ndarray:
    """(T, K, 3) named holistic points -> (T, J, 3) joints of ``graph`` (float64, same units).

    ``names``: K ``"part:name"`` as :func:`m3t.render.posefile.holistic_points` returns them (``pose:nose``,
    ``left_hand:wrist``, ``face:61``) or as a ``.pose`` file's components name them (``POSE_LANDMARKS:NOSE``,
    ``LEFT_HAND_LANDMARKS:WRIST``, ``FACE_LANDMARKS:61``); parts and names match case-insensitively. Graph joint
    ``body:<p>`` reads ``pose:<p>``, hand and face joints their namesakes; ``body:neck`` is the mean of the two
    shoulders. Missing points (NaN) stay NaN. A ``ValueError`` names the points ``names`` lacks.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[-1] != 3 or points.shape[1] != len(names):
        raise ValueError(f"holistic points: expected (T, {len(names)}, 3) for {len(names)} names, got "
                         f"{points.shape}")
    position: dict[str, int] = {}
    for k, name in enumerate(names):
        position.setdefault(_canonical(name), k)
    wanted = []
    for joint in graph.joints:
        region, point = joint.split(":", 1)
        if joint == "body:neck":
            wanted.append(("pose:left_shoulder", "pose:right_shoulder"))
        else:
            wanted.append((_canonical(f"{'pose' if region == 'body' else region}:{point}"),))
    missing = sorted({n for group in wanted for n in group if n not in position})
    if missing:
        raise ValueError(f"skeleton {graph.name!r}: the holistic points lack {missing}")
    out = np.empty((points.shape[0], len(graph.joints), 3), dtype=np.float64)
    for j, group in enumerate(wanted):
        out[:, j] = points[:, [position[n] for n in group]].mean(axis=1)
    return out


def _shoulders(graph: SkeletonGraph) -> tuple[int, int]:
    return graph.index("body:left_shoulder"), graph.index("body:right_shoulder")


def _check_points(points: np.ndarray, graph: SkeletonGraph) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[1:] != (len(graph.joints), 3):
        raise ValueError(f"skeleton {graph.name!r}: expected (T, {len(graph.joints)}, 3) points, got {points.shape}")
    return points


def normalise(points: np.ndarray, graph: SkeletonGraph) -> tuple[np.ndarray, float]:
    """(T, J, 3) metres -> ((T, 3 J) float32 coordinates, scale in metres).

    Every frame is centred on its neck (joint 0) and the clip divided by ``scale``, the mean over frames of the
    shoulder width (distance between ``body:left_shoulder`` and ``body:right_shoulder``): the model sees a
    signer-size- and position-free skeleton, and :func:`denormalise` brings it back to metres. NaN points (missing
    holistic points away from the neck and shoulders) stay NaN. A ``ValueError`` for a clip without frames or with
    a degenerate scale (non-finite or < 1e-6 m, e.g. a missing shoulder).
    """
    points = _check_points(points, graph)
    if points.shape[0] == 0:
        raise ValueError(f"skeleton {graph.name!r}: cannot normalise a clip of 0 frames")
    left, right = _shoulders(graph)
    scale = float(np.mean(np.linalg.norm(points[:, left] - points[:, right], axis=-1)))
    if not np.isfinite(scale) or scale < 1e-6:
        raise ValueError(f"skeleton {graph.name!r}: degenerate clip, mean shoulder width {scale} m (expected a finite "
                         "width >= 1e-6 m)")
    centred = (points - points[:, :1]) / scale
    return centred.reshape(points.shape[0], -1).astype(np.float32), scale


def denormalise(coords: np.ndarray, graph: SkeletonGraph, scale: float) -> np.ndarray:
    """(T, 3 J) normalised coordinates -> (T, J, 3) float64 metres with the neck at the origin (the inverse of
    :func:`normalise` up to the neck's translation)."""
    coords = np.asarray(coords, dtype=np.float64)
    if coords.ndim != 2 or coords.shape[1] != graph.width:
        raise ValueError(f"skeleton {graph.name!r}: expected (T, {graph.width}) coordinates, got {coords.shape}")
    return coords.reshape(coords.shape[0], len(graph.joints), 3) * float(scale)


def regions(points: np.ndarray, graph: SkeletonGraph) -> dict[str, np.ndarray]:
    """(T, J, 3) -> {region: (T, K, 3)} in :data:`REGIONS` order for the graph's regions (the form
    :func:`m3t.metrics.motion.evaluate_pairs` takes; body neck-first, hands wrist-first as its metrics assume)."""
    points = _check_points(points, graph)
    return {region: points[:, idx] for region, idx in graph.region_index().items()}
