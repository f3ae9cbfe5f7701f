"""Active-window trimming's arithmetic (:func:`m3t.slr.trim.active_window`) and the trimmer without a body model,
on activity patterns whose kept windows are worked out by hand from the rule (M3T Sec. 3.4): keep the first to
the last active frame, ``margin`` more on each side within the clip, widened around its centre to ``min_frames``
within the clip. Written to pin behaviours that mutation testing found unchecked (the existing trimming tests
use ``margin=0`` and check a widened window only loosely)."""
from __future__ import annotations

import numpy as np
import pytest
from builders import RecordingRun

from m3t.experiment import RunRecord
from m3t.slr.config import TrimConfig
from m3t.slr.table import recognition_table
from m3t.slr.trim import (
    ActiveWindow,
    ClipTooShortError,
    Trimmer,
    active_window,
    trim_params,
)


def activity(frames: int, *active: int) -> np.ndarray:
    out = np.zeros(frames, dtype=bool)
    out[list(active)] = True
    return out


@pytest.mark.parametrize(("active", "margin", "min_frames", "window"), [
    ((5, 6, 7, 8, 9), 2, 4, (3, 12)),  # 5 - 2 .. 9 + 1 + 2
    ((5, 6, 7, 8, 9), 0, 4, (5, 10)),
    ((1,), 2, 1, (0, 4)),  # the margin stops at the clip's first frame
    ((18,), 2, 1, (16, 20)),  # ... and at its last
    ((10, 11), 0, 8, (7, 15)),  # widened around the centre: (10 + 12 - 8) // 2 = 7
    ((10,), 0, 8, (6, 14)),  # (10 + 11 - 8) // 2 = 6
    ((1,), 0, 8, (0, 8)),  # widened, but not before the first frame
    ((19,), 0, 8, (12, 20)),  # ... nor past the last
    ((3, 15), 1, 4, (2, 17)),  # inactive frames between two active ones stay
])
def test_the_kept_window_follows_the_rule(active, margin, min_frames, window):
    got = active_window(activity(20, *active), TrimConfig(margin=margin, min_frames=min_frames))
    assert (got.start, got.end, got.frames, got.active_frames) == (*window, 20, len(active))
    assert got.kept == window[1] - window[0]
    assert got.trimmed_share == pytest.approx(1 - (window[1] - window[0]) / 20)  # a float quotient: approx


def test_a_clip_without_activity_or_with_trimming_off_is_kept_whole():
    assert active_window(activity(12), TrimConfig(min_frames=4)) == ActiveWindow(0, 12, 12, 0)
    off = TrimConfig(enabled=False, min_frames=4)
    assert active_window(activity(12, 3, 4, 5), off) == ActiveWindow(0, 12, 12, 3)
    assert ActiveWindow(0, 12, 12, 0).trimmed_share == 0.0
    assert ActiveWindow(0, 0, 0, 0).trimmed_share == 0.0  # no frames: nothing trimmed, no division by zero
    assert ActiveWindow(2, 5, 10, 1).to_dict() == {"start": 2, "end": 5, "frames": 10, "active_frames": 1}


def test_a_clip_shorter_than_min_frames_is_refused_by_name_and_one_of_exactly_min_frames_is_not():
    cfg = TrimConfig(min_frames=8)
    with pytest.raises(ClipTooShortError, match=r"'clip-7' has 7 frames, fewer than slr.trim.min_frames=8"):
        active_window(activity(7, 2), cfg, "clip-7")
    assert active_window(activity(8, 2), cfg).kept == 8


def test_trim_params_cuts_every_modality_to_the_window():
    params = {"body": np.arange(20).reshape(10, 2), "face": np.arange(10)[:, None]}
    kept = trim_params(params, ActiveWindow(3, 7, 10, 2))
    assert kept["body"].tolist() == [[6, 7], [8, 9], [10, 11], [12, 13]] and kept["face"][:, 0].tolist() == [3, 4, 5, 6]


def test_the_trimmer_without_trimming_needs_no_body_and_still_refuses_short_clips():
    with pytest.raises(ValueError, match="needs the body model"):
        Trimmer(None, TrimConfig(enabled=True))
    trimmer = Trimmer(None, TrimConfig(enabled=False, min_frames=4))
    params = {"body": np.ones((10, 3)), "face": np.zeros((10, 2))}
    kept, window = trimmer(params, np.zeros(4), "whole")
    assert window == ActiveWindow(0, 10, 10, 0) and kept["body"].shape == (10, 3) and kept["face"].shape == (10, 2)
    with pytest.raises(ClipTooShortError, match="'short'"):
        trimmer({"body": np.ones((3, 3))}, np.zeros(4), "short")


@pytest.mark.parametrize("bad", [{"height_threshold": 0.0}, {"displacement_threshold": -1.0}, {"margin": -1},
                                 {"min_frames": 0}])
def test_trim_settings_out_of_range_are_refused(bad):
    with pytest.raises(ValueError):
        TrimConfig(**bad)


# ------------------------------------------------------------------------------------------ Tab. 4 from MLflow
def slr_run(run_id: str, top1: float, status: str = "FINISHED", variants=("no_face", "full"),
            confidence: str = "0.9") -> RunRecord:
    metrics = {}
    for variant in variants:
        shift = 10.0 if variant == "full" else 0.0
        metrics.update({f"{variant}/overall/top1": top1 + shift, f"{variant}/overall/top1_ci_low": top1 + shift - 1,
                        f"{variant}/overall/top1_ci_high": top1 + shift + 1, f"{variant}/overall/top1_chance": 25.0,
                        f"{variant}/overall/top5": 100.0, f"{variant}/overall/top5_chance": 100.0,
                        f"{variant}/overall/clips": 8, f"{variant}/overall/classes": 4})
    return RunRecord(run_id, "evaluate-slr", 0, status, {"slr_evaluate.confidence": confidence}, metrics, None,
                     {"corpus": "synthetic", "split": "test", "subsets_reason": "no subset list"})


def test_the_recognition_table_is_the_newest_finished_run_full_probe_first():
    records = [slr_run("running", 90.0, status="RUNNING"), slr_run("newest", 40.0), slr_run("older", 70.0)]
    table = recognition_table(records)
    rows = [line for line in table.splitlines() if line.startswith("| M3T")]
    assert rows[0].startswith("| M3T probe (body, hands, face) | 50.0 [49.0, 51.0] | 100.0 [nan, nan] |")
    assert rows[1].startswith("| M3T probe w/o face | 40.0 [39.0, 41.0] |")
    assert "| chance (uniform guess) | 25.0 | 100.0 |" in table
    assert "synthetic, test split; accuracies in %, [90% percentile bootstrap interval over clips]." in table
    assert "Overall: 8 clip(s) of 4 class(es)" in table and "Subsets unavailable: no subset list" in table
    assert recognition_table([slr_run("failed", 1.0, status="FAILED")]).startswith("no finished evaluate-slr runs")


# --------------------------------------------------------------------------------------------- the probe's pooling
def _probe(pooling: str, streams: tuple[str, ...] = ("body",)):
    import torch

    from m3t.slr.config import SLRConfig
    from m3t.slr.model import ProbeDims, SLRProbe

    torch.manual_seed(0)
    probe = SLRProbe(SLRConfig(layers=1, heads=2, dropout=0.0, max_steps=8, pooling=pooling), ProbeDims(4, 3, streams))
    return probe.eval()


def _features(steps: int, streams: tuple[str, ...] = ("body",), batch: int = 2):
    import torch

    generator = torch.Generator().manual_seed(1)
    return {s: torch.randn(batch, steps, 4, generator=generator) for s in streams}


def test_mean_pooling_is_the_mean_of_the_encoder_outputs_over_the_valid_positions_only():
    """One valid step of one stream is one position: the pooled vector is that position's encoder output itself
    (a divisor other than the number of valid positions would scale it); padding steps change nothing."""
    import torch

    probe = _probe("mean")
    features = _features(3)
    mask = torch.tensor([[True, False, False], [True, True, False]])
    with torch.no_grad():
        logits = probe(features, mask)
        x, valid = probe.sequence(features, mask)
        h = probe.encoder(x, src_key_padding_mask=~valid)
        expected = torch.stack([h[0, :1].mean(0), h[1, :2].mean(0)])
        assert torch.allclose(logits, probe.head(expected), atol=1e-6)
        # the same clips without their padding steps: the same logits (padding is masked out of attention and pool)
        alone = [probe({"body": features["body"][i: i + 1, :n]}, torch.ones(1, n, dtype=torch.bool))
                 for i, n in enumerate((1, 2))]
    assert torch.allclose(logits, torch.cat(alone), atol=1e-5)


def test_cls_pooling_reads_the_learned_token_prepended_to_every_clip():
    import torch

    probe = _probe("cls")
    features = _features(2)
    mask = torch.tensor([[True, False], [True, True]])
    with torch.no_grad():
        logits = probe(features, mask)
        x, valid = probe.sequence(features, mask)
        x = torch.cat([probe.cls.expand(2, -1, -1), x], dim=1)
        valid = torch.cat([torch.ones(2, 1, dtype=torch.bool), valid], dim=1)
        h = probe.encoder(x, src_key_padding_mask=~valid)
        assert torch.allclose(logits, probe.head(h[:, 0]), atol=1e-6)
        alone = probe({"body": features["body"][:1, :1]}, torch.ones(1, 1, dtype=torch.bool))
    assert logits.shape == (2, 3) and torch.allclose(logits[:1], alone, atol=1e-5)


def test_the_bootstrap_interval_is_the_same_with_the_default_seed_and_seed_0():
    from m3t.slr.evaluate import Score, bootstrap_ci

    hits = (np.arange(97) % 7 < 3).astype(float)  # 42 hits in 97 clips: many distinct resampled means
    assert bootstrap_ci(hits, 50) == bootstrap_ci(hits, 50, seed=0)
    assert bootstrap_ci(hits, 50, seed=0) != bootstrap_ci(hits, 50, seed=1)  # the seed is really used
    score = Score.of(hits, 50.0, 50, 0.95, 0)
    assert (score.ci_low, score.ci_high) == bootstrap_ci(hits, 50) and score.value == pytest.approx(100 * 42 / 97)


def test_evaluations_come_back_from_a_runs_flat_metrics_with_every_count():
    from m3t.slr.evaluate import evaluations_from_flat

    flat = {"full/overall/top1": 50.0, "full/overall/top1_ci_low": 40.0, "full/overall/top1_ci_high": 60.0,
            "full/overall/top1_chance": 25.0, "full/overall/top5": 90.0, "full/overall/clips": 12.0,
            "full/overall/classes": 4.0,
            "full/confusing/top1": 30.0, "full/confusing/clips": 6.0, "full/confusing/classes": 4.0,
            "full/confusing/pair_top1": 70.0, "full/confusing/pair_clips": 6.0,
            "full/normal/top1": 70.0, "full/normal/clips": 6.0, "full/normal/classes": 4.0,
            "clips": 12.0}  # a key that is not <variant>/<subset>/<key> is not a score
    ev = evaluations_from_flat(flat)["full"]
    overall, confusing = ev.scores["overall"], ev.scores["confusing"]
    assert (overall.clips, overall.classes, overall.top1.value, overall.top1.ci_low, overall.top1.chance) == \
        (12, 4, 50.0, 40.0, 25.0)
    assert overall.top5.value == 90.0 and np.isnan(overall.top5.ci_low) and overall.pair_top1 is None
    assert confusing.pair_top1.value == 70.0 and confusing.pair_clips == 6 and overall.pair_clips == 0
    assert ev.subsets_available and set(ev.scores) == {"overall", "confusing", "normal"}


@pytest.mark.parametrize("corpus", [None, "other"], ids=["configured", "named"])
def test_train_and_log_trains_the_named_corpus_and_logs_curves_report_and_files(monkeypatch, tmp_path, corpus):
    """train-slr's MLflow wrapper: the corpus it is given (else ``slr.corpus``) is trained, tagged and names the
    run; every variant's epoch records become ``<variant>/<metric>`` curves; the dev confusion pictures are logged
    in name order after metrics.json and skipped.jsonl."""
    import dataclasses
    from contextlib import contextmanager
    from types import SimpleNamespace

    from m3t.body.config import BodyConfig
    from m3t.experiment import ExperimentConfig
    from m3t.shards.folders import DataConfig
    from m3t.slr import pipeline
    from m3t.slr.config import SLRConfig, SLRTrainConfig

    opened, trained = [], []

    @contextmanager
    def fake_start_run(experiment, stage, tags=None, variant=None):
        run = RecordingRun()
        opened.append(SimpleNamespace(stage=stage, tags=tags, variant=variant, run=run))
        yield run

    def fake_train(cfg, train_cfg, body, data, corpus, on_epoch=None, progress=True):
        trained.append((corpus, body, progress))
        on_epoch("full", {"train_loss": 2.0}, 3)
        return {"full/top1": 0.5}

    monkeypatch.setattr(pipeline, "start_run", fake_start_run)
    monkeypatch.setattr(pipeline, "run_train_slr", fake_train)
    monkeypatch.setattr(pipeline, "load_body_model", lambda cfg: "body")
    data = DataConfig(models_dir=str(tmp_path))
    data.slr_dir.mkdir(parents=True)
    for name in ("confusion_dev_b.png", "confusion_dev_a.png", "confusion_test_a.png"):
        (data.slr_dir / name).write_bytes(b"")
    cfg, train_cfg, body_cfg = SLRConfig(corpus="synthetic"), SLRTrainConfig(seed=5), BodyConfig()
    report = pipeline.train_and_log(cfg, train_cfg, body_cfg, data, ExperimentConfig(), corpus, progress=False)
    expected = corpus or "synthetic"
    assert report == {"full/top1": 0.5} and trained == [(expected, "body", False)]
    [run] = opened
    assert (run.stage, run.variant) == ("train-slr", expected)
    assert run.tags == {"corpus": expected, "variants": ",".join(train_cfg.variants), "body_model": body_cfg.model,
                        "seed": "5"}
    assert run.run.params["slr.corpus"] == "synthetic" and "slr_train.seed" in run.run.params
    assert "data.models_dir" in run.run.params
    assert run.run.metrics == [({"full/train_loss": 2.0}, 3), ({"full/top1": 0.5}, None)]
    assert run.run.artifacts == [(data.slr_dir / "metrics.json", None), (data.slr_dir / "skipped.jsonl", None),
                                 (data.slr_dir / "confusion_dev_a.png", None),
                                 (data.slr_dir / "confusion_dev_b.png", None)]
    untrimmed = dataclasses.replace(cfg, trim=dataclasses.replace(cfg.trim, enabled=False))
    pipeline.train_and_log(untrimmed, train_cfg, body_cfg, data, ExperimentConfig(), corpus, progress=True)
    assert trained[-1] == (expected, None, True)  # no body model without trimming
