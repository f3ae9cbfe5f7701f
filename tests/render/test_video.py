"""Rendering to video: the MP4 writer (H.264, yuv420p, faststart, atomic), the z-buffer rasteriser, mesh and
skeleton videos side by side (a finished sequence holds its last frame), skeleton ``.pose`` export, and the
batched vertices of a clip.

MP4 files are read back with ffmpeg itself (``imageio_ffmpeg.read_frames``: codec, size, frame count) and their
box order checked as ISO/IEC 14496-12 lays a file out (``ftyp`` first; ``moov``, the index, before ``mdat``, the
media, when written with ``+faststart``). Skeleton ``.pose`` files are read back with pose-format's own reader.
"""
from __future__ import annotations

import numpy as np
import pytest

imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")


def read_mp4(path) -> tuple[dict, list[np.ndarray]]:
    """(ffmpeg's metadata, decoded (H, W, 3) uint8 frames)."""
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    width, height = meta["size"]
    return meta, [np.frombuffer(f, np.uint8).reshape(height, width, 3) for f in reader]


def test_mp4_is_h264_with_every_frame_even_sides_and_the_index_first(tmp_path):
    from m3t.render.video import write_mp4

    # odd sides (33 x 21) must be padded to 34 x 22, not resized; frames differ so none can be dropped
    frames = [np.full((21, 33, 3), 30 * i, np.uint8) for i in range(7)]
    frames[3][:, :10] = (255, 0, 0)
    path = write_mp4(iter(frames), tmp_path / "clip.mp4", fps=12.5)
    meta, decoded = read_mp4(path)
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert meta["size"] == (34, 22) and meta["fps"] == pytest.approx(12.5)
    assert len(decoded) == 7
    # content survives (lossy: compare means), padding repeats the edge rather than adding black
    assert abs(decoded[5][:21, :33].mean() - 150) < 3 and abs(decoded[5][21:, 33:].mean() - 150) < 3
    assert decoded[3][5, 4, 0] > 200 and decoded[3][5, 4, 1] < 60
    data = path.read_bytes()
    assert data[4:8] == b"ftyp" and 0 < data.find(b"moov") < data.find(b"mdat")
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]


def test_failure_mid_stream_leaves_the_old_file_and_no_temporary(tmp_path):
    from m3t.render.video import write_mp4

    target = tmp_path / "clip.mp4"
    target.write_bytes(b"previous")

    def frames():
        for i in range(3):
            yield np.zeros((16, 16, 3), np.uint8)
        raise RuntimeError("renderer failed at frame 3")

    with pytest.raises(RuntimeError, match="frame 3"):
        write_mp4(frames(), target)
    assert target.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]
    with pytest.raises(ValueError, match="frame 1: shape"):
        write_mp4([np.zeros((16, 16, 3), np.uint8), np.zeros((16, 18, 3), np.uint8)], tmp_path / "new.mp4")
    with pytest.raises(ValueError, match="no frame"):
        write_mp4([], tmp_path / "new.mp4")
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]


def pixel_centres_inside(corners: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool, brute force: pixel centres on the inner side of all three edges of a triangle."""
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    sides = []
    for k in range(3):
        (ax, ay), (bx, by) = corners[k], corners[(k + 1) % 3]
        sides.append((bx - ax) * (ys - ay) - (by - ay) * (xs - ax))
    sides = np.stack(sides)
    return (sides >= 0).all(0) | (sides <= 0).all(0)


def test_rasteriser_fills_the_triangle_and_the_nearer_triangle_wins(tmp_path):
    from m3t.render.raster import rasterise

    corners = np.array([[10.2, 8.7], [90.4, 12.1], [20.3, 85.9]])
    screen = np.column_stack([corners, np.full(3, 5.0)])
    one = rasterise(screen, np.array([[0, 1, 2]]), 100, 100)
    expected = pixel_centres_inside(corners, 100, 100)
    assert expected.sum() > 2500 and (one.mask == expected).all()
    assert np.isclose(one.depth[one.mask], 5.0).all() and np.isinf(one.depth[~one.mask]).all()
    assert (one.shade[one.mask] > 0.3).all()  # facing the viewer: lit, never below the ambient term

    # two overlapping triangles, the nearer (depth 1) listed first or last: it must win wherever both cover
    near = np.column_stack([corners, np.full(3, 1.0)])
    far = np.column_stack([corners + [15.0, 5.0], np.full(3, 9.0)])
    for order in ((near, far), (far, near)):
        raster = rasterise(np.concatenate(order), np.array([[0, 1, 2], [3, 4, 5]]), 100, 100)
        near_index = 0 if order[0] is near else 1
        both = expected & pixel_centres_inside(corners + [15.0, 5.0], 100, 100)
        assert both.sum() > 1000
        assert (raster.face[both] == near_index).all() and np.isclose(raster.depth[both], 1.0).all()
        only_far = pixel_centres_inside(corners + [15.0, 5.0], 100, 100) & ~expected
        assert (raster.face[only_far] == 1 - near_index).all()


def test_rasteriser_closes_a_cube_without_gaps():
    """A unit cube seen face on (12 triangles, winding mixed): its front square is covered entirely, by the
    front face's two triangles only."""
    from m3t.render.raster import rasterise

    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    screen = corners * [40.0, 40.0, 1.0] + [20.0, 20.0, 0.0]  # x, y pixels; z depth (front face at z = 0)
    raster = rasterise(screen, faces, 80, 80)
    square = np.zeros((80, 80), bool)
    square[20:60, 20:60] = True
    assert (raster.mask == square).all()
    front = [k for k, f in enumerate(faces) if (corners[f][:, 2] == 0).all()]
    assert set(np.unique(raster.face[square])) == set(front)


def tall_triangle(frames: int, up: str) -> np.ndarray:
    """(T, 3, 3) a triangle 1.7 m tall and 0.4 m wide at its base, apex up, moving 15 cm along x per frame."""
    base = np.array([[-0.2, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.0, 1.7]])  # protocol frame: Z up
    sway = np.zeros((frames, 1, 3))
    sway[:, 0, 0] = 0.15 * np.arange(frames)
    verts = base[None] + sway
    return verts if up == "z" else verts[..., [0, 2, 1]] * [1, 1, -1]  # Y up, facing +Z


def test_mesh_frames_put_up_axis_up_from_the_data():
    from m3t.render.mesh_video import front_views, render_mesh_frame

    faces = np.array([[0, 1, 2]])
    pictures = {}
    for up in ("z", "y"):
        verts = tall_triangle(4, up)
        view = front_views({"a": verts}, 64, visible_height=1.0)["a"]
        pictures[up] = render_mesh_frame(verts[0], faces, view)
    covered = (pictures["z"] != 255).any(-1)
    rows = np.flatnonzero(covered.any(1))
    widths = covered.sum(1)[rows]
    assert widths[0] < widths[-1] / 4  # apex at the top of the picture, base at the bottom
    assert (pictures["z"] == pictures["y"]).all()


def test_mesh_video_plays_panels_together_and_holds_the_shorter_one(tmp_path):
    from m3t.render.mesh_video import render_mesh_video
    from m3t.render.video import LABEL_HEIGHT

    faces = np.array([[0, 1, 2]])
    long, short = tall_triangle(8, "z"), tall_triangle(3, "z")
    path = render_mesh_video({"reference": long, "generated": short}, faces, tmp_path / "m.mp4", fps=10, size=64,
                             title="clip", visible_height=1.0)
    meta, decoded = read_mp4(path)
    assert len(decoded) == 8 and meta["size"] == (64 + 4 + 64, 2 * LABEL_HEIGHT + 64)
    body = [f[2 * LABEL_HEIGHT:].astype(int) for f in decoded]
    left, right = [b[:, :64] for b in body], [b[:, 68:] for b in body]
    # the reference keeps moving; the generated panel holds its third frame from then on
    assert np.abs(left[7] - left[2]).mean() > 3
    for t in range(3, 8):
        assert np.abs(right[t] - right[2]).mean() < 1.5
    assert np.abs(right[1] - right[2]).mean() > 3


def test_mesh_video_through_a_fitted_camera(tmp_path):
    """Fitting's camera dict (fx, fy, cx, cy, world -> camera rotation / translation, image size): the panel keeps
    the camera's aspect, scaled so its longer side is ``size``; the triangle lands where the pinhole puts it."""
    from m3t.render.mesh_video import render_mesh_video

    camera = {"fx": 100.0, "fy": 100.0, "cx": 100.0, "cy": 50.0, "width": 200, "height": 100,
              "rotation": [[1, 0, 0], [0, 0, -1], [0, 1, 0]], "translation": [0.0, 0.0, 4.0]}  # 4 m in front, Z up
    square = np.array([[-0.8, 0.0, -0.8], [0.8, 0.0, -0.8], [0.8, 0.0, 0.8], [-0.8, 0.0, 0.8]])  # 1.6 m, facing -Y
    verts = np.stack([square, square + [0.0, 0.0, 0.5]])  # the second frame half a metre higher
    path = render_mesh_video({"fit": verts}, np.array([[0, 1, 2], [0, 2, 3]]), tmp_path / "c.mp4", size=64,
                             camera=camera)
    meta, decoded = read_mp4(path)
    assert meta["size"] == (64, 20 + 32) and len(decoded) == 2
    # 1.6 m at 4 m through f = 100 px: 40 px of the 200 x 100 image, shown at 64 / 200: 12.8 px, centred
    for frame, centre_row in zip(decoded, (15.5, 15.5 - 0.5 * 100 / 4 * 0.32)):
        drawn = (frame[20:] < 200).any(-1)  # (32, 64)
        rows, cols = np.flatnonzero(drawn.any(1)), np.flatnonzero(drawn.any(0))
        assert 12 <= rows[-1] - rows[0] + 1 <= 14 and 12 <= cols[-1] - cols[0] + 1 <= 14
        assert abs((rows[0] + rows[-1]) / 2 - centre_row) <= 1 and abs((cols[0] + cols[-1]) / 2 - 31.5) <= 1


def test_skeleton_video_mp4_and_gif(tmp_path):
    from PIL import Image

    from m3t.body.skeleton import body_graph
    from m3t.render.skeleton_video import render_skeleton_video

    graph = body_graph()
    rng = np.random.default_rng(0)
    ref = rng.normal(scale=0.2, size=(6, len(graph.joints), 3))
    ref[:, 0] = [0.0, 0.0, 1.5]  # the neck above the mean point: z up
    gen = ref[:4] + 0.01
    gen[:, 5] = np.nan  # a missing joint: its limbs are left out, the frame still drawn
    path = render_skeleton_video({"reference": ref, "sgsa": gen}, graph, tmp_path / "v.mp4", fps=25, size=96)
    meta, decoded = read_mp4(path)
    assert meta["codec"] == "h264" and len(decoded) == 6 and meta["size"] == (96 + 4 + 96, 20 + 96)
    gif = render_skeleton_video({"reference": ref}, graph, tmp_path / "v.gif", size=64)
    assert Image.open(gif).n_frames == 6


def test_skeleton_pose_export_reads_back_with_the_graph_as_component(tmp_path):
    from pose_format import Pose

    from m3t.body.skeleton import body_graph
    from m3t.render.posefile import export_skeleton_pose

    graph = body_graph(face_points=True)
    rng = np.random.default_rng(1)
    points = rng.normal(scale=0.3, size=(5, len(graph.joints), 3))
    points[2, 7] = np.nan
    path = export_skeleton_pose(tmp_path / "pose" / "sgsa" / "clip.pose", points, graph, fps=25.0, width=512,
                                height=256)
    pose = Pose.read(path.read_bytes())
    (component,) = pose.header.components
    assert component.name == graph.name and tuple(component.points) == graph.joints
    assert [tuple(limb) for limb in component.limbs] == list(graph.edges) and component.format == "XYZC"
    assert pose.body.data.shape == (5, 1, len(graph.joints), 3) and pose.body.fps == 25.0
    conf = np.asarray(pose.body.confidence)
    assert conf[2, 0, 7] == 0 and conf.sum() == 5 * len(graph.joints) - 1
    xy = np.asarray(pose.body.data)[..., :2][conf > 0]
    assert (xy >= 0).all() and (xy[:, 0] <= 512).all() and (xy[:, 1] <= 256).all()
    # image y is down: a joint higher up (larger Z) has a smaller y
    top, bottom = np.argmax(points[0, :, 2]), np.argmin(points[0, :, 2])
    assert pose.body.data[0, 0, top, 1] < pose.body.data[0, 0, bottom, 1]


def test_clip_vertices_chunked_equal_one_forward(body):
    import torch

    from m3t.render.mesh import clip_vertices

    torch.manual_seed(0)
    params = {k: (v + 0.05 * torch.randn_like(v)).numpy() for k, v in body.rest_params(5).items()}
    identity = body.default_identity().numpy()
    chunked = clip_vertices(body, params, identity, chunk=2)
    with torch.no_grad():
        whole = body.forward({k: torch.as_tensor(v) for k, v in params.items()}, torch.as_tensor(identity)).vertices
    assert chunked.shape == (5, whole.shape[1], 3) and chunked.dtype == np.float32
    np.testing.assert_allclose(chunked, whole.numpy(), atol=1e-5)


# ---- the frame plumbing, by hand: which frame a finished sequence shows, its label, even sides, the panel layout
def test_a_finished_sequence_holds_its_last_frame_and_says_so():
    from m3t.render.video import held, progress_label

    assert [held(3, t) for t in range(5)] == [0, 1, 2, 2, 2]
    assert [progress_label("PT", 3, t) for t in (0, 2, 3, 9)] == ["PT", "PT", "PT (3/3)", "PT (3/3)"]


def test_odd_sides_are_padded_by_repeating_the_last_row_and_column():
    from m3t.render.video import pad_even

    even = np.zeros((4, 6, 3), np.uint8)
    assert pad_even(even) is even
    frame = np.arange(3 * 5 * 3, dtype=np.uint8).reshape(3, 5, 3)
    padded = pad_even(frame)
    assert padded.shape == (4, 6, 3)
    assert np.array_equal(padded[:3, :5], frame) and np.array_equal(padded[3, :5], frame[2])
    assert np.array_equal(padded[:3, 5], frame[:, 4])
    assert pad_even(np.zeros((2, 3, 3), np.uint8)).shape == (2, 4, 3)
    assert pad_even(np.zeros((3, 2, 3), np.uint8)).shape == (4, 2, 3)


def test_frames_are_checked_for_type_shape_and_one_size():
    from m3t.render.video import _ascii, _checked, write_video

    ok = np.zeros((4, 4, 3), np.uint8)
    first, frames = _checked([ok, ok])
    assert first is not None and len(list(frames)) == 2
    with pytest.raises(ValueError, match="no frame to write"):
        _checked([])
    for bad in (np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), np.uint8), np.zeros((4, 4, 4), np.uint8),
                np.zeros((0, 4, 3), np.uint8)):
        with pytest.raises(ValueError, match=r"frame 0: .* expected \(H, W, 3\) uint8"):
            _checked([bad])
    _, rest = _checked([ok, np.zeros((4, 6, 3), np.uint8)])
    with pytest.raises(ValueError, match=r"frame 1: shape \(4, 6, 3\), but frame 0 was \(4, 4, 3\)"):
        list(rest)
    with pytest.raises(ValueError, match="written as .mp4"):
        write_video([ok], "clip.avi")
    assert _ascii("Zürich 1 ~") == "Z?rich 1 ~" and _ascii("\t") == "?"


def test_panels_sit_side_by_side_under_their_labels_with_white_gaps():
    from m3t.render.video import BACKGROUND, LABEL_HEIGHT, side_by_side

    tall, short = np.zeros((10, 6, 3), np.uint8), np.full((4, 3, 3), 7, np.uint8)
    row = side_by_side([tall, short], ["a", "b"], gap=2)
    assert row.shape == (10 + LABEL_HEIGHT, 6 + 2 + 3, 3)
    assert np.array_equal(row[LABEL_HEIGHT:, :6], tall)  # the first panel under its label strip
    assert (row[:, 6:8] == BACKGROUND).all()  # the gap
    assert np.array_equal(row[LABEL_HEIGHT:LABEL_HEIGHT + 4, 8:], short)
    assert (row[LABEL_HEIGHT + 4:, 8:] == BACKGROUND).all()  # the shorter panel padded with white below
    assert side_by_side([tall, short], ["a", "b"], gap=0).shape[1] == 9
    titled = side_by_side([tall], ["a"], title="T")
    assert titled.shape == (10 + 2 * LABEL_HEIGHT, 6, 3)
    with pytest.raises(ValueError, match="1 panels and 2 labels"):
        side_by_side([tall], ["a", "b"])
    with pytest.raises(ValueError, match="0 panels"):
        side_by_side([], [])


def test_the_fit_comparison_strip_is_titled_with_the_clips_reprojection_and_joint_errors(body, tmp_path, monkeypatch):
    import matplotlib.figure

    from m3t.camera import Camera
    from m3t.render.skeleton import render_fit_comparison

    titles: list[str] = []
    original = matplotlib.figure.Figure.suptitle
    monkeypatch.setattr(matplotlib.figure.Figure, "suptitle",
                        lambda fig, text, **kw: titles.append(text) or original(fig, text, **kw))
    camera = Camera(500.0, 500.0, 64.0, 64.0, ((1, 0, 0), (0, -1, 0), (0, 0, -1)), (0.0, 1.0, 3.0), 128, 128)
    params = {k: v.numpy() for k, v in body.rest_params(3).items()}
    identity = body.default_identity().numpy()

    class Fitted:  # the fields the strip reads of a FittedClip
        clip = type("C", (), {"id": "clip-7"})()

        def __init__(self, metrics):
            self.params, self.identity, self.camera, self.metrics = params, identity, camera.as_dict(), metrics

    path = render_fit_comparison(body, Fitted({"reproj_px": 3.26, "joint_mm": 12.4}), (params, identity, camera),
                                 tmp_path / "strip.png", frames=2)
    assert path.stat().st_size > 0
    render_fit_comparison(body, Fitted({}), None, tmp_path / "alone.png", frames=2)
    assert titles == ["clip-7: reprojection 3.3 px, joints 12 mm vs ground truth", "clip-7: reprojection nan px"]


def test_camera_tensors_take_the_asked_dtype():
    import torch

    from m3t.camera import Camera, camera_tensors

    camera = Camera(500.0, 510.0, 64.0, 60.0, ((1, 0, 0), (0, 1, 0), (0, 0, 1)), (0.0, 1.0, 3.0), 128, 128)
    rotation, translation, intrinsics = camera_tensors(camera, torch.float64)
    assert {rotation.dtype, translation.dtype, intrinsics.dtype} == {torch.float64}
    assert intrinsics.tolist() == [500.0, 510.0, 64.0, 60.0] and translation.tolist() == [0.0, 1.0, 3.0]
    assert {t.dtype for t in camera_tensors(camera)} == {torch.float32}


def test_a_skeleton_frame_draws_each_bone_where_its_points_are_in_its_colour():
    """x right and up up in [-extent, extent] map onto the picture: a horizontal bone at y = +extent / 2 lies in
    the upper quarter row band, from x = -extent / 2 to 0 (columns 16 to 32 of 64); a bone to a NaN point is
    not drawn."""
    from m3t.render.skeleton_video import draw_skeleton

    points = np.array([[-0.5, 0.5], [0.0, 0.5], [0.5, -0.5], [np.nan, 0.0]])
    picture = draw_skeleton(points, [(0, 1), (2, 3)], size=64, extent=1.0, color=(200, 0, 0), thickness=1)
    drawn = (picture != 255).any(-1)
    rows, cols = np.nonzero(drawn)
    assert set(rows) <= {15, 16, 17} and cols.min() >= 15 and cols.max() <= 33 and drawn[16, 16:33].all()
    red, green, blue = picture[16, 20].astype(int)  # the bone's colour mid-line, blended at its anti-aliased edge
    assert abs(red - 200) < 10 and green < 40 and blue < 40
    assert not drawn[40:].any()  # the bone to the NaN point is left out


def test_the_holistic_order_maps_each_header_point_to_the_model_point_of_its_name_or_none():
    from m3t.render.posefile import _order

    order = _order(("pose:nose", "left_hand:wrist"))
    assert sorted(order[order >= 0].tolist()) == [0, 1] and (order == -1).sum() == len(order) - 2
    with pytest.raises(ValueError, match=r"holistic correspondence names \['pose:tail'\] \(of 1\) match no point"):
        _order(("pose:nose", "pose:tail"))


def test_the_face_of_the_mediapipe_correspondence_is_drawn_with_the_joints(body):
    from m3t.render.reconstruction import face_landmarks

    face = face_landmarks(body)
    assert face is not None and len(face.names) > 100 and all(n.startswith("face:") for n in face.names)
    assert len(face.index) == len(face.names) == len(face.kind)


def test_a_reconstruction_without_a_camera_is_drawn_from_the_front_in_both_colours(body, tmp_path):
    """Motion without a stored camera (imported from 3D keypoints): an orthographic front view fitted to every
    point of both sequences; the fitted clip in orange, the reconstruction in blue, each held once it ends."""
    from types import SimpleNamespace

    from m3t.render.reconstruction import render_reconstruction

    params = {k: v.numpy() for k, v in body.rest_params(3).items()}
    moved = {k: v.copy() for k, v in params.items()}
    moved["body"] = moved["body"] + 0.3  # another pose: the two skeletons part
    fitted = SimpleNamespace(params=params, identity=body.default_identity().numpy(), camera={},
                             clip=SimpleNamespace(id="c", fps=12.5))
    path = render_reconstruction(body, fitted, {k: v[:2] for k, v in moved.items()}, tmp_path / "r.mp4", size=96)
    meta, frames = read_mp4(path)
    assert len(frames) == 3 and 96 in meta["size"]  # the panel's longer side, a legend strip below
    pixels = np.concatenate([f.reshape(-1, 3).astype(int) for f in frames])
    orange = ((pixels[:, 0] > 200) & (pixels[:, 2] < 100)).sum()
    blue = ((pixels[:, 2] > 150) & (pixels[:, 0] < 100)).sum()
    assert orange > 20 and blue > 20
