"""Skeleton graphs of SGSA (m3t.body.skeleton): the coordinate adjacency against hand-written matrices, the body
and holistic layouts, posing on the body model against the metric points, normalisation, holistic name lookup."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from builders import jittered_motion

from m3t.body.metric_sets import BODY_POINTS, HAND_POINTS
from m3t.body.skeleton import (
    FACE_POINTS,
    REGIONS,
    SkeletonGraph,
    adjacency,
    body_graph,
    graph_for,
    holistic_graph,
)
from m3t.body.skeleton_points import (
    body_points,
    denormalise,
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
    from m3t.trackers.posefile import HAND_POINTS as POSE_HAND
    from m3t.trackers.posefile import POSE_POINTS

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


# ------------------------------------------------------------------------------------------------ skeleton graph
def test_skeleton_graph_rejects_malformed_joints_and_edges_naming_them():
    with pytest.raises(ValueError, match=r"skeleton 'bad': joints \['neck'\] are not '<region>:<point>'"):
        SkeletonGraph("bad", ("body:nose", "neck"), ())
    with pytest.raises(ValueError, match=r"joints \['torso:neck'\].*'left_hand'"):
        SkeletonGraph("bad", ("torso:neck", "left_hand:wrist"), ())
    with pytest.raises(ValueError, match=r"skeleton 'dup': duplicate joints \['body:neck', 'body:nose'\]"):
        SkeletonGraph("dup", ("body:nose", "body:neck", "body:nose", "face:4", "body:neck"), ())
    with pytest.raises(ValueError, match=r"edges \[\(0, 3\)\] are not \(i, j\) with 0 <= i < j < 3"):
        SkeletonGraph("far", ("body:neck", "body:nose", "face:4"), ((0, 1), (0, 3)))
    with pytest.raises(ValueError, match="skeleton 'twice': duplicate edges"):
        SkeletonGraph("twice", ("body:neck", "body:nose"), ((0, 1), (0, 1)))
    # Joints may hold further colons after the region; numpy indices become plain int pairs.
    graph = SkeletonGraph("ok", ("body:neck", "face:lip:inner"), (np.array([0, 1], dtype=np.int64),))
    assert graph.edges == ((0, 1),) and type(graph.edges[0][0]) is int
    assert graph.region_index()["face"].tolist() == [1] and graph.index("face:lip:inner") == 1
    with pytest.raises(KeyError, match="skeleton 'ok' has no joint 'body:ear'"):
        graph.index("body:ear")
    with pytest.raises(ValueError, match=r"lacks \['edges'\]"):
        SkeletonGraph.from_dict({"name": "x", "joints": ["body:neck"]})


def test_neck_joint_is_the_models_named_neck_else_the_first_neck_like_joint():
    from types import SimpleNamespace

    from m3t.body.metric_sets import _neck_index

    # The model's own neck joint wins over an earlier neck-like name.
    assert _neck_index(SimpleNamespace(name="anny", joint_names=("root", "neck02", "neck01", "head"))) == 2
    assert _neck_index(SimpleNamespace(name="smplfx", joint_names=("pelvis", "neck_twist", "neck", "head"))) == 2
    # Unknown models, or a known one lacking its neck: the first joint whose name starts with 'neck' (any case).
    assert _neck_index(SimpleNamespace(name="custom", joint_names=("spine", "Neck_1", "neck_2"))) == 1
    assert _neck_index(SimpleNamespace(name="anny", joint_names=("spine", "upper_neck", "NECK03"))) == 2
    with pytest.raises(KeyError, match="body model 'custom' has no neck joint; add it to NECK_JOINT"):
        _neck_index(SimpleNamespace(name="custom", joint_names=("spine", "head", "upper_neck")))


def _holistic_body(names, kind, index, name="smplfx", joints=("pelvis", "neck", "head")):
    """A stand-in body model whose MediaPipe-Holistic correspondence is the given table."""
    from types import SimpleNamespace

    from m3t.body.protocol import Correspondence

    corr = Correspondence(tuple(names), np.array(kind, dtype=np.int64), np.array(index, dtype=np.int64))
    sets = {"mediapipe_holistic": corr}
    return SimpleNamespace(name=name, joint_names=joints, correspondence=lambda landmark_set: sets[landmark_set])


def test_graph_correspondence_maps_body_joints_to_pose_landmarks_and_the_neck_to_the_neck_joint():
    from m3t.body.skeleton_points import graph_correspondence

    body = _holistic_body(
        ["pose:nose", "pose:left_ear", "pose:mouth:left", "pose:left", "left_hand:wrist", "face:61"],
        [0, 1, 0, 0, 0, -1], [10, 2, 20, 30, 40, 0])
    graph = SkeletonGraph("g", ("body:neck", "body:nose", "body:mouth:left", "left_hand:wrist", "body:left_ear"),
                          ((0, 1), (1, 2)))
    corr = graph_correspondence(body, graph)
    assert corr.names == graph.joints
    assert corr.kind.tolist() == [1, 0, 0, 0, 1] and corr.index.tolist() == [1, 10, 20, 40, 2]
    assert corr.kind.dtype == np.int64 and corr.index.dtype == np.int64  # indices, as every Correspondence
    with pytest.raises(ValueError, match=r"skeleton 'chin' on body model 'smplfx': landmarks \['pose:chin'\] are "
                                         r"not in the correspondence"):
        graph_correspondence(body, SkeletonGraph("chin", ("body:neck", "body:chin"), ()))
    with pytest.raises(ValueError, match=r"body model 'smplfx' has no point for joints \['face:61'\] of skeleton "
                                         r"'lips'"):
        graph_correspondence(body, SkeletonGraph("lips", ("body:nose", "face:61"), ()))


def test_skeleton_graph_rejects_an_edge_from_a_joint_to_itself():
    with pytest.raises(ValueError, match=r"skeleton 'loop': edges \[\(1, 1\)\] are not \(i, j\) with 0 <= i < j < 3"):
        SkeletonGraph("loop", ("body:neck", "body:nose", "face:4"), ((0, 1), (1, 1)))


def test_holistic_points_reject_an_array_whose_point_count_differs_from_the_names():
    from m3t.body.skeleton_points import holistic_points

    graph = SkeletonGraph("g", ("body:nose",), ())
    names = ["pose:nose", "pose:left_eye"]
    with pytest.raises(ValueError, match=r"expected \(T, 2, 3\) for 2 names, got \(4, 3, 3\)"):
        holistic_points(np.zeros((4, 3, 3)), names, graph)
    with pytest.raises(ValueError, match=r"expected \(T, 2, 3\) for 2 names, got \(4, 2, 2\)"):
        holistic_points(np.zeros((4, 2, 2)), names, graph)
    with pytest.raises(ValueError, match=r"got \(2, 3\)"):
        holistic_points(np.zeros((2, 3)), names, graph)
    points = np.arange(24, dtype=float).reshape(4, 2, 3)
    np.testing.assert_array_equal(holistic_points(points, names, graph), points[:, :1])


def test_metric_joints_are_the_rotation_streams_bones_as_integer_joint_entries(fx):
    """The metric skeleton: one joint entry per bone a rotation stream drives (body, then hands), in stream order;
    ``joints_for`` poses exactly those joints."""
    from m3t.body.metric_sets import joints_for, metric_joints

    corr = metric_joints(fx)
    names = [label for m in fx.layout.modalities if m.kind == "rotation6d" for label in m.labels]
    assert corr.names == tuple(names) and len(names) == 10 + 15 + 15
    assert corr.kind.dtype.kind == "i" and corr.index.dtype.kind == "i", "Correspondence holds integer arrays"
    assert (corr.kind == 1).all() and corr.valid.all()
    assert corr.index.tolist() == [fx.joint_names.index(n) for n in names]
    params = {k: v.numpy() for k, v in fx.rest_params(2).items()}
    params["body"] = params["body"] + 0.1 * np.random.default_rng(0).normal(size=params["body"].shape)
    got = joints_for(fx, params, np.zeros(fx.layout.identity_dim, dtype=np.float32))
    dense = fx.forward({k: torch.as_tensor(v, dtype=torch.float32) for k, v in params.items()},
                       fx.default_identity()).joints[:, corr.index]
    torch.testing.assert_close(got, dense, atol=1e-5, rtol=0)
