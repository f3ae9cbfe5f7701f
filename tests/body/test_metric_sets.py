"""The evaluation keypoint sets (SOKE's 12 upper-body points, 21 per hand, face vertices) for both body models."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from smplfx_fixtures import smplfx_motion

from m3t.body.metric_sets import (
    BODY_POINTS,
    HAND_POINTS,
    metric_keypoints,
    metric_points,
)


@pytest.fixture(params=["anny", "smplfx"])
def model(request, body, fx):
    return body if request.param == "anny" else fx


def test_sets_have_soke_sizes_and_are_complete(model):
    sets = metric_keypoints(model)
    assert set(sets) == {"body", "left_hand", "right_hand", "face"}
    assert sets["body"].names == BODY_POINTS and len(BODY_POINTS) == 12
    for side in ("left_hand", "right_hand"):
        hand = sets[side]
        assert hand.names == HAND_POINTS and len(hand.names) == 21
        assert hand.valid.all()
        assert hand.kind[0] == 1  # the wrist is a joint
        assert all(hand.kind[i] == 0 for i in (4, 8, 12, 16, 20))  # fingertips are vertices
    assert sets["body"].valid.all() and sets["body"].kind[0] == 1  # the neck joint
    assert len(sets["face"].index) > 50 and (sets["face"].kind == 0).all()


def test_sets_evaluate_through_the_sparse_forward(model):
    sets = metric_keypoints(model)
    params = model.rest_params(2)
    points = metric_points(model, params, model.default_identity(), sets)
    assert {k: tuple(v.shape) for k, v in points.items()} == {
        "body": (2, 12, 3), "left_hand": (2, 21, 3), "right_hand": (2, 21, 3), "face": (2, len(sets["face"].index), 3)}
    body = points["body"][0]
    # Consistency: the left wrist of the body set is the wrist of the left-hand set; the hands lie on the
    # subject's left (+x) / right (-x); fingertips are within a hand length of the wrist.
    assert torch.allclose(body[BODY_POINTS.index("left_wrist")], points["left_hand"][0, 0], atol=1e-6)
    assert points["left_hand"][0, :, 0].min() > 0 > points["right_hand"][0, :, 0].max()
    for side in ("left_hand", "right_hand"):
        reach = torch.linalg.norm(points[side][0] - points[side][0, :1], dim=-1)
        assert reach.max() < 0.25


def test_smplfx_face_vertices_are_on_the_flame_head(fx):
    face = metric_keypoints(fx)["face"].index
    teeth = range(fx.data.num_smplx_vertices, fx.template.shape[0])
    assert set(face.tolist()) <= set(fx.data.head_vertices.tolist()) | set(teeth)
    params = smplfx_motion(fx, frames=2)
    points = metric_points(fx, params, fx.default_identity())
    assert all(torch.isfinite(v).all() for v in points.values())


def test_anny_body_points_map_to_its_bones(body):
    sets = metric_keypoints(body)
    joints = {body.joint_names[i] for k, i in zip(sets["body"].kind, sets["body"].index) if k == 1}
    assert {"neck01", "upperarm01.L", "upperarm01.R", "lowerarm01.L", "wrist.R"} <= joints
    assert np.unique(sets["face"].index).size == sets["face"].index.size
