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


# ---- the reconstruction video, frame by frame: a three-joint stick body whose points are read from its parameters
class _StickBody:
    """A body model of three chained joints (root -> elbow -> hand, all driven by rotations) and two face vertices,
    whose keypoints are the parameters themselves: joints from ``joints`` (T, 3, 3), vertices from ``verts``
    (T, 2, 3). Its MediaPipe correspondence holds a pose point (not drawn as face), two face vertices and a face
    point without correspondence."""

    joint_names = ("root", "elbow", "hand")
    joint_parents = (-1, 0, 1)

    def __init__(self, face: bool = True):
        from types import SimpleNamespace

        self.layout = SimpleNamespace(modalities=(SimpleNamespace(kind="rotation6d", labels=self.joint_names),
                                                  SimpleNamespace(kind="scalar", labels=("smile",))))
        self.face = face
        self.asked: list[str] = []

    def correspondence(self, name):
        from m3t.body.protocol import Correspondence

        self.asked.append(name)
        if name != "mediapipe_holistic" or not self.face:
            raise KeyError(name)
        return Correspondence(("pose:nose", "face:1", "face:2", "face:3"), np.array([1, 0, 0, -1]),
                              np.array([2, 0, 1, 0]))

    def keypoint_set(self, correspondence):
        return correspondence

    def forward_keypoints(self, params, identity, kp):
        import torch

        assert identity.dtype == torch.float32 and identity.shape == (2,)
        joints, verts = params["joints"], params["verts"]
        return torch.stack([joints[:, i] if kind == 1 else verts[:, i] if kind == 0 else torch.zeros_like(joints[:, 0])
                            for kind, i in zip(kp.kind, kp.index)], 1)


def _stick_clip(fps=12.5, camera=None):
    """A fitted 3-frame clip of the stick body: the arm sweeps right, the two face points sit above it."""
    from types import SimpleNamespace

    joints = np.array([[[0.25, 0.0, -0.75], [0.5, 0.0, -0.75], [0.5, 0.0, -0.5]]] * 3)
    joints[:, :, 0] += np.array([0.0, 0.0625, 0.125])[:, None]
    verts = np.array([[[0.375, 0.0, -0.125], [0.625, 0.0, -0.125]]] * 3)
    params = {"joints": joints, "verts": verts}
    return SimpleNamespace(params=params, identity=np.zeros(2), camera=camera or {},
                           clip=SimpleNamespace(id="clip-3", fps=fps))


def _captured_video(monkeypatch):
    """Replace the reconstruction's video writer by one that keeps the frames (exact, no lossy encoding)."""
    from m3t.render import reconstruction

    out = {}

    def keep(frames, path, fps):
        out.update(frames=list(frames), path=path, fps=fps)
        return path

    monkeypatch.setattr(reconstruction, "write_video", keep)
    return out


def _expected_reconstruction(sides, low, zoom, size_wh, lengths, labels, title):
    """The frames drawn by hand: per side (orange fitted, blue reconstruction) its bones root-elbow and
    elbow-hand as 1 px anti-aliased lines and its face points as 1 px dots, at 1/16 px fixed point; the legend
    in the bottom-left corner; the panel under a strip holding ``title``."""
    import cv2

    from m3t.render.video import side_by_side

    width, height = size_wh
    frames = []
    for t in range(max(lengths)):
        panel = np.full((height, width, 3), 255, np.uint8)
        for (joints, face), colour, n in zip(sides, ((255, 127, 14), (31, 119, 180)), lengths):
            k = min(t, n - 1)
            ends = np.round((np.nan_to_num(joints[k]) - low) * zoom * 16).astype(int)
            for a, b in ((0, 1), (1, 2)):
                if np.isfinite(joints[k][[a, b]]).all():
                    cv2.line(panel, tuple(ends[a]), tuple(ends[b]), colour, 1, cv2.LINE_AA, 4)
            for point in np.round((face[k] - low) * zoom * 16).astype(int):
                cv2.circle(panel, tuple(point), 16, colour, -1, cv2.LINE_AA, 4)
        for row, (label, colour, n) in enumerate(zip(labels, ((255, 127, 14), (31, 119, 180)), lengths)):
            text = f"{label} ({n}/{n})" if t >= n else label
            cv2.putText(panel, text, (6, height - 24 + 16 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1,
                        cv2.LINE_AA)
        frames.append(side_by_side([panel], [title]))
    return frames


def test_a_reconstruction_without_a_camera_is_drawn_exactly_from_the_front(monkeypatch, capsys):
    """No camera: image x = X, image y = -Z, the view fitted to every point of both sides plus 5 cm; the panel's
    longer side is ``size``. The shorter reconstruction holds its last frame and its legend says so; the
    title defaults to the clip id; the clip's frame rate is kept."""
    from m3t.render.reconstruction import render_reconstruction

    body, fitted = _StickBody(), _stick_clip()
    recon = {"joints": fitted.params["joints"][:2] + [0.0, 0.0, 0.125]}  # two frames, 12.5 cm higher
    recon["joints"][1, 2] = np.nan  # the hand lost in the last frame: only the root-elbow bone is drawn
    captured = _captured_video(monkeypatch)
    path = render_reconstruction(body, fitted, recon, "r.mp4", size=96)
    assert path == "r.mp4" and captured["path"] == "r.mp4" and captured["fps"] == 12.5
    assert "mediapipe_holistic" in body.asked and capsys.readouterr().err == ""  # no progress bar by default

    def image(points):  # (T, K, 3) -> (T, K, 2) image x = X, y = -Z
        return np.stack([points[..., 0], -points[..., 2]], -1).astype(np.float32).astype(np.float64)

    sides = [(image(fitted.params["joints"]), image(fitted.params["verts"])),
             (image(recon["joints"]), image(fitted.params["verts"][:2]))]
    every = np.concatenate([s.reshape(-1, 2) for side in sides for s in side])
    low, high = np.nanmin(every, 0) - 0.05, np.nanmax(every, 0) + 0.05
    zoom = 96 / (high - low).max()
    size_wh = tuple(max(1, round(float(d) * zoom)) for d in high - low)
    assert size_wh == (63, 96)  # x spans 0.25 .. 0.625, y 0.125 .. 0.75, plus the margins
    expected = _expected_reconstruction(sides, low, zoom, size_wh, (3, 2), ("fitted", "reconstructed"), "clip-3")
    assert len(captured["frames"]) == 3
    assert ((expected[2] == (31, 119, 180)).all(-1).sum() > 3 and (expected[2] == (255, 127, 14)).all(-1).sum() > 3)  # drawn
    for got, want in zip(captured["frames"], expected):
        assert got.shape == want.shape and np.array_equal(got, want)


@pytest.mark.parametrize("fps, played", [(0.0, 25.0), (None, 25.0), (0.5, 0.5)])
def test_a_reconstruction_through_the_clips_camera_fills_its_image(monkeypatch, capsys, fps, played):
    """With a stored camera the panel is the camera's image scaled to ``size``: a 32 x 24 px image at 64 px is
    64 x 48, each point where the pinhole puts it, times two. A body without a MediaPipe correspondence has no
    face dots; ``max_frames`` cuts the video; the labels and title given are drawn; a clip without a positive
    frame rate plays at 25 fps; ``progress`` shows a bar named after the file."""
    from m3t.render.reconstruction import render_reconstruction

    camera = {"fx": 32.0, "fy": 32.0, "cx": 16.0, "cy": 8.0, "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
              "translation": [0.0, 0.0, 2.0], "width": 32, "height": 24}
    body, fitted = _StickBody(face=False), _stick_clip(fps=fps, camera=camera)
    fitted.params["joints"][..., 1] = fitted.params["joints"][..., 2] + 0.75  # in the camera's plane z = 0
    fitted.params["joints"][..., 2] = 0.0
    recon = {"joints": fitted.params["joints"] + [0.0, 0.25, 0.0]}  # 25 cm lower in the picture (y down)
    captured = _captured_video(monkeypatch)
    render_reconstruction(body, fitted, recon, "c.gif", title="T", max_frames=2, labels=("a", "b"), size=64,
                          progress=True)
    assert captured["fps"] == played and "render c.gif" in capsys.readouterr().err

    def image(points):  # pinhole at 2 m: 16 px per metre around (16, 8)
        return points[..., :2] * 16 + [16.0, 8.0]

    sides = [(image(fitted.params["joints"]), np.zeros((3, 0, 2))), (image(recon["joints"]), np.zeros((3, 0, 2)))]
    expected = _expected_reconstruction(sides, np.zeros(2), 2.0, (64, 48), (3, 3), ("a", "b"), "T")
    assert len(captured["frames"]) == 2
    for got, want in zip(captured["frames"], expected):
        assert got.shape == (20 + 48, 64, 3) and np.array_equal(got, want)


def test_the_face_landmarks_are_the_valid_face_points_of_the_mediapipe_correspondence():
    from m3t.render.reconstruction import face_landmarks

    body = _StickBody()
    face = face_landmarks(body)
    assert body.asked == ["mediapipe_holistic"]
    assert face.names == ("face:1", "face:2") and face.kind.tolist() == [0, 0] and face.index.tolist() == [0, 1]
    assert face_landmarks(_StickBody(face=False)) is None  # no such correspondence: no face drawn


def test_skeleton_edges_join_each_joint_to_its_nearest_ancestor_in_the_set():
    """Parents outside the set (twist bones) are skipped; a joint whose ancestors are all outside starts a tree."""
    from types import SimpleNamespace

    from m3t.body.protocol import Correspondence
    from m3t.render.skeleton import skeleton_edges

    body = SimpleNamespace(joint_parents=(-1, 0, 1, 2, 0))

    def corr(*index):
        return Correspondence(tuple(map(str, index)), np.ones(len(index), int), np.array(index))

    assert skeleton_edges(body, corr(0, 2, 3, 4)) == [(0, 1), (1, 2), (0, 3)]
    assert skeleton_edges(body, corr(3, 1)) == [(1, 0)]  # listed child first; joint 1's parent 0 is not in the set
    assert skeleton_edges(body, corr(0, 1)) == [(0, 1)]  # the root (joint 0) is a parent like any other


def _fit_strip(monkeypatch, tmp_path, metrics, ground_truth, frames):
    """Draw the fit comparison of a 4-frame stick-body clip; returns (path, the saved figure, savefig's kwargs)."""
    import matplotlib.figure

    from m3t.render.skeleton import render_fit_comparison

    saved = {}
    original = matplotlib.figure.Figure.savefig

    def keep(fig, path, **kw):
        saved.update(fig=fig, kw=kw)
        return original(fig, path, **kw)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    camera = {"fx": 32.0, "fy": 32.0, "cx": 16.0, "cy": 8.0, "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
              "translation": [0.0, 0.0, 2.0], "width": 32, "height": 24}
    fitted = _stick_clip(camera=camera)
    joints = np.concatenate([fitted.params["joints"], fitted.params["joints"][-1:] + [0.0, 0.0, 0.0]])
    joints[..., 1], joints[..., 2] = joints[..., 2] + 0.75, 0.0  # in the camera's plane z = 0, y down
    joints[3, :, 1] += 0.25
    fitted.params = {"joints": joints, "verts": np.zeros((4, 2, 3))}
    fitted.metrics = metrics
    path = render_fit_comparison(_StickBody(), fitted, ground_truth and (fitted.params, fitted.identity, ground_truth),
                                 tmp_path / "figures" / "fit" / "strip.png", frames=frames)
    return path, saved["fig"], saved["kw"], joints[..., :2] * 16 + [16.0, 8.0]


def test_the_fit_comparison_draws_the_fitted_skeleton_over_the_ground_truth_at_evenly_spaced_frames(
        monkeypatch, tmp_path):
    """Three of four frames (0, 2, 3: evenly spaced, rounded); per frame the ground truth's bones and joints in
    orange under the fitted ones in blue, on the camera's image (y down, equal aspect, no ticks); one legend."""
    import matplotlib.colors
    from matplotlib.figure import Figure

    from m3t.camera import Camera

    gt_camera = Camera(32.0, 32.0, 20.0, 8.0, ((1, 0, 0), (0, 1, 0), (0, 0, 1)), (0.0, 0.0, 2.0), 32, 24)
    path, fig, kw, uv = _fit_strip(monkeypatch, tmp_path, {"reproj_px": 1.04}, gt_camera, frames=3)
    assert path == tmp_path / "figures" / "fit" / "strip.png" and path.stat().st_size > 0
    assert kw == {"dpi": 100, "bbox_inches": "tight"}
    assert isinstance(fig, Figure) and tuple(fig.get_size_inches()) == pytest.approx((3 * 3.2, 3.4))
    assert fig._suptitle.get_text() == "clip-3: reprojection 1.0 px" and fig._suptitle.get_fontsize() == 9
    axes = fig.axes
    assert len(axes) == 3
    for ax, t in zip(axes, (0, 2, 3)):
        assert ax.get_title() == f"frame {t}" and ax.title.get_fontsize() == 8
        assert ax.get_xlim() == (0, 32) and ax.get_ylim() == (24, 0) and ax.get_aspect() == 1.0
        assert list(ax.get_xticks()) == [] and list(ax.get_yticks()) == []
        lines = ax.get_lines()
        assert [line.get_color() for line in lines] == ["tab:orange"] * 2 + ["tab:blue"] * 2
        assert all(line.get_linewidth() == 1.2 for line in lines)
        for line, (a, b), shift in zip(lines, [(0, 1), (1, 2)] * 2, (4.0, 4.0, 0.0, 0.0)):
            np.testing.assert_array_equal(line.get_xdata(), uv[t, [a, b], 0] + shift)
            np.testing.assert_array_equal(line.get_ydata(), uv[t, [a, b], 1])
        gt, fit = ax.collections
        np.testing.assert_array_equal(gt.get_offsets(), uv[t] + [4.0, 0.0])
        np.testing.assert_array_equal(fit.get_offsets(), uv[t])
        assert list(gt.get_sizes()) == [3] and list(fit.get_sizes()) == [3]
        assert matplotlib.colors.to_hex(gt.get_facecolor()[0]) == matplotlib.colors.to_hex("tab:orange")
        assert matplotlib.colors.to_hex(fit.get_facecolor()[0]) == matplotlib.colors.to_hex("tab:blue")
        assert (gt.get_label(), fit.get_label()) == ("ground truth", "fitted")
    legend = axes[0].get_legend()
    assert [t.get_text() for t in legend.get_texts()] == ["ground truth", "fitted"]
    assert legend._loc == 3 and legend.get_texts()[0].get_fontsize() == 7  # 3: matplotlib's code of "lower left"
    assert all(ax.get_legend() is None for ax in axes[1:])


def test_the_fit_comparison_alone_shows_only_the_fit_and_never_more_frames_than_the_clip(monkeypatch, tmp_path):
    _, fig, _, _ = _fit_strip(monkeypatch, tmp_path, {"joint_mm": 7.6}, None, frames=9)
    assert fig._suptitle.get_text() == "clip-3: reprojection nan px, joints 8 mm vs ground truth"
    assert [ax.get_title() for ax in fig.axes] == ["frame 0", "frame 1", "frame 2", "frame 3"]
    assert tuple(fig.get_size_inches()) == pytest.approx((4 * 3.2, 3.4))
    for ax in fig.axes:
        assert [line.get_color() for line in ax.get_lines()] == ["tab:blue"] * 2 and len(ax.collections) == 1
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == ["fitted"]


def test_the_attention_map_shows_each_head_on_a_fixed_colour_scale(monkeypatch, tmp_path):
    """One panel per head, titled ``head 1``..., keys across and queries down, viridis from 0 to 1 with no
    smoothing; the figure is saved at 90 dpi (creating the folder) and closed; a title goes above all."""
    import matplotlib.figure
    import matplotlib.pyplot as plt

    from m3t.render.skeleton_video import render_attention_map

    saved = []
    original = matplotlib.figure.Figure.savefig
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig",
                        lambda fig, path, **kw: saved.append((fig, kw)) or original(fig, path, **kw))
    weights = np.arange(2 * 3 * 3).reshape(2, 3, 3) / 17.0
    path = render_attention_map(weights, str(tmp_path / "att" / "heads.png"), title="SGSA layer 1")
    assert path == tmp_path / "att" / "heads.png" and path.read_bytes()[:4] == b"\x89PNG"
    assert [p.name for p in path.parent.iterdir()] == ["heads.png"]
    (fig, kw), = saved
    assert kw == {"dpi": 90} and not plt.fignum_exists(fig.number)
    assert tuple(fig.get_size_inches()) == pytest.approx((6.0, 3.2))
    assert fig._suptitle.get_text() == "SGSA layer 1" and fig._suptitle.get_fontsize() == 9
    for h, ax in enumerate(fig.axes):
        (image,) = ax.images
        np.testing.assert_array_equal(image.get_array(), weights[h])
        assert image.get_cmap().name == "viridis" and image.get_clim() == (0.0, 1.0)
        assert image.get_interpolation() == "nearest"
        assert ax.get_title() == f"head {h + 1}" and ax.title.get_fontsize() == 9
        assert (ax.get_xlabel(), ax.get_ylabel()) == ("key frame", "query frame")
    one = render_attention_map(weights[0], tmp_path / "one.png")  # (U, U): one head, no title
    fig, _ = saved[-1]
    assert one.exists() and len(fig.axes) == 1 and fig._suptitle is None
    assert tuple(fig.get_size_inches()) == pytest.approx((3.0, 3.2))


@pytest.mark.parametrize("shape", [(3, 4), (2, 3, 4), (1, 3, 3, 3), (3,)])
def test_the_attention_map_refuses_non_square_weights(tmp_path, shape):
    import re

    from m3t.render.skeleton_video import render_attention_map

    with pytest.raises(ValueError, match=re.escape(f"attention weights of shape {shape}; expected (h, U, U) or "
                                                   "(U, U)")):
        render_attention_map(np.zeros(shape), tmp_path / "a.png")
    assert not (tmp_path / "a.png").exists()


def test_the_up_axis_is_where_the_neck_sits_furthest_from_the_mean():
    from m3t.render.skeleton_video import _up_axis

    points = np.array([[[0.0, 0.1, 1.5], [0.3, 0.0, 1.0], [-0.3, 0.0, 1.0], [np.nan, np.nan, np.nan]]])
    assert _up_axis(points, None) == 2
    assert _up_axis(points[..., [0, 2, 1]], None) == 1  # Y up
    assert _up_axis(points * [1, 1, -1], None) == 2  # upside down: the distance counts, not its sign
    assert _up_axis(points[..., [0, 2, 1]] * [1, -1, 1], None) == 1
    two = np.concatenate([points, points + [0.0, 0.0, 0.2]])  # averaged over frames
    two[1, 0] = [0.0, 0.9, 1.2]
    assert _up_axis(two, None) == 1
    # the neck (joint 0) decides, not another joint: joint 1 sits furthest along Y, the neck along Z
    assert _up_axis(np.array([[[0.0, 0.0, 5.0], [0.0, 5.0, 0.0], [0.0, 0.0, 0.0]]]), None) == 2


def test_a_skeleton_frame_is_drawn_exactly_at_sub_pixel_positions():
    """(x, up) in [-extent, extent] -> pixel ((0.5 + 0.5 x / extent) size, (0.5 - 0.5 up / extent) size) at 1/16 px,
    anti-aliased lines of the given thickness; a bone with a NaN end is skipped."""
    import cv2

    from m3t.render.skeleton_video import draw_skeleton

    points = np.array([[-0.5, 0.5], [0.25, 0.5], [0.5, -0.75], [np.nan, 0.0], [0.0, 0.0]])
    edges = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0)]
    got = draw_skeleton(points, edges, size=40, extent=2.0, color=(10, 200, 30), thickness=3)
    want = np.full((40, 40, 3), 255, np.uint8)
    for a, b in ((0, 1), (1, 2), (4, 0)):
        ends = [(round((0.5 + 0.25 * points[k, 0]) * 40 * 16), round((0.5 - 0.25 * points[k, 1]) * 40 * 16))
                for k in (a, b)]
        cv2.line(want, ends[0], ends[1], (10, 200, 30), 3, cv2.LINE_AA, 4)
    assert got.dtype == np.uint8 and np.array_equal(got, want)
    default = draw_skeleton(points, edges, size=40, extent=2.0, color=(10, 200, 30))
    thin = np.full((40, 40, 3), 255, np.uint8)
    for a, b in ((0, 1), (1, 2), (4, 0)):
        ends = [(round((0.5 + 0.25 * points[k, 0]) * 640), round((0.5 - 0.25 * points[k, 1]) * 640)) for k in (a, b)]
        cv2.line(thin, ends[0], ends[1], (10, 200, 30), 2, cv2.LINE_AA, 4)
    assert np.array_equal(default, thin)  # 2 px by default


def _captured_skeleton_video(monkeypatch):
    from m3t.render import skeleton_video

    out = {}

    def keep(frames, path, fps):
        out.update(frames=list(frames), path=path, fps=fps)
        return path

    monkeypatch.setattr(skeleton_video, "write_video", keep)
    return out


def test_skeleton_video_frames_are_neck_centred_panels_on_one_scale(monkeypatch, capsys):
    """Every panel: x right and up up around each frame's neck, one extent (1.1 x the largest offset) for all;
    the reference in blue, the others in red; the shorter one holds its last frame, its label saying so."""
    from m3t.body.skeleton import SkeletonGraph
    from m3t.render.skeleton_video import draw_skeleton, render_skeleton_video
    from m3t.render.video import side_by_side

    graph = SkeletonGraph("tiny", ("body:neck", "left_hand:wrist", "right_hand:wrist", "face:61"),
                          ((0, 1), (0, 2), (0, 3)))
    ref = np.array([[[0.0, 0.0, 1.5], [0.5, 0.0, 1.0], [-0.25, 0.0, 1.0], [0.0, -0.1, 1.75]]] * 3)
    ref[:, :, 0] += np.array([0.0, 0.5, 1.0])[:, None]  # walks right: the neck-centred panel does not move
    ref[2, 1, 2] = 1.25
    gen = ref[:2] + [0.0, 0.0, 0.1]
    gen[1, 3] = np.nan
    captured = _captured_skeleton_video(monkeypatch)
    out = render_skeleton_video({"sgsa": gen, "reference": ref}, graph, "v.mp4", fps=12.0, title="clip", size=48)
    assert out == "v.mp4" and captured["path"] == "v.mp4" and captured["fps"] == 12.0
    assert capsys.readouterr().err == ""
    extent = 0.5 * 1.1  # the largest offset from the neck: the wrists' 0.5 m
    frames = captured["frames"]
    assert len(frames) == 3
    for t, frame in enumerate(frames):
        panels = [draw_skeleton((seq[k] - seq[k, :1])[:, [0, 2]], graph.edges, 48, extent, colour)
                  for seq, k, colour in ((gen, min(t, 1), (214, 39, 40)), (ref, t, (31, 119, 180)))]
        labels = ["sgsa (2/2)" if t >= 2 else "sgsa", "reference"]
        assert np.array_equal(frame, side_by_side(panels, labels, "clip"))
    # Y-up input gives the same pictures; max_frames cuts; progress shows a bar named after the file
    out = render_skeleton_video({"sgsa": gen[..., [0, 2, 1]], "reference": ref[..., [0, 2, 1]]}, graph, "w.gif", fps=5.0,
                 title="clip", size=48, max_frames=2, progress=True)
    assert "render w.gif" in capsys.readouterr().err
    assert len(captured["frames"]) == 2 and all(np.array_equal(a, b) for a, b in zip(captured["frames"], frames))


def test_skeleton_video_refuses_no_sequence_and_wrong_shapes():
    import re

    from m3t.body.skeleton import body_graph
    from m3t.render.skeleton_video import render_skeleton_video

    graph = body_graph()
    with pytest.raises(ValueError, match="^no sequence to render$"):
        render_skeleton_video({}, graph, "v.mp4")
    joints = len(graph.joints)
    ok = np.ones((2, joints, 3))
    for bad in (np.zeros((0, joints, 3)), np.zeros((2, joints + 1, 3)), np.zeros((2, joints, 2)), np.zeros((joints, 3))):
        with pytest.raises(ValueError, match=re.escape(f"sequence 'gen': shape {bad.shape}, expected (T, {joints}, 3)")):
            render_skeleton_video({"reference": ok, "gen": bad}, graph, "v.mp4")


# ---- refusals, word for word, and small values by hand: rasteriser, writers, meshes
def test_the_rasteriser_refuses_bad_input_word_for_word():
    import re

    from m3t.render.raster import rasterise

    screen, face = np.zeros((3, 3)), np.array([[0, 1, 2]])
    cases = [((np.zeros((3, 2)), face, 5, 5), "rasterise: screen (3, 2) and faces (1, 3); expected (V, 3) and (F, 3)"),
             ((screen, np.array([0, 1, 2]), 5, 5), "rasterise: screen (3, 3) and faces (3,); expected (V, 3) and (F, 3)"),
             ((screen, np.array([[0, 1, 3]]), 5, 5), "rasterise: face indices span 0..3, but there are 3 vertices"),
             ((screen, np.array([[-1, 1, 2]]), 5, 5), "rasterise: face indices span -1..2, but there are 3 vertices"),
             ((screen, face, 0, 5), "rasterise: image 0 x 5 px; both sides must be >= 1"),
             ((screen, face, 5, 0), "rasterise: image 5 x 0 px; both sides must be >= 1")]
    for args, message in cases:
        with pytest.raises(ValueError, match=re.escape(message)):
            rasterise(*args)
    with pytest.raises(ValueError, match=re.escape("rasterise: view (2, 3) and screen (3, 3) differ")):
        rasterise(screen, face, 5, 5, view=np.zeros((2, 3)))
    one = rasterise(screen, np.zeros((0, 3), int), 1, 1)  # no face, a 1 x 1 image: background
    assert one.face.tolist() == [[-1]] and one.face.dtype == np.int32 and one.shade.dtype == np.float32


def test_lambert_shade_follows_the_light_and_the_ambient_term():
    """A triangle facing the viewer (normal along z): lit from the default light (0, -0.45, -1) its shade is
    0.3 + 0.7 / |(0, -0.45, -1)|; from the side, the ambient term; the view frame, not the screen, gives normals."""
    from m3t.render.raster import colorise, rasterise

    screen = np.array([[1.0, 1.0, 2.0], [15.0, 1.0, 2.0], [1.0, 15.0, 2.0]])
    faces = np.array([[0, 1, 2]])
    lit = rasterise(screen, faces, 16, 16)
    assert lit.depth.dtype == np.float64 and lit.shade.shape == (16, 16)
    np.testing.assert_allclose(lit.shade[lit.mask], 0.3 + 0.7 / np.sqrt(1 + 0.45 ** 2), rtol=1e-6)  # float32 buffer
    assert (lit.shade[~lit.mask] == 0).all()
    side = rasterise(screen, faces, 16, 16, light=(3.0, 0.0, 0.0), ambient=0.25)
    np.testing.assert_allclose(side.shade[side.mask], 0.25, rtol=1e-6)
    full = rasterise(screen, faces, 16, 16, light=(0.0, 0.0, -2.0), ambient=0.25)
    np.testing.assert_allclose(full.shade[full.mask], 1.0, rtol=1e-6)
    tilted = screen.copy()
    tilted[:, 2] = [0.0, 14.0, 0.0]  # in the view frame the normal is (-1, 0, 1) / sqrt(2): cosine 1 / sqrt(2)
    np.testing.assert_allclose(rasterise(screen, faces, 16, 16, view=tilted, light=(0.0, 0.0, 1.0)).shade[lit.mask],
                               0.3 + 0.7 / np.sqrt(2), rtol=1e-6)
    picture = colorise(full, color=(0.5, 1.0, 0.0), background=(1, 2, 3))
    assert picture.dtype == np.uint8 and picture.shape == (16, 16, 3)
    assert (picture[full.mask] == (128, 255, 0)).all() and (picture[~full.mask] == (1, 2, 3)).all()
    default = colorise(side)  # the body colour (0.55, 0.7, 0.9) x shade, white around
    assert (default[side.mask] == np.floor(255 * np.array([0.55, 0.7, 0.9]) * 0.25 + 0.5)).all()
    assert (default[~side.mask] == 255).all()


def test_writers_refuse_bad_rates_suffixes_and_frames_word_for_word(tmp_path):
    import re

    from m3t.render.video import _checked, write_mp4, write_video

    ok = np.zeros((4, 4, 3), np.uint8)
    for fps in (0, -1.0, float("nan")):
        with pytest.raises(ValueError, match=re.escape(f"{tmp_path / 'a.mp4'}: fps {fps!r}; expected a positive "
                                                       "frame rate")):
            write_mp4([ok], tmp_path / "a.mp4", fps=fps)
    with pytest.raises(ValueError, match=re.escape("clip.avi: videos are written as .mp4 (H.264) or .gif")):
        write_video([ok], "clip.avi")
    with pytest.raises(ValueError, match=re.escape("no frame to write: a video needs at least one frame")):
        _checked(iter([]))
    with pytest.raises(ValueError, match=re.escape("frame 0: float32 array of shape (4, 4, 3), expected (H, W, 3) uint8")):
        _checked([ok.astype(np.float32)])
    _, rest = _checked([ok, ok, np.zeros((4, 5, 3), np.uint8)])
    with pytest.raises(ValueError, match=re.escape("frame 2: shape (4, 5, 3), but frame 0 was (4, 4, 3); every frame "
                                                   "needs one size")):
        list(rest)
    assert not list(tmp_path.iterdir())


def test_gifs_loop_at_the_frame_rate_in_milliseconds_never_below_20(tmp_path):
    from PIL import Image

    from m3t.render.video import write_video

    frames = [np.full((6, 8, 3), v, np.uint8) for v in (0, 120, 240)]
    for fps, duration in ((10.0, 100), (25.0, 40), (100.0, 20), (4.0, 250)):  # GIF keeps centiseconds
        path = write_video(iter(frames), str(tmp_path / f"clip{int(fps)}.GIF"), fps=fps)
        assert path == tmp_path / f"clip{int(fps)}.GIF"
        with Image.open(path) as gif:
            assert gif.n_frames == 3 and gif.size == (8, 6) and gif.info["loop"] == 0
            assert gif.info["duration"] == duration
            gif.seek(1)
            assert np.asarray(gif.convert("RGB"))[0, 0].tolist() == [120, 120, 120]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip10.GIF", "clip100.GIF", "clip25.GIF", "clip4.GIF"]


def test_a_text_strip_centres_its_text_and_shrinks_then_cuts_long_text():
    import cv2

    from m3t.render.video import text_strip

    strip = text_strip("PT", 60, 24, color=(200, 0, 0))
    want = np.full((24, 60, 3), 255, np.uint8)
    (w, h), _ = cv2.getTextSize("PT", cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
    cv2.putText(want, "PT", ((60 - w) // 2, (24 + h) // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (200, 0, 0), 1, cv2.LINE_AA)
    assert strip.dtype == np.uint8 and np.array_equal(strip, want)
    assert text_strip("é", 30).shape == (20, 30, 3)  # non-ASCII drawn as '?', the default height
    assert np.array_equal(text_strip("é", 30), text_strip("?", 30))
    assert np.array_equal(text_strip("ab", 30), text_strip("ab", 30, color=(0, 0, 0)))
    # a long label in 40 px: shrunk to scale max(0.3, 0.45 * 36 / w), then cut by 4 characters plus '...' at a time
    text = "reconstruction of clip 12"
    (w0, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
    scale = max(0.3, 0.45 * 36 / w0)
    shown = text
    while cv2.getTextSize(shown, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] > 36:
        shown = shown[:-4] + "..." if len(shown) > 4 else ""
    assert shown.endswith("...") and len(shown) < len(text)
    (w, h), _ = cv2.getTextSize(shown, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    want = np.full((20, 40, 3), 255, np.uint8)
    cv2.putText(want, shown, ((40 - w) // 2, (20 + h) // 2), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)
    assert np.array_equal(text_strip(text, 40), want)
    assert (text_strip("abc", 3) == 255).all()  # nothing fits in 3 px: an empty strip


def test_side_by_side_labels_each_panel_and_titles_the_row_word_for_word():
    import re

    from m3t.render.video import LABEL_HEIGHT, side_by_side, text_strip

    a, b = np.zeros((8, 30, 3), np.uint8), np.full((8, 40, 3), 9, np.uint8)
    row = side_by_side([a, b], ["left", "right"], title="both")
    assert row.shape == (2 * LABEL_HEIGHT + 8, 30 + 4 + 40, 3)  # a 4 px gap by default
    assert np.array_equal(row[:LABEL_HEIGHT], text_strip("both", 74))
    assert np.array_equal(row[LABEL_HEIGHT:2 * LABEL_HEIGHT, :30], text_strip("left", 30))
    assert np.array_equal(row[LABEL_HEIGHT:2 * LABEL_HEIGHT, 34:], text_strip("right", 40))
    assert row.dtype == np.uint8 and (row[:, 30:34][LABEL_HEIGHT:] == 255).all()
    assert side_by_side([a, b], ["l", "r"], gap=-2).shape == (LABEL_HEIGHT + 8, 70, 3)  # no negative gap
    with pytest.raises(ValueError, match=re.escape(
            "side by side: 2 panels and 1 labels; expected as many, at least one")):
        side_by_side([a, b], ["l"])


def test_mesh_export_and_projection_by_hand(tmp_path):
    import re

    import trimesh

    from m3t.render.mesh import _project, export_mesh, project_camera

    verts, faces = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]]), np.array([[0, 1, 2]])
    with pytest.raises(ValueError, match=re.escape(f"{tmp_path / 'm.stl'}: mesh export supports .ply and .obj")):
        export_mesh(verts, faces, tmp_path / "m.stl")
    for name in ("deep/m.ply", "m.OBJ"):
        path = export_mesh(verts.tolist(), faces, str(tmp_path / name))
        assert path == tmp_path / name
        mesh = trimesh.load(path, process=False, force="mesh")
        np.testing.assert_allclose(mesh.vertices, verts)
        np.testing.assert_array_equal(mesh.faces, faces)
    camera = {"fx": 100.0, "fy": 50.0, "cx": 10.0, "cy": 20.0, "rotation": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
              "translation": [0.0, 0.0, 4.0]}
    uv, depth, cam = project_camera(np.array([[1.0, 0.0, 2.0], [0.0, -5.0, 0.0]]), camera)
    np.testing.assert_allclose(cam, [[1.0, -2.0, 4.0], [0.0, 0.0, -1.0]])
    np.testing.assert_allclose(depth, [4.0, 1e-3])  # behind the camera: clamped to 1 mm
    np.testing.assert_allclose(uv, [[10.0 + 100 / 4, 20.0 - 50 * 2 / 4], [10.0, 20.0]])
    # no camera: an orthographic front view (x = X, y = -Z) filling 90 % of the shorter side, centred
    uv, depth, cam = _project(verts, None, (200, 100))
    np.testing.assert_allclose(cam, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -2.0, 0.0]])
    np.testing.assert_allclose(uv, [[100 - 0.5 * 45, 50 + 45], [100 + 0.5 * 45, 50 + 45], [100 - 0.5 * 45, 50 - 45]])
    np.testing.assert_allclose(depth, 0.0)
    same = _project(verts, camera, (1, 1))
    np.testing.assert_allclose(same[0], project_camera(verts, camera)[0])


def test_render_mesh_writes_an_rgb_png_of_the_camera_size_or_512(tmp_path):
    import cv2

    from m3t.render.mesh import render_mesh

    verts = np.array([[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 0.0, 1.0]])  # facing -Y: seen from the front
    path = render_mesh(verts, np.array([[0, 1, 2]]), str(tmp_path / "front.png"))
    assert path == tmp_path / "front.png"
    picture = cv2.imread(str(path))[..., ::-1]  # BGR on disk
    assert picture.shape == (512, 512, 3) and (picture[0, 0] == 255).all()
    r, g, b = picture[400, 256].astype(int)  # the body colour (0.55, 0.7, 0.9), shaded: blue the strongest
    assert b > g > r and b < 255
    small = render_mesh(verts, np.array([[0, 1, 2]]), tmp_path / "s.png", size=(40, 30), color=(1.0, 0.0, 0.0))
    picture = cv2.imread(str(small))[..., ::-1]
    assert picture.shape == (30, 40, 3) and picture[15, 20, 0] > 200 and picture[15, 20, 1] == 0
    camera = {"fx": 20.0, "fy": 20.0, "cx": 12.0, "cy": 8.0, "rotation": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
              "translation": [0.0, 0.0, 4.0], "width": 24, "height": 16}
    seen = cv2.imread(str(render_mesh(verts, np.array([[0, 1, 2]]), tmp_path / "c.png", camera=camera)))
    assert seen.shape == (16, 24, 3) and (seen[8, 12] != 255).any() and (seen[0, 0] == 255).all()


def test_mesh_video_views_refuse_bad_input_word_for_word():
    import re

    from m3t.render.mesh_video import CameraView, front_views, render_mesh_video

    tri = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])
    for bad in (0, -0.5, 1.5):
        with pytest.raises(ValueError, match=re.escape(f"visible_height {bad}; expected a fraction in (0, 1]")):
            front_views({"a": tri}, 32, visible_height=bad)
    with pytest.raises(ValueError, match=re.escape("mesh video panel 'b': no finite vertex to frame the view on")):
        front_views({"a": tri, "b": np.full((1, 3, 3), np.nan)}, 32)
    with pytest.raises(ValueError, match=re.escape("mesh video camera lacks ['cy', 'fy']; expected fitting's camera "
                                                   "dict")):
        CameraView.fit({"fx": 1, "cx": 0, "rotation": 0, "translation": 0, "width": 4, "height": 2}, 10)
    view = CameraView.fit({"fx": 1, "fy": 1, "cx": 0, "cy": 0, "rotation": 0, "translation": 0, "width": 300,
                           "height": 1}, 64)
    assert (view.zoom, view.width, view.height) == (64 / 300, 64, 1)
    view = CameraView.fit({"fx": 1, "fy": 1, "cx": 0, "cy": 0, "rotation": 0, "translation": 0, "width": 60,
                           "height": 90}, 64)
    assert (view.zoom, view.width, view.height) == (64 / 90, 43, 64)
    with pytest.raises(ValueError, match="^mesh video: no sequence to render$"):
        render_mesh_video({}, np.array([[0, 1, 2]]), "m.mp4")
    with pytest.raises(ValueError, match=re.escape("mesh video panel 'g': vertices of shape (0, 3, 3), expected "
                                                   "(T, V, 3)")):
        render_mesh_video({"r": tri, "g": tri[:0]}, np.array([[0, 1, 2]]), "m.mp4")
    with pytest.raises(ValueError, match=re.escape("mesh video panel 'r': 3 vertices, but the faces index vertex 3; "
                                                   "the panels must be meshes of the body model these faces are of")):
        render_mesh_video({"r": tri}, np.array([[0, 1, 3]]), "m.mp4")


def test_front_views_share_one_scale_and_frame_the_top_of_each_body():
    """Z up: view y = -Z; a 2 m body framed at its top half is 1 m tall, scaled to 88 % of 100 px; the other
    panel, 1 m tall, gets the same scale and its own centre."""
    from m3t.render.mesh_video import Y_UP, Z_UP, front_views

    tall = np.array([[[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 2.0]]] * 2)
    short = tall * [1.0, 1.0, 0.5] + [3.0, 0.0, 0.0]
    views = front_views({"tall": tall, "short": short}, 100, visible_height=0.5)
    assert list(views) == ["tall", "short"] and views["tall"].rotation is Z_UP
    assert views["tall"].scale == pytest.approx(88.0) and views["short"].scale == views["tall"].scale
    np.testing.assert_allclose(views["tall"].centre, [0.0, -1.5])  # x of the vertices above the cut, y -2 .. -1
    np.testing.assert_allclose(views["short"].centre, [3.0, -0.75])
    assert (views["tall"].width, views["tall"].height) == (100, 100)
    screen, view = views["tall"].screen(tall[0])
    np.testing.assert_allclose(view, [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, -2.0, 0.0]])
    np.testing.assert_allclose(screen, [[50.0, 50 + 1.5 * 88, 0.0], [50 + 0.5 * 88, 50 + 1.5 * 88, 0.0],
                                        [50.0, 50 - 0.5 * 88, 0.0]])
    y_up = front_views({"a": tall[..., [0, 2, 1]]}, 100)["a"]
    assert y_up.rotation is Y_UP and y_up.scale == pytest.approx(100 * 0.88 / (0.6 * 2))


def test_mesh_video_frames_by_hand(monkeypatch, capsys):
    """Each frame: the panels' pictures (front views, or the fitted camera's) under their labels and the title;
    a finished panel holds its last picture; ``max_frames`` cuts; the rate and target are handed on."""
    from m3t.render import mesh_video
    from m3t.render.video import side_by_side

    out = {}
    monkeypatch.setattr(mesh_video, "write_video",
                        lambda frames, path, fps: out.update(frames=list(frames), path=path, fps=fps) or path)
    faces = np.array([[0, 1, 2]])
    long, short = tall_triangle(4, "z"), tall_triangle(2, "z") + [0.0, 0.0, 0.2]
    assert mesh_video.render_mesh_video({"ref": long, "gen": short}, faces, "m.mp4", fps=8.0, size=24,
                                        title="T", visible_height=0.8) == "m.mp4"
    assert out["path"] == "m.mp4" and out["fps"] == 8.0 and capsys.readouterr().err == ""
    views = mesh_video.front_views({"ref": long, "gen": short}, 24, 0.8)
    assert len(out["frames"]) == 4
    for t, frame in enumerate(out["frames"]):
        panels = [mesh_video.render_mesh_frame(long[t], faces, views["ref"]),
                  mesh_video.render_mesh_frame(short[min(t, 1)], faces, views["gen"])]
        assert np.array_equal(frame, side_by_side(panels, ["ref", "gen (2/2)" if t >= 2 else "gen"], "T"))
    camera = {"fx": 20.0, "fy": 20.0, "cx": 12.0, "cy": 8.0, "rotation": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
              "translation": [0.0, -1.0, 4.0], "width": 24, "height": 16}
    mesh_video.render_mesh_video({"ref": long}, faces, "c.gif", size=48, camera=camera, max_frames=3, progress=True)
    assert out["fps"] == 25.0 and len(out["frames"]) == 3 and "render c.gif" in capsys.readouterr().err
    view = mesh_video.CameraView.fit(camera, 48)
    for t, frame in enumerate(out["frames"]):
        assert np.array_equal(frame, side_by_side([mesh_video.render_mesh_frame(long[t], faces, view)], ["ref"]))
    assert (out["frames"][0] != 255).any(-1)[20:].sum() > 10  # the triangle is in the picture


def test_a_fitted_frame_is_logged_as_a_ply_and_a_png_under_the_artifact_path(tmp_path):
    """The asked frame of the clip is posed (only it: a one-frame batch), written as ``<stem>_<frame:05d>``
    ``.ply`` and ``.png``, both handed to the run under ``artifact_path``."""
    from types import SimpleNamespace

    import cv2
    import torch
    import trimesh

    from m3t.render.mesh import log_fitted_frame

    class Body:
        faces = np.array([[0, 1, 2]])

        def forward(self, params, identity):
            assert identity.dtype == torch.float32 and params["body"].shape == (1, 3)
            x = params["body"][:, :1]  # (1, 1): the frame's value moves the triangle along X
            base = torch.tensor([[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
            return SimpleNamespace(vertices=base[None] + torch.cat([x, 0 * x, 0 * x], 1)[:, None])

    class Run:
        def __init__(self):
            self.logged = []

        def log_artifact(self, path, artifact_path):
            self.logged.append((path, artifact_path))

    run, params = Run(), {"body": np.arange(9.0).reshape(3, 3)}
    paths = log_fitted_frame(run, Body(), params, np.zeros(2), 2, tmp_path / "out", stem="clip")
    assert paths == [tmp_path / "out" / "clip_00002.ply", tmp_path / "out" / "clip_00002.png"]
    assert run.logged == [(p, "meshes") for p in paths]
    mesh = trimesh.load(paths[0], process=False, force="mesh")
    np.testing.assert_allclose(mesh.vertices[:, 0], [5.0, 7.0, 6.0])
    np.testing.assert_array_equal(mesh.faces, Body.faces)
    assert paths[1].read_bytes()[:4] == b"\x89PNG"
    run = Run()
    camera = {"fx": 20.0, "fy": 20.0, "cx": 12.0, "cy": 8.0, "rotation": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
              "translation": [-6.0, 0.0, 8.0], "width": 24, "height": 16}
    paths = log_fitted_frame(run, Body(), params, np.zeros(2), 2, tmp_path, camera=camera, artifact_path="fit")
    assert [p.name for p in paths] == ["fit_00002.ply", "fit_00002.png"] and run.logged[0][1] == "fit"
    assert cv2.imread(str(paths[1])).shape == (16, 24, 3)  # seen through the camera
