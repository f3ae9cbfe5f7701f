"""``m3t score PRED/ REF/`` on folders of SMPL-X parameters in SOKE's layout (:mod:`m3t.scoring.smplx_folders`),
on the SMPL-FX stand-in built from the synthetic SMPL-X / FLAME files (:mod:`smplfx_fixtures`)."""
from __future__ import annotations

import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import roma
import torch

from m3t.body.rotations import matrix_to_6d
from m3t.body.smplfx import SMPLFXBody
from m3t.body.smplfx_build import SMPLFXFiles
from m3t.corpora.clip import Clip
from m3t.scoring.params import score_parameter_shards
from m3t.scoring.poses import ScoreInputError
from m3t.scoring.score import score
from m3t.shards.io import write_shard
from m3t.shards.schema import FittedClip

SOKE_KEYS = {"smplx_root_pose": 3, "smplx_body_pose": 63, "smplx_lhand_pose": 45, "smplx_rhand_pose": 45,
             "smplx_jaw_pose": 3, "smplx_shape": 10, "smplx_expr": 10}
RIGHT_WRIST = slice(60, 63)  # smplx_body_pose columns of joint 21 (R_Wrist): body_pose holds joints 1-21
# SMPL-X joints 12-21, smplx_body_pose[:, 33:] (SOKE ``mGPT/utils/human_models.py`` ``orig_joints_name``)
SMPLX_UPPER = ("neck", "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow",
               "right_elbow", "left_wrist", "right_wrist")


def soke_clip(frames: int, seed: int) -> dict[str, np.ndarray]:
    """One clip in SOKE's layout: the frame record its loaders read (2000ZRL/SOKE
    ``mGPT/data/humanml/load_data.py``, ``keys`` and the comment under ``load_h2s_sample``: ``smplx_root_pose``
    (3,), ``smplx_body_pose`` (63,), ``smplx_lhand_pose`` (45,), ``smplx_rhand_pose`` (45,), ``smplx_jaw_pose``
    (3,), ``smplx_shape`` (10,), ``smplx_expr`` (10,), float32 axis-angle radians and coefficients, as SMPLer-X
    writes them) stacked over ``frames``: (T, D) per key, one signer's shape repeated in every row."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, frames)[:, None]
    clip = {k: (0.3 * rng.normal(size=(1, d)) * np.sin(3 * t + 6 * rng.random((1, d)))).astype(np.float32)
            for k, d in SOKE_KEYS.items()}
    clip["smplx_shape"] = np.repeat(0.5 * rng.normal(size=(1, 10)), frames, 0).astype(np.float32)
    return clip


def write_pickle(path: Path, value) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(value))
    return path


def write_frames(folder: Path, name: str, clip: dict[str, np.ndarray]) -> None:
    """SOKE's released How2Sign poses: ``<clip>/<clip>_<n>_3D.pkl``, one (D,) record per frame."""
    for n in range(len(clip["smplx_body_pose"])):
        write_pickle(folder / name / f"{name}_{n}_3D.pkl", {k: v[n] for k, v in clip.items()})


def rotated_wrist(clip: dict[str, np.ndarray], angle: float = 0.4) -> dict[str, np.ndarray]:
    """The clip with its right wrist turned by a constant ``angle`` about the x axis after its own rotation."""
    out = {k: v.copy() for k, v in clip.items()}
    wrist = roma.rotvec_to_rotmat(torch.as_tensor(clip["smplx_body_pose"][:, RIGHT_WRIST], dtype=torch.float64))
    turn = roma.rotvec_to_rotmat(torch.tensor([angle, 0.0, 0.0], dtype=torch.float64))
    out["smplx_body_pose"][:, RIGHT_WRIST] = roma.rotmat_to_rotvec(wrist @ turn).numpy()
    return out


def as_6d(aa: np.ndarray) -> np.ndarray:
    rotvec = torch.as_tensor(aa, dtype=torch.float64).reshape(len(aa), -1, 3)  # (T, J, 3)
    return matrix_to_6d(roma.rotvec_to_rotmat(rotvec)).reshape(len(aa), -1).float().numpy()


def smplfx_row(body, clip_id: str, clip: dict[str, np.ndarray], mean: tuple[np.ndarray, np.ndarray]) -> FittedClip:
    """The shard row of a SOKE clip written from SOKE's layout directly: ``smplx_body_pose[:, 33:]`` (joints 12-21,
    neck .. wrists: what SOKE's features keep, ``load_data.py``) in the order of SMPL-FX's ``body`` stream labels
    as the body, the hands plus SMPL-X's mean hand
    (smplx's ``flat_hand_mean=False``), the expression in the first face dims and the jaw's 6D, the mean shape's
    betas as the identity (FLAME shape 0)."""
    frames = len(clip["smplx_body_pose"])
    face = np.zeros((frames, 108), np.float32)
    face[:, :10] = clip["smplx_expr"]
    face[:, 102:] = as_6d(clip["smplx_jaw_pose"])
    upper = clip["smplx_body_pose"][:, 33:].reshape(frames, 10, 3)
    order = [SMPLX_UPPER.index(j) for j in body.layout["body"].labels]
    params = {"body": as_6d(upper[:, order].reshape(frames, 30)),
              "left_hand": as_6d(clip["smplx_lhand_pose"].astype(np.float64) + mean[0]),
              "right_hand": as_6d(clip["smplx_rhand_pose"].astype(np.float64) + mean[1]), "face": face}
    identity = np.zeros(110, np.float32)
    identity[:10] = clip["smplx_shape"].mean(0)
    record = Clip(clip_id, "soke", "test", "unknown", "unknown", "", "", clip_id, 25.0)
    return FittedClip(record, "k", params, identity, {}, {}, "smplfx")


@pytest.fixture
def hand_mean(fx_files):
    from m3t.fitting.imports import smplx_hand_mean

    return smplx_hand_mean(fx_files.smplx)


def test_identical_folders_score_zero(fx, fx_files, tmp_path):
    clips = {"dev/a": soke_clip(12, 1), "b": soke_clip(9, 2)}
    for name, clip in clips.items():
        write_pickle(tmp_path / "pred" / f"{name}.pkl", clip)
    for name, clip in clips.items():  # the references as SOKE's loaders read them: one pickle per frame
        write_frames(tmp_path / "ref" / Path(name).parent, Path(name).name, clip)
    report = score(tmp_path / "pred", tmp_path / "ref", body=lambda: fx, smplx_path=fx_files.smplx)
    assert report.kind == "parameters" and report.paired == 2 and not report.unscored
    assert report.clips_scored == {"m3t": 2, "soke_exact": 2}
    for key in ("m3t_dtw_jpe_body_m", "m3t_dtw_jpe_right_hand_m", "soke_exact_dtw_jpe_body_m"):
        assert report.metrics[key] == pytest.approx(0.0, abs=1e-7)  # float32 rounding of one pose path


def test_a_turned_wrist_scores_as_through_shards(fx, fx_files, hand_mean, tmp_path):
    """The folders give the values of :func:`score_parameter_shards` on the same clips written as shards from
    SOKE's layout directly. Both conversions compute the same float64 operations before the float32 cast and the
    scorer is the same, so the values agree to the last bits (rel 1e-9 leaves room for a summation order only); a
    joint put in the wrong slot of the body stream would change them at the centimetre."""
    refs = {"a": soke_clip(14, 3), "b": soke_clip(11, 4)}
    preds = {k: rotated_wrist(v) for k, v in refs.items()}
    for side, clips in (("pred", preds), ("ref", refs)):
        (tmp_path / side).mkdir()
        for name, clip in clips.items():
            np.savez(tmp_path / side / f"{name}.npz", **clip)
    report = score(tmp_path / "pred", tmp_path / "ref", body=fx, smplx_path=fx_files.smplx)
    write_shard(tmp_path / "pred.parquet", [smplfx_row(fx, k, v, hand_mean) for k, v in preds.items()], fx.layout)
    write_shard(tmp_path / "ref.parquet", [smplfx_row(fx, k, v, hand_mean) for k, v in refs.items()], fx.layout)
    shards = score_parameter_shards(tmp_path / "pred.parquet", tmp_path / "ref.parquet", fx)
    assert report.metrics["m3t_dtw_jpe_right_hand_m"] > 1e-3  # the turned wrist moves the right hand ...
    assert report.metrics["m3t_dtw_jpe_left_hand_m"] == pytest.approx(0.0, abs=1e-7)  # ... and nothing else
    assert set(report.metrics) == set(shards.metrics)
    for key, value in shards.metrics.items():
        assert report.metrics[key] == pytest.approx(value, rel=1e-9, abs=1e-12), key


def test_unpaired_and_malformed_files_are_listed_with_their_reason(fx, fx_files, tmp_path):
    good = soke_clip(8, 5)
    for side in ("pred", "ref"):
        write_pickle(tmp_path / side / "good.pkl", good)
        write_pickle(tmp_path / side / "short.pkl", {k: v[:0] for k, v in good.items()})  # zero frames
    write_pickle(tmp_path / "pred" / "only_pred.pkl", good)
    write_pickle(tmp_path / "ref" / "only_ref.pkl", good)
    write_pickle(tmp_path / "pred" / "narrow.pkl", good | {"smplx_body_pose": good["smplx_body_pose"][:, :60]})
    write_pickle(tmp_path / "ref" / "narrow.pkl", good)
    write_pickle(tmp_path / "pred" / "flat.pkl", good | {"smplx_body_pose": good["smplx_body_pose"][0]})
    write_pickle(tmp_path / "ref" / "flat.pkl", good)
    (tmp_path / "pred" / "garbage.pkl").write_bytes(b"not a pickle")
    write_pickle(tmp_path / "ref" / "garbage.pkl", good)
    # SOKE's test output (mGPT/models/base.py test_step): normalised (T, 133) features, not SMPL-X arrays
    write_pickle(tmp_path / "pred" / "soke_out.pkl", {"feats_rst": np.zeros((8, 133), np.float32),
                                                      "feats_ref": np.zeros((8, 133), np.float32), "text": "hi"})
    write_pickle(tmp_path / "ref" / "soke_out.pkl", good)
    report = score(tmp_path / "pred", tmp_path / "ref", ["m3t"], body=fx, smplx_path=fx_files.smplx)
    reasons = {u["clip"]: u["reason"] for u in report.unscored}
    assert report.clips_scored == {"m3t": 1} and report.paired == 6
    assert reasons["only_ref"].startswith("no prediction (no SMPL-X clip 'only_ref'")
    assert reasons["only_pred"].startswith("no reference (no SMPL-X clip 'only_pred'")
    assert reasons["short"].endswith("short.pkl: no frames")
    assert reasons["narrow"].endswith("narrow.pkl: key 'smplx_body_pose' has 60 values; expected 63")
    assert reasons["flat"].endswith("flat.pkl: key 'smplx_body_pose' has shape (63,); expected (T, D), one row "
                                    "per frame (a clip's shape may be (D,))")
    assert "garbage.pkl: not a readable pickle" in reasons["garbage"]
    assert "soke_out.pkl: SOKE's test output (feats_rst / feats_ref" in reasons["soke_out"]


def test_a_clip_without_shape_takes_the_neutral_one(fx, fx_files, tmp_path):
    clip = soke_clip(10, 6)
    write_pickle(tmp_path / "pred" / "a.pkl", {k: v for k, v in clip.items() if k != "smplx_shape"})
    write_pickle(tmp_path / "ref" / "a.pkl", clip | {"smplx_shape": np.zeros(10, np.float32)})  # (D,): per clip
    report = score(tmp_path / "pred", tmp_path / "ref", ["m3t"], body=fx, smplx_path=fx_files.smplx)
    assert report.metrics["m3t_dtw_jpe_body_m"] == pytest.approx(0.0, abs=1e-7) and not report.unscored


def test_mixed_folders_and_missing_body_model_are_clear_errors(fx, fx_files, tmp_path):
    clip = soke_clip(6, 7)
    write_pickle(tmp_path / "ref" / "a.pkl", clip)
    write_pickle(tmp_path / "mixed" / "a.pkl", clip)
    (tmp_path / "mixed" / "b.pose").write_bytes(b"")
    with pytest.raises(ScoreInputError, match=r"mixed holds both \.pose files \(b\.pose\) and SMPL-X parameter "
                                              r"files \(a\.pkl\); score each kind from a folder of its own"):
        score(tmp_path / "mixed", tmp_path / "ref", body=fx)
    (tmp_path / "poses").mkdir()
    (tmp_path / "poses" / "a.pose").write_bytes(b"")
    with pytest.raises(ScoreInputError, match=r"poses holds \.pose files .*ref holds SMPL-X parameter files"):
        score(tmp_path / "poses", tmp_path / "ref", body=fx)
    with pytest.raises(ScoreInputError, match=r"hold SMPL-X parameter files: scoring them needs the SMPL-FX body "
                                              r"model \(body\.model: smplfx in params\.yaml\)"):
        score(tmp_path / "ref", tmp_path / "ref")
    missing = replace(SMPLFXFiles(fx_files.smplx, fx_files.flame, fx_files.correspondence),
                      smplx=tmp_path / "nowhere" / "SMPLX_NEUTRAL.npz")
    with pytest.raises(ScoreInputError, match=r"(?s)body\.model: smplfx in params\.yaml.*body\.smplx_path = "
                                              r".*nowhere/SMPLX_NEUTRAL\.npz: not found"):
        score(tmp_path / "ref", tmp_path / "ref", body=lambda: SMPLFXBody(missing), smplx_path=fx_files.smplx)
    anny = type("Anny", (), {"name": "anny", "layout": None})()
    with pytest.raises(ScoreInputError, match=r"the workspace's body model is 'anny': set body\.model: smplfx"):
        score(tmp_path / "ref", tmp_path / "ref", body=anny)
    with pytest.raises(ScoreInputError, match=r"relative to SMPL-X's mean hand .* needs the SMPL-X file "
                                              r"\(body\.smplx_path in params\.yaml\)"):
        score(tmp_path / "ref", tmp_path / "ref", body=fx)
    flat = score(tmp_path / "ref", tmp_path / "ref", ["soke_exact"], body=fx, flat_hand_mean=True)
    assert flat.metrics["soke_exact_dtw_jpe_left_hand_m"] == pytest.approx(0.0, abs=1e-7)
