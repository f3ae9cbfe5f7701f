"""The ``.pose`` export is a MediaPipe-Holistic file that pose-format's own tools and the project's reader use.

Reference layout: pose-format 0.15's ``pose_format.utils.holistic.holistic_components()`` (what its
``load_holistic`` writes) and the real files shipped in the spoken-to-signed 0.4.0 wheel, e.g.
``assets/fingerspelling_lexicon/ase/fs-sts13206cebad70790ee136a34c7a74af5e.pose``: version 0.2, 500 x 500 x 0,
components POSE_LANDMARKS 33 (NOSE, LEFT_EYE_INNER, ...; limbs (15, 21), (16, 20), ...; colour (255, 0, 0)),
FACE_LANDMARKS 478 ("0", "1", ...; 2564 limbs = 2556 mesh + 8 iris), LEFT_HAND_LANDMARKS 21 and
RIGHT_HAND_LANDMARKS 21 (WRIST, THUMB_CMC, ...), POSE_WORLD_LANDMARKS 33, all XYZC; body 24 frames x 1 person
x 586 points x 3, float32, 25 fps. The export writes the unrefined face (468 points, pose-format's default).
"""
from __future__ import annotations

import copy
import os
import stat
from contextlib import contextmanager

import numpy as np
import pytest
from builders import jittered_motion

from m3t.atomic import atomic_path, copy_file, write_bytes
from m3t.render.posefile import export_pose, front_view, holistic_points

WIDTH, HEIGHT, FPS = 640, 480, 25.0
COUNTS = [("POSE_LANDMARKS", 33), ("FACE_LANDMARKS", 468), ("LEFT_HAND_LANDMARKS", 21),
          ("RIGHT_HAND_LANDMARKS", 21), ("POSE_WORLD_LANDMARKS", 33)]


@contextmanager
def umask(mask: int):
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


@pytest.fixture(scope="module")
def exported(body, tmp_path_factory):
    """(path, metres (T, K, 3), validity (K,), names) of a 3-frame Anny clip exported on a 640 x 480 canvas."""
    params, identity = jittered_motion(body), body.default_identity().numpy()
    path = tmp_path_factory.mktemp("pose") / "clip.pose"
    with umask(0o022):
        export_pose(path, body, params, identity, FPS, width=WIDTH, height=HEIGHT)
    points, valid, names = holistic_points(body, params, identity)
    return path, points, valid, names


def _read(path):
    from pose_format import Pose

    return Pose.read(path.read_bytes())


def _real_file():
    from m3t.corpora.fingerspelling import lexicon_root

    return sorted(lexicon_root().glob("*/*.pose"))[0]


def _index(header, component: str, point: str) -> int:
    return header.get_point_index(component, point)


def test_header_is_pose_formats_holistic_header(exported):
    path = exported[0]
    header = _read(path).header
    assert [(c.name, len(c.points)) for c in header.components] == COUNTS
    assert (header.dimensions.width, header.dimensions.height, header.dimensions.depth) == (WIDTH, HEIGHT, 0)
    assert round(header.version, 3) == 0.2
    # The real shipped file: same names and limbs (its face has 10 iris points more).
    real = _read(_real_file()).header
    for ours, theirs in zip(header.components, real.components):
        n = len(ours.points)
        assert (ours.name, ours.format) == (theirs.name, theirs.format)
        assert ours.points == theirs.points[:n]
        assert ours.limbs == [(a, b) for a, b in theirs.limbs if a < n and b < n]
        assert len(ours.limbs) == {33: 35, 468: 2556, 21: 21}[n]
    # pose-format's own header (it imports mediapipe, an optional install).
    pytest.importorskip("mediapipe")
    from pose_format.utils.holistic import holistic_components

    for ours, theirs in zip(header.components, holistic_components()):
        assert (ours.name, ours.points, ours.limbs, ours.format) == \
            (theirs.name, theirs.points, theirs.limbs, theirs.format)
        np.testing.assert_array_equal(np.asarray(ours.colors), np.asarray(theirs.colors))


def test_front_view_one_camera_per_clip():
    """x = X, y = -Z, z = Y; one scale for the clip; the fitted points fill the canvas up to the margin."""
    points = np.array([[[0.0, 0.0, 0.0], [0.4, 0.1, 0.2], [9.0, 9.0, 9.0]],
                       [[0.2, 0.0, 0.0], [0.6, -0.1, 0.3], [9.0, 9.0, 9.0]]])  # (T=2, K=3, 3) metres, Z up
    seen = np.array([[True, True, True], [True, True, False]])
    fit = np.array([True, True, False])  # point 2 (e.g. a leg) is not fitted
    got = front_view(points, seen, fit, 1000, 500, margin=0.1)
    # Fitted box: X 0..0.6, Z 0..0.3, depth Y -0.1..0.1; scale min(800 / 0.6, 400 / 0.3) = 1333.3 px/m.
    s = 800 / 0.6
    np.testing.assert_allclose(got[0, 0], [500 - 0.3 * s, 250 + 0.15 * s, 0.0])
    np.testing.assert_allclose(got[1, 1], [500 + 0.3 * s, 250 - 0.15 * s, -0.1 * s])
    np.testing.assert_allclose(got[1, 0] - got[0, 0], [0.2 * s, 0.0, 0.0])  # same scale in every frame
    fitted = got[seen & fit[None]]
    assert fitted[:, 0].min() == pytest.approx(100) and fitted[:, 0].max() == pytest.approx(900)
    with pytest.raises(ValueError, match="no valid point"):
        front_view(points, np.zeros_like(seen), fit, 1000, 500)


def test_coordinates_on_the_canvas_and_world_in_metres(exported):
    path, metres, valid, names = exported
    pose = _read(path)
    header, data = pose.header, np.ma.getdata(pose.body.data)[:, 0]  # (T, K, 3)
    conf = pose.body.confidence[:, 0]
    at = {n: i for i, n in enumerate(names)}
    lsh, rsh = (_index(header, "POSE_LANDMARKS", p) for p in ("LEFT_SHOULDER", "RIGHT_SHOULDER"))
    nose, hip = _index(header, "POSE_LANDMARKS", "NOSE"), _index(header, "POSE_LANDMARKS", "LEFT_HIP")
    assert (data[:, lsh, 0] > data[:, rsh, 0]).all()  # the subject's left on the image's right
    assert (data[:, nose, 1] < data[:, lsh, 1]).all() and (data[:, lsh, 1] < data[:, hip, 1]).all()  # y down
    # Pixels and depth share one scale: the 3D shoulder distance is the metric one times a constant.
    scale = np.linalg.norm(data[:, lsh] - data[:, rsh], axis=-1) / np.linalg.norm(
        metres[:, at["pose:left_shoulder"]] - metres[:, at["pose:right_shoulder"]], axis=-1)
    np.testing.assert_allclose(scale, scale[0], rtol=1e-5)
    wrist = _index(header, "RIGHT_HAND_LANDMARKS", "WRIST")
    np.testing.assert_allclose(np.linalg.norm(data[:, wrist] - data[:, lsh], axis=-1) / scale[0], np.linalg.norm(
        metres[:, at["right_hand:wrist"]] - metres[:, at["pose:left_shoulder"]], axis=-1), rtol=1e-5)
    # Everything but the legs lies on the canvas.
    upper = conf > 0
    for leg in ("KNEE", "ANKLE", "HEEL", "FOOT_INDEX"):
        for side in ("LEFT", "RIGHT"):
            upper[:, _index(header, "POSE_LANDMARKS", f"{side}_{leg}")] = False
    upper[:, -33:] = False
    xy = data[upper][:, :2]
    assert (xy >= 0).all() and (xy[:, 0] <= WIDTH).all() and (xy[:, 1] <= HEIGHT).all()
    assert np.ptp(xy[:, 0]) > 0.7 * WIDTH or np.ptp(xy[:, 1]) > 0.7 * HEIGHT  # the signer fills the canvas
    # World landmarks: metres, MediaPipe's axes, origin between the hips.
    world = data[:, -33:]
    hips = [_index(header, "POSE_WORLD_LANDMARKS", p) - (data.shape[1] - 33) for p in ("LEFT_HIP", "RIGHT_HIP")]
    np.testing.assert_allclose(world[:, hips].mean(1), 0.0, atol=1e-6)
    m = metres - (metres[:, [at["pose:left_hip"]]] + metres[:, [at["pose:right_hip"]]]) / 2
    np.testing.assert_allclose(world[:, 0], np.stack([m[:, 0, 0], -m[:, 0, 2], m[:, 0, 1]], -1), atol=1e-6)
    # Points without a correspondence: confidence 0, coordinates 0.
    missing = [i for i, n in enumerate(names) if not valid[i]]
    assert missing, "the fixture should have a point without correspondence"
    for i in missing:
        part, point = names[i].split(":")
        k = _index(header, {"pose": "POSE_LANDMARKS", "face": "FACE_LANDMARKS"}.get(part, part), point.upper())
        assert (conf[:, k] == 0).all() and (data[:, k] == 0).all()
    assert (conf[:, [i for i in range(data.shape[1]) if conf[0, i] > 0]] == 1).all()


def test_pose_format_tools_work(exported):
    from pose_format.utils.generic import (
        correct_wrists,
        hands_indexes,
        pose_hide_legs,
        reduce_holistic,
    )

    path = exported[0]
    pose = _read(path)
    header = pose.header

    normalized = copy.deepcopy(pose).normalize()
    data = normalized.body.data[:, 0]
    assert np.isfinite(np.ma.getdata(data)[~np.ma.getmaskarray(data)]).all()
    lsh, rsh = (_index(header, "POSE_LANDMARKS", p) for p in ("LEFT_SHOULDER", "RIGHT_SHOULDER"))
    assert np.linalg.norm(data[:, lsh] - data[:, rsh], axis=-1).mean() == pytest.approx(1.0, rel=1e-5)

    left, right = hands_indexes(header)
    assert (left, right) == (_index(header, "LEFT_HAND_LANDMARKS", "MIDDLE_FINGER_MCP"),
                             _index(header, "RIGHT_HAND_LANDMARKS", "MIDDLE_FINGER_MCP"))
    assert (pose.body.confidence[:, 0, [left, right]] == 1).all()

    shifted = copy.deepcopy(pose)  # a body wrist that disagrees with the hand's: correct_wrists repairs it
    body_wrist = _index(header, "POSE_LANDMARKS", "LEFT_WRIST")
    shifted.body.data[:, :, body_wrist] += 25.0
    fixed = correct_wrists(shifted)
    hand_wrist = _index(header, "LEFT_HAND_LANDMARKS", "WRIST")
    np.testing.assert_allclose(fixed.body.data[:, 0, body_wrist], pose.body.data[:, 0, hand_wrist])

    legs = [_index(header, c, f"{s}_{p}") for c in ("POSE_LANDMARKS", "POSE_WORLD_LANDMARKS")
            for s in ("LEFT", "RIGHT") for p in ("KNEE", "ANKLE", "HEEL", "FOOT_INDEX", "HIP")]
    assert (pose.body.confidence[:, 0, legs] > 0).all()
    hidden = pose_hide_legs(copy.deepcopy(pose))
    assert (hidden.body.confidence[:, 0, legs] == 0).all()

    reduced = reduce_holistic(copy.deepcopy(pose))
    assert [(c.name, len(c.points)) for c in reduced.header.components] == [
        ("POSE_LANDMARKS", 8), ("FACE_LANDMARKS", 128), ("LEFT_HAND_LANDMARKS", 21), ("RIGHT_HAND_LANDMARKS", 21)]


def test_pose_visualizer_draws_the_signer(exported):
    from pose_format.pose_visualizer import PoseVisualizer

    pose = _read(exported[0])
    frames = list(PoseVisualizer(pose).draw())
    assert len(frames) == 3 and all(f.shape == (HEIGHT, WIDTH, 3) for f in frames)
    inked = (frames[0] != 255).any(-1)  # (H, W) non-background pixels
    assert inked.mean() > 0.01
    cols, rows = np.flatnonzero(inked[HEIGHT // 8:].any(0)), np.flatnonzero(inked.any(1))
    assert cols.max() - cols.min() > WIDTH / 2 and rows.max() - rows.min() > HEIGHT / 2


def test_round_trip_through_the_project_reader_and_tracks(exported):
    from m3t.corpora.posefile import read_pose, read_pose_info
    from m3t.trackers.posefile import pose_to_track
    from m3t.trackers.track import landmark_slices

    path, metres, valid, names = exported
    info = read_pose_info(path)
    assert (info.fps, info.frames, info.people, info.width, info.height) == (FPS, 3, 1, WIDTH, HEIGHT)
    assert list(info.components) == COUNTS
    data = read_pose(path)
    written = np.ma.getdata(_read(path).body.data)[:, 0]
    np.testing.assert_array_equal(data.points, written)
    assert data.point_names[0][:2] == ("NOSE", "LEFT_EYE_INNER") and data.dims == 3

    out = pose_to_track(_read(path), source=str(path))
    track = out.track
    assert track.image_size == (WIDTH, HEIGHT) and track.fps == FPS and track.keypoints.shape == (3, 543, 2)
    # The track's landmarks are the correspondence's (pose, left hand, right hand, face), matched by name.
    parts = landmark_slices("mediapipe_holistic")
    assert all(names[k].startswith(f"{part}:") for part, sl in parts.items() for k in range(sl.start, sl.stop))
    first = dict(zip([c for c, _ in COUNTS], np.cumsum([0] + [n for _, n in COUNTS])))
    for part, component in (("pose", "POSE_LANDMARKS"), ("left_hand", "LEFT_HAND_LANDMARKS"),
                            ("right_hand", "RIGHT_HAND_LANDMARKS"), ("face", "FACE_LANDMARKS")):
        block = written[:, first[component]: first[component] + parts[part].stop - parts[part].start]
        got = track.keypoints[:, parts[part]]
        seen = track.confidence[:, parts[part]] > 0
        np.testing.assert_array_equal(got[seen], block[..., :2][seen])
        np.testing.assert_array_equal(track.extras["depth"][:, parts[part]][seen], block[..., 2][seen])
        assert np.isnan(got[~seen]).all()
    np.testing.assert_array_equal(track.confidence > 0, np.broadcast_to(valid, (3, len(valid))))
    at = {n: i for i, n in enumerate(names)}
    shoulders = metres[:, at["pose:left_shoulder"]] - metres[:, at["pose:right_shoulder"]]
    np.testing.assert_allclose(np.linalg.norm(out.pose_world[:, 11] - out.pose_world[:, 12], axis=-1),
                               np.linalg.norm(shoulders, axis=-1), rtol=1e-5)


def test_export_file_mode_and_unchanged_rewrite(exported, body):
    path = exported[0]
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    before = path.stat().st_mtime_ns
    params, identity = jittered_motion(body), body.default_identity().numpy()
    export_pose(path, body, params, identity, FPS, width=WIDTH, height=HEIGHT)
    assert path.stat().st_mtime_ns == before  # identical bytes: left alone (DVC sees no change)


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_atomic_outputs_get_the_mode_open_gives(tmp_path, mask, mode):
    source = tmp_path / "source.bin"
    source.write_bytes(b"x")
    with umask(mask):
        plain = tmp_path / "plain.bin"
        with open(plain, "wb") as fh:
            fh.write(b"x")
        write_bytes(tmp_path / "a.bin", b"abc")
        with atomic_path(tmp_path / "b.npz", suffix=".npz") as tmp:
            np.savez(tmp, x=np.zeros(1))
        copy_file(source, tmp_path / "c.bin")
        old = tmp_path / "d.bin"
        old.write_bytes(b"old")
        old.chmod(0o600)  # an output of the previous writer
        write_bytes(old, b"new")
    assert stat.S_IMODE(plain.stat().st_mode) == mode
    for name in ("a.bin", "b.npz", "c.bin", "d.bin"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == mode, name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.npz", "c.bin", "d.bin", "plain.bin",
                                                          "source.bin"]  # no temporary file left behind


def test_smplfx_export_without_hips(fx, tmp_path):
    """SMPL-FX has no leg joints and 51 face points: world landmarks centre on the shoulders, the rest is masked."""
    from pose_format.utils.generic import pose_hide_legs

    params, identity = jittered_motion(fx, frames=2), fx.default_identity().numpy()
    path = export_pose(tmp_path / "fx.pose", fx, params, identity, FPS)
    pose = _read(path)
    header, conf = pose.header, pose.body.confidence[:, 0]
    world = np.ma.getdata(pose.body.data)[:, 0, -33:]
    np.testing.assert_allclose(world[:, [11, 12]].mean(1), 0.0, atol=1e-6)
    _, valid, names = holistic_points(fx, params, identity)
    face = [i for i, n in enumerate(names) if n.startswith("face:")]
    assert (conf[:, 33:33 + 468] > 0).sum(1).tolist() == [int(valid[face].sum())] * 2 and 0 < valid[face].sum() < 468
    assert (conf[:, _index(header, "POSE_LANDMARKS", "LEFT_KNEE")] == 0).all()
    assert (header.dimensions.width, header.dimensions.height) == (1024, 1024)
    pose_hide_legs(pose)  # legs already missing: still fine


# ---- the holistic export by hand: a stub body whose MediaPipe points are its parameters
NAMES = ("pose:left_shoulder", "pose:left_eye", "pose:right_shoulder", "pose:left_hip", "pose:right_hip", "pose:nose",
         "pose:left_knee", "left_hand:wrist", "face:1")
KIND = np.array([1, -1, 1, 1, 1, 0, 1, 1, 0])  # the left eye has no correspondence
# header index of each name: POSE_LANDMARKS 0..32, FACE_LANDMARKS 33.., LEFT_HAND_LANDMARKS 501.., world 543..
HEADER = [11, 2, 12, 23, 24, 0, 25, 501, 34]


class _HolisticStub:
    """A body model whose holistic keypoints are ``params["points"]`` (T, 9, 3), named :data:`NAMES`."""

    def __init__(self, names=NAMES, kind=KIND):
        self.names, self.kind = names, kind

    def correspondence(self, name):
        from m3t.body.protocol import Correspondence

        assert name == "mediapipe_holistic"
        return Correspondence(self.names, self.kind, np.arange(len(self.names)))

    def keypoint_set(self, correspondence):
        return correspondence

    def forward_keypoints(self, params, identity, kp):
        import torch

        assert identity.dtype == torch.float32
        return params["points"]


def _stub_points() -> np.ndarray:
    """(2, 9, 3) metres, protocol frame (X the subject's left, Y away, Z up); frame 1 is frame 0 moved 25 cm to
    the subject's left, its face point lost."""
    frame = np.array([[0.25, 0.0, 1.5], [9.0, 9.0, 9.0], [-0.25, 0.0, 1.5], [0.125, 0.0, 1.0], [-0.125, 0.0, 1.0],
                      [0.0, -0.125, 1.75], [0.125, 0.0, 0.5], [0.5, -0.25, 1.25], [0.0, -0.125, 1.625]])
    points = np.stack([frame, frame + [0.25, 0.0, 0.0]])
    points[1, 8] = np.nan
    return points


def test_holistic_pose_places_every_point_by_hand():
    """The fitted box (legs and points without correspondence aside) is x -0.25 .. 0.75, y = -Z -1.75 .. -1.0,
    z = Y -0.25 .. 0 over both frames: on 200 x 100 px with 8 % margins the scale is min(168 / 1.0, 84 / 0.75) =
    112 px/m, centred on (0.25, -1.375, -0.125). World landmarks: metres, origin between the hips per frame."""
    from m3t.render.posefile import holistic_pose

    points = _stub_points()
    pose = holistic_pose(_HolisticStub(), {"points": points}, np.zeros(3), fps=12.5, width=200, height=100)
    assert [(c.name, len(c.points), c.format) for c in pose.header.components] == [(n, k, "XYZC") for n, k in COUNTS]
    dims = pose.header.dimensions
    assert (dims.width, dims.height, dims.depth) == (200, 100, 0) and round(pose.header.version, 3) == 0.2
    assert pose.body.fps == 12.5 and isinstance(pose.body.fps, float)
    data, conf = np.ma.getdata(pose.body.data), np.asarray(pose.body.confidence)
    assert data.shape == (2, 1, 576, 3) and data.dtype == np.float32 and conf.shape == (2, 1, 576)
    assert conf.dtype == np.float32
    data, conf = data[:, 0], conf[:, 0]
    seen = np.zeros((2, 576), bool)
    for k, name in zip(HEADER, NAMES):
        if name != "pose:left_eye":
            seen[:, k] = True
    seen[1, 34] = False  # the face point lost in frame 1
    seen[:, 543:] = seen[:, :33]  # world landmarks: the pose points
    np.testing.assert_array_equal(conf, seen.astype(np.float32))
    assert (data[~seen] == 0).all()  # unseen: coordinates 0
    for t in range(2):
        for k, (x, y, z) in zip(HEADER, points[t]):
            if seen[t, k]:  # float32 output
                np.testing.assert_allclose(data[t, k], [(x - 0.25) * 112 + 100, (1.375 - z) * 112 + 50,
                                                        (y + 0.125) * 112], rtol=1e-6, atol=1e-4)
                if k < 33:
                    np.testing.assert_allclose(data[t, 543 + k], [x - 0.125 * t * 2, 1.0 - z, y], atol=1e-6)


def test_holistic_pose_centres_the_world_on_the_shoulders_without_hips():
    from m3t.render.posefile import holistic_pose

    points = _stub_points()
    points[1, 4] = np.nan  # the right hip lost in one frame: the shoulders are the origin in every frame
    pose = holistic_pose(_HolisticStub(), {"points": points}, np.zeros(3), fps=25, width=200, height=100)
    world = np.ma.getdata(pose.body.data)[:, 0, 543:]
    np.testing.assert_allclose(world[:, 11], [[0.25, 0.0, 0.0], [0.25, 0.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(world[:, 12], [[-0.25, 0.0, 0.0], [-0.25, 0.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(world[:, 23], [[0.125, 0.5, 0.0], [0.125, 0.5, 0.0]], atol=1e-6)
    assert (world[1, 24] == 0).all() and pose.body.confidence[1, 0, 543 + 24] == 0


def test_holistic_pose_refuses_bad_canvases_empty_clips_and_a_body_without_origin():
    import re

    from m3t.render.posefile import holistic_pose

    body, params = _HolisticStub(), {"points": _stub_points()}
    for width, height in ((0, 10), (10, 0), (65536, 10), (10, 65536)):
        with pytest.raises(ValueError, match=re.escape(f".pose export: canvas {width} x {height} px; each side must be "
                                                       "in 1..65535")):
            holistic_pose(body, params, np.zeros(3), 25.0, width, height)
    big = holistic_pose(body, params, np.zeros(3), 25.0, 65535, 65535)  # the largest canvas a .pose file holds
    assert (big.header.dimensions.width, big.header.dimensions.height) == (65535, 65535)
    with pytest.raises(ValueError, match=re.escape(".pose export: no frames to write (holistic points of shape "
                                                   "(0, 9, 3))")):
        holistic_pose(body, {"points": np.zeros((0, 9, 3))}, np.zeros(3), 25.0)
    lost = _stub_points()
    lost[0, 0] = np.nan  # a shoulder lost in frame 0, a hip in frame 1
    lost[1, 3] = np.nan
    with pytest.raises(ValueError, match=re.escape(
            ".pose export: the body model gives neither both hips nor both shoulders in every frame; "
            "POSE_WORLD_LANDMARKS need one of them as origin")):
        holistic_pose(body, {"points": lost}, np.zeros(3), 25.0)
    for leg in ("knee", "ankle", "heel", "foot_index"):  # only a leg: legs are never fitted
        with pytest.raises(ValueError, match="no valid point to fit"):
            holistic_pose(_HolisticStub((f"pose:left_{leg}",), np.array([1])), {"points": np.ones((1, 1, 3))},
                          np.zeros(3), 25.0)


def test_export_pose_writes_what_holistic_pose_gives_on_a_1024_px_canvas_by_default(tmp_path):
    import io

    from m3t.render.posefile import holistic_pose

    body, params = _HolisticStub(), {"points": _stub_points()}
    path = export_pose(str(tmp_path / "stub.pose"), body, params, np.zeros(3), 10.0)
    assert path == tmp_path / "stub.pose"
    buffer = io.BytesIO()
    holistic_pose(body, params, np.zeros(3), 10.0, 1024, 1024).write(buffer)
    assert path.read_bytes() == buffer.getvalue()
    pose = _read(path)
    assert (pose.header.dimensions.width, pose.header.dimensions.height) == (1024, 1024) and pose.body.fps == 10.0
    other = export_pose(tmp_path / "small.pose", body, params, np.zeros(3), 10.0, width=300, height=200)
    assert (_read(other).header.dimensions.width, _read(other).header.dimensions.height) == (300, 200)


def test_holistic_components_are_fresh_copies_of_the_header_template():
    from m3t.render.posefile import _template, holistic_components

    first, second = holistic_components(), holistic_components()
    assert [c.name for c in first] == [n for n, _ in COUNTS] and all(c.format == "XYZC" for c in first)
    for component, (name, points, limbs, colors) in zip(first, _template()):
        assert component.name == name and component.points == list(points) and component.limbs == list(limbs)
        assert component.colors == [tuple(c) for c in colors] and isinstance(component.points, list)
    assert first[0].points[:2] == ["NOSE", "LEFT_EYE_INNER"] and first[2].points[0] == "WRIST"
    first[0].points.append("TAIL")  # mutating one copy leaves the template and the next copy alone
    assert len(second[0].points) == 33 and len(holistic_components()[0].points) == 33


def test_the_holistic_order_names_at_most_five_unknown_points_and_the_parts():
    import re

    from m3t.render.posefile import _order

    order = _order(("face:0", "pose:nose", "right_hand:wrist"))
    assert order[0] == 1 and order[33] == 0 and order[33 + 468 + 21] == 2 and (order == -1).sum() == 33 + 468 + 42 - 3
    assert order.dtype.kind == "i" and len(order) == 33 + 468 + 42
    unknown = tuple(f"pose:tail{k}" for k in (6, 5, 4, 3, 2, 1))
    with pytest.raises(ValueError, match=re.escape(
            "holistic correspondence names ['pose:tail1', 'pose:tail2', 'pose:tail3', 'pose:tail4', 'pose:tail5'] "
            "(of 6) match no point of pose-format's holistic header; expected 'part:name' with part in "
            "['pose', 'face', 'left_hand', 'right_hand']")):
        _order(unknown + ("pose:nose",))
    with pytest.raises(ValueError, match=re.escape("['pose:NOSE'] (of 1)")):  # names are lower case
        _order(("pose:NOSE",))


def test_front_view_default_margin_and_only_seen_fitted_points():
    import re

    points = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [5.0, 3.0, -4.0]]])  # (1, 3, 3); point 2 far away
    seen = np.array([[True, True, False]])  # point 2 missing, though in the fitted set
    got = front_view(points, seen, np.ones(3, bool), 100, 100)
    # box x 0 .. 1, y = -Z -0.5 .. 0, z = Y 0 .. 0: 8 % margins, scale min(84 / 1, 84 / 0.5) = 84
    np.testing.assert_allclose(got[0, :2], [[8.0, 50 + 0.25 * 84, 0.0], [92.0, 50 - 0.25 * 84, 0.0]])
    np.testing.assert_allclose(got[0, 2], [50 + 4.5 * 84, 50 + 4.25 * 84, 3 * 84])
    flat = front_view(points[:, :1], seen[:, :1], np.ones(1, bool), 40, 20)  # one point: no span, the centre
    np.testing.assert_allclose(flat, [[[20.0, 10.0, 0.0]]])
    with pytest.raises(ValueError, match=re.escape(
            "front view: no valid point to fit the canvas to (all points missing or non-finite)")):
        front_view(points, seen, np.array([False, False, True]), 100, 100)


def _tiny_graph():
    from m3t.body.skeleton import SkeletonGraph

    return SkeletonGraph("tiny", ("body:neck:base", "left_hand:wrist", "right_hand:wrist", "face:61"),
                         ((0, 1), (0, 2), (0, 3)))


def test_skeleton_pose_by_hand_one_component_coloured_by_region():
    """Joints (protocol frame) on a 100 x 50 canvas: box x -0.5 .. 0.5, y = -Z -1.5 .. -1.0, z = Y 0 .. 0.25;
    scale min(84 / 1, 42 / 0.5) = 84 px/m. A NaN joint: confidence 0, coordinates 0, the rest still placed."""
    from m3t.render.posefile import skeleton_pose

    points = np.array([[[0.0, 0.0, 1.25], [0.5, 0.0, 1.0], [-0.5, 0.25, 1.0], [0.0, 0.0, 1.5]]] * 2)
    points[1, 2] = [np.nan, 0.0, 0.0]
    points[1, :2, 0] -= 0.25  # frame 1: moved, still within the box of frame 0
    pose = skeleton_pose(points.tolist(), _tiny_graph(), fps=30, width=100, height=50)
    (component,) = pose.header.components
    assert (component.name, component.points, component.format) == ("tiny", list(_tiny_graph().joints), "XYZC")
    assert [tuple(limb) for limb in component.limbs] == [(0, 1), (0, 2), (0, 3)]
    assert [tuple(c) for c in component.colors] == [(80, 80, 80), (214, 39, 40), (31, 119, 180), (44, 160, 44)]
    dims = pose.header.dimensions
    assert (dims.width, dims.height, dims.depth) == (100, 50, 0) and round(pose.header.version, 3) == 0.2
    assert pose.body.fps == 30.0 and isinstance(pose.body.fps, float)
    data, conf = np.ma.getdata(pose.body.data), np.asarray(pose.body.confidence)
    assert data.dtype == np.float32 and conf.dtype == np.float32 and data.shape == (2, 1, 4, 3)
    np.testing.assert_array_equal(conf[:, 0], [[1, 1, 1, 1], [1, 1, 0, 1]])
    for t in range(2):
        for k, (x, y, z) in enumerate(points[t]):
            want = [0.0, 0.0, 0.0] if (t, k) == (1, 2) else [x * 84 + 50, (1.25 - z) * 84 + 25, (y - 0.125) * 84]
            np.testing.assert_allclose(data[t, 0, k], want, atol=1e-4)


def test_skeleton_pose_refuses_bad_shapes_and_canvases():
    import re

    from m3t.render.posefile import skeleton_pose

    graph, ok = _tiny_graph(), np.zeros((2, 4, 3))
    ok[:, 1, 0] = 1.0
    for bad in (np.zeros((0, 4, 3)), np.zeros((2, 5, 3)), np.zeros((2, 4, 2)), np.zeros((4, 3))):
        with pytest.raises(ValueError, match=re.escape(f".pose export of skeleton 'tiny': points of shape {bad.shape}, "
                                                       "expected (T > 0, 4, 3)")):
            skeleton_pose(bad, graph, 25.0)
    for width, height in ((0, 10), (10, 0), (65536, 10), (10, 65536)):
        with pytest.raises(ValueError, match=re.escape(f".pose export: canvas {width} x {height} px; each side must be "
                                                       "in 1..65535")):
            skeleton_pose(ok, graph, 25.0, width, height)
    for width, height in ((1, 1), (65535, 65535)):
        dims = skeleton_pose(ok, graph, 25.0, width, height).header.dimensions
        assert (dims.width, dims.height) == (width, height)
    dims = skeleton_pose(ok, graph, 25.0).header.dimensions
    assert (dims.width, dims.height) == (1024, 1024)


def test_export_skeleton_pose_writes_what_skeleton_pose_gives(tmp_path):
    import io

    from m3t.render.posefile import export_skeleton_pose, skeleton_pose

    points = np.array([[[0.0, 0.0, 1.25], [0.5, 0.0, 1.0], [-0.5, 0.25, 1.0], [0.0, 0.0, 1.5]]])
    path = export_skeleton_pose(str(tmp_path / "a" / "s.pose"), points, _tiny_graph(), 20.0)
    assert path == tmp_path / "a" / "s.pose"
    buffer = io.BytesIO()
    skeleton_pose(points, _tiny_graph(), 20.0, 1024, 1024).write(buffer)
    assert path.read_bytes() == buffer.getvalue()
    small = _read(export_skeleton_pose(tmp_path / "b.pose", points, _tiny_graph(), 20.0, width=64, height=32))
    assert (small.header.dimensions.width, small.header.dimensions.height) == (64, 32) and small.body.fps == 20.0
