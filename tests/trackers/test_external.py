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


# --- NLF: per-frame lists and stacked arrays, hand-made ------------------------------------------------------

def _nlf_pose(seed: int) -> np.ndarray:
    """One person's (165,) axis-angle pose: small, distinct rotations per joint (well away from pi)."""
    return np.random.default_rng(seed).uniform(-0.5, 0.5, 165)


def test_nlf_per_frame_lists_take_the_first_person_and_skip_empty_frames(tmp_path):
    """``detect_smpl_batched`` lists: the first (most confident) person of a frame is kept, its box score is the
    confidence, a frame with nobody is skipped (and later frames still read), values come back float64."""
    from m3t.trackers.nlf_reader import axis_angle_to_matrix

    first, second, third = _nlf_pose(1), _nlf_pose(2), _nlf_pose(3)
    pose = [torch.tensor(np.stack([first, second]), dtype=torch.float64), torch.zeros(0, 165),
            torch.tensor(third[None])]
    betas = [torch.tensor(np.stack([np.arange(10.0), -np.arange(10.0)])), torch.zeros(0, 10),
             torch.full((1, 10), 7.0)]
    trans = [torch.tensor([[1.0, 2.0, 3.0], [9.0, 9.0, 9.0]]), torch.zeros(0, 3), torch.tensor([[4.0, 5.0, 6.0]])]
    boxes = [torch.tensor([[0, 0, 10, 10, 0.75], [0, 0, 10, 10, 0.25]]), torch.zeros(0, 5),
             torch.tensor([[0, 0, 10, 10, 0.5]])]
    torch.save({"pose": pose, "betas": betas, "trans": trans, "boxes": boxes}, tmp_path / "nlf.pt")
    nlf = read_nlf(tmp_path / "nlf.pt")
    assert nlf.frame.dtype == np.int64 and list(nlf.frame) == [0, 2]
    assert np.array_equal(nlf.confidence, [0.75, 0.5])
    assert np.array_equal(nlf.betas, [np.arange(10.0), np.full(10, 7.0)]) and nlf.betas.shape == (2, 10)
    assert np.array_equal(nlf.translation, [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    assert nlf.rotations.shape == (2, 55, 3, 3) and nlf.rotations.dtype == np.float64
    expected = axis_angle_to_matrix(np.stack([first, third]).reshape(2, 55, 3))
    np.testing.assert_allclose(nlf.rotations, expected, atol=1e-12)  # roma's float64 maths, same inputs
    # the matrices are the axis-angle's rotations: R(aa) rotates aa onto itself
    aa = first.reshape(55, 3)[5]
    np.testing.assert_allclose(nlf.rotations[0, 5] @ aa, aa, atol=1e-12)


def test_nlf_per_frame_lists_without_boxes_are_fully_confident(tmp_path):
    pose = [torch.tensor(_nlf_pose(4)[None]), torch.tensor(_nlf_pose(5)[None])]
    torch.save({"pose": pose, "betas": [torch.ones(1, 10)] * 2, "trans": [torch.zeros(1, 3)] * 2}, tmp_path / "n.pt")
    nlf = read_nlf(tmp_path / "n.pt")
    assert list(nlf.frame) == [0, 1] and np.array_equal(nlf.confidence, [1.0, 1.0])


def test_nlf_per_frame_tuples_of_plain_numbers_read(tmp_path):
    """A tuple of per-frame nested lists (no tensors at all) is the per-frame form too."""
    pose = (_nlf_pose(6)[None].tolist(), [], _nlf_pose(7)[None].tolist())
    data = {"pose": pose, "betas": ([[2.0] * 10], [], [[3.0] * 10]),
            "trans": ([[0.0, 0.0, 1.0]], [], [[0.0, 0.0, 2.0]])}
    (tmp_path / "n.pkl").write_bytes(pickle.dumps(data, protocol=2))
    nlf = read_nlf(tmp_path / "n.pkl")
    assert list(nlf.frame) == [0, 2] and np.array_equal(nlf.translation[:, 2], [1.0, 2.0])
    assert np.array_equal(nlf.betas[:, 0], [2.0, 3.0])


def test_nlf_stacked_arrays_drop_rows_with_non_finite_pose_or_betas(tmp_path):
    """Stacked ``.npz``: betas wider than 10 are cut to SMPL-X's 10, frame indices and confidence are kept per
    row, and a row whose pose *or* betas hold NaN is a lost frame."""
    pose = np.stack([_nlf_pose(t) for t in range(4)])
    betas = np.tile(np.arange(16.0), (4, 1))
    pose[1, 7] = np.nan
    betas[2, 3] = np.nan
    np.savez(tmp_path / "n.npz", pose=pose.astype(np.float32), betas=betas, trans=np.arange(12.0).reshape(4, 3),
             frame_index=np.array([5, 6, 7, 8], dtype=np.int32), confidence=np.array([0.1, 0.2, 0.3, 0.4]))
    nlf = read_nlf(tmp_path / "n.npz")
    assert nlf.frame.dtype == np.int64 and list(nlf.frame) == [5, 8]
    assert np.array_equal(nlf.confidence, [0.1, 0.4])
    assert nlf.betas.shape == (2, 10) and np.array_equal(nlf.betas[0], np.arange(10.0))
    assert np.array_equal(nlf.translation, [[0.0, 1.0, 2.0], [9.0, 10.0, 11.0]])
    assert nlf.rotations.shape == (2, 55, 3, 3)
    # float32 on disk, float64 rotations of those float32 values (tolerance: the float32 rounding of the input)
    from m3t.trackers.nlf_reader import axis_angle_to_matrix

    np.testing.assert_allclose(nlf.rotations[1], axis_angle_to_matrix(pose[3].reshape(55, 3)), atol=1e-6)


def test_nlf_stacked_arrays_without_indices_or_scores_number_rows_and_trust_them(tmp_path):
    np.savez(tmp_path / "n.npz", pose=np.zeros((3, 165)), betas=np.zeros((3, 10)), trans=np.zeros((3, 3)))
    nlf = read_nlf(tmp_path / "n.npz")
    assert list(nlf.frame) == [0, 1, 2] and np.array_equal(nlf.confidence, np.ones(3))
    np.testing.assert_array_equal(nlf.rotations, np.broadcast_to(np.eye(3), (3, 55, 3, 3)))


def test_nlf_file_without_any_estimate_gives_empty_arrays(tmp_path):
    pose = np.full((2, 165), np.nan)
    np.savez(tmp_path / "n.npz", pose=pose, betas=np.zeros((2, 10)), trans=np.zeros((2, 3)))
    nlf = read_nlf(tmp_path / "n.npz")
    assert nlf.rotations.shape == (0, 55, 3, 3) and len(nlf.frame) == 0 and nlf.betas.shape == (0, 10)
    torch.save({"pose": [torch.zeros(0, 165)], "betas": [torch.zeros(0, 10)], "trans": [torch.zeros(0, 3)]},
               tmp_path / "e.pt")
    empty = read_nlf(tmp_path / "e.pt")
    assert empty.rotations.shape == (0, 55, 3, 3) and empty.frame.shape == (0,) and empty.translation.shape == (0, 3)


def test_nlf_fields_of_the_wrong_width_are_named(tmp_path):
    import re

    np.savez(tmp_path / "n.npz", pose=np.zeros((2, 72)), betas=np.zeros((2, 10)), trans=np.zeros((2, 3)))
    with pytest.raises(TrackerFileError, match=re.escape(f"{tmp_path / 'n.npz'}: field 'pose' has shape (2, 72), "
                                                         "expected (..., 165)")):
        read_nlf(tmp_path / "n.npz")
    np.savez(tmp_path / "t.npz", pose=np.zeros((2, 165)), betas=np.zeros((2, 10)), trans=np.zeros((2, 4)))
    with pytest.raises(TrackerFileError, match=re.escape("field 'trans' has shape (2, 4), expected (..., 3)")):
        read_nlf(tmp_path / "t.npz")
    np.savez(tmp_path / "b.npz", pose=np.zeros((2, 165)), trans=np.zeros((2, 3)))
    with pytest.raises(TrackerFileError, match=re.escape("field 'betas' missing; found ['pose', 'trans']")):
        read_nlf(tmp_path / "b.npz")


# --- tracker files --------------------------------------------------------------------------------------------

def test_tracker_file_errors_name_the_file_and_the_fix(tmp_path):
    import re

    with pytest.raises(TrackerFileError, match=re.escape(f"tracker output {tmp_path / 'x.npz'} does not exist")):
        load_tracker_file(tmp_path / "x.npz")
    (tmp_path / "x.json").write_text("{}")
    with pytest.raises(TrackerFileError, match=re.escape(f"{tmp_path / 'x.json'}: unsupported tracker output type "
                                                         "'.json'; expected .npz, .pt, .frame or .pkl")):
        load_tracker_file(tmp_path / "x.json")
    torch.save([torch.zeros(2)], tmp_path / "list.pt")
    with pytest.raises(TrackerFileError, match=re.escape(f"{tmp_path / 'list.pt'}: expected a dict of arrays, "
                                                         "found list")):
        load_tracker_file(tmp_path / "list.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a zip at all")
    with pytest.raises(TrackerFileError, match=re.escape(f"{tmp_path / 'junk.pt'}: refused or unreadable (")
                       + r".*" + re.escape("). Tracker outputs are loaded without executing code; save plain "
                                           "tensors / numpy arrays.")):
        load_tracker_file(tmp_path / "junk.pt")


@pytest.mark.parametrize("suffix", [".pt", ".PTH", ".frame", ".Frame"])
def test_torch_tracker_files_of_any_torch_suffix_load_with_numpy_values(tmp_path, suffix):
    """Torch files (any case of .pt / .pth / .frame) load on the CPU with numpy arrays and scalars inside."""
    torch.save({"a": np.arange(3.0, dtype=np.float32), "s": np.float64(2.5), "i": np.int64(4),
                "t": torch.ones(2)}, tmp_path / f"f{suffix}")
    out = load_tracker_file(tmp_path / f"f{suffix}")
    assert np.array_equal(out["a"], [0.0, 1.0, 2.0]) and out["a"].dtype == np.float32
    assert out["s"] == 2.5 and out["i"] == 4 and out["t"].device.type == "cpu"


def test_npz_and_pickle_tracker_files_of_any_case_load(tmp_path):
    with open(tmp_path / "a.NPZ", "wb") as fh:  # a path would get ".npz" appended
        np.savez(fh, x=np.arange(2))
    assert np.array_equal(load_tracker_file(tmp_path / "a.NPZ")["x"], [0, 1])
    (tmp_path / "b.PKL").write_bytes(pickle.dumps({"x": np.arange(3)}, protocol=2))
    assert np.array_equal(load_tracker_file(tmp_path / "b.PKL")["x"], [0, 1, 2])


def test_torch_tracker_files_written_under_numpy_1_load(tmp_path):
    """A ``.pt`` pickled by numpy 1 names ``numpy.core.multiarray`` (numpy 2 writes ``numpy._core``): both
    spellings of numpy's array and scalar reconstruction are allow-listed."""
    import warnings
    import zipfile

    torch.save({"a": np.arange(3.0), "s": np.float64(2.5)}, tmp_path / "new.pt")
    with zipfile.ZipFile(tmp_path / "new.pt") as archive:
        records = {name: archive.read(name) for name in archive.namelist()}
    pkl = next(name for name in records if name.endswith("data.pkl"))
    records[pkl] = records[pkl].replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
    assert b"numpy.core.multiarray\n_reconstruct" in records[pkl] and b"numpy.core.multiarray\nscalar" in records[pkl]
    with zipfile.ZipFile(tmp_path / "old.pt", "w") as archive:
        for name, blob in records.items():
            archive.writestr(name, blob)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # numpy 2 warns about the numpy.core alias
        out = load_tracker_file(tmp_path / "old.pt")
    assert np.array_equal(out["a"], [0.0, 1.0, 2.0]) and out["s"] == 2.5


def test_tracker_array_converts_tensors_and_checks_the_trailing_shape(tmp_path):
    import re

    from m3t.trackers.tracker_files import tracker_array

    data = {"r": torch.arange(6, dtype=torch.float32).reshape(1, 2, 3), "l": [[1.0, 2.0]], "c": np.ones(2, np.complex64)}
    value = tracker_array(data, "r", tmp_path / "f.pt", (2, 3))
    assert isinstance(value, np.ndarray) and value.dtype == np.float64 and value.shape == (1, 2, 3)
    assert tracker_array(data, "l", tmp_path / "f.pt", (2,)).dtype == np.float64
    with pytest.raises(TrackerFileError, match=re.escape(f"{tmp_path / 'f.pt'}: field 'r' has shape (1, 2, 3), "
                                                         "expected (..., 3, 3)")):
        tracker_array(data, "r", tmp_path / "f.pt", (3, 3))
    with pytest.raises(TrackerFileError, match=re.escape(f"{tmp_path / 'f.pt'}: field 'x' missing; found "
                                                         "['c', 'l', 'r']")):
        tracker_array(data, "x", tmp_path / "f.pt")


def test_rotmat_to_6d_keeps_the_first_two_columns():
    from m3t.body.rotations import sixd_to_matrix
    from m3t.trackers.tracker_files import rotmat_to_6d

    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z
    six = rotmat_to_6d(np.stack([rot, np.eye(3)]))
    assert six.shape == (2, 6) and six.dtype == np.float64
    np.testing.assert_allclose(sixd_to_matrix(torch.as_tensor(six)).numpy(), np.stack([rot, np.eye(3)]), atol=1e-12)


# --- WiLoR: hand-made detections ------------------------------------------------------------------------------

def _rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _wilor_rows(frames, right, conf, angles):
    """Stacked WiLoR detections: detection i rotates every joint by ``angles[i]`` degrees about z (and about
    x for its wrist), with betas all ``i``."""
    n = len(frames)
    go = np.stack([(_rot_z(a) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]))[None] for a in angles])
    hp = np.stack([np.tile(_rot_z(a), (15, 1, 1)) for a in angles])
    return {"frame_index": np.asarray(frames), "is_right": np.asarray(right, dtype=np.float32),
            "global_orient": go, "hand_pose": hp, "betas": np.arange(n, dtype=np.float64)[:, None] * np.ones((n, 10)),
            "confidence": np.asarray(conf, dtype=np.float64)}


def test_wilor_keeps_the_most_confident_hand_per_side_and_frame_and_mirrors_left_hands(tmp_path):
    rows = _wilor_rows(frames=[3, 1, 1, 1, 3, 1], right=[1, 1, 1, 0, 0, 0], conf=[0.5, 0.4, 0.9, 0.6, 0.8, 0.7],
                       angles=[10, 20, 30, 40, 50, 60])
    np.savez(tmp_path / "w.npz", **rows)
    hands = read_wilor(tmp_path / "w.npz")
    right, left = hands["right"], hands["left"]
    assert list(right.frame) == [1, 3] and right.frame.dtype == np.int64  # in frame order
    assert np.array_equal(right.confidence, [0.9, 0.5]) and np.array_equal(right.betas[:, 0], [2.0, 0.0])
    np.testing.assert_allclose(right.hand_pose[0, 14], _rot_z(30), atol=1e-12)
    np.testing.assert_allclose(right.global_orient[1], rows["global_orient"][0, 0], atol=1e-12)
    assert right.hand_pose.shape == (2, 15, 3, 3) and right.global_orient.shape == (2, 3, 3)
    assert list(left.frame) == [1, 3] and np.array_equal(left.confidence, [0.7, 0.8])
    mirror = np.diag([-1.0, 1.0, 1.0])
    np.testing.assert_allclose(left.hand_pose[0, 0], _rot_z(-60), atol=1e-12)  # M Rz(a) M = Rz(-a)
    np.testing.assert_allclose(left.global_orient[1], mirror @ rows["global_orient"][4, 0] @ mirror, atol=1e-12)
    assert np.array_equal(left.betas[:, 0], [5.0, 4.0])


def test_wilor_ties_keep_the_first_detection_and_missing_scores_trust_every_row(tmp_path):
    rows = _wilor_rows(frames=[0, 0], right=[1, 1], conf=[0.5, 0.5], angles=[10, 20])
    del rows["confidence"]
    torch.save({**{k: torch.as_tensor(v) for k, v in rows.items() if k in ("frame_index", "is_right")},
                "pred_mano_params": {k: torch.as_tensor(rows[k]) for k in ("global_orient", "hand_pose", "betas")}},
               tmp_path / "w.pt")
    hands = read_wilor(tmp_path / "w.pt")
    assert np.array_equal(hands["right"].confidence, [1.0]) and hands["right"].betas[0, 0] == 0.0
    np.testing.assert_allclose(hands["right"].hand_pose[0, 0], _rot_z(10), atol=1e-6)  # stored as float64 tensors
    assert len(hands["left"].frame) == 0 and hands["left"].hand_pose.shape == (0, 15, 3, 3)


def test_wilor_fields_that_disagree_are_refused(tmp_path):
    import re

    rows = _wilor_rows(frames=[0, 1], right=[1, 0], conf=[0.5, 0.5], angles=[10, 20])
    np.savez(tmp_path / "w.npz", **{**rows, "frame_index": np.array([0, 1, 2])})
    with pytest.raises(TrackerFileError, match=re.escape(f"{tmp_path / 'w.npz'}: fields disagree on the number of "
                                                         "detections")):
        read_wilor(tmp_path / "w.npz")
    np.savez(tmp_path / "c.npz", **{**rows, "confidence": np.ones(3)})
    with pytest.raises(TrackerFileError, match="fields disagree"):
        read_wilor(tmp_path / "c.npz")
    np.savez(tmp_path / "r.npz", **{**rows, "is_right": np.ones(1)})
    with pytest.raises(TrackerFileError, match="fields disagree"):
        read_wilor(tmp_path / "r.npz")
    np.savez(tmp_path / "g.npz", **{**rows, "global_orient": np.zeros((2, 1, 3))})
    with pytest.raises(TrackerFileError, match=re.escape("field 'global_orient' has shape (2, 1, 3), expected "
                                                         "(..., 3, 3)")):
        read_wilor(tmp_path / "g.npz")


# --- Pixel3DMM: hand-made .frame files -------------------------------------------------------------------------

def _p3d_rows(rot: np.ndarray) -> np.ndarray:
    return rot[:2, :].reshape(1, 6)  # PyTorch3D's 6D: the first two rows


def _write_frame(path, frame_id=None, exp_dim=100, value=0.0, **flame_extra):
    flame = {"exp": np.full((1, exp_dim), value), "shape": np.full((1, 300), value),
             "eyelids": np.array([[value, -value]]), **flame_extra}
    data = {"flame": flame} if frame_id is None else {"flame": flame, "frame_id": frame_id}
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(data, path)


def test_pixel3dmm_frames_sort_by_frame_id_and_convert_pytorch3d_rotations(tmp_path):
    folder = tmp_path / "clip.pixel3dmm" / "checkpoint"
    rz = _rot_z(30)
    rx = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    _write_frame(folder / "00000.frame", frame_id=np.array([7]), value=2.0, jaw=_p3d_rows(rz), neck=_p3d_rows(rx),
                 R=_p3d_rows(rx @ rz), t=np.array([[1.0, 2.0, 3.0]]))
    _write_frame(folder / "00001.frame", frame_id=3, value=1.0)  # no jaw / neck / R / t: identity and zero
    _write_frame(folder / "00002.frame", frame_id=5, value=4.0, exp_dim=120)
    face = read_pixel3dmm(tmp_path / "clip.pixel3dmm")
    assert face.frame.dtype == np.int64 and list(face.frame) == [3, 5, 7]
    assert face.expression.shape == (3, 100) and np.array_equal(face.expression[:, 0], [1.0, 4.0, 2.0])
    assert np.array_equal(face.eyelids, [[1.0, -1.0], [4.0, -4.0], [2.0, -2.0]])
    np.testing.assert_allclose(face.jaw[2], rz, atol=1e-12)
    np.testing.assert_allclose(face.neck[2], rx, atol=1e-12)
    np.testing.assert_allclose(face.head_rotation[2], rx @ rz, atol=1e-12)
    np.testing.assert_allclose(face.jaw[:2], np.broadcast_to(np.eye(3), (2, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(face.head_rotation[0], np.eye(3), atol=1e-12)
    assert np.array_equal(face.head_translation, [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    assert face.shape.shape == (300,) and np.array_equal(face.shape, np.full(300, 2.0))  # median over frames


def test_pixel3dmm_short_expressions_are_zero_padded_and_names_give_missing_frame_ids(tmp_path):
    _write_frame(tmp_path / "00012.frame", exp_dim=50, value=3.0)
    _write_frame(tmp_path / "00004.frame", exp_dim=50, value=1.0)
    face = read_pixel3dmm(tmp_path / "00012.frame")  # one file read on its own
    assert list(face.frame) == [12] and face.expression.shape == (1, 100)
    assert np.array_equal(face.expression[0], np.r_[np.full(50, 3.0), np.zeros(50)])
    both = read_pixel3dmm(tmp_path)
    assert list(both.frame) == [4, 12] and np.array_equal(both.expression[:, 0], [1.0, 3.0])


def test_pixel3dmm_6d_rows_follow_pytorch3d_layout():
    from m3t.trackers.pixel3dmm_reader import pytorch3d_6d_to_matrix

    rot = _rot_z(40) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    six = np.stack([_p3d_rows(rot), _p3d_rows(rot.T)])  # (2, 1, 6)
    out = pytorch3d_6d_to_matrix(six)
    assert out.shape == (2, 1, 3, 3)
    np.testing.assert_allclose(out[:, 0], np.stack([rot, rot.T]), atol=1e-12)
    # rows are orthonormalised in order: a scaled first row keeps its direction
    np.testing.assert_allclose(pytorch3d_6d_to_matrix(np.r_[3.0, 0, 0, 1.0, 1.0, 0]), np.eye(3), atol=1e-12)


def test_pixel3dmm_errors_name_the_folder_or_the_frame(tmp_path):
    import re

    (tmp_path / "empty").mkdir()
    with pytest.raises(TrackerFileError, match=re.escape(f"{tmp_path / 'empty'}: no Pixel3DMM '*.frame' files "
                                                         "(expected <output>/checkpoint/00000.frame ...)")):
        read_pixel3dmm(tmp_path / "empty")
    with pytest.raises(TrackerFileError, match="no Pixel3DMM"):
        read_pixel3dmm(tmp_path / "gone.frame")
    torch.save({"exp": np.zeros((1, 100))}, tmp_path / "flat.frame")
    with pytest.raises(TrackerFileError, match=re.escape(f"{tmp_path / 'flat.frame'}: field 'flame' missing or "
                                                         "not a dict; found ['exp']")):
        read_pixel3dmm(tmp_path / "flat.frame")
    _write_frame(tmp_path / "bad" / "00000.frame", eyelids=np.zeros((1, 3)))
    with pytest.raises(TrackerFileError, match=re.escape("field 'eyelids' has shape (1, 3), expected (..., 2)")):
        read_pixel3dmm(tmp_path / "bad")
    _write_frame(tmp_path / "jaw" / "00000.frame", jaw=np.zeros((1, 9)))
    with pytest.raises(TrackerFileError, match=re.escape("field 'jaw' has shape (1, 9), expected (..., 6)")):
        read_pixel3dmm(tmp_path / "jaw")
    _write_frame(tmp_path / "t" / "00000.frame", t=np.zeros((1, 2)))
    with pytest.raises(TrackerFileError, match=re.escape("field 't' has shape (1, 2), expected (..., 3)")):
        read_pixel3dmm(tmp_path / "t")


def test_pixel3dmm_frames_folder_prefers_checkpoint_only_without_frames_of_its_own(tmp_path):
    from m3t.trackers.pixel3dmm_reader import frames_folder

    out = tmp_path / "clip.pixel3dmm"
    (out / "checkpoint").mkdir(parents=True)
    assert frames_folder(out) == out / "checkpoint"
    (out / "00000.frame").write_bytes(b"")
    assert frames_folder(out) == out  # frames directly in the output folder win
    assert frames_folder(tmp_path / "missing") == tmp_path / "missing"
    (tmp_path / "plain").mkdir()
    assert frames_folder(tmp_path / "plain") == tmp_path / "plain"


# --- finding tracker outputs beside the media -----------------------------------------------------------------

def test_tracker_outputs_are_found_beside_video_and_frame_folder(tmp_path):
    from m3t.trackers.external import TrackerOutputs, find_tracker_outputs

    (tmp_path / "abc.mp4").write_bytes(b"video")
    assert find_tracker_outputs(tmp_path / "abc.mp4") == TrackerOutputs()
    assert not TrackerOutputs().any() and TrackerOutputs().names() == () and TrackerOutputs().digest() == "none"
    (tmp_path / "abc.nlf.pt").write_bytes(b"n")
    (tmp_path / "abc.wilor.npz").write_bytes(b"w")
    (tmp_path / "abc.pixel3dmm" / "checkpoint").mkdir(parents=True)
    (tmp_path / "abc.pixel3dmm" / "checkpoint" / "00001.frame").write_bytes(b"1")
    (tmp_path / "abc.pixel3dmm" / "checkpoint" / "00000.frame").write_bytes(b"0")
    (tmp_path / "abc.pixel3dmm" / "checkpoint" / "mesh.ply").write_bytes(b"m")
    found = find_tracker_outputs(tmp_path / "abc.mp4")
    assert found == TrackerOutputs(tmp_path / "abc.nlf.pt", tmp_path / "abc.wilor.npz",
                                   tmp_path / "abc.pixel3dmm" / "checkpoint")
    assert found.names() == ("nlf", "wilor", "pixel3dmm") and found.any()
    assert found.files() == {"nlf": [tmp_path / "abc.nlf.pt"], "wilor": [tmp_path / "abc.wilor.npz"],
                             "pixel3dmm": [found.pixel3dmm / "00000.frame", found.pixel3dmm / "00001.frame"]}
    (found.pixel3dmm / "00002.frame").mkdir()  # a folder named like a frame is not read
    assert found.files()["pixel3dmm"] == [found.pixel3dmm / "00000.frame", found.pixel3dmm / "00001.frame"]
    (tmp_path / "abc").mkdir()  # a frame folder keeps its whole name
    assert find_tracker_outputs(tmp_path / "abc") == found
    assert TrackerOutputs(wilor=tmp_path / "abc.wilor.npz").names() == ("wilor",)


def test_tracker_outputs_digest_follows_the_bytes_read(tmp_path):
    from m3t.trackers.external import TrackerOutputs, find_tracker_outputs

    (tmp_path / "c.pose").write_bytes(b"pose")
    (tmp_path / "c.nlf.npz").write_bytes(b"n1")
    nlf_only = find_tracker_outputs(tmp_path / "c.pose").digest()
    from m3t.digest import chunks_digest, file_digest

    # the cache-key format: a version tag, then per tracker its name and file count, per file its name and bytes
    assert nlf_only == chunks_digest([b"m3t tracker outputs v1", b"\0nlf\x001",
                                      f"\0c.nlf.npz\0{file_digest(tmp_path / 'c.nlf.npz')}".encode()])
    (tmp_path / "c.nlf.npz").write_bytes(b"n2")
    changed = find_tracker_outputs(tmp_path / "c.pose").digest()
    assert changed != nlf_only
    (tmp_path / "c.pixel3dmm").mkdir()
    (tmp_path / "c.pixel3dmm" / "render.png").write_bytes(b"r")
    with_empty_face = find_tracker_outputs(tmp_path / "c.pose")
    empty_face = with_empty_face.digest()
    assert with_empty_face.files()["pixel3dmm"] == [] and empty_face != changed
    (tmp_path / "c.pixel3dmm" / "render.png").write_bytes(b"r2")  # not read: no change
    assert find_tracker_outputs(tmp_path / "c.pose").digest() == empty_face
    (tmp_path / "c.pixel3dmm" / "00000.frame").write_bytes(b"f")
    assert find_tracker_outputs(tmp_path / "c.pose").digest() != empty_face
    # the same bytes under another tracker's name are another digest
    assert TrackerOutputs(wilor=tmp_path / "c.nlf.npz").digest() != TrackerOutputs(nlf=tmp_path / "c.nlf.npz").digest()


def test_tracker_outputs_refuse_duplicates_links_outside_and_broken_links(tmp_path):
    import re

    from m3t.trackers.external import TrackerOutputs, find_tracker_outputs

    clips, elsewhere = tmp_path / "clips", tmp_path / "elsewhere"
    clips.mkdir()
    elsewhere.mkdir()
    (clips / "a.mp4").write_bytes(b"v")
    (clips / "a.wilor.npz").write_bytes(b"1")
    (clips / "a.wilor.pt").write_bytes(b"2")
    with pytest.raises(TrackerFileError, match=re.escape("two wilor outputs for a.mp4: a.wilor.npz, a.wilor.pt; "
                                                         "keep one")):
        find_tracker_outputs(clips / "a.mp4")
    (clips / "a.wilor.pt").unlink()
    (elsewhere / "n.npz").write_bytes(b"n")
    (clips / "a.nlf.npz").symlink_to(elsewhere / "n.npz")
    with pytest.raises(TrackerFileError, match=re.escape(f"nlf output {clips / 'a.nlf.npz'} leads outside the "
                                                         f"clip's folder {clips} (to {elsewhere / 'n.npz'}); tracker "
                                                         "outputs are read only beside the media: copy them there")):
        find_tracker_outputs(clips / "a.mp4")
    (clips / "a.nlf.npz").unlink()
    (clips / "a.nlf.npz").symlink_to(clips / "missing.npz")  # a broken link inside the folder is found ...
    found = find_tracker_outputs(clips / "a.mp4")
    assert found.nlf == clips / "a.nlf.npz"
    with pytest.raises(TrackerFileError, match=re.escape(f"nlf output {clips / 'a.nlf.npz'} does not exist (a "
                                                         "broken link?)")):
        found.digest()  # ... and refused when its bytes are needed
    (clips / "a.nlf.npz").unlink()
    (elsewhere / "p3").mkdir()
    (clips / "a.pixel3dmm").symlink_to(elsewhere / "p3", target_is_directory=True)
    with pytest.raises(TrackerFileError, match="pixel3dmm output .* leads outside"):
        find_tracker_outputs(clips / "a.mp4")
    (clips / "a.pixel3dmm").unlink()
    (clips / "a.pixel3dmm" / "checkpoint").mkdir(parents=True)
    (clips / "a.pixel3dmm" / "checkpoint" / "00000.frame").symlink_to(elsewhere / "n.npz")
    with pytest.raises(TrackerFileError, match=re.escape(f"pixel3dmm output "
                                                         f"{clips / 'a.pixel3dmm' / 'checkpoint' / '00000.frame'} "
                                                         "leads outside")):
        find_tracker_outputs(clips / "a.mp4")
    (clips / "a.pixel3dmm" / "checkpoint" / "00000.frame").unlink()
    (clips / "a.pixel3dmm" / "checkpoint").rmdir()
    (clips / "a.pixel3dmm" / "checkpoint").symlink_to(elsewhere / "p3", target_is_directory=True)
    with pytest.raises(TrackerFileError, match="checkpoint leads outside"):
        find_tracker_outputs(clips / "a.mp4")
    assert TrackerOutputs(nlf=clips / "a.wilor.npz").files() == {"nlf": [clips / "a.wilor.npz"]}


def test_tracker_outputs_of_a_relative_media_path_resolve_against_the_working_folder(tmp_path, monkeypatch):
    from m3t.trackers.external import find_tracker_outputs

    monkeypatch.chdir(tmp_path)
    (tmp_path / "r.mp4").write_bytes(b"v")
    (tmp_path / "r.nlf.npz").write_bytes(b"n")
    assert find_tracker_outputs("r.mp4").nlf == tmp_path / "r.nlf.npz"


# --- the simulated tracker with a stand-in body model ------------------------------------------------------------

def _sim_layout():
    from m3t.body.protocol import Modality, ModalityLayout

    return ModalityLayout((Modality("body", "rotation6d", ("a", "b")), Modality("left_hand", "rotation6d", ("f",)),
                           Modality("face", "scalar", ("x", "y", "z"), bounds=(0.0, 1.0)),
                           Modality("expr", "scalar", ("e",))), ("beta",))


def _sim_params(frames: int) -> dict:
    from m3t.body.rotations import matrix_to_6d

    rot = torch.as_tensor(np.tile(_rot_z(20), (frames, 2, 1, 1)))
    return {"body": matrix_to_6d(rot).reshape(frames, 12), "left_hand": matrix_to_6d(rot[:, :1]).reshape(frames, 6),
            "face": torch.full((frames, 3), 0.5, dtype=torch.float64), "expr": torch.zeros(frames, 1, dtype=torch.float64)}


def _angles_deg(six_a, six_b) -> np.ndarray:
    """Geodesic angles (degrees) between two (..., 6) rotation arrays."""
    import roma

    from m3t.body.rotations import sixd_to_matrix

    a, b = (sixd_to_matrix(torch.as_tensor(np.asarray(x, dtype=np.float64))) for x in (six_a, six_b))
    return torch.rad2deg(roma.rotmat_geodesic_distance(a, b)).numpy()


def test_noisy_initialisation_noises_each_stream_by_its_own_setting():
    from m3t.trackers.simulated import SimulatedTrackerConfig, noisy_initialisation

    frames, params, layout = 400, _sim_params(400), _sim_layout()
    cfg = SimulatedTrackerConfig(init_noise_deg_body=0.0, init_noise_deg_hand=10.0, init_noise_scalar=0.0)
    out = noisy_initialisation(params, layout, cfg, np.random.default_rng(0))
    assert set(out) == {"body", "left_hand", "face", "expr"} and all(v.dtype == np.float32 for v in out.values())
    assert out["body"].shape == (frames, 12) and out["face"].shape == (frames, 3)
    np.testing.assert_allclose(out["body"], params["body"].numpy(), atol=1e-6)  # float32 rounding
    np.testing.assert_allclose(out["face"], 0.5) and np.testing.assert_allclose(out["expr"], 0.0)
    hand = _angles_deg(out["left_hand"], params["left_hand"].numpy())
    # rotation vectors with N(0, 10 deg) per axis: angles average 10 * sqrt(8 / pi) deg (Maxwell); 400 samples
    assert abs(hand.mean() - 10 * np.sqrt(8 / np.pi)) < 1.5
    cfg = SimulatedTrackerConfig(init_noise_deg_body=5.0, init_noise_deg_hand=0.0, init_noise_scalar=0.2)
    out = noisy_initialisation(params, layout, cfg, np.random.default_rng(1))
    np.testing.assert_allclose(out["left_hand"], params["left_hand"].numpy(), atol=1e-6)
    body = _angles_deg(out["body"].reshape(frames, 2, 6), params["body"].numpy().reshape(frames, 2, 6))
    assert abs(body.mean() - 5 * np.sqrt(8 / np.pi)) < 0.6 and (body[:, 0] != body[:, 1]).all()  # per joint
    assert out["face"].min() >= 0.0 and out["face"].max() <= 1.0 and (out["face"] == 1.0).any()  # clipped to bounds
    assert out["expr"].min() < -0.3 and abs(out["expr"].std() - 0.2) < 0.03  # unbounded: N(0, 0.2)
    again = noisy_initialisation(params, layout, cfg, np.random.default_rng(1))
    assert all(np.array_equal(out[k], again[k]) for k in out)


def test_clip_streams_depend_on_seed_and_clip_only():
    from m3t.trackers.simulated import clip_rng

    first = clip_rng(3, "clip-a").random(4)
    assert np.array_equal(first, clip_rng(3, "clip-a").random(4))
    assert not np.array_equal(first, clip_rng(4, "clip-a").random(4))
    assert not np.array_equal(first, clip_rng(3, "clip-b").random(4))
    import zlib

    assert np.array_equal(first, np.random.default_rng([3, zlib.crc32(b"clip-a")]).random(4))


class _StandInBody:
    """What :func:`simulate_track` asks of a body model: landmark k of frame t at (x, y) = (k mod 50 + t, k // 50 + 5)
    one unit in front of the camera; the last ``invalid`` landmarks have no correspondence."""

    def __init__(self, frames: int, invalid: int = 3):
        from types import SimpleNamespace

        self.frames, self.layout = frames, _sim_layout()
        self.valid = np.ones(543, bool)
        self.valid[543 - invalid:] = False
        self.correspondence = lambda landmark_set: SimpleNamespace(valid=self.valid, landmark_set=landmark_set)
        self.keypoint_set = lambda correspondence: correspondence

    def forward_keypoints(self, params, identity, keypoint_set):
        k = torch.arange(543, dtype=torch.float32)
        t = torch.arange(self.frames, dtype=torch.float32)[:, None]
        return torch.stack([(k % 50 + t).expand(self.frames, -1), (k // 50 + 5).expand(self.frames, -1),
                            torch.ones(self.frames, 543)], -1)


def test_simulated_track_projects_corrupts_and_masks_like_a_tracker():
    from m3t.camera import Camera
    from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track

    frames = 6
    camera = Camera(1.0, 1.0, 0.0, 0.0, ((1.0, 0, 0), (0, 1.0, 0), (0, 0, 1.0)), (0.0, 0.0, 0.0), 52, 10)
    quiet = SimulatedTrackerConfig(noise_px_pose=0.0, noise_px_hand=0.0, noise_px_face=0.0, hand_dropout_prob=0.0,
                                   occlusion_prob=0.0, seed=5)
    body = _StandInBody(frames)
    track = simulate_track("c", _sim_params(frames), torch.zeros(1), camera, 30, body, quiet)
    assert track.tracker == "simulated" and track.fps == 30.0 and type(track.fps) is float
    assert track.image_size == (52, 10) and track.landmark_set == "mediapipe_holistic"
    assert track.keypoints.dtype == np.float32 and track.confidence.dtype == np.float32
    assert np.array_equal(track.intrinsics, [1.0, 1.0, 0.0, 0.0]) and track.intrinsics.dtype == np.float32
    k = np.arange(543)
    x, y = k % 50 + np.arange(frames)[:, None], np.broadcast_to(k // 50 + 5, (frames, 543))
    inside = (x < 52) & (y < 10) & body.valid
    assert (track.confidence[inside] >= 0.3).all() and (track.confidence[inside] <= 0.97).all()
    np.testing.assert_allclose(track.keypoints[inside], np.stack([x, y], -1)[inside], atol=1e-4)  # float32 projection
    assert np.isnan(track.keypoints[~inside]).all() and (track.confidence[~inside] == 0).all()
    assert (~inside[:, 540:]).all() and inside[0, 49] and not inside[3, 49]  # x = 52 leaves a 52-wide image
    assert inside[0, 249] and not inside[0, 250]  # y = 10 leaves a 10-high image
    assert set(track.init) == {"body", "left_hand", "face", "expr"}
    again = simulate_track("c", _sim_params(frames), torch.zeros(1), camera, 30, body, quiet)
    assert np.array_equal(again.confidence, track.confidence)  # the clip's own random stream
    other = simulate_track("d", _sim_params(frames), torch.zeros(1), camera, 30, body, quiet)
    assert not np.array_equal(other.confidence, track.confidence)


def test_simulated_noise_drops_hands_and_hides_the_camera_as_configured():
    from m3t.camera import Camera
    from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track

    frames = 40
    # principal point (60, 60): noisy points stay well inside the 200 x 200 image
    camera = Camera(1.0, 1.0, 60.0, 60.0, ((1.0, 0, 0), (0, 1.0, 0), (0, 0, 1.0)), (0.0, 0.0, 0.0), 200, 200)
    cfg = SimulatedTrackerConfig(noise_px_pose=0.0, noise_px_hand=2.0, noise_px_face=0.0, hand_dropout_prob=1.0,
                                 hand_dropout_max_frac=0.5, occlusion_prob=0.0, intrinsics_known=False)
    track = simulate_track("c", _sim_params(frames), torch.zeros(1), camera, 25.0, _StandInBody(frames, 0), cfg)
    assert np.isnan(track.intrinsics).all() and track.intrinsics.shape == (4,)
    parts = _holistic_parts()
    for hand in ("left_hand", "right_hand"):
        lost = np.isnan(track.keypoints[:, parts[hand], 0]).all(-1)
        assert 1 <= lost.sum() <= 20 and np.isnan(track.keypoints[:, parts[hand], 0]).any(-1).sum() == lost.sum()
        spans = np.flatnonzero(np.diff(np.r_[0, lost.astype(int), 0]))
        assert len(spans) == 2  # one contiguous span per hand
    kp, k = track.keypoints, np.arange(543)
    pose_err = kp[:, parts["pose"], 0] - (k[parts["pose"]] % 50 + np.arange(frames)[:, None] + 60)
    assert np.abs(pose_err).max() < 1e-4  # no pose noise configured
    seen = ~np.isnan(kp[:, parts["right_hand"], 0])
    hand_err = (kp[:, parts["right_hand"], 0] - (k[parts["right_hand"]] % 50 + np.arange(frames)[:, None] + 60))[seen]
    assert 1.0 < hand_err.std() < 4.0  # 2 px noise, divided by confidences in [0.3, 0.97]
    occluded = dataclasses.replace(cfg, hand_dropout_prob=0.0, occlusion_prob=1.0, noise_px_hand=0.0)
    masked = simulate_track("c", _sim_params(frames), torch.zeros(1), camera, 25.0, _StandInBody(frames, 0), occluded)
    share = np.isnan(masked.keypoints[..., 0]).mean()
    assert 0.07 < share < 0.13  # every frame occluded: 10 % of its points each


def _holistic_parts():
    from m3t.trackers.track import landmark_slices

    return landmark_slices("mediapipe_holistic")


def test_synthetic_clips_are_tracked_by_the_simulated_tracker_from_their_motion(tmp_path):
    """A synthetic clip's motion file gives the ground truth back, and tracking it is the simulated tracker on
    that motion with the clip's own random stream (the same track as calling it directly)."""
    import json
    from types import SimpleNamespace

    from m3t.camera import Camera
    from m3t.corpora.clip import Clip
    from m3t.trackers.dispatch import ground_truth, track_media
    from m3t.trackers.simulated import SimulatedTrackerConfig as Config

    frames = 4
    camera = Camera(1.0, 1.0, 60.0, 60.0, ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), (0.0, 0.0, 0.0), 200, 200)
    params = {k: v.numpy() for k, v in _sim_params(frames).items()}
    np.savez(tmp_path / "m.npz", **{f"param__{k}": v for k, v in params.items()}, identity=np.zeros(1),
             camera=np.array(json.dumps(camera.as_dict())))
    clip = Clip("s1", "synthetic", "train", "ase", "s0", "", "", "m.npz", 20.0)
    motion, identity, cam = ground_truth(clip, tmp_path)
    assert set(motion) == set(params) and np.array_equal(motion["body"], params["body"]) and cam == camera
    assert np.array_equal(identity, np.zeros(1))
    cfg = Config(seed=3)
    inputs = SimpleNamespace(mediapipe=None, simulated=cfg, body=_StandInBody(frames, 0), body_key="b")
    track = track_media(clip, tmp_path, inputs)
    direct = simulate_track("s1", _sim_params(frames), torch.zeros(1), camera, 20.0, _StandInBody(frames, 0), cfg)
    assert track.fps == 20.0 and track.tracker == "simulated" and track.image_size == (200, 200)
    np.testing.assert_array_equal(track.confidence, direct.confidence)
    np.testing.assert_allclose(track.keypoints, direct.keypoints, atol=1e-4)  # float64 vs float32 params
