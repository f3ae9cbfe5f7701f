"""The SMPL-FX build steps (m3t.body.smplfx_build) on the synthetic stand-in files of :mod:`smplfx_fixtures`: neck rings, teeth, 'eyes' and 'mean' alignments, head / jaw pose correctives from FLAME, the checks naming a model file that lacks keys or joints, expressions from FLAME's directions 300-400, the missing-files message and the eyelid buffers."""
from __future__ import annotations

import numpy as np
import pytest

from m3t.body.model_files import ModelFileError, load_model_arrays
from m3t.body.smplfx_build import (
    FLAME_JAW,
    FLAME_LEFT_EYE,
    FLAME_NECK,
    FLAME_RIGHT_EYE,
    POSED_JOINTS,
    SMPLX_JOINTS,
    SMPLFXFiles,
    build_smplfx,
)
from m3t.body.smplfx_geometry import neck_rings, teeth_geometry


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
