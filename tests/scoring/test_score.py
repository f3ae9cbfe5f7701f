"""``m3t score``: folders of ``.pose`` files and sentence files scored under the named definitions.

Fixture layout: the files are written by pose-format itself with its MediaPipe Holistic header
(``pose_format.utils.holistic.holistic_components()``: ``POSE_LANDMARKS`` 33 points ``NOSE`` ... ``RIGHT_FOOT_INDEX``,
``FACE_LANDMARKS`` 468 points ``"0"`` ... ``"467"`` (478 with ``additional_face_points=10``),
``LEFT_HAND_LANDMARKS`` / ``RIGHT_HAND_LANDMARKS`` 21 points ``WRIST`` ... ``PINKY_TIP``, ``POSE_WORLD_LANDMARKS``
33; point format XYZC), the layout of every file pose-format's ``video_to_pose`` writes: a real row of one frame
is ``data[t, 0, k] = (x_px, y_px, z)`` with ``confidence[t, 0, k]`` in [0, 1], 0 where MediaPipe saw nothing.

Expected values are computed from the arrays the test wrote (not read back through the module), with the metric
functions of :mod:`m3t.metrics` that tests/metrics check against the peers; floats compare with ``rel=1e-12``
(the same float64 operations in the same order, but summation order inside numpy may differ between builds).
"""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from cli.main import main as cli_main
from m3t.metrics.definitions import text_metrics
from m3t.metrics.pose_eval import VARIANTS, pose_eval_distance
from m3t.metrics.slrtp import SLRTP_FACE_MESH_INDICES, slrtp_pose_corpus_metrics
from m3t.scoring.poses import (
    ScoreInputError,
    holistic_array,
    read_pose_clip,
    slrtp_array,
)
from m3t.scoring.score import score
from m3t.shards.io import read_shard

TOL = {"rel": 1e-12, "abs": 1e-12}
POSE, HAND = 33, 21
R_SHOULDER, R_ELBOW, R_WRIST, L_SHOULDER, L_ELBOW, L_WRIST, R_HIP, L_HIP = 12, 14, 16, 11, 13, 15, 24, 23


def holistic_file(path, points: np.ndarray, confidence: np.ndarray | None = None, fps: float = 25.0,
                  face: int = 478, world: bool = True, reverse: bool = False) -> None:
    """Write (T, 33 + face + 42, 3) ``points`` (pose, face, left hand, right hand) as a pose-format holistic file;
    ``reverse``: the components in reverse order in the header (and data), ``world``: with world landmarks."""
    from pose_format import Pose
    from pose_format.numpy.pose_body import NumPyPoseBody
    from pose_format.pose_header import PoseHeader, PoseHeaderDimensions
    from pose_format.utils.holistic import holistic_components

    frames = len(points)
    confidence = np.ones(points.shape[:2], np.float32) if confidence is None else confidence
    components = holistic_components(additional_face_points=face - 468)
    blocks = np.split(np.arange(points.shape[1]), np.cumsum([POSE, face, HAND]))
    data = [points[:, b] for b in blocks]
    conf = [confidence[:, b] for b in blocks]
    if world:
        data.append(np.full((frames, POSE, 3), 0.5))
        conf.append(np.ones((frames, POSE)))
    else:
        components = components[:4]
    if reverse:
        components, data, conf = components[::-1], data[::-1], conf[::-1]
    header = PoseHeader(0.2, PoseHeaderDimensions(640, 480), components)
    body = NumPyPoseBody(fps, np.concatenate(data, 1)[:, None].astype(np.float32),
                         np.concatenate(conf, 1)[:, None].astype(np.float32))
    with open(path, "wb") as fh:
        Pose(header, body).write(fh)


def motion(frames: int, seed: int, face: int = 478) -> np.ndarray:
    """(T, J, 3) float32-representable pixel coordinates (integers / 4: exact in float32)."""
    rng = np.random.default_rng(seed)
    return (rng.integers(0, 2000, size=(frames, POSE + face + 2 * HAND, 3)) / 4).astype(np.float64)


@pytest.fixture
def folders(tmp_path):
    """pred/ and ref/: clips a, b, sub/c on both sides (different lengths), d only predicted, e only referenced."""
    pred, ref = tmp_path / "pred", tmp_path / "ref"
    (pred / "sub").mkdir(parents=True)
    (ref / "sub").mkdir(parents=True)
    arrays = {}
    for n, clip in enumerate(("a", "b", "sub/c")):
        arrays[clip] = motion(6 + n, seed=n), motion(9 - n, seed=10 + n)
        holistic_file(pred / f"{clip}.pose", arrays[clip][0])
        holistic_file(ref / f"{clip}.pose", arrays[clip][1])
    holistic_file(pred / "d.pose", motion(3, 20))
    holistic_file(ref / "e.pose", motion(3, 21))
    return pred, ref, arrays


# ---- the layouts ------------------------------------------------------------------------------------------------
def test_points_are_placed_by_name_whatever_the_component_order(tmp_path):
    x = motion(3, 0)
    conf = np.ones(x.shape[:2], np.float32)
    conf[1, 5] = 0.0  # pose-format's mask: a landmark MediaPipe did not see
    holistic_file(tmp_path / "plain.pose", x, conf)
    holistic_file(tmp_path / "reversed.pose", x, conf, world=False, reverse=True)
    expected = x.copy()
    expected[1, 5] = np.nan
    for name in ("plain", "reversed"):
        clip = read_pose_clip(tmp_path / f"{name}.pose", name)
        assert clip.points.shape == (3, 553, 3) and clip.fps == 25.0 and clip.face_points == 478
        np.testing.assert_array_equal(clip.points, expected)


def test_a_file_without_hands_is_refused_by_name(tmp_path):
    from pose_format import Pose
    from pose_format.numpy.pose_body import NumPyPoseBody
    from pose_format.pose_header import PoseHeader, PoseHeaderDimensions
    from pose_format.utils.holistic import holistic_components

    header = PoseHeader(0.2, PoseHeaderDimensions(640, 480), holistic_components()[:2])
    body = NumPyPoseBody(25.0, np.zeros((2, 1, 501, 3), np.float32), np.ones((2, 1, 501), np.float32))
    with open(tmp_path / "face.pose", "wb") as fh:
        Pose(header, body).write(fh)
    with pytest.raises(ScoreInputError, match=r"face\.pose: not a MediaPipe Holistic \.pose file; it lacks "
                                              r"\['LEFT_HAND_LANDMARKS', 'RIGHT_HAND_LANDMARKS'\]"):
        read_pose_clip(tmp_path / "face.pose", "face")


def test_slrtp_keypoints_from_the_holistic_points():
    x = motion(2, 3)
    y = slrtp_array(x)
    assert y.shape == (2, 178, 3)
    body = [R_SHOULDER, R_ELBOW, R_WRIST, L_SHOULDER, L_ELBOW, L_WRIST, R_HIP, L_HIP]
    np.testing.assert_array_equal(y[:, :8], x[:, body])
    right_hand, left_hand = POSE + 478 + HAND, POSE + 478
    np.testing.assert_array_equal(y[:, 8:29], x[:, right_hand:right_hand + HAND])
    np.testing.assert_array_equal(y[:, 29:50], x[:, left_hand:left_hand + HAND])
    np.testing.assert_array_equal(y[:, 50:], x[:, [POSE + i for i in SLRTP_FACE_MESH_INDICES]])
    np.testing.assert_array_equal(slrtp_array(np.delete(x, range(POSE + 468, POSE + 478), axis=1)), y)


# ---- pose folders -----------------------------------------------------------------------------------------------
def test_pose_folders_scored_under_both_definitions(folders):
    pred, ref, arrays = folders
    report = score(pred, ref)
    clips = ["a", "b", "sub/c"]
    assert report.paired == 3 and report.clips_scored == {"pose_eval": 3, "slrtp": 3}
    for name in VARIANTS:
        expected = np.mean([pose_eval_distance(*arrays[c], name) for c in clips])
        assert report.metrics[name] == pytest.approx(expected, **TOL)
        assert report.definition_of[name] == "pose_eval"
    # the challenge's pooling over the three pairs, at 25 fps (every second frame on both sides)
    expected = slrtp_pose_corpus_metrics([slrtp_array(arrays[c][0]) for c in clips],
                                         [slrtp_array(arrays[c][1]) for c in clips])
    for name in ("slrtp_dtw_mje", "slrtp_wrist_path_ratio", "slrtp_duration_ratio"):
        assert report.metrics[name] == pytest.approx(expected[name], **TOL)
    assert report.metrics["slrtp_duration_ratio"] == pytest.approx(np.mean([3 / 5, 4 / 4, 4 / 4]), **TOL)
    unscored = {(u["clip"], u["definition"]): u["reason"] for u in report.unscored}
    assert unscored == {("e", "all"): f"no prediction (no .pose file 'e' under {pred})",
                        ("d", "all"): f"no reference (no .pose file 'd' under {ref})"}
    per_clip = {(r["clip"], r["metric"]): r["value"] for r in report.per_clip}
    assert per_clip[("sub/c", "pose_eval_dtwp")] == pytest.approx(pose_eval_distance(*arrays["sub/c"]), **TOL)
    assert len(per_clip) == 3 * (len(VARIANTS) + 3)


def test_one_definition_only(folders):
    pred, ref, _ = folders
    report = score(pred, ref, ["slrtp"])
    assert list(report.metrics) == ["slrtp_dtw_mje", "slrtp_wrist_path_ratio", "slrtp_duration_ratio"]
    with pytest.raises(ScoreInputError, match=r"definitions \['soke'\] do not apply to pose inputs; choose from "
                                              r"pose_eval, slrtp"):
        score(pred, ref, ["soke"])


def test_pairs_that_cannot_be_scored_are_listed_with_their_reason(tmp_path):
    pred, ref = tmp_path / "pred", tmp_path / "ref"
    pred.mkdir()
    ref.mkdir()
    x = motion(4, 0)
    holistic_file(pred / "ok.pose", x)
    holistic_file(ref / "ok.pose", x)
    holistic_file(pred / "rate.pose", x, fps=50.0)
    holistic_file(ref / "rate.pose", x)
    (pred / "broken.pose").write_bytes(b"not a pose file")
    holistic_file(ref / "broken.pose", x)
    report = score(pred, ref)
    assert report.clips_scored == {"pose_eval": 1, "slrtp": 1}
    assert report.metrics["pose_eval_dtw"] == 0.0 and report.metrics["slrtp_dtw_mje"] == 0.0
    reasons = {u["clip"]: u["reason"] for u in report.unscored}
    assert reasons["rate"] == ("prediction at 50 fps, reference at 25 fps; resample the prediction to the "
                               "reference's rate, or score across rates as the peers do (--any-fps)")
    assert str(pred / "broken.pose") in reasons["broken"] and "re-export it" in reasons["broken"]
    assert set(reasons) == {"rate", "broken"}
    across = score(pred, ref, any_fps=True)
    assert across.clips_scored["slrtp"] == 2  # 50 fps is kept as given, the 25 fps side halved (the challenge)
    assert across.metrics["slrtp_duration_ratio"] == pytest.approx((1 + 4 / 2) / 2, **TOL)


def test_nothing_paired_is_an_error(tmp_path):
    (tmp_path / "p").mkdir()
    (tmp_path / "r").mkdir()
    holistic_file(tmp_path / "p" / "x.pose", motion(2, 0))
    holistic_file(tmp_path / "r" / "y.pose", motion(2, 0))
    with pytest.raises(ScoreInputError, match=r"no clip id is on both sides: 1 predictions \('x'\) and 1 "
                                              r"references \('y'\); name each prediction as its reference"):
        score(tmp_path / "p", tmp_path / "r")


def test_a_468_point_face_against_a_478_point_face(tmp_path):
    pred, ref = tmp_path / "pred", tmp_path / "ref"
    pred.mkdir()
    ref.mkdir()
    x, y = motion(5, 0, face=468), motion(4, 1)
    holistic_file(pred / "c.pose", x, face=468)
    holistic_file(ref / "c.pose", y)
    report = score(pred, ref, ["pose_eval"])
    mesh = np.delete(y, range(POSE + 468, POSE + 478), axis=1)
    for name in VARIANTS:
        assert report.metrics[name] == pytest.approx(pose_eval_distance(x, mesh, name), **TOL)
    assert any("scored on the 468 mesh points" in n for n in report.notes)


def test_missing_points_reach_the_metrics_as_missing(tmp_path):
    pred, ref = tmp_path / "pred", tmp_path / "ref"
    pred.mkdir()
    ref.mkdir()
    x, y = motion(4, 0), motion(4, 1)
    conf = np.ones(x.shape[:2], np.float32)
    conf[:, POSE + 478:POSE + 478 + HAND] = 0  # the left hand never seen
    holistic_file(pred / "c.pose", x, conf)
    holistic_file(ref / "c.pose", y)
    report = score(pred, ref, ["pose_eval"])
    hidden = x.copy()
    hidden[:, POSE + 478:POSE + 478 + HAND] = np.nan
    # DTWp fills missing hand points with 10.0: the hidden hand counts as a constant track at 10
    assert report.metrics["pose_eval_dtwp"] == pytest.approx(pose_eval_distance(hidden, y, "pose_eval_dtwp"), **TOL)
    assert report.metrics["pose_eval_dtwp"] != pytest.approx(pose_eval_distance(x, y, "pose_eval_dtwp"), **TOL)


# ---- sentence files ---------------------------------------------------------------------------------------------
def test_sentence_files_by_line_and_by_id(tmp_path):
    hyps, refs = ["the weather is nice", "tomorrow it rains"], ["the weather is nice today", "tomorrow rain"]
    (tmp_path / "h.txt").write_text("\n".join(hyps) + "\n")
    (tmp_path / "r.txt").write_text("\n".join(refs) + "\n")
    report = score(tmp_path / "h.txt", tmp_path / "r.txt")
    assert report.metrics == pytest.approx(text_metrics(hyps, refs, "en"), **TOL)
    assert report.clips_scored == {"slt": 2, "soke": 2, "slrtp": 2}
    assert report.definition_of["soke_rouge_l"] == "soke" and report.definition_of["slrtp_wer"] == "slrtp"
    (tmp_path / "h.tsv").write_text("id\ttext\nx2\ttomorrow it rains\nx1\tthe weather is nice\n")
    (tmp_path / "r.tsv").write_text("text\tid\nthe weather is nice today\tx1\ntomorrow rain\tx2\nextra\tx3\n")
    by_id = score(tmp_path / "h.tsv", tmp_path / "r.tsv", ["slt"])
    assert by_id.metrics == pytest.approx(text_metrics(hyps, refs, "en", ["slt"]), **TOL)
    assert by_id.unscored == [{"clip": "x3", "definition": "all",
                               "reason": f"no prediction (no id 'x3' under {tmp_path / 'h.tsv'})"}]


def test_sentence_file_errors(tmp_path):
    (tmp_path / "h.tsv").write_text("key\tsentence\na\tb\n")
    (tmp_path / "r.tsv").write_text("id\ttext\na\tb\na\tc\n")
    with pytest.raises(ScoreInputError, match=r"h\.tsv: a \.tsv of sentences needs a header with 'id' and 'text' "
                                              r"columns; found \['key', 'sentence'\]"):
        score(tmp_path / "h.tsv", tmp_path / "r.tsv")
    (tmp_path / "h.tsv").write_text("id\ttext\na\tb\n")
    with pytest.raises(ScoreInputError, match=r"r\.tsv line 3: id 'a' appears twice; ids must be unique"):
        score(tmp_path / "h.tsv", tmp_path / "r.tsv")
    (tmp_path / "h.txt").write_text("a\n")
    with pytest.raises(ScoreInputError, match=r"differ in format; give two \.txt or two \.tsv files"):
        score(tmp_path / "h.txt", tmp_path / "r.tsv")
    with pytest.raises(ScoreInputError, match=r"cannot score .* give two folders of \.pose files, two parameter "
                                              r"shards \(\.parquet\) or two sentence files \(\.txt / \.tsv\)"):
        score(tmp_path / "h.txt", tmp_path)
    with pytest.raises(ScoreInputError, match=r"nowhere\.txt does not exist"):
        score(tmp_path / "nowhere.txt", tmp_path / "h.txt")


# ---- outputs and the command ------------------------------------------------------------------------------------
def test_report_files_and_the_command(folders, tmp_path, capsys):
    pred, ref, _ = folders
    out = tmp_path / "out"
    assert cli_main(["score", str(pred), str(ref), "--definitions", "slrtp", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "slrtp_dtw_mje" in printed and "e [all]: no prediction" in printed and "pose_eval" not in printed
    saved = json.loads((out / "score.json").read_text())
    assert saved["clips_scored"] == {"slrtp": 3} and saved["paired"] == 3 and len(saved["unscored"]) == 2
    rows = (out / "score.csv").read_text().splitlines()
    assert rows[0] == "definition,metric,value,clips" and rows[1].startswith("slrtp,slrtp_dtw_mje,")
    assert rows[1].endswith(",3") and len(rows) == 4
    assert (out / "clips.csv").read_text().count("\n") == 1 + 3 * 3
    assert (out / "unscored.csv").read_text().splitlines()[1:] == [
        f"e,all,no prediction (no .pose file 'e' under {pred})", f"d,all,no reference (no .pose file 'd' under {ref})"]
    assert cli_main(["score", str(pred), str(ref), "--format", "json", "--definitions", "pose_eval"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert set(printed["metrics"]) == set(VARIANTS)
    assert cli_main(["score", str(tmp_path / "missing"), str(ref)]) == 2
    assert capsys.readouterr().err == f"m3t score: {tmp_path / 'missing'} does not exist\n"


def test_non_finite_values_are_null_in_json(tmp_path):
    (tmp_path / "p").mkdir()
    (tmp_path / "r").mkdir()
    still = np.zeros((4, 553, 3))
    holistic_file(tmp_path / "p" / "c.pose", still)
    holistic_file(tmp_path / "r" / "c.pose", still)
    report = score(tmp_path / "p", tmp_path / "r", ["slrtp"])
    assert math.isnan(report.metrics["slrtp_wrist_path_ratio"])  # 0 / 0: no wrist moved on either side
    assert report.as_json()["metrics"]["slrtp_wrist_path_ratio"] is None


def test_holistic_array_needs_point_names():
    from m3t.corpora.posefile import PoseData

    data = PoseData(np.zeros((1, 2, 3), np.float32), np.ones((1, 2), np.float32), 25.0, (("X", 2),), 1, 1)
    with pytest.raises(ScoreInputError, match=r"x\.pose: the \.pose data carry no point names"):
        holistic_array(data, "x.pose")


# ---- parameter shards -------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def parameter_shards(body, tmp_path_factory):
    """A reference shard of three smooth clips (c0 18 frames, c1 25, c2 32; :func:`tiny_pipeline.write_shards`, the
    shard layout every fitting stage writes) and a prediction shard holding other motion for c0 and c1 (c1 cut
    to 10 frames) plus a clip c9 the references lack."""
    from builders import smooth_motion
    from tiny_pipeline import write_shards

    from m3t.shards.io import write_shard

    root = tmp_path_factory.mktemp("parameter_shards")
    write_shards(root / "ref", body, {"test": 3})
    ref = read_shard(root / "ref" / "test.parquet")
    predicted = []
    for clip, frames, seed in ((ref.clips[0], 18, 40), (ref.clips[1], 10, 41)):
        params = {k: v.numpy() for k, v in smooth_motion(body, frames=frames, seed=seed).items()}
        predicted.append(replace(clip, params=params))
    extra = replace(ref.clips[0], clip=replace(ref.clips[0].clip, id="c9"))
    write_shard(root / "pred.parquet", [*predicted, extra], body.layout)
    return root / "pred.parquet", root / "ref" / "test.parquet", ref, predicted


def test_parameter_shards_scored_as_the_smlm_evaluation_scores(body, parameter_shards):
    from m3t.metrics.scorer import MotionPair, MotionScorer

    pred, ref, reference, predicted = parameter_shards
    report = score(pred, ref, body=lambda: body)
    expected = MotionScorer(body).score([MotionPair(p.clip.id, "synthetic/ASL-SYN", p.params, r.identity, r.params)
                                         for p, r in zip(predicted, reference.clips)])
    assert report.kind == "parameters" and report.clips_scored == {"m3t": 2}  # Anny: no soke_exact by default
    for key, value in expected.overall.items():
        assert report.metrics[f"m3t_{key}"] == pytest.approx(value, rel=1e-9)
    assert report.metrics["m3t_dtw_jpe_body_m"] > 0 and report.metrics["m3t_empty_rate"] == 0.0
    assert {(u["clip"], u["reason"].split(" (")[0]) for u in report.unscored} == {("c2", "no prediction"),
                                                                                  ("c9", "no reference")}
    same = score(ref, ref, ["m3t"], body=body)
    assert same.metrics["m3t_dtw_jpe_body_m"] == pytest.approx(0.0, abs=1e-9)  # a clip against itself


def test_parameter_shard_refusals(body, parameter_shards, tmp_path):
    pred, ref, _, _ = parameter_shards
    with pytest.raises(ScoreInputError, match=r"are parameter shards: scoring them needs the body model they were "
                                              r"fitted with \(body\.model in params\.yaml\)"):
        score(pred, ref)
    with pytest.raises(ScoreInputError, match=r"motion metric mode 'soke_exact' reproduces SOKE's SMPL-X "
                                              r"evaluation and needs body\.model: smplfx"):
        score(pred, ref, ["soke_exact"], body=body)
    with pytest.raises(ScoreInputError, match=r"definitions \['pose_eval'\] do not apply to parameter inputs; "
                                              r"choose from m3t, soke_exact, slt, soke, slrtp"):
        score(pred, ref, ["pose_eval"], body=body)
    with pytest.raises(ScoreInputError, match=r"definitions \['slrtp'\] score back-translated sentences and need a "
                                              r"judge: the folder of back-translation checkpoints"):
        score(pred, ref, ["slrtp"], body=body)
    (tmp_path / "bad.parquet").write_bytes(b"PAR1 not really")
    with pytest.raises(ScoreInputError, match=r"^prediction shard .*bad\.parquet"):
        score(tmp_path / "bad.parquet", ref, body=body)


def test_the_command_loads_the_workspace_body_for_shards(parameter_shards, capsys):
    from tiny_pipeline import ROOT

    pred, ref, _, _ = parameter_shards
    assert cli_main(["--params", str(ROOT / "params.yaml"), "score", str(pred), str(ref), "--format", "csv"]) == 0
    rows = dict(line.split(",")[1:3] for line in capsys.readouterr().out.splitlines()[1:])
    assert float(rows["m3t_dtw_jpe_body_m"]) > 0 and rows["m3t_empty_rate"] == "0.0"
