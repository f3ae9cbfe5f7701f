"""Behaviour details of the fitting component (:mod:`m3t.fitting`) that the coarser engine tests do not pin down:
what the content keys of tracks, fits, batch fits and imports follow; how one signer's batch treats its imported,
failing and fused clips; the quarantine record; which config sections and artifact folders the MLflow run of a
corpus gets; the data-quality and import summaries; the solver's schedule, the default camera and the batch's
error message; the executors built without starting a cluster. Written to pin behaviours that mutation testing
found unchecked.

Corpora:

- a hand-written synthetic corpus (:func:`m3t.corpora.synthetic.write_corpus`, the project's own layout:
  ``clips.jsonl`` + ``motion/<id>.npz``) of four short clips, three of signer ``s0``, one of ``s1``;
- an index-CSV ``.pose`` collection of real pose-format files (the packaged fingerspelling lexicon, as in
  ``tests/test_fusion_flow.py``), one clip with an NLF output beside its media;
- neccam/slt's gzip pickles (``corpus_fixtures.build_slt_import``, which cites its source).
"""
from __future__ import annotations

import csv
import dataclasses
import json
import math
import shutil
from pathlib import Path
from typing import ClassVar

import corpus_fixtures as cfx
import numpy as np
import pytest
import torch
from test_fitting import front_camera, smooth_motion

from m3t.config import load_params
from m3t.corpora.clip import Clip
from m3t.corpora.synthetic import SyntheticClip, write_corpus
from m3t.fitting.corpus import (
    NO_EXTERNAL,
    FitContext,
    process_batch,
    process_clip,
    track_clip,
)
from m3t.fitting.report import ClipOutcome
from m3t.shards.io import read_shard
from m3t.trackers.track import load_track

ROOT = Path(__file__).resolve().parents[1]
FAST = {"iterations": 4, "camera_iterations": 2}
IDENTITY = np.array([0.4, 0.5, 0.5, 0.45, 0.6, 0.5], np.float32)
SYNTHETIC = (("s0-a", "s0", 8), ("s0-b", "s0", 6), ("s0-c", "s0", 5), ("s1-a", "s1", 7))


@pytest.fixture(autouse=True)
def _one_thread():
    """Small fits run fastest on one intra-op thread (conftest restores the count after each test)."""
    torch.set_num_threads(1)


# ------------------------------------------------------------------------------------------ corpora
def synthetic_clip(body, clip_id: str, signer: str, frames: int, seed: int) -> SyntheticClip:
    """One clip of the synthetic corpus' own layout: smooth motion, a fixed identity, a frontal camera."""
    params = {k: v.numpy() for k, v in smooth_motion(body, frames=frames, seed=seed).items()}
    clip = Clip(clip_id, "synthetic", "train", "ASL-SYN", signer, "a text", "A GLOSS", f"motion/{clip_id}.npz", 25.0)
    return SyntheticClip(clip, params, IDENTITY, front_camera())


@pytest.fixture(scope="module")
def synthetic_root(body, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synthetic") / "corpus"
    write_corpus([synthetic_clip(body, i, s, n, seed) for seed, (i, s, n) in enumerate(SYNTHETIC)], root)
    return root


def fit_job(tmp_path: Path, corpus: str, root: Path, options: dict | None = None, fit_corpus: dict | None = None,
            **sections):
    """The tiny preset's job of ``corpus`` at ``root``, with its cache and shards under ``tmp_path``."""
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "corpora": {corpus: {"root": str(root), "options": options or {}}},
        "data": {"shards_root": str(tmp_path / "shards")},
        "fitting": {**FAST, **sections.pop("fitting", {})},
        "fit_corpus": {"cache_dir": str(tmp_path / "cache"), "workers": 1, **(fit_corpus or {})},
        **sections})
    return params.fit_job(corpus)


def synthetic_ctx(tmp_path: Path, root: Path, model, **sections) -> FitContext:
    """The synthetic job's context sharing the session's built Anny ``model`` (``sections`` override params)."""
    return FitContext(fit_job(tmp_path, "synthetic", root, **sections), model)


def clips_of(ctx: FitContext) -> dict[str, Clip]:
    return {c.id: c for c in ctx.corpus.listing().clips}


# ------------------------------------------------------------------------------------------ track keys
def test_a_synthetic_track_is_keyed_by_its_media_the_tracker_and_the_body_model(body, synthetic_root, tmp_path):
    """The cached track is reused while nothing it depends on changes, and redone (a new file) when the motion
    file, the simulated tracker's settings or the body model's key change."""
    root = tmp_path / "corpus"
    shutil.copytree(synthetic_root, root)
    ctx = synthetic_ctx(tmp_path, root, body)
    clip = clips_of(ctx)["s0-b"]
    first = track_clip(clip, ctx)
    assert first.parent == tmp_path / "cache" / "tracks" and first.name.startswith("s0-b-")
    assert track_clip(clip, synthetic_ctx(tmp_path, root, body)) == first  # a new process finds it again
    assert load_track(first).num_frames == 6

    noisier = track_clip(clip, synthetic_ctx(tmp_path, root, body, tracker={"seed": 5}))
    assert noisier != first
    assert not np.array_equal(load_track(noisier).keypoints, load_track(first).keypoints, equal_nan=True)
    # the body model's cache key (SMPL-FX: its options and files) is part of the track's address
    other_body = synthetic_ctx(tmp_path, root, body, body={"model": "smplfx"})
    assert track_clip(clip, other_body) not in (first, noisier)

    with np.load(root / clip.media) as data:
        arrays = dict(data)
    arrays["identity"] = arrays["identity"] + np.float32(0.01)  # another signer's body in the motion file
    np.savez(root / clip.media, **arrays)
    moved = track_clip(clip, synthetic_ctx(tmp_path, root, body))
    assert moved not in (first, noisier) and moved.name.startswith("s0-b-")
    assert not np.array_equal(load_track(moved).keypoints, load_track(first).keypoints, equal_nan=True)

    (root / clip.media).unlink()
    with pytest.raises(FileNotFoundError, match=r"s0-b\.npz of clip s0-b is missing"):
        track_clip(clip, ctx)
    # an id with a slash names a file in the tracks folder, never a subfolder
    nested = track_clip(dataclasses.replace(clips_of(ctx)["s0-c"], id="session/s0-c"), ctx)
    assert nested.parent == first.parent and nested.name.startswith("session_s0-c-")


# ------------------------------------------------------------------------------------------ one clip
def test_a_synthetic_fit_records_what_refinement_gained_over_the_tracker(body, synthetic_root, tmp_path):
    from m3t.fitting.evaluate import joints_for, procrustes_error_mm

    ctx = synthetic_ctx(tmp_path, synthetic_root, body)
    clip = clips_of(ctx)["s1-a"]
    outcome = process_clip(clip, ctx)
    assert outcome.status == "fitted" and outcome.frames == outcome.track_frames == 7
    assert outcome.init == {"init_source": "simulated tracker initialisation"}
    assert outcome.seconds > 0 and set(outcome.coverage) == {"missing_left_hand", "missing_right_hand", "missing_face"}
    fitted = read_shard(outcome.part).clips[0]
    assert fitted.metrics == outcome.metrics and fitted.key in Path(outcome.part).name
    track = load_track(track_clip(clip, ctx))
    params, identity, _ = ctx.ground_truth(clip)
    with torch.no_grad():
        want = procrustes_error_mm(joints_for(body, track.init, body.default_identity().numpy()),
                                   joints_for(body, params, identity))
    assert outcome.metrics["init_pa_joint_mm"] == pytest.approx(want, rel=1e-5)
    # against the ground truth, per landmark part, and the solver's own
    for key in ("pa_joint_mm", "joint_mm", "reproj_px_parts", "reproj_px_pose", "reproj_px", "final_loss"):
        assert math.isfinite(outcome.metrics[key]), key
    again = process_clip(clip, ctx)
    assert (again.status, again.part, again.metrics, again.init) == ("cached", outcome.part, outcome.metrics,
                                                                    outcome.init)


def test_a_clip_that_fails_is_quarantined_with_its_reason_file_and_time(body, synthetic_root, tmp_path):
    ctx = synthetic_ctx(tmp_path, synthetic_root, body)
    gone = dataclasses.replace(clips_of(ctx)["s0-a"], id="gone", media="motion/gone.npz", split="dev")
    outcome = process_clip(gone, ctx)
    assert (outcome.clip_id, outcome.split, outcome.status, outcome.part) == ("gone", "dev", "quarantined", None)
    assert outcome.reason.startswith("FileNotFoundError: media file ") and "gone.npz of clip gone" in outcome.reason
    assert outcome.group == "FileNotFoundError" and outcome.file == "motion/gone.npz"
    assert isinstance(outcome.seconds, float) and 0 <= outcome.seconds < 60
    # a refusal counts under its own short reason
    unknown = Clip("x1", "posefile", "train", "ase", "s0", "", "", "x1.pose", 25.0)
    refused = process_clip(unknown, ctx)
    assert refused.status == "quarantined" and refused.group == "no media kind"
    assert "clip x1 carries no media_kind" in refused.reason and refused.file == "x1.pose"
    assert isinstance(refused.seconds, float)


# ------------------------------------------------------------------------------------------ signer batches
def identity_of(outcome: ClipOutcome) -> np.ndarray:
    return read_shard(outcome.part).clips[0].identity


def test_two_clips_of_a_signer_are_fitted_together(body, synthetic_root, tmp_path):
    ctx = synthetic_ctx(tmp_path, synthetic_root, body, fit_corpus={"batch_clips": 2})
    clips = clips_of(ctx)
    outcomes = process_batch([clips["s0-a"], clips["s0-b"]], ctx)
    assert [o.clip_id for o in outcomes] == ["s0-a", "s0-b"] and {o.status for o in outcomes} == {"fitted"}
    for o in outcomes:
        assert o.init == {"init_source": "simulated tracker initialisation",
                          "identity": "one per batch: 2 clips of signer 's0'"}
        assert "init_pa_joint_mm" in o.metrics and o.frames == o.track_frames
    assert np.array_equal(identity_of(outcomes[0]), identity_of(outcomes[1]))
    keys = {read_shard(o.part).clips[0].key for o in outcomes}
    assert len(keys) == 1  # one fit, one key
    assert all(Path(o.part).name == f"{o.clip_id}-{next(iter(keys))}.parquet" for o in outcomes)
    assert [o.frames for o in outcomes] == [8, 6]


def test_a_batch_fit_is_keyed_by_its_members_tracks_and_chunking(body, synthetic_root, tmp_path):
    """Another tracker (other tracks) or another chunking refits the batch; the same inputs find its parts."""
    clips = clips_of(synthetic_ctx(tmp_path, synthetic_root, body))
    pair = [clips["s0-a"], clips["s0-c"]]
    ctx = synthetic_ctx(tmp_path, synthetic_root, body, fit_corpus={"batch_clips": 2})
    first = [o.part for o in process_batch(pair, ctx)]
    again = process_batch(pair, synthetic_ctx(tmp_path, synthetic_root, body, fit_corpus={"batch_clips": 2}))
    assert [o.part for o in again] == first and {o.status for o in again} == {"cached"}
    for changed in (synthetic_ctx(tmp_path, synthetic_root, body, tracker={"seed": 9}, fit_corpus={"batch_clips": 2}),
                    synthetic_ctx(tmp_path, synthetic_root, body, fit_corpus={"batch_clips": 2, "batch_frames": 7})):
        outcomes = process_batch(pair, changed)
        assert {o.status for o in outcomes} == {"fitted"}
        assert not {o.part for o in outcomes} & set(first)


def test_a_clip_failing_to_track_leaves_the_batch_to_the_others(body, synthetic_root, tmp_path):
    ctx = synthetic_ctx(tmp_path, synthetic_root, body, fit_corpus={"batch_clips": 3})
    clips = clips_of(ctx)
    gone = dataclasses.replace(clips["s0-c"], id="gone", media="motion/gone.npz")
    outcomes = process_batch([clips["s0-a"], gone, clips["s0-b"]], ctx)
    by_id = {o.clip_id: o for o in outcomes}
    assert sorted(by_id) == ["gone", "s0-a", "s0-b"]
    assert by_id["gone"].status == "quarantined" and "gone.npz of clip gone is missing" in by_id["gone"].reason
    assert by_id["gone"].group == "FileNotFoundError" and by_id["gone"].file == "motion/gone.npz"
    for clip_id in ("s0-a", "s0-b"):
        assert by_id[clip_id].status == "fitted"
        assert by_id[clip_id].init["identity"] == "one per batch: 2 clips of signer 's0'"
    # one member left: it is fitted alone (its own identity, no batch record)
    alone = process_batch([gone, clips["s0-c"]], ctx)
    assert [o.status for o in alone] == ["quarantined", "fitted"]
    assert alone[1].init == {"init_source": "simulated tracker initialisation"}


# ------------------------------------------------------------------------------------------ real clips
LETTERS = {"fused": "A", "plain-a": "H", "plain-b": "I"}  # ids -> ASL letters of the packaged lexicon


def write_nlf_npz(path: Path, frames: int) -> None:
    """NLF's stacked ``.npz`` as ``fusion_fixtures.write_nlf`` documents it (``detect_smpl_batched`` with
    ``model_name='smplx'``, stacked for the signer): ``pose`` (T, 165) axis-angle, ``betas`` (T, 10), ``trans``
    (T, 3), ``confidence`` (T,); the signer at rest, facing the camera."""
    pose = np.zeros((frames, 55, 3))
    pose[:, 0] = (0.0, 3.1, 0.1)
    np.savez(path, pose=pose.reshape(frames, 165), betas=np.zeros((frames, 10)),
             trans=np.tile([0.0, 0.2, 3.0], (frames, 1)), confidence=np.full(frames, 0.9))


@pytest.fixture(scope="module")
def pose_root(tmp_path_factory) -> Path:
    """Three ASL letters copied from the packaged lexicon (real pose-format files, as in
    ``tests/test_fusion_flow.py``) into an index-CSV ``.pose`` collection (``id,path,split,text,language,signer``,
    :mod:`m3t.corpora.posefile`), one signer; ``fused`` has an NLF output beside its media."""
    from pose_format import Pose

    from m3t.corpora.fingerspelling import lexicon_root

    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        paths = {r["words"]: r["path"] for r in csv.DictReader(fh) if r["signed_language"] == "ase"}
    root = tmp_path_factory.mktemp("poses") / "collection"
    root.mkdir()
    lines = ["id,path,split,text,language,signer"]
    for clip_id, letter in LETTERS.items():
        shutil.copyfile(lexicon_root() / paths[letter], root / f"{clip_id}.pose")
        lines.append(f"{clip_id},{clip_id}.pose,train,{letter},ase,s0")
    (root / "index.csv").write_text("\n".join(lines) + "\n")
    frames = int(Pose.read((root / "fused.pose").read_bytes()).body.data.shape[0])
    write_nlf_npz(root / "fused.nlf.npz", frames)
    return root


def pose_ctx(tmp_path: Path, root: Path, model, **sections) -> FitContext:
    job = fit_job(tmp_path, "posefile", root, {"index": "index.csv"}, **sections)
    return FitContext(job, model)


def test_a_signers_batch_leaves_a_clip_with_tracker_outputs_to_its_own_fit(body, pose_root, tmp_path):
    """Anny cannot take NLF's SMPL-X rotations: that clip is fitted on its own from the rest pose and its record
    says why; the signer's two other clips share one identity."""
    ctx = pose_ctx(tmp_path, pose_root, body, fit_corpus={"batch_clips": 3})
    clips = clips_of(ctx)
    outcomes = {o.clip_id: o for o in process_batch([clips[i] for i in LETTERS], ctx)}
    assert sorted(outcomes) == sorted(LETTERS) and {o.status for o in outcomes.values()} == {"fitted"}
    fused = outcomes["fused"]
    assert fused.init["init_source"].startswith("rest pose: external outputs (nlf) present but not usable: "
                                                "body model 'anny' cannot take nlf")
    assert "identity" not in fused.init
    for clip_id in ("plain-a", "plain-b"):
        assert outcomes[clip_id].init == {"init_source": NO_EXTERNAL,
                                          "identity": "one per batch: 2 clips of signer 's0'"}
    assert np.array_equal(identity_of(outcomes["plain-a"]), identity_of(outcomes["plain-b"]))
    assert not np.array_equal(identity_of(fused), identity_of(outcomes["plain-a"]))
    for o in outcomes.values():  # real clips: no ground truth, only how well the fit explains the track
        assert "pa_joint_mm" not in o.metrics and "init_pa_joint_mm" not in o.metrics
        assert math.isfinite(o.metrics["reproj_px_parts"]) and o.frames == o.track_frames > 0


def test_a_real_clips_track_and_fit_follow_its_media_and_its_tracker_outputs(body, pose_root, tmp_path):
    root = tmp_path / "collection"
    shutil.copytree(pose_root, root)
    ctx = pose_ctx(tmp_path, root, body)
    clips = clips_of(ctx)
    fused, plain = process_clip(clips["fused"], ctx), process_clip(clips["plain-a"], ctx)
    track = track_clip(clips["plain-b"], ctx)
    assert track_clip(clips["plain-b"], ctx) == track and load_track(track).num_frames == 22  # letter I
    off = pose_ctx(tmp_path, root, body, fusion={"use_external": False})
    unfused = process_clip(clips["fused"], off)
    assert unfused.status == "fitted" and unfused.part != fused.part
    assert unfused.init == {"init_source": "rest pose: fusion.use_external is off"}
    assert process_clip(clips["plain-a"], off).part == plain.part  # no outputs: the fusion settings do not count
    write_nlf_npz(root / "fused.nlf.npz", fused.track_frames)  # the same content: the same fit
    assert process_clip(clips["fused"], ctx).status == "cached"
    arrays = dict(np.load(root / "fused.nlf.npz"))
    arrays["betas"] = arrays["betas"] + 0.5
    np.savez(root / "fused.nlf.npz", **arrays)
    refit = process_clip(clips["fused"], pose_ctx(tmp_path, root, body))
    assert refit.status == "fitted" and refit.part not in (fused.part, unfused.part)
    # a real clip's track follows its media's content
    shutil.copyfile(root / "plain-a.pose", root / "plain-b.pose")
    retracked = track_clip(clips["plain-b"], pose_ctx(tmp_path, root, body))
    assert retracked != track and load_track(retracked).num_frames == 20  # letter H now


# ------------------------------------------------------------------------------------------ imports
def slt_ctx(tmp_path: Path, root: Path, **fit_corpus) -> FitContext:
    """An slt import job: no body model is built (the FLAME path points nowhere)."""
    return FitContext(fit_job(tmp_path, "slt_pickle", root, body={"flame_path": str(tmp_path / "absent.pkl")},
                              fit_corpus=fit_corpus))


def rewrite_sign(pickle_file: Path, name: str, change) -> None:
    """Apply ``change`` to the ``sign`` array of record ``name`` of an slt gzip pickle, in place."""
    import gzip
    import pickle

    with gzip.open(pickle_file, "rb") as fh:
        entries = pickle.load(fh)
    for entry in entries:
        if entry["name"] == name:
            entry["sign"] = change(entry["sign"].copy())
    with gzip.open(pickle_file, "wb") as fh:
        pickle.dump(entries, fh)


def test_an_imported_part_is_keyed_by_the_source_arrays_bytes(tmp_path):
    root = cfx.build_slt_import(tmp_path / "slt").root
    ctx = slt_ctx(tmp_path, root, batch_clips=2)
    clips = clips_of(ctx)
    clip = clips["train__clip0"]
    outcomes = process_batch([clip, clips["train__clip1"]], ctx)  # imports go one by one, never batch-fitted
    assert [o.clip_id for o in outcomes] == ["train__clip0", "train__clip1"]
    assert [o.init for o in outcomes] == [{"init_source": "imported: slt sign arrays, no tracking or fitting"}] * 2
    first = outcomes[0]
    row = read_shard(first.part).clips[0]
    assert Path(first.part).name == f"train__clip0-{row.key}.parquet"
    original = ctx.corpus.sequence(clip)
    np.testing.assert_array_equal(row.params["sign"], original)

    pickle_file = root / "phoenix14t.pami0.train"
    rewrite_sign(pickle_file, "train/clip0", lambda a: np.where(np.arange(a.shape[1]) == 5, a + 1, a))
    changed = process_clip(clip, slt_ctx(tmp_path, root))
    assert changed.status == "fitted" and changed.part != first.part
    np.testing.assert_array_equal(read_shard(changed.part).clips[0].params["sign"][:, 5], original[:, 5] + 1)
    rewrite_sign(pickle_file, "train/clip0", lambda a: original)  # the same bytes again: the first part
    back = process_clip(clip, slt_ctx(tmp_path, root))
    assert (back.status, back.part) == ("cached", first.part)


# ------------------------------------------------------------------------------------------ MLflow
def file_store(tmp_path: Path, monkeypatch):
    """An MLflow store in ``tmp_path`` (the file backend: no database to create) and its client."""
    import mlflow

    from m3t.experiment import ExperimentConfig

    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    cfg = ExperimentConfig(tracking_uri=str(tmp_path / "store"), artifact_dir=str(tmp_path / "artifacts"),
                           experiment="fit-corpus-test", enabled=True)
    return cfg, mlflow.MlflowClient(tracking_uri=(tmp_path / "store").as_uri())


def only_run(client, cfg):
    experiment = client.get_experiment_by_name(cfg.experiment)
    (run,) = client.search_runs([experiment.experiment_id])
    return run


def artifacts(client, run_id: str, folder: str | None = None) -> set[str]:
    return {a.path for a in client.list_artifacts(run_id, folder)}


def test_a_synthetic_run_logs_its_sections_quality_and_fit_pictures(body, synthetic_root, tmp_path, monkeypatch):
    import m3t.fitting.corpus as engine

    monkeypatch.setattr(engine, "load_body_model", lambda cfg: body)  # the session's Anny, not a second build
    cfg, client = file_store(tmp_path, monkeypatch)
    job = fit_job(tmp_path, "synthetic", synthetic_root, fit_corpus={"max_clips": 1, "render_clips": 1})
    report = engine.fit_and_log(job, cfg, progress=False)
    assert report.summary["clips_fitted"] == 1
    run = only_run(client, cfg)
    params = run.data.params
    assert params["body.model"] == "anny" and params["fitting.iterations"] == "4"
    assert params["fit_corpus.render_clips"] == "1" and params["tracker.seed"] == str(job.tracker.seed)
    assert not [k for k in params if k.startswith("fusion.")]  # synthetic clips are never fused
    assert params["corpus"] == "synthetic" and params["shards_dir"] == job.shards_dir
    assert str(synthetic_root) in params["corpora.synthetic"]
    assert run.data.tags["corpus"] == "synthetic" and run.data.tags["body_model"] == "anny"
    assert run.data.metrics["clips_fitted"] == 1 and run.data.metrics["quality_clips_listed"] == 1
    run_id = run.info.run_id
    assert {"quarantine.jsonl", "summary.json", "quality.json", "quality.csv", "quality"} <= artifacts(client, run_id)
    assert "quality/quality-synthetic.png" in artifacts(client, run_id, "quality")
    assert artifacts(client, run_id, "fit_vs_ground_truth") == {"fit_vs_ground_truth/s0-a.png"}
    assert artifacts(client, run_id, "meshes") == {"meshes/s0-a_00004.ply", "meshes/s0-a_00004.png"}


def test_a_real_corpus_run_logs_the_fusion_section_and_no_tracker(tmp_path, monkeypatch):
    from m3t.fitting.corpus import fit_and_log

    cfg, client = file_store(tmp_path, monkeypatch)
    job = fit_job(tmp_path, "slt_pickle", cfx.build_slt_import(tmp_path / "slt").root,
                  body={"flame_path": str(tmp_path / "absent.pkl")}, fit_corpus={"render_clips": 2})
    fit_and_log(job, cfg, progress=False)
    run = only_run(client, cfg)
    params = run.data.params
    assert params["fusion.use_external"] == "True" and params["body.model"] == job.body.model
    assert not [k for k in params if k.startswith("tracker.")]
    assert params["corpus"] == "slt_pickle" and run.data.tags["body_model"] == ""  # feature shards: no pictures
    names = artifacts(client, run.info.run_id)
    assert "fit_vs_ground_truth" not in names and "meshes" not in names
    assert "quality/quality-slt_pickle.png" in artifacts(client, run.info.run_id, "quality")


# ------------------------------------------------------------------------------------------ reports
def test_the_quality_report_counts_fits_cache_hits_quarantines_and_missing_parts():
    from m3t.fitting.quality import quality_report

    seen = {"missing_left_hand": 0.0, "missing_right_hand": 0.5, "missing_face": 0.1}
    outcomes = [
        ClipOutcome("e", "test", "quarantined", reason="ValueError: the fit diverged", group="ValueError",
                    file="motion/e.npz", track_frames=20,
                    coverage={"missing_left_hand": 1.0, "missing_right_hand": 1.0, "missing_face": 1.0}),
        ClipOutcome("b", "dev", "cached", "parts/b.parquet", frames=30, track_frames=30,
                    coverage={"missing_left_hand": 0.2, "missing_right_hand": 0.0, "missing_face": 0.0},
                    metrics={"reproj_px_parts": 4.0, "reproj_shoulder_frac": 0.04}, init={"init_source": NO_EXTERNAL}),
        ClipOutcome("", "", "quarantined", reason="no split", group="listing: no split", file="index.csv", row=7,
                    from_listing=True),
        ClipOutcome("a", "train", "fitted", "parts/a.parquet", frames=10, track_frames=10, coverage=seen,
                    metrics={"reproj_px_parts": 2.0, "reproj_shoulder_frac": 0.02, "reproj_px_pose": 1.5,
                             "pa_joint_mm": 9.0}, init={"init_source": "simulated tracker initialisation"}),
        ClipOutcome("c", "train", "quarantined", reason="FileNotFoundError: gone", group="FileNotFoundError",
                    file="motion/c.npz"),
    ]
    report = quality_report(outcomes, "synthetic")
    assert [(r["clip_id"], r["status"]) for r in report.rows] == [
        ("a", "fitted"), ("b", "fitted"), ("", "quarantined"), ("c", "quarantined"), ("e", "quarantined")]
    a, b, listing = report.rows[:3]
    assert (a["missing_right_hand"], a["reproj_px_pose"], a["init_source"], a["frames"]) == (
        0.5, 1.5, "simulated tracker initialisation", 10)
    assert "pa_joint_mm" not in a and a["reproj_px_face"] == "" and a["row"] == ""
    assert (b["split"], b["reproj_px_parts"], b["init_source"]) == ("dev", 4.0, NO_EXTERNAL)
    assert (listing["file"], listing["row"], listing["group"], listing["reason"]) == ("index.csv", 7,
                                                                                      "listing: no split", "no split")
    s = report.summary
    assert (s["corpus"], s["clips_listed"], s["clips_fitted"], s["clips_quarantined"],
            s["clips_quarantined_at_listing"], s["frames"]) == ("synthetic", 4, 2, 3, 1, 40)
    assert s["quarantine_reasons"] == {"listing: no split": 1, "FileNotFoundError": 1, "ValueError": 1}
    assert s["init_sources"] == {"simulated tracker initialisation": 1, "rest pose": 1}
    # every tracked clip counts (the quarantined one too): frame-weighted overall, plain mean per clip
    assert s["missing_left_hand_ratio"] == pytest.approx((0.0 * 10 + 0.2 * 30 + 1.0 * 20) / 60)
    assert s["missing_left_hand_ratio_clip_mean"] == pytest.approx(0.4)
    assert s["missing_right_hand_ratio"] == pytest.approx((0.5 * 10 + 1.0 * 20) / 60)
    assert (s["reproj_px_parts_median"], s["reproj_px_parts_max"]) == (3.0, 4.0)
    assert s["reproj_px_parts_p90"] == pytest.approx(3.8) and s["reproj_shoulder_frac_max"] == 0.04

    empty = quality_report([ClipOutcome("x", "train", "quarantined", group=None)], "slt")
    assert empty.summary["quarantine_reasons"] == {"unknown": 1} and empty.summary["frames"] == 0
    assert math.isnan(empty.summary["missing_face_ratio"]) and math.isnan(empty.summary["reproj_px_parts_median"])


def test_quality_files_hold_rounded_rows_and_null_for_missing_values(tmp_path):
    from m3t.atomic import write_text
    from m3t.fitting.quality import COLUMNS, quality_report, write_quality

    report = quality_report([ClipOutcome("a", "train", "fitted", frames=3, metrics={"reproj_px_parts": 1 / 3})], "x")
    csv_path, json_path = write_quality(report, tmp_path, write_text)
    rows = list(csv.DictReader(csv_path.open()))
    assert tuple(rows[0]) == COLUMNS and rows[0]["reproj_px_parts"] == "0.3333" and rows[0]["frames"] == "3"
    summary = json.loads(json_path.read_text())
    assert summary["missing_face_ratio"] is None and summary["reproj_px_parts_median"] == pytest.approx(1 / 3)


def test_the_import_summary_covers_imported_clips_only():
    from m3t.fitting.report import import_summary

    imported = {"init_source": "imported: slt sign arrays, no tracking or fitting"}
    outcomes = [
        ClipOutcome("i1", "train", "fitted", frames=10, init=imported,
                    metrics={"src_nonfinite_frame_frac": 0.1, "src_sign_min": -2.0, "src_sign_max": 3.0,
                             "src_betas_frame_std": 0.5}),
        ClipOutcome("i2", "dev", "cached", frames=30, init=imported,
                    metrics={"src_nonfinite_frame_frac": 0.0, "src_sign_min": -1.0, "src_sign_max": 5.0}),
        ClipOutcome("f", "train", "fitted", frames=50, init={"init_source": "simulated tracker initialisation"},
                    metrics={"src_sign_min": -100.0}),
        ClipOutcome("n", "train", "fitted", frames=50, metrics={"src_sign_max": 100.0}),
        ClipOutcome("q", "train", "quarantined", init=imported, metrics={"src_sign_max": 100.0}),
    ]
    assert import_summary(outcomes) == {"imported_clips": 2, "imported_nonfinite_frame_frac": pytest.approx(0.025),
                                        "imported_sign_min": -2.0, "imported_sign_max": 5.0}
    assert import_summary(outcomes[2:]) == {}
    no_frames = import_summary([dataclasses.replace(outcomes[0], frames=0)])
    assert no_frames["imported_clips"] == 1 and math.isnan(no_frames["imported_nonfinite_frame_frac"])


# ------------------------------------------------------------------------------------------ import conversion
def import_kw():
    from m3t.fitting.imports import ImportSettings

    clip = Clip("c7", "mead", "train", "en", "M003", "", "", "M003/front/c7.hdf5", 30.0)
    return clip, ImportSettings("smplfx", 100)


def test_non_finite_frames_take_the_nearest_finite_frame_in_every_array():
    from m3t.fitting.imports import import_clip

    clip, settings = import_kw()
    src = cfx.flame_arrays(frames=5)
    src["jaw"][[0, 2, 4]] = np.nan  # frames 1 and 3 finite: frame 2 is a tie (the earlier wins)
    src["exp"][0, 3] = np.inf
    fitted, init = import_clip(clip, "flame_params", src, "key0", settings)
    assert init == {"init_source": "imported: MEAD FLAME parameters, no tracking or fitting"}
    assert fitted.metrics["src_nonfinite_frame_frac"] == pytest.approx(0.6)
    face = fitted.params["face"]
    for t, source in enumerate((1, 1, 1, 3, 3)):
        np.testing.assert_array_equal(face[t, :50], src["exp"][source], err_msg=str(t))
    assert fitted.metrics["src_jaw_min"] == float(np.nanmin(src["jaw"][[1, 3]]))
    assert fitted.key == "key0" and fitted.camera == {} and fitted.body_model == "smplfx"


def test_a_source_without_usable_frames_is_refused_naming_the_clip():
    from m3t.fitting.imports import import_clip
    from m3t.trackers.dispatch import ClipRefused

    clip, settings = import_kw()
    with pytest.raises(ClipRefused, match=r"clip c7: every one of its 3 frames holds NaN or inf") as info:
        import_clip(clip, "keypoints", {"sign": np.full((3, 4), np.nan, np.float32)}, "k", settings)
    assert info.value.group == "no finite frame"
    with pytest.raises(ClipRefused, match=r"clip c7: source arrays have \[2, 3\] frames") as info:
        import_clip(clip, "flame_params", {**cfx.flame_arrays(3), "jaw": np.zeros((2, 3))}, "k", settings)
    assert info.value.group == "no frames"
    with pytest.raises(ClipRefused, match=r"\[0\] frames") as info:
        import_clip(clip, "keypoints", {"sign": np.zeros((0, 4), np.float32)}, "k", settings)
    assert info.value.group == "no frames"


# ------------------------------------------------------------------------------------------ the solver
@pytest.fixture(scope="module")
def short_track(body):
    from m3t.trackers.simulated import SimulatedTrackerConfig, simulate_track

    return simulate_track("short", smooth_motion(body, frames=3), torch.as_tensor(IDENTITY), front_camera(), 25.0,
                          body, SimulatedTrackerConfig(seed=3))


def test_a_track_without_intrinsics_gets_a_centred_camera_of_the_guessed_focal_length(body, short_track):
    from m3t.fitting.fit import FittingConfig, fit_track

    cfg = FittingConfig(iterations=1, camera_iterations=1, focal_guess=1.5)
    track = dataclasses.replace(short_track, intrinsics=np.full(4, np.nan), image_size=(640, 480))
    camera = fit_track(track, body, cfg).camera
    assert (camera["fx"], camera["fy"], camera["cx"], camera["cy"]) == (960.0, 960.0, 320.0, 240.0)
    assert (camera["width"], camera["height"]) == (640, 480)
    known = dataclasses.replace(track, intrinsics=np.array([700.0, 710.0, 300.0, 250.0]))
    camera = fit_track(known, body, cfg).camera
    assert (camera["fx"], camera["fy"], camera["cx"], camera["cy"]) == (700.0, 710.0, 300.0, 250.0)


def test_a_batch_names_its_tracks_without_any_visible_landmark(body, short_track):
    from m3t.fitting.fit import FittingConfig, fit_tracks

    blind = dataclasses.replace(short_track, confidence=np.zeros_like(short_track.confidence))
    cfg = FittingConfig(iterations=1, camera_iterations=1)
    with pytest.raises(ValueError, match=r"^track\(s\) 0, 2 of the batch have no visible landmark with a body-model "
                                         r"correspondence in any frame$"):
        fit_tracks([blind, short_track, blind], body, cfg)
    with pytest.raises(ValueError, match=r"^the track has no visible landmark"):
        fit_tracks([blind], body, cfg)


def test_adam_steps_decay_on_a_cosine_to_five_percent_of_the_rate():
    """On a linear objective every Adam step moves the variable by the current learning rate."""
    from m3t.fitting.fit import FittingConfig, _minimise

    x = torch.zeros(1, requires_grad=True)
    curve: list[float] = []
    projected = []
    cfg = FittingConfig(solver="adam", iterations=20, camera_iterations=3)
    _minimise(lambda: x.sum(), [x], cfg, "full", 0.1, curve, project_bounds=lambda: projected.append(1))
    positions = [0.0, *curve[1:], float(x.detach())]
    steps = -np.diff(positions)  # step k: the rate after k decays
    assert len(curve) == 20 and len(projected) == 20 and curve[0] == 0.0
    assert steps[0] == pytest.approx(0.1, rel=1e-4)
    assert np.all(np.diff(steps) < 0)  # decaying
    assert 0.05 * 0.1 < steps[-1] < 0.06 * 0.1  # close to 5 % at the end (cosine: 5 % + 95 % * 0.6 %)
    assert steps[10] == pytest.approx(0.1 * (0.05 + 0.95 * 0.5), rel=1e-4)  # half-way: half of the decay

    camera: list[float] = []
    _minimise(lambda: x.sum(), [x], cfg, "camera", 0.1, camera)
    assert len(camera) == 3  # the camera stage's own budget


def test_lbfgs_spends_at_most_its_evaluation_budget():
    from m3t.fitting.fit import FittingConfig, _minimise

    x = torch.tensor([3.0, -2.0], requires_grad=True)
    curve: list[float] = []
    _minimise(lambda: ((x - 1.0) ** 2).sum(), [x], FittingConfig(iterations=7, lbfgs_round=3), "full", 0.0, curve)
    assert 0 < len(curve) <= 7 and curve[-1] < 1e-6 < curve[0]
    untouched = torch.tensor([3.0], requires_grad=True)
    none: list[float] = []
    _minimise(lambda: (untouched ** 2).sum(), [untouched], FittingConfig(iterations=0), "full", 0.0, none)
    assert none == [] and float(untouched.detach()) == 3.0


# ------------------------------------------------------------------------------------------ executors
def test_the_local_process_pool_spawns_single_threaded_workers():
    """Spawned, not forked: a forked child inherits torch's thread pool and locks of a process that already
    fitted; each worker runs with one intra-op thread."""
    from concurrent.futures import ProcessPoolExecutor

    from m3t.fitting.cluster import one_thread, open_executor, process_pool
    from m3t.fitting.config import FitCorpusConfig

    assert process_pool(1) is None and process_pool(0) is None  # one worker: clips run in this process
    pool = process_pool(3)
    try:
        assert isinstance(pool, ProcessPoolExecutor) and pool._max_workers == 3
        assert pool._mp_context.get_start_method() == "spawn" and pool._initializer is one_thread
    finally:
        pool.shutdown()
    with open_executor(FitCorpusConfig(executor="local", workers=1)) as executor:
        assert executor is None
    with (pytest.raises(ValueError, match=r"fit_corpus.executor: 'ray' is not allowed; expected 'local' or 'dask'"),
          open_executor(FitCorpusConfig(executor="ray"))):
        pass


class FakeCluster:
    """What ``connect_dask`` asks of ``distributed.LocalCluster``: its arguments, and ``close``."""

    made: ClassVar[list] = []

    def __init__(self, **kwargs):
        self.kwargs, self.closed = kwargs, False
        FakeCluster.made.append(self)

    def close(self, timeout=None):
        self.closed = True


class FakeClient:
    """What ``DaskExecutor`` asks of ``distributed.Client``: the scheduler's address, an executor, ``close``."""

    made: ClassVar[list] = []
    fail: ClassVar[Exception | None] = None

    def __init__(self, address, **kwargs):
        if FakeClient.fail is not None:
            raise FakeClient.fail
        self.address, self.kwargs, self.closed, self.status = address, kwargs, False, "closed"
        self.scheduler = type("Scheduler", (), {"address": address if isinstance(address, str) else "tcp://local"})
        FakeClient.made.append(self)

    def get_executor(self):
        return None

    def close(self, timeout=None):
        self.closed = True


@pytest.fixture()
def fake_dask(monkeypatch):
    import distributed

    monkeypatch.setattr(distributed, "LocalCluster", FakeCluster)
    monkeypatch.setattr(distributed, "Client", FakeClient)
    FakeCluster.made, FakeClient.made, FakeClient.fail = [], [], None
    yield
    FakeClient.fail = None


def test_a_dask_run_without_an_address_starts_and_closes_its_own_single_threaded_cluster(fake_dask):
    from m3t.fitting.cluster import CONNECT_SECONDS, connect_dask
    from m3t.fitting.config import FitCorpusConfig

    executor = connect_dask(FitCorpusConfig(executor="dask", workers=3))
    (cluster,), (client,) = FakeCluster.made, FakeClient.made
    assert {k: cluster.kwargs[k] for k in ("n_workers", "threads_per_worker", "processes")} == {
        "n_workers": 3, "threads_per_worker": 1, "processes": True}
    assert cluster.kwargs["dashboard_address"].endswith(":0")  # a free port, never the default 8787
    assert client.address is cluster and client.kwargs == {"set_as_default": False}  # never the process' default
    assert executor.client is client and executor.address == "tcp://local"
    executor.shutdown()
    assert client.closed and cluster.closed

    connect_dask(FitCorpusConfig(executor="dask", workers=0))
    assert FakeCluster.made[-1].kwargs["n_workers"] == 1

    FakeClient.fail = RuntimeError("no client")
    with pytest.raises(RuntimeError, match="no client"):
        connect_dask(FitCorpusConfig(executor="dask", workers=2))
    assert FakeCluster.made[-1].closed  # a cluster started for nothing is not left running

    FakeClient.fail = None
    remote = connect_dask(FitCorpusConfig(executor="dask", dask_address="tcp://scheduler:8786"))
    assert len(FakeCluster.made) == 3 and FakeClient.made[-1].address == "tcp://scheduler:8786"
    assert FakeClient.made[-1].kwargs == {"timeout": CONNECT_SECONDS, "set_as_default": False}
    remote.shutdown()
    assert FakeClient.made[-1].closed  # a running cluster is left running: only the client closes
    FakeClient.fail = OSError("refused")
    with pytest.raises(ConnectionError, match=rf"no Dask scheduler answered at 'tcp://scheduler:8786' within "
                                              rf"{CONNECT_SECONDS:.0f} s \(refused\)"):
        connect_dask(FitCorpusConfig(executor="dask", dask_address="tcp://scheduler:8786"))
