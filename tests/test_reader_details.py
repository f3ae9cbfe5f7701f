"""Behaviour details of the corpus readers (m3t.corpora) and the shard files (m3t.shards) that the coarser
corpus and shard tests do not pin down.

Written to pin behaviours that mutation testing found unchecked: what a reader's error message names (the file,
the clip folder, the line and byte, the metadata key) and the fix it advises, every field of a quarantine record,
the defaults a listed clip gets for columns its source leaves empty, the media kind a clip's extra starts with,
how text files split into lines, which keys a SOKE frame keeps when renamed, how a 2D or partly masked ``.pose``
body is read and how letter clips are resampled, that splits and spelled words are
reproducible, the geometry of the synthetic corpus (signers stand upright and face the camera, hand targets lie in
front of the body within reach, movements stay bounded and circles turn one way, the idle sway is subtle), the
synthetic lexicon's constraints (minimal pairs, distinct manual forms, sentence lengths), how the corpus is written
(atomically, through a hidden temporary sibling folder), and the edge cases of shard validation.
"""
from __future__ import annotations

import csv
import gzip
import json
import os
import pickle
import shutil
import struct
from pathlib import Path, PurePosixPath

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
from m3t.corpora.base import (
    CORPORA,
    Collector,
    CorpusError,
    Quarantined,
    adapter_class,
    check_fractions,
    hash_split,
    hash_unit,
    load_data_pickle,
    media_path_problem,
    read_lines,
    with_kind,
)
from m3t.corpora.clip import Clip
from m3t.corpora.config import SyntheticCorpusConfig
from m3t.corpora.csl_daily import INFO_KEYS, CslDailyConfig, CslDailyCorpus, _record
from m3t.corpora.fingerspelling import (
    FingerspellingConfig,
    FingerspellingCorpus,
    concatenate,
    lexicon_root,
    resample,
    spelled_paths,
)
from m3t.corpora.fitted_pickles import (
    SltPickleCorpus,
    SmplxSequenceError,
    SokeSmplxConfig,
    SokeSmplxCorpus,
    load_smplx_sequence,
)
from m3t.corpora.how2sign import How2SignConfig, How2SignCorpus
from m3t.corpora.mead import MeadCorpus, read_flame_params
from m3t.corpora.nmfs_csl import NmfsCslConfig, NmfsCslCorpus
from m3t.corpora.phoenix14t import Phoenix14TCorpus
from m3t.corpora.posefile import PoseData, PoseFileConfig, PoseFileCorpus, pose_data, read_pose, read_pose_info
from m3t.corpora.synthetic_lexicon import CONCEPTS, LANGUAGES, VISEMES, SignForm, build_lexicon, make_sentence
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


# ----------------------------------------------------------------------------------------- shared reader pieces
def test_quarantine_record_names_files_inside_the_root_relatively_and_others_in_full(tmp_path):
    out = Collector(tmp_path / "corpus")
    out.quarantine(tmp_path / "corpus" / "lists" / "train.txt", 4, "clip-4", "missing media")
    elsewhere = tmp_path / "shared" / "annotations.csv"
    out.quarantine(elsewhere, 2, None, "empty name")
    assert out.listing().quarantined == (Quarantined("lists/train.txt", 4, "clip-4", "missing media"),
                                         Quarantined(str(elsewhere), 2, None, "empty name"))
    assert out.listing().clips == ()


def test_media_leaving_the_root_through_a_link_is_refused_with_the_fix(tmp_path):
    root, outside = tmp_path / "corpus", tmp_path / "elsewhere"
    (outside / "clip").mkdir(parents=True)
    root.mkdir()
    (root / "inside").mkdir()
    (root / "link").symlink_to(outside, target_is_directory=True)
    reason = media_path_problem(root, "link/clip/0.png")
    assert reason.startswith("unsafe media path: 'link/clip/0.png' resolves outside the corpus root")
    assert str(outside.resolve() / "clip" / "0.png") in reason
    assert reason.endswith("through a symbolic link; move the media under the root, or point the root at a folder "
                           "that holds it")
    assert media_path_problem(root, "inside/0.png") is None
    out = Collector(root)
    assert out.media_problem("link/clip/0.png") == reason and out.media_problem("inside/0.png") is None


def test_read_lines_splits_at_newlines_only_and_drops_one_final_newline(tmp_path):
    path = tmp_path / "list.txt"
    cases = {b"": [], b"a": ["a"], b"a\n": ["a"], b"a\n\n": ["a", ""], b"a\n\nb": ["a", "", "b"],
             b"\xef\xbb\xbfa\r\nb\r\n": ["a", "b"], "x\u2028y\u0085z\nw\n".encode(): ["x\u2028y\u0085z", "w"],
             b"\n": [""]}
    for data, expected in cases.items():
        path.write_bytes(data)
        assert read_lines(path, "hint") == expected, data


def test_read_lines_errors_name_the_file_the_line_the_bytes_and_the_fix(tmp_path):
    path = tmp_path / "split_1.txt"
    with pytest.raises(CorpusError) as err:
        read_lines(path, "Point the root at the corpus.")
    assert str(err.value) == f"{path} not found. Point the root at the corpus."
    path.write_bytes(b"\xef\xbb\xbfname|split\nS1|tr\xe9in\n")  # one Latin-1 byte on line 2
    with pytest.raises(CorpusError) as err:
        read_lines(path, "Point the root at the corpus.")
    message = str(err.value)
    assert message.startswith(f"{path} line 2 (byte 19): not UTF-8 text (")
    bad = repr(b"\xe9in\n")  # the first bad byte and the three after it
    assert f"{bad}); re-save the file as UTF-8. Point the root at the corpus." in message


# ----------------------------------------------------------------------------------------- CSL-Daily pickle
def test_csl_daily_pickle_without_info_list_is_refused_naming_what_it_holds(tmp_path):
    """The annotation pickle must be the release's dict with an ``info`` list (see ``build_csl_daily``)."""
    fx.build_csl_daily(tmp_path)
    corpus = CslDailyCorpus(tmp_path)
    path = tmp_path / "sentence_label" / "csl2020ct_v2.pkl"
    info = corpus.read_info()
    assert info[0]["name"] == "S000000_P0000_T00" and fx.CSL_REAL_INFO in info and len(info) == 12
    for payload, found in (({"gloss_map": ["你"], "char_map": []}, "['char_map', 'gloss_map']"),
                           ({"info": "S000007_P0003_T00"}, "['info']"), ([fx.CSL_REAL_INFO], "list")):
        with open(path, "wb") as fh:
            pickle.dump(payload, fh)
        with pytest.raises(CorpusError) as err:
            corpus.read_info()
        assert str(err.value).startswith(f"{path}: expected a dict with an 'info' list of clip records, "
                                         f"found {found}. Point the corpus root at the CSL-Daily folder")


# ----------------------------------------------------------------------------------------- fingerspelling lexicon
def _letter_table(root: Path, rows: list[dict], extra_lines: tuple[str, ...] = ()) -> Path:
    """A copy of ``rows`` of the lexicon's ``data.csv`` (spoken-to-signed's ``assets/fingerspelling_lexicon/
    data.csv``, e.g. ``ase/fs-stse28e9ac023b0e29ca0a3acc12dc46540.pose,en,ase,0,2720,A,A,0``) with their real
    ``.pose`` files, plus ``extra_lines`` appended verbatim."""
    for r in rows:
        (root / r["path"]).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(lexicon_root() / r["path"], root / r["path"])
    with open(root / "data.csv", "w", encoding="utf-8", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        fh.writelines(line + "\n" for line in extra_lines)
    return root / "data.csv"


@pytest.fixture(scope="module")
def ase_letters() -> list[dict]:
    """The first four ASL letter rows (A, B, C, D) of the lexicon's ``data.csv``."""
    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        return [r for r in csv.DictReader(fh) if r["signed_language"] == "ase"][:4]


def test_letter_table_quarantines_paths_leaving_the_lexicon_and_repeated_letters(tmp_path, ase_letters):
    table = _letter_table(tmp_path, ase_letters[:2], (
        "../ase/escape.pose,en,ase,0,100,E,E,0",
        "ase/../../escape.pose,en,ase,0,100,F,F,0",
        "/abs/ase/g.pose,en,ase,0,100,G,G,0",
        "ase/again.pose,en,ase,0,100,a,a,0",
        "ase/h.pose,en,ase,0,100,,,0",
        "ase/i.pose,en,ase,0,100,I,I,0,extra"))
    out = Collector(tmp_path)
    letters = FingerspellingCorpus(tmp_path).table(out)
    assert [(x.letter, x.language, x.label, x.row, x.path) for x in letters] == [
        ("A", "ase", 0, 2, ase_letters[0]["path"]), ("B", "ase", 1, 3, ase_letters[1]["path"])]
    assert (letters[0].spoken_language, letters[0].start_ms, letters[0].end_ms) == ("en", "0", ase_letters[0]["end"])
    malformed = "malformed row: empty signed_language, words or path, or extra columns"
    assert out.listing().quarantined == (
        Quarantined("data.csv", 4, None, "path ../ase/escape.pose must be relative to the lexicon folder"),
        Quarantined("data.csv", 5, None, "path ase/../../escape.pose must be relative to the lexicon folder"),
        Quarantined("data.csv", 6, None, "path /abs/ase/g.pose must be relative to the lexicon folder"),
        Quarantined("data.csv", 7, None, "letter 'a' listed twice for ase"),
        Quarantined("data.csv", 8, None, malformed), Quarantined("data.csv", 9, None, malformed))
    assert [x.letter for x in FingerspellingCorpus(tmp_path).table()] == ["A", "B"]  # without a collector: skipped
    table.unlink()
    with pytest.raises(CorpusError) as err:
        FingerspellingCorpus(tmp_path).table()
    assert str(err.value) == f"{table} not found. Reinstall spoken-to-signed."


def test_fingerspelling_splits_and_spelled_words_are_reproducible(tmp_path, ase_letters):
    """Splits and the drawn words are part of the data version: a re-listing must give the same ones (pinned),
    and every clip, letter or word, takes the corpus's hash split of its id."""
    _letter_table(tmp_path, ase_letters)
    fractions = (0.4, 0.3, 0.3)
    cfg = FingerspellingConfig(words_per_language=3, max_letters=3, split_fractions=fractions, seed=1)
    clips = FingerspellingCorpus(tmp_path, cfg).listing().clips
    assert [(c.text, c.split) for c in clips] == [("A", "train"), ("B", "train"), ("C", "test"), ("D", "train"),
                                                   ("BC", "dev"), ("CD", "test"), ("DC", "test")]
    assert all(c.split == hash_split(c.id, fractions, "fingerspelling") for c in clips)
    words = FingerspellingCorpus(tmp_path, FingerspellingConfig(words_per_language=3, max_letters=3)).listing().clips
    assert [(c.id, c.text, c.gloss) for c in words[4:]] == [("ase-spelled-000", "BA", "B A"),
                                                            ("ase-spelled-001", "CD", "C D"),
                                                            ("ase-spelled-002", "CDC", "C D C")]
    frames = {c.text: int(c.get("frames")) for c in words}
    assert [int(c.get("frames")) for c in words[4:]] == [frames["B"] + frames["A"], frames["C"] + frames["D"],
                                                         2 * frames["C"] + frames["D"]]
    letter = {c.text: c.media for c in words[:4]}
    assert words[6].get("letter_paths") == "|".join(letter[x] for x in "CDC") and words[6].media == "ase"
    assert spelled_paths(words[6], tmp_path) == [tmp_path / letter[x] for x in "CDC"]


def test_spelled_clip_without_letter_paths_is_refused_naming_the_clip(tmp_path):
    clip = Clip(id="ase-spelled-007", corpus="fingerspelling", split="train", language="ase", signer="unknown",
                text="AB", gloss="A B", media="ase", fps=25.0, extra=(("media_kind", "spelled"),))
    with pytest.raises(CorpusError) as err:
        spelled_paths(clip, tmp_path)
    assert str(err.value) == "spelled clip ase-spelled-007 lists no letter_paths; re-list the fingerspelling corpus"
    one = Clip(**{**clip.__dict__, "extra": (("letter_paths", "ase/a.pose"),)})
    assert spelled_paths(one, tmp_path) == [tmp_path / "ase" / "a.pose"]


def _pose_data(points: np.ndarray, confidence: np.ndarray, fps: float) -> PoseData:
    return PoseData(points.astype(np.float32), confidence.astype(np.float32), fps, (("hand", points.shape[1]),),
                    640, 480)


def test_resample_interpolates_seen_points_and_takes_the_nearest_frame_otherwise():
    """Linear in time where both neighbouring frames see a point (its confidence too); nearest frame otherwise."""
    T = 5
    points = np.zeros((T, 2, 3))
    points[:, :, 0] = np.arange(T)[:, None] * 10.0  # x = 10 t
    confidence = np.tile([[0.2, 0.9]], (T, 1))
    confidence[:, 0] = [0.2, 0.6, 0.2, 0.6, 0.2]
    confidence[2, 1] = 0.0  # point 1 unseen at frame 2
    data = _pose_data(points, confidence, 25.0)
    up = resample(data, 50.0)
    assert up.points.shape == (10, 2, 3) and up.confidence.shape == (10, 2) and up.fps == 50.0
    assert up.points.dtype == np.float32 and up.confidence.dtype == np.float32
    np.testing.assert_allclose(up.points[:, 0, 0], [0, 5, 10, 15, 20, 25, 30, 35, 40, 40])  # the last frame held
    np.testing.assert_allclose(up.confidence[:, 0], [0.2, 0.4, 0.6, 0.4, 0.2, 0.4, 0.6, 0.4, 0.2, 0.2], rtol=1e-6)
    # point 1 at frames 1.5 and 2.5 has one unseen neighbour: nearest frame (2 and 3), not a blend
    np.testing.assert_allclose(up.points[[3, 5], 1, 0], [20.0, 30.0])
    np.testing.assert_allclose(up.confidence[[3, 4, 5], 1], [0.0, 0.0, 0.9])
    np.testing.assert_allclose(up.confidence[[1, 7], 1], [0.9, 0.9])
    assert resample(data, 25.0) is data
    near = resample(_pose_data(np.zeros((100, 1, 3)), np.ones((100, 1)), 25.0), 25.5)  # a small rate change
    assert near.points.shape[0] == 102 and near.fps == 25.5
    down = resample(_pose_data(np.zeros((3, 1, 3)), np.ones((3, 1)), 50.0), 10.0)
    assert down.points.shape[0] == 1  # never fewer than one frame


# ----------------------------------------------------------------------------------------- SMPL-X fits, slt pickles
def _write_frames(folder: Path, frames: list[dict]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for n, frame in enumerate(frames):
        with open(folder / f"{n}.pkl", "wb") as fh:
            pickle.dump(frame, fh)


def test_smplx_export_names_are_read_in_both_array_shapes_and_checked_per_key(tmp_path):
    """Exports with the smplx package's names (``fx.smplx_frame(names="smplx")``) store (D,) or (1, D) arrays;
    both stack to (T, D). A wrong or missing key is named as the file names it."""
    rng = np.random.default_rng(4)
    frames = [fx.smplx_frame(rng, names="smplx") for _ in range(3)]
    frames[1] = {k: v[None] for k, v in frames[1].items()}  # (1, D), as some exporters write
    _write_frames(tmp_path / "clip", frames)
    seq = load_smplx_sequence(tmp_path / "clip")
    assert {k: v.shape for k, v in seq.items()} == {
        "global_orient": (3, 3), "body_pose": (3, 63), "left_hand_pose": (3, 45), "right_hand_pose": (3, 45),
        "jaw_pose": (3, 3), "expression": (3, 10), "betas": (3, 10), "transl": (3, 3)}
    np.testing.assert_array_equal(seq["body_pose"][1], frames[1]["body_pose"][0])

    missing = [dict(f) for f in frames]
    del missing[2]["body_pose"]
    _write_frames(tmp_path / "missing", missing)
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(tmp_path / "missing")
    assert str(err.value) == f"{tmp_path / 'missing' / '2.pkl'}: SMPL-X key 'body_pose' missing"
    assert (err.value.file, err.value.key) == (tmp_path / "missing" / "2.pkl", "body_pose")

    for key, width, names in (("global_orient", 4, "smplx"), ("smplx_root_pose", 4, "soke"),
                              ("right_hand_pose", 48, "smplx"), ("transl", 2, "smplx")):
        frame = fx.smplx_frame(rng, names=names)
        frame[key] = np.zeros(width, np.float32)
        _write_frames(tmp_path / key, [frame])
        with pytest.raises(SmplxSequenceError) as err:
            load_smplx_sequence(tmp_path / key)
        expected = {"transl": 3, "right_hand_pose": 45}.get(key, 3)
        assert str(err.value) == f"{tmp_path / key / '0.pkl'}: key {key!r} has {width} values; expected {expected}"
        assert (err.value.file, err.value.key) == (tmp_path / key / "0.pkl", key)

    without_transl = {k: v for k, v in fx.smplx_frame(rng, names="smplx").items() if k != "transl"}
    for name, pair, expected in (("late", [without_transl, frames[0]], "present but absent in 0.pkl"),
                                 ("dropped", [frames[0], without_transl], "missing (present in 0.pkl)")):
        _write_frames(tmp_path / name, pair)  # an optional key is kept only when every frame has it
        with pytest.raises(SmplxSequenceError) as err:
            load_smplx_sequence(tmp_path / name)
        assert str(err.value) == f"{tmp_path / name / '1.pkl'}: key 'transl' {expected}"
        assert (err.value.file, err.value.key) == (tmp_path / name / "1.pkl", "transl")


def test_soke_empty_clip_folder_and_repeated_annotation_id_are_quarantined_with_every_field(tmp_path):
    fx.build_soke(tmp_path, "phoenix")  # SOKE's Phoenix layout, see corpus_fixtures.build_soke
    (tmp_path / "notes.csv").write_text("id,text,gloss,signer\nb1_0-8-rgb_front,guten morgen,,\n"
                                        "c1_3-5-rgb_front,es regnet,REGEN,s3\nb1_0-8-rgb_front,noch einmal,,\n",
                                        encoding="utf-8")
    listing = SokeSmplxCorpus(tmp_path, SokeSmplxConfig(annotation="notes.csv")).listing()
    assert {c.id: (c.split, c.text, c.gloss, c.signer) for c in listing.clips} == {
        "b1_0-8-rgb_front": ("dev", "guten morgen", "", "unknown"),
        "c1_3-5-rgb_front": ("test", "es regnet", "REGEN", "s3")}
    assert listing.quarantined[0] == Quarantined("notes.csv", 4, "b1_0-8-rgb_front", "id listed twice")
    assert Quarantined("train/empty", None, "empty", "missing media (no <frame>.pkl files)") in listing.quarantined


def test_soke_clip_folder_linking_out_of_the_root_is_refused_before_it_is_read(tmp_path):
    root, outside = tmp_path / "soke", tmp_path / "elsewhere" / "clip"
    fx.build_soke(root, "phoenix")
    outside.mkdir(parents=True)  # holds no frame pickles: only the link is wrong
    (root / "train" / "escape").symlink_to(outside, target_is_directory=True)
    listing = SokeSmplxCorpus(root).listing()
    (q,) = [q for q in listing.quarantined if q.clip_id == "escape"]
    assert q.file == "train/escape" and q.row is None
    assert q.reason.startswith("unsafe media path: 'train/escape' resolves outside the corpus root")
    assert q.reason.endswith("point the root at a folder that holds it: train/escape")
    assert "escape" not in {c.id for c in listing.clips}


def test_slt_records_that_are_not_named_dicts_are_quarantined_and_clips_record_their_shape(tmp_path):
    """Records of neccam/slt's gzip pickles (``fx.slt_entries``), with the kinds of broken record one meets."""
    rng = np.random.default_rng(0)
    entries = fx.slt_entries("train", 2, rng, dims=12)
    entries += [["train/listed", "s", "", "", np.zeros((2, 3), np.float32)],
                {**fx.slt_entries("train", 1, rng)[0], "name": ""},
                {**fx.slt_entries("train", 1, rng)[0], "name": 17},
                {**fx.slt_entries("train", 1, rng)[0], "name": "train/ints", "sign": np.zeros((3, 4), np.int64)},
                {**fx.slt_entries("train", 1, rng)[0], "name": "train/none", "sign": np.zeros((0, 4), np.float32)},
                {**fx.slt_entries("train", 1, rng)[0], "name": "train/nested", "sign": [[0.5, 0.5]]}]
    with gzip.open(tmp_path / "phoenix14t.pami0.train", "wb") as fh:
        pickle.dump(entries, fh)
    listing = SltPickleCorpus(tmp_path).listing()
    assert [(c.id, c.split, c.signer, c.media) for c in listing.clips] == [
        ("train__clip0", "train", "Signer00", "phoenix14t.pami0.train"),
        ("train__clip1", "train", "Signer01", "phoenix14t.pami0.train")]
    assert [dict(c.extra) for c in listing.clips] == [
        {"media_kind": "keypoints", "index": str(i), "frames": str(5 + i), "dims": "12", "name": f"train/clip{i}"}
        for i in range(2)]
    file = "phoenix14t.pami0.train"
    q = listing.quarantined
    assert (q[0], *q[2:]) == (
        Quarantined(file, 2, None, "entry is a list, expected a dict with keys name, signer, gloss, text, sign"),
        Quarantined(file, 4, None, "name is not a non-empty string"),
        Quarantined(file, 5, "train/ints", "sign is (3, 4); expected a non-empty (T, D) float array"),
        Quarantined(file, 6, "train/none", "sign is (0, 4); expected a non-empty (T, D) float array"),
        Quarantined(file, 7, "train/nested", "sign is list; expected a non-empty (T, D) float array"))
    assert len(q) == 6 and q[1] == Quarantined(file, 3, None, "name is not a non-empty string")  # "" is no id


# ----------------------------------------------------------------------------------------- MEAD, NMFs-CSL, PHOENIX
def test_flame_files_are_read_by_suffix_and_a_missing_one_is_named(tmp_path):
    """EMOTE's release stores (1, T, D) datasets (``fx.flame_arrays(batch_axis=True)``); ``.h5`` is the same format
    as ``.hdf5``."""
    arrays = fx.flame_arrays(4, exp=100, shape=300, batch_axis=True)
    for name in ("shape_pose_cam.hdf5", "shape_pose_cam.h5"):
        fx.write_hdf5(tmp_path / name, arrays)
        params = read_flame_params(tmp_path / name)
        assert {k: v.shape for k, v in params.items()} == {"exp": (4, 100), "jaw": (4, 3), "global_pose": (4, 3),
                                                          "shape": (4, 300), "cam": (4, 3)}
        np.testing.assert_array_equal(params["jaw"], arrays["jaw"][0])
    (tmp_path / "shape_pose_cam.mat").write_bytes(b"MATLAB 5.0")
    with pytest.raises(CorpusError, match="unsupported FLAME parameter file; expected shape_pose_cam.npz or .hdf5"):
        read_flame_params(tmp_path / "shape_pose_cam.mat")
    missing = tmp_path / "M003" / "front" / "angry" / "level_1" / "001" / "shape_pose_cam.hdf5"
    with pytest.raises(CorpusError) as err:
        read_flame_params(missing)
    assert str(err.value) == f"FLAME parameter file {missing} not found"


def test_nmfs_list_blank_lines_are_skipped_and_rows_keep_their_line_numbers(tmp_path):
    fx.build_nmfs_csl(tmp_path)
    lines = (tmp_path / "train.txt").read_text(encoding="utf-8").splitlines()
    (tmp_path / "train.txt").write_text("\n".join(lines[:2] + ["", "  "] + lines[2:]) + "\n", encoding="utf-8")
    listing = NmfsCslCorpus(tmp_path).listing()
    train = [c for c in listing.clips if c.split == "train"]
    assert [c.id for c in train] == ["P01__0_01", "P01__1_01", "P02__2_01", "P02__3_01", "P03__0_02"]
    assert all(c.signer == "unknown" and c.language == "CSL" for c in listing.clips)
    assert [(q.file, q.row, q.clip_id) for q in listing.quarantined] == [
        ("train.txt", 8, "P09__9_01"), ("train.txt", 9, None), ("train.txt", 10, "P09__missing"),
        ("train.txt", 11, None)]


def test_phoenix_rows_without_name_or_frame_folder_are_quarantined_with_every_field(tmp_path):
    """Rows in the release's ``|``-separated layout (see ``fx.build_phoenix14t``) with the name or the video
    column's folder left out."""
    fixture = fx.build_phoenix14t(tmp_path)
    path = tmp_path / fx.PHOENIX_FILE.format(split="train")
    lines = path.read_text(encoding="utf-8").splitlines()
    lines.append("|26October_2010_Tuesday_tagesschau-1/1/*.png|-1|-1|Signer05|REGEN|es regnet")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    quarantined = Phoenix14TCorpus(tmp_path).listing().quarantined
    file = fx.PHOENIX_FILE.format(split="train")
    (no_folder_row,) = [row for f, row, reason in fixture.bad if "names no frame folder" in reason]
    assert Quarantined(file, no_folder_row, "train_no_folder",
                       "video column '*.png' names no frame folder; expected '<name>/1/*.png'") in quarantined
    assert quarantined[-1] == Quarantined(file, len(lines), None, "empty name")


# ----------------------------------------------------------------------------------------- .pose collections (2)
def test_truncated_pose_body_error_names_the_file_the_failure_and_the_fix(tmp_path, ase_rows):
    data = (lexicon_root() / ase_rows[0]["path"]).read_bytes()
    path = tmp_path / "cut.pose"
    path.write_bytes(data[: len(data) - 1000])  # header intact, the body cut short
    with pytest.raises(CorpusError) as err:
        read_pose(path)
    message, cause = str(err.value), err.value.__cause__
    assert cause is not None
    assert message.startswith(f"{path}: unreadable or truncated .pose file ({type(cause).__name__}: {cause})")
    assert message.endswith("; re-export it")
    with pytest.raises(CorpusError, match="does not exist; check the corpus root"):
        read_pose(tmp_path / "none.pose")


def test_pose_index_header_and_empty_fields_are_reported_naming_file_row_and_clip(tmp_path, ase_rows):
    shutil.copyfile(lexicon_root() / ase_rows[0]["path"], tmp_path / "a.pose")
    index = tmp_path / "index.csv"
    index.write_text("id,path,label\na,a.pose,0\n", encoding="utf-8")
    with pytest.raises(CorpusError) as err:
        PoseFileCorpus(tmp_path, PoseFileConfig(index="index.csv")).listing()
    assert str(err.value) == (f"{index} line 1: columns ['id', 'path', 'label'] lack ['split', 'text', 'language', "
                              "'signer']; expected id,path,split,text,language,signer and optional label")
    index.write_text("id,path,split,text,language,signer,label\na,a.pose,train,A,ase,s0,7\nnopath,,train,B,ase,s0,1\n"
                     ",a.pose,dev,C,ase,s0,2\nb,a.pose,dev,A,ase,s0,\nc,a.pose,test,A,ase,s0,-1\n", encoding="utf-8")
    listing = PoseFileCorpus(tmp_path, PoseFileConfig(index="index.csv")).listing()
    assert [(c.id, c.split, c.label) for c in listing.clips] == [("a", "train", 7), ("b", "dev", None),
                                                                  ("c", "test", -1)]
    assert listing.quarantined == (Quarantined("index.csv", 3, "nopath", "empty id or path"),
                                   Quarantined("index.csv", 4, None, "empty id or path"))


# ----------------------------------------------------------------------------------------- synthetic corpus (2)
def test_hand_targets_lie_in_front_of_the_body_within_the_arms_reach(body):
    """The right hand's targets per location (body faces -y, z up, its right is -x) are reachable by the right
    arm, lie in front of the torso, and are ordered as the locations' names say."""
    targets, rest = synthetic._targets(body)
    with torch.no_grad():
        joints = body.forward(body.rest_params(1), body.default_identity()).joints[0].numpy()
    j = {n: joints[synthetic._joint(body, n)] for n in ("head", "neck01", "upperarm01.R", "upperarm01.L",
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
    shoulder, _ = synthetic._movement(_sign("circle", axis), 33, 1.0)
    turn = np.cross(shoulder[:-1], shoulder[1:]) @ axis
    assert np.all(turn > 0)
    back, _ = synthetic._movement(_sign("circle", -axis), 33, 1.0)
    assert np.all(np.cross(back[:-1], back[1:]) @ -axis > 0)


def test_clip_index_records_without_extra_are_read_and_bad_lines_are_named(tmp_path):
    record = {k: v for k, v in _tiny_clip(0).clip.__dict__.items() if k != "extra"}
    index = tmp_path / "clips.jsonl"
    index.write_text(json.dumps(record, ensure_ascii=False) + "\n"
                     + json.dumps({**record, "id": "b", "extra": [["kind", "sentence"]]}) + "\n", encoding="utf-8")
    first, second = synthetic.SyntheticCorpus(tmp_path).clips()
    assert first == Clip(**{**record, "extra": ()}) and second.extra == (("kind", "sentence"),)
    index.write_text(json.dumps(record) + "\n" + json.dumps({"id": "x"}) + "\n", encoding="utf-8")
    with pytest.raises(ValueError, match=rf"{index} line 2: not a clip record"):
        synthetic.SyntheticCorpus(tmp_path).clips()


# ----------------------------------------------------------------------------------------- synthetic lexicon
def test_lexicon_can_be_all_minimal_pairs_but_not_more_pairs_than_signs():
    signs = build_lexicon(6, 3, np.random.default_rng(0))
    assert [s.group for s in signs] == ["confusing"] * 6 and [s.pair for s in signs] == [0, 0, 1, 1, 2, 2]
    for a, b in zip(signs[::2], signs[1::2]):
        assert a.manual() == b.manual() and a.mouthing != b.mouthing and a.brows != b.brows
    assert len(build_lexicon(5, 2, np.random.default_rng(0))) == 5
    with pytest.raises(ValueError, match=r"corpus.confusing_pairs=3 needs at least 6 signs"):
        build_lexicon(5, 3, np.random.default_rng(0))
    with pytest.raises(ValueError, match=rf"corpus.num_signs=29 exceeds the {len(CONCEPTS)} concepts"):
        build_lexicon(len(CONCEPTS) + 1, 0, np.random.default_rng(0))


@pytest.mark.parametrize("seed", range(6))
def test_normal_signs_differ_in_their_manual_form(seed):
    """Normal signs are told apart by the hands alone: no two share handshape, location, movement and
    handedness (only the minimal pairs share a manual form)."""
    signs = build_lexicon(len(CONCEPTS), 2, np.random.default_rng(seed))
    np.testing.assert_allclose([np.linalg.norm(s.axis) for s in signs], 1.0)  # movement directions are unit vectors
    normal = [s.manual()[:4] for s in signs if s.group == "normal"]
    assert len(normal) == len(CONCEPTS) - 4 and len(set(normal)) == len(normal)


def test_sentences_have_as_many_glosses_as_asked_in_each_word_order():
    signs = build_lexicon(len(CONCEPTS), 0, np.random.default_rng(1))
    rng = np.random.default_rng(2)
    for language in LANGUAGES:
        for length in (2, 3, 4):
            for _ in range(5):
                text, gloss = make_sentence(signs, language, length, rng)
                roles = [CONCEPTS[g][0] for g in gloss]
                assert len(gloss) == length and sorted(roles) == sorted(["person", "verb", "thing", "time"][:length])
                assert text and (text.endswith("。") if language == "CSL-SYN" else text[0].isupper())
    _, gloss = make_sentence(signs, "ASL-SYN", 4, np.random.default_rng(3))
    assert [CONCEPTS[g][0] for g in gloss] == ["time", "thing", "person", "verb"]


# ----------------------------------------------------------------------------------------- split rows and errors
def test_csl_daily_split_rows_without_name_or_split_are_quarantined_and_clips_carry_the_corpus_name(tmp_path):
    """Rows of ``sentence_label/split_1.txt`` (``name|split``, see ``build_csl_daily``) with one half empty."""
    fx.build_csl_daily(tmp_path)
    split_file = tmp_path / "sentence_label" / "split_1.txt"
    lines = split_file.read_text(encoding="utf-8").splitlines()
    split_file.write_text("\n".join(lines + ["|train", "S100009_P0000_T00|", "a|b|test"]) + "\n", encoding="utf-8")
    corpus = CslDailyCorpus(tmp_path)
    out = Collector(tmp_path)
    splits = corpus.read_splits(out)
    assert "" not in splits and "S100009_P0000_T00" not in splits and splits["S000004_P0000_T00"] == ("dev", 6)
    n = len(lines)
    assert out.listing().quarantined[-3:] == (
        Quarantined("sentence_label/split_1.txt", n + 1, None,
                    "malformed row: expected '<name>|<split>', found '|train'"),
        Quarantined("sentence_label/split_1.txt", n + 2, "S100009_P0000_T00",
                    "split '' unknown; expected one of train, dev, test"),
        Quarantined("sentence_label/split_1.txt", n + 3, None,
                    "malformed row: expected '<name>|<split>', found 'a|b|test'"))
    listing = corpus.listing()
    assert {c.corpus for c in listing.clips} == {"csl_daily"} and len(listing.clips) == 6


def test_smplx_clip_folders_without_usable_frames_are_refused_naming_the_folder(tmp_path):
    empty = tmp_path / "train" / "empty_clip"
    empty.mkdir(parents=True)
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(empty)
    assert (str(err.value), err.value.file, err.value.key) == (
        f"{empty}: missing media (no <frame>.pkl files)", empty, None)
    (empty / "frame.pkl").write_bytes(b"")
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(str(empty))
    assert str(err.value).startswith(f"{empty}: frame pickle frame.pkl has no frame number (expected <n>.pkl")
    assert (err.value.file, err.value.key) == (empty, None)


def test_soke_annotation_errors_name_the_file_and_malformed_rows_are_quarantined(tmp_path):
    fx.build_soke(tmp_path, "phoenix")
    corpus = SokeSmplxCorpus(tmp_path, SokeSmplxConfig(annotation="notes.csv"))
    with pytest.raises(CorpusError) as err:
        corpus.read_annotation(Collector(tmp_path))
    assert str(err.value) == (f"{tmp_path / 'notes.csv'} not found. Set corpora.soke_smplx.annotation to a CSV with "
                              f"columns id,text[,gloss,signer,language,split].")
    (tmp_path / "notes.csv").write_text("id,text\n,no id\nb1,hello,extra\nb1,ok\nb1,again\n", encoding="utf-8")
    out = Collector(tmp_path)
    rows = corpus.read_annotation(out)
    assert rows == {"b1": {"id": "b1", "text": "ok", "row": "4"}}
    assert out.listing().quarantined == (
        Quarantined("notes.csv", 2, None, "malformed row: empty id or extra columns"),
        Quarantined("notes.csv", 3, "b1", "malformed row: empty id or extra columns"),
        Quarantined("notes.csv", 5, "b1", "id listed twice"))
    assert SokeSmplxCorpus(tmp_path, SokeSmplxConfig()).read_annotation(out) is None


def test_an_slt_clip_whose_record_moved_is_refused_naming_the_file_and_clip(tmp_path):
    built = fx.build_slt(tmp_path)
    corpus = SltPickleCorpus(tmp_path)
    clip = next(c for c in corpus.listing().clips if c.split == "dev")
    assert corpus.sequence(clip).dtype == np.float32
    for extra in ((("index", "99"),), (("index", clip.get("index")), ("name", "dev/other"))):
        moved = Clip(clip.id, clip.corpus, clip.split, clip.language, clip.signer, clip.text, clip.gloss, clip.media,
                     clip.fps, extra=extra)
        with pytest.raises(CorpusError) as err:
            corpus.sequence(moved)
        index = moved.get("index")
        assert str(err.value) == (f"{tmp_path / built.extra['files']['dev']}: record {index} is no longer clip "
                                  f"{clip.id}; list the corpus again")


def test_how2sign_clip_folder_option_is_formatted_per_split(tmp_path):
    from m3t.corpora.how2sign import How2SignConfig, How2SignCorpus

    corpus = How2SignCorpus(tmp_path, How2SignConfig(clips_dir="videos/{split}/clips"))
    assert corpus.clips_dir("val") == PurePosixPath("videos/val/clips")
    assert corpus.clips_dir("train") == PurePosixPath("videos/train/clips")


def test_nmfs_dictionary_glosses_may_hold_spaces(tmp_path):
    (tmp_path / "dictionary.txt").write_text("0\t打 电话\n1 thank you very much\n", encoding="utf-8")
    assert NmfsCslCorpus(tmp_path).read_dictionary() == {0: "打 电话", 1: "thank you very much"}


def test_media_paths_are_checked_against_the_resolved_root_the_caller_gives(tmp_path):
    real = tmp_path / "corpus"
    (real / "clips").mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    os.symlink(tmp_path / "elsewhere", real / "out")
    unresolved = Path("not-a-folder-here")  # its own resolve() would accept every name
    assert media_path_problem(unresolved, "clips/a.mp4", real.resolve()) is None
    problem = media_path_problem(unresolved, "out/a.mp4", real.resolve())
    assert problem.startswith("unsafe media path: 'out/a.mp4' resolves outside the corpus root (to ")
    assert media_path_problem(real, "out/a.mp4") == problem


def test_pose_index_gloss_column_is_read_into_the_clip(tmp_path, ase_rows):
    shutil.copyfile(lexicon_root() / ase_rows[0]["path"], tmp_path / "a.pose")
    (tmp_path / "index.csv").write_text("id,path,split,text,language,signer,gloss\n"
                                        "a,a.pose,dev,hello,ase,s2,HELLO WORLD\n", encoding="utf-8")
    (clip,) = PoseFileCorpus(tmp_path, PoseFileConfig(index="index.csv")).listing().clips
    assert (clip.text, clip.gloss, clip.split, clip.corpus) == ("hello", "HELLO WORLD", "dev", "posefile")


def test_letter_rows_without_a_path_are_quarantined(tmp_path, ase_letters):
    _letter_table(tmp_path, ase_letters[:1], (",en,ase,0,100,J,J,0", "  ,en,ase,0,100,K,K,0"))
    out = Collector(tmp_path)
    assert [x.letter for x in FingerspellingCorpus(tmp_path).table(out)] == ["A"]
    malformed = "malformed row: empty signed_language, words or path, or extra columns"
    assert out.listing().quarantined == (Quarantined("data.csv", 3, None, malformed),
                                         Quarantined("data.csv", 4, None, malformed))


def test_letter_and_word_clips_say_which_they_are(tmp_path, ase_letters):
    _letter_table(tmp_path, ase_letters)
    clips = FingerspellingCorpus(tmp_path, FingerspellingConfig(words_per_language=2, max_letters=3)).listing().clips
    assert [c.get("clip_type") for c in clips] == ["letter"] * 4 + ["spelled"] * 2
    assert [c.get("media_kind") for c in clips] == ["pose"] * 4 + ["spelled"] * 2


def test_letter_clips_with_another_point_layout_anywhere_in_the_word_are_refused():
    hand = _pose_data(np.zeros((2, 2, 3)), np.ones((2, 2)), 25.0)
    other = PoseData(np.zeros((3, 2, 3), np.float32), np.ones((3, 2), np.float32), 25.0, (("face", 2),), 640, 480)
    for parts in ([hand, other], [hand, hand, other]):
        with pytest.raises(CorpusError) as err:
            concatenate(parts)
        assert str(err.value) == ("letter clips have different point layouts (hand:2 vs face:2); they cannot be "
                                  "concatenated")
    word = concatenate([hand, hand, hand])
    assert word.points.shape == (6, 2, 3) and word.confidence.shape == (6, 2) and word.fps == 25.0
    with pytest.raises(ValueError, match="the word has no letters"):
        concatenate([])


def test_make_corpus_writes_the_generated_clips_and_counts_them_per_split(tmp_path, monkeypatch):
    import m3t.body.factory as factory

    dev = _tiny_clip(2)
    dev = synthetic.SyntheticClip(Clip(**{**dev.clip.__dict__, "split": "dev"}), dev.params, dev.identity, dev.camera)
    made = [_tiny_clip(0), _tiny_clip(1), dev]
    seen = {}
    monkeypatch.setattr(factory, "load_body_model", lambda cfg: seen.setdefault("body_cfg", cfg) and "model")
    monkeypatch.setattr(synthetic, "generate_corpus", lambda cfg, model: seen.update(cfg=cfg, model=model) or made)
    cfg = SyntheticCorpusConfig()
    assert synthetic.make_corpus(cfg, "the-body-config", tmp_path / "synthetic") == {
        "clips": 3, "splits": {"train": 2, "dev": 1}}
    assert seen == {"body_cfg": "the-body-config", "cfg": cfg, "model": "model"}
    assert [c.id for c in synthetic.SyntheticCorpus(tmp_path / "synthetic").clips()] == [c.clip.id for c in made]


def test_a_performance_scales_speed_and_amplitude_within_the_jitter_and_tilts_each_posture_axis():
    signer = synthetic.Signer("signer00", np.full(6, 0.5), 1.0, 2.0, np.array([0.1, -0.2, 0.3]))
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


def test_sentence_text_follows_each_languages_word_order():
    signs = build_lexicon(28, 2, np.random.default_rng(0))
    column = {"ASL-SYN": 1, "DGS-SYN": 2, "CSL-SYN": 3}
    for language, col in column.items():
        for length in (2, 3, 4):
            for seed in range(3):
                text, gloss = make_sentence(signs, language, length, np.random.default_rng(seed))
                role = {CONCEPTS[g][0]: CONCEPTS[g][col] for g in gloss}
                s, v, o, t = (role.get(r) for r in ("person", "verb", "thing", "time"))
                if language == "ASL-SYN":
                    words = [s, v, o, t]
                elif language == "DGS-SYN":
                    words = [t, v, s, o] if t else [s, v, o]
                else:
                    words = [t, s, v, o]
                words = [x for x in words if x]
                if language == "CSL-SYN":
                    assert text == "".join(words) + "。"
                else:
                    joined = " ".join(words)
                    assert text == joined[0].upper() + joined[1:]


def test_clip_extra_starts_with_the_media_kind_and_an_unknown_kind_is_named():
    assert with_kind("pose", clip_type="letter", frames=12, gloss=None) == (
        ("media_kind", "pose"), ("clip_type", "letter"), ("frames", "12"))
    assert with_kind("synthetic") == (("media_kind", "synthetic"),)
    with pytest.raises(ValueError) as err:
        with_kind("audio", start_s=1.0)
    assert str(err.value) == ("media kind 'audio' unknown; expected one of video, frames, pose, smplx_params, "
                              "flame_params, keypoints, spelled, synthetic")


def test_soke_frames_keep_their_other_keys_and_may_not_mix_both_namings(tmp_path):
    """SOKE's keys are renamed to the smplx package's; the frame's other keys (a translation, eye poses that some
    exports add) keep their names and are stacked like in any export. A frame holding a parameter under both
    names is refused naming the file and the SOKE key."""
    rng = np.random.default_rng(5)
    frames = [fx.smplx_frame(rng) | {"transl": np.full(3, n, np.float32), "leye_pose": np.zeros(3, np.float32),
                                      "reye_pose": np.ones(3, np.float32)} for n in range(2)]
    _write_frames(tmp_path / "clip", frames)
    seq = load_smplx_sequence(tmp_path / "clip")
    assert {k: v.shape for k, v in seq.items()} == {
        "global_orient": (2, 3), "body_pose": (2, 63), "left_hand_pose": (2, 45), "right_hand_pose": (2, 45),
        "jaw_pose": (2, 3), "expression": (2, 10), "betas": (2, 10), "transl": (2, 3), "leye_pose": (2, 3),
        "reye_pose": (2, 3)}
    np.testing.assert_array_equal(seq["transl"], [[0, 0, 0], [1, 1, 1]])
    np.testing.assert_array_equal(seq["reye_pose"], np.ones((2, 3)))
    np.testing.assert_array_equal(seq["global_orient"][1], frames[1]["smplx_root_pose"])

    mixed = fx.smplx_frame(rng) | {"global_orient": np.zeros(3, np.float32)}
    _write_frames(tmp_path / "mixed", [mixed])
    with pytest.raises(SmplxSequenceError) as err:
        load_smplx_sequence(tmp_path / "mixed")
    file = tmp_path / "mixed" / "0.pkl"
    assert str(err.value) == f"{file}: holds both 'smplx_root_pose' and 'global_orient'; keep one naming"
    assert (err.value.file, err.value.key) == (file, "smplx_root_pose")


def test_python2_corpus_pickles_decode_text_as_utf8_and_array_buffers_as_latin1(tmp_path):
    """Without numpy, 8-bit strings are text (UTF-8: a Chinese gloss survives); with numpy, they are decoded as
    latin-1 so that an array's raw buffer (any byte values) rebuilds the array exactly (``numpy.load``'s
    documentation names ``encoding='latin1'`` as the one that reads Python 2 pickles holding numpy arrays)."""
    path = tmp_path / "info.pkl"
    fx.write_python2_pickle(path, {"name": "S000000_P0000_T00", "label_word": ["谢谢", "你好"]}, "utf-8")
    assert pickle.SHORT_BINSTRING + b"\x04name" in path.read_bytes()  # a Python 2 str, not unicode
    assert load_data_pickle(path, allow_numpy=False) == {"name": "S000000_P0000_T00", "label_word": ["谢谢", "你好"]}

    array = np.array([[0.5, -1.25, 3.0], [1e-3, 255.0, -7.5]], np.float32)  # buffer bytes above 0x7f
    assert max(array.tobytes()) > 0x7F
    fx.write_python2_pickle(path, {"sign": array}, "utf-8")
    loaded = load_data_pickle(path, allow_numpy=True)
    assert loaded["sign"].dtype == np.float32
    np.testing.assert_array_equal(loaded["sign"], array)
    with pytest.raises(CorpusError) as err:
        load_data_pickle(path, allow_numpy=False)
    message = str(err.value)
    assert message.startswith(f"{path}: the pickle references numpy.")
    assert "a non-data class, and was refused" in message
    assert "Re-save it holding only builtin containers, numbers, strings." in message


@pytest.mark.parametrize("module, name", [("chumpy.ch", "Ch"), ("scipy.sparse._csr", "csr_matrix"),
                                          ("torch._utils", "_rebuild_tensor_v2")])
def test_corpus_pickles_refuse_model_file_classes_naming_the_class_and_the_file(tmp_path, module, name):
    """Body-model files may hold chumpy / scipy objects (read as inert records there); a corpus file that
    references them, in a submodule too, is refused before anything is built."""
    path = tmp_path / "clip.pkl"
    path.write_bytes(b"\x80\x02}q\x00X\x01\x00\x00\x00xq\x01c" + f"{module}\n{name}\n".encode() + b")Rq\x02s.")
    for allow_numpy in (True, False):
        with pytest.raises(CorpusError) as err:
            load_data_pickle(path, allow_numpy=allow_numpy)
        message = str(err.value)
        assert message.startswith(f"{path}: the pickle references {module}.{name}, a non-data class, and was "
                                  "refused (nothing was run).")
        assert ("torch tensors are refused" in message) == (module == "torch._utils")


def test_fractions_may_leave_a_split_empty_but_must_be_three_non_negative_summing_to_one():
    for fractions in ((1.0, 0.0, 0.0), (0.9, 0.1, 0.0), (0.0, 0.5, 0.5), (0.8, 0.1, 0.1)):
        check_fractions(fractions, "corpora.x.split_fractions")
    for bad in ((0.8, 0.3, -0.1), (0.8, 0.1), (0.5, 0.3, 0.1), (0.25, 0.25, 0.25, 0.25)):
        with pytest.raises(ValueError) as err:
            check_fractions(bad, "corpora.x.split_fractions")
        assert str(err.value) == ("option corpora.x.split_fractions: expected three non-negative train/dev/test "
                                  f"fractions summing to 1, got {bad}")


def test_fingerspelling_may_spell_one_letter_words_into_one_split(tmp_path, ase_letters):
    _letter_table(tmp_path, ase_letters)
    cfg = FingerspellingConfig(words_per_language=3, min_letters=1, max_letters=1, split_fractions=(1.0, 0.0, 0.0))
    clips = FingerspellingCorpus(tmp_path, cfg).listing().clips
    words = [c for c in clips if "spelled" in c.id]
    assert len(words) == 3 and all(len(c.text) == 1 for c in words)
    assert {c.split for c in clips} == {"train"}
    assert {c.corpus for c in clips} == {"fingerspelling"} and {c.language for c in clips} == {"ase"}
    for bad in ({"min_letters": 0}, {"min_letters": 3, "max_letters": 2}, {"words_per_language": -1}):
        with pytest.raises(ValueError) as err:
            FingerspellingConfig(**bad)
        assert "need words_per_language >= 0 and 1 <= min_letters <= max_letters" in str(err.value)
    with pytest.raises(ValueError, match=r"option corpora.fingerspelling.split_fractions: .*got \(0.5, 0.5, 0.5\)"):
        FingerspellingConfig(split_fractions=(0.5, 0.5, 0.5))


def test_soke_annotation_language_and_signer_override_the_defaults(tmp_path):
    fx.build_soke(tmp_path, "phoenix")
    (tmp_path / "notes.csv").write_text("id,text,signer,language\nb1_0-8-rgb_front,guten morgen,Signer05,DGS\n"
                                        "c1_3-5-rgb_front,regen,,\n", encoding="utf-8")
    clips = SokeSmplxCorpus(tmp_path, SokeSmplxConfig(annotation="notes.csv", language="GSL")).listing().clips
    assert [(c.id, c.language, c.signer, c.corpus) for c in clips] == [
        ("b1_0-8-rgb_front", "DGS", "Signer05", "soke_smplx"), ("c1_3-5-rgb_front", "GSL", "unknown", "soke_smplx")]


@pytest.mark.parametrize("config, option, bad, good", [(How2SignConfig, "how2sign", (0.0, -24.0), 30.0),
                                                      (CslDailyConfig, "csl_daily", (0, -30.0), 25.0)])
def test_video_corpora_refuse_a_non_positive_frame_rate_naming_the_option(config, option, bad, good):
    for fps in bad:
        with pytest.raises(ValueError) as err:
            config(fps=fps)
        assert str(err.value) == f"corpora.{option}.fps must be > 0, got {fps}"
    assert config(fps=good).fps == good


def test_csl_daily_info_entry_that_is_not_a_dict_names_its_type_and_the_keys_expected():
    assert _record(["S000000_P0000_T00", 120]) == ("info entry is a list, expected a dict with keys name, length, "
                                                    "label_gloss, label_char, label_word, signer")
    assert _record("S000000_P0000_T00").startswith("info entry is a str, expected a dict with keys name, length,")
    entry = {"name": "S000000_P0000_T00", "length": 120, "label_gloss": ["你", "好"], "label_char": ["你", "好"],
             "label_word": ["你好"], "signer": 0}
    assert _record(entry) is entry and set(entry) == set(INFO_KEYS)
    assert _record({k: v for k, v in entry.items() if k != "signer"}) == "info entry lacks keys ['signer']"
    assert _record({**entry, "name": ""}) == "name '' is not a non-empty string"
    assert _record({**entry, "name": 7}) == "name 7 is not a non-empty string"
    assert _record({**entry, "label_char": "你好"}) == "label_char is not a list of strings"
    assert _record({**entry, "label_gloss": ["你", 2]}) == "label_gloss is not a list of strings"
    assert _record({**entry, "label_word": []}) == "label_word is empty (no sentence text)"


def test_nmfs_dictionary_bad_lines_are_quarantined_with_the_file_and_line(tmp_path):
    (tmp_path / "dictionary.txt").write_text("0\t谢谢\n\nx\t你好\n0 再见\n2\n3\tthank you\n", encoding="utf-8")
    out = Collector(tmp_path)
    assert NmfsCslCorpus(tmp_path).read_dictionary(out) == {0: "谢谢", 3: "thank you"}
    assert out.listing().quarantined == (
        Quarantined("dictionary.txt", 3, None, "malformed class line 'x\\t你好': expected '<index><tab or space><gloss>'"),
        Quarantined("dictionary.txt", 4, None, "class 0 defined twice"),
        Quarantined("dictionary.txt", 5, None, "malformed class line '2': expected '<index><tab or space><gloss>'"))
    with pytest.raises(CorpusError) as err:
        NmfsCslCorpus(tmp_path).read_dictionary()
    assert str(err.value).startswith(f"{tmp_path / 'dictionary.txt'} line 3: malformed class line")


def test_nmfs_dev_clips_are_drawn_from_train_by_the_documented_hash(tmp_path):
    """``dev_fraction`` moves the train clips with ``hash_unit(id, salt="nmfs_csl-dev") < dev_fraction`` (module
    docstring): the dev set is part of the data version and is pinned here."""
    fx.build_nmfs_csl(tmp_path)
    clips = NmfsCslCorpus(tmp_path, NmfsCslConfig(dev_fraction=0.5)).listing().clips
    moved = {c.id for c in clips if c.split == "dev"}
    assert moved == {c.id for c in clips if c.get("source_split") == "train"
                     and hash_unit(c.id, salt="nmfs_csl-dev") < 0.5}
    assert sorted(moved) == ["P02__2_01", "P02__3_01", "P03__0_02"]
    assert all(c.split == "test" for c in clips if c.get("source_split") == "test")
    assert {c.split for c in NmfsCslCorpus(tmp_path).listing().clips} == {"train", "test"}


def test_phoenix_clips_record_the_rows_start_and_end(tmp_path):
    fx.build_phoenix14t(tmp_path)
    path = tmp_path / fx.PHOENIX_FILE.format(split="dev")
    lines = path.read_text(encoding="utf-8").splitlines()
    name = lines[1].split("|")[0]
    lines[1] = f"{name}|{name}/1/*.png|12|87|Signer00|REGEN MORGEN|morgen regnet es"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    clips = {c.id: c for c in Phoenix14TCorpus(tmp_path).listing().clips}
    assert (clips[name].get("start"), clips[name].get("end"), clips[name].get("frame_glob")) == ("12", "87", "*.png")
    assert clips[name].get("annotation") == f"{fx.PHOENIX_FILE.format(split='dev')}:2"
    other = clips[lines[2].split("|")[0]]
    assert (other.get("start"), other.get("end")) == ("-1", "-1")


def test_arm_calibration_puts_the_knuckle_on_each_target(body):
    """The right arm's inverse kinematics reaches the middle knuckle's targets to within a centimetre."""
    torch.set_num_threads(1)
    targets, rest_target = synthetic._targets(body)
    goal = np.stack([targets["chin"], rest_target])
    rest = synthetic._stream_rest(body)
    solved = synthetic._arm_ik(body, rest, goal, steps=150)
    assert solved.shape == (2, 4, 3)
    arm_idx = [body.layout["body"].labels.index(f"{b}.R") for b in synthetic.ARM]
    zeros = {k: torch.zeros(2, len(body.layout[k].labels), 3) for k in rest}
    zeros["body"][:, arm_idx] = torch.as_tensor(solved)
    with torch.no_grad():
        out = body.forward(synthetic._to_params(zeros, torch.zeros(2, body.layout["face"].dim), rest),
                           body.default_identity())
    knuckle = out.joints[:, synthetic._joint(body, "finger3-1.R")].numpy()
    assert np.linalg.norm(knuckle - goal, axis=-1).max() < 0.01


def test_mouthings_run_one_to_three_visemes():
    signs = build_lexicon(len(CONCEPTS), 2, np.random.default_rng(0))
    assert all(set(s.mouthing) <= set(VISEMES) for s in signs)
    assert {len(s.mouthing) for s in signs if s.group == "normal"} == {1, 2, 3}
    assert {len(s.mouthing) for s in signs if s.group == "confusing"} <= {1, 2, 3}


# ----------------------------------------------------------------------------------------- more reader details
def test_csl_daily_info_entry_that_is_not_a_dict_is_quarantined_and_clips_keep_their_length(tmp_path):
    """An ``info`` list (see ``build_csl_daily``) with a bare name string among the release's dict records."""
    fx.build_csl_daily(tmp_path)
    path = tmp_path / "sentence_label" / "csl2020ct_v2.pkl"
    with open(path, "rb") as fh:
        data = pickle.load(fh)
    data["info"][0]["length"] = 117
    data["info"].insert(1, "S000001_P0000_T00")
    with open(path, "wb") as fh:
        pickle.dump(data, fh)
    listing = CslDailyCorpus(tmp_path).listing()
    assert Quarantined("sentence_label/csl2020ct_v2.pkl", 1, None,
                       "info entry is a str, expected a dict with keys name, length, label_gloss, label_char, "
                       "label_word, signer") in listing.quarantined
    lacking = next(i for i, e in enumerate(data["info"]) if isinstance(e, dict) and e["name"] == "S100001_P0000_T00")
    assert Quarantined("sentence_label/csl2020ct_v2.pkl", lacking, "S100001_P0000_T00",
                       "info entry lacks keys ['label_gloss']") in listing.quarantined
    assert [q.file for q in listing.quarantined if q.clip_id == "S100001_P0000_T00"] == [
        "sentence_label/csl2020ct_v2.pkl"]  # its split row is not reported a second time
    clips = {c.id: c for c in listing.clips}
    assert dict(clips["S000000_P0000_T00"].extra) == {"media_kind": "frames", "chars": "你好吗", "length": "117"}
    assert dict(clips["S000002_P0000_T00"].extra)["length"] == "2"


def test_soke_csl_layout_row_with_an_unknown_split_is_quarantined_at_its_annotation_row(tmp_path):
    """SOKE's CSL-Daily layout (``poses/<clip>/<n>.pkl``, split from the annotation's ``split`` column, see
    ``build_soke``) with one row's split misspelt."""
    fx.build_soke(tmp_path, "csl")
    notes = tmp_path / "annotation.csv"
    lines = notes.read_text(encoding="utf-8").splitlines()
    row = next(i for i, line in enumerate(lines, start=1) if line.startswith("b1_0-8-rgb_front,"))
    lines[row - 1] = lines[row - 1].rsplit(",", 1)[0] + ",foo"
    notes.write_text("\n".join(lines) + "\n", encoding="utf-8")
    listing = SokeSmplxCorpus(tmp_path, SokeSmplxConfig(annotation="annotation.csv")).listing()
    assert Quarantined("annotation.csv", row, "b1_0-8-rgb_front",
                       "split 'foo'; expected one of train, dev, val, test") in listing.quarantined
    assert "b1_0-8-rgb_front" not in {c.id for c in listing.clips}
    assert {c.id: c.split for c in listing.clips}["c1_3-5-rgb_front"] == "test"


def _how2sign_train_csv(root: Path) -> Path:
    (path,) = root.rglob("how2sign_realigned_train.csv")
    return path


def test_how2sign_row_without_sentence_name_is_quarantined_and_a_bad_header_gets_the_hint(tmp_path):
    """The realigned CSVs of ``build_how2sign`` (the official download script's layout) with a row whose
    SENTENCE_NAME is blank, then with a comma-separated header."""
    fx.build_how2sign(tmp_path)
    path = _how2sign_train_csv(tmp_path)
    text = path.read_text(encoding="utf-8")
    lines = text.splitlines()
    path.write_text(text + "v\tv-rgb\tv_9\t \t1.0\t2.0\tNo name.\n", encoding="utf-8")
    listing = How2SignCorpus(tmp_path).listing()
    rel = path.relative_to(tmp_path).as_posix()
    assert Quarantined(rel, len(lines) + 1, None, "empty SENTENCE_NAME") in listing.quarantined
    path.write_text(text.replace("\t", ",", 6), encoding="utf-8")
    with pytest.raises(CorpusError) as err:
        How2SignCorpus(tmp_path).listing()
    message = str(err.value)
    assert message.startswith(f"{path} line 1: header is ")
    assert message.endswith("Is this a How2Sign realigned CSV (tab-separated)? Point the corpus root at the How2Sign "
                            "folder, or set option annotations_dir to the folder holding "
                            "how2sign_realigned_<split>.csv and clips_dir to the sentence clip folders.")


def test_phoenix_row_without_name_leaves_the_rows_after_it_listed(tmp_path):
    """PHOENIX-2014-T's test ``corpus.csv`` (see ``build_phoenix14t``) with a nameless row before its one row."""
    fx.build_phoenix14t(tmp_path)
    (path,) = tmp_path.rglob("PHOENIX-2014-T.test.corpus.csv")
    before = {c.id for c in Phoenix14TCorpus(tmp_path).listing().clips if c.split == "test"}
    header, *rows = path.read_text(encoding="utf-8").splitlines()
    path.write_text("\n".join([header, "|x/1/*.png|-1|-1|Signer01|REGEN|es regnet"] + rows) + "\n", encoding="utf-8")
    listing = Phoenix14TCorpus(tmp_path).listing()
    assert len(before) == 1 and {c.id for c in listing.clips if c.split == "test"} == before
    assert Quarantined(path.relative_to(tmp_path).as_posix(), 2, None, "empty name") in listing.quarantined


def _pose_v0_1(path: Path, frames: int) -> None:
    """A ``.pose`` file of the format's version 0.1 (pose-format ``PoseBody.read_v0_1``: fps and frame count as
    ushorts, a ushort person count, then float32 data (T, P, K, D) and confidence (T, P, K)), one OpenPose hand."""
    import io as _io

    pose = _openpose_hand_pose(frames, None)
    buffer = _io.BytesIO()
    pose.header.write(buffer)
    header = bytearray(buffer.getvalue())
    header[:4] = struct.pack("<f", 0.1)
    data = np.ma.getdata(pose.body.data).astype(np.float32)
    body = struct.pack("<HHH", 25, frames, 1) + data.tobytes() + np.asarray(pose.body.confidence, np.float32).tobytes()
    path.write_bytes(bytes(header) + body)


def test_a_version_0_1_pose_file_holds_one_person(tmp_path):
    _pose_v0_1(tmp_path / "old.pose", 4)
    info = read_pose_info(tmp_path / "old.pose")
    assert (info.frames, info.people, info.fps, round(info.version, 3)) == (4, 1, 25.0, 0.1)
    (clip,) = PoseFileCorpus(tmp_path, PoseFileConfig()).listing().clips
    assert dict(clip.extra)["people"] == "1" and dict(clip.extra)["frames"] == "4"


def test_pose_index_row_with_too_many_columns_is_quarantined_naming_its_id(tmp_path, ase_rows):
    shutil.copyfile(lexicon_root() / ase_rows[0]["path"], tmp_path / "a.pose")
    (tmp_path / "index.csv").write_text("id,path,split,text,language,signer\na,a.pose,train,A,ase,s0\n"
                                        "abc,a.pose,dev,B,ase,s0,extra\n,a.pose,dev,C,ase,s0,extra\n",
                                        encoding="utf-8")
    listing = PoseFileCorpus(tmp_path, PoseFileConfig(index="index.csv")).listing()
    assert [c.id for c in listing.clips] == ["a"]
    assert listing.quarantined == (Quarantined("index.csv", 3, "abc", "malformed row: wrong number of columns"),
                                   Quarantined("index.csv", 4, None, "malformed row: wrong number of columns"))


def test_mead_errors_name_the_root_or_the_file_and_what_was_expected(tmp_path):
    not_a_folder = tmp_path / "mead.txt"
    not_a_folder.write_text("x", encoding="utf-8")
    with pytest.raises(CorpusError) as err:
        MeadCorpus(not_a_folder).listing()
    assert str(err.value) == (f"MEAD root {not_a_folder} is not a folder; point it at the folder of subject folders "
                              f"(EMOTE's release: .../reconstructions/EMICA-MEAD_flame2020)")
    corrupt = tmp_path / "shape_pose_cam.npz"
    corrupt.write_bytes(b"PK\x03\x04 not really a zip archive")
    with pytest.raises(CorpusError) as err:
        read_flame_params(corrupt)
    assert str(err.value).startswith(f"{corrupt}: not a readable .npz (")
    assert str(err.value).endswith("); re-export the clip")
    np.savez(corrupt, exp=np.zeros((2, 50), np.float32), jaw=np.zeros((2, 3), np.float32))
    with pytest.raises(CorpusError) as err:
        read_flame_params(corrupt)
    assert str(err.value) == (f"{corrupt} lacks datasets ['global_pose', 'shape', 'cam']; expected exp, jaw, "
                              f"global_pose, shape, cam (EMOTE's export)")


def test_an_unknown_corpus_name_is_refused_listing_the_known_ones():
    with pytest.raises(ValueError) as err:
        adapter_class("phoenix")
    assert str(err.value) == f"corpus 'phoenix' unknown; expected one of {', '.join(CORPORA)}"
    assert "phoenix14t, " in str(err.value) and adapter_class("phoenix14t") is Phoenix14TCorpus


def test_a_clip_lasts_its_holds_signs_and_the_transitions_between_them(body):
    """Rest hold, each sign, rest hold, with a blend of ``transition_frames / speed`` (at least 2) frames before
    every segment but the first."""
    cfg = SyntheticCorpusConfig(hold_frames=5, frames_per_sign=10, transition_frames=3)
    synth = synthetic.Synthesiser(body, _rest_calibration(), cfg)
    signs = [_sign("hold"), _sign("tap"), _sign("hold")]
    for speed, per_sign, transition in ((1.25, 8, 2), (0.5, 20, 6)):
        signer = synthetic.Signer("s", np.full(6, 0.5), speed, 1.0, np.zeros(3))
        params = synth.synthesise(signs, signer)
        frames = 2 * 5 + len(signs) * per_sign + (len(signs) + 1) * transition
        assert {k: v.shape[0] for k, v in params.items()} == {k: frames for k in params}


def test_a_signs_hand_curls_each_finger_bone_about_its_flexion_axis(body):
    """Each of the 15 finger bones turns by 1.3 x its handshape curl (radians) about the calibrated axis."""
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(15, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    cal = synthetic.Calibration(axes, _rest_calibration().locations, np.zeros((4, 3)))
    synth = synthetic.Synthesiser(body, cal, SyntheticCorpusConfig())
    signer = synthetic.Signer("s", np.full(6, 0.5), 1.0, 1.0, np.zeros(3))
    for shape in ("fist", "C"):
        state = synth._sign_segment(_sign("hold", handshape=shape), 6, signer)
        curls = np.repeat(np.asarray(synthetic.HANDSHAPES[shape]), 3)
        expected = 1.3 * curls[:, None] * axes
        assert state["right_hand"].shape == (6, 15, 3)
        np.testing.assert_allclose(state["right_hand"], np.broadcast_to(expected, (6, 15, 3)))
        np.testing.assert_allclose(np.linalg.norm(state["right_hand"][0], axis=1), 1.3 * curls)


def test_an_interrupt_while_removing_the_old_corpus_propagates_and_leaves_the_new_one(tmp_path, monkeypatch):
    root = tmp_path / "synthetic"
    synthetic.write_corpus([_tiny_clip(0)], root)
    real_rmtree = shutil.rmtree

    def interrupted(path, *args, **kwargs):
        if Path(path).name == ".synthetic.old":
            raise KeyboardInterrupt
        return real_rmtree(path, *args, **kwargs)

    monkeypatch.setattr(synthetic.shutil, "rmtree", interrupted)
    with pytest.raises(KeyboardInterrupt):
        synthetic.write_corpus([_tiny_clip(1)], root)
    monkeypatch.undo()
    assert [c.id for c in synthetic.SyntheticCorpus(root).clips()] == ["iso-house-signer00-1"]
