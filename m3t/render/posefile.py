"""Export body-model motion as a ``.pose`` file (pose-format) laid out like a MediaPipe-Holistic recording, so
generated signing opens in the tools the community already uses: pose-format's ``normalize``,
``hands_indexes``, ``correct_wrists``, ``pose_hide_legs``, ``reduce_holistic`` and ``PoseVisualizer``,
spoken-to-signed, sign-language segmentation / recognition.

Header: pose-format's own holistic header (``pose_format.utils.holistic.holistic_components()``, what its
``load_holistic`` writes): ``POSE_LANDMARKS`` 33, ``FACE_LANDMARKS`` 468, ``LEFT_HAND_LANDMARKS`` 21,
``RIGHT_HAND_LANDMARKS`` 21, ``POSE_WORLD_LANDMARKS`` 33 in that order, MediaPipe's point names (``NOSE``,
``WRIST``, ``"0"``...), its limbs and colours, point format ``XYZC``, version 0.2, depth 0. That function
imports mediapipe (an optional install here), so points and limbs are read from a real holistic file shipped
in the spoken-to-signed wheel (written with the refined face: of its 478 face points the 468 mesh points and
their limbs are kept, which is pose-format's unrefined header exactly); the hand colours come from
``pose_format.utils.openpose.hand_colors`` as in pose-format's ``holistic_hand_component`` (the shipped files
predate its current pinky colours).

Coordinates. The body model's points are in the protocol frame (metres, Z up, the body facing -Y, +X the
subject's left; Anny natively, SMPL-FX turned into it). An orthographic camera in front of the signer gives
image x = X (the subject's left on the image's right, as in a video of someone facing the camera),
image y = -Z (down) and z = Y (larger = farther from the camera, MediaPipe's sign and the order
``PoseVisualizer`` paints in). One scale and offset per clip centre the signer's points (legs aside) on a
``width`` x ``height`` canvas and fill it up to a margin, so the camera does not move within a clip; legs
fall below the canvas as in a video framed at the waist. z shares the pixel scale of x and y, centred on the
signer: pose-format's ``normalize`` measures the shoulders in 3D, so the units must be the same on all axes.
``POSE_WORLD_LANDMARKS`` are MediaPipe's world landmarks: the same axes in metres, origin between the hips in
each frame (between the shoulders for a body model without hips, e.g. SMPL-FX). pose-format's own MediaPipe
reader multiplies world x and y by the video size; this export keeps metres. Like any holistic file, they draw
as a dot at the canvas' corner in ``PoseVisualizer``; drop them first to hide it
(``pose.remove_components(["POSE_WORLD_LANDMARKS"])``).

Points the body model has no correspondence for get confidence 0 and coordinates 0, which pose-format reads
as masked points.

Skeletons (:func:`export_skeleton_pose`): a skeletal production model (SGSA, Progressive Transformers) emits
the joints of a :class:`m3t.body.skeleton.SkeletonGraph`, not body-model parameters, so there is no holistic
header to fill. Its clips are written as a ``.pose`` file of one component named after the graph
(``body``, ``holistic+face``...), whose points are the graph's joint names (``body:neck``, ``left_hand:wrist``,
``face:61``...) and whose limbs are the graph's edges, on the same front-view canvas as above; missing (NaN)
joints get confidence 0. pose-format's ``normalize`` knows only its own headers: pass the shoulders by name,
``pose.normalize(pose.header.normalization_info(p1=(name, "body:left_shoulder"), p2=(name,
"body:right_shoulder")))``.

Axis legend: T frames, K points.
"""
from __future__ import annotations

import io
from functools import cache
from pathlib import Path

import numpy as np
import torch

from m3t.atomic import write_bytes
from m3t.body.protocol import BodyModel, as_tensors
from m3t.body.skeleton import SkeletonGraph

# Correspondence part -> .pose component; pose-format's holistic component order, world landmarks last.
COMPONENTS = {"pose": "POSE_LANDMARKS", "face": "FACE_LANDMARKS", "left_hand": "LEFT_HAND_LANDMARKS",
              "right_hand": "RIGHT_HAND_LANDMARKS"}
WORLD = "POSE_WORLD_LANDMARKS"
POINTS = {"POSE_LANDMARKS": 33, "FACE_LANDMARKS": 468, "LEFT_HAND_LANDMARKS": 21, "RIGHT_HAND_LANDMARKS": 21,
          WORLD: 33}
LEGS = ("KNEE", "ANKLE", "HEEL", "FOOT_INDEX")  # pose points left out of the canvas fit
MARGIN = 0.08  # fraction of the canvas left free on each side
# Protocol frame (X the subject's left, Y away from the camera, Z up) -> image axes (x right, y down, z depth).
FRONT_VIEW = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@torch.no_grad()
def holistic_points(body: BodyModel, params: dict[str, np.ndarray],
                    identity: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """(T, K, 3) holistic points in metres, (K,) validity and the K point names (``part:name``)."""
    corr = body.correspondence("mediapipe_holistic")
    ident = torch.as_tensor(np.asarray(identity), dtype=torch.float32)
    points = body.forward_keypoints(as_tensors(params), ident, body.keypoint_set(corr)).numpy()
    return points, corr.valid, tuple(corr.names)


@cache
def _template() -> tuple[tuple[str, tuple[str, ...], tuple[tuple[int, int], ...], tuple[tuple[int, ...], ...]], ...]:
    """(name, points, limbs, colours) per holistic component, from a real file of the spoken-to-signed wheel
    (immutable, so the cache is safe to share)."""
    from importlib.resources import files as package_files

    from pose_format.pose_header import PoseHeader
    from pose_format.utils.openpose import hand_colors
    from pose_format.utils.reader import BufferReader

    # Read directly, not through m3t.corpora.fingerspelling: every stage exporting .pose files would otherwise
    # depend (in DVC) on that corpus adapter's code.
    hint = "install spoken-to-signed==0.4.0 (unzipped); its MediaPipe-Holistic files give the .pose export its header"
    try:
        root = Path(str(package_files("spoken_to_signed") / "assets" / "fingerspelling_lexicon"))
    except ModuleNotFoundError as exc:
        raise ModuleNotFoundError(f"the .pose export needs spoken-to-signed: {hint}") from exc
    files = sorted(root.glob("*/*.pose"))
    if not files:
        raise FileNotFoundError(f"no .pose file under {root}; {hint}")
    header = PoseHeader.read(BufferReader(files[0].read_bytes()))
    found = {c.name: c for c in header.components}
    if [c.name for c in header.components] != list(POINTS) or any(
            len(found[n].points) < k or found[n].format != "XYZC" for n, k in POINTS.items()):
        raise ValueError(f"{files[0]}: components {[(c.name, len(c.points), c.format) for c in header.components]}, "
                         f"expected {list(POINTS.items())} in XYZC; {hint}")
    out = []
    for name, n in POINTS.items():
        c = found[name]
        colors = hand_colors if "HAND" in name else c.colors
        out.append((name, tuple(c.points[:n]), tuple((int(a), int(b)) for a, b in c.limbs if a < n and b < n),
                    tuple(tuple(int(v) for v in rgb) for rgb in colors)))
    return tuple(out)


def holistic_components() -> list:
    """pose-format's holistic header components (fresh, mutable ``PoseHeaderComponent`` objects)."""
    from pose_format.pose_header import PoseHeaderComponent

    return [PoseHeaderComponent(name, list(points), list(limbs), [tuple(c) for c in colors], "XYZC")
            for name, points, limbs, colors in _template()]


def _order(names: tuple[str, ...]) -> np.ndarray:
    """(K_file,) index into the correspondence's points for each header point of the four image components,
    -1 where the body model has no such point; every correspondence name must map onto the header."""
    position = {name: k for k, name in enumerate(names)}
    part_of = {component: part for part, component in COMPONENTS.items()}
    order = []
    for component, points, _, _ in _template():
        if component in part_of:
            order += [position.pop(f"{part_of[component]}:{p.lower()}", -1) for p in points]
    if position:
        raise ValueError(f"holistic correspondence names {sorted(position)[:5]} (of {len(position)}) match no point "
                         f"of pose-format's holistic header; expected 'part:name' with part in {list(COMPONENTS)}")
    return np.asarray(order)


def front_view(points: np.ndarray, seen: np.ndarray, fit: np.ndarray, width: int, height: int,
               margin: float = MARGIN) -> np.ndarray:
    """Project protocol-frame points onto a ``width`` x ``height`` canvas (pixels, z in the same scale).

    Parameters
    ----------
    points : (T, K, 3) metres in the protocol frame (Z up, facing -Y)
    seen : (T, K) bool, the points that exist
    fit : (K,) bool, the points the canvas is fitted to (over all frames where seen)
    width, height : canvas size in pixels
    margin : fraction of each side left free

    Returns (T, K, 3) float64: x right, y down, z away from the camera; one scale and offset for the clip.
    """
    view = points @ FRONT_VIEW.T  # (T, K, 3)
    chosen = view[seen & fit[None]]  # (N, 3)
    if not len(chosen):
        raise ValueError("front view: no valid point to fit the canvas to (all points missing or non-finite)")
    low, high = chosen.min(0), chosen.max(0)
    span = np.maximum(high[:2] - low[:2], 1e-9)
    scale = min(width * (1 - 2 * margin) / span[0], height * (1 - 2 * margin) / span[1])
    return (view - (low + high) / 2) * scale + np.array([width / 2, height / 2, 0.0])


def holistic_pose(body: BodyModel, params: dict[str, np.ndarray], identity: np.ndarray, fps: float,
                  width: int = 1024, height: int = 1024):
    """``params`` (T frames) as a ``pose_format.Pose`` with pose-format's holistic header (see module doc)."""
    from pose_format import Pose
    from pose_format.numpy.pose_body import NumPyPoseBody
    from pose_format.pose_header import PoseHeader, PoseHeaderDimensions

    if not (0 < width <= 65535 and 0 < height <= 65535):
        raise ValueError(f".pose export: canvas {width} x {height} px; each side must be in 1..65535")
    points, valid, names = holistic_points(body, params, identity)
    if points.ndim != 3 or points.shape[0] == 0:
        raise ValueError(f".pose export: no frames to write (holistic points of shape {points.shape})")
    order = _order(names)
    has = order >= 0
    image = np.zeros((points.shape[0], len(order), 3))  # (T, K_file, 3)
    image[:, has] = points[:, order[has]]
    seen = has[None] & valid[np.maximum(order, 0)][None] & np.isfinite(image).all(-1)  # (T, K_file)
    image = np.where(seen[..., None], image, 0.0)
    pose_names = _template()[0][1]
    fit = np.ones(len(order), dtype=bool)
    fit[: len(pose_names)] = [not any(leg in p for leg in LEGS) for p in pose_names]
    canvas = np.where(seen[..., None], front_view(image, seen, fit, width, height), 0.0)

    n_pose = len(pose_names)
    world = image[:, :n_pose] @ FRONT_VIEW.T  # (T, 33, 3) metres
    world_seen = seen[:, :n_pose]
    at = {p: i for i, p in enumerate(pose_names)}
    for pair in (("LEFT_HIP", "RIGHT_HIP"), ("LEFT_SHOULDER", "RIGHT_SHOULDER")):
        idx = [at[p] for p in pair]
        if world_seen[:, idx].all():
            world = world - world[:, idx].mean(1, keepdims=True)
            break
    else:
        raise ValueError(".pose export: the body model gives neither both hips nor both shoulders in every frame; "
                         "POSE_WORLD_LANDMARKS need one of them as origin")
    world = np.where(world_seen[..., None], world, 0.0)

    data = np.concatenate([canvas, world], axis=1)[:, None].astype(np.float32)  # (T, 1 person, K, 3)
    conf = np.concatenate([seen, world_seen], axis=1)[:, None].astype(np.float32)  # (T, 1, K)
    header = PoseHeader(0.2, PoseHeaderDimensions(width, height, 0), holistic_components())
    return Pose(header, NumPyPoseBody(fps=float(fps), data=data, confidence=conf))


def export_pose(path: str | Path, body: BodyModel, params: dict[str, np.ndarray], identity: np.ndarray,
                fps: float, width: int = 1024, height: int = 1024) -> Path:
    """Write ``params`` as a holistic ``.pose`` file on a ``width`` x ``height`` canvas (atomically; an
    identical file is left untouched)."""
    buffer = io.BytesIO()
    holistic_pose(body, params, identity, fps, width, height).write(buffer)
    path = Path(path)
    write_bytes(path, buffer.getvalue())
    return path


REGION_RGB = {"body": (80, 80, 80), "left_hand": (214, 39, 40), "right_hand": (31, 119, 180),
              "face": (44, 160, 44)}  # point colours of a skeleton .pose, by the joint's region


def skeleton_pose(points: np.ndarray, graph: SkeletonGraph, fps: float, width: int = 1024, height: int = 1024):
    """(T, J, 3) metres of ``graph``'s joints (protocol frame) as a ``pose_format.Pose`` of one component (see
    the module docstring)."""
    from pose_format import Pose
    from pose_format.numpy.pose_body import NumPyPoseBody
    from pose_format.pose_header import PoseHeader, PoseHeaderComponent, PoseHeaderDimensions

    if not (0 < width <= 65535 and 0 < height <= 65535):
        raise ValueError(f".pose export: canvas {width} x {height} px; each side must be in 1..65535")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[1:] != (len(graph.joints), 3) or not len(points):
        raise ValueError(f".pose export of skeleton {graph.name!r}: points of shape {points.shape}, expected "
                         f"(T > 0, {len(graph.joints)}, 3)")
    seen = np.isfinite(points).all(-1)  # (T, J)
    placed = np.where(seen[..., None], points, 0.0)
    canvas = np.where(seen[..., None], front_view(placed, seen, np.ones(len(graph.joints), bool), width, height), 0.0)
    colors = [REGION_RGB[j.split(":", 1)[0]] for j in graph.joints]
    component = PoseHeaderComponent(graph.name, list(graph.joints), [tuple(e) for e in graph.edges], colors, "XYZC")
    header = PoseHeader(0.2, PoseHeaderDimensions(width, height, 0), [component])
    return Pose(header, NumPyPoseBody(fps=float(fps), data=canvas[:, None].astype(np.float32),
                                      confidence=seen[:, None].astype(np.float32)))


def export_skeleton_pose(path: str | Path, points: np.ndarray, graph: SkeletonGraph, fps: float,
                         width: int = 1024, height: int = 1024) -> Path:
    """Write (T, J, 3) skeleton joints as a one-component ``.pose`` file (atomically; an identical file is left
    untouched)."""
    buffer = io.BytesIO()
    skeleton_pose(points, graph, fps, width, height).write(buffer)
    path = Path(path)
    write_bytes(path, buffer.getvalue())
    return path
