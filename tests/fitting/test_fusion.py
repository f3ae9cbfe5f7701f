"""Tracker fusion for one corpus clip: outputs found beside the media, their digest, the fused initialisation
against known ground truth (all trackers, some of them, none), the body models that cannot take them, and
refinement around the fused initialisation."""
from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest
import torch
from fusion_fixtures import (
    NLF_MISSING,
    PIXEL3DMM_MISSING,
    WILOR_RIGHT_MISSING,
    T,
    output_paths,
    pixel3dmm_frame,
    rot_err_deg,
    write_clip,
    write_media,
)
from smplfx_fixtures import front_camera_fx

from m3t.body.anny_body import BODY_BONES, PHENOTYPES, hand_bones
from m3t.body.protocol import Modality, ModalityLayout
from m3t.fitting.config import FittingConfig, FusionConfig
from m3t.fitting.fit import FitResult, fit_track
from m3t.fitting.fusion import (
    FusionUnsupported,
    describe,
    initialise_from_trackers,
    refine,
)
from m3t.fitting.stream_fusion import HELD, INTERPOLATED, REST
from m3t.trackers.external import TrackerOutputs, find_tracker_outputs
from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track
from m3t.trackers.tracker_files import TrackerFileError

ALL = ("nlf", "wilor", "pixel3dmm")


def frames_except(*missing: int) -> list[int]:
    return [t for t in range(T) if t not in missing]


# ------------------------------------------------------------------------------------------- finding
@pytest.mark.parametrize("kind", ["video", "pose", "frames"])
@pytest.mark.parametrize("suffix", [".npz", ".pt"])
def test_find_tracker_outputs_finds_each_kind_and_nothing_else(fx, truth, tmp_path, kind, suffix):
    media = write_clip(tmp_path / "clips", fx, truth, kind=kind, suffix=suffix)
    stem = "abc"
    # Decoys: another clip's outputs, an unknown suffix, a name that only starts like the clip's.
    write_clip(tmp_path / "clips", fx, truth, trackers=("nlf",), kind="video", name="other")
    (tmp_path / "clips" / f"{stem}.nlf.json").write_text("{}")
    (tmp_path / "clips" / f"{stem}x.wilor.npz").write_bytes(b"")
    out = find_tracker_outputs(media)
    assert out == TrackerOutputs(nlf=tmp_path / "clips" / f"{stem}.nlf{suffix}",
                                 wilor=tmp_path / "clips" / f"{stem}.wilor{suffix}",
                                 pixel3dmm=tmp_path / "clips" / f"{stem}.pixel3dmm" / "checkpoint")
    assert out.names() == ALL and out.any()

    bare = write_media(tmp_path / "clips", "bare", kind)
    assert find_tracker_outputs(bare) == TrackerOutputs()
    assert not find_tracker_outputs(bare).any() and find_tracker_outputs(bare).digest() == "none"
    some = write_clip(tmp_path / "some", fx, truth, trackers=("pixel3dmm", "nlf"), kind=kind)
    assert find_tracker_outputs(some).names() == ("nlf", "pixel3dmm")


def test_frames_directly_in_the_pixel3dmm_folder_are_found(fx, truth, tmp_path):
    media = write_clip(tmp_path, fx, truth, trackers=("pixel3dmm",))
    folder = output_paths(media)["pixel3dmm"]
    for f in (folder / "checkpoint").iterdir():
        f.rename(folder / f.name)
    (folder / "checkpoint").rmdir()
    assert find_tracker_outputs(media).pixel3dmm == folder


def test_links_leaving_the_clip_folder_and_duplicates_are_refused(fx, truth, tmp_path):
    media = write_clip(tmp_path / "clips", fx, truth, trackers=("wilor",))
    outside = write_clip(tmp_path / "elsewhere", fx, truth, trackers=("nlf", "pixel3dmm"))
    paths, far = output_paths(media), output_paths(outside)
    paths["nlf"].symlink_to(far["nlf"])
    with pytest.raises(TrackerFileError, match="outside the clip's folder"):
        find_tracker_outputs(media)
    paths["nlf"].unlink()
    paths["pixel3dmm"].symlink_to(far["pixel3dmm"], target_is_directory=True)
    with pytest.raises(TrackerFileError, match="outside the clip's folder"):
        find_tracker_outputs(media)
    paths["pixel3dmm"].unlink()
    (paths["pixel3dmm"] / "checkpoint").mkdir(parents=True)
    (paths["pixel3dmm"] / "checkpoint" / "00000.frame").symlink_to(far["pixel3dmm"] / "checkpoint" / "00000.frame")
    with pytest.raises(TrackerFileError, match="outside the clip's folder"):
        find_tracker_outputs(media)
    shutil.rmtree(paths["pixel3dmm"])
    paths["nlf"].symlink_to(paths["wilor"].name)  # a link that stays beside the media is fine
    assert find_tracker_outputs(media).names() == ("nlf", "wilor")
    paths["nlf"].unlink()
    shutil.copy(paths["wilor"], paths["wilor"].with_suffix(".pt"))
    with pytest.raises(TrackerFileError, match="two wilor outputs"):
        find_tracker_outputs(media)


def test_digest_follows_the_bytes_the_readers_read(fx, truth, tmp_path):
    media = write_clip(tmp_path / "a", fx, truth)
    paths = output_paths(media)
    d0 = find_tracker_outputs(media).digest()
    assert d0 == find_tracker_outputs(write_clip(tmp_path / "b", fx, truth)).digest()  # same content, same digest
    (paths["pixel3dmm"] / "mesh" / "00000.ply").write_text("ply\n")  # not read: no refit
    assert find_tracker_outputs(media).digest() == d0

    frame_file = paths["pixel3dmm"] / "checkpoint" / "00003.frame"
    original = frame_file.read_bytes()
    row = pixel3dmm_frame(truth, 3)
    row["flame"]["exp"] = row["flame"]["exp"] + 0.01
    torch.save(row, frame_file)
    assert find_tracker_outputs(media).digest() != d0
    frame_file.write_bytes(original)
    assert find_tracker_outputs(media).digest() == d0
    frame_file.unlink()
    assert find_tracker_outputs(media).digest() != d0
    frame_file.write_bytes(original)

    data = dict(np.load(paths["nlf"]))
    data["betas"] = data["betas"] + 1e-3
    np.savez(paths["nlf"], **data)
    assert find_tracker_outputs(media).digest() != d0


# ------------------------------------------------------------------------------------------- fusing
@pytest.mark.parametrize("suffix", [".npz", ".pt"])
def test_initialise_from_trackers_recovers_the_ground_truth(fx, truth, tmp_path, suffix):
    media = write_clip(tmp_path, fx, truth, suffix=suffix)
    fused = initialise_from_trackers(fx, find_tracker_outputs(media), T, FusionConfig())
    fx.layout.check({k: torch.as_tensor(v) for k, v in fused.init.items()})
    body_frames = frames_except(*NLF_MISSING)
    assert rot_err_deg(fused.init["body"][body_frames], truth.rot["body"][body_frames]) < 1e-3
    for side in ("left_hand", "right_hand"):  # WiLoR where it saw the hand, NLF's hands where it did not
        assert rot_err_deg(fused.init[side], truth.rot[side]) < 1e-3
    face_frames = frames_except(*PIXEL3DMM_MISSING)
    face = truth.params["face"].numpy()
    assert np.allclose(fused.init["face"][face_frames, :102], face[face_frames, :102], atol=1e-5)
    assert rot_err_deg(fused.init["face"][face_frames, 102:], truth.rot["jaw"][face_frames]) < 1e-2
    assert np.allclose(fused.identity, truth.identity, atol=1e-5)

    info = describe(fused)
    assert info["init_source"] == "fused: nlf, wilor, pixel3dmm"
    assert info["init_identity"] == "nlf, pixel3dmm"
    assert info["init_share_nlf_body"] == pytest.approx(0.9) and info["init_share_interpolated_body"] == pytest.approx(0.1)
    assert info["init_share_wilor_right_hand"] == pytest.approx(0.7)
    assert info["init_share_nlf_right_hand"] == pytest.approx(0.3)
    assert info["init_share_tracker_right_hand"] == pytest.approx(1.0)
    assert info["init_share_wilor_left_hand"] == pytest.approx(1.0)
    assert info["init_share_pixel3dmm_face"] == pytest.approx(0.8)
    assert info["init_share_interpolated_face"] == pytest.approx(0.2)
    for m in fx.layout.names:
        shares = [info[f"init_share_{s}_{m}"] for s in ("tracker", "interpolated", "held", "rest")]
        assert sum(shares) == pytest.approx(1.0)
    assert all(info[f"init_outside_frames_{t}"] == 0 for t in ALL)


def test_estimates_outside_the_clip_are_counted(fx, truth, tmp_path):
    media = write_clip(tmp_path, fx, truth)
    info = describe(initialise_from_trackers(fx, find_tracker_outputs(media), T - 2))
    # Frames 8 and 9 lie outside an 8-frame clip: NLF's two rows, both hands in WiLoR, two Pixel3DMM frames.
    assert (info["init_outside_frames_nlf"], info["init_outside_frames_wilor"], info["init_outside_frames_pixel3dmm"]) == (2, 4, 2)


def test_missing_trackers_fall_back_per_modality(fx, truth, tmp_path):
    only_nlf = initialise_from_trackers(fx, find_tracker_outputs(write_clip(tmp_path / "a", fx, truth, trackers=("nlf",))), T)
    assert only_nlf.stream_names["right_hand"] == ("nlf:right_hand",)
    assert rot_err_deg(only_nlf.init["right_hand"][frames_except(*NLF_MISSING)],
                       truth.rot["right_hand"][frames_except(*NLF_MISSING)]) < 1e-3
    assert (only_nlf.source["face"] == REST).all()
    info = describe(only_nlf)
    assert info["init_source"] == "fused: nlf" and info["init_share_rest_face"] == 1.0
    assert info["init_share_nlf_right_hand"] == pytest.approx(0.9)
    assert np.allclose(only_nlf.identity[:10], truth.betas, atol=1e-5) and np.allclose(only_nlf.identity[10:], 0)

    no_nlf = initialise_from_trackers(
        fx, find_tracker_outputs(write_clip(tmp_path / "b", fx, truth, trackers=("wilor", "pixel3dmm"))), T)
    assert (no_nlf.source["body"] == REST).all()
    assert [no_nlf.source["right_hand"][t] for t in WILOR_RIGHT_MISSING] == [INTERPOLATED] * 3  # no NLF to fill in
    assert describe(no_nlf)["init_source"] == "fused: wilor, pixel3dmm"
    assert np.allclose(no_nlf.identity[:10], 0) and np.allclose(no_nlf.identity[10:], truth.identity[10:], atol=1e-5)

    long_gaps = initialise_from_trackers(
        fx, find_tracker_outputs(write_clip(tmp_path / "c", fx, truth, trackers=("wilor",))), T, FusionConfig(max_gap=2))
    assert [long_gaps.source["right_hand"][t] for t in WILOR_RIGHT_MISSING] == [HELD] * 3


def test_use_external_off_keeps_the_rest_pose(fx, truth, tmp_path):
    media = write_clip(tmp_path, fx, truth)
    fused = initialise_from_trackers(fx, find_tracker_outputs(media), T, FusionConfig(use_external=False))
    assert all((s == REST).all() for s in fused.source.values()) and fused.identity is None
    assert describe(fused)["init_source"] == "rest pose: no external tracker outputs"
    assert describe(fused)["init_identity"] == "default"


class AnnyLayout:
    """Anny's layout (:class:`m3t.body.anny_body.AnnyBody`) without building the model: only the layout is
    consulted before anything is read."""

    name = "anny"

    def __init__(self):
        from anny.models.facial_actions import FACIAL_ACTION_LABELS

        self.layout = ModalityLayout(
            modalities=(Modality("body", "rotation6d", BODY_BONES),
                        Modality("left_hand", "rotation6d", hand_bones("L"), mirror_of="right_hand"),
                        Modality("right_hand", "rotation6d", hand_bones("R"), mirror_of="left_hand"),
                        Modality("face", "scalar", tuple(FACIAL_ACTION_LABELS), bounds=(0.0, 1.0))),
            identity_labels=PHENOTYPES, identity_bounds=(0.0, 1.0))


def test_anny_takes_no_tracker_stream(fx, truth, tmp_path):
    media = write_clip(tmp_path, fx, truth)
    outputs = find_tracker_outputs(media)
    for path in (outputs.nlf, outputs.wilor):
        path.write_bytes(b"not read")  # the refusal comes before any file is opened
    with pytest.raises(FusionUnsupported) as info:
        initialise_from_trackers(AnnyLayout(), outputs, T)
    exc = info.value
    assert exc.body_model == "anny" and "'anny'" in str(exc)
    targets = [u.split(":")[0] for u in exc.unusable]
    assert targets == ["nlf -> body", "nlf -> left_hand", "nlf -> right_hand", "nlf -> identity",
                       "wilor -> left_hand", "wilor -> right_hand", "pixel3dmm -> face", "pixel3dmm -> identity"]
    assert "'spine03'" in str(exc) and "not SMPL-X joints" in str(exc)
    # Each tracker alone is refused too, naming only its own streams.
    with pytest.raises(FusionUnsupported, match=r"pixel3dmm -> face: face is 52 values"):
        initialise_from_trackers(AnnyLayout(), TrackerOutputs(pixel3dmm=outputs.pixel3dmm), T)


# ------------------------------------------------------------------------------------------ refining
@pytest.mark.slow
def test_refinement_around_the_fused_initialisation_beats_the_rest_pose(fx, truth, tmp_path):
    media = write_clip(tmp_path, fx, truth)
    fused = initialise_from_trackers(fx, find_tracker_outputs(media), T)
    track = simulate_track("clip", truth.params, torch.as_tensor(truth.identity), front_camera_fx(), 25.0, fx,
                           SimulatedTrackerConfig(seed=3))
    cfg = FittingConfig(solver="adam", iterations=40, camera_iterations=40)  # the measurements below
    from_fused = refine(track, fused, fx, cfg)
    from_rest = fit_track(dataclasses.replace(track, init=None), fx, cfg)
    assert isinstance(from_fused, FitResult) and type(from_fused) is type(from_rest)

    def joint_error_m(result: FitResult) -> float:
        with torch.no_grad():
            got = fx.forward({k: torch.as_tensor(v) for k, v in result.params.items()}, torch.as_tensor(result.identity))
            want = fx.forward(truth.params, torch.as_tensor(truth.identity))
        return float(torch.linalg.norm(got.joints - want.joints, dim=-1).mean())

    # Measured: ~1.6 mm for the fused initialisation itself, ~11 mm after refinement from it (the noisy 2D
    # track pulls it off), ~100 mm from the rest pose.
    fused_err, rest_err = joint_error_m(from_fused), joint_error_m(from_rest)
    assert fused_err < 0.25 * rest_err, (fused_err, rest_err)


# ------------------------------------------------------------------------------------------ fusion
def test_a_body_model_that_cannot_take_the_trackers_is_told_what_and_why():
    from m3t.fitting.fusion import FusionUnsupported

    exc = FusionUnsupported("anny", ("nlf -> body: 2 of its 2 joints are not SMPL-X joints", "wilor -> left_hand: x"))
    assert isinstance(exc, ValueError) and exc.body_model == "anny" and len(exc.unusable) == 2
    assert str(exc) == ("body model 'anny' cannot take nlf -> body: 2 of its 2 joints are not SMPL-X joints; "
                        "wilor -> left_hand: x (the tracker converters need SMPL-FX's SMPL-X / FLAME layout)")


def test_unusable_tracker_streams_name_the_first_three_offending_labels():
    from m3t.body.protocol import Modality, ModalityLayout
    from m3t.body.smplfx import smplfx_layout
    from m3t.fitting.fusion import unusable_outputs
    from m3t.trackers.external import TRACKERS

    assert unusable_outputs(smplfx_layout(100), TRACKERS) == ()
    layout = ModalityLayout((Modality("body", "rotation6d", ("spine01", "upperarm01_l", "neck01")),
                             Modality("left_hand", "scalar", ("curl",)),
                             Modality("face", "scalar", ("jawOpen", "eyeBlink_L"))),
                            ("age", "gender", "height", "weight"))
    assert unusable_outputs(layout, ("nlf", "pixel3dmm")) == (
        "nlf -> body: 3 of its 3 joints are not SMPL-X joints ('spine01', 'upperarm01_l', 'neck01')",
        "nlf -> left_hand: left_hand is scalar, the converters write rotations",
        "nlf -> right_hand: the layout has no 'right_hand' modality",
        "nlf -> identity: identity ('age', 'gender', 'height', ...) lacks the 10 SMPL-X betas 'smplx_beta_<i>'",
        ("pixel3dmm -> face: face is 2 values ('jawOpen', 'eyeBlink_L'), not FLAME's 100 expressions + 2 eyelids + "
         "jaw rotation"),
        "pixel3dmm -> identity: identity ('age', 'gender', 'height', ...) has no FLAME shape 'flame_shape_<iii>'")
    mixed = ModalityLayout((Modality("body", "rotation6d", ("neck", "spine01", "left_wrist")),), ("smplx_beta_0",))
    assert unusable_outputs(mixed, ("wilor",)) == ("wilor -> left_hand: the layout has no 'left_hand' modality",
                                                   "wilor -> right_hand: the layout has no 'right_hand' modality")
    assert unusable_outputs(mixed, ("nlf",))[0] == "nlf -> body: 1 of its 3 joints are not SMPL-X joints ('spine01')"


def face_estimates(frames: list[int], expression_dims: int = 100):
    """Pixel3DMM's per-frame estimates as :func:`m3t.trackers.pixel3dmm_reader.read_pixel3dmm` returns them."""
    from m3t.trackers.pixel3dmm_reader import FaceEstimates

    n = len(frames)
    rng = np.random.default_rng(4)
    eye = np.tile(np.eye(3), (n, 1, 1))
    return FaceEstimates(np.array(frames), rng.normal(size=(n, expression_dims)), rng.uniform(size=(n, 2)), eye, eye,
                         eye, np.zeros((n, 3)), np.zeros(300))


def test_pixel3dmm_face_values_land_on_their_frames_of_a_flame_face_layout():
    from m3t.body.protocol import Modality, ModalityLayout
    from m3t.body.smplfx import smplfx_layout
    from m3t.fitting.tracker_streams import pixel3dmm_stream

    face = face_estimates([0, 2, 7])
    stream = pixel3dmm_stream(face, smplfx_layout(100), 5)  # frame 7 lies outside the 5-frame clip
    assert stream.source == "pixel3dmm" and stream.values.shape == (5, 108)
    np.testing.assert_array_equal(stream.confidence, [1, 0, 1, 0, 0])
    np.testing.assert_array_equal(stream.values[2, :100], face.expression[1])
    np.testing.assert_array_equal(stream.values[2, 100:102], face.eyelids[1])
    np.testing.assert_allclose(stream.values[0, 102:], [1, 0, 0, 0, 1, 0])  # the identity jaw rotation in 6D
    assert np.isnan(stream.values[1]).all()
    arkit = ModalityLayout((Modality("face", "scalar", tuple(f"au{i}" for i in range(52))),), ("age",))
    with pytest.raises(ValueError, match=r"^Pixel3DMM gives 108 face values; the layout's face has 52$"):
        pixel3dmm_stream(face, arkit, 5)


def test_fusion_interpolates_rotations_along_the_geodesic_and_scalars_linearly():
    import roma

    from m3t.body.protocol import Modality, ModalityLayout
    from m3t.fitting.config import FusionConfig
    from m3t.fitting.stream_fusion import (
        INTERPOLATED,
        REST,
        TrackerStream,
        fuse,
        rot_to_flat6d,
    )

    def about_z(degrees: float) -> np.ndarray:
        return rot_to_flat6d(roma.rotvec_to_rotmat(torch.tensor([[0.0, 0.0, np.radians(degrees)]],
                                                                 dtype=torch.float64)).numpy())

    layout = ModalityLayout((Modality("jaw", "rotation6d", ("jaw",)), Modality("weights", "scalar", ("w0", "w1")),
                             Modality("hand", "rotation6d", ("wrist",))), ("age",))
    rest = {"jaw": about_z(0), "weights": np.array([0.5, 0.5]), "hand": about_z(10)}
    jaw = np.full((5, 6), np.nan)
    jaw[0], jaw[4] = about_z(0), about_z(80)
    weights = np.zeros((5, 2))
    weights[0], weights[4] = (0.0, 1.0), (0.8, 0.2)
    covered = np.array([1.0, 0, 0, 0, 1.0])
    fused = fuse(layout, {"jaw": [TrackerStream("pixel3dmm", jaw, covered)],
                          "weights": [TrackerStream("pixel3dmm", weights, covered)]}, rest, 5, FusionConfig(max_gap=3))
    for t in range(5):
        np.testing.assert_allclose(fused.init["jaw"][t], about_z(20 * t), atol=1e-6, err_msg=str(t))
    np.testing.assert_allclose(fused.init["weights"][2], (0.4, 0.6), atol=1e-6)
    np.testing.assert_array_equal(fused.source["jaw"], [0, INTERPOLATED, INTERPOLATED, INTERPOLATED, 0])
    np.testing.assert_array_equal(fused.source["hand"], [REST] * 5)  # no stream: the rest pose
    np.testing.assert_allclose(fused.init["hand"], np.tile(about_z(10), (5, 1)), atol=1e-7)
    assert fused.stream_names == {"jaw": ("pixel3dmm",), "weights": ("pixel3dmm",), "hand": ()}
    assert fused.init["jaw"].dtype == np.float32 and fused.identity is None
    with pytest.raises(ValueError, match=r"stream 'pixel3dmm' for 'jaw' has shape \(5, 5\) / \(5,\); expected "
                                         r"\(5, 6\) / \(5,\)"):
        fuse(layout, {"jaw": [TrackerStream("pixel3dmm", jaw[:, :5], covered)]}, rest, 5)


def test_the_initialisation_record_says_which_tracker_gave_each_modalitys_frames():
    from m3t.fitting.fusion import describe
    from m3t.fitting.stream_fusion import HELD, INTERPOLATED, REST, FusedInit

    source = {"body": np.array([0, 0, INTERPOLATED, HELD]), "face": np.full(4, REST),
              "left_hand": np.array([1, 1, 0, REST])}
    names = {"body": ("nlf:body",), "face": ("pixel3dmm",), "left_hand": ("wilor:left", "nlf:left_hand")}
    fused = FusedInit({}, source, names, np.zeros(3), ("nlf", "pixel3dmm"), {"nlf": 2, "pixel3dmm": 0})
    assert describe(fused) == {
        "init_share_tracker_body": 0.5, "init_share_nlf_body": 0.5, "init_share_interpolated_body": 0.25,
        "init_share_held_body": 0.25, "init_share_rest_body": 0.0,
        "init_share_tracker_face": 0.0, "init_share_pixel3dmm_face": 0.0, "init_share_interpolated_face": 0.0,
        "init_share_held_face": 0.0, "init_share_rest_face": 1.0,
        "init_share_tracker_left_hand": 0.75, "init_share_wilor_left_hand": 0.25, "init_share_nlf_left_hand": 0.5,
        "init_share_interpolated_left_hand": 0.0, "init_share_held_left_hand": 0.0, "init_share_rest_left_hand": 0.25,
        "init_outside_frames_nlf": 2.0, "init_outside_frames_pixel3dmm": 0.0,
        "init_source": "fused: nlf, wilor", "init_identity": "nlf, pixel3dmm"}
    unused = describe(FusedInit({}, {"face": np.full(4, REST)}, {"face": ("pixel3dmm",)}, None))
    assert unused["init_source"] == "rest pose: no external tracker estimate reached fusion.min_confidence"
    assert unused["init_identity"] == "default"
    nothing = describe(FusedInit({}, {"face": np.full(4, REST)}, {"face": ()}, None))
    assert nothing["init_source"] == "rest pose: no external tracker outputs"


def test_a_one_frame_fused_initialisation_shares_its_single_frame_fully():
    from m3t.fitting.fusion import describe
    from m3t.fitting.stream_fusion import HELD, REST, FusedInit

    fused = FusedInit(init={"body": np.zeros((1, 3)), "face": np.zeros((1, 2))},
                      source={"body": np.array([0]), "face": np.array([REST])},
                      stream_names={"body": ("nlf",), "face": ("pixel3dmm",)}, identity=None, outside={"nlf": 2})
    d = describe(fused)
    assert (d["init_share_tracker_body"], d["init_share_nlf_body"], d["init_share_rest_body"]) == (1.0, 1.0, 0.0)
    assert (d["init_share_rest_face"], d["init_share_tracker_face"], d["init_share_pixel3dmm_face"]) == (1.0, 0.0, 0.0)
    assert d["init_outside_frames_nlf"] == 2.0 and d["init_source"] == "fused: nlf"
    held = describe(FusedInit(init={"body": np.zeros((2, 3))}, source={"body": np.array([HELD, HELD])},
                              stream_names={"body": ("nlf",)}, identity=None))
    assert held["init_share_held_body"] == 1.0 and held["init_source"].startswith("rest pose: no external tracker est")


def test_a_modality_without_tracker_streams_has_no_frames():
    from m3t.fitting.config import FusionConfig
    from m3t.fitting.stream_fusion import fuse_modality

    values, source = fuse_modality([], np.zeros(6), True, FusionConfig())
    assert values.shape == (0, 6) and values.dtype == np.float32 and source.shape == (0,)


def test_a_face_tracker_can_write_an_identity_with_a_single_flame_shape_coefficient():
    from m3t.body.smplfx import smplfx_layout
    from m3t.fitting.fusion import _target_problem
    from m3t.fitting.imports import face_layout

    assert _target_problem(face_layout(1), "pixel3dmm", "identity") is None
    assert _target_problem(smplfx_layout(1), "nlf", "identity") is None
    problem = _target_problem(face_layout(0), "pixel3dmm", "identity")
    assert problem.startswith("identity ") and problem.endswith("has no FLAME shape 'flame_shape_<iii>'")
    assert _target_problem(face_layout(1), "pixel3dmm", "face") is None
    assert _target_problem(face_layout(1), "nlf", "body") == "the layout has no 'body' modality"


def test_two_streams_of_one_tracker_add_up_in_the_initialisation_record():
    from m3t.fitting.fusion import describe
    from m3t.fitting.stream_fusion import REST, FusedInit

    source = {"body": np.array([0, 1, 1, REST])}
    fused = FusedInit({}, source, {"body": ("nlf:a", "nlf:b")}, None)
    d = describe(fused)
    assert d["init_share_nlf_body"] == 0.75 and d["init_share_tracker_body"] == 0.75
    assert d["init_share_rest_body"] == 0.25 and d["init_source"] == "fused: nlf"
