"""The synthetic corpus's motion and storage (:mod:`m3t.corpora.synthetic` and the modules it draws on) in detail:
the geometry of the signs (taps, circles, arcs, face curves, hand curls), signers that stand upright and face the
camera, hand targets in front of the body within reach, a subtle idle sway, performances within the jitter, clip
durations, and how the corpus is written (atomically, through a hidden temporary sibling folder). Written to pin
behaviours that mutation testing found unchecked.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import roma
import torch

from m3t.body.rotations import sixd_to_matrix
from m3t.corpora import (
    synthetic,
    synthetic_calibration,
    synthetic_face,
    synthetic_motion,
    synthetic_storage,
)
from m3t.corpora.clip import Clip
from m3t.corpora.config import SyntheticCorpusConfig
from m3t.corpora.synthetic_lexicon import HANDSHAPES, SignForm


# ----------------------------------------------------------------------------------------- synthetic motion
def _sign(movement: str, axis=(0.0, 0.0, 1.0), **kw) -> SignForm:
    fields = {"gloss": "HOUSE", "handshape": "flat", "location": "neutral", "movement": movement,
              "two_handed": False, "mouthing": ("a",), "brows": "none", "eyes": "none", "group": "normal",
              "pair": -1, "axis": tuple(axis)}
    return SignForm(**(fields | kw))


def test_tap_bends_the_elbow_by_a_bounded_non_negative_amount():
    """A tap bends the elbow (about one axis, never backwards) a few times by some degrees, in proportion to
    the signer's amplitude; the shoulder stays put."""
    frames, amplitude = 48, 1.1
    shoulder, elbow = synthetic_motion._movement(_sign("tap"), frames, amplitude)
    assert np.all(np.isfinite(elbow)) and np.all(shoulder == 0)
    assert np.all(elbow[:, 1:] == 0)  # the bend is about one axis
    bend = np.degrees(elbow[:, 0])
    assert bend.min() >= 0 and 5 * amplitude < bend.max() <= 12 * amplitude
    taps = np.sum((bend[1:] > 0) & (bend[:-1] == 0)) + (bend[0] > 0)
    assert taps == 3
    np.testing.assert_allclose(synthetic_motion._movement(_sign("tap"), frames, 2 * amplitude)[1], 2 * elbow)
    for other in ("straight", "arc", "circle", "repeat", "hold"):
        assert np.all(synthetic_motion._movement(_sign(other), frames, amplitude)[1] == 0)


@pytest.mark.parametrize("axis", [(0.0, 0.0, 1.0), (0.3, 0.2, 0.93), (-0.2, -0.3, -0.93), (0.6, 0.0, 0.8),
                                  (0.48, -0.6, 0.64)])
def test_circle_is_a_closed_loop_about_the_sign_axis_starting_at_a_body_anchored_phase(axis):
    """A circle turns the shoulder about directions perpendicular to the sign's axis, at a constant radius, and
    ends where it started; its phase is anchored to the body: it starts turning about a horizontal direction
    (or, for a near-vertical axis, a direction in the sagittal plane), the same for every performance."""
    axis = np.asarray(axis) / np.linalg.norm(axis)
    amplitude, frames = 0.9, 41
    shoulder, elbow = synthetic_motion._movement(_sign("circle", axis), frames, amplitude)
    np.testing.assert_allclose(shoulder @ axis, 0, atol=1e-12)
    radius = np.linalg.norm(shoulder, axis=1)
    np.testing.assert_allclose(radius, radius[0], rtol=1e-9)
    assert 3 * amplitude < np.degrees(radius[0]) < 12 * amplitude
    np.testing.assert_allclose(shoulder[0], shoulder[-1], atol=1e-12)
    start = shoulder[0]
    anchor = 0 if abs(axis[2]) >= 0.9 else 2  # left-right (x) or vertical (z) component of the start is 0
    assert abs(start[anchor]) < 1e-12
    assert np.all(elbow == 0)


def test_straight_arc_repeat_and_hold_turn_about_the_sign_axis():
    axis = np.array([0.6, 0.0, 0.8])
    s = {m: synthetic_motion._movement(_sign(m, axis), 21, 1.0)[0] for m in ("straight", "arc", "repeat", "hold")}
    for m in ("straight", "arc", "repeat"):
        np.testing.assert_allclose(np.cross(s[m], axis), 0, atol=1e-12)
        assert 3 < np.degrees(np.abs(s[m] @ axis).max()) < 12
    np.testing.assert_allclose(s["straight"][0], -s["straight"][-1])  # a sweep through the location
    np.testing.assert_allclose(s["straight"][10], 0, atol=1e-12)
    arc = s["arc"] @ axis
    assert np.all(arc >= -1e-12) and abs(arc[0]) < 1e-12 and abs(arc[-1]) < 1e-12 and arc.argmax() == 10
    repeat = s["repeat"] @ axis
    assert np.sum(np.diff(np.sign(repeat[1:-1])) != 0) == 3  # two back-and-forth strokes
    assert np.all(s["hold"] == 0)


def test_face_curve_shapes_mouthing_brows_and_blink_over_the_sign():
    """Visemes are raised-cosine bumps, one after the other; brows a plateau; a blink peaks mid-sign."""
    from m3t.corpora.synthetic_lexicon import BROWS, EYES, VISEMES

    labels = ("cheekPuff",) + tuple(sorted({a for table in (*VISEMES.values(), *BROWS.values(), *EYES.values())
                                           for a in table}))
    col = {name: i for i, name in enumerate(labels)}
    face = synthetic_face.face_curve(_sign("hold", mouthing=("a", "o"), brows="raise", eyes="blink"), 41, labels)
    assert face.shape == (41, len(labels)) and face.dtype == np.float32
    assert face.min() >= 0 and face.max() <= 1
    jaw, funnel = face[:, col["jawOpen"]], face[:, col["mouthFunnel"]]
    assert jaw[10] == pytest.approx(0.6) and jaw[30] == pytest.approx(0.3)  # peaks at 1/4 ("a") and 3/4 ("o")
    np.testing.assert_allclose(jaw[[0, 20, 40]], 0, atol=1e-6)  # each bump spans its half of the sign
    assert np.all(np.diff(jaw[:11]) > 0) and np.all(np.diff(jaw[10:21]) < 0)
    np.testing.assert_allclose(funnel[:21], 0, atol=1e-6)
    assert funnel[30] == pytest.approx(0.6)
    brow = face[:, col["browInnerUp"]]
    assert brow[0] == 0 and brow[-1] == 0 and np.allclose(brow[8:33], 0.7) and np.all(np.diff(brow[:9]) >= 0)
    blink = face[:, col["eyeBlinkLeft"]]
    assert blink[20] == pytest.approx(1.0) and blink.argmax() == 20 and blink[[0, 40]].max() < 1e-6
    np.testing.assert_array_equal(face[:, col["eyeBlinkLeft"]], face[:, col["eyeBlinkRight"]])
    for idle in ("cheekPuff", "eyeSquintLeft", "browDownLeft", "mouthPucker"):
        assert np.all(face[:, col[idle]] == 0)
    three = synthetic_face.face_curve(_sign("hold", mouthing=("m", "a", "u")), 31, labels)
    pucker = three[:, col["mouthPucker"]]  # "u" only: the last third
    np.testing.assert_allclose(pucker[:21], 0, atol=1e-6)
    assert pucker[25] == pytest.approx(0.8) and pucker[25] == pucker.max()
    squint = synthetic_face.face_curve(_sign("hold", eyes="squint"), 41, labels)[:, col["eyeSquintLeft"]]
    assert squint[20] == pytest.approx(0.6) and squint[0] == 0


def test_signers_stand_nearly_upright_with_varied_phenotypes():
    cfg = SyntheticCorpusConfig(num_signers=12)
    signers = synthetic._signers(cfg, np.random.default_rng(3))
    assert [s.id for s in signers] == [f"signer{i:02d}" for i in range(12)]
    tilt = np.degrees(np.linalg.norm(np.stack([s.posture for s in signers]), axis=1))
    assert tilt.max() < 15 and tilt.mean() < 8  # a few degrees of personal posture, never a lean
    speed, amplitude = np.array([s.speed for s in signers]), np.array([s.amplitude for s in signers])
    assert speed.min() >= 0.8 and speed.max() <= 1.25 and amplitude.min() >= 0.8 and amplitude.max() <= 1.2
    assert speed.min() < 0.95 and speed.max() > 1.1  # some sign slower, some faster than nominal
    assert amplitude.min() < 0.95 and amplitude.max() > 1.05  # some smaller, some larger
    assert all(s.identity.shape == (6,) and np.all((s.identity >= 0.2) & (s.identity <= 0.8)) for s in signers)
    assert len({s.identity.tobytes() for s in signers}) == 12


def _pixel(cam, point) -> np.ndarray:
    """Pixel (x right, y down) of a world point seen by ``cam``; the point must be in front of it."""
    c = np.asarray(cam.rotation) @ np.asarray(point, dtype=float) + np.asarray(cam.translation)
    assert c[2] > 0
    return np.array([cam.fx * c[0] / c[2] + cam.cx, cam.fy * c[1] / c[2] + cam.cy])


def test_camera_keeps_the_signer_upright_centred_and_framed_in_the_image():
    """Cameras look at the signer's upper body from the front (the body faces -y, z up), a little from either
    side: the signer is upright, centred, their left hand on the image's right, the signing space in frame."""
    rng = np.random.default_rng(5)
    yaws = []
    for _ in range(30):
        cam = synthetic._camera(rng, 256)
        rot, t = np.asarray(cam.rotation), np.asarray(cam.translation)
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(rot) > 0 and (cam.width, cam.height) == (256, 256)
        head, hips = _pixel(cam, [0.0, 0.0, 0.6]), _pixel(cam, [0.0, 0.0, 0.0])
        assert head[1] < hips[1] - 20  # image y points down: the head is above the hips
        assert abs(head[0] - hips[0]) < 0.1 * (hips[1] - head[1])  # the body axis is close to vertical
        left, right = _pixel(cam, [0.5, 0.0, 0.32]), _pixel(cam, [-0.5, 0.0, 0.32])
        assert left[0] > right[0]  # the signer faces the camera: their left (+x) is on the image's right
        assert 0.5 * 256 < left[0] - right[0]  # the signing space fills a good part of the image ...
        box = [_pixel(cam, [x, 0.0, z]) for x in (-0.5, 0.5) for z in (-0.1, 0.75)]
        assert all(0 <= u <= 256 and 0 <= v <= 256 for u, v in box)  # ... and lies inside it
        assert np.all(np.abs(_pixel(cam, [0.0, 0.0, 0.32]) - 128) < 0.1 * 256)
        eye = -rot.T @ t
        assert 2.1 < np.linalg.norm(eye - [0, 0, 0.32]) < 2.9 and eye[1] < 0  # in front of the signer
        yaws.append(np.degrees(np.arctan2(eye[0], -eye[1])))
    assert min(yaws) < -4 and max(yaws) > 4 and max(map(abs, yaws)) < 15  # from either side, never in profile


def _rest_calibration() -> synthetic_calibration.Calibration:
    from m3t.corpora.synthetic_lexicon import LOCATIONS

    return synthetic_calibration.Calibration(np.zeros((15, 3)), {k: np.zeros((4, 3)) for k in LOCATIONS}, np.zeros((4, 3)))


def test_idle_sway_is_subtle_and_centred_on_the_signers_posture(body):
    """The spine sways by under 2 degrees around the signer's own posture, once per clip."""
    cfg = SyntheticCorpusConfig()
    synth = synthetic_motion.Synthesiser(body, _rest_calibration(), cfg)
    posture = np.deg2rad([2.0, -1.0, 1.5])
    signer = synthetic_motion.Signer("s", np.full(6, 0.5), 1.0, 1.0, posture)
    params = synth.synthesise([_sign("hold"), _sign("tap")], signer)
    n = len(body.layout["body"].labels)
    rot = sixd_to_matrix(torch.as_tensor(params["body"]).reshape(-1, n, 6))  # (T, n, 3, 3)
    offset = roma.rotmat_to_rotvec(rot @ synth.rest["body"].transpose(-1, -2)).numpy()  # (T, n, 3)
    spine = offset[:, synth.spine]  # (T, 3 joints, 3)
    assert spine.shape[0] == params["face"].shape[0]
    np.testing.assert_allclose(spine.mean(0), np.broadcast_to(posture, (3, 3)), atol=2e-3)
    sway = np.degrees(np.linalg.norm(spine - posture, axis=-1))
    assert sway.max() < 2.0 and sway.max() > 0.5
    np.testing.assert_allclose(sway[[0, -1]], 0, atol=0.05)


# ----------------------------------------------------------------------------------------- writing the corpus
def _tiny_clip(i: int) -> synthetic_storage.SyntheticClip:
    clip = Clip(id=f"iso-house-signer00-{i}", corpus="synthetic", split="train", language="ISO-SYN",
                signer="signer00", text="家 (house)", gloss="HOUSE", media=f"motion/iso-house-signer00-{i}.npz", fps=25.0,
                label=0, extra=(("kind", "isolated"),))
    cam = synthetic._camera(np.random.default_rng(i), 64)
    return synthetic_storage.SyntheticClip(clip, {"body": np.full((3, 6), i, np.float32)}, np.full(6, 0.5, np.float32), cam)


def test_corpus_is_written_through_a_hidden_temporary_sibling(tmp_path, monkeypatch):
    root = tmp_path / "data" / "synthetic"
    (tmp_path / "data" / "other").mkdir(parents=True)
    seen = []
    real_replace = os.replace

    def spy(src, dst):
        seen.append((Path(src), Path(dst), sorted(os.listdir(Path(dst).parent))))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", spy)  # the swap is m3t.atomic.replace_dir's
    synthetic_storage.write_corpus([_tiny_clip(0)], root)
    (src, dst, entries), = seen
    assert dst == root and src.parent == root.parent and src.name.startswith(".synthetic.")
    assert [e for e in entries if not e.startswith(".")] == ["other"]  # no half-written corpus in plain sight
    assert sorted(os.listdir(root.parent)) == ["other", "synthetic"]
    reader = synthetic_storage.SyntheticCorpus(root)
    (clip,) = reader.clips()
    assert clip == _tiny_clip(0).clip
    assert "家 (house)" in (root / "clips.jsonl").read_text(encoding="utf-8")  # the index stays readable text
    params, identity, camera = reader.ground_truth(clip)
    np.testing.assert_array_equal(params["body"], np.zeros((3, 6), np.float32))
    assert camera == _tiny_clip(0).camera and identity.shape == (6,)

    seen.clear()
    synthetic_storage.write_corpus([_tiny_clip(1), _tiny_clip(2)], root)  # replaces the old corpus as a whole
    assert [s.name.startswith(".synthetic.") for s, _, _ in seen] == [False, True]  # old moved aside, new in
    assert [c.id for c in synthetic_storage.SyntheticCorpus(root).clips()] == ["iso-house-signer00-1", "iso-house-signer00-2"]
    assert sorted(os.listdir(root / "motion")) == ["iso-house-signer00-1.npz", "iso-house-signer00-2.npz"]
    assert sorted(os.listdir(root.parent)) == ["other", "synthetic"]


def test_failed_corpus_write_leaves_the_old_corpus_and_no_temporary_folder(tmp_path):
    root = tmp_path / "data" / "corpora" / "synthetic"  # folders created as needed
    synthetic_storage.write_corpus([_tiny_clip(0)], root)
    broken = _tiny_clip(1)
    broken = synthetic_storage.SyntheticClip(Clip(**{**broken.clip.__dict__, "media": "missing_dir/x.npz"}),
                                     broken.params, broken.identity, broken.camera)
    with pytest.raises(OSError):
        synthetic_storage.write_corpus([_tiny_clip(1), broken], root)
    assert sorted(os.listdir(root.parent)) == ["synthetic"]
    assert [c.id for c in synthetic_storage.SyntheticCorpus(root).clips()] == ["iso-house-signer00-0"]


# ----------------------------------------------------------------------------------------- synthetic corpus (2)
def test_hand_targets_lie_in_front_of_the_body_within_the_arms_reach(body):
    """The right hand's targets per location (body faces -y, z up, its right is -x) are reachable by the right
    arm, lie in front of the torso, and are ordered as the locations' names say."""
    targets, rest = synthetic_calibration._targets(body)
    with torch.no_grad():
        joints = body.forward(body.rest_params(1), body.default_identity()).joints[0].numpy()
    j = {n: joints[synthetic_calibration._joint(body, n)] for n in ("head", "neck01", "upperarm01.R", "upperarm01.L",
                                                       "lowerarm01.R", "wrist.R", "finger3-1.R")}
    chain = ("upperarm01.R", "lowerarm01.R", "wrist.R", "finger3-1.R")
    reach = sum(np.linalg.norm(j[b] - j[a]) for a, b in zip(chain, chain[1:]))  # shoulder to middle knuckle
    assert 0.45 < reach < 0.8
    front = j["neck01"][1]  # the body's midline depth; in front = smaller y
    for name, point in {**targets, "rest": rest}.items():
        assert np.linalg.norm(point - j["upperarm01.R"]) < 0.95 * reach, name
        assert 0.08 < front - point[1] < 0.45, name
    shoulder_z, head_z = j["upperarm01.R"][2], j["head"][2]
    chest = targets["chest"]
    assert shoulder_z - 0.3 < chest[2] < shoulder_z - 0.05 and abs(chest[0]) < 0.05  # on the sternum
    assert front - chest[1] < 0.3  # close to the chest: the hand touches it
    assert targets["neutral"][1] < chest[1] - 0.1  # the neutral signing space is further out
    assert targets["neutral_high"][2] - targets["neutral"][2] > 0.1
    assert rest[2] < targets["neutral"][2] < targets["chest"][2] < targets["chin"][2] < targets["forehead"][2]
    assert j["neck01"][2] < targets["chin"][2] < head_z < targets["forehead"][2]
    assert targets["cheek"][0] < -0.03 and targets["shoulder"][0] > 0.1  # own right cheek, the other shoulder
    assert all(point[0] < 0 for name, point in targets.items() if name.startswith("neutral"))


@pytest.mark.parametrize("axis", [(0.0, 0.0, 1.0), (0.3, 0.2, 0.93), (0.6, 0.0, 0.8), (0.48, -0.6, 0.64)])
def test_circle_turns_right_handedly_about_the_sign_axis(axis):
    """A circle's direction is part of the sign: it turns counter-clockwise seen from the tip of the sign's axis
    (a sign with the opposite axis circles the other way)."""
    axis = np.asarray(axis) / np.linalg.norm(axis)
    shoulder, _ = synthetic_motion._movement(_sign("circle", axis), 33, 1.0)
    turn = np.cross(shoulder[:-1], shoulder[1:]) @ axis
    assert np.all(turn > 0)
    back, _ = synthetic_motion._movement(_sign("circle", -axis), 33, 1.0)
    assert np.all(np.cross(back[:-1], back[1:]) @ -axis > 0)


def test_clip_index_records_without_extra_are_read_and_bad_lines_are_named(tmp_path):
    record = {k: v for k, v in _tiny_clip(0).clip.__dict__.items() if k != "extra"}
    index = tmp_path / "clips.jsonl"
    index.write_text(json.dumps(record, ensure_ascii=False) + "\n"
                     + json.dumps({**record, "id": "b", "extra": [["kind", "sentence"]]}) + "\n", encoding="utf-8")
    first, second = synthetic_storage.SyntheticCorpus(tmp_path).clips()
    assert first == Clip(**{**record, "extra": ()}) and second.extra == (("kind", "sentence"),)
    index.write_text(json.dumps(record) + "\n" + json.dumps({"id": "x"}) + "\n", encoding="utf-8")
    with pytest.raises(ValueError, match=rf"{index} line 2: not a clip record"):
        synthetic_storage.SyntheticCorpus(tmp_path).clips()


def test_make_corpus_writes_the_generated_clips_and_counts_them_per_split(tmp_path, monkeypatch):
    import m3t.body.factory as factory

    dev = _tiny_clip(2)
    dev = synthetic_storage.SyntheticClip(Clip(**{**dev.clip.__dict__, "split": "dev"}), dev.params, dev.identity, dev.camera)
    made = [_tiny_clip(0), _tiny_clip(1), dev]
    seen = {}
    monkeypatch.setattr(factory, "load_body_model", lambda cfg: seen.setdefault("body_cfg", cfg) and "model")
    monkeypatch.setattr(synthetic, "generate_corpus", lambda cfg, model: seen.update(cfg=cfg, model=model) or made)
    cfg = SyntheticCorpusConfig()
    assert synthetic.make_corpus(cfg, "the-body-config", tmp_path / "synthetic") == {
        "clips": 3, "splits": {"train": 2, "dev": 1}}
    assert seen == {"body_cfg": "the-body-config", "cfg": cfg, "model": "model"}
    assert [c.id for c in synthetic_storage.SyntheticCorpus(tmp_path / "synthetic").clips()] == [c.clip.id for c in made]


def test_a_performance_scales_speed_and_amplitude_within_the_jitter_and_tilts_each_posture_axis():
    signer = synthetic_motion.Signer("signer00", np.full(6, 0.5), 1.0, 2.0, np.array([0.1, -0.2, 0.3]))
    assert synthetic._performance(signer, np.random.default_rng(0), 0.0) is signer
    rng = np.random.default_rng(5)
    takes = [synthetic._performance(signer, rng, 0.2) for _ in range(200)]
    speed = np.array([t.speed for t in takes])
    amplitude = np.array([t.amplitude for t in takes]) / 2.0
    for factor in (speed, amplitude):
        assert 0.8 <= factor.min() < 0.85 and 1.15 < factor.max() <= 1.2
    offsets = np.stack([t.posture for t in takes]) - signer.posture
    assert offsets.shape == (200, 3) and np.all(np.abs(offsets) < np.deg2rad(5))
    assert np.allclose(offsets.std(axis=0), np.deg2rad(1.0), rtol=0.2)
    assert abs(np.corrcoef(offsets.T)[0, 1]) < 0.3  # each axis tilts on its own
    assert all(t.id == "signer00" and t.identity is signer.identity for t in takes)


def test_arm_calibration_puts_the_knuckle_on_each_target(body):
    """The right arm's inverse kinematics reaches the middle knuckle's targets to within a centimetre."""
    torch.set_num_threads(1)
    targets, rest_target = synthetic_calibration._targets(body)
    goal = np.stack([targets["chin"], rest_target])
    rest = synthetic_calibration.stream_rest(body)
    solved = synthetic_calibration._arm_ik(body, rest, goal, steps=150)
    assert solved.shape == (2, 4, 3)
    arm_idx = [body.layout["body"].labels.index(f"{b}.R") for b in synthetic_calibration.ARM]
    zeros = {k: torch.zeros(2, len(body.layout[k].labels), 3) for k in rest}
    zeros["body"][:, arm_idx] = torch.as_tensor(solved)
    with torch.no_grad():
        out = body.forward(synthetic_calibration.to_params(zeros, torch.zeros(2, body.layout["face"].dim), rest),
                           body.default_identity())
    knuckle = out.joints[:, synthetic_calibration._joint(body, "finger3-1.R")].numpy()
    assert np.linalg.norm(knuckle - goal, axis=-1).max() < 0.01


def test_a_clip_lasts_its_holds_signs_and_the_transitions_between_them(body):
    """Rest hold, each sign, rest hold, with a blend of ``transition_frames / speed`` (at least 2) frames before
    every segment but the first."""
    cfg = SyntheticCorpusConfig(hold_frames=5, frames_per_sign=10, transition_frames=3)
    synth = synthetic_motion.Synthesiser(body, _rest_calibration(), cfg)
    signs = [_sign("hold"), _sign("tap"), _sign("hold")]
    for speed, per_sign, transition in ((1.25, 8, 2), (0.5, 20, 6)):
        signer = synthetic_motion.Signer("s", np.full(6, 0.5), speed, 1.0, np.zeros(3))
        params = synth.synthesise(signs, signer)
        frames = 2 * 5 + len(signs) * per_sign + (len(signs) + 1) * transition
        assert {k: v.shape[0] for k, v in params.items()} == {k: frames for k in params}


def test_a_signs_hand_curls_each_finger_bone_about_its_flexion_axis(body):
    """Each of the 15 finger bones turns by 1.3 x its handshape curl (radians) about the calibrated axis."""
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(15, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    cal = synthetic_calibration.Calibration(axes, _rest_calibration().locations, np.zeros((4, 3)))
    synth = synthetic_motion.Synthesiser(body, cal, SyntheticCorpusConfig())
    signer = synthetic_motion.Signer("s", np.full(6, 0.5), 1.0, 1.0, np.zeros(3))
    for shape in ("fist", "C"):
        state = synth._sign_segment(_sign("hold", handshape=shape), 6, signer)
        curls = np.repeat(np.asarray(HANDSHAPES[shape]), 3)
        expected = 1.3 * curls[:, None] * axes
        assert state["right_hand"].shape == (6, 15, 3)
        np.testing.assert_allclose(state["right_hand"], np.broadcast_to(expected, (6, 15, 3)))
        np.testing.assert_allclose(np.linalg.norm(state["right_hand"][0], axis=1), 1.3 * curls)


def test_an_interrupt_while_removing_the_old_corpus_propagates_and_leaves_the_new_one(tmp_path, monkeypatch):
    root = tmp_path / "synthetic"
    synthetic_storage.write_corpus([_tiny_clip(0)], root)
    real_rmtree = shutil.rmtree

    def interrupted(path, *args, **kwargs):
        if Path(path).name == ".synthetic.old":
            raise KeyboardInterrupt
        return real_rmtree(path, *args, **kwargs)

    monkeypatch.setattr(synthetic_storage.shutil, "rmtree", interrupted)
    with pytest.raises(KeyboardInterrupt):
        synthetic_storage.write_corpus([_tiny_clip(1)], root)
    monkeypatch.undo()
    assert [c.id for c in synthetic_storage.SyntheticCorpus(root).clips()] == ["iso-house-signer00-1"]
