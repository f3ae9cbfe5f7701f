"""Skeleton graphs of SGSA (m3t.body.skeleton): the coordinate adjacency against hand-written matrices, the body
and holistic layouts, posing on the body model against the metric points, normalisation, holistic name lookup."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from m3t.body.metric_sets import BODY_POINTS, HAND_POINTS
from m3t.body.skeleton import (
    FACE_POINTS,
    REGIONS,
    SkeletonGraph,
    adjacency,
    body_graph,
    body_points,
    denormalise,
    graph_for,
    holistic_graph,
    holistic_points,
    normalise,
    regions,
)

TOY = SkeletonGraph("toy", ("body:neck", "body:left_shoulder", "body:right_shoulder"), ((0, 1), (1, 2)))


def test_toy_adjacency_with_counter_is_the_hand_written_matrix():
    # A: joint 0 <-> joint 1 <-> joint 2 on every coordinate pair, counter (index 9) <-> every coordinate.
    # Degrees in A: joint 0 and 2 coordinates 3 (limb) + 1 (counter) = 4, joint 1 coordinates 6 + 1 = 7, the
    # counter 9. A* = D^-1 A + I*: own-joint 3x3 blocks of ones, the counter's self-loop 1.
    q, s, n = 1 / 4, 1 / 7, 1 / 9
    expected = np.array([
        [1, 1, 1, q, q, q, 0, 0, 0, q],
        [1, 1, 1, q, q, q, 0, 0, 0, q],
        [1, 1, 1, q, q, q, 0, 0, 0, q],
        [s, s, s, 1, 1, 1, s, s, s, s],
        [s, s, s, 1, 1, 1, s, s, s, s],
        [s, s, s, 1, 1, 1, s, s, s, s],
        [0, 0, 0, q, q, q, 1, 1, 1, q],
        [0, 0, 0, q, q, q, 1, 1, 1, q],
        [0, 0, 0, q, q, q, 1, 1, 1, q],
        [n, n, n, n, n, n, n, n, n, 1],
    ])
    got = adjacency(TOY)
    assert got.shape == (10, 10) and got.dtype == np.float32
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-7)


def test_toy_adjacency_without_counter_is_the_hand_written_matrix():
    # Degrees: ends 3, middle joint 6.
    t, h = 1 / 3, 1 / 6
    expected = np.array([
        [1, 1, 1, t, t, t, 0, 0, 0],
        [1, 1, 1, t, t, t, 0, 0, 0],
        [1, 1, 1, t, t, t, 0, 0, 0],
        [h, h, h, 1, 1, 1, h, h, h],
        [h, h, h, 1, 1, 1, h, h, h],
        [h, h, h, 1, 1, 1, h, h, h],
        [0, 0, 0, t, t, t, 1, 1, 1],
        [0, 0, 0, t, t, t, 1, 1, 1],
        [0, 0, 0, t, t, t, 1, 1, 1],
    ])
    np.testing.assert_allclose(adjacency(TOY, counter=False), expected, rtol=0, atol=1e-7)


def test_isolated_joint_keeps_only_its_self_loops():
    graph = SkeletonGraph("two", ("body:neck", "body:nose"), ())
    np.testing.assert_array_equal(adjacency(graph, counter=False), np.kron(np.eye(2), np.ones((3, 3))))


def _components(graph: SkeletonGraph) -> int:
    parent = list(range(len(graph.joints)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for i, j in graph.edges:
        parent[root(i)] = root(j)
    return len({root(i) for i in range(len(graph.joints))})


def _check_layout(graph: SkeletonGraph, body_joints: int, face: bool) -> None:
    index = graph.region_index()
    assert tuple(index) == (REGIONS if face else REGIONS[:3])
    assert len(index["body"]) == body_joints and graph.joints[index["body"][0]] == "body:neck"
    for side in ("left_hand", "right_hand"):
        assert [graph.joints[i] for i in index[side]] == [f"{side}:{p}" for p in HAND_POINTS]
    if face:
        assert [graph.joints[i] for i in index["face"]] == [f"face:{p}" for p, _ in FACE_POINTS]
    assert np.array_equal(np.concatenate(list(index.values())), np.arange(len(graph.joints)))
    assert all(0 <= i < j < len(graph.joints) for i, j in graph.edges)
    assert len(set(graph.edges)) == len(graph.edges)
    assert _components(graph) == 1
    assert graph.coordinate_names()[:4] == ("body:neck.x", "body:neck.y", "body:neck.z", f"{graph.joints[1]}.x")
    a = adjacency(graph)
    assert a.shape == (graph.width + 1, graph.width + 1)
    assert np.array_equal(a > 0, (a > 0).T)  # undirected support
    np.testing.assert_allclose(np.diag(a), 1.0)


@pytest.mark.parametrize("face", [False, True])
def test_body_graph_layout(face):
    graph = body_graph(face)
    assert graph.name == ("body+face" if face else "body")
    joints = 54 + (len(FACE_POINTS) if face else 0)
    assert len(graph.joints) == joints and graph.width == 3 * joints
    assert graph.joints[:12] == tuple(f"body:{p}" for p in BODY_POINTS)
    _check_layout(graph, 12, face)
    edges = {(graph.joints[i], graph.joints[j]) for i, j in graph.edges}
    assert ("body:left_wrist", "left_hand:wrist") in edges and ("body:neck", "body:nose") in edges
    assert len(graph.edges) == 11 + 2 + 2 * 21 + (29 if face else 0)
    assert graph_for("body", face) == graph


@pytest.mark.parametrize("face", [False, True])
def test_holistic_graph_layout(face):
    graph = holistic_graph(face)
    assert graph.name == ("holistic+face" if face else "holistic")
    joints = 18 + 42 + (len(FACE_POINTS) if face else 0)
    assert len(graph.joints) == joints and graph.width == 3 * joints
    assert graph.joints[:3] == ("body:neck", "body:nose", "body:left_eye_inner")
    _check_layout(graph, 18, face)
    edges = {(graph.joints[i], graph.joints[j]) for i, j in graph.edges}
    assert ("body:left_elbow", "body:left_wrist") in edges and ("body:left_shoulder", "body:right_shoulder") in edges
    assert graph_for("holistic", face) == graph
    with pytest.raises(ValueError, match="unknown skeleton"):
        graph_for("openpose")


def test_graph_round_trips_through_a_dict():
    for graph in (TOY, body_graph(True), holistic_graph()):
        assert SkeletonGraph.from_dict(graph.to_dict()) == graph
    with pytest.raises(ValueError, match="edges"):
        SkeletonGraph("bad", TOY.joints, ((1, 0),))
    with pytest.raises(ValueError, match="region"):
        SkeletonGraph("bad", ("torso:neck",), ())


def jittered_motion(body, frames: int = 3, seed: int = 0) -> dict[str, np.ndarray]:
    """Rest pose plus small random rotations / facial actions (within bounds), ``frames`` frames."""
    rng = np.random.default_rng(seed)
    rest = {k: v.numpy().astype(np.float64) for k, v in body.rest_params(frames).items()}
    out = {}
    for m in body.layout.modalities:
        noise = rng.normal(0.0, 0.05, rest[m.name].shape)
        value = rest[m.name] + (np.abs(noise) if m.kind == "scalar" else noise)
        out[m.name] = np.clip(value, *m.bounds) if m.bounds is not None else value
    return out


def test_body_points_are_the_scored_metric_points(body):
    from m3t.metrics.scorer import MotionScorer

    params, identity = jittered_motion(body), body.default_identity().numpy()
    graph = body_graph(face_points=True)
    points = body_points(body, params, identity, graph)
    assert points.shape == (3, len(graph.joints), 3) and points.dtype == np.float64 and np.isfinite(points).all()
    scored = MotionScorer(body).points(params, identity)
    got = regions(points, graph)
    assert list(got) == list(REGIONS)
    for region in ("body", "left_hand", "right_hand"):
        np.testing.assert_allclose(got[region], scored[region], rtol=0, atol=1e-6)
    # Face points: the holistic correspondence's, as the .pose export poses them.
    from m3t.render.posefile import holistic_points as pose_points

    holistic, _, names = pose_points(body, params, identity)
    position = {n: i for i, n in enumerate(names)}
    np.testing.assert_allclose(got["face"], holistic[:, [position[f"face:{p}"] for p, _ in FACE_POINTS]], atol=1e-6)
    assert got["face"][0, [p for p, _ in FACE_POINTS].index("61"), 0] < 0  # right mouth corner on the right (-x)


def test_face_subset_exists_on_smplfx_too(fx):
    """The face points are iBUG-68 landmarks, the only face points SMPL-FX's correspondence has."""
    from m3t.metrics.scorer import MotionScorer

    params, identity = jittered_motion(fx, frames=2), fx.default_identity().numpy()
    graph = body_graph(face_points=True)
    got = regions(body_points(fx, params, identity, graph), graph)
    assert all(np.isfinite(v).all() for v in got.values())
    scored = MotionScorer(fx).points(params, identity)
    for region in ("body", "left_hand", "right_hand"):
        np.testing.assert_allclose(got[region], scored[region], rtol=0, atol=1e-6)


def test_normalise_round_trip_scale_and_invariance():
    graph = body_graph()
    rng = np.random.default_rng(1)
    points = rng.normal(0.0, 0.2, (4, len(graph.joints), 3)) + np.array([0.3, -1.0, 1.4])
    left, right = graph.joints.index("body:left_shoulder"), graph.joints.index("body:right_shoulder")
    points[:, left] = points[:, 0] + [0.2, 0.0, 0.0]
    points[:, right] = points[:, 0] - np.outer(0.15 + 0.05 * np.arange(4), [1.0, 0.0, 0.0])  # widths vary
    coords, scale = normalise(points, graph)
    widths = np.linalg.norm(points[:, left] - points[:, right], axis=-1)
    assert coords.shape == (4, graph.width) and coords.dtype == np.float32
    assert scale == pytest.approx(widths.mean())
    np.testing.assert_allclose(coords[:, :3], 0.0, atol=1e-7)  # neck at the origin
    back = denormalise(coords, graph, scale)
    np.testing.assert_allclose(back, points - points[:, :1], atol=1e-6)
    doubled, scale2 = normalise(points * 2.0, graph)
    assert scale2 == pytest.approx(2 * scale)
    np.testing.assert_allclose(doubled, coords, atol=1e-6)
    flat = points.copy()
    flat[:, right] = flat[:, left]
    with pytest.raises(ValueError, match="degenerate"):
        normalise(flat, graph)
    flat[:, right] = np.nan
    with pytest.raises(ValueError, match="degenerate"):
        normalise(flat, graph)


def test_holistic_points_from_names():
    from m3t.trackers.posefile import HAND_POINTS as POSE_HAND, POSE_POINTS

    graph = holistic_graph(face_points=True)
    names = [f"POSE_LANDMARKS:{p}" for p in POSE_POINTS]
    names += [f"{part}:{p}" for part in ("LEFT_HAND_LANDMARKS", "RIGHT_HAND_LANDMARKS") for p in POSE_HAND]
    names += [f"face:{i}" for i in range(468)]
    rng = np.random.default_rng(2)
    points = rng.normal(size=(2, len(names), 3))
    out = holistic_points(points, names, graph)
    assert out.shape == (2, len(graph.joints), 3)
    at = {n: i for i, n in enumerate(names)}
    np.testing.assert_allclose(out[:, 0], (points[:, at["POSE_LANDMARKS:LEFT_SHOULDER"]]
                                           + points[:, at["POSE_LANDMARKS:RIGHT_SHOULDER"]]) / 2)
    np.testing.assert_array_equal(out[:, graph.joints.index("body:right_wrist")],
                                  points[:, at["POSE_LANDMARKS:RIGHT_WRIST"]])
    np.testing.assert_array_equal(out[:, graph.joints.index("right_hand:pinky_tip")],
                                  points[:, at["RIGHT_HAND_LANDMARKS:PINKY_TIP"]])
    np.testing.assert_array_equal(out[:, graph.joints.index("face:291")], points[:, at["face:291"]])
    # The render export's lower-case names give the same points.
    lower = [n.replace("POSE_LANDMARKS", "pose").replace("LEFT_HAND_LANDMARKS", "left_hand")
             .replace("RIGHT_HAND_LANDMARKS", "right_hand").lower() for n in names]
    np.testing.assert_array_equal(holistic_points(points, lower, graph), out)
    keep = [k for k, n in enumerate(names) if n not in ("POSE_LANDMARKS:LEFT_ELBOW", "face:61")]
    with pytest.raises(ValueError, match=r"face:61.*pose:left_elbow"):
        holistic_points(points[:, keep], [names[k] for k in keep], graph)


def test_regions_split_in_graph_order():
    graph = body_graph()
    points = torch.arange(len(graph.joints) * 3, dtype=torch.float64).reshape(1, -1, 3).numpy()
    parts = regions(points, graph)
    assert {k: v.shape for k, v in parts.items()} == {"body": (1, 12, 3), "left_hand": (1, 21, 3),
                                                       "right_hand": (1, 21, 3)}
    np.testing.assert_array_equal(parts["left_hand"][0, 0], points[0, 12])
