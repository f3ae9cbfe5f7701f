"""fit-corpus on real corpora: the packaged fingerspelling letters and spelled words end to end, a Phoenix14T tree
with bad rows and undetectable frames, refused media kinds, the ``corpora`` params section, Track extras."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import corpus_fixtures as fx
import numpy as np
import pytest

from m3t.config import ConfigError, load_params
from m3t.corpora.clip import Clip
from m3t.fitting.context import FitContext
from m3t.fitting.corpus import list_corpus, run_fit_corpus
from m3t.fitting.per_clip import process_clip
from m3t.trackers.track import Track, TrackError, load_track, save_track

ROOT = Path(__file__).resolve().parents[2]
FAST = {"iterations": 30, "camera_iterations": 20}


def context(tmp_path: Path, body, corpus: str, corpora: dict | None = None, **fit_corpus) -> FitContext:
    """The corpus' job with shards in tmp/shards (``data.shards_root`` = tmp) and the session's body model."""
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "fitting": FAST, "corpora": corpora or {}, "data": {"shards_root": str(tmp_path)},
        "fit_corpus": {"cache_dir": str(tmp_path / "cache"), "workers": 1, **fit_corpus}})
    job = params.fit_job(corpus)
    job = dataclasses.replace(job, shards_dir=str(tmp_path / "shards"))
    return FitContext(job, body)


def run(ctx: FitContext, **kwargs):
    return run_fit_corpus(ctx.job, ctx=ctx, progress=False, **kwargs)


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.mark.slow
def test_fingerspelling_letters_and_a_spelled_word(tmp_path, body):
    options = {"languages": ["ase"], "words_per_language": 1, "min_letters": 2, "max_letters": 2}
    ctx = context(tmp_path, body, "fingerspelling", {"fingerspelling": {"options": options}})
    listing = list_corpus(ctx.job)
    letters = [c for c in listing.clips if c.get("media_kind") == "pose"][:2]
    (word,) = [c for c in listing.clips if c.get("media_kind") == "spelled"]
    report = run(ctx, clips=letters + [word])

    out = Path(ctx.job.shards_dir)
    assert {Path(p).name for p in report.shards.values()} == {"train.parquet", "dev.parquet", "test.parquet"}
    q = json.loads((out / "quality.json").read_text())
    assert (q["corpus"], q["clips_listed"], q["clips_fitted"], q["clips_quarantined"]) == ("fingerspelling", 3, 3, 0)
    assert q["missing_left_hand_ratio"] == 1.0  # the lexicon removed ASL's (non-signing) left hand
    assert q["missing_right_hand_ratio"] < 0.1 and q["missing_face_ratio"] < 0.1
    # 30 iterations only: loose, but a broken projection or correspondence is off by the whole shoulder width
    assert 0 < q["reproj_px_parts_median"] <= q["reproj_px_parts_p90"] <= q["reproj_px_parts_max"]
    assert q["reproj_shoulder_frac_max"] < 0.5
    rows = (out / "quality.csv").read_text().splitlines()
    assert rows[0].startswith("clip_id,split,status,frames,missing_left_hand") and len(rows) == 4
    frames = {o.clip_id: o.frames for o in report.outcomes}
    assert frames[word.id] == int(word.get("frames")) == sum(int(c.get("frames")) for c in listing.clips
                                                             if c.text in word.gloss.split())

    tracks = sorted((Path(ctx.job.run.cache_dir) / "tracks").glob("*.npz"))
    assert len(tracks) == 3
    for path in tracks:
        track = load_track(path)
        assert track.extras["pose_world"].shape == (track.num_frames, 33, 3)
        assert track.extras["depth"].shape == track.confidence.shape
        assert np.isnan(track.extras["depth"][track.confidence == 0]).all()

    again = run(ctx, clips=letters + [word])
    assert [o.status for o in again.outcomes] == ["cached"] * 3
    assert again.quality["reproj_px_parts_median"] == pytest.approx(q["reproj_px_parts_median"])


def phoenix(tmp_path: Path, body, **fit_corpus) -> tuple[FitContext, fx.Fixture]:
    fixture = fx.build_phoenix14t(tmp_path / "phoenix")
    corpora = {"phoenix14t": {"root": str(fixture.root)}}
    return context(tmp_path, body, "phoenix14t", corpora, **fit_corpus), fixture


@pytest.mark.slow
def test_bad_rows_and_undetectable_frames_are_quarantined(tmp_path, body):
    pytest.importorskip("mediapipe", reason="MediaPipe not installed: bash .ci/install-tracking")
    ctx, fixture = phoenix(tmp_path, body)
    report = run(ctx)
    records = read_jsonl(Path(ctx.job.shards_dir) / "quarantine.jsonl")
    for file, row, fragment in fixture.bad:  # the adapter's refusals: file + row + reason
        assert any(r["file"] == file and r["row"] == row and fragment in r["reason"] for r in records), (file, row)
    # The good clips were tracked: 2x2-pixel frames show nobody, which quarantines the clip (not a fake fit).
    tracked = [r for r in records if r["row"] is None]
    assert len(tracked) == sum(fixture.per_split.values())
    assert all("no person detected" in r["reason"] and r["file"].startswith("features/") for r in tracked)
    q = report.quality
    assert q["clips_listed"] == len(tracked) and q["clips_quarantined_at_listing"] == len(fixture.bad)
    assert q["quarantine_reasons"]["no person detected"] == len(tracked)
    assert q["quarantine_reasons"]["listing: missing media"] == 1
    rows = (Path(ctx.job.shards_dir) / "quality.csv").read_text().splitlines()
    assert len(rows) == 1 + len(records)


def test_missing_mediapipe_names_the_installer(tmp_path, body, monkeypatch):
    import m3t.trackers.mediapipe_holistic as holistic

    def absent():
        raise ImportError(f"MediaPipe tracking needs the `mediapipe` package: {holistic.INSTALL_HINT}")

    monkeypatch.setattr(holistic, "import_mediapipe", absent)
    ctx, _ = phoenix(tmp_path, body)
    clip = list_corpus(ctx.job).clips[0]
    outcome = process_clip(clip, ctx)
    assert outcome.status == "quarantined" and ".ci/install-tracking" in outcome.reason
    assert outcome.group == "mediapipe not installed"


@pytest.mark.parametrize("kind, group", [("smplx_params", "needs body.model: smplfx"),
                                         ("flame_params", "needs body.model: smplfx"),
                                         ("keypoints", "no source reader")])
def test_already_fitted_kinds_are_imported_not_tracked(tmp_path, body, kind, group):
    """Fitted parameters go to the import (m3t.fitting.imports), never to a tracker: under Anny the SMPL-X / FLAME
    kinds are refused naming the body model they need, and a keypoint clip of a corpus without a reader says so."""
    ctx, _ = phoenix(tmp_path, body)
    clip = Clip("c0", "phoenix14t", "train", "DGS", "s", "t", "g", "x.pkl", 25.0, extra=(("media_kind", kind),))
    outcome = process_clip(clip, ctx)
    assert outcome.status == "quarantined" and outcome.group == group, outcome
    assert "not implemented" not in outcome.reason


@pytest.mark.parametrize("corpora, message", [
    ({"fingerspelling": {"rooot": "x"}}, r"corpora\.fingerspelling\.rooot"),
    ({"phoenix2014": {"root": "x"}}, r"corpora\.phoenix2014.*allowed corpora: synthetic"),
    ({"fingerspelling": {"options": {"language": ["ase"]}}}, r"corpora\.fingerspelling\.options\.language"),
    ({"fingerspelling": {"options": {"words_per_language": "many"}}},
     r"corpora\.fingerspelling\.options\.words_per_language: expected an integer"),
    ({"fingerspelling": {"options": {"split_fractions": [0.5, 0.5, 0.5]}}}, r"corpora\.fingerspelling.*sum"),
])
def test_corpora_section_is_checked(corpora, message):
    with pytest.raises(ConfigError, match=message):
        load_params(ROOT / "params.yaml", overrides={"corpora": corpora})


def test_fit_corpus_paths_live_in_corpora_and_data():
    params = load_params(ROOT / "params.yaml")
    job = params.fit_job("fingerspelling")
    assert (job.corpus, job.source.root, job.shards_dir) == ("fingerspelling", "", "data/shards/fingerspelling")
    assert params.fit_job().corpus == params.fit_corpus.default_corpus == "synthetic"
    with pytest.raises(ConfigError, match=r"unknown key\(s\) fit_corpus\.corpus_dir"):
        load_params(ROOT / "params.yaml", overrides={"fit_corpus": {"corpus_dir": "elsewhere"}})
    with pytest.raises(ConfigError, match=r"corpora\.synthetic\.shards_dir: shard folders are derived"):
        load_params(ROOT / "params.yaml", overrides={"corpora": {"synthetic": {"shards_dir": "elsewhere"}}})
    with pytest.raises(ConfigError, match=r"corpora\.mead is not in params.yaml"):
        params.fit_job("mead")
    with pytest.raises(ConfigError, match=r"data\.train_corpora names how2sign, not listed in corpora"):
        load_params(ROOT / "params.yaml", overrides={"data": {"train_corpora": ["synthetic", "how2sign"]}})


def test_track_extras_round_trip(tmp_path):
    T, K = 3, 543
    world = np.full((T, 33, 3), np.nan, np.float32)
    world[1] = 0.25
    track = Track(np.zeros((T, K, 2), np.float32), np.ones((T, K), np.float32), "mediapipe_holistic", (64, 48),
                  25.0, np.full(4, np.nan, np.float32), "test", extras={"pose_world": world})
    loaded = load_track(save_track(track, tmp_path / "t.npz"))
    np.testing.assert_array_equal(loaded.extras["pose_world"], world)  # NaN kept where nothing was seen
    assert load_track(save_track(dataclasses.replace(track, extras=None), tmp_path / "u.npz")).extras is None
    bad = dataclasses.replace(track, extras={"pose_world": world[:2]})
    with pytest.raises(TrackError, match=r"u\.npz: extra 'pose_world' has shape \(2, 33, 3\); expected \(3, \.\.\.\)"):
        load_track(save_track(bad, tmp_path / "u.npz"))
