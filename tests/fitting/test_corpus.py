"""fit-corpus's engine (:mod:`m3t.fitting.corpus` and the modules it runs) in detail: what the content keys of tracks, fits, batch fits and
imports follow (the key version included); how one signer's batch treats its failing and fused clips; the quarantine
record; the cache's integrity checks; which config sections and artifact folders the MLflow run of a corpus gets.
Written to pin behaviours that mutation testing found unchecked. Corpora: a hand-written synthetic corpus
(:func:`m3t.corpora.synthetic.write_corpus`: ``clips.jsonl`` + ``motion/<id>.npz``) of four short clips, three of
signer ``s0``, one of ``s1``; an index-CSV ``.pose`` collection of real pose-format files (the packaged
fingerspelling lexicon, as in ``tests/pipeline/test_fusion_flow.py``), one clip with an NLF output beside its media;
neccam/slt's gzip pickles (``corpus_fixtures.build_slt_import``, which cites its source).
"""
from __future__ import annotations

import csv
import dataclasses
import json
import math
import shutil
from pathlib import Path

import corpus_fixtures as cfx
import numpy as np
import pytest
import torch
from builders import front_camera, smooth_motion

from m3t.config import load_params
from m3t.corpora.clip import Clip
from m3t.corpora.synthetic_storage import SyntheticClip, write_corpus
from m3t.fitting.context import FitContext
from m3t.fitting.per_clip import NO_EXTERNAL, process_clip, track_clip
from m3t.fitting.report import ClipOutcome
from m3t.fitting.signer_batches import process_batch
from m3t.shards.io import read_shard
from m3t.trackers.track import load_track

ROOT = Path(__file__).resolve().parents[2]


# lbfgs: a signer batch (fit_corpus.batch_clips) is one problem with one identity, what the batch tests here check;
# the default, lbfgs_batched (every clip its own problem), is tested in fitting/test_lbfgs.py and the pipeline tests
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
    from m3t.trackers.dispatch import ground_truth

    ctx = synthetic_ctx(tmp_path, synthetic_root, body)
    clip = clips_of(ctx)["s1-a"]
    outcome = process_clip(clip, ctx)
    assert outcome.status == "fitted" and outcome.frames == outcome.track_frames == 7
    assert outcome.init == {"init_source": "simulated tracker initialisation"}
    assert outcome.seconds > 0 and set(outcome.coverage) == {"missing_left_hand", "missing_right_hand", "missing_face"}
    fitted = read_shard(outcome.part).clips[0]
    assert fitted.metrics == outcome.metrics and fitted.key in Path(outcome.part).name
    track = load_track(track_clip(clip, ctx))
    params, identity, _ = ground_truth(clip, ctx.corpus.root)
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
    ``tests/pipeline/test_fusion_flow.py``) into an index-CSV ``.pose`` collection
    (``id,path,split,text,language,signer``, :mod:`m3t.corpora.posefile`), one signer; ``fused`` has an NLF output
    beside its media."""
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
    from m3t.fitting import context

    monkeypatch.setattr(context, "load_body_model", lambda cfg: body)  # the session's Anny, not a second build
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


# ------------------------------------------------------------------------------------------ keys and paths
def test_a_jobs_key_follows_its_content_not_the_order_options_were_written_in(tmp_path):
    from m3t.fitting.context import worker_context

    def job(options):
        return fit_job(tmp_path, "posefile", tmp_path, options)

    a, b = job({"index": "index.csv", "language": "ase"}), job({"language": "ase", "index": "index.csv"})
    assert a == b and a.key() == b.key() and len(a.key()) == 16
    assert job({"index": "other.csv", "language": "ase"}).key() != a.key()
    assert dataclasses.replace(a, shards_dir="elsewhere").key() != a.key()
    assert worker_context(a) is worker_context(b)  # one context (one body model) per process and job
    assert worker_context(job({"index": "other.csv"})) is not worker_context(a)


def test_a_clips_part_file_lies_in_the_parts_folder_of_the_cache(tmp_path):
    from m3t.fitting.cache import part_path

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


def test_a_video_clips_track_follows_its_bytes_its_frame_rate_and_the_mediapipe_settings(pose_root, tmp_path,
                                                                                          monkeypatch):
    """MediaPipe is replaced by a recorder returning a real track: the cache key is what is tested."""
    from m3t.trackers import dispatch

    pose = pose_ctx(tmp_path, pose_root, None)
    track = load_track(track_clip(clips_of(pose)["plain-a"], pose))
    tracked = []
    monkeypatch.setattr(dispatch, "track_real_clip",
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
    from m3t.fitting import signer_batches

    ctx = synthetic_ctx(tmp_path, synthetic_root, body, fit_corpus={"batch_clips": 2})
    clips = clips_of(ctx)
    pair = [clips["s0-b"], clips["s0-c"]]
    batch = process_batch(pair, ctx)
    Path(batch[1].part).unlink()  # the second clip's part is lost; the first stays cached

    def diverges(tracks, ctx):
        raise FloatingPointError("the batch fit diverged")

    monkeypatch.setattr(signer_batches, "fit_signer_batch", diverges)
    outcomes = process_batch(pair, ctx)
    assert [(o.clip_id, o.status) for o in outcomes] == [("s0-b", "cached"), ("s0-c", "fitted")]
    assert outcomes[0].part == batch[0].part and outcomes[1].part != batch[1].part
    assert outcomes[1].init == {"init_source": "simulated tracker initialisation"}  # its own fit, its own identity
    alone = process_batch(pair, synthetic_ctx(tmp_path, synthetic_root, body,
                                              fit_corpus={"batch_clips": 2, "batch_frames": 9}))
    assert [(o.clip_id, o.status) for o in alone] == [("s0-b", "fitted"), ("s0-c", "cached")]
    assert alone[0].init == {"init_source": "simulated tracker initialisation"}


def fitted(batch) -> list[ClipOutcome]:
    return [ClipOutcome(c.id, c.split, "fitted", frames=3, seconds=0.5) for c in batch]


def test_fit_and_log_hands_the_mlflow_run_the_ground_truth_of_synthetic_clips(body, synthetic_root, tmp_path,
                                                                              monkeypatch, capsys):
    """What :func:`m3t.fitting.corpus.fit_and_log` gives the MLflow logger (replaced by a recorder): the corpus'
    sections, the report, the body model to picture with and, for synthetic clips, their ground truth."""
    import m3t.fitting.corpus as engine
    import m3t.fitting.report as reporting
    from m3t.corpora.synthetic_storage import SyntheticCorpus
    from m3t.fitting import context

    monkeypatch.setattr(context, "load_body_model", lambda cfg: body)
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
    from m3t.fitting import cache

    def ctx():
        return synthetic_ctx(tmp_path, synthetic_root, body, fit_corpus={"batch_clips": 2})

    clips = clips_of(ctx())
    pair = [clips["s0-b"], clips["s0-c"]]
    first = process_batch(pair, ctx())
    assert {o.status for o in first} == {"fitted"}
    assert {o.status for o in process_batch(pair, ctx())} == {"cached"}
    monkeypatch.setattr(cache, "KEY_VERSION", cache.KEY_VERSION + "-next")
    again = process_batch(pair, ctx())
    assert {o.status for o in again} == {"fitted"}
    assert not {o.part for o in again} & {o.part for o in first}


def test_a_batch_sent_to_a_worker_is_processed_with_that_workers_context(tmp_path):
    from m3t.fitting.corpus import fit_batch

    root = cfx.build_slt_import(tmp_path / "slt").root
    ctx = slt_ctx(tmp_path, root)
    clips = clips_of(ctx)
    outcomes = fit_batch(ctx.job, [clips["train__clip0"], clips["train__clip1"]])
    assert [(o.clip_id, o.status) for o in outcomes] == [("train__clip0", "fitted"), ("train__clip1", "fitted")]
    assert all(Path(o.part).parent == tmp_path / "cache" / "parts" and Path(o.part).is_file() for o in outcomes)


def test_a_real_clips_track_name_follows_the_key_version(pose_root, tmp_path, monkeypatch):
    """A code change that bumps ``KEY_VERSION`` retracks every clip: its track file gets another name."""
    from m3t.fitting import cache
    from m3t.trackers import dispatch

    pose = pose_ctx(tmp_path, pose_root, None)
    track = load_track(track_clip(clips_of(pose)["plain-a"], pose))
    monkeypatch.setattr(dispatch, "track_real_clip", lambda clip, root, cfg: track)
    videos = tmp_path / "videos"
    videos.mkdir()
    (videos / "v1.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42 first")
    (videos / "index.csv").write_text("id,path,split,text,language,signer\n")
    ctx = FitContext(fit_job(tmp_path, "posefile", videos, {"index": "index.csv"}))
    clip = Clip("v1", "posefile", "train", "ase", "s0", "", "", "v1.mp4", 25.0, extra=(("media_kind", "video"),))
    first = track_clip(clip, ctx)
    monkeypatch.setattr(cache, "KEY_VERSION", cache.KEY_VERSION + "-next")
    second = track_clip(clip, ctx)
    assert second != first and second.parent == first.parent and second.name.startswith("v1-")
    monkeypatch.undo()
    assert track_clip(clip, FitContext(ctx.job)) == first
