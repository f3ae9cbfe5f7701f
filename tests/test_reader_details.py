"""Behaviour details of the corpus readers (m3t.corpora) and the shard files (m3t.shards) that the coarser
corpus and shard tests do not pin down.

Written to pin behaviours that mutation testing found unchecked: what a reader's error message names (the file,
the clip folder, the metadata key), which row a quarantine record points at, the defaults a listed clip gets for
columns its source leaves empty, how a 2D or partly masked ``.pose`` body is read, the geometry of the synthetic
corpus (signers stand upright and face the camera, movements stay bounded, the idle sway is subtle) and how it is
written (atomically, through a hidden temporary sibling folder), and the edge cases of shard validation.
"""
from __future__ import annotations

import csv
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import roma
import torch

import corpus_fixtures as fx
from m3t.body.protocol import Modality, ModalityLayout
from m3t.body.rotations import sixd_to_matrix
from m3t.corpora import synthetic
from m3t.corpora.base import CorpusError, load_data_pickle
from m3t.corpora.clip import Clip
from m3t.corpora.config import SyntheticCorpusConfig
from m3t.corpora.fingerspelling import FingerspellingConfig, FingerspellingCorpus, lexicon_root
from m3t.corpora.fitted_pickles import SmplxSequenceError, SokeSmplxConfig, SokeSmplxCorpus, load_smplx_sequence
from m3t.corpora.nmfs_csl import NmfsCslConfig, NmfsCslCorpus
from m3t.corpora.posefile import PoseFileConfig, PoseFileCorpus, pose_data, read_pose_info
from m3t.corpora.synthetic_lexicon import SignForm
from m3t.shards.io import validate_clip, write_shard
from m3t.shards.schema import FittedClip, ShardFormatError, arrow_schema
from m3t.shards.tokens import TokenClip, TokenInfo, read_token_shard, write_token_shard


@pytest.fixture(scope="module")
def ase_rows() -> list[dict]:
    """Two ASL letter rows of the lexicon's ``data.csv`` (the spoken-to-signed wheel's own table)."""
    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        return [r for r in csv.DictReader(fh) if r["signed_language"] == "ase"][:2]


# ----------------------------------------------------------------------------------------- safe pickles
def test_missing_pickle_error_names_the_file_and_what_to_check(tmp_path):
    path = tmp_path / "train" / "clip.pkl"
    with pytest.raises(CorpusError) as err:
        load_data_pickle(path, allow_numpy=True)
    assert str(path) in str(err.value) and "not found" in str(err.value) and "corpus root" in str(err.value)


def test_unreadable_pickle_error_names_the_file(tmp_path):
    path = tmp_path / "frame.pkl"
    path.write_bytes(b"not a pickle at all")
    with pytest.raises(CorpusError, match="not a readable pickle") as err:
        load_data_pickle(path, allow_numpy=True)
    assert str(path) in str(err.value)
    with open(path, "wb") as fh:
        pickle.dump({"a": np.zeros(2, np.float32)}, fh)
    with pytest.raises(CorpusError, match="numpy.*refused") as err:
        load_data_pickle(path, allow_numpy=False)
    assert str(path) in str(err.value) and "Re-save it" in str(err.value)
    assert set(load_data_pickle(path, allow_numpy=True)) == {"a"}


# ----------------------------------------------------------------------------------------- SOKE SMPL-X fits
def test_missing_smplx_clip_folder_error_names_the_folder(tmp_path):
    folder = tmp_path / "train" / "poses" / "-fZc293MpJk_0-1-rgb_front"
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(folder)
    assert str(folder) in str(err.value) and "not found" in str(err.value)
    assert err.value.file == folder and err.value.key is None


def test_frame_mixing_both_namings_is_refused_naming_the_file_and_key(tmp_path):
    """A frame holding SOKE's ``smplx_root_pose`` and the smplx package's ``global_orient`` is ambiguous."""
    folder = tmp_path / "clip"
    folder.mkdir()
    frame = fx.smplx_frame(np.random.default_rng(0))
    frame["global_orient"] = frame["smplx_root_pose"].copy()
    with open(folder / "0.pkl", "wb") as fh:
        pickle.dump(frame, fh)
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(folder)
    message = str(err.value)
    assert str(folder / "0.pkl") in message and "'smplx_root_pose'" in message and "'global_orient'" in message
    assert err.value.file == folder / "0.pkl" and err.value.key == "smplx_root_pose"


def test_soke_clips_without_annotation_have_empty_text_and_gloss(tmp_path):
    fx.build_soke(tmp_path, "phoenix")
    listing = SokeSmplxCorpus(tmp_path, SokeSmplxConfig()).listing()
    assert len(listing.clips) == 7  # every clip folder with frames, the broken ones too (validate is off)
    assert all(c.text == "" and c.gloss == "" for c in listing.clips)
    assert all(c.signer == "unknown" and c.language == "unknown" for c in listing.clips)


def test_soke_annotation_without_gloss_column_gives_empty_gloss(tmp_path):
    fx.build_soke(tmp_path, "phoenix")
    (tmp_path / "notes.csv").write_text("id,text\nb1_0-8-rgb_front,guten morgen\n", encoding="utf-8")
    listing = SokeSmplxCorpus(tmp_path, SokeSmplxConfig(annotation="notes.csv")).listing()
    (clip,) = listing.clips
    assert (clip.id, clip.split, clip.text, clip.gloss) == ("b1_0-8-rgb_front", "dev", "guten morgen", "")
    assert clip.get("frames") == "3"


# ----------------------------------------------------------------------------------------- NMFs-CSL
def test_confusing_list_rows_are_numbered_from_line_one(tmp_path):
    fx.build_nmfs_csl(tmp_path)
    (tmp_path / "confusing.txt").write_text("0\nzwei\n\n9\n2\n", encoding="utf-8")
    corpus = NmfsCslCorpus(tmp_path, NmfsCslConfig(confusing_list="confusing.txt"))
    bad = {(q.file, q.row): q.reason for q in corpus.listing().quarantined if q.file == "confusing.txt"}
    assert bad == {("confusing.txt", 2): "'zwei' is not a class index",
                   ("confusing.txt", 4): "class 9 is not in dictionary.txt"}
    with pytest.raises(CorpusError, match=r"confusing.txt line 2: 'zwei' is not a class index"):
        corpus.subset(0)
    (tmp_path / "confusing.txt").write_text("0\n2\n", encoding="utf-8")
    assert (corpus.subset(0), corpus.subset(1), corpus.subset(2)) == ("confusing", "normal", "confusing")


# ----------------------------------------------------------------------------------------- .pose bodies
def _openpose_hand_pose(frames: int, masked: tuple[int, int] | None):
    """A 2D ``Pose`` with one OpenPose hand component (21 points, point format XYC), the layout pose-format
    itself ships for OpenPose output (``pose_format.utils.openpose.OpenPose_Hand_Component``). Confidence 0.9
    everywhere; ``masked``: (frame, point) whose coordinates are masked."""
    from pose_format import Pose
    from pose_format.numpy.pose_body import NumPyPoseBody
    from pose_format.pose_header import PoseHeader, PoseHeaderDimensions
    from pose_format.utils.openpose import OpenPose_Hand_Component

    header = PoseHeader(0.2, PoseHeaderDimensions(640, 480), [OpenPose_Hand_Component("hand_right_keypoints_2d")])
    rng = np.random.default_rng(0)
    data = np.ma.masked_array(rng.uniform(0, 400, (frames, 1, 21, 2)).astype(np.float32),
                              mask=np.zeros((frames, 1, 21, 2), bool))
    if masked is not None:
        data.mask[masked[0], 0, masked[1]] = True
    confidence = np.full((frames, 1, 21), 0.9, np.float32)
    return Pose(header, NumPyPoseBody(25.0, data, confidence))


def test_two_dimensional_pose_is_read_with_zero_depth():
    pose = _openpose_hand_pose(3, None)
    data = pose_data(pose, "hand.pose")
    assert data.points.shape == (3, 21, 3) and data.points.dtype == np.float32 and data.dims == 2
    np.testing.assert_array_equal(data.points[..., :2], np.ma.getdata(pose.body.data)[:, 0])
    assert np.all(data.points[..., 2] == 0)
    assert data.components == (("hand_right_keypoints_2d", 21),) and (data.width, data.height) == (640, 480)
    assert data.fps == 25.0 and data.point_names[0][0] == "BASE"


def test_masked_pose_points_get_zero_confidence():
    data = pose_data(_openpose_hand_pose(4, masked=(2, 5)), "hand.pose")
    assert data.confidence.shape == (4, 21) and data.confidence.dtype == np.float32
    assert data.confidence[2, 5] == 0.0
    expected = np.full((4, 21), 0.9, np.float32)
    expected[2, 5] = 0.0
    np.testing.assert_array_equal(data.confidence, expected)


def test_pose_body_without_frames_or_person_is_refused_naming_the_file():
    with pytest.raises(CorpusError, match="hand.pose: no frames"):
        pose_data(_openpose_hand_pose(0, None), "hand.pose")
    with pytest.raises(CorpusError, match=r"hand.pose has 1 person\(s\); person=1"):
        pose_data(_openpose_hand_pose(2, None), "hand.pose", person=1)


# ----------------------------------------------------------------------------------------- .pose collections
def test_pose_index_rows_with_empty_language_and_signer_default_to_unknown(tmp_path, ase_rows):
    (tmp_path / "p").mkdir()
    for i, row in enumerate(ase_rows):
        shutil.copyfile(lexicon_root() / row["path"], tmp_path / "p" / f"{i}.pose")
    (tmp_path / "index.csv").write_text("id,path,split,text,language,signer\n"
                                        "a,p/0.pose,train,A,,\nb,p/1.pose,test,B,ase,s1\n", encoding="utf-8")
    clips = {c.id: c for c in PoseFileCorpus(tmp_path, PoseFileConfig(index="index.csv")).listing().clips}
    assert (clips["a"].language, clips["a"].signer, clips["a"].gloss) == ("unknown", "unknown", "")
    assert (clips["b"].language, clips["b"].signer, clips["b"].text) == ("ase", "s1", "B")


def test_pose_clip_extra_records_frames_people_and_components(tmp_path, ase_rows):
    shutil.copyfile(lexicon_root() / ase_rows[0]["path"], tmp_path / "a.pose")
    (clip,) = PoseFileCorpus(tmp_path, PoseFileConfig()).listing().clips
    info = read_pose_info(tmp_path / "a.pose")
    assert info.frames > 0 and info.people == 1
    assert dict(clip.extra) == {"media_kind": "pose", "frames": str(info.frames), "people": "1",
                                "components": ",".join(f"{n}:{k}" for n, k in info.components)}
    assert clip.fps == info.fps and clip.media == "a.pose" and clip.id == "a"


def test_unreadable_letter_file_is_quarantined_naming_the_clip_and_the_relative_path(tmp_path, ase_rows):
    """A fingerspelling table in the lexicon's ``data.csv`` layout (spoken-to-signed's
    ``assets/fingerspelling_lexicon/data.csv``, e.g. ``ase/fs-stse28e9ac023b0e29ca0a3acc12dc46540.pose,en,ase,
    0,2720,A,A,0``) whose second letter file is cut in half."""
    (tmp_path / "ase").mkdir()
    good, cut = (Path(r["path"]) for r in ase_rows)
    shutil.copyfile(lexicon_root() / good, tmp_path / good)
    data = (lexicon_root() / cut).read_bytes()
    (tmp_path / cut).write_bytes(data[: len(data) // 2])
    with open(tmp_path / "data.csv", "w", encoding="utf-8", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(ase_rows[0]))
        writer.writeheader()
        writer.writerows(ase_rows)
    listing = FingerspellingCorpus(tmp_path, FingerspellingConfig(words_per_language=0)).listing()
    assert [c.id for c in listing.clips] == [f"ase-{good.stem}"]
    (q,) = listing.quarantined
    assert (q.file, q.row, q.clip_id) == ("data.csv", 3, f"ase-{cut.stem}")
    assert q.reason.startswith(f"{cut.as_posix()}: truncated") and str(tmp_path) not in q.reason


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
    shoulder, elbow = synthetic._movement(_sign("tap"), frames, amplitude)
    assert np.all(np.isfinite(elbow)) and np.all(shoulder == 0)
    assert np.all(elbow[:, 1:] == 0)  # the bend is about one axis
    bend = np.degrees(elbow[:, 0])
    assert bend.min() >= 0 and 5 * amplitude < bend.max() <= 12 * amplitude
    taps = np.sum((bend[1:] > 0) & (bend[:-1] == 0)) + (bend[0] > 0)
    assert taps == 3
    np.testing.assert_allclose(synthetic._movement(_sign("tap"), frames, 2 * amplitude)[1], 2 * elbow)
    for other in ("straight", "arc", "circle", "repeat", "hold"):
        assert np.all(synthetic._movement(_sign(other), frames, amplitude)[1] == 0)


@pytest.mark.parametrize("axis", [(0.0, 0.0, 1.0), (0.3, 0.2, 0.93), (-0.2, -0.3, -0.93), (0.6, 0.0, 0.8),
                                  (0.48, -0.6, 0.64)])
def test_circle_is_a_closed_loop_about_the_sign_axis_starting_at_a_body_anchored_phase(axis):
    """A circle turns the shoulder about directions perpendicular to the sign's axis, at a constant radius, and
    ends where it started; its phase is anchored to the body: it starts turning about a horizontal direction
    (or, for a near-vertical axis, a direction in the sagittal plane), the same for every performance."""
    axis = np.asarray(axis) / np.linalg.norm(axis)
    amplitude, frames = 0.9, 41
    shoulder, elbow = synthetic._movement(_sign("circle", axis), frames, amplitude)
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
    s = {m: synthetic._movement(_sign(m, axis), 21, 1.0)[0] for m in ("straight", "arc", "repeat", "hold")}
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
    face = synthetic._face_curve(_sign("hold", mouthing=("a", "o"), brows="raise", eyes="blink"), 41, labels)
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
    three = synthetic._face_curve(_sign("hold", mouthing=("m", "a", "u")), 31, labels)
    pucker = three[:, col["mouthPucker"]]  # "u" only: the last third
    np.testing.assert_allclose(pucker[:21], 0, atol=1e-6)
    assert pucker[25] == pytest.approx(0.8) and pucker[25] == pucker.max()
    squint = synthetic._face_curve(_sign("hold", eyes="squint"), 41, labels)[:, col["eyeSquintLeft"]]
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


def _rest_calibration() -> synthetic.Calibration:
    from m3t.corpora.synthetic_lexicon import LOCATIONS

    return synthetic.Calibration(np.zeros((15, 3)), {k: np.zeros((4, 3)) for k in LOCATIONS}, np.zeros((4, 3)))


def test_idle_sway_is_subtle_and_centred_on_the_signers_posture(body):
    """The spine sways by under 2 degrees around the signer's own posture, once per clip."""
    cfg = SyntheticCorpusConfig()
    synth = synthetic.Synthesiser(body, _rest_calibration(), cfg)
    posture = np.deg2rad([2.0, -1.0, 1.5])
    signer = synthetic.Signer("s", np.full(6, 0.5), 1.0, 1.0, posture)
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
def _tiny_clip(i: int) -> synthetic.SyntheticClip:
    clip = Clip(id=f"iso-house-signer00-{i}", corpus="synthetic", split="train", language="ISO-SYN",
                signer="signer00", text="家 (house)", gloss="HOUSE", media=f"motion/iso-house-signer00-{i}.npz", fps=25.0,
                label=0, extra=(("kind", "isolated"),))
    cam = synthetic._camera(np.random.default_rng(i), 64)
    return synthetic.SyntheticClip(clip, {"body": np.full((3, 6), i, np.float32)}, np.full(6, 0.5, np.float32), cam)


def test_corpus_is_written_through_a_hidden_temporary_sibling(tmp_path, monkeypatch):
    root = tmp_path / "data" / "synthetic"
    (tmp_path / "data" / "other").mkdir(parents=True)
    seen = []
    real_replace = os.replace

    def spy(src, dst):
        seen.append((Path(src), Path(dst), sorted(os.listdir(Path(dst).parent))))
        return real_replace(src, dst)

    monkeypatch.setattr(synthetic.os, "replace", spy)
    synthetic.write_corpus([_tiny_clip(0)], root)
    (src, dst, entries), = seen
    assert dst == root and src.parent == root.parent and src.name.startswith(".synthetic.")
    assert [e for e in entries if not e.startswith(".")] == ["other"]  # no half-written corpus in plain sight
    assert sorted(os.listdir(root.parent)) == ["other", "synthetic"]
    reader = synthetic.SyntheticCorpus(root)
    (clip,) = reader.clips()
    assert clip == _tiny_clip(0).clip
    assert "家 (house)" in (root / "clips.jsonl").read_text(encoding="utf-8")  # the index stays readable text
    params, identity, camera = reader.ground_truth(clip)
    np.testing.assert_array_equal(params["body"], np.zeros((3, 6), np.float32))
    assert camera == _tiny_clip(0).camera and identity.shape == (6,)

    seen.clear()
    synthetic.write_corpus([_tiny_clip(1), _tiny_clip(2)], root)  # replaces the old corpus as a whole
    assert [s.name.startswith(".synthetic.") for s, _, _ in seen] == [False, True]  # old moved aside, new in
    assert [c.id for c in synthetic.SyntheticCorpus(root).clips()] == ["iso-house-signer00-1", "iso-house-signer00-2"]
    assert sorted(os.listdir(root / "motion")) == ["iso-house-signer00-1.npz", "iso-house-signer00-2.npz"]
    assert sorted(os.listdir(root.parent)) == ["other", "synthetic"]


def test_failed_corpus_write_leaves_the_old_corpus_and_no_temporary_folder(tmp_path):
    root = tmp_path / "data" / "corpora" / "synthetic"  # folders created as needed
    synthetic.write_corpus([_tiny_clip(0)], root)
    broken = _tiny_clip(1)
    broken = synthetic.SyntheticClip(Clip(**{**broken.clip.__dict__, "media": "missing_dir/x.npz"}),
                                     broken.params, broken.identity, broken.camera)
    with pytest.raises(OSError):
        synthetic.write_corpus([_tiny_clip(1), broken], root)
    assert sorted(os.listdir(root.parent)) == ["synthetic"]
    assert [c.id for c in synthetic.SyntheticCorpus(root).clips()] == ["iso-house-signer00-0"]


# ----------------------------------------------------------------------------------------- shards
LAYOUT = ModalityLayout(
    modalities=(Modality("body", "rotation6d", ("pelvis",)), Modality("face", "scalar", ("jaw_open",))),
    identity_labels=("height", "weight"),
)


def _fitted(frames: int, layout: ModalityLayout = LAYOUT, cid: str = "csl-0007") -> FittedClip:
    clip = Clip(id=cid, corpus="toy", split="train", language="CSL", signer="s1", text="你好", gloss="你好",
                media=f"video/{cid}.mp4", fps=25.0)
    params = {m.name: np.zeros((frames, m.dim), np.float32) for m in layout.modalities}
    return FittedClip(clip, "sha256:0", params, np.zeros(layout.identity_dim, np.float32), {}, {}, "anny")


def test_a_one_frame_clip_is_valid_and_a_clip_without_frames_is_refused(tmp_path):
    validate_clip(_fitted(1), LAYOUT)
    path = write_shard(tmp_path / "one.parquet", [_fitted(1)], LAYOUT)
    assert pq.read_metadata(path).num_rows == 1
    with pytest.raises(ValueError, match=r"clip 'csl-0007': has no frames"):
        validate_clip(_fitted(0), LAYOUT)
    with pytest.raises(ValueError, match=r"clip 'csl-0007', modality 'face': 2 frames, other modalities have 3"):
        validate_clip(FittedClip(**{**_fitted(3).__dict__, "params": {"body": np.zeros((3, 6), np.float32),
                                                                       "face": np.zeros((2, 1), np.float32)}}), LAYOUT)


def test_schema_accepts_width_one_streams_and_refuses_empty_ones():
    one = ModalityLayout((Modality("face", "scalar", ("jaw_open",)),), ("height",))
    schema = arrow_schema(one)
    assert schema.field("face").type.value_type.list_size == 1 and schema.field("identity").type.list_size == 1
    empty = ModalityLayout((Modality("face", "scalar", ()), Modality("body", "rotation6d", ("pelvis",))), ("h",))
    with pytest.raises(ValueError, match=r"streams \['face'\] have dim 0"):
        arrow_schema(empty)
    with pytest.raises(ValueError, match=r"streams \['identity'\] have dim 0"):
        arrow_schema(ModalityLayout((Modality("face", "scalar", ("jaw_open",)),), ()))


def test_token_shard_with_unparsable_metadata_names_the_file_and_key(tmp_path):
    info = TokenInfo({"body": 8}, 4, {"body": "sha256:ab"})
    clip = TokenClip(_fitted(1).clip, 5, {"body": np.array([1, 7])})
    path = write_token_shard(tmp_path / "tokens.parquet", [clip], info)
    assert read_token_shard(path).clips[0].tokens["body"].tolist() == [1, 7]
    table = pq.read_table(path)
    for bad in (b"{not json", b'{"streams": {"body": 8}}', b'{"streams": [], "downsample": 4, "tokenizers": {}}'):
        meta = dict(table.schema.metadata) | {b"m3t.tokens": bad}
        pq.write_table(table.replace_schema_metadata(meta), tmp_path / "bad.parquet")
        with pytest.raises(ShardFormatError) as err:
            read_token_shard(tmp_path / "bad.parquet")
        message = str(err.value)
        assert str(tmp_path / "bad.parquet") in message and "m3t.tokens metadata" in message
        assert "rerun the tokenize stage" in message


@pytest.mark.parametrize("kind", ["body", "holistic"])
def test_skeleton_clip_poses_the_fit_into_the_graph_and_normalises_it(body, kind):
    from m3t.body.skeleton import denormalise, graph_for
    from m3t.shards.skeletons import SKELETON_STREAM, skeleton_clip

    graph = graph_for(kind)
    params = {k: v.numpy() for k, v in body.rest_params(2).items()}
    fitted = FittedClip(_fitted(2).clip, "sha256:1", params, body.default_identity().numpy(), {}, {}, body.name)
    sk = skeleton_clip(body, fitted, graph)
    assert sk.clip_id == "csl-0007" and sk.points.shape == (2, len(graph.joints), 3)
    assert sk.coords.shape == (2, graph.width) and sk.coords.dtype == np.float32
    left, right = graph.index("body:left_shoulder"), graph.index("body:right_shoulder")
    width = np.linalg.norm(sk.points[:, left] - sk.points[:, right], axis=-1).mean()
    assert 0.2 < sk.scale < 0.5 and sk.scale == pytest.approx(width)  # metres: an adult's shoulder width
    np.testing.assert_allclose(sk.coords[:, :3], 0, atol=1e-6)  # neck-centred
    np.testing.assert_allclose(denormalise(sk.coords, graph, sk.scale), sk.points - sk.points[:, :1], atol=1e-5)
    as_fitted = sk.as_fitted()
    assert set(as_fitted.params) == {SKELETON_STREAM} and as_fitted.clip == fitted.clip
    broken = {k: v.copy() for k, v in params.items()}
    broken["body"][:] = np.nan
    with pytest.raises(ValueError, match=r"clip 'csl-0007': skeleton .*degenerate clip"):
        skeleton_clip(body, FittedClip(fitted.clip, "k", broken, fitted.identity, {}, {}, body.name), graph)


def test_token_shard_reader_refuses_other_files_naming_the_file_and_the_fix(tmp_path):
    info = TokenInfo({"body": 8, "face": 4}, 2, {"body": "sha256:ab", "face": "sha256:cd"})
    clips = [TokenClip(_fitted(1, cid=f"c{i}").clip, 3, {"body": np.array([i, 7]), "face": np.array([3, 0])})
             for i in range(2)]
    path = write_token_shard(tmp_path / "tokens.parquet", clips, info)
    shard = read_token_shard(path)
    assert shard.path == path and shard.info == info and [c.clip.id for c in shard.clips] == ["c0", "c1"]
    assert shard.clips[1].num_frames == 3 and shard.clips[1].tokens["face"].dtype == np.int64
    table = pq.read_table(path)
    meta = dict(table.schema.metadata)
    cases = {
        "no_meta": (table.replace_schema_metadata({}), r"not an m3t token shard of version 1 \(found none\)"),
        "version_2": (table.replace_schema_metadata(meta | {b"m3t.token_schema_version": b"2"}), r"\(found 2\)"),
        "no_info": (table.replace_schema_metadata({b"m3t.token_schema_version": b"1"}), r"\(found 1\)"),
        "no_face": (table.drop(["face"]), r"columns \['face'\] missing"),
        "bad_row": (table.set_column(table.schema.get_field_index("num_frames"), "num_frames",
                                     pa.array([3, 9], pa.int32())).replace_schema_metadata(meta),
                    r"row 1 \(0-based\): clip 'c1', stream 'body': 2 tokens, expected ceil\(9 / 2\) = 5"),
    }
    for name, (bad, fragment) in cases.items():
        pq.write_table(bad, tmp_path / f"{name}.parquet")
        with pytest.raises(ShardFormatError, match=fragment) as err:
            read_token_shard(tmp_path / f"{name}.parquet")
        assert str(tmp_path / f"{name}.parquet") in str(err.value) and "rerun the tokenize stage" in str(err.value)
