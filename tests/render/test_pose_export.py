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
