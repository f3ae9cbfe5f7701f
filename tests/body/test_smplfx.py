"""SMPL-FX invariants on synthetic SMPL-X / FLAME files (no licensed data), and on the real files when present.

Real files: set M3T_SMPLX_DIR (SMPLX_NEUTRAL.npz, SMPL-X__FLAME_vertex_ids.npy) and M3T_FLAME_DIR
(generic_model.pkl or an .npz conversion) to run the mesh-count test.
"""
from __future__ import annotations

import copy
import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import roma
import torch
from smplfx_fixtures import (
    front_camera_fx,
    smplfx_motion,
    write_chumpy_style_pickle,
)

from m3t.body.factory import BodyConfig, load_body_model
from m3t.body.model_files import ModelFileError, load_model_arrays
from m3t.body.protocol import Correspondence
from m3t.body.rotations import matrix_to_6d, mirror_rotations, sixd_to_matrix
from m3t.body.smplfx import TO_PROTOCOL_FRAME, SMPLFXBody, _depth_levels
from m3t.body.smplfx_build import SMPLFXFiles, SMPLFXFilesMissing
from m3t.fitting.evaluate import ground_truth_errors, joints_for, procrustes_error_mm
from m3t.fitting.fit import FittingConfig, fit_track
from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track


def to_frame(points: np.ndarray, root: np.ndarray) -> torch.Tensor:
    return torch.as_tensor((points - root) @ TO_PROTOCOL_FRAME.numpy().T, dtype=torch.float32)


def test_layout_matches_paper_eq1(fx):
    assert fx.layout.dims == {"body": 60, "left_hand": 90, "right_hand": 90, "face": 108}
    assert fx.layout.identity_dim == 110
    assert fx.layout["left_hand"].mirror_of == "right_hand" and fx.layout["right_hand"].mirror_of == "left_hand"
    assert len(fx.joint_names) == 44 and fx.joint_parents[0] == -1
    assert not {"pelvis", "left_knee", "spine1"} & set(fx.joint_names)
    for m in fx.layout.modalities:
        if m.kind == "rotation6d":
            assert all(label in fx.joint_names for label in m.labels)


def test_rest_pose_joints_equal_regressed_template(fx, fx_files):
    """At rest the joints are SMPL-X's regressor (FLAME's rows for the eyes) applied to the SMPL-FX mesh."""
    out = fx.forward(fx.rest_params(1), fx.default_identity())
    sx = load_model_arrays(fx_files.smplx)
    V = sx["v_template"].shape[0]
    jreg = sx["J_regressor"][[SMPLX_INDEX[n] for n in fx.joint_names if n not in ("left_eye", "right_eye")]]
    keep = [i for i, n in enumerate(fx.joint_names) if n not in ("left_eye", "right_eye")]
    regressed = torch.as_tensor(jreg, dtype=torch.float32) @ out.vertices[0, :V]
    assert torch.allclose(out.joints[0, keep], regressed, atol=1e-5)
    assert torch.allclose(out.joints[0, 0], torch.zeros(3), atol=1e-6)  # the root at the origin
    assert torch.allclose(out.vertices[0], to_frame(fx.data.template, fx.data.joint_template[0]), atol=1e-5)


def test_eyes_aligned_and_body_untouched(fx, fx_files):
    """Eye alignment: SMPL-FX eye joints sit on SMPL-X's; away from the head the mesh is SMPL-X's own."""
    sx = load_model_arrays(fx_files.smplx)
    joints_sx = sx["J_regressor"] @ sx["v_template"]
    eyes = [fx.joint_names.index(n) for n in ("left_eye", "right_eye")]
    assert np.allclose(fx.data.joint_template[eyes].mean(0), joints_sx[[23, 24]].mean(0), atol=1e-6)
    body = np.setdiff1d(np.arange(sx["v_template"].shape[0]), fx.data.head_vertices)
    assert np.allclose(fx.data.template[body], sx["v_template"][body], atol=1e-6)
    assert not np.allclose(fx.data.template[fx.data.head_vertices], sx["v_template"][fx.data.head_vertices], atol=1e-4)


def test_zero_expression_leaves_body_unchanged_and_expression_moves_head_only(fx):
    params = smplfx_motion(fx, frames=3)
    neutral = dict(params, face=params["face"].clone())
    neutral["face"][:, :102] = 0.0
    expressive = dict(params, face=params["face"].clone())
    expressive["face"][:, 102:] = neutral["face"][:, 102:]  # same jaw
    a = fx.forward(neutral, fx.default_identity()).vertices
    b = fx.forward(expressive, fx.default_identity()).vertices
    moved = np.flatnonzero((torch.linalg.norm(a - b, dim=-1) > 1e-7).any(0).numpy())
    assert moved.size > 0
    assert set(moved) <= set(fx.data.head_vertices.tolist())
    rest = fx.forward(fx.rest_params(1), fx.default_identity()).vertices
    zero = fx.forward(dict(fx.rest_params(1), face=fx.rest_params(1)["face"]), fx.default_identity()).vertices
    assert torch.equal(rest, zero)


def test_identity_split_between_body_and_head(fx):
    ident = fx.default_identity().clone()
    ident[:10] = 1.0  # SMPL-X betas only
    inner = fx.data.head_vertices[fx.data.smplx_ratio[fx.data.head_vertices] == 0]
    rest = fx.rest_params(1)
    a = fx.forward(rest, fx.default_identity()).vertices[0]
    b = fx.forward(rest, ident).vertices[0]
    centred = lambda x: x[inner] - x[inner].mean(0)  # noqa: E731 - the root (spine3) moves with body shape
    assert torch.allclose(centred(a), centred(b), atol=1e-6)  # SMPL-X shape zeroed on the head
    ident2 = fx.default_identity().clone()
    ident2[10:] = 1.0  # FLAME shape only
    c = fx.forward(rest, ident2).vertices[0]
    moved = np.flatnonzero((torch.linalg.norm(a - c, dim=-1) > 1e-6).numpy())
    teeth = np.arange(fx.data.num_smplx_vertices, fx.template.shape[0])
    assert moved.size and set(moved) <= set(fx.data.head_vertices.tolist()) | set(teeth.tolist())


def test_neck_ring_ratios_monotone(fx):
    ratios = [np.unique(fx.data.smplx_ratio[ring]) for ring in fx.data.neck_rings]
    assert all(r.size == 1 for r in ratios)
    values = np.array([r[0] for r in ratios])
    assert values[0] == pytest.approx(0.9) and values[-1] == pytest.approx(0.1)
    assert np.all(np.diff(values) < 0)
    ring_set = np.concatenate(fx.data.neck_rings)
    inner = np.setdiff1d(fx.data.head_vertices, ring_set)
    assert np.all(fx.data.smplx_ratio[inner] == 0)
    # Blended vertices lie between the SMPL-X and FLAME positions: the template moves monotonically.
    assert np.all(fx.data.smplx_ratio[: fx.data.num_smplx_vertices][np.setdiff1d(np.arange(fx.data.num_smplx_vertices), fx.data.head_vertices)] == 1)


def test_teeth_are_rigid_on_the_jaw(fx):
    n_teeth = fx.template.shape[0] - fx.data.num_smplx_vertices
    assert n_teeth == 520 and fx.faces.max() < fx.template.shape[0]
    rest = fx.rest_params(1)
    opened = {k: v.clone() for k, v in rest.items()}
    opened["face"][:, 102:] = matrix_to_6d(roma.rotvec_to_rotmat(torch.tensor([[0.3, 0.0, 0.0]])))
    opened["face"][:, :100] = 2.0  # expressions do not deform teeth
    a = fx.forward(rest, fx.default_identity()).vertices[0, fx.data.num_smplx_vertices:]
    b = fx.forward(opened, fx.default_identity()).vertices[0, fx.data.num_smplx_vertices:]
    upper, lower = slice(0, n_teeth // 2), slice(n_teeth // 2, None)
    assert torch.allclose(a[upper], b[upper], atol=1e-6)
    assert (torch.linalg.norm(a[lower] - b[lower], dim=-1) > 1e-3).all()
    def pairwise(x):
        return torch.linalg.norm(x[:, None] - x[None], dim=-1)

    d_rest, d_open = pairwise(a[lower]), pairwise(b[lower])
    assert torch.allclose(d_rest, d_open, atol=1e-5)  # rigid


def test_sparse_forward_equals_full_forward(fx):
    params = smplfx_motion(fx, frames=2, seed=3)
    ident = 0.5 * torch.randn(110, generator=torch.Generator().manual_seed(1))
    vertices = np.array([0, 100, 5000, int(fx.data.head_vertices[7]), fx.template.shape[0] - 1])
    joints = np.array([fx.joint_names.index(n) for n in ("left_wrist", "jaw", "right_thumb3")])
    corr = Correspondence(tuple(str(i) for i in range(9)), np.array([0] * 5 + [1] * 3 + [-1]),
                          np.concatenate([vertices, joints, [0]]))
    sparse = fx.forward_keypoints(params, ident, fx.keypoint_set(corr))
    full = fx.forward(params, ident)
    assert torch.allclose(sparse[:, :5], full.vertices[:, vertices], atol=1e-5)
    assert torch.allclose(sparse[:, 5:8], full.joints[:, joints], atol=1e-5)
    assert torch.all(sparse[:, 8] == 0)


def test_mirroring_hands(fx):
    params = smplfx_motion(fx, frames=4, seed=5)
    left = params["left_hand"]
    assert torch.allclose(mirror_rotations(mirror_rotations(left)), left)
    mirrored = dict(fx.rest_params(4), left_hand=left, right_hand=mirror_rotations(left))
    out = fx.forward(mirrored, fx.default_identity())
    names = ["wrist"] + [f"{f}{k}" for f in ("index", "middle", "pinky", "ring", "thumb") for k in (1, 2, 3)]
    li = [fx.joint_names.index(f"left_{n}") for n in names]
    ri = [fx.joint_names.index(f"right_{n}") for n in names]
    reflect = torch.tensor([-1.0, 1.0, 1.0])
    assert torch.allclose(out.joints[:, li] * reflect, out.joints[:, ri], atol=1e-5)


def test_6d_round_trip_of_smplfx_streams(fx):
    params = smplfx_motion(fx, frames=3, seed=2)
    for name in ("body", "left_hand", "right_hand"):
        six = params[name].reshape(3, -1, 6)
        assert torch.allclose(matrix_to_6d(sixd_to_matrix(six)), six, atol=1e-6)
    rest = fx.rest_params(2)
    assert torch.allclose(sixd_to_matrix(rest["face"][:, 102:]), torch.eye(3).expand(2, 3, 3))


def test_matches_smplx_package_away_from_the_head(fx, fx_files):
    """Arm and finger joints of the same rotations agree with smplx's own SMPL-X layer on the same file."""
    smplx = pytest.importorskip("smplx")
    layer = smplx.SMPLXLayer(str(fx_files.smplx), num_betas=10, num_expression_coeffs=10)
    params = smplfx_motion(fx, frames=2, seed=4)
    eye = torch.eye(3).expand(2, 21, 3, 3).clone()
    body_names = ("left_hip right_hip spine1 left_knee right_knee spine2 left_ankle right_ankle spine3 left_foot "
                  "right_foot neck left_collar right_collar head left_shoulder right_shoulder left_elbow right_elbow "
                  "left_wrist right_wrist").split()
    rot = sixd_to_matrix(params["body"].reshape(2, 10, 6))
    for k, n in enumerate(fx.layout["body"].labels):
        eye[:, body_names.index(n)] = rot[:, k]
    ref = layer(body_pose=eye, left_hand_pose=sixd_to_matrix(params["left_hand"].reshape(2, 15, 6)),
                right_hand_pose=sixd_to_matrix(params["right_hand"].reshape(2, 15, 6)))
    ours = fx.forward(params, fx.default_identity())
    names = [n for n in fx.joint_names if n.startswith(("left_", "right_")) and not n.endswith("eye")]
    smplx_idx = [SMPLX_INDEX[n] for n in names]
    root = ref.joints[:, SMPLX_INDEX["spine3"]][:, None]
    theirs = (ref.joints[:, smplx_idx] - root) @ TO_PROTOCOL_FRAME.T
    assert torch.allclose(ours.joints[:, [fx.joint_names.index(n) for n in names]], theirs, atol=1e-4)


@pytest.mark.slow
def test_fit_recovers_synthetic_smplfx(fx):
    params = smplfx_motion(fx, frames=12)
    identity = torch.zeros(110)
    identity[:10] = 0.3
    camera = front_camera_fx()
    track = simulate_track("fx-0", params, identity, camera, 25.0, fx, SimulatedTrackerConfig(seed=1, hand_dropout_prob=0.0))
    assert np.isfinite(track.keypoints[:, 33:54]).mean() > 0.9  # the hands are in view
    result = fit_track(track, fx, FittingConfig(iterations=150, camera_iterations=80, lr=0.02))
    truth = {k: v.numpy() for k, v in params.items()}
    errors = ground_truth_errors(fx, result.params, result.identity, result.camera, truth, identity.numpy(), camera.as_dict())
    with torch.no_grad():
        init_pa = procrustes_error_mm(joints_for(fx, track.init, fx.default_identity().numpy()),
                                      joints_for(fx, truth, identity.numpy()))
    assert result.metrics["reproj_px"] < 3.0
    assert errors["pa_joint_mm"] < 0.85 * init_pa
    assert result.loss_curve[-1] < 0.1 * result.loss_curve[0]


@pytest.mark.slow
def test_fit_corpus_runs_with_smplfx(fx_files, tmp_path):
    """fit-corpus end to end with ``body.model: smplfx`` (load_body_model) on a tiny SMPL-FX corpus."""
    from m3t.corpora.base import CorpusSource
    from m3t.corpora.clip import Clip
    from m3t.corpora.synthetic_storage import SyntheticClip, write_corpus
    from m3t.fitting.config import FitCorpusConfig, FitJob
    from m3t.fitting.corpus import run_fit_corpus

    cfg = BodyConfig(model="smplfx", smplx_path=str(fx_files.smplx), flame_path=str(fx_files.flame),
                     flame_correspondence_path=str(fx_files.correspondence))
    body = load_body_model(cfg)
    assert isinstance(body, SMPLFXBody)
    clips = []
    for i, split in enumerate(("train", "dev", "test")):
        params = {k: v.numpy() for k, v in smplfx_motion(body, frames=8, seed=i).items()}
        clip = Clip(f"fx-{i}", "synthetic", split, "ASL", "s0", "hello", "HELLO", f"motion/fx-{i}.npz", 25.0)
        clips.append(SyntheticClip(clip, params, np.zeros(110, dtype=np.float32), front_camera_fx()))
    write_corpus(clips, tmp_path / "corpus")
    job = FitJob("synthetic", CorpusSource(str(tmp_path / "corpus")), str(tmp_path / "shards"),
                 FitCorpusConfig(cache_dir=str(tmp_path / "cache"), workers=1), cfg,
                 FittingConfig(iterations=20, camera_iterations=10), SimulatedTrackerConfig(seed=0))
    report = run_fit_corpus(job, progress=False)
    assert report.summary["clips_quarantined"] == 0, [o.reason for o in report.outcomes]
    assert report.summary["clips_fitted"] == 3
    assert np.isfinite(report.summary["pa_joint_mm_mean"])


def test_missing_files_error_lists_each_file_and_source(tmp_path):
    cfg = BodyConfig(model="smplfx", smplx_path=str(tmp_path / "a.npz"), flame_path=str(tmp_path / "b.pkl"),
                     flame_correspondence_path=str(tmp_path / "c.npy"))
    with pytest.raises(SMPLFXFilesMissing) as err:
        load_body_model(cfg)
    msg = str(err.value)
    for needle in ("a.npz", "b.pkl", "c.npy", "smpl-x.is.tue.mpg.de", "flame.is.tue.mpg.de",
                   "SMPL-X__FLAME_vertex_ids.npy", "body.smplx_path", "body.flame_path"):
        assert needle in msg


def test_chumpy_pickle_reads_like_the_npz(fx_files):
    pkl = load_model_arrays(fx_files.flame)
    npz = load_model_arrays(fx_files.flame_npz)
    for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f"):
        np.testing.assert_allclose(pkl[key], npz[key])


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned > /dev/null",))


def test_malicious_model_pickle_refused(tmp_path):
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"v_template": np.zeros((3, 3)), "payload": _Evil()}, protocol=2))
    with pytest.raises(ModelFileError, match="refused global"):
        load_model_arrays(path)


def test_chumpy_expression_without_value_gives_conversion_route(fx_files, tmp_path):
    arrays = load_model_arrays(fx_files.flame_npz)
    path = tmp_path / "expr.pkl"
    write_chumpy_style_pickle(path, arrays, value_key="a")  # a Ch without its stored value 'x'
    with pytest.raises(ModelFileError, match="numpy.savez"):
        load_model_arrays(path)


SMPLX_INDEX = {n: i for i, n in enumerate(
    "pelvis left_hip right_hip spine1 left_knee right_knee spine2 left_ankle right_ankle spine3 left_foot right_foot "
    "neck left_collar right_collar head left_shoulder right_shoulder left_elbow right_elbow left_wrist right_wrist "
    "jaw left_eye right_eye".split() + [f"{s}_{f}{k}" for s in ("left", "right")
                                        for f in ("index", "middle", "pinky", "ring", "thumb") for k in (1, 2, 3)])}


def _real_files() -> SMPLFXFiles | None:
    sx, fl = os.environ.get("M3T_SMPLX_DIR"), os.environ.get("M3T_FLAME_DIR")
    if not sx or not fl:
        return None
    flame = next((p for p in (Path(fl) / "generic_model.pkl", Path(fl) / "flame2020.npz") if p.exists()), Path(fl) / "generic_model.pkl")
    return SMPLFXFiles(Path(sx) / "SMPLX_NEUTRAL.npz", flame, Path(sx) / "SMPL-X__FLAME_vertex_ids.npy")


@pytest.mark.skipif(_real_files() is None, reason="licensed SMPL-X / FLAME files not provided (M3T_SMPLX_DIR, M3T_FLAME_DIR)")
def test_real_files_give_the_papers_mesh():
    body = SMPLFXBody(_real_files())
    out = body.forward(body.rest_params(1), body.default_identity())
    assert out.vertices.shape[1] == 10_995  # Table A.1
    assert body.layout.dims == {"body": 60, "left_hand": 90, "right_hand": 90, "face": 108}
    assert body.correspondence("mediapipe_holistic").valid.sum() > 100


def test_mesh_export_and_picture_are_logged(fx, tmp_path):
    import trimesh
    from matplotlib.image import imread

    from m3t.render.mesh import export_mesh, log_fitted_frame

    class Run:
        def __init__(self):
            self.logged = []

        def log_artifact(self, path, artifact_path=None):
            self.logged.append((Path(path).name, artifact_path))

    params = {k: v.numpy() for k, v in smplfx_motion(fx, frames=3).items()}
    run = Run()
    paths = log_fitted_frame(run, fx, params, np.zeros(110, np.float32), 1, tmp_path, camera=front_camera_fx().as_dict())
    assert [name for name, _ in run.logged] == ["fit_00001.ply", "fit_00001.png"]
    mesh = trimesh.load(paths[0], process=False)
    assert mesh.vertices.shape == (fx.template.shape[0], 3) and mesh.faces.shape == fx.faces.shape
    image = imread(paths[1])
    assert image.shape[:2] == (512, 512) and (image[..., :3] < 0.95).any()  # something drawn on white
    obj = export_mesh(mesh.vertices, mesh.faces, tmp_path / "m.obj")
    assert trimesh.load(obj, process=False).vertices.shape[0] == fx.template.shape[0]


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


def test_smplfx_checkpoints_hold_no_model_geometry(fx):
    """The template, blend shapes and kinematic tree are rebuilt from the licensed model files, never saved."""
    state = fx.state_dict()
    assert fx.pose_dirs.numel() > 0 and fx.parents.numel() > 0
    assert "pose_dirs" not in state and "parents" not in state
    assert not any(t.numel() > 1000 for t in state.values())


def test_smplfx_names_the_landmark_sets_it_has_when_one_is_unknown(fx):
    with pytest.raises(FileNotFoundError) as info:
        fx.correspondence("openpose")
    assert str(info.value) == ("no landmark correspondence smplfx_openpose.json for body model 'smplfx'; available: "
                               "['mediapipe_holistic']")


def test_smplfx_body_passes_its_alignment_to_the_build(fx_files):
    files = SMPLFXFiles(fx_files.smplx, fx_files.flame_npz, fx_files.correspondence)
    with pytest.raises(ValueError, match="alignment 'nose' unknown; use 'eyes' or 'mean'"):
        SMPLFXBody(files, alignment="nose")


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
