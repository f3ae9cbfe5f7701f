"""Behaviour details of the body models (m3t.body) that the coarser body, SMPL-FX and skeleton tests do not pin down.

Written to pin behaviours that mutation testing found unchecked: the skeleton graph's validation messages, Anny's
identity range and rest pose (a freshly built model reproduces its template), reading Python-2 model pickles,
SMPL-FX's skinning, depth levels and device handling, and the SMPL-FX build steps (neck rings, teeth, 'eyes' and
'mean' alignments, head / jaw pose correctives from FLAME, integer faces,
the checks naming a model file that lacks keys or joints, expressions from FLAME's directions 300-400), landmark
correspondences (Anny's available sets, the neck joint, skeleton graphs, SMPL-FX's resolved table), the body cache
key and protocol-0/1 pickles with sparse regressors. The SMPL-FX build tests use the synthetic stand-in files of
:mod:`smplfx_fixtures`.
"""
from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest
import roma
import torch
from corpus_fixtures import write_python2_pickle

from m3t.body.model_files import ModelFileError, load_model_arrays, load_pickle_safely
from m3t.body.rotations import matrix_to_6d
from m3t.body.skeleton import SkeletonGraph
from m3t.body.smplfx import TO_PROTOCOL_FRAME, SMPLFXBody, _depth_levels
from m3t.body.smplfx_build import (
    FLAME_JAW,
    FLAME_LEFT_EYE,
    FLAME_NECK,
    FLAME_RIGHT_EYE,
    POSED_JOINTS,
    SMPLX_JOINTS,
    SMPLFXFiles,
    build_smplfx,
    neck_rings,
    teeth_geometry,
)


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


# ------------------------------------------------------------------------------------------------ Anny
def test_anny_identity_is_bounded_to_the_phenotype_range(body):
    """Anny's six phenotype parameters live in [0, 1] (the fit clamps identity to these bounds)."""
    from m3t.body.anny_body import PHENOTYPES, AnnyBody

    model = AnnyBody()  # the Anny model itself is shared with the session's ``body``: cheap
    layout = model.layout
    assert layout.identity_labels == PHENOTYPES
    assert layout.identity_bounds == (0.0, 1.0)
    low, high = layout.identity_bounds
    ident = model.default_identity()
    assert ident.shape == (6,) and bool(((ident > low) & (ident < high)).all())
    assert layout["face"].bounds == (0.0, 1.0)


# ------------------------------------------------------------------------------------------------ model files
def test_python2_model_pickle_strings_are_read_as_latin1(tmp_path):
    """The pickle reads like FLAME 2020's ``generic_model.pkl``: a protocol-2 Python-2 pickle whose keys and array
    buffers are 8-bit strings. FLAME's readers (soubhiksanyal/FLAME_PyTorch ``flame.py``, Ribosome-rbx/PBNS
    ``preprocess.py`` for SMPL) load such files with ``pickle.load(f, encoding='latin1')``."""
    rng = np.random.default_rng(0)
    arrays = {"v_template": rng.normal(size=(5, 3)), "f": np.array([[0, 1, 2], [2, 3, 4]], dtype=np.uint32)}
    path = tmp_path / "generic_model.pkl"
    write_python2_pickle(path, {**arrays, "bs_style": "lbs", "author": "Ren\xe9e"}, "latin1")
    assert pickle.SHORT_BINSTRING + b"\x0av_template" in path.read_bytes()  # a Python 2 str, not unicode
    raw = load_pickle_safely(path)
    assert raw["bs_style"] == "lbs" and raw["author"] == "Ren\xe9e"  # 8-bit strings decoded as latin-1
    np.testing.assert_array_equal(raw["v_template"], arrays["v_template"])
    loaded = load_model_arrays(path, required=("v_template", "f"))
    assert sorted(loaded) == ["f", "v_template"]  # text entries are not arrays
    assert loaded["f"].dtype == np.uint32
    np.testing.assert_array_equal(loaded["f"], arrays["f"])
    with pytest.raises(ModelFileError, match=r"generic_model\.pkl lacks keys \['weights'\]"):
        load_model_arrays(path, required=("v_template", "weights"))


def test_model_file_reader_keeps_arrays_and_numbers_and_names_what_it_cannot_read(tmp_path):
    from scipy import sparse

    dense = np.array([[0.0, 0.5, 0.0], [0.25, 0.0, 0.75]])
    path = tmp_path / "model.pkl"
    with open(path, "wb") as fh:
        pickle.dump({"J_regressor": sparse.csr_matrix(dense), "nested": {"J": sparse.csc_matrix(dense)}, "scale": 2.5,
                     "ids": [1, 2, 3], "flag": True, "ragged": [[1], [2, 3]], "name": "x"}, fh, protocol=2)
    loaded = load_model_arrays(path)
    assert sorted(loaded) == ["J_regressor", "ids", "scale"]  # bools, ragged lists, text and dicts are no arrays
    np.testing.assert_array_equal(loaded["J_regressor"], dense)  # sparse -> dense
    assert loaded["scale"] == 2.5 and loaded["ids"].tolist() == [1, 2, 3]
    np.testing.assert_array_equal(load_pickle_safely(path)["nested"]["J"], dense)  # records inside dicts too
    coo = tmp_path / "coo.pkl"
    coo.write_bytes(pickle.dumps({"J_regressor": sparse.coo_matrix(dense)}, protocol=2))
    unsupported = r"coo\.pkl: key '<root>\.J_regressor' is a sparse matrix in an unsupported layout \('coo'\)"
    with pytest.raises(ModelFileError, match=unsupported):
        load_model_arrays(coo)
    listed = tmp_path / "list.pkl"
    listed.write_bytes(pickle.dumps([np.zeros(3)], protocol=2))
    with pytest.raises(ModelFileError, match=r"list\.pkl: expected a dict of arrays, found list"):
        load_model_arrays(listed)
    truncated = tmp_path / "truncated.pkl"
    truncated.write_bytes(path.read_bytes()[:40])
    with pytest.raises(ModelFileError, match=r"truncated\.pkl: pickle data was truncated; the file was not loaded"):
        load_model_arrays(truncated)
    (tmp_path / "empty.pkl").write_bytes(b"")
    with pytest.raises(ModelFileError, match=r"empty\.pkl: not a readable model pickle \(EOFError"):
        load_model_arrays(tmp_path / "empty.pkl")
    np.save(tmp_path / "ids.npy", np.arange(4))
    assert load_model_arrays(tmp_path / "ids.npy")["array"].tolist() == [0, 1, 2, 3]
    np.savez(tmp_path / "mixed.npz", v=np.ones(2), names=np.array([{"a": 1}], dtype=object))
    assert sorted(load_model_arrays(tmp_path / "mixed.npz")) == ["v"]  # object arrays are never unpickled
    with pytest.raises(ModelFileError, match=r"model\.obj: unsupported model file type '\.obj'"):
        (tmp_path / "model.obj").write_text("v 0 0 0\n")
        load_model_arrays(tmp_path / "model.obj")
    with pytest.raises(ModelFileError, match=r"model file .*absent\.npz does not exist"):
        load_model_arrays(tmp_path / "absent.npz")


# ------------------------------------------------------------------------------------------------ SMPL-FX model
@pytest.mark.slow
def test_depth_levels_group_joints_by_their_depth_below_the_root(fx):
    levels = _depth_levels(np.array([-1, 0, 0, 1, 3, 2, 0]))
    assert [lv.tolist() for lv in levels] == [[1, 2, 6], [3, 5], [4]]
    assert all(lv.dtype == torch.int64 for lv in levels)
    assert [lv.tolist() for lv in _depth_levels(np.array([-1, 0]))] == [[1]]
    # SMPL-FX's tree: every non-root joint in exactly one level, right after its parent's level.
    parents = np.asarray(fx.data.parents)
    levels = _depth_levels(parents)
    seen = np.concatenate([lv.numpy() for lv in levels])
    assert sorted(seen.tolist()) == [j for j in range(len(parents)) if parents[j] >= 0]
    level_of = {int(j): d + 1 for d, lv in enumerate(levels) for j in lv}
    level_of[int(np.flatnonzero(parents < 0)[0])] = 0
    assert all(level_of[j] == level_of[int(p)] + 1 for j, p in enumerate(parents) if p >= 0)


def test_rest_parameters_and_forward_follow_the_models_device(fx):
    """Parameters are made on the model's device (checked on PyTorch's 'meta' device, which needs no GPU)."""
    meta = copy.copy(fx)  # a shallow copy with its own buffer table: the shared model stays on the CPU
    meta._buffers = {k: v.to("meta") for k, v in fx._buffers.items()}
    rest = meta.rest_params(2)
    assert {k: v.device.type for k, v in rest.items()} == dict.fromkeys(fx.layout.names, "meta")
    assert {k: tuple(v.shape) for k, v in rest.items()} == {k: (2, d) for k, d in fx.layout.dims.items()}
    assert meta.default_identity().device.type == "meta"
    out = meta.forward(rest, meta.default_identity())
    assert out.vertices.device.type == "meta" and out.vertices.shape == (2, fx.template.shape[0], 3)
    assert fx.template.device.type == "cpu"
    cpu = fx.rest_params(2)
    assert cpu["face"].device.type == "cpu" and torch.count_nonzero(cpu["face"][:, :102]) == 0


def test_skinning_applies_each_joints_rigid_motion(fx):
    """Linear blend skinning: a point moves with the blend of its joints' rigid motions x -> R (x - c) + p
    (rotation R about the joint's rest position c, which lands at p); a common motion moves every point alike."""
    g = torch.Generator().manual_seed(0)
    n_joints, n_points = 4, 6
    points = torch.randn(2, n_points, 3, generator=g)
    rest_joints = torch.randn(1, n_joints, 3, generator=g)
    weights = torch.rand(n_points, n_joints, generator=g)
    weights = weights / weights.sum(1, keepdim=True)
    # A pure translation of the whole skeleton moves every point by exactly that translation.
    shift = torch.tensor([0.3, -0.2, 0.5])
    eye = torch.eye(3).expand(2, n_joints, 3, 3)
    moved = SMPLFXBody._skin(fx, points, weights, eye, rest_joints.expand(2, -1, -1) + shift, rest_joints)
    torch.testing.assert_close(moved, points + shift)
    # A common rigid motion (R, t): every point goes to R x + t, whatever its weights.
    rot = roma.rotvec_to_rotmat(torch.tensor([[0.2, -0.4, 0.7], [1.0, 0.1, -0.3]]))  # (2, 3, 3) one per frame
    pos = (rot[:, None] @ rest_joints[..., None])[..., 0] + shift  # (2, J, 3)
    moved = SMPLFXBody._skin(fx, points, weights, rot[:, None].expand(2, n_joints, 3, 3), pos, rest_joints)
    torch.testing.assert_close(moved, (rot[:, None] @ points[..., None])[..., 0] + shift)
    # One-hot weights: the point follows its joint's own motion.
    glob = roma.rotvec_to_rotmat(torch.randn(2, n_joints, 3, generator=g))
    pos = torch.randn(2, n_joints, 3, generator=g)
    one_hot = torch.nn.functional.one_hot(torch.arange(n_points) % n_joints, n_joints).float()
    moved = SMPLFXBody._skin(fx, points, one_hot, glob, pos, rest_joints)
    j = torch.arange(n_points) % n_joints
    expected = (glob[:, j] @ (points - rest_joints[:, j])[..., None])[..., 0] + pos[:, j]
    torch.testing.assert_close(moved, expected)


def test_upper_teeth_follow_the_head_rigidly_when_the_neck_turns(fx):
    """Upper teeth are skinned to the head alone: a neck rotation R carries them about the neck like the head,
    so their offsets from the head joint turn by R (in the protocol frame)."""
    params = fx.rest_params(1)
    rot = roma.rotvec_to_rotmat(torch.tensor([0.35, -0.5, 0.2]))
    body = params["body"].reshape(1, -1, 6).clone()
    body[0, fx.layout["body"].labels.index("neck")] = matrix_to_6d(rot)
    turned = dict(params, body=body.reshape(1, -1))
    ident = fx.default_identity()
    head = fx.joint_names.index("head")
    V = fx.data.num_smplx_vertices
    upper = slice(V, V + (fx.template.shape[0] - V) // 2)
    rest, posed = fx.forward(params, ident), fx.forward(turned, ident)
    in_frame = TO_PROTOCOL_FRAME @ rot @ TO_PROTOCOL_FRAME.T
    offsets = rest.vertices[0, upper] - rest.joints[0, head]
    torch.testing.assert_close(posed.vertices[0, upper] - posed.joints[0, head], offsets @ in_frame.T,
                               atol=1e-5, rtol=0)
    # ... and the head joint itself swings about the neck joint by R.
    neck = fx.joint_names.index("neck")
    torch.testing.assert_close(posed.joints[0, head] - posed.joints[0, neck],
                               (rest.joints[0, head] - rest.joints[0, neck]) @ in_frame.T, atol=1e-6, rtol=0)
    torch.testing.assert_close(posed.joints[0, neck], rest.joints[0, neck], atol=1e-6, rtol=0)


# ------------------------------------------------------------------------------------------------ SMPL-FX build
def _tube(rows: int, around: int, up: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """An open cylinder: ``rows`` rings of ``around`` vertices at heights up * 0.01 * row; both ends open."""
    angle = 2 * np.pi * np.arange(around) / around
    verts = np.array([(np.cos(a), up * 0.01 * r, np.sin(a)) for r in range(rows) for a in angle])
    faces = []
    for r in range(rows - 1):
        for k in range(around):
            a, b = r * around + k, r * around + (k + 1) % around
            faces += [(a, b, a + around), (b, b + around, a + around)]
    return verts, np.array(faces, dtype=np.int64)


def test_neck_rings_grow_from_the_lowest_open_boundary():
    verts, faces = _tube(rows=6, around=8)
    rings = neck_rings(verts, faces, 3)
    assert [r.tolist() for r in rings] == [list(range(r * 8, r * 8 + 8)) for r in range(3)]  # rows 0, 1, 2
    # Upside down, the neck (the boundary with the lowest mean height) is the other end.
    flipped = neck_rings(verts * [1.0, -1.0, 1.0], faces, 2)
    assert [r.tolist() for r in flipped] == [list(range(40, 48)), list(range(32, 40))]
    assert [r.size for r in neck_rings(verts, faces, 8)] == [8] * 6 + [0, 0]  # more rings than the mesh has rows
    tetrahedron = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]])
    with pytest.raises(ModelFileError, match="no open boundary"):
        neck_rings(np.eye(4, 3), tetrahedron, 3)


def _inner_lips() -> np.ndarray:
    """iBUG 61-68 (inner lip contour from the right mouth corner over the upper lip) in SMPL-X's frame (Y up,
    facing +Z), 4 cm wide."""
    return np.array([[-0.02, 1.50, 0.10], [-0.01, 1.503, 0.102], [0.0, 1.503, 0.103], [0.01, 1.503, 0.102],
                     [0.02, 1.50, 0.10], [0.01, 1.497, 0.102], [0.0, 1.497, 0.103], [-0.01, 1.497, 0.102]])


def test_teeth_arches_sit_behind_the_lips_mirrored_about_the_occlusal_plane():
    lips = _inner_lips()
    centre = lips.mean(0)
    verts, faces = teeth_geometry(lips)
    assert verts.shape == (520, 3) and faces.shape == (1000, 3) and faces.dtype == np.int64
    upper, lower = verts[:260], verts[260:]
    assert (upper[:, 1] > centre[1]).all() and (lower[:, 1] < centre[1]).all()
    np.testing.assert_allclose(upper[:, 1].mean() - centre[1], 0.007, atol=1e-9)
    # Mirror images about the horizontal plane through the lips' centre (profile point j <-> -j of each ring).
    mirrored = upper.reshape(26, 10, 3)[:, (10 - np.arange(10)) % 10] * [1.0, -1.0, 1.0] + [0.0, 2 * centre[1], 0.0]
    np.testing.assert_allclose(lower, mirrored.reshape(-1, 3), atol=1e-12)
    # A horseshoe opening backwards: the front 6 mm behind the lips (tube radius 3 mm), the ends 0.55 x the mouth
    # width to either side and 1.1 x that further back.
    half = 0.55 * 0.04
    spine = upper.reshape(26, 10, 3).mean(1)
    np.testing.assert_allclose(spine[[0, 25], 0] - centre[0], [-half, half], atol=1e-9)
    np.testing.assert_allclose(spine[[0, 25], 2], centre[2] - 0.006 - 1.1 * half, atol=1e-9)
    assert verts[:, 2].max() == pytest.approx(centre[2] - 0.006 + 0.003, abs=1e-4)
    assert np.argmax(spine[:, 2]) in (12, 13) and (np.diff(spine[:13, 2]) > 0).all()
    assert (faces[:500] < 260).all() and (faces[500:] >= 260).all() and faces.max() == 519  # each arch's own
    # A narrow mouth still gets arches 2 cm wide.
    narrow = lips * [0.1, 1.0, 1.0]
    verts, _ = teeth_geometry(narrow)
    np.testing.assert_allclose(verts.reshape(2, 26, 10, 3).mean(2)[0, [0, 25], 0], [-0.011, 0.011], atol=1e-9)


def test_teeth_faces_are_wound_counter_clockwise_seen_from_outside():
    """Outward normals on every tooth face, like the body mesh's (the shading and exported meshes rely on a
    consistent winding; it used to flip halfway along each arch)."""
    verts, faces = teeth_geometry(_inner_lips())
    spines = verts.reshape(2, 26, 10, 3).mean(2)  # each ring's centre on the arch's centre line
    arch, ring = faces[:, 0] // 260, (faces[:, 0] % 260) // 10
    assert (faces // 260 == arch[:, None]).all() and (((faces % 260) // 10 - ring[:, None]) <= 1).all()
    normal = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    outward = verts[faces].mean(1) - 0.5 * (spines[arch, ring] + spines[arch, ring + 1])
    assert (np.einsum("fc,fc->f", normal, outward) > 0).all()


@pytest.fixture(scope="module")
def fx_files(tmp_path_factory):
    from smplfx_fixtures import ensure_fixture_files

    return ensure_fixture_files(tmp_path_factory)


@pytest.mark.slow
def test_mean_alignment_moves_flame_by_the_mean_displacement(fx_files):
    """``alignment='mean'``: the FLAME head is moved by its mean displacement onto the corresponding SMPL-X
    vertices (instead of the eyes'); the built mesh has int64 faces, the teeth's after SMPL-X's."""
    files = SMPLFXFiles(fx_files.smplx, fx_files.flame_npz, fx_files.correspondence, fx_files.eyelids)
    data = build_smplfx(files, alignment="mean")
    sx, fl = load_model_arrays(fx_files.smplx), load_model_arrays(fx_files.flame_npz)
    corr = data.head_vertices
    offset = (sx["v_template"][corr] - fl["v_template"]).mean(0)
    eyes_sx = (sx["J_regressor"] @ sx["v_template"])[[23, 24]].mean(0)
    eyes = eyes_sx - (fl["J_regressor"] @ fl["v_template"])[[FLAME_LEFT_EYE, FLAME_RIGHT_EYE]].mean(0)
    assert np.linalg.norm(offset - eyes) > 1e-3  # the two alignments differ on these files
    ratio = data.smplx_ratio[corr][:, None].astype(np.float64)
    expected = ratio * sx["v_template"][corr] + (1 - ratio) * (fl["v_template"] + offset)
    np.testing.assert_allclose(data.template[corr], expected, atol=2e-6)
    inner = ratio[:, 0] == 0
    assert inner.sum() > 0.5 * len(corr)
    np.testing.assert_allclose((data.template[corr][inner] - fl["v_template"][inner]).astype(np.float64),
                               np.broadcast_to(offset, (int(inner.sum()), 3)), atol=2e-6)
    # Faces: SMPL-X's (uint32 in the file) as int64, then the teeth's, indexing the appended vertices.
    V = data.num_smplx_vertices
    n_body = len(sx["f"])
    assert data.faces.dtype == np.int64
    np.testing.assert_array_equal(data.faces[:n_body], sx["f"].astype(np.int64))
    assert data.faces[n_body:].min() >= V and data.faces.max() == data.template.shape[0] - 1
    with pytest.raises(ValueError, match="alignment 'nose' unknown; use 'eyes' or 'mean'"):
        build_smplfx(files, alignment="nose")


@pytest.mark.slow
def test_head_and_jaw_pose_correctives_come_from_flame(fx_files):
    """On the head, the head joint's pose correctives are FLAME's neck block and the jaw's FLAME's jaw block,
    blended with the neck ratio; the other posed joints keep only SMPL-X's (zero on the FLAME-only head)."""
    files = SMPLFXFiles(fx_files.smplx, fx_files.flame_npz, fx_files.correspondence, fx_files.eyelids)
    data = build_smplfx(files, n_rings=3)
    sx, fl = load_model_arrays(fx_files.smplx), load_model_arrays(fx_files.flame_npz)
    corr = data.head_vertices
    ratio = data.smplx_ratio[corr].astype(np.float64)
    assert sorted(np.unique(ratio).round(6).tolist()) == [0.0, 0.1, 0.5, 0.9]
    smplx_names = list(POSED_JOINTS)
    for name, flame_joint in (("head", FLAME_NECK), ("jaw", FLAME_JAW), ("neck", None), ("left_wrist", None)):
        k = smplx_names.index(name)
        block = data.pose_dirs[9 * k: 9 * (k + 1)][:, corr].astype(np.float64)  # (9, Vf, 3)
        j = SMPLX_JOINTS.index(name)
        expected = np.moveaxis(sx["posedirs"][corr][:, :, 9 * (j - 1): 9 * j], -1, 0) * ratio[None, :, None]
        if flame_joint is not None:
            flame_block = np.moveaxis(fl["posedirs"][:, :, 9 * (flame_joint - 1): 9 * flame_joint], -1, 0)
            assert np.abs(flame_block[:, ratio == 0]).max() > 1e-5
            expected = expected + flame_block * (1 - ratio)[None, :, None]
        np.testing.assert_allclose(block, expected, atol=1e-7, err_msg=name)
    assert np.all(data.pose_dirs[:, data.num_smplx_vertices:] == 0)  # teeth: rigid, no correctives


# ------------------------------------------------------------------------------------------------ correspondences
def test_anny_names_its_landmark_sets_when_one_is_unknown(body):
    from m3t.body.anny_body import AnnyBody

    with pytest.raises(FileNotFoundError) as err:
        AnnyBody.correspondence(body, "openpose_body25")
    message = str(err.value)
    assert "no landmark correspondence anny_openpose_body25.json for body model 'anny'" in message
    assert message.endswith("available: ['mediapipe_holistic']")  # set names, as one passes them back


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
    from m3t.body.skeleton import graph_correspondence

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


def test_smplfx_correspondence_resolves_joints_smplx_vertices_and_ibug_landmarks():
    from types import SimpleNamespace

    from m3t.body.smplfx import resolve_correspondence

    data = SimpleNamespace(num_smplx_vertices=100, landmark_vertices=np.arange(500, 551))  # iBUG 18..68
    spec = {"landmarks": [
        {"name": "neck", "joint": "neck"},
        {"name": "wrist", "smplx_vertex": 42},
        {"name": "lip", "smplx_vertex": 150, "ibug": 62},  # a head vertex SMPL-FX replaced: its iBUG landmark
        {"name": "brow", "ibug": 18},
        {"name": "ear", "smplx_vertex": 100},  # beyond SMPL-X's vertices, no landmark: none
        {"name": "tongue"},
    ]}
    corr = resolve_correspondence(spec, ("pelvis", "spine", "neck"), data)
    assert corr.names == ("neck", "wrist", "lip", "brow", "ear", "tongue")
    assert corr.kind.tolist() == [1, 0, 0, 0, -1, -1]
    assert corr.index.tolist() == [2, 42, 544, 500, 0, 0]
    assert corr.valid.tolist() == [True, True, True, True, False, False]
    empty = resolve_correspondence({"landmarks": []}, ("pelvis",), data)
    assert empty.names == () and empty.kind.dtype == np.int64 and empty.index.dtype == np.int64


# ------------------------------------------------------------------------------------------------ body cache key
def test_body_cache_key_hashes_the_model_files_and_ignores_the_cache_folder(tmp_path):
    import dataclasses
    import hashlib

    from m3t.body.config import BodyConfig
    from m3t.body.factory import body_cache_key

    assert body_cache_key(BodyConfig(model="anny")) == "anny"
    assert body_cache_key(BodyConfig(model="anny", cache_dir="elsewhere")) == "anny"
    smplx, flame = tmp_path / "SMPLX_NEUTRAL.npz", tmp_path / "generic_model.pkl"
    smplx.write_bytes(b"smplx v1.1")
    flame.write_bytes(b"flame 2020")
    cfg = BodyConfig(model="smplfx", smplx_path=str(smplx), flame_path=str(flame),
                     flame_correspondence_path=str(tmp_path / "absent.npy"))
    key = body_cache_key(cfg)
    assert key == {**dataclasses.asdict(cfg), "cache_dir": None,
                   "files": {"smplx_path": hashlib.sha256(b"smplx v1.1").hexdigest(),
                             "flame_path": hashlib.sha256(b"flame 2020").hexdigest(),
                             "flame_correspondence_path": "missing"}}
    # Anny's cache folder is no property of the SMPL-FX model: moving it keeps the cached fits.
    assert body_cache_key(dataclasses.replace(cfg, cache_dir="/elsewhere/anny")) == key
    assert body_cache_key(dataclasses.replace(cfg, flame_shape_dims=50)) != key
    flame.write_bytes(b"flame 2023")
    assert body_cache_key(cfg)["files"]["flame_path"] == hashlib.sha256(b"flame 2023").hexdigest()


# ------------------------------------------------------------------------------------------------ older model pickles
def test_protocol_0_and_1_pickles_with_sparse_regressors_keep_their_shape(tmp_path):
    """Pickle protocols 0 and 1 rebuild objects through ``copy_reg._reconstructor`` (what Python 2 wrote for
    them); a sparse regressor whose last rows / columns are empty keeps its stored shape (a vertex that no
    joint uses is still a column)."""
    from scipy import sparse

    dense = np.array([[0.0, 0.5, 0.0, 0.0], [0.25, 0.0, 0.75, 0.0], [0.0, 0.0, 0.0, 0.0]])  # last row, column empty
    model = {"J_regressor": sparse.csr_matrix(dense), "J_csc": sparse.csc_matrix(dense),
             "v_template": np.arange(6.0).reshape(2, 3), "parts": {"head", "neck"}, "fixed": frozenset({"jaw"})}
    for protocol in (0, 1):
        for python2_names in (True, False):  # copy_reg / __builtin__ (as Python 2 wrote) or copyreg / builtins
            path = tmp_path / f"model_p{protocol}_{python2_names}.pkl"
            path.write_bytes(pickle.dumps(model, protocol=protocol, fix_imports=python2_names))
            assert (b"copy_reg\n_reconstructor" if python2_names else b"copyreg\n_reconstructor") in path.read_bytes()
            loaded = load_model_arrays(path, required=("J_regressor", "v_template"))
            assert sorted(loaded) == ["J_csc", "J_regressor", "v_template"]
            for key in ("J_regressor", "J_csc"):
                assert loaded[key].shape == (3, 4), key
                np.testing.assert_array_equal(loaded[key], dense)
            np.testing.assert_array_equal(loaded["v_template"], np.arange(6.0).reshape(2, 3))
            raw = load_pickle_safely(path)
            assert raw["parts"] == {"head", "neck"} and raw["fixed"] == frozenset({"jaw"})
    import os

    evil = tmp_path / "evil.pkl"
    evil.write_bytes(pickle.dumps({"v_template": os.system}, protocol=2))
    with pytest.raises(ModelFileError, match=r"evil\.pkl: refused global (posix|nt)\.system: not an array or a known "
                                             r"model-file type; the file was not loaded"):
        load_model_arrays(evil)


# ------------------------------------------------------------------------------------------------ SMPL-FX layout
def test_smplfx_layout_defaults_to_the_papers_110_identity_coefficients():
    """M3T Eq. 1: 10 SMPL-X betas + 100 FLAME shape coefficients by default; the layout needs no model files."""
    from m3t.body.smplfx import smplfx_layout

    layout = smplfx_layout()
    assert layout.identity_dim == 110 and layout == smplfx_layout(100)
    assert layout.identity_labels[:2] == ("smplx_beta_0", "smplx_beta_1")
    assert layout.identity_labels[9:11] == ("smplx_beta_9", "flame_shape_000")
    assert layout.identity_labels[-1] == "flame_shape_099"
    assert layout.names == ("body", "left_hand", "right_hand", "face") and layout["face"].dim == 108
    assert smplfx_layout(20).identity_dim == 30


# ------------------------------------------------------------------------------------------------ SMPL-FX build checks
def _small_model_file(path, **arrays):
    """A model file holding every key SMPL-FX's build requires, tiny placeholders unless given."""
    from m3t.body.smplfx_build import SMPLX_REQUIRED

    np.savez(path, **{**{k: np.zeros((1, 1)) for k in SMPLX_REQUIRED}, **arrays})
    return path


def test_build_names_the_model_file_that_lacks_a_key_or_has_the_wrong_joints(fx_files, tmp_path):
    corr = np.load(fx_files.correspondence)
    files = SMPLFXFiles(tmp_path / "SMPLX_NEUTRAL.npz", fx_files.flame_npz, fx_files.correspondence)
    vertices = np.zeros((int(corr.max()) + 1, 3))
    np.savez(files.smplx, v_template=vertices, f=np.zeros((1, 3), np.int64), shapedirs=np.zeros((1, 1, 1)),
             J_regressor=np.zeros((55, 1)), weights=np.zeros((1, 55)), kintree_table=np.zeros((2, 55)))
    with pytest.raises(ModelFileError, match=r"SMPLX_NEUTRAL\.npz lacks keys \['posedirs'\]; found \[.*'weights'\]"):
        build_smplfx(files)
    joints = "expected SMPL-X with 55 joints and FLAME with 5 joints; check the model files"
    _small_model_file(files.smplx, v_template=vertices, J_regressor=np.zeros((24, 1)))  # SMPL's 24 joints
    with pytest.raises(ModelFileError, match=joints):
        build_smplfx(files)
    flame = _small_model_file(tmp_path / "flame.npz", v_template=np.zeros((len(corr), 3)), J_regressor=np.zeros((4, 1)))
    _small_model_file(files.smplx, v_template=vertices, J_regressor=np.zeros((55, 1)))
    with pytest.raises(ModelFileError, match=joints):
        build_smplfx(SMPLFXFiles(files.smplx, flame, fx_files.correspondence))
    np.savez(flame, **{k: v for k, v in load_model_arrays(flame).items() if k != "kintree_table"})
    with pytest.raises(ModelFileError, match=r"flame\.npz lacks keys \['kintree_table'\]"):
        build_smplfx(SMPLFXFiles(files.smplx, flame, fx_files.correspondence))
    # FLAME needs 300 shape + 100 expression directions, and the identity at most its 300 shapes.
    _small_model_file(flame, v_template=np.zeros((len(corr), 3)), J_regressor=np.zeros((5, 1)),
                      shapedirs=np.zeros((1, 1, 300)))
    with pytest.raises(ModelFileError, match=r"flame\.npz: FLAME 2020 has 300 shape \+ 100 expression directions; "
                                             r"found 300 \(flame_shape_dims=100\)"):
        build_smplfx(SMPLFXFiles(files.smplx, flame, fx_files.correspondence))
    _small_model_file(flame, v_template=np.zeros((len(corr), 3)), J_regressor=np.zeros((5, 1)),
                      shapedirs=np.zeros((1, 1, 400)))
    with pytest.raises(ModelFileError, match=r"found 400 \(flame_shape_dims=301\)"):
        build_smplfx(SMPLFXFiles(files.smplx, flame, fx_files.correspondence), flame_shape_dims=301)
    # The correspondence: one SMPL-X vertex per FLAME vertex, each inside SMPL-X's mesh.
    for name, ids in (("short.npy", corr[:-1]), ("negative.npy", np.concatenate([[-1], corr[1:]])),
                      ("beyond.npy", np.concatenate([[len(vertices)], corr[1:]]))):
        np.save(tmp_path / name, ids)
        low, high = int(ids.min()), int(ids.max())
        message = (rf"{name.replace('.', '[.]')}: expected {len(corr)} SMPL-X vertex indices in \[0, {len(vertices)}\) "
                   rf"\(one per FLAME vertex\), found shape \({len(ids)},\) with range \[{low}, {high}\]")
        with pytest.raises(ModelFileError, match=message):
            build_smplfx(SMPLFXFiles(files.smplx, flame, tmp_path / name))


@pytest.mark.slow
def test_expressions_are_flames_directions_300_to_400_even_when_the_file_has_more(fx_files, tmp_path):
    """FLAME 2020's shapedirs hold 300 shape then 100 expression directions; further ones are ignored, so the
    face stream keeps 100 expressions + 2 eyelids."""
    fl = load_model_arrays(fx_files.flame_npz)
    extra = np.random.default_rng(0).normal(scale=1e-3, size=(*fl["shapedirs"].shape[:2], 10))
    longer = tmp_path / "flame_410.npz"
    np.savez(longer, **{**fl, "shapedirs": np.concatenate([fl["shapedirs"], extra], axis=-1)})
    data = build_smplfx(SMPLFXFiles(fx_files.smplx, longer, fx_files.correspondence, fx_files.eyelids),
                        flame_shape_dims=20)
    V = data.num_smplx_vertices
    assert data.face_dirs.shape == (102, data.template.shape[0], 3)
    assert data.identity_dirs.shape == (30, data.template.shape[0], 3)
    corr = data.head_vertices
    flame_share = (1 - data.smplx_ratio[corr].astype(np.float64))[None, :, None]
    expressions = np.moveaxis(fl["shapedirs"][:, :, 300:400], -1, 0) * flame_share
    np.testing.assert_allclose(data.face_dirs[:100][:, corr], expressions, atol=1e-7)
    shapes = np.moveaxis(fl["shapedirs"][:, :, :20], -1, 0) * flame_share
    np.testing.assert_allclose(data.identity_dirs[10:][:, corr], shapes, atol=1e-7)
    assert not data.face_dirs[:, V:].any()  # teeth: no expressions


# ------------------------------------------------------------------------------------------------ small helpers
def test_euler_angles_become_the_6d_columns_of_the_same_rotation():
    from m3t.body.rotations import euler_to_6d

    angles = torch.tensor([[0.0, 0.0, torch.pi / 2], [0.3, -0.2, 0.1]])
    out = euler_to_6d(angles)
    assert out.shape == (2, 6)
    # A quarter turn about z: the first column is the y axis, the second minus the x axis.
    torch.testing.assert_close(out[0], torch.tensor([0.0, 1.0, 0.0, -1.0, 0.0, 0.0]), atol=1e-6, rtol=0)
    torch.testing.assert_close(out[1], matrix_to_6d(roma.euler_to_rotmat("XYZ", angles[1])), atol=1e-6, rtol=0)
    zyx = euler_to_6d(angles[1], convention="ZYX")
    torch.testing.assert_close(zyx, matrix_to_6d(roma.euler_to_rotmat("ZYX", angles[1])), atol=1e-6, rtol=0)


def test_skeleton_graph_rejects_an_edge_from_a_joint_to_itself():
    with pytest.raises(ValueError, match=r"skeleton 'loop': edges \[\(1, 1\)\] are not \(i, j\) with 0 <= i < j < 3"):
        SkeletonGraph("loop", ("body:neck", "body:nose", "face:4"), ((0, 1), (1, 1)))


def test_holistic_points_reject_an_array_whose_point_count_differs_from_the_names():
    from m3t.body.skeleton import holistic_points

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


def test_smplfx_checkpoints_hold_no_model_geometry(fx):
    """The template, blend shapes and kinematic tree are rebuilt from the licensed model files, never saved."""
    state = fx.state_dict()
    assert fx.pose_dirs.numel() > 0 and fx.parents.numel() > 0
    assert "pose_dirs" not in state and "parents" not in state
    assert not any(t.numel() > 1000 for t in state.values())


def test_missing_licensed_files_are_listed_with_their_setting_source_and_the_way_out(fx_files, tmp_path):
    from m3t.body.smplfx_build import SMPLFXFilesMissing

    files = SMPLFXFiles(fx_files.smplx, tmp_path / "generic_model.pkl", fx_files.correspondence, tmp_path / "lids")
    with pytest.raises(SMPLFXFilesMissing) as info:
        files.check()
    message = str(info.value)
    assert message.startswith("body.model 'smplfx' is built from licensed model files; missing:\n")
    assert f"  - body.flame_path = {tmp_path / 'generic_model.pkl'}: not found. Get FLAME 2020" in message
    assert f"  - body.eyelids_path = {tmp_path / 'lids'}: not found. Get optional:" in message
    assert "body.smplx_path" not in message and "body.flame_correspondence_path" not in message
    assert message.endswith("\nRegister and accept each licence on those sites, place the files there (or change the "
                            "paths in the body section of params.yaml), or use body.model: anny (embedded, open).")
    SMPLFXFiles(fx_files.smplx, fx_files.flame_npz, fx_files.correspondence).check()  # no eyelids: optional


@pytest.mark.slow
def test_all_300_flame_shape_directions_may_be_used_but_no_more(fx_files):
    files = SMPLFXFiles(fx_files.smplx, fx_files.flame_npz, fx_files.correspondence)
    assert build_smplfx(files, flame_shape_dims=300).identity_dirs.shape[0] == 310
    for bad in (301, -1):
        with pytest.raises(ModelFileError, match=rf"FLAME 2020 has 300 shape \+ 100 expression directions; "
                                                 rf"found \d+ \(flame_shape_dims={bad}\)"):
            build_smplfx(files, flame_shape_dims=bad)


def test_smplfx_names_the_landmark_sets_it_has_when_one_is_unknown(fx):
    with pytest.raises(FileNotFoundError) as info:
        fx.correspondence("openpose")
    assert str(info.value) == ("no landmark correspondence smplfx_openpose.json for body model 'smplfx'; available: "
                               "['mediapipe_holistic']")


def test_smplfx_body_passes_its_alignment_to_the_build(fx_files):
    files = SMPLFXFiles(fx_files.smplx, fx_files.flame_npz, fx_files.correspondence)
    with pytest.raises(ValueError, match="alignment 'nose' unknown; use 'eyes' or 'mean'"):
        SMPLFXBody(files, alignment="nose")


@pytest.mark.slow
def test_eyelid_buffers_read_from_one_npz_file_equal_the_two_npy_files(fx_files, tmp_path):
    """Pixel3DMM / VHAP ship ``l_eyelid.npy`` and ``r_eyelid.npy``; an ``.npz`` holding both keys is read the same."""
    lids = {side: np.load(fx_files.eyelids / f"{side}_eyelid.npy") for side in ("l", "r")}
    np.savez(tmp_path / "eyelids.npz", l_eyelid=lids["l"], r_eyelid=lids["r"])
    from_dir = build_smplfx(SMPLFXFiles(fx_files.smplx, fx_files.flame_npz, fx_files.correspondence, fx_files.eyelids))
    from_npz = build_smplfx(SMPLFXFiles(fx_files.smplx, fx_files.flame_npz, fx_files.correspondence,
                                        tmp_path / "eyelids.npz"))
    np.testing.assert_array_equal(from_npz.face_dirs[100:], from_dir.face_dirs[100:])
    assert np.abs(from_npz.face_dirs[100:]).max() > 0
    np.savez(tmp_path / "one_lid.npz", l_eyelid=lids["l"])
    with pytest.raises(ModelFileError, match=r"one_lid\.npz.*r_eyelid"):
        build_smplfx(SMPLFXFiles(fx_files.smplx, fx_files.flame_npz, fx_files.correspondence, tmp_path / "one_lid.npz"))


def test_the_body_factory_reads_the_eyelids_setting_and_names_an_unknown_model(fx_files, tmp_path):
    from m3t.body.config import BodyConfig
    from m3t.body.factory import load_body_model
    from m3t.body.smplfx_build import SMPLFXFilesMissing

    cfg = BodyConfig(model="smplfx", smplx_path=str(fx_files.smplx), flame_path=str(fx_files.flame_npz),
                     flame_correspondence_path=str(fx_files.correspondence), eyelids_path=str(tmp_path / "lids"))
    with pytest.raises(SMPLFXFilesMissing, match=r"body\.eyelids_path = .*lids: not found"):
        load_body_model(cfg)
    with pytest.raises(ValueError, match="body.model 'smpl' unknown; allowed: anny, smplfx"):
        load_body_model(BodyConfig(model="smpl"))


def test_anny_exposes_its_mesh_faces_over_its_template_vertices(body):
    faces = body.faces
    assert isinstance(faces, np.ndarray) and faces.ndim == 2 and faces.shape[1] in (3, 4) and len(faces) > 1000
    assert np.issubdtype(faces.dtype, np.integer)
    assert faces.min() == 0 and faces.max() == body.template.shape[0] - 1


def test_a_new_anny_model_reproduces_its_template_mesh_and_skeleton_at_rest(body):
    """Rest parameters give the template mesh (every vertex, the legs included) and the template skeleton, moved so
    that the root sits at the origin: every bone starts from its template rotation except the root's, which is
    the identity (the camera carries the global placement). Built afresh (the Anny model itself is shared with
    the session's ``body``), so the construction itself is checked."""
    from m3t.body.anny_body import AnnyBody

    model = AnnyBody()
    identity = model.default_identity()
    coeffs = model._identity_coeffs(identity)
    rest_bones = model._rest_bones(coeffs)[0]
    root = rest_bones[0, :3, 3]
    template = model.template + torch.einsum("bn,nvc->bvc", coeffs, model.pheno_bs)[0]
    out = model.forward(model.rest_params(1), identity)
    assert float(torch.linalg.norm(out.vertices[0] - (template - root), dim=-1).max()) < 1e-4  # 0.1 mm
    assert float(torch.linalg.norm(out.joints[0] - (rest_bones[:, :3, 3] - root), dim=-1).max()) < 1e-4
    leg_bones = ("pelvis", "upperleg", "lowerleg", "foot")
    legs = [i for i, name in enumerate(model.joint_names) if name.startswith(leg_bones)]
    assert len(legs) >= 6
    on_legs = (model.skin_weights * torch.isin(model.skin_bones, torch.tensor(legs))).sum(1) > 0.5
    assert int(on_legs.sum()) > 1000
    np.testing.assert_allclose(out.vertices[0, on_legs].numpy(), (template - root)[on_legs].numpy(), atol=1e-4)
    assert torch.equal(model.base_delta[0], torch.eye(4))
    # the template's own bone rotations are kept (the pelvis bones are tilted by a few degrees)
    pelvis = model.joint_names.index("pelvis.L")
    assert float(torch.linalg.norm(model.base_delta[pelvis, :3, :3] - torch.eye(3))) > 1e-2


@pytest.mark.slow
def test_eye_alignment_puts_the_flame_eyes_midpoint_on_smplx_eyes_on_every_axis(fx_files):
    """``alignment='eyes'`` (the default): the FLAME head is moved by the displacement of its eyes' midpoint onto
    SMPL-X's, axis by axis; the built mesh's eye joints (FLAME's rows) then sit on SMPL-X's eyes."""
    files = SMPLFXFiles(fx_files.smplx, fx_files.flame_npz, fx_files.correspondence, fx_files.eyelids)
    data = build_smplfx(files)
    sx, fl = load_model_arrays(fx_files.smplx), load_model_arrays(fx_files.flame_npz)
    eyes_sx = (sx["J_regressor"] @ sx["v_template"].astype(np.float64))[[23, 24]].mean(0)
    eyes_fl = (fl["J_regressor"] @ fl["v_template"].astype(np.float64))[[FLAME_LEFT_EYE, FLAME_RIGHT_EYE]].mean(0)
    assert np.ptp(eyes_sx) > 0.05 and np.ptp(eyes_sx - eyes_fl) > 0.05  # the axes differ on these files
    corr = data.head_vertices
    inner = data.smplx_ratio[corr] == 0  # pure FLAME vertices: moved by the offset alone
    assert inner.sum() > 0.5 * len(corr)
    np.testing.assert_allclose((data.template[corr][inner] - fl["v_template"][inner]).astype(np.float64),
                               np.broadcast_to(eyes_sx - eyes_fl, (int(inner.sum()), 3)), atol=2e-6)
    eyes = [data.joint_names.index(n) for n in ("left_eye", "right_eye")]
    np.testing.assert_allclose(data.joint_template[eyes].mean(0), eyes_sx, atol=1e-5)


def test_smplfx_rest_pose_mesh_is_the_template_plus_identity_expression_and_eyelid_offsets(fx):
    """At the rest pose a vertex is the template plus each coefficient times its direction (identity, the 100
    FLAME expressions and the two eyelids): the mesh moves by exactly ``c * direction`` in the protocol frame,
    for the full mesh and for the sparse vertex keypoints alike."""
    frame = TO_PROTOCOL_FRAME.to(fx.template.dtype)
    params = fx.rest_params(1)
    zero_id = fx.default_identity()
    base = fx.forward(params, zero_id).vertices[0]
    root = fx.joint_template[fx._root]
    torch.testing.assert_close(base, (fx.template - root) @ frame.T, atol=1e-6, rtol=0)

    face = params["face"].clone()
    face[0, 7], face[0, 100], face[0, 101] = 2.0, 0.8, -0.5  # an expression and both eyelids
    moved = fx.forward({**params, "face": face}, zero_id).vertices[0]
    offset = 2.0 * fx.face_dirs[7] + 0.8 * fx.face_dirs[100] - 0.5 * fx.face_dirs[101]
    assert offset.abs().max() > 1e-3  # the directions do move the face
    torch.testing.assert_close(moved - base, offset @ frame.T, atol=1e-6, rtol=0)

    corr = fx.correspondence("mediapipe_holistic")
    keypoints = fx.keypoint_set(corr)
    vert = keypoints.is_vertex & keypoints.valid.bool()
    vidx = keypoints.vertex_index[vert]
    kp_base = fx.forward_keypoints(params, zero_id, keypoints)[0, vert]
    kp_moved = fx.forward_keypoints({**params, "face": face}, zero_id, keypoints)[0, vert]
    torch.testing.assert_close(kp_moved - kp_base, offset[vidx] @ frame.T, atol=1e-6, rtol=0)
    torch.testing.assert_close(kp_moved, moved[vidx], atol=1e-6, rtol=0)

    identity = zero_id.clone()
    identity[3], identity[12] = 1.5, -2.0  # a SMPL-X beta and a FLAME shape coefficient
    shaped = fx.forward(params, identity).vertices[0]
    root_shift = 1.5 * fx.joint_identity_dirs[3, fx._root] - 2.0 * fx.joint_identity_dirs[12, fx._root]
    shape_offset = 1.5 * fx.identity_dirs[3] - 2.0 * fx.identity_dirs[12] - root_shift
    assert shape_offset.abs().max() > 1e-3
    torch.testing.assert_close(shaped - base, shape_offset @ frame.T, atol=1e-6, rtol=0)


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


@pytest.mark.slow
def test_the_body_factory_hands_the_flame_shape_count_to_smplfx_and_keeps_no_geometry_in_its_state(fx_files):
    from m3t.body.config import BodyConfig
    from m3t.body.factory import load_body_model

    cfg = BodyConfig(model="smplfx", smplx_path=str(fx_files.smplx), flame_path=str(fx_files.flame_npz),
                     flame_correspondence_path=str(fx_files.correspondence), flame_shape_dims=50)
    body = load_body_model(cfg)
    labels = body.layout.identity_labels
    assert len(labels) == 60 and labels[-1] == "flame_shape_049"  # 10 SMPL-X shapes + the 50 asked for
    # every buffer is rebuilt from the licensed files: a saved state would copy their geometry into checkpoints
    assert body.state_dict() == {} and len(list(body.buffers())) > 0


def test_landmark_vertices_take_each_faces_corner_of_largest_weight():
    from m3t.body.smplfx_build import _landmark_vertices

    smplx = {"f": np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]]), "lmk_faces_idx": np.array([2, 0, 1]),
             "lmk_bary_coords": np.array([[0.8, 0.1, 0.1], [0.1, 0.1, 0.8], [0.2, 0.7, 0.1]])}
    assert _landmark_vertices(smplx).tolist() == [6, 2, 4]
    with pytest.raises(ModelFileError) as info:
        _landmark_vertices({"f": smplx["f"], "lmk_faces_idx": smplx["lmk_faces_idx"]})
    assert str(info.value) == ("the SMPL-X file lacks 'lmk_faces_idx' / 'lmk_bary_coords' (the landmark embedding); "
                               "use SMPLX_NEUTRAL.npz from the SMPL-X v1.1 download")
