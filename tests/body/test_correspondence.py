"""The stored MediaPipe Holistic -> Anny correspondence (``m3t/body/data/anny_mediapipe_holistic.json``).

Checks the stored data only (no mediapipe needed): layout and order, sidedness of hand landmarks, that face
landmarks sit on the head, and that the face landmarks form a plausible face at Anny's rest pose.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from m3t.body.anny_body import DATA_DIR, load_correspondence
from m3t.body.landmarks import HAND_LANDMARKS as HAND_NAMES
from m3t.body.landmarks import POSE_LANDMARKS as POSE_NAMES
from tools.build_correspondence import N_FACE

PATH = DATA_DIR / "anny_mediapipe_holistic.json"
HEAD_BONES = ("head", "neck01", "neck02", "neck03")


@pytest.fixture(scope="module")
def spec():
    return json.loads(PATH.read_text())


@pytest.fixture(scope="module")
def rest_points(body):
    """(543, 3) rest-pose positions of all landmarks (zeros for null ones)."""
    keypoints = body.keypoint_set(body.correspondence("mediapipe_holistic"))
    with torch.no_grad():
        return body.forward_keypoints(body.rest_params(1), body.default_identity(), keypoints)[0].numpy()


def _mass_on(body, vertex: int, bones) -> float:
    """Skinning weight of ``vertex`` carried by bones satisfying the predicate ``bones(name)``."""
    names = body.joint_names
    return sum(float(w) for b, w in zip(body.skin_bones[vertex], body.skin_weights[vertex]) if bones(names[int(b)]))


def test_layout_and_order(spec, body):
    assert spec["landmark_set"] == "mediapipe_holistic"
    assert spec["how_made"]
    expected = (
        [f"pose:{n}" for n in POSE_NAMES]
        + [f"left_hand:{n}" for n in HAND_NAMES]
        + [f"right_hand:{n}" for n in HAND_NAMES]
        + [f"face:{i}" for i in range(N_FACE)]
    )
    assert len(expected) == 543
    assert [e["name"] for e in spec["landmarks"]] == expected
    assert POSE_NAMES[0] == "nose" and POSE_NAMES[-1] == "right_foot_index" and len(POSE_NAMES) == 33
    assert HAND_NAMES[0] == "wrist" and HAND_NAMES[-1] == "pinky_tip" and len(HAND_NAMES) == 21
    n_vert = body.template.shape[0]
    for e in spec["landmarks"]:
        assert not (e["vertex"] is not None and e["bone"] is not None), e
        if e["vertex"] is not None:
            assert 0 <= e["vertex"] < n_vert
        if e["bone"] is not None:
            assert e["bone"] in body.joint_names
    corr = load_correspondence(PATH, body.joint_names)
    assert len(corr.names) == 543


@pytest.mark.parametrize("prefix, side", [("left_hand", "L"), ("right_hand", "R")])
def test_hand_sidedness(spec, body, prefix, side):
    entries = [e for e in spec["landmarks"] if e["name"].startswith(prefix + ":")]
    assert len(entries) == 21
    for e in entries:
        if e["bone"] is not None:
            assert e["bone"].endswith(f".{side}"), e
        else:
            assert e["vertex"] is not None, e
            assert _mass_on(body, e["vertex"], lambda n: n.endswith(f".{side}")) > 0.5, e
    # MediaPipe's joints are bone heads; only the tips are vertices.
    assert [e["name"] for e in entries if e["vertex"] is not None] == [
        f"{prefix}:{d}_tip" for d in ("thumb", "index_finger", "middle_finger", "ring_finger", "pinky")
    ]


def test_pose_sidedness(spec, body, rest_points):
    for k, e in enumerate(spec["landmarks"][:33]):
        name = e["name"].removeprefix("pose:")
        if e["bone"] is not None:
            side = "L" if name.startswith("left_") else "R"
            assert e["bone"].endswith(f".{side}"), e
        if name.startswith("left_"):
            assert rest_points[k, 0] > 0.005, e  # subject's left = +X
        elif name.startswith("right_"):
            assert rest_points[k, 0] < -0.005, e
    pose = {e["name"].removeprefix("pose:"): rest_points[k] for k, e in enumerate(spec["landmarks"][:33])}
    assert pose["nose"][2] > pose["left_shoulder"][2] > pose["left_elbow"][2] > pose["left_hip"][2]
    assert pose["left_hip"][2] > pose["left_knee"][2] > pose["left_ankle"][2] > pose["left_heel"][2]
    assert pose["left_heel"][1] > pose["left_foot_index"][1]  # the heel is behind the toes (front = -Y)


def test_face_on_head(spec, body):
    faces = [e for e in spec["landmarks"][75:]]
    assert all(e["bone"] is None for e in faces)
    vertices = [e["vertex"] for e in faces if e["vertex"] is not None]
    for v in vertices:
        assert _mass_on(body, v, lambda n: n in HEAD_BONES) > 0.5, v
    assert len(set(vertices)) == len(vertices)  # no two landmarks share a vertex


def test_null_counts(spec):
    lms = spec["landmarks"]
    null = [e["vertex"] is None and e["bone"] is None for e in lms]
    assert sum(null[:33]) == 0
    assert sum(null[33:75]) == 0
    n_face_null = sum(null[75:])
    assert n_face_null <= 10
    stats = spec["stats"]
    assert stats["face_null"] == n_face_null
    assert stats["face_distinct_vertices"] == N_FACE - n_face_null
    assert stats["face_residual_median_mm"] < 4.0
    assert stats["face_residual_p95_mm"] < 8.0


def test_face_is_plausible_at_rest(spec, rest_points):
    face = rest_points[75:]
    valid = np.array([e["vertex"] is not None for e in spec["landmarks"][75:]])
    key = (0, 1, 10, 13, 14, 17, 33, 61, 133, 145, 152, 159, 263, 291, 362, 374, 386)
    assert valid[list(key)].all()
    x, y, z = face.T
    # subject's right is -X: right-eye / right-mouth landmarks have the smaller x
    assert x[33] < x[133] < 0 < x[362] < x[263]
    assert x[61] < 0 < x[291]
    # the nose tip is the frontmost (most -Y) of a few central landmarks
    central = (0, 1, 10, 13, 14, 17, 152, 168, 6, 9)
    assert min(central, key=lambda i: y[i]) == 1
    # vertical order: forehead > eyes > nose tip > upper lip > inner lips > lower lip > chin
    assert z[10] > z[159] > z[1] > z[0] > z[13] >= z[14] > z[17] > z[152]
    assert z[159] > z[145] and z[386] > z[374]  # upper eyelids above lower eyelids
    # a plausible size: outer eye corners 7-11 cm apart, mouth 3.5-6 cm wide
    assert 0.07 < x[263] - x[33] < 0.11
    assert 0.035 < x[291] - x[61] < 0.06
    # pose face points agree with the face mesh
    assert np.allclose(rest_points[9], face[291]) and np.allclose(rest_points[10], face[61])
