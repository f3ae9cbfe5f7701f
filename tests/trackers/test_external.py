"""Tracker readers (WiLoR, Pixel3DMM, NLF) on files written in their documented formats, fusion, refinement,
and refusal of files that would run code."""
from __future__ import annotations

import dataclasses
import os
import pickle

import numpy as np
import pytest
import torch
from fusion_fixtures import T, rot_err_deg, write_nlf, write_pixel3dmm, write_wilor
from smplfx_fixtures import front_camera_fx

from m3t.body.smplfx_build import SMPLX_JOINTS
from m3t.fitting.config import FusionConfig
from m3t.fitting.fit import FittingConfig
from m3t.fitting.fusion import refine
from m3t.fitting.stream_fusion import HELD, INTERPOLATED, TrackerStream, fuse
from m3t.fitting.tracker_streams import fuse_trackers
from m3t.trackers.nlf_reader import read_nlf
from m3t.trackers.pixel3dmm_reader import read_pixel3dmm
from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track
from m3t.trackers.tracker_files import TrackerFileError, load_tracker_file
from m3t.trackers.wilor_reader import read_wilor


@pytest.mark.parametrize("suffix", [".npz", ".pt"])
def test_readers_recover_what_was_written(fx, truth, tmp_path, suffix):
    params, rot = truth.params, truth.rot
    write_nlf(tmp_path / f"nlf{suffix}", fx.layout, truth)
    write_wilor(tmp_path / f"wilor{suffix}", truth)
    write_pixel3dmm(tmp_path / "p3dmm", truth)
    nlf = read_nlf(tmp_path / f"nlf{suffix}")
    assert list(nlf.frame) == [t for t in range(T) if t != 2]
    cols = [SMPLX_JOINTS.index(n) for n in fx.layout["body"].labels]
    assert np.allclose(nlf.rotations[:, cols], rot["body"][nlf.frame], atol=1e-6)
    assert np.allclose(nlf.betas, truth.betas, atol=1e-6)
    hands = read_wilor(tmp_path / f"wilor{suffix}")
    assert list(hands["right"].frame) == [t for t in range(T) if t not in (3, 4, 5)]
    assert np.allclose(hands["left"].hand_pose, rot["left_hand"], atol=1e-6)  # mirrored back to a left hand
    assert np.allclose(hands["right"].hand_pose[0], rot["right_hand"][0], atol=1e-6)  # the confident one
    face = read_pixel3dmm(tmp_path / "p3dmm" / "checkpoint")
    assert list(read_pixel3dmm(tmp_path / "p3dmm").frame) == list(face.frame)  # the output folder holding it
    assert list(face.frame) == [t for t in range(T) if t not in (6, 7)]
    assert np.allclose(face.expression, params["face"][face.frame, :100].numpy(), atol=1e-6)
    assert np.allclose(face.jaw, rot["jaw"][face.frame], atol=1e-5)
    assert face.shape.shape == (300,)


def test_fusion_covers_gaps_and_flags_them(fx, truth, tmp_path):
    params, rot = truth.params, truth.rot
    write_nlf(tmp_path / "nlf.npz", fx.layout, truth)
    write_wilor(tmp_path / "wilor.npz", truth)
    write_pixel3dmm(tmp_path / "p3dmm", truth)
    fused = fuse_trackers(fx, T, nlf=read_nlf(tmp_path / "nlf.npz"), wilor=read_wilor(tmp_path / "wilor.npz"),
                          pixel3dmm=read_pixel3dmm(tmp_path / "p3dmm"))
    fx.layout.check({k: torch.as_tensor(v) for k, v in fused.init.items()})
    assert fused.stream_names["right_hand"] == ("wilor:right", "nlf:right_hand")
    # WiLoR missed the right hand in frames 3-5: NLF's hands fill them (stream 1).
    assert list(fused.source["right_hand"][3:6]) == [1, 1, 1] and fused.source["right_hand"][0] == 0
    assert rot_err_deg(fused.init["right_hand"], rot["right_hand"]) < 1e-3
    assert fused.source["body"][2] == INTERPOLATED  # NLF lost frame 2
    covered = [t for t in range(T) if t != 2]
    assert rot_err_deg(fused.init["body"][covered], rot["body"][covered]) < 1e-3
    assert rot_err_deg(fused.init["body"][2:3], rot["body"][2:3]) < 10.0  # geodesic interpolation
    assert list(fused.source["face"][6:8]) == [INTERPOLATED] * 2
    assert np.allclose(fused.init["face"][0, :102], params["face"][0, :102].numpy(), atol=1e-6)
    assert np.allclose(fused.identity, truth.identity, atol=1e-6)


def test_long_gaps_are_held_and_rest_when_uncovered(fx):
    dim = fx.layout["face"].dim
    values = np.zeros((T, dim))
    values[:, 0] = np.arange(T)
    conf = np.zeros(T)
    conf[[0, 9]] = 1.0
    rest = {k: v[0].numpy() for k, v in fx.rest_params(1).items()}
    fused = fuse(fx.layout, {"face": [TrackerStream("x", values, conf)]}, rest, T, FusionConfig(max_gap=3))
    assert list(fused.source["face"][1:9]) == [HELD] * 8
    assert fused.init["face"][4, 0] == 0 and fused.init["face"][5, 0] == 9  # nearest covered frame
    assert (fused.source["body"] < 0).all() and np.allclose(fused.init["body"], rest["body"])


@pytest.mark.slow
def test_refinement_from_fused_initialisation(fx, truth, tmp_path):
    params = truth.params
    write_nlf(tmp_path / "nlf.npz", fx.layout, truth)
    fused = fuse_trackers(fx, T, nlf=read_nlf(tmp_path / "nlf.npz"))
    identity = torch.as_tensor(fused.identity)
    track = simulate_track("ext", params, identity, front_camera_fx(), 25.0, fx, SimulatedTrackerConfig(seed=2))
    result = refine(dataclasses.replace(track, init=None), fused, fx, FittingConfig(iterations=30, camera_iterations=30))
    assert np.allclose(result.identity[:10], fused.identity[:10], atol=0.5)  # started from the fused identity
    assert result.metrics["reproj_px"] < 10.0
    assert all(v.shape == (T, fx.layout.dims[k]) for k, v in result.params.items())


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned > /dev/null",))


def test_files_that_would_run_code_are_refused(tmp_path):
    torch.save({"pose": _Evil()}, tmp_path / "evil.pt")
    with pytest.raises(TrackerFileError):
        load_tracker_file(tmp_path / "evil.pt")
    (tmp_path / "evil.pkl").write_bytes(pickle.dumps({"pose": _Evil()}, protocol=2))
    with pytest.raises(TrackerFileError, match="refused"):
        load_tracker_file(tmp_path / "evil.pkl")
    np.savez(tmp_path / "evil.npz", pose=np.array([_Evil()], dtype=object))
    with pytest.raises(TrackerFileError):
        load_tracker_file(tmp_path / "evil.npz")
    with pytest.raises(TrackerFileError, match="does not exist"):
        read_nlf(tmp_path / "missing.npz")


def test_an_nlf_file_with_frame_indices_keeps_them_and_drops_the_lost_frames(fx, truth, tmp_path):
    """A stacked NLF file may carry ``frame_index`` (a video read every other frame from frame 10, say): the
    estimates keep those indices, not their row numbers, and a row NLF lost (NaN) is dropped with its index."""
    written = dict(np.load(write_nlf(tmp_path / "rows.npz", fx.layout, truth)))
    np.savez(tmp_path / "indexed.npz", **written, frame_index=10 + 2 * np.arange(T))
    nlf = read_nlf(tmp_path / "indexed.npz")
    assert list(nlf.frame) == [10 + 2 * t for t in range(T) if t != 2]
    assert list(read_nlf(tmp_path / "rows.npz").frame) == [t for t in range(T) if t != 2]


def test_a_frame_folder_with_unnumbered_names_plays_in_name_order(tmp_path):
    from m3t.trackers.media import list_frame_files

    for name in ("b.png", "frame10.png", "a.jpg", "frame9.png", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in list_frame_files(tmp_path)] == ["a.jpg", "b.png", "frame10.png", "frame9.png"]
    (tmp_path / "a.jpg").unlink()
    (tmp_path / "b.png").unlink()
    assert [p.name for p in list_frame_files(tmp_path)] == ["frame9.png", "frame10.png"]  # all numbered: by number


def test_tracker_fields_come_back_as_float64_numpy_whatever_their_stored_float_type(tmp_path):
    from m3t.trackers.tracker_files import tracker_array

    data = {"pose": torch.ones(2, 3, dtype=torch.float32), "betas": np.ones((2, 3), np.float16),
            "frame_index": np.arange(2, dtype=np.int32)}
    assert tracker_array(data, "pose", tmp_path / "t.pt").dtype == np.float64
    assert tracker_array(data, "betas", tmp_path / "t.pt").dtype == np.float64
    assert tracker_array(data, "frame_index", tmp_path / "t.pt").dtype == np.int32  # integers stay integers


def test_an_nlf_file_of_per_frame_plain_lists_reads_like_one_of_tensors(fx, truth, tmp_path):
    """``detect_smpl_batched``'s per-frame lists saved as plain nested lists (a converted output) read the same."""
    tensors = torch.load(write_nlf(tmp_path / "nlf.pt", fx.layout, truth), weights_only=True)
    torch.save({k: [t.tolist() for t in v] for k, v in tensors.items()}, tmp_path / "numpy.pt")
    as_numpy, as_tensors = read_nlf(tmp_path / "numpy.pt"), read_nlf(tmp_path / "nlf.pt")
    assert list(as_numpy.frame) == list(as_tensors.frame) == [t for t in range(T) if t != 2]
    assert np.array_equal(as_numpy.rotations, as_tensors.rotations)
