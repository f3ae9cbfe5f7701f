"""Body-model invariants: layout dims, rest pose, full vs sparse forward, mirroring, 6D round trips."""
from __future__ import annotations

import numpy as np
import pytest
import roma
import torch
from builders import random_params

from m3t.body.protocol import Correspondence
from m3t.body.rotations import (
    identity_6d,
    matrix_to_6d,
    mirror_rotations,
    sixd_to_matrix,
)


def test_the_model_is_built_to_the_same_bits_whatever_the_thread_count():
    """Processes differ in their thread count (spawned fit workers run one): every built buffer must not."""
    from m3t.body.anny_body import AnnyBody

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        two = AnnyBody()
        torch.set_num_threads(1)
        one = AnnyBody()
        assert torch.get_num_threads() == 1  # the build restores the caller's count
    finally:
        torch.set_num_threads(before)
    for (name, a), (_, b) in zip(two.named_buffers(), one.named_buffers(), strict=True):
        assert torch.equal(a, b), name


def test_layout_dims(body):
    assert body.layout.dims == {"body": 72, "left_hand": 90, "right_hand": 90, "face": 52}
    assert body.layout.identity_dim == 6
    assert body.layout["left_hand"].mirror_of == "right_hand"
    for m in body.layout.modalities:
        if m.kind == "rotation6d":
            assert all(label in body.joint_names for label in m.labels)


def test_rest_pose_equals_template_skeleton(body):
    """Rest parameters reproduce the template skeleton and mesh, translated so the root sits at the origin."""
    out = body.forward(body.rest_params(1), body.default_identity())
    coeffs = body._identity_coeffs(body.default_identity())
    rest_heads = body._rest_bones(coeffs)[0, :, :3, 3]
    root = rest_heads[0]
    assert torch.allclose(out.joints[0, 0], torch.zeros(3), atol=1e-6)
    assert torch.allclose(out.joints[0], rest_heads - root, atol=1e-5)
    rest_vertices = body.template + torch.einsum("bn,nvc->bvc", coeffs, body.pheno_bs)[0]
    assert torch.allclose(out.vertices[0], rest_vertices - root, atol=1e-5)


def test_forward_matches_anny_reference(body):
    params = random_params(body, 3)
    identity = torch.tensor([0.2, 0.7, 0.4, 0.6, 0.3, 0.5])
    ours = body.forward(params, identity)
    delta = body.base_delta.expand(3, -1, -1, -1).clone()
    for m in body.layout.modalities:
        if m.kind == "rotation6d":
            idx = [body.joint_names.index(label) for label in m.labels]
            delta[:, idx, :3, :3] = sixd_to_matrix(params[m.name].reshape(3, -1, 6))
    ref = body._anny(pose_parameters=delta, phenotype_kwargs=identity[None], facial_actions=params["face"])
    assert torch.allclose(ours.vertices, ref["vertices"], atol=1e-5)
    assert torch.allclose(ours.joints, ref["bone_poses"][..., :3, 3], atol=1e-5)


def test_moving_one_body_leaves_the_others_where_they_are(body):
    """``.to()`` of one AnnyBody must not move the process-wide Anny instance every other body shares: a GPU
    fitter beside a CPU scorer failed with 'found at least two devices'. A dtype stands in for the device."""
    from m3t.body.anny_body import AnnyBody

    params = random_params(body, 2, seed=5)
    identity = torch.tensor([0.2, 0.7, 0.4, 0.6, 0.3, 0.5])
    before = body.forward(params, identity).vertices
    wide = AnnyBody().double()
    assert wide._anny is not body._anny and wide._anny.template_vertices.dtype == torch.float64
    out = wide.forward({k: v.double() for k, v in params.items()}, identity.double())
    assert out.vertices.dtype == torch.float64
    assert torch.allclose(out.vertices.float(), before, atol=1e-5)
    assert body._anny.template_vertices.dtype == torch.float32
    assert torch.equal(body.forward(params, identity).vertices, before)
    assert AnnyBody().double()._anny is wide._anny  # one copy per (device, dtype) and process


@pytest.mark.parametrize("reference", ["anny", "none"])
@pytest.mark.parametrize("per_frame_identity", [False, True])
def test_sparse_forward_equals_full_forward(body, monkeypatch, reference, per_frame_identity):
    """The keypoint path's own kinematics (matmul products) against Anny's full forward, with Anny's reference
    bone orientations and without (a rig that has none: the rest orientations serve), for one identity and
    for one per frame."""
    if reference == "none":
        monkeypatch.setitem(body._anny._buffers, "reference_bone_orientations", None)
    params = random_params(body, 2, seed=3)
    identity = torch.tensor([[0.2, 0.7, 0.4, 0.6, 0.3, 0.5], [0.8, 0.3, 0.5, 0.1, 0.9, 0.4]]) if per_frame_identity \
        else body.default_identity()
    vertices = np.array([0, 100, 5000, 13000, 7777])
    bones = np.array([body.joint_names.index(n) for n in ("wrist.L", "head", "finger2-3.R")])
    corr = Correspondence(
        tuple(str(i) for i in range(9)),
        np.array([0] * 5 + [1] * 3 + [-1]),
        np.concatenate([vertices, bones, [0]]),
    )
    sparse = body.forward_keypoints(params, identity, body.keypoint_set(corr))
    full = body.forward(params, identity)
    assert torch.allclose(sparse[:, :5], full.vertices[:, vertices], atol=1e-5)
    assert torch.allclose(sparse[:, 5:8], full.joints[:, bones], atol=1e-5)
    assert torch.all(sparse[:, 8] == 0)  # no correspondence -> nothing invented


def test_mirroring_twice_is_identity_and_matches_geometry(body):
    params = random_params(body, 4, seed=5)
    left = params["left_hand"]
    assert torch.allclose(mirror_rotations(mirror_rotations(left)), left)
    mirrored = dict(body.rest_params(4), right_hand=mirror_rotations(left), left_hand=left)
    out = body.forward(mirrored, body.default_identity())
    names = ["wrist"] + [f"finger{f}-{p}" for f in range(1, 6) for p in range(1, 4)]
    li = [body.joint_names.index(f"{n}.L") for n in names]
    ri = [body.joint_names.index(f"{n}.R") for n in names]
    reflect = torch.tensor([-1.0, 1.0, 1.0])
    assert torch.allclose(out.joints[:, li] * reflect, out.joints[:, ri], atol=1e-5)


@pytest.mark.parametrize("shape", [(5,), (2, 3)])
def test_6d_round_trip(shape):
    rot = roma.random_rotmat(shape)
    assert torch.allclose(sixd_to_matrix(matrix_to_6d(rot)), rot, atol=1e-6)
    assert torch.allclose(sixd_to_matrix(identity_6d(*shape)), torch.eye(3).expand(*shape, 3, 3))


def test_layout_check_rejects_wrong_dims(body):
    params = body.rest_params(2)
    params["face"] = torch.zeros(2, 10)
    with pytest.raises(ValueError, match="face"):
        body.layout.check(params)
    del params["face"]
    with pytest.raises(ValueError, match="lack"):
        body.layout.check(params)


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
