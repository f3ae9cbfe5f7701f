"""Behaviour details of the fitting component (:mod:`m3t.fitting`) that the coarser engine tests do not pin down:
what the content keys of tracks, fits, batch fits and imports follow (the key version included); how one signer's
batch treats its imported, failing and fused clips; the quarantine record; which config sections and artifact
folders the MLflow run of a corpus gets; the data-quality and import summaries; the solver's schedule, the bounds
every objective evaluation respects, the identity a batch holds fixed, the default camera and the batch's error
message; the executors built without starting a cluster; the run's scheduler (capacity, polling, dead workers,
failing tasks) driven by in-process stand-in executors; the cache's integrity checks; fusion's messages,
interpolation and initialisation record; the camera-only stage. Written to pin behaviours that mutation testing
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
from builders import front_camera, smooth_motion

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
# lbfgs: a signer batch (fit_corpus.batch_clips) is one problem with one identity, what the batch tests here check;
# the default, lbfgs_batched (every clip its own problem), is tested in test_lbfgs_batched.py and the pipeline tests
FAST = {"iterations": 4, "camera_iterations": 2, "solver": "lbfgs"}
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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
    cfg = FittingConfig(solver="lbfgs", iterations=7, lbfgs_round=3)
    _minimise(lambda: ((x - 1.0) ** 2).sum(), [x], cfg, "full", 0.0, curve)
    assert 0 < len(curve) <= 7 and curve[-1] < 1e-6 < curve[0]
    untouched = torch.tensor([3.0], requires_grad=True)
    none: list[float] = []
    _minimise(lambda: (untouched ** 2).sum(), [untouched], FittingConfig(solver="lbfgs", iterations=0), "full", 0.0,
              none)
    assert none == [] and float(untouched.detach()) == 3.0


# ------------------------------------------------------------------------------------------ executors
@pytest.mark.slow
def test_the_local_process_pool_spawns_single_threaded_workers():
    """Spawned, not forked: a forked child inherits torch's thread pool and locks of a process that already
    fitted; each worker runs with one intra-op thread."""
    from concurrent.futures import ProcessPoolExecutor

    from m3t.fitting.cluster import open_executor, process_pool
    from m3t.fitting.config import FitCorpusConfig

    assert process_pool(1) is None and process_pool(0) is None  # one worker: clips run in this process
    torch.set_num_threads(2)  # what the workers must not inherit
    pool = process_pool(3)
    try:
        assert isinstance(pool, ProcessPoolExecutor) and pool._max_workers == 3
        assert pool._mp_context.get_start_method() == "spawn"
        assert pool.submit(torch.get_num_threads).result(timeout=120) == 1
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


# ------------------------------------------------------------------------------------------ jobs sent to workers
def test_a_worker_process_fits_with_one_torch_thread():
    from m3t.fitting.cluster import on_worker, one_thread

    torch.set_num_threads(2)
    one_thread()
    assert torch.get_num_threads() == 1
    one_thread()  # already one: stays one
    assert torch.get_num_threads() == 1
    torch.set_num_threads(3)
    assert on_worker(lambda a, b=0: (a, b, torch.get_num_threads()), "clip", b=4) == ("clip", 4, 1)


def test_a_job_sent_to_other_machines_names_its_paths_absolutely(tmp_path, monkeypatch):
    """The cache dir, the corpus root and the body model's build cache are made absolute against this process'
    working directory; an empty root (the adapter's packaged default) and the licensed body files (part of the
    fits' key as written) stay as given, and so does everything else of the job."""
    from m3t.fitting.cluster import for_workers

    job = fit_job(tmp_path, "synthetic", tmp_path)
    relative = dataclasses.replace(job, run=dataclasses.replace(job.run, cache_dir=".cache/fit"),
                                   source=dataclasses.replace(job.source, root="data/corpus"),
                                   body=dataclasses.replace(job.body, cache_dir=".cache/anny"))
    monkeypatch.chdir(tmp_path)
    moved = for_workers(relative)
    assert moved.run.cache_dir == str(tmp_path / ".cache" / "fit")
    assert moved.source.root == str(tmp_path / "data" / "corpus")
    assert moved.body.cache_dir == str(tmp_path / ".cache" / "anny")
    assert moved.body.smplx_path == relative.body.smplx_path == "models/smplx/SMPLX_NEUTRAL.npz"
    assert moved.source.options == relative.source.options and moved.run.workers == relative.run.workers
    assert (moved.corpus, moved.shards_dir, moved.fitting, moved.tracker) == (
        relative.corpus, relative.shards_dir, relative.fitting, relative.tracker)
    assert for_workers(moved) == moved  # absolute paths stay
    packaged = for_workers(dataclasses.replace(relative, source=dataclasses.replace(relative.source, root="")))
    assert packaged.source.root == ""


class SchedulerClient:
    """What :class:`m3t.fitting.cluster.DaskExecutor` asks of a ``distributed.Client``: its scheduler's address
    and ``identity`` (asked through ``sync``), an executor, ``status`` and ``close``; every call recorded."""

    def __init__(self, identity=None, fail: Exception | None = None, status: str = "running"):
        self.status, self.identity, self.fail = status, identity or {}, fail
        self.calls: list = []
        self.submitted: list = []
        self.scheduler = type("Scheduler", (), {"address": "tcp://10.0.0.2:8786", "identity": object()})()
        client = self

        class Tasks:
            def submit(self, fn, *args, key=None, **kwargs):
                client.submitted.append((fn, args, key, kwargs))
                return "future"

            def shutdown(self, wait=True):
                client.calls.append(("executor.shutdown", wait))

        self.tasks = Tasks()

    def get_executor(self):
        return self.tasks

    def sync(self, fn, **kwargs):
        self.calls.append(("sync", fn, kwargs))
        if self.fail is not None:
            raise self.fail
        return self.identity

    def close(self, timeout=None):
        self.calls.append(("close", timeout))
        self.status = "closed"


def test_a_dask_executor_keeps_one_task_per_worker_thread_in_flight():
    from m3t.fitting.cluster import CONNECT_SECONDS, DaskExecutor

    client = SchedulerClient({"total_threads": 3, "workers": {}})
    executor = DaskExecutor(client)
    assert executor.address == "tcp://10.0.0.2:8786" and executor.capacity() == 3
    # the scheduler's summary without per-worker details, asked with a timeout
    assert client.calls == [("sync", client.scheduler.identity, {"n_workers": 0, "callback_timeout": CONNECT_SECONDS})]
    executor.check()
    assert len(client.calls) == 2 and client.calls[1] == client.calls[0]
    for identity in ({"total_threads": 0}, {}):  # no worker yet: one task waits for one to join
        assert DaskExecutor(SchedulerClient(identity)).capacity() == 1


@pytest.mark.parametrize("client, why", [
    (SchedulerClient(status="closed"), "the client's connection is closed"),
    (SchedulerClient(fail=OSError("Timed out trying to connect")),
     "it did not answer within 30 s: OSError: Timed out trying to connect"),
])
def test_a_lost_scheduler_stops_the_run_naming_its_address(client, why):
    from m3t.fitting.cluster import DaskExecutor, SchedulerLost

    executor = DaskExecutor(client)
    for ask in (executor.check, executor.capacity):
        with pytest.raises(SchedulerLost) as info:
            ask()
        assert str(info.value) == (f"lost the Dask scheduler at tcp://10.0.0.2:8786 ({why}); finished clips are "
                                   "cached, rerun to resume")


def test_a_dask_task_carries_the_workers_job_and_a_key_of_its_own(tmp_path, monkeypatch):
    from m3t.fitting.cluster import DaskExecutor, on_worker
    from m3t.fitting.corpus import fit_batch

    job = fit_job(tmp_path, "synthetic", tmp_path)
    job = dataclasses.replace(job, run=dataclasses.replace(job.run, cache_dir="cache"))
    monkeypatch.chdir(tmp_path)
    client = SchedulerClient()
    executor = DaskExecutor(client)
    assert executor.submit(fit_batch, job, ["clip"], extra=1) == "future"
    executor.submit(fit_batch, job, ["clip"])
    (fn, args, key, kwargs), again = client.submitted
    assert fn is on_worker and args[0] is fit_batch and args[2] == ["clip"] and kwargs == {"extra": 1}
    assert args[1].run.cache_dir == str(tmp_path / "cache")  # the job as the workers must see it
    assert key.startswith("fit-clips-") and again[2].startswith("fit-clips-") and key != again[2]


def test_a_dask_executor_closes_its_client_and_only_the_cluster_it_started():
    from m3t.fitting.cluster import CONNECT_SECONDS, DaskExecutor

    client, cluster = SchedulerClient(), FakeCluster()
    DaskExecutor(client, cluster).shutdown()
    assert client.calls == [("executor.shutdown", True), ("close", CONNECT_SECONDS)] and cluster.closed
    for kwargs in ({"cancel_futures": True}, {"wait": False}):  # a stopped run waits for nothing
        client = SchedulerClient()
        DaskExecutor(client).shutdown(**kwargs)
        assert client.calls == [("close", CONNECT_SECONDS)]
    lost = SchedulerClient(status="closed")
    DaskExecutor(lost).shutdown()
    assert lost.calls == [("close", CONNECT_SECONDS)]

    class Failing(SchedulerClient):
        def close(self, timeout=None):
            raise OSError("connection reset")

    cluster = FakeCluster()
    with pytest.raises(OSError, match="connection reset"):
        DaskExecutor(Failing(), cluster).shutdown()
    assert cluster.closed  # the local cluster is closed whatever the client did


def test_only_a_dead_dask_worker_quarantines_a_batch():
    from types import SimpleNamespace

    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    from m3t.fitting.cluster import worker_died

    assert worker_died(KilledWorker("fit-clips-1", SimpleNamespace(address="tcp://10.0.0.7:4000"), 3))
    assert worker_died(CommClosedError("in <TCP (closed)>: Stream is closed"))
    assert not worker_died(ValueError("a bad clip")) and not worker_died(MemoryError())


def test_a_process_pools_failures_are_never_taken_for_dead_dask_workers(monkeypatch):
    """Only Dask raises a dead worker's errors: without Dask imported, nothing is one, and Dask stays unimported."""
    import sys

    from m3t.fitting.cluster import worker_died

    monkeypatch.delitem(sys.modules, "distributed", raising=False)
    assert not worker_died(MemoryError()) and not worker_died(OSError("Broken pipe"))
    assert "distributed" not in sys.modules


# ------------------------------------------------------------------------------------------ keys and paths
def test_a_jobs_key_follows_its_content_not_the_order_options_were_written_in(tmp_path):
    from m3t.fitting.corpus import worker_context

    def job(options):
        return fit_job(tmp_path, "posefile", tmp_path, options)

    a, b = job({"index": "index.csv", "language": "ase"}), job({"language": "ase", "index": "index.csv"})
    assert a == b and a.key() == b.key() and len(a.key()) == 16
    assert job({"index": "other.csv", "language": "ase"}).key() != a.key()
    assert dataclasses.replace(a, shards_dir="elsewhere").key() != a.key()
    assert worker_context(a) is worker_context(b)  # one context (one body model) per process and job
    assert worker_context(job({"index": "other.csv"})) is not worker_context(a)


def test_the_listings_refused_rows_become_quarantine_records():
    from m3t.corpora.base import Listing, Quarantined
    from m3t.fitting.corpus import listing_outcomes

    listing = Listing((), (Quarantined("index.csv", 7, "c7", "no split: 'val' is not train, dev or test; fix row 7"),
                           Quarantined("annotations/train.corpus.csv", 3, None, "3 '|'-separated columns, expected 7")))
    first, second = listing_outcomes(listing)
    assert first == ClipOutcome("c7", "", "quarantined", reason="no split: 'val' is not train, dev or test; fix row 7",
                                file="index.csv", row=7, group="listing: no split", from_listing=True)
    assert (second.clip_id, second.split, second.status, second.file, second.row) == (
        "", "", "quarantined", "annotations/train.corpus.csv", 3)
    assert second.group == "listing: 3 '|'-separated columns, expected 7" and second.from_listing
    assert second.part is None and second.frames == 0 and second.metrics == {}
    long = listing_outcomes(Listing((), (Quarantined("f", None, "x", "a" * 80 + ": detail"),)))[0]
    assert long.group == "listing: " + "a" * 60 and long.row is None


def test_a_clips_part_file_lies_in_the_parts_folder_of_the_cache(tmp_path):
    from m3t.fitting.corpus import part_path

    ctx = FitContext(fit_job(tmp_path, "synthetic", tmp_path))
    clip = Clip("session/c1", "synthetic", "train", "ASL-SYN", "s0", "", "", "motion/c1.npz", 25.0)
    assert part_path(clip, "0123abcd", ctx) == tmp_path / "cache" / "parts" / "session_c1-0123abcd.parquet"


def test_a_part_comes_from_the_cache_only_with_its_record_and_its_digest(tmp_path):
    """A part file is reused when its init record exists and its bytes match the SHA-256 written beside it; a
    missing record or a flipped byte redoes it, and a part cached before digests existed is trusted once it
    reads back (and then gets its digest)."""
    import hashlib

    root = cfx.build_slt_import(tmp_path / "slt").root
    ctx = slt_ctx(tmp_path, root)
    clip = clips_of(ctx)["train__clip0"]
    first = process_clip(clip, ctx)
    part = Path(first.part)
    record, digest = part.with_suffix(".init.json"), part.with_suffix(".sha256")
    assert first.status == "fitted" and json.loads(record.read_text()) == first.init
    assert part.parent == tmp_path / "cache" / "parts"
    assert digest.read_text() == hashlib.sha256(part.read_bytes()).hexdigest()
    record.unlink()
    redone = process_clip(clip, ctx)
    assert (redone.status, redone.part, redone.init) == ("fitted", first.part, first.init) and record.exists()
    assert process_clip(clip, ctx).status == "cached"
    data = bytearray(part.read_bytes())
    data[len(data) // 2] ^= 0xFF
    part.write_bytes(bytes(data))
    assert process_clip(clip, ctx).status == "fitted"
    assert digest.read_text() == hashlib.sha256(part.read_bytes()).hexdigest()
    digest.unlink()
    cached = process_clip(clip, ctx)
    assert (cached.status, cached.part, cached.frames) == ("cached", first.part, first.frames) and digest.exists()
    digest.unlink()
    part.write_bytes(b"not a parquet file")
    assert process_clip(clip, ctx).status == "fitted"  # unreadable and no digest: redone


def test_an_import_refused_at_its_id_is_quarantined_with_every_field(tmp_path):
    root = cfx.build_slt_import(tmp_path / "slt").root
    ctx = slt_ctx(tmp_path, root)
    clip = dataclasses.replace(clips_of(ctx)["train__clip1"], id="../clip1", split="dev")
    outcome = process_clip(clip, ctx)
    assert (outcome.clip_id, outcome.split, outcome.status, outcome.part, outcome.group, outcome.file, outcome.row) == (
        "../clip1", "dev", "quarantined", None, "unsafe clip id", clip.media, None)
    assert outcome.reason == ("ClipRefused: clip id '../clip1' is empty, '.' or '..', or holds a path separator; it "
                              f"would name a file outside the cache: rename the clip in {clip.media}")
    assert 0 < outcome.seconds < 60 and not outcome.from_listing
    assert not (tmp_path / "cache" / "parts").exists()  # nothing written for it


@pytest.mark.parametrize("clip_id", ["", ".", "..", "a/b", "a\\b", "a\0b"])
def test_an_import_refuses_a_clip_id_that_would_name_a_file_outside_the_cache(clip_id):
    from m3t.fitting.imports import check_importable
    from m3t.trackers.dispatch import ClipRefused

    clip, settings = import_kw()
    clip = dataclasses.replace(clip, id=clip_id)
    with pytest.raises(ClipRefused) as info:
        check_importable(clip, "keypoints", settings)
    assert info.value.group == "unsafe clip id"
    assert str(info.value).startswith(f"clip id {clip_id!r} is empty, '.' or '..', or holds a path separator; ")
    assert str(info.value).endswith("rename the clip in M003/front/c7.hdf5")


def test_smplx_and_flame_imports_need_smplfx_and_slt_arrays_any_body_model():
    from m3t.fitting.imports import ImportSettings, check_importable
    from m3t.trackers.dispatch import ClipRefused

    clip, smplfx = import_kw()
    anny = ImportSettings("anny", 100)
    for kind, what in (("smplx_params", "SOKE SMPL-X parameters"), ("flame_params", "MEAD FLAME parameters")):
        check_importable(clip, kind, smplfx)
        with pytest.raises(ClipRefused) as info:
            check_importable(clip, kind, anny)
        assert info.value.group == "needs body.model: smplfx"
        assert str(info.value) == (f"clip c7: {what} are imported into SMPL-FX streams, which needs body.model: "
                                   "smplfx (it is 'anny')")
    check_importable(clip, "keypoints", anny)


def test_a_video_clips_track_follows_its_bytes_its_frame_rate_and_the_mediapipe_settings(pose_root, tmp_path,
                                                                                          monkeypatch):
    """MediaPipe is replaced by a recorder returning a real track: the cache key is what is tested."""
    import m3t.fitting.corpus as engine

    pose = pose_ctx(tmp_path, pose_root, None)
    track = load_track(track_clip(clips_of(pose)["plain-a"], pose))
    tracked = []
    monkeypatch.setattr(engine, "track_real_clip",
                        lambda clip, root, cfg: tracked.append((clip.id, root, cfg)) or track)
    videos = tmp_path / "videos"
    videos.mkdir()
    (videos / "v1.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42 first")
    (videos / "index.csv").write_text("id,path,split,text,language,signer\n")

    def ctx(**sections):
        return FitContext(fit_job(tmp_path, "posefile", videos, {"index": "index.csv"}, **sections))

    clip = Clip("v1", "posefile", "train", "ase", "s0", "", "", "v1.mp4", 25.0, extra=(("media_kind", "video"),))
    first = track_clip(clip, ctx())
    assert first.parent == tmp_path / "cache" / "tracks" and first.name.startswith("v1-")
    assert tracked == [("v1", videos, ctx().job.mediapipe)]
    assert track_clip(clip, ctx()) == first and len(tracked) == 1  # the same settings: the cached track
    strict = ctx(mediapipe={"min_detection_confidence": 0.8})
    assert track_clip(clip, strict) not in (first,) and tracked[-1][2].min_detection_confidence == 0.8
    assert track_clip(dataclasses.replace(clip, fps=30.0), ctx()) not in (first,)
    (videos / "v1.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42 second")
    assert track_clip(clip, ctx()) not in (first,) and len(tracked) == 4


def test_a_failed_batch_fit_fits_the_clips_it_had_not_finished_one_by_one(body, synthetic_root, tmp_path, monkeypatch):
    import m3t.fitting.corpus as engine

    ctx = synthetic_ctx(tmp_path, synthetic_root, body, fit_corpus={"batch_clips": 2})
    clips = clips_of(ctx)
    pair = [clips["s0-b"], clips["s0-c"]]
    batch = process_batch(pair, ctx)
    Path(batch[1].part).unlink()  # the second clip's part is lost; the first stays cached

    def diverges(tracks, ctx):
        raise FloatingPointError("the batch fit diverged")

    monkeypatch.setattr(engine, "fit_signer_batch", diverges)
    outcomes = process_batch(pair, ctx)
    assert [(o.clip_id, o.status) for o in outcomes] == [("s0-b", "cached"), ("s0-c", "fitted")]
    assert outcomes[0].part == batch[0].part and outcomes[1].part != batch[1].part
    assert outcomes[1].init == {"init_source": "simulated tracker initialisation"}  # its own fit, its own identity
    alone = process_batch(pair, synthetic_ctx(tmp_path, synthetic_root, body,
                                              fit_corpus={"batch_clips": 2, "batch_frames": 9}))
    assert [(o.clip_id, o.status) for o in alone] == [("s0-b", "fitted"), ("s0-c", "cached")]
    assert alone[0].init == {"init_source": "simulated tracker initialisation"}


# ------------------------------------------------------------------------------------------ the run's scheduler
class BareExecutor:
    """An in-process stand-in for a process pool: ``submit`` records what it is sent and returns a future that
    ``plan(batch)`` settles at once (a list of outcomes, or an exception) or leaves pending (None) for the test
    to settle (:meth:`settle`); no process, no cluster."""

    def __init__(self, plan):
        self.plan, self.sent, self.futures = plan, [], {}

    def submit(self, fn, *args):
        from concurrent.futures import Future

        future = Future()
        self.sent.append((fn, args))
        self.futures[tuple(c.id for c in args[1])] = future
        result = self.plan(args[1])
        if isinstance(result, BaseException):
            future.set_exception(result)
        elif result is not None:
            future.set_result(result)
        return future

    def settle(self, *clip_ids: str) -> None:
        future = self.futures[clip_ids]
        if not future.done():
            future.set_result([ClipOutcome(i, "train", "fitted", frames=3, seconds=0.5) for i in clip_ids])


class ClusterExecutor(BareExecutor):
    """A stand-in for :class:`m3t.fitting.cluster.DaskExecutor`: ``capacity()`` worker threads and ``check()``,
    which counts the questions and raises ``lost`` when it is set."""

    def __init__(self, plan, slots: int, lost: Exception | None = None):
        super().__init__(plan)
        self.slots, self.lost, self.checks = slots, lost, 0

    def capacity(self) -> int:
        return self.slots

    def check(self) -> None:
        self.checks += 1
        if self.lost is not None:
            raise self.lost


def fitted(batch) -> list[ClipOutcome]:
    return [ClipOutcome(c.id, c.split, "fitted", frames=3, seconds=0.5) for c in batch]


def signer_clips(*signers: str) -> list[Clip]:
    """Clips ``<signer><n>`` of the given signers (one letter each), listed in that order; never opened."""
    seen: dict[str, int] = {}
    out = []
    for s in signers:
        seen[s] = seen.get(s, 0) + 1
        clip_id = f"{s}{seen[s]}"
        out.append(Clip(clip_id, "synthetic", "dev", "ASL-SYN", s, "", "", f"motion/{clip_id}.npz", 25.0))
    return out


def test_a_cluster_gets_at_most_its_capacity_and_each_batch_counts_when_it_ends(body, tmp_path, capsys):
    """Two worker threads: two batches in flight; a slow batch does not hold back the report of those sent after
    it, and the progress bar counts every clip."""
    import threading

    from m3t.fitting.corpus import fit_batch, run_fit_corpus

    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus")
    clips = signer_clips("a", "b", "c", "d")
    executor = ClusterExecutor(lambda batch: None if batch[0].id == "b1" else fitted(batch), slots=2)
    seen = []

    def on_outcome(outcome: ClipOutcome) -> None:
        seen.append((outcome.clip_id, executor.futures[("b1",)].done(), len(executor.sent)))
        if outcome.clip_id == "d1":
            executor.settle("b1")

    late = threading.Timer(3.0, executor.settle, ("b1",))  # never needed unless the run waits for every batch
    late.start()
    try:
        report = run_fit_corpus(job, executor, clips=clips, progress=True, on_outcome=on_outcome,
                                ctx=FitContext(job, body))
    finally:
        late.cancel()
    # b1 holds one of the two slots throughout: the others go one at a time
    assert seen == [("a1", False, 2), ("c1", False, 3), ("d1", False, 4), ("b1", True, 4)]
    assert [args for _, args in executor.sent] == [(job, [c]) for c in (clips[0], clips[1], clips[2], clips[3])]
    assert all(fn is fit_batch for fn, _ in executor.sent)
    assert [o.clip_id for o in report.outcomes] == ["a1", "b1", "c1", "d1"] and report.summary["clips_fitted"] == 4
    bar = capsys.readouterr().err
    assert "fit-corpus synthetic" in bar and "4/4" in bar


def test_a_run_shows_its_progress_bar_only_when_asked(body, tmp_path, capsys):
    from m3t.fitting.corpus import run_fit_corpus

    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus")
    run_fit_corpus(job, ClusterExecutor(fitted, slots=1), clips=signer_clips("a", "a"), progress=False,
                   ctx=FitContext(job, body))
    assert "fit-corpus" not in capsys.readouterr().err


def test_while_no_batch_ends_the_run_asks_whether_the_cluster_is_still_there(tmp_path, monkeypatch):
    import threading

    import m3t.fitting.corpus as engine
    from m3t.fitting.cluster import SchedulerLost

    monkeypatch.setattr(engine, "POLL_SECONDS", 0.02)
    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus")
    clips = signer_clips("a", "b")
    cluster = ClusterExecutor(lambda batch: None, slots=4)
    threading.Timer(0.3, lambda: [cluster.settle(i) for i in ("a1", "b1")]).start()
    assert sorted(o.clip_id for o in engine._outcomes(job, clips, cluster, None)) == ["a1", "b1"]
    assert cluster.checks >= 2

    pool = BareExecutor(lambda batch: None)  # no capacity: every batch at once; no check: only waiting
    sent = []
    threading.Timer(0.3, lambda: [sent.append(len(pool.sent)), *[pool.settle(i) for i in ("a1", "b1")]]).start()
    assert sorted(o.clip_id for o in engine._outcomes(job, clips, pool, None)) == ["a1", "b1"] and sent == [2]

    gone = ClusterExecutor(lambda batch: None, slots=4, lost=SchedulerLost("lost the Dask scheduler at tcp://s:8786"))
    with pytest.raises(SchedulerLost, match="tcp://s:8786"):
        list(engine._outcomes(job, clips, gone, None))
    assert all(f.cancelled() for f in gone.futures.values())  # nothing left running for nobody


def test_a_batch_whose_worker_died_is_quarantined_and_the_run_goes_on(tmp_path):
    from types import SimpleNamespace

    from distributed.scheduler import KilledWorker

    from m3t.fitting.corpus import _outcomes

    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus", fit_corpus={"batch_clips": 2})
    clips = signer_clips("a", "b", "a")
    killed = KilledWorker("fit-clips-7", SimpleNamespace(address="tcp://10.0.0.7:4000"), 3)
    executor = ClusterExecutor(lambda batch: killed if batch[0].signer == "a" else fitted(batch), slots=1)
    outcomes = {o.clip_id: o for o in _outcomes(job, clips, executor, None)}
    assert [args[1] for _, args in executor.sent] == [[clips[0], clips[2]], [clips[1]]]  # one batch per signer
    assert outcomes["b1"].status == "fitted"
    for clip in (clips[0], clips[2]):
        assert outcomes[clip.id] == ClipOutcome(
            clip.id, "dev", "quarantined", group="worker died", file=clip.media,
            reason=f"worker died while fitting this clip: KilledWorker: {killed} (the next run retries it)")


def test_a_failing_task_stops_the_run_and_cancels_the_others(tmp_path):
    from concurrent.futures.process import BrokenProcessPool

    from m3t.fitting.cluster import SchedulerLost
    from m3t.fitting.corpus import _outcomes

    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus")
    clips = signer_clips("a", "b")

    def failing(error):
        return ClusterExecutor(lambda batch: error if batch[0].id == "a1" else None, slots=2)

    bug = failing(ValueError("an engine bug"))
    with pytest.raises(ValueError, match="^an engine bug$"):
        list(_outcomes(job, clips, bug, None))
    assert bug.futures[("b1",)].cancelled()

    pool = failing(BrokenProcessPool("A child process terminated abruptly"))
    with pytest.raises(RuntimeError) as info:
        list(_outcomes(job, clips, pool, None))
    assert str(info.value) == ("a fit-corpus worker process died (out of memory or killed); finished clips are "
                               "cached, rerun to resume")
    assert isinstance(info.value.__cause__, BrokenProcessPool) and pool.futures[("b1",)].cancelled()

    class Cancelling(ClusterExecutor):
        def submit(self, fn, *args):
            future = super().submit(fn, *args)
            if args[1][0].id == "a1":
                future.cancel()  # what Dask does to every task when the scheduler connection drops
                future.set_running_or_notify_cancel()  # as an executor does: waiters see it end
            return future

    cancelled = Cancelling(lambda batch: None, slots=2)
    with pytest.raises(RuntimeError) as info:
        list(_outcomes(job, clips, cancelled, None))
    assert str(info.value) == "clip a1: the executor cancelled its task; finished clips are cached, rerun to resume"
    assert cancelled.checks == 1 and cancelled.futures[("b1",)].cancelled()
    lost = Cancelling(lambda batch: None, slots=2, lost=SchedulerLost("lost the Dask scheduler at tcp://s:8786"))
    with pytest.raises(SchedulerLost):  # the scheduler's loss is the reason given, when that is what happened
        list(_outcomes(job, clips, lost, None))


def test_fit_and_log_hands_the_mlflow_run_the_ground_truth_of_synthetic_clips(body, synthetic_root, tmp_path,
                                                                              monkeypatch, capsys):
    """What :func:`m3t.fitting.corpus.fit_and_log` gives the MLflow logger (replaced by a recorder): the corpus'
    sections, the report, the body model to picture with and, for synthetic clips, their ground truth."""
    import m3t.fitting.corpus as engine
    import m3t.fitting.report as reporting
    from m3t.corpora.synthetic import SyntheticCorpus

    monkeypatch.setattr(engine, "load_body_model", lambda cfg: body)
    logged = []
    monkeypatch.setattr(reporting, "log_fit_corpus", lambda *args: logged.append(args) or "run-id")
    job = fit_job(tmp_path, "synthetic", synthetic_root, fit_corpus={"max_clips": 1, "render_clips": 1})
    experiment = object()
    seen = []
    report = engine.fit_and_log(job, experiment, progress=False, on_outcome=seen.append)
    assert "fit-corpus" not in capsys.readouterr().err  # no progress bar asked for
    assert [o.clip_id for o in seen] == ["s0-a"] and report.outcomes == seen
    ((to, params, got, model, corpus, shards_dir, cache_dir, render, truth),) = logged
    assert (to, got, model, corpus, shards_dir, cache_dir, render) == (
        experiment, report, body, "synthetic", job.shards_dir, job.run.cache_dir, 1)
    assert params["corpus"] == "synthetic" and params["shards_dir"] == job.shards_dir
    assert params["corpora.synthetic"] == {"root": str(synthetic_root), "options": {}}
    assert params["tracker.seed"] == job.tracker.seed and params["fitting.iterations"] == 4
    assert not [k for k in params if k.startswith("fusion.")]
    clip = report.outcomes[0]
    want = SyntheticCorpus(str(synthetic_root)).ground_truth(clips_of(FitContext(job))[clip.clip_id])
    got_params, got_identity, got_camera = truth(clips_of(FitContext(job))[clip.clip_id])
    assert all(np.array_equal(got_params[k], want[0][k]) for k in want[0])
    assert np.array_equal(got_identity, want[1]) and got_camera == want[2]

    logged.clear()
    engine.fit_and_log(job, experiment, log=False, progress=True)
    assert logged == [] and "fit-corpus synthetic" in capsys.readouterr().err


def test_fit_and_log_pictures_nothing_for_feature_shards(tmp_path, monkeypatch):
    import m3t.fitting.corpus as engine
    import m3t.fitting.report as reporting

    logged = []
    monkeypatch.setattr(reporting, "log_fit_corpus", lambda *args: logged.append(args))
    job = fit_job(tmp_path, "slt_pickle", cfx.build_slt_import(tmp_path / "slt").root,
                  body={"flame_path": str(tmp_path / "absent.pkl")}, fit_corpus={"render_clips": 2})
    engine.fit_and_log(job, "experiment", progress=False)
    ((_, params, _, model, corpus, _, _, render, truth),) = logged
    assert (model, corpus, render, truth) == (None, "slt_pickle", 0, None)
    assert params["fusion.use_external"] is True and not [k for k in params if k.startswith("tracker.")]


# ------------------------------------------------------------------------------------------ the solver (more)
def test_lbfgs_line_search_reaches_the_minimum_of_a_robust_loss():
    """A pseudo-Huber loss (curvature vanishing far from its minimum): full quasi-Newton steps overshoot and run
    away; the strong-Wolfe line search keeps every step a descent and reaches the minimum within the budget."""
    from m3t.fitting.fit import FittingConfig, _minimise

    x = torch.tensor([0.0, 10.0, -5.0], dtype=torch.float64, requires_grad=True)
    curve: list[float] = []
    _minimise(lambda: torch.sqrt(1 + (x - 3.0) ** 2).sum(), [x], FittingConfig(solver="lbfgs", iterations=30), "full",
              0.0, curve)
    assert len(curve) <= 30 and curve[-1] == pytest.approx(3.0, abs=1e-9)
    np.testing.assert_allclose(x.detach().numpy(), 3.0, atol=1e-4)


def test_a_fit_uses_the_landmark_correspondence_it_is_given(body, short_track):
    from m3t.fitting.fit import FittingConfig, fit_track, fit_tracks
    from m3t.trackers.track import landmark_slices

    cfg = FittingConfig(iterations=2, camera_iterations=2)
    default = body.correspondence(short_track.landmark_set)
    nowhere = dataclasses.replace(default, kind=np.full_like(default.kind, -1))
    with pytest.raises(ValueError, match=r"^the track has no visible landmark with a body-model correspondence"):
        fit_track(short_track, body, cfg, nowhere)
    pose = landmark_slices(short_track.landmark_set)["pose"]
    pose_only = dataclasses.replace(default, kind=np.where(np.arange(len(default.kind)) < pose.stop, default.kind, -1))
    result = fit_track(short_track, body, cfg, pose_only)
    assert np.array_equal(result.params["body"], fit_tracks([short_track], body, cfg, pose_only)[0].params["body"])
    assert not np.array_equal(result.params["body"], fit_track(short_track, body, cfg).params["body"])


def test_the_camera_is_placed_from_the_torso_and_head_points_alone(body, short_track):
    """The camera-only stage ignores the arms (pose points 13-22: elbows, wrists, hand points), the hands and the
    face mesh, which start far from the rest pose; the shoulders, the hips and the head's pose points place it."""
    from m3t.fitting.fit import FittingConfig, fit_track
    from m3t.trackers.track import landmark_slices

    cfg = FittingConfig(iterations=0, camera_iterations=3)
    parts = landmark_slices(short_track.landmark_set)

    def camera(*shift: tuple[slice, float]) -> dict:
        keypoints = short_track.keypoints.copy()
        for where, by in shift:
            keypoints[:, where] += by
        return fit_track(dataclasses.replace(short_track, keypoints=keypoints), body, cfg).camera

    placed = camera()
    pose = parts["pose"].start
    moved = camera((slice(pose + 13, pose + 23), 60.0), (parts["left_hand"], -50.0), (parts["right_hand"], 50.0),
                   (parts["face"], 30.0))
    assert moved["translation"] == placed["translation"] and moved["rotation"] == placed["rotation"]
    # shoulders, hip, nose
    for kept in (slice(pose + 11, pose + 13), slice(pose + 23, pose + 24), slice(pose, pose + 1)):
        assert camera((kept, 60.0))["translation"] != placed["translation"], kept


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
    """Pixel3DMM's per-frame estimates as :func:`m3t.trackers.external.read_pixel3dmm` returns them."""
    from m3t.trackers.external import FaceEstimates

    n = len(frames)
    rng = np.random.default_rng(4)
    eye = np.tile(np.eye(3), (n, 1, 1))
    return FaceEstimates(np.array(frames), rng.normal(size=(n, expression_dims)), rng.uniform(size=(n, 2)), eye, eye,
                         eye, np.zeros((n, 3)), np.zeros(300))


def test_pixel3dmm_face_values_land_on_their_frames_of_a_flame_face_layout():
    from m3t.body.protocol import Modality, ModalityLayout
    from m3t.body.smplfx import smplfx_layout
    from m3t.fitting.fusion import pixel3dmm_stream

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
    from m3t.fitting.fusion import INTERPOLATED, REST, FusionConfig, TrackerStream, fuse, rot_to_flat6d

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
    from m3t.fitting.fusion import HELD, INTERPOLATED, REST, FusedInit, describe

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


def test_refinement_starts_from_the_fused_initialisation_and_identity(body, short_track):
    from m3t.fitting.fit import FittingConfig
    from m3t.fitting.fusion import FusedInit, refine

    cfg = FittingConfig(iterations=0, camera_iterations=1)  # no joint stage: the result is where it started
    init = {k: v[::-1].copy() for k, v in short_track.init.items()}  # another valid motion than the track's own
    identity = np.array([0.3, 0.6, 0.4, 0.5, 0.5, 0.7], np.float32)
    result = refine(short_track, FusedInit(init, {}, {}, identity), body, cfg)
    for k, v in init.items():
        np.testing.assert_allclose(result.params[k], v, atol=1e-5, err_msg=k)
    np.testing.assert_array_equal(result.identity, identity)
    default = refine(short_track, FusedInit(init, {}, {}, None), body, cfg)
    np.testing.assert_array_equal(default.identity, body.default_identity().numpy())
    with pytest.raises(ValueError, match=r"disagree on the number of frames \(3\)"):
        refine(short_track, FusedInit({k: v[:2] for k, v in init.items()}, {}, {}, None), body, cfg)


# ------------------------------------------------------------------------------------------ imports and reports
def test_a_flame_source_with_more_expressions_than_flame_2020_is_refused_naming_the_clip():
    from m3t.fitting.imports import import_clip
    from m3t.trackers.dispatch import ClipRefused

    clip, settings = import_kw()
    with pytest.raises(ClipRefused) as info:
        import_clip(clip, "flame_params", cfx.flame_arrays(frames=3, exp=101), "k", settings)
    assert info.value.group == "too many expression dims"
    assert str(info.value) == "clip c7: 'exp' has 101 columns; FLAME 2020 has 100 expression coefficients"


def test_an_imported_face_row_is_float32_and_reports_the_identitys_drift_over_frames():
    from m3t.fitting.imports import import_clip

    clip, settings = import_kw()
    src = cfx.flame_arrays(frames=4)
    src["shape"] = np.tile(np.linspace(-1, 1, 100, dtype=np.float32), (4, 1))  # one signer: the same every frame
    src["eyelids"] = np.full((4, 2), 0.25, np.float32)
    fitted, _ = import_clip(clip, "flame_params", src, "k", settings)
    assert fitted.metrics["src_shape_frame_std"] == 0.0
    assert fitted.params["face"].dtype == np.float32 and fitted.identity.dtype == np.float32
    np.testing.assert_array_equal(fitted.params["face"][:, 100:102], 0.25)
    np.testing.assert_allclose(fitted.identity[10:], src["shape"][0], atol=1e-7)
    assert not fitted.identity[:10].any()  # no SMPL-X betas in a FLAME source
    src["shape"][:, 0] = (0.0, 1.0, 0.0, 1.0)  # one coefficient drifts: std 0.5 over frames, mean over 100 dims
    drifting, _ = import_clip(clip, "flame_params", src, "k", settings)
    assert drifting.metrics["src_shape_frame_std"] == pytest.approx(0.005)


def test_run_statistics_count_this_runs_work_and_its_throughput():
    from m3t.fitting.report import run_stats

    outcomes = [ClipOutcome("a", "train", "fitted", frames=30, seconds=2.0),
                ClipOutcome("b", "dev", "fitted", frames=10, seconds=2.0),
                ClipOutcome("c", "train", "cached", frames=50),
                ClipOutcome("d", "test", "quarantined", seconds=1.0)]
    assert run_stats(outcomes, 8.0) == {"clips_fitted_now": 2, "clips_cached": 1, "wall_seconds": 8.0,
                                        "fit_frames_per_s_per_worker": 10.0, "fit_frames_per_s_wall": 5.0}
    resumed = run_stats(outcomes[2:], 3.0)  # nothing fitted now: no throughput to report
    assert (resumed["clips_fitted_now"], resumed["clips_cached"], resumed["wall_seconds"]) == (0, 1, 3.0)
    assert math.isnan(resumed["fit_frames_per_s_per_worker"]) and math.isnan(resumed["fit_frames_per_s_wall"])
    unclocked = run_stats(outcomes, 0.0)
    assert math.isnan(unclocked["fit_frames_per_s_wall"]) and unclocked["fit_frames_per_s_per_worker"] == 10.0


def test_an_imported_clip_without_a_non_finite_count_counts_as_all_finite():
    from m3t.fitting.report import import_summary

    imported = {"init_source": "imported: MEAD FLAME parameters, no tracking or fitting"}
    summary = import_summary([ClipOutcome("i1", "train", "fitted", frames=10, init=imported,
                                          metrics={"src_nonfinite_frame_frac": 0.1}),
                              ClipOutcome("i2", "train", "cached", frames=30, init=imported, metrics={})])
    assert summary == {"imported_clips": 2, "imported_nonfinite_frame_frac": pytest.approx(0.025)}


def test_the_quality_picture_is_a_small_png_written_where_asked(tmp_path):
    from m3t.fitting.quality import plot_quality, quality_report

    report = quality_report([ClipOutcome("a", "train", "fitted", frames=3, metrics={"reproj_px_parts": 2.5},
                                         coverage={"missing_left_hand": 0.5, "missing_right_hand": 0.0,
                                                   "missing_face": 0.0}, track_frames=3)], "synthetic")
    path = plot_quality(report, tmp_path / "render" / "quality-synthetic.png")
    assert path == tmp_path / "render" / "quality-synthetic.png"
    header = path.read_bytes()[:24]
    assert header[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(header[16:20], "big"), int.from_bytes(header[20:24], "big")
    assert (width, height) == (800, 320)  # 10 x 4 inches at 80 dpi: light enough for every run's artifacts


# ------------------------------------------------------------------------------------------ run results
def test_the_run_summary_counts_clips_and_averages_fit_metrics_of_fitted_clips_only():
    from m3t.fitting.report import summarise

    outcomes = [
        ClipOutcome("a", "train", "fitted", frames=10, metrics={"fit_px": 2.0, "reproj_px_parts": 9.0}),
        ClipOutcome("b", "dev", "cached", frames=30, metrics={"fit_px": 4.0, "pa_mm": float("nan")}),
        ClipOutcome("c", "train", "fitted", frames=5, metrics={"fit_px": 9.0, "reproj_shoulder_frac": 0.1}),
        ClipOutcome("q", "train", "quarantined", frames=99, metrics={"fit_px": 1000.0}),
    ]
    assert summarise(outcomes) == {"clips_total": 4, "clips_fitted": 3, "clips_quarantined": 1, "frames": 45,
                                   "fit_px_mean": 5.0, "fit_px_median": 4.0}
    assert summarise([]) == {"clips_total": 0, "clips_fitted": 0, "clips_quarantined": 0, "frames": 0}


def test_consolidate_creates_a_nested_shards_folder_and_writes_every_split(tmp_path):
    from m3t.corpora.base import SPLITS
    from m3t.fitting.report import consolidate
    from m3t.fitting.imports import ImportSettings

    layout = ImportSettings("smplfx", 100).layout("keypoints", 6)
    out = tmp_path / "data" / "shards" / "synthetic"
    outcomes = [ClipOutcome("q", "train", "quarantined", reason="ValueError: bad", group="ValueError",
                            file="motion/q.npz")]
    report = consolidate(outcomes, layout, out, "synthetic", 1.0)
    assert set(report.shards) == set(SPLITS) and all(Path(p).parent == out for p in report.shards.values())
    assert sorted(p.name for p in out.glob("*.parquet")) == sorted(f"{s}.parquet" for s in SPLITS)
    (out / "holdout.parquet").write_bytes((out / "train.parquet").read_bytes())  # a split of an older run
    consolidate(outcomes, layout, out, "synthetic", 1.0)
    assert sorted(p.name for p in out.glob("*.parquet")) == sorted(f"{s}.parquet" for s in SPLITS)
    assert [json.loads(line) for line in (out / "quarantine.jsonl").read_text().splitlines()] == [
        {"clip_id": "q", "split": "train", "file": "motion/q.npz", "row": None, "reason": "ValueError: bad",
         "group": "ValueError"}]
    assert json.loads((out / "summary.json").read_text())["clips_quarantined"] == 1


def test_quality_json_keys_are_sorted_so_identical_results_give_identical_bytes(tmp_path):
    from m3t.atomic import write_text
    from m3t.fitting.quality import QualityReport, write_quality

    _, json_path = write_quality(QualityReport([], {"zeta": 1, "alpha": float("inf"), "mid": "x"}), tmp_path,
                                 write_text)
    assert json_path.read_text() == '{\n  "alpha": null,\n  "mid": "x",\n  "zeta": 1\n}\n'


def test_a_quality_row_without_a_file_or_row_leaves_both_cells_empty():
    from m3t.fitting.quality import quality_report

    report = quality_report([ClipOutcome("q", "train", "quarantined", reason="boom", group="RuntimeError"),
                             ClipOutcome("r", "dev", "quarantined", reason="bad row", file="index.csv", row=0)], "x")
    q, r = report.rows
    assert (q["file"], q["row"], q["reason"], q["group"], q["split"]) == ("", "", "boom", "RuntimeError", "train")
    assert (r["file"], r["row"], r["group"]) == ("index.csv", 0, "")


def test_a_one_frame_fused_initialisation_shares_its_single_frame_fully():
    from m3t.fitting.fusion import HELD, REST, FusedInit, describe

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


def test_an_slt_clip_without_a_recorded_width_is_refused_beside_the_common_width():
    from m3t.fitting.imports import ImportSettings, plan_import

    clips = [Clip(cid, "slt", "train", "de", "s1", "", "", f"train.pkl#{i}", 25.0, extra=extra)
             for i, (cid, extra) in enumerate([("a", (("dims", "6"),)), ("b", (("dims", "6"),)), ("c", ()),
                                              ("d", (("dims", "9"),))])]
    layout, keep, refused = plan_import("keypoints", ImportSettings("smplfx", 100), clips)
    assert [c.id for c in keep] == ["a", "b"] and sum(layout.dims.values()) == 6
    assert [(o.clip_id, o.status, o.group, o.file) for o in refused] == [
        ("c", "quarantined", "other sign width", "train.pkl#2"),
        ("d", "quarantined", "other sign width", "train.pkl#3")]
    assert refused[0].reason == ("sign has None values per frame; 2 of the corpus' clips have 6 and a shard holds "
                                 "one layout")
    assert refused[1].reason.startswith("sign has 9 values per frame; 2 of")


def test_a_modality_without_tracker_streams_has_no_frames():
    from m3t.fitting.config import FusionConfig
    from m3t.fitting.fusion import fuse_modality

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


def test_reprojection_loss_weighs_each_part_by_its_own_confidence_even_when_it_is_small():
    from m3t.fitting.fit import reprojection_loss

    pred = torch.zeros(2, 3, 2)
    target = torch.zeros(2, 3, 2)
    target[:, 0, 0] = 2.0  # part 1: 4 px^2 at every confident point
    target[:, 2, 1] = 3.0  # part 2: 9 px^2
    conf = torch.tensor([[1.0, 1.0, 0.25], [1.0, 0.0, 0.25]])
    parts = [slice(0, 2), slice(2, 3), slice(1, 2)]
    # part 1: (4 + 4) / 3 over its confidence 3; part 2: 9 at total confidence 0.5; part 3: no error
    assert reprojection_loss(pred, target, conf, parts).item() == pytest.approx((8 / 3 + 9 + 0) / 3)
    unseen = conf.clone()
    unseen[:, 2] = 0.0  # a part nobody saw is left out, not counted as zero error
    assert reprojection_loss(pred, target, unseen, parts).item() == pytest.approx((8 / 3 + 0) / 2)


def test_the_run_log_names_the_corpus_variant_and_draws_each_fit_against_its_truth(tmp_path, monkeypatch):
    """``log_fit_corpus`` with the MLflow run, the shard reader and the pictures replaced by recorders."""
    import contextlib
    from types import SimpleNamespace

    import m3t.experiment as experiment
    import m3t.fitting.report as report_module
    import m3t.render.mesh as mesh
    import m3t.render.skeleton as skeleton

    calls: dict[str, list] = {"start": [], "compare": [], "mesh": [], "artifacts": []}

    class FakeRun:
        run_id = "run-1"

        def log_params(self, params): pass

        def log_metrics(self, metrics): pass

        def log_table(self, path, name): pass

        def log_artifact(self, path, folder=None):
            calls["artifacts"].append((Path(path).name, folder))

    @contextlib.contextmanager
    def start_run(exp, stage, tags=None, variant=None):
        calls["start"].append((exp, stage, tags, variant))
        yield FakeRun()

    clip = Clip("s0-a", "synthetic", "train", "ISO-SYN", "s0", "", "", "motion/s0-a.npz", 25.0)
    fitted = SimpleNamespace(clip=clip, camera={"f": 1.0}, params={"body": np.zeros((4, 6))},
                             identity=np.zeros(6), num_frames=4)
    monkeypatch.setattr(experiment, "start_run", start_run)
    monkeypatch.setattr(report_module, "read_shard", lambda part: SimpleNamespace(clips=[fitted]))
    monkeypatch.setattr(report_module, "plot_quality", lambda quality, path: Path(path))
    monkeypatch.setattr(skeleton, "render_fit_comparison",
                        lambda body, fit, truth, image: calls["compare"].append((fit.clip.id, truth)) or image)
    monkeypatch.setattr(mesh, "log_fitted_frame",
                        lambda run, body, params, identity, frame, folder, camera, stem: calls["mesh"].append(
                            (frame, camera, stem)))
    report = report_module.FitCorpusReport(shards={}, outcomes=[ClipOutcome("s0-a", "train", "fitted", "p.parquet")],
                                           summary={}, quality={"clips_listed": 1, "corpus": "synthetic"},
                                           run_stats={})
    truths = {"s0-a": ("truth-params", "truth-identity", "truth-camera")}
    body = SimpleNamespace(name="anny")
    assert report_module.log_fit_corpus("exp", {}, report, body, "synthetic", tmp_path, tmp_path / "cache", 1,
                                        lambda c: truths[c.id]) == "run-1"
    assert calls["start"] == [("exp", "fit-corpus", {"corpus": "synthetic", "body_model": "anny"}, "synthetic")]
    assert calls["compare"] == [("s0-a", truths["s0-a"])] and calls["mesh"] == [(2, {"f": 1.0}, "s0-a")]
    assert ("s0-a.png", "fit_vs_ground_truth") in calls["artifacts"]
    calls["compare"].clear()
    report_module.log_fit_corpus("exp", {}, report, body, "synthetic", tmp_path, tmp_path / "cache", 1)
    assert calls["compare"] == [("s0-a", None)]  # no truth to draw: the fit alone


def test_the_progress_bar_counts_the_quarantined_clips_as_they_come(tmp_path, capsys):
    from m3t.fitting.corpus import run_fit_corpus

    ctx = slt_ctx(tmp_path, cfx.build_slt_import(tmp_path / "slt").root)
    report = run_fit_corpus(ctx.job, progress=True, ctx=ctx)
    quarantined = sum(o.status == "quarantined" for o in report.outcomes)
    assert quarantined > 0
    err = capsys.readouterr().err
    assert "fit-corpus slt_pickle" in err and f"quarantined={quarantined}" in err


def test_fits_cached_under_an_older_key_version_are_redone(body, synthetic_root, tmp_path, monkeypatch):
    """Bumping ``KEY_VERSION`` (fitting code changed) invalidates a signer batch's cached fit: nothing computed
    under the older version is reused."""
    import m3t.fitting.corpus as corpus

    def ctx():
        return synthetic_ctx(tmp_path, synthetic_root, body, fit_corpus={"batch_clips": 2})

    clips = clips_of(ctx())
    pair = [clips["s0-b"], clips["s0-c"]]
    first = process_batch(pair, ctx())
    assert {o.status for o in first} == {"fitted"}
    assert {o.status for o in process_batch(pair, ctx())} == {"cached"}
    monkeypatch.setattr(corpus, "KEY_VERSION", corpus.KEY_VERSION + "-next")
    again = process_batch(pair, ctx())
    assert {o.status for o in again} == {"fitted"}
    assert not {o.part for o in again} & {o.part for o in first}


def test_a_known_identity_is_held_fixed_in_every_clips_fit(body, short_track):
    """``identity`` given (a signer's identity from an earlier chunk): every result carries exactly it, even with
    ``fit_identity`` on; without it the fit starts from the default identity and fits it, or keeps the default
    when ``fit_identity`` is off."""
    from m3t.fitting.fit import FittingConfig, fit_tracks

    cfg = FittingConfig(iterations=3, camera_iterations=1)
    assert cfg.fit_identity
    known = np.array([0.3, 0.6, 0.4, 0.55, 0.45, 0.7])  # float64, as read from a file: results are float32
    for fit_identity in (True, False):
        results = fit_tracks([short_track, short_track], body, dataclasses.replace(cfg, fit_identity=fit_identity),
                             identity=known)
        assert len(results) == 2
        for result in results:
            assert result.identity.dtype == np.float32
            np.testing.assert_array_equal(result.identity, known.astype(np.float32))
    default = body.default_identity().numpy()
    fitted = fit_tracks([short_track], body, cfg)[0].identity
    assert not np.array_equal(fitted, default) and np.all((fitted >= 0) & (fitted <= 1))
    held = fit_tracks([short_track], body, dataclasses.replace(cfg, fit_identity=False))[0].identity
    np.testing.assert_array_equal(held, default)


@pytest.mark.parametrize("solver", ["lbfgs", "adam"])
def test_bounded_streams_enter_the_objective_clamped_to_their_bounds(body, short_track, monkeypatch, solver):
    """Anny's facial actions live in [0, 1]: from an initialisation outside them (a tracker's estimate
    overshooting), every evaluation of the objective (the camera stage's and each solver step's or line-search
    trial's) hands the body model values clamped to the bounds, and the result lies within them."""
    from m3t.fitting.fit import FittingConfig, fit_track

    face = short_track.init["face"].copy()
    face[:, 0], face[:, 1], face[:, 2] = -0.4, 1.5, 3.0
    track = dataclasses.replace(short_track, init={**short_track.init, "face": face})
    seen: list[torch.Tensor] = []
    forward_keypoints = body.forward_keypoints

    def recording(params, identity, keypoints):
        seen.append(params["face"].detach().clone())
        return forward_keypoints(params, identity, keypoints)

    monkeypatch.setattr(body, "forward_keypoints", recording)
    result = fit_track(track, body, FittingConfig(solver=solver, iterations=4, camera_iterations=1))
    faces = torch.cat(seen)
    assert len(seen) >= 5 and float(faces.min()) >= 0.0 and float(faces.max()) <= 1.0
    assert result.params["face"].min() >= 0.0 and result.params["face"].max() <= 1.0
    np.testing.assert_array_equal(seen[0][:, :3].numpy(), np.tile([0.0, 1.0, 1.0], (3, 1)))


def test_a_batch_sent_to_a_worker_is_processed_with_that_workers_context(tmp_path):
    from m3t.fitting.corpus import fit_batch

    root = cfx.build_slt_import(tmp_path / "slt").root
    ctx = slt_ctx(tmp_path, root)
    clips = clips_of(ctx)
    outcomes = fit_batch(ctx.job, [clips["train__clip0"], clips["train__clip1"]])
    assert [(o.clip_id, o.status) for o in outcomes] == [("train__clip0", "fitted"), ("train__clip1", "fitted")]
    assert all(Path(o.part).parent == tmp_path / "cache" / "parts" and Path(o.part).is_file() for o in outcomes)


def test_an_import_whose_adapter_cannot_read_sources_is_refused_naming_the_clip_and_corpus(tmp_path):
    from m3t.corpora.how2sign import How2SignCorpus
    from m3t.fitting.imports import read_source
    from m3t.trackers.dispatch import ClipRefused

    clip = Clip("c7", "how2sign", "train", "ASL", "s0", "", "", "clips/c7", 24.0)
    with pytest.raises(ClipRefused) as info:
        read_source(clip, "smplx_params", How2SignCorpus(tmp_path))
    assert info.value.group == "no source reader"
    assert str(info.value) == ("clip c7: corpus 'how2sign' lists smplx_params clips but its adapter cannot read "
                               "them (no source() method)")


def test_a_listing_quarantine_is_grouped_by_its_reason_up_to_the_first_semicolon():
    from m3t.corpora.base import Listing, Quarantined
    from m3t.fitting.corpus import listing_outcomes

    reasons = ("split 'foo'; expected one of train, dev, val, test", "bad times: end 5.0 s <= start 5.0 s",
               "plain reason", "b" * 61)
    listing = Listing((), tuple(Quarantined("annotation.csv", i + 2, f"c{i}", r) for i, r in enumerate(reasons)))
    assert [o.group for o in listing_outcomes(listing)] == ["listing: split 'foo'", "listing: bad times",
                                                           "listing: plain reason", "listing: " + "b" * 60]


def test_a_real_clips_track_name_follows_the_key_version(pose_root, tmp_path, monkeypatch):
    """A code change that bumps ``KEY_VERSION`` retracks every clip: its track file gets another name."""
    import m3t.fitting.corpus as engine

    pose = pose_ctx(tmp_path, pose_root, None)
    track = load_track(track_clip(clips_of(pose)["plain-a"], pose))
    monkeypatch.setattr(engine, "track_real_clip", lambda clip, root, cfg: track)
    videos = tmp_path / "videos"
    videos.mkdir()
    (videos / "v1.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42 first")
    (videos / "index.csv").write_text("id,path,split,text,language,signer\n")
    ctx = FitContext(fit_job(tmp_path, "posefile", videos, {"index": "index.csv"}))
    clip = Clip("v1", "posefile", "train", "ase", "s0", "", "", "v1.mp4", 25.0, extra=(("media_kind", "video"),))
    first = track_clip(clip, ctx)
    monkeypatch.setattr(engine, "KEY_VERSION", engine.KEY_VERSION + "-next")
    second = track_clip(clip, ctx)
    assert second != first and second.parent == first.parent and second.name.startswith("v1-")
    monkeypatch.undo()
    assert track_clip(clip, FitContext(ctx.job)) == first


def test_a_run_given_an_executor_and_no_context_sends_it_every_batch_and_counts_each_clip_once(
        body, tmp_path, monkeypatch):
    """The run only opens an executor of its own when it is given none (and no in-process context); the
    progress bar ends at the number of clips."""
    import tqdm.auto

    import m3t.fitting.cluster as cluster
    import m3t.fitting.corpus as engine
    from m3t.fitting.corpus import fit_batch, run_fit_corpus

    job = fit_job(tmp_path, "synthetic", tmp_path / "corpus", fit_corpus={"batch_clips": 2})
    clips = signer_clips("a", "b", "a", "c")
    monkeypatch.setattr(engine, "worker_context", lambda j: FitContext(j, body))

    def no_own_executor(run):
        raise AssertionError("the run opened an executor of its own")

    monkeypatch.setattr(cluster, "open_executor", no_own_executor)
    bars = []

    class Bar(tqdm.auto.tqdm):
        def close(self):
            bars.append(self.n)
            super().close()

    monkeypatch.setattr(tqdm.auto, "tqdm", Bar)
    executor = BareExecutor(fitted)
    report = run_fit_corpus(job, executor, clips=clips, progress=True)
    assert sorted(tuple(c.id for c in args[1]) for _, args in executor.sent) == [("a1", "a2"), ("b1",), ("c1",)]
    assert all(fn is fit_batch and args[0] is job for fn, args in executor.sent)
    assert sorted(o.clip_id for o in report.outcomes) == ["a1", "a2", "b1", "c1"]
    assert bars and set(bars) == {4}  # closed (once or twice: tqdm closes again when collected) at 4 of 4


def test_two_streams_of_one_tracker_add_up_in_the_initialisation_record():
    from m3t.fitting.fusion import REST, FusedInit, describe

    source = {"body": np.array([0, 1, 1, REST])}
    fused = FusedInit({}, source, {"body": ("nlf:a", "nlf:b")}, None)
    d = describe(fused)
    assert d["init_share_nlf_body"] == 0.75 and d["init_share_tracker_body"] == 0.75
    assert d["init_share_rest_body"] == 0.25 and d["init_source"] == "fused: nlf"


def test_an_imported_keypoint_clip_has_no_body_model_and_no_identity():
    from m3t.fitting.imports import NO_IDENTITY, import_clip

    clip, settings = import_kw()
    sign = np.arange(12, dtype=np.float32).reshape(3, 4)
    fitted, init = import_clip(clip, "keypoints", {"sign": sign}, "k", settings)
    assert fitted.body_model == "none" and fitted.key == "k" and fitted.camera == {}
    np.testing.assert_array_equal(fitted.params["sign"], sign)
    assert list(fitted.params) == ["sign"]
    np.testing.assert_array_equal(fitted.identity, np.zeros(len(NO_IDENTITY), np.float32))
    assert init["init_source"].startswith("imported: ") and init["init_source"].endswith(", no tracking or fitting")


def test_a_fit_without_a_recorded_initialisation_counts_as_unknown():
    from m3t.fitting.quality import quality_report

    outcomes = [ClipOutcome("a", "train", "fitted", frames=3), ClipOutcome("b", "train", "cached", frames=2,
                                                                           init={"init_source": "fused: nlf"})]
    summary = quality_report(outcomes, "x").summary
    assert summary["init_sources"] == {"unknown": 1, "fused": 1}
    assert quality_report(outcomes[:1], "x").summary["init_sources"] == {"unknown": 1}


def test_the_quality_picture_shows_each_parts_missing_ratio(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    from m3t.fitting.quality import MISSING_PARTS, plot_quality, quality_report

    coverage = {"missing_left_hand": 0.25, "missing_right_hand": 0.5, "missing_face": 0.75}
    report = quality_report([ClipOutcome("a", "train", "fitted", frames=4, track_frames=4, coverage=coverage,
                                         metrics={"reproj_px_parts": 3.0})], "synthetic")
    figures = []
    real_savefig = Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **kw: figures.append(fig) or real_savefig(fig, *a, **kw))
    path = plot_quality(report, tmp_path / "q.png")
    assert path.is_file() and path.stat().st_size > 0
    (fig,) = figures
    left, right = fig.axes
    assert [p.get_height() for p in right.patches] == [report.summary[f"missing_{p}_ratio"] for p in MISSING_PARTS]
    assert [t.get_text() for t in right.get_xticklabels()] == list(MISSING_PARTS)
    assert right.get_ylim() == (0, 1) and left.get_ylabel() == "clips"
    empty = quality_report([ClipOutcome("x", "train", "quarantined")], "slt")
    figures.clear()
    plot_quality(empty, tmp_path / "empty.png")
    assert [p.get_height() for p in figures[0].axes[1].patches] == [0.0] * len(MISSING_PARTS)


def test_lbfgs_minimises_a_loss_of_tiny_absolute_size_too():
    """Only the relative ``tolerance`` stops the solver early: a loss whose values are a millionth of the usual
    (the pseudo-Huber loss above, scaled) still reaches its minimum."""
    from m3t.fitting.fit import FittingConfig, _minimise

    x = torch.tensor([0.0, 10.0, -5.0], dtype=torch.float64, requires_grad=True)
    curve: list[float] = []
    _minimise(lambda: 1e-6 * torch.sqrt(1 + (x - 3.0) ** 2).sum(), [x], FittingConfig(solver="lbfgs", iterations=30),
              "full", 0.0, curve)
    assert 2 < len(curve) <= 30 and curve[-1] == pytest.approx(3e-6, rel=1e-6)
    np.testing.assert_allclose(x.detach().numpy(), 3.0, atol=1e-3)
