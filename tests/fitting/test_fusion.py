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
    HELD,
    INTERPOLATED,
    REST,
    FusionUnsupported,
    describe,
    initialise_from_trackers,
    refine,
)
from m3t.trackers.external import TrackerFileError, TrackerOutputs, find_tracker_outputs
from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track

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
