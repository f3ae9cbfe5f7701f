"""The Anny body model (m3t.body.anny_body): the identity bounded to the phenotype range, its landmark sets, its mesh faces, a freshly built model reproducing its template at rest, and the body cache key."""
from __future__ import annotations

import numpy as np
import pytest
import torch


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


# ------------------------------------------------------------------------------------------------ correspondences
def test_anny_names_its_landmark_sets_when_one_is_unknown(body):
    from m3t.body.anny_body import AnnyBody

    with pytest.raises(FileNotFoundError) as err:
        AnnyBody.correspondence(body, "openpose_body25")
    message = str(err.value)
    assert "no landmark correspondence anny_openpose_body25.json for body model 'anny'" in message
    assert message.endswith("available: ['mediapipe_holistic']")  # set names, as one passes them back


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
