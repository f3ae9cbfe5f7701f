"""fit-corpus on already-fitted corpora: SOKE SMPL-X pickles -> SMPL-FX shards, MEAD FLAME parameters -> face-only
shards, slt ``sign`` arrays -> feature shards; values equal the sources after the documented conversion, bad clips
are quarantined with their reason, nothing is tracked or fitted, and no licensed model is built.

The trees are the published layouts of :mod:`corpus_fixtures` (``build_soke``, ``build_mead_release``,
``build_slt_import``, each citing its source)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import corpus_fixtures as cfx
import corpus_fixtures as fx
import numpy as np
import pytest
import roma
import torch

from m3t.body.rotations import sixd_to_matrix
from m3t.config import load_params
from m3t.corpora.base import open_corpus
from m3t.corpora.clip import Clip
from m3t.corpora.mead import read_flame_params
from m3t.corpora.soke_smplx import load_smplx_sequence
from m3t.fitting.context import FitContext
from m3t.fitting.corpus import run_fit_corpus
from m3t.fitting.imports import BODY_POSE_INDEX, IMPORTERS, face_layout, smplfx_layout
from m3t.fitting.report import ClipOutcome
from m3t.shards.io import read_shard
from m3t.shards.schema import layout_to_json
from m3t.trackers.dispatch import REFUSED, ClipRefused, track_real_clip

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def smplx_file(tmp_path_factory) -> Path:
    """The synthetic SMPL-X file (its ``hands_meanl`` / ``hands_meanr`` are what the SOKE import adds)."""
    from smplfx_fixtures import ensure_fixture_files

    return ensure_fixture_files(tmp_path_factory).smplx


def context(tmp_path: Path, corpus: str, root: Path, options: dict | None = None, body: dict | None = None,
            **fit_corpus) -> FitContext:
    """The corpus' job with shards in tmp/shards; the FLAME path points nowhere: importing builds no model."""
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "corpora": {corpus: {"root": str(root), "options": options or {}}},
        "body": {"flame_path": str(tmp_path / "absent_flame.pkl"), **(body or {})},
        "data": {"shards_root": str(tmp_path)},
        "fit_corpus": {"cache_dir": str(tmp_path / "cache"), "workers": 1, **fit_corpus}})
    job = dataclasses.replace(params.fit_job(corpus), shards_dir=str(tmp_path / "shards"))
    return FitContext(job)


def run(ctx: FitContext):
    return run_fit_corpus(ctx.job, ctx=ctx, progress=False)


def shard_clips(ctx: FitContext) -> dict:
    out = {}
    for split in ("train", "dev", "test"):
        out.update({c.clip.id: c for c in read_shard(Path(ctx.job.shards_dir) / f"{split}.parquet").clips})
    return out


def quarantine(ctx: FitContext) -> dict[str, str]:
    """clip id (or file) -> "<group>: <reason>" of quarantine.jsonl."""
    lines = (Path(ctx.job.shards_dir) / "quarantine.jsonl").read_text().splitlines()
    return {q["clip_id"] or q["file"]: f"{q['group']}: {q['reason']}" for q in map(json.loads, lines)}


def rotmats(aa: np.ndarray) -> np.ndarray:
    """(T, J*3) axis-angle -> (T, J, 3, 3)."""
    return roma.rotvec_to_rotmat(torch.as_tensor(aa, dtype=torch.float64).reshape(aa.shape[0], -1, 3)).numpy()


def from_6d(sixd: np.ndarray) -> np.ndarray:
    """(T, J*6) -> (T, J, 3, 3)."""
    return sixd_to_matrix(torch.as_tensor(sixd, dtype=torch.float64).reshape(sixd.shape[0], -1, 6)).numpy()


def test_every_refused_kind_is_imported_and_never_tracked(tmp_path):
    assert set(IMPORTERS) == set(REFUSED)
    for kind in REFUSED:
        clip = fx_clip(kind)
        with pytest.raises(ClipRefused, match="not tracked"):
            track_real_clip(clip, tmp_path)


def fx_clip(kind: str):
    from m3t.corpora.clip import Clip

    return Clip("c0", "x", "train", "DGS", "s", "t", "g", "x.pkl", 25.0, extra=(("media_kind", kind),))


def test_smplfx_layout_without_licensed_files_equals_the_model_layout(fx):
    assert layout_to_json(smplfx_layout(100)) == layout_to_json(fx.layout)
    face = face_layout(100)
    assert face.names == ("face",) and face["face"] == fx.layout["face"]
    assert face.identity_labels == fx.layout.identity_labels


@pytest.mark.parametrize("flat_hand_mean", [False, True])
def test_soke_smplx_import_round_trips_into_smplfx_shards(tmp_path, smplx_file, flat_hand_mean):
    fixture = fx.build_soke(tmp_path / "soke", "how2sign")
    options = {"annotation": "annotation.csv", "flat_hand_mean": flat_hand_mean}
    ctx = context(tmp_path, "soke_smplx", fixture.root, options, {"model": "smplfx", "smplx_path": str(smplx_file)})
    report = run(ctx)
    assert report.summary["clips_fitted"] == 4 and report.summary["frames"] == 12
    assert read_shard(Path(ctx.job.shards_dir) / "train.parquet").layout == smplfx_layout(100)
    with np.load(smplx_file) as data:
        mean = {"left_hand": data["hands_meanl"], "right_hand": data["hands_meanr"]}
    corpus = open_corpus("soke_smplx", fixture.root, **options)
    shards = shard_clips(ctx)
    for clip in corpus.listing().clips:
        if clip.id.startswith("bad"):
            continue
        src, got = load_smplx_sequence(fixture.root / clip.media), shards[clip.id]
        assert got.body_model == "smplfx" and got.num_frames == 3 and got.camera == {}
        body = src["body_pose"].reshape(3, 21, 3)[:, BODY_POSE_INDEX].reshape(3, 30)
        np.testing.assert_allclose(from_6d(got.params["body"]), rotmats(body), atol=1e-6)
        # axis-angle -> 6D -> axis-angle gives the source back (angles below pi)
        back = roma.rotmat_to_rotvec(torch.as_tensor(from_6d(got.params["body"]))).numpy().reshape(3, 30)
        np.testing.assert_allclose(back, body, atol=1e-5)
        for stream, key in (("left_hand", "left_hand_pose"), ("right_hand", "right_hand_pose")):
            hand = src[key] + (0.0 if flat_hand_mean else mean[stream])
            np.testing.assert_allclose(from_6d(got.params[stream]), rotmats(hand), atol=1e-6)
        face = got.params["face"]
        np.testing.assert_array_equal(face[:, :10], src["expression"])
        assert not face[:, 10:102].any()  # the rest of FLAME's expression and both eyelids: SMPL-X has none
        np.testing.assert_allclose(from_6d(face[:, 102:]), rotmats(src["jaw_pose"]), atol=1e-6)
        np.testing.assert_allclose(got.identity[:10], src["betas"].mean(0), atol=1e-7)
        assert not got.identity[10:].any()
        assert got.metrics["src_nonfinite_frame_frac"] == 0.0
        assert got.metrics["src_body_pose_max"] == pytest.approx(float(src["body_pose"].max()))
    reasons = quarantine(ctx)
    assert set(reasons) == {"bad_key", "bad_shape", "empty", "no_note"}
    assert "bad_key_1_3D.pkl: SMPL-X key 'smplx_lhand_pose' missing" in reasons["bad_key"]
    assert "'smplx_expr' has 50 values; expected 10" in reasons["bad_shape"]
    quality = json.loads((Path(ctx.job.shards_dir) / "quality.json").read_text())
    assert quality["imported_clips"] == 4 and quality["init_sources"] == {"imported": 4}
    assert quality["imported_nonfinite_frame_frac"] == 0.0
    assert quality["imported_body_pose_min"] == min(c.metrics["src_body_pose_min"] for c in shards.values())
    again = run(ctx)
    assert again.run_stats["clips_cached"] == 4 and again.run_stats["clips_fitted_now"] == 0


def test_soke_smplx_needs_smplfx(tmp_path):
    fixture = fx.build_soke(tmp_path / "soke", "phoenix")
    ctx = context(tmp_path, "soke_smplx", fixture.root, {"annotation": "annotation.csv"})  # body.model: anny
    report = run(ctx)
    assert report.summary["clips_fitted"] == 0
    refused = [o for o in report.outcomes if o.group == "needs body.model: smplfx"]
    assert len(refused) == 6 and "which needs body.model: smplfx (it is 'anny')" in refused[0].reason


def test_mead_release_import_into_face_only_shards(tmp_path):
    from m3t.tokenizers.data import check_layout, clip_sequences
    from m3t.tokenizers.pipeline import face_only_clips

    fixture = fx.build_mead_release(tmp_path / "mead")
    ctx = context(tmp_path, "mead", fixture.root, body={"model": "smplfx"})
    report = run(ctx)
    assert report.summary["clips_fitted"] == 4
    shards = shard_clips(ctx)
    assert set(shards) == {"M003_front_angry_level_1_001", "M003_front_happy_level_3_002",
                           "W009_front_sad_level_2_001", "W011_front_fear_level_1_004"}
    for clip_id, got in shards.items():
        rel = fixture.root / got.clip.media
        src = read_flame_params(rel)
        face = got.params["face"]
        assert set(got.params) == {"face"} and face.shape == (fixture.extra["frames"][str(rel.parent.relative_to(
            fixture.root))], 108)
        if clip_id.endswith("004"):  # frame 1 held a NaN: it takes frame 0's values (the nearer, earlier one)
            assert np.isnan(src["exp"][1]).any()
            src = {k: np.concatenate([v[:1], v[:1], v[2:]]) for k, v in src.items()}
            assert got.metrics["src_nonfinite_frame_frac"] == 0.25
        np.testing.assert_array_equal(face[:, :100], src["exp"])
        assert not face[:, 100:102].any()
        np.testing.assert_allclose(from_6d(face[:, 102:]), rotmats(src["jaw"]), atol=1e-6)
        np.testing.assert_allclose(got.identity[10:], src["shape"][:, :100].mean(0), atol=1e-6)
        assert not got.identity[:10].any()
    reasons = quarantine(ctx)
    assert set(reasons) == {"M003/left_30/angry/level_1/001/shape_pose_cam.hdf5", "W011_front_fear_level_1_003"}
    assert "every one of its 4 frames holds NaN or inf" in reasons["W011_front_fear_level_1_003"]
    quality = json.loads((Path(ctx.job.shards_dir) / "quality.json").read_text())
    assert quality["imported_nonfinite_frame_frac"] == pytest.approx(1 / (5 + 4 + 6 + 4))
    # what the face tokenizer reads from tokenizer_train.extra_face_shards
    extra = face_only_clips((str(Path(ctx.job.shards_dir) / "train.parquet"),
                             str(Path(ctx.job.shards_dir) / "test.parquet")))
    assert check_layout(smplfx_layout(100), "face") == 108
    assert [clip_sequences(c.params, "face", c.clip.id)[0].shape[1] for c in extra] == [108] * len(extra)


def test_slt_import_keeps_the_arrays_as_they_are(tmp_path):
    from m3t.backtranslation.data import InputSpec

    fixture = fx.build_slt_import(tmp_path / "slt")
    ctx = context(tmp_path, "slt_pickle", fixture.root)
    report = run(ctx)
    shards = shard_clips(ctx)
    assert {c.clip.split for c in shards.values()} == {"train", "dev"} and len(shards) == 4
    assert report.summary["clips_quarantined"] == 4
    corpus = open_corpus("slt_pickle", fixture.root)
    for clip in corpus.listing().clips:
        if clip.id not in shards:
            continue
        src = corpus.sequence(clip)
        if clip.id == "train__clip1":
            assert np.isnan(src[3, 7])
            src[3] = src[2]  # held from the nearer, earlier finite frame
        np.testing.assert_array_equal(shards[clip.id].params["sign"], src)
    reasons = quarantine(ctx)
    for clip_id, _, fragment in fixture.bad:
        assert fragment in reasons[clip_id], (clip_id, reasons)
    layout = read_shard(Path(ctx.job.shards_dir) / "train.parquet").layout
    assert layout.names == ("sign",) and layout.dims == {"sign": 1024}
    assert InputSpec.from_layout("model", layout).dim == 1024  # a back-translation model reads them as they are


@pytest.mark.slow
@pytest.mark.parametrize("corpus", ["mead", "soke_smplx"])
def test_fit_and_log_pictures_imports_without_a_fit_camera(tmp_path, tmp_path_factory, corpus):
    """The stage's path (MLflow off): face-only shards build no body model (the FLAME path points nowhere);
    SMPL-FX shards from SOKE picture their mesh from the front (an imported clip has no camera)."""
    from smplfx_fixtures import ensure_fixture_files

    from m3t.experiment import ExperimentConfig
    from m3t.fitting.corpus import fit_and_log

    if corpus == "mead":
        ctx = context(tmp_path, "mead", fx.build_mead_release(tmp_path / "mead").root, body={"model": "smplfx"},
                      render_clips=1)
    else:
        files = ensure_fixture_files(tmp_path_factory)
        body = {"model": "smplfx", "smplx_path": str(files.smplx), "flame_path": str(files.flame),
                "flame_correspondence_path": str(files.correspondence)}
        ctx = context(tmp_path, corpus, fx.build_soke(tmp_path / "soke").root, {"annotation": "annotation.csv"}, body,
                      render_clips=1)
    report = fit_and_log(ctx.job, ExperimentConfig(enabled=False), progress=False)
    assert report.summary["clips_fitted"] == 4
    pictures = sorted(p.name for p in (Path(ctx.job.run.cache_dir) / "render").glob("*.png"))
    if corpus == "mead":
        assert pictures == ["quality-mead.png"]
    else:
        assert len(pictures) == 2 and pictures[0].endswith("_00001.png")  # the middle of 3 frames


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


def fitted(batch) -> list[ClipOutcome]:
    return [ClipOutcome(c.id, c.split, "fitted", frames=3, seconds=0.5) for c in batch]


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
