"""Recognition probe (M3T Sec. 3.4, App. 0.D.3) on a tiny synthetic isolated-sign corpus with tiny tokenizers:
frozen encoders, the face-less ablation, active-window trimming, overfitting, the paper's 26M parameters,
bootstrap intervals, bad clips, and the train-slr -> evaluate-slr runs end to end."""
from __future__ import annotations

import csv
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from m3t.body.protocol import STREAM_ORDER
from m3t.corpora.clip import Clip
from m3t.corpora.config import SyntheticCorpusConfig
from m3t.corpora.synthetic import generate_corpus
from m3t.experiment import RunRecord
from m3t.shards.folders import DataConfig
from m3t.shards.io import write_shard
from m3t.shards.schema import FittedClip
from m3t.slr.checkpoint import load_slr
from m3t.slr.config import SLRConfig, SLREvaluateConfig, SLRTrainConfig, TrimConfig
from m3t.slr.evaluate import bootstrap_ci, evaluate_logits
from m3t.slr.features import FrozenEncoders, build_examples, variant_streams
from m3t.slr.model import ProbeDims, SLRProbe, count_parameters
from m3t.slr.pipeline import run_evaluate_slr, run_train_slr
from m3t.slr.table import recognition_table, table_markdown
from m3t.slr.train import collate, train_slr, validation_metrics
from m3t.slr.checkpoint import ProbeMeta
from m3t.slr.trim import ClipTooShortError, HandActivityProbe, Trimmer, active_window
from m3t.tokenizers.checkpoint import save_tokenizer
from m3t.tokenizers.config import TokenizerConfig
from m3t.tokenizers.data import GROUPS, clip_sequences, normalisation
from m3t.tokenizers.vae import MotionTokenizer
from float_order import assert_close_json, assert_close_numbers, assert_close_weights

TINY_PROBE = SLRConfig(layers=1, heads=2, ffn_mult=2, dropout=0.0, max_steps=32,
                       trim=TrimConfig(margin=1, min_frames=8))
TINY_TRAIN = SLRTrainConfig(epochs=3, batch_size=8, lr=3e-3, device="cpu", workers=1)


@pytest.fixture(scope="module")
def corpus(body):
    """4 signs (one manual-identical pair) x 2 signers x 3 repetitions + 1 sentence, ground-truth motion."""
    cfg = SyntheticCorpusConfig(num_signs=4, confusing_pairs=1, num_signers=2, isolated_per_sign=3,
                                sentences_per_language=1, languages=("ASL-SYN",), frames_per_sign=8,
                                transition_frames=3, hold_frames=3)
    return generate_corpus(cfg, body)


def fitted(sc, body) -> FittedClip:
    return FittedClip(sc.clip, "k", sc.params, sc.identity, sc.camera.as_dict(), {}, body.name)


@pytest.fixture(scope="module")
def tokenizers(corpus) -> dict[str, MotionTokenizer]:
    torch.manual_seed(0)
    models = {}
    for group in GROUPS:
        seqs = [s for sc in corpus for s in clip_sequences(sc.params, group)]
        model = MotionTokenizer(TokenizerConfig(width=16, depth=1).vae_config(group, seqs[0].shape[1]))
        model.set_normalisation(*normalisation(seqs))
        models[group] = model.eval()
    return models


@pytest.fixture(scope="module")
def data(corpus, tokenizers, body, tmp_path_factory) -> DataConfig:
    root = tmp_path_factory.mktemp("slr")
    (root / "shards" / "synthetic").mkdir(parents=True)
    for split in ("train", "dev", "test"):
        write_shard(root / "shards" / "synthetic" / f"{split}.parquet",
                    [fitted(sc, body) for sc in corpus if sc.clip.split == split], body.layout)
    for group, model in tokenizers.items():
        save_tokenizer(root / "models" / "tokenizers" / f"{group}.pt", model, group, 1, 1, "v", {})
    return DataConfig(shards_root=str(root / "shards"), models_dir=str(root / "models"),
                      metrics_dir=str(root / "metrics"))


def isolated(corpus, split: str | None = None):
    return [sc for sc in corpus if sc.clip.label is not None and (split is None or sc.clip.split == split)]


# ----------------------------------------------------------------------------------------- probe
def test_probe_at_paper_width_has_26m_parameters():
    """App. 0.D.3: 3 layers, 4 heads, width 1024 on NMFs-CSL's 1067 classes: "26M parameters"."""
    probe = SLRProbe(SLRConfig(), ProbeDims(1024, 1067, STREAM_ORDER))
    assert abs(count_parameters(probe) - 26e6) / 26e6 < 0.05, count_parameters(probe)
    wide_ffn = SLRProbe(SLRConfig(ffn_mult=4), ProbeDims(1024, 1067, STREAM_ORDER))
    assert count_parameters(wide_ffn) > 1.4 * 26e6  # the FFN of 4W is not the paper's probe


def test_gradients_never_reach_the_frozen_encoders(corpus, tokenizers):
    encoders = FrozenEncoders(tokenizers)
    before = {k: v.clone() for k, v in encoders.state_dict().items()}
    encoders.train()
    assert not encoders.training and not any(m.training for m in encoders.modules())
    assert not any(p.requires_grad for p in encoders.parameters())
    sc = isolated(corpus)[0]
    feats = encoders(sc.params, STREAM_ORDER, sc.clip.id)
    assert all(not f.requires_grad for f in feats.values())
    probe = SLRProbe(TINY_PROBE, ProbeDims(encoders.width, 4, STREAM_ORDER))
    optim = torch.optim.Adam(probe.parameters(), lr=1e-2)
    for _ in range(3):
        logits = probe({k: v[None] for k, v in feats.items()}, torch.ones(1, feats["body"].shape[0], dtype=torch.bool))
        loss = F.cross_entropy(logits, torch.tensor([1]))
        optim.zero_grad()
        loss.backward()
        optim.step()
    assert all(p.grad is None for p in encoders.parameters())
    assert all(torch.equal(before[k], v) for k, v in encoders.state_dict().items())


def test_face_less_probe_really_removes_the_face(corpus, tokenizers, monkeypatch):
    encoders = FrozenEncoders(tokenizers)
    sc = isolated(corpus)[0]

    def untouchable(*args, **kwargs):
        raise AssertionError("the face encoder ran for the face-less probe")

    monkeypatch.setattr(encoders.tokenizers["face"], "hidden", untouchable)  # restored after the test
    feats = encoders(sc.params, variant_streams("no_face"), sc.clip.id)
    assert list(feats) == ["body", "left_hand", "right_hand"]
    steps = feats["body"].shape[0]
    batch = {k: v[None] for k, v in feats.items()}
    mask = torch.ones(1, steps, dtype=torch.bool)
    no_face = SLRProbe(TINY_PROBE, ProbeDims(encoders.width, 4, variant_streams("no_face")))
    full = SLRProbe(TINY_PROBE, ProbeDims(encoders.width, 4, STREAM_ORDER))
    x, valid = no_face.sequence(batch, mask)
    assert x.shape == (1, 3 * steps, encoders.width) and valid.shape == (1, 3 * steps)
    assert torch.isfinite(no_face({**batch, "face": torch.full_like(batch["body"], float("nan"))}, mask)).all()
    with pytest.raises(KeyError, match="face"):
        full(batch, mask)
    assert full.sequence({**batch, "face": batch["body"]}, mask)[0].shape[1] == 4 * steps


def test_interleaving_follows_the_stream_order():
    probe = SLRProbe(TINY_PROBE, ProbeDims(8, 3, STREAM_ORDER))
    with torch.no_grad():
        probe.modality.zero_()
        probe.position.zero_()
    feats = {s: torch.full((1, 2, 8), float(i)) for i, s in enumerate(STREAM_ORDER)}
    x, _ = probe.sequence(feats, torch.ones(1, 2, dtype=torch.bool))
    assert x[0, :, 0].tolist() == [0, 1, 2, 3, 0, 1, 2, 3]  # {body, left, right, face} per time step


# ----------------------------------------------------------------------------------------- trimming
@pytest.mark.slow
@pytest.mark.parametrize("reference", ["clip_rest", "body_rest"])
def test_trimming_cuts_exactly_the_rest_frames(corpus, body, reference):
    sc = isolated(corpus)[0]
    sign = {k: np.repeat(v[len(v) // 2][None], 12, axis=0) for k, v in sc.params.items()}  # hands raised
    if reference == "body_rest":
        rest = {k: v[0].numpy()[None] for k, v in body.rest_params(1).items()}
    else:
        rest = {k: v[:1] for k, v in sc.params.items()}  # the signer's own resting posture
    params = {k: np.concatenate([np.repeat(rest[k], 5, 0), sign[k], np.repeat(rest[k], 7, 0)]) for k in sign}
    cfg = TrimConfig(reference=reference, margin=0, min_frames=4)
    kept, window = Trimmer(body, cfg)(params, sc.identity, "clip")
    assert (window.start, window.end, window.frames) == (5, 17, 24)
    assert kept["face"].shape[0] == 12 and np.isclose(window.trimmed_share, 12 / 24)
    activity = HandActivityProbe(body).activity(params, sc.identity, cfg)
    assert activity.active.tolist() == [False] * 5 + [True] * 12 + [False] * 7


def test_trimming_keeps_a_minimum_and_names_too_short_clips(corpus, tokenizers, body):
    cfg = TrimConfig(margin=0, min_frames=8)
    active = np.zeros(20, dtype=bool)
    active[10:12] = True
    window = active_window(active, cfg)
    assert window.kept == 8 and window.start <= 10 and window.end >= 12
    assert active_window(np.zeros(20, dtype=bool), cfg).kept == 20  # nothing active: the clip stays whole
    sc = isolated(corpus)[0]
    short = dataclasses.replace(fitted(sc, body), clip=dataclasses.replace(sc.clip, id="tiny-clip"),
                                params={k: v[:5] for k, v in sc.params.items()})
    trimmer = Trimmer(body, cfg)
    with pytest.raises(ClipTooShortError, match="tiny-clip"):
        trimmer(short.params, short.identity, short.clip.id)
    encoders = FrozenEncoders(tokenizers)
    with pytest.raises(ClipTooShortError, match="tiny-clip"):
        build_examples([short], {sc.clip.label: 0}, trimmer, encoders, STREAM_ORDER, 32)
    skipped: list[dict] = []
    assert build_examples([short], {sc.clip.label: 0}, trimmer, encoders, STREAM_ORDER, 32, bad_clips="skip",
                          skipped=skipped) == []
    assert skipped[0]["clip_id"] == "tiny-clip" and "min_frames" in skipped[0]["reason"]


# ----------------------------------------------------------------------------------------- training
def test_probe_overfits_a_few_labelled_clips(corpus, tokenizers, body, tmp_path):
    clips = [fitted(sc, body) for sc in isolated(corpus, "train")][:8]
    labels = sorted({c.clip.label for c in clips})
    index = {label: i for i, label in enumerate(labels)}
    encoders = FrozenEncoders(tokenizers)
    examples = build_examples(clips, index, Trimmer(body, TINY_PROBE.trim), encoders, STREAM_ORDER, 32)
    meta = ProbeMeta("full", tuple(labels), tuple(str(label) for label in labels), {})
    cfg = dataclasses.replace(TINY_TRAIN, epochs=60, batch_size=4, label_smoothing=0.0)
    result = train_slr(TINY_PROBE, cfg, meta, encoders.width, examples, examples, "v", tmp_path / "best.pt",
                       progress=False)
    assert result.best["val_top1"] == 100.0, result.best
    assert result.history[-1]["train_loss"] < result.history[0]["train_loss"] / 5
    loaded = load_slr(tmp_path / "best.pt")
    assert validation_metrics(loaded.model, examples, 8, "fp32", 0.0)["top1"] == 100.0
    batch = collate(examples[:2], STREAM_ORDER)
    assert batch.mask.sum(1).tolist() == [e.steps for e in examples[:2]]


def test_resumed_training_continues_the_same_curve(corpus, tokenizers, body, tmp_path):
    clips = [fitted(sc, body) for sc in isolated(corpus, "train")]
    labels = sorted({c.clip.label for c in clips})
    examples = build_examples(clips, {label: i for i, label in enumerate(labels)}, Trimmer(body, TINY_PROBE.trim),
                              FrozenEncoders(tokenizers), variant_streams("no_face"), 32)
    meta = ProbeMeta("no_face", tuple(labels), tuple(map(str, labels)), {})
    cfg = dataclasses.replace(TINY_TRAIN, epochs=4)
    dev = examples[:3]

    def run(folder: Path, **kw):
        return train_slr(TINY_PROBE, cfg, meta, 16, examples, dev, "v", folder / "best.pt", folder / "last.pt",
                         progress=False, **kw)

    straight = run(tmp_path / "a")
    assert len(run(tmp_path / "b", stop_after_epochs=2).history) == 2
    resumed = run(tmp_path / "b")
    assert resumed.resumed_from_epoch == 2
    curve = lambda r: [h["train_loss"] for h in r.history]  # noqa: E731
    assert np.allclose(curve(resumed), curve(straight), rtol=1e-5, atol=1e-7)
    assert load_slr(tmp_path / "b" / "best.pt").model.dims.streams == STREAM_ORDER[:3]


# ----------------------------------------------------------------------------------------- scoring
def test_bootstrap_interval_contains_the_estimate_and_narrows_with_more_clips():
    rng = np.random.default_rng(0)
    few, many = rng.random(20) < 0.7, rng.random(2000) < 0.7
    lo_few, hi_few = bootstrap_ci(few, 1000, 0.95, seed=0)
    lo_many, hi_many = bootstrap_ci(many, 1000, 0.95, seed=0)
    assert lo_few <= 100 * few.mean() <= hi_few and lo_many <= 100 * many.mean() <= hi_many
    assert (hi_many - lo_many) < (hi_few - lo_few) / 5  # ~ 1 / sqrt(100)
    assert bootstrap_ci(few, 1000, 0.95, seed=0) == (lo_few, hi_few)  # seeded
    assert bootstrap_ci(few, 1000, 0.5, seed=0)[1] - bootstrap_ci(few, 1000, 0.5, seed=0)[0] < hi_few - lo_few
    assert bootstrap_ci(np.ones(10, dtype=bool)) == (100.0, 100.0)
    # coverage: the 95% interval of a 50-clip sample holds the true accuracy ~95% of the time
    covered = [lo <= 60.0 <= hi for lo, hi in (bootstrap_ci(rng.random(50) < 0.6, 400, 0.95, s) for s in range(200))]
    assert 0.88 <= np.mean(covered) <= 0.99


def test_subsets_without_group_info_are_reported_unavailable():
    clips = [Clip(f"c{i}", "x", "test", "CSL", "s", "t", "G", "m", 25.0, label=i % 3,
                  extra=(("subset", "unknown"),)) for i in range(6)]
    logits = torch.randn(6, 3)
    ev = evaluate_logits(logits, torch.tensor([c.label for c in clips]), clips, subset_hint="set the list")
    assert not ev.subsets_available and "6 of 6 clips" in ev.subsets_reason and "set the list" in ev.subsets_reason
    assert set(ev.scores) == {"overall"}
    table = table_markdown({"full": ev}, "x", "test")
    assert "n/a" in table and "Subsets unavailable" in table


def test_corpus_without_labelled_clips_is_refused(body, tmp_path):
    root = tmp_path / "shards" / "sentences"
    root.mkdir(parents=True)
    params = {k: v.numpy() for k, v in body.rest_params(12).items()}
    for split in ("train", "dev", "test"):
        clip = Clip(f"s-{split}", "sentences", split, "ASL", "s", "a sentence", "A B", "m", 25.0)
        write_shard(root / f"{split}.parquet", [FittedClip(clip, "k", params, body.default_identity().numpy(), {},
                                                           {}, body.name)], body.layout)
    data = DataConfig(shards_root=str(tmp_path / "shards"), models_dir=str(tmp_path / "models"))
    with pytest.raises(ValueError, match="no labelled"):
        run_train_slr(TINY_PROBE, dataclasses.replace(TINY_TRAIN, cache_dir=str(tmp_path / "cache")), body, data,
                      corpus="sentences", progress=False)


def test_variants_trained_in_worker_processes_equal_one_process_on_their_threads(data, body, tmp_path):
    """``slr_train.workers: 2`` trains the full and the face-less probe in two spawned processes of one thread
    each (this process has two): checkpoints, metrics.json and the per-epoch records are those of one process
    that trains the variants one after another on one thread, up to float rounding (:mod:`float_order`)."""
    from m3t.training_jobs import worker_split

    runs = {}
    for workers, threads in ((1, 1), (2, 2)):
        torch.set_num_threads(threads)  # conftest restores the count
        root = tmp_path / f"workers{workers}"
        where = dataclasses.replace(data, models_dir=str(root / "models"))
        shutil.copytree(Path(data.models_dir) / "tokenizers", Path(where.models_dir) / "tokenizers")
        cfg = dataclasses.replace(TINY_TRAIN, cache_dir=str(root / "cache"), workers=workers)
        assert worker_split(cfg.workers, 2, cfg.device) == ((1, 0) if workers == 1 else (2, 1))
        records: list = []
        report = run_train_slr(TINY_PROBE, cfg, body, where, progress=False, on_epoch=lambda variant, record, epoch,
                               out=records: out.append((variant, epoch, record)))
        runs[workers] = (report, records, Path(where.models_dir) / "slr")
    (one, one_records, one_dir), (two, two_records, two_dir) = runs[1], runs[2]
    # equal up to float rounding (tests/float_order.py): the features are computed here on 1 or 2 threads
    assert_close_numbers(one, two, "report")
    assert_close_numbers(one_records, two_records, "records")
    assert len(one_records) == 2 * TINY_TRAIN.epochs
    assert_close_json(one_dir / "metrics.json", two_dir / "metrics.json")
    for name in ("full.pt", "no_face.pt"):
        assert_close_weights(one_dir, two_dir, name)
    assert (two_dir / "confusion_dev_no_face.png").stat().st_size > 0  # drawn in the worker


# ----------------------------------------------------------------------------------------- end to end
def test_train_and_evaluate_write_tab4_outputs(data, corpus, tokenizers, body, tmp_path):
    train_cfg = dataclasses.replace(TINY_TRAIN, cache_dir=str(tmp_path / "cache"))
    report = run_train_slr(TINY_PROBE, train_cfg, body, data, progress=False)
    n_train, n_dev = len(isolated(corpus, "train")), len(isolated(corpus, "dev"))
    assert report["train_clips"] == n_train and report["dev_clips"] == n_dev and report["classes"] == 4
    assert 0.0 < report["trimmed_share"] < 0.6
    models = Path(data.models_dir) / "slr"
    for variant, streams in (("full", STREAM_ORDER), ("no_face", STREAM_ORDER[:3])):
        loaded = load_slr(models / f"{variant}.pt")
        assert loaded.model.dims.streams == streams and loaded.meta.classes == (0, 1, 2, 3)
        assert loaded.model.cfg.trim == TINY_PROBE.trim and set(loaded.meta.tokenizers) == set(GROUPS)
        assert (models / f"confusion_dev_{variant}.png").stat().st_size > 0
    assert json.loads((models / "metrics.json").read_text())["full/best_epoch"] >= 1

    result = run_evaluate_slr(SLREvaluateConfig(bootstrap=200, device="cpu"), body, data)
    out = data.metrics("slr")
    n_test = len(isolated(corpus, "test"))
    for variant in ("full", "no_face"):
        ev = result.evaluations[variant]
        assert ev.subsets_available and ev.scores["overall"].clips == n_test
        assert ev.scores["confusing"].clips + ev.scores["normal"].clips == n_test
        top1 = ev.scores["overall"].top1
        assert top1.ci_low <= top1.value <= top1.ci_high and top1.chance == 25.0
        assert ev.scores["confusing"].pair_top1 is not None  # the synthetic pairs give the 50%-chance score
    with open(out / "predictions.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * n_test and {r["variant"] for r in rows} == {"full", "no_face"}
    # the pair hit is scored on confusing clips only (the synthetic pairs hold every confusing target)
    assert {r["correct_pair"] for r in rows if r["subset"] == "confusing"} <= {"0", "1"}
    assert {r["correct_pair"] for r in rows if r["subset"] != "confusing"} == {""}
    assert sum(r["subset"] == "confusing" for r in rows) == 2 * result.evaluations["full"].scores["confusing"].clips
    assert (result.summary["clips"], result.summary["skipped"], result.summary["classes"]) == (n_test, 0.0, 4.0)
    from m3t.slr.evaluate import evaluations_from_flat

    again = evaluations_from_flat(result.summary)["full"].scores["confusing"]
    assert again.pair_clips == result.evaluations["full"].scores["confusing"].pair_clips > 0
    table = (out / "table.md").read_text()
    assert "w/o face" in table and "chance" in table and "Conf. T-1" in table
    with open(out / "table.csv", newline="") as fh:
        assert [r["variant"] for r in csv.DictReader(fh)] == ["full", "no_face"]
    assert json.loads((out / "metrics.json").read_text())["variants"]["full"]["subsets"]["available"]
    assert (out / "confusion_no_face.png").exists()
    record = RunRecord("r", "evaluate-slr", 0, "FINISHED", {"slr_evaluate.confidence": "0.95"}, result.summary, None,
                       {"corpus": "synthetic", "split": "test"})
    assert recognition_table([record]) == table  # the CLI's table from the MLflow run is the file's


@pytest.fixture(scope="module")
def data_copy(data, tmp_path_factory):
    """A copy of ``data``'s shards and tokenizers (the refusals below alter their files)."""
    root = tmp_path_factory.mktemp("slr-refusals")
    shutil.copytree(Path(data.shards_root), root / "shards")
    shutil.copytree(Path(data.models_dir) / "tokenizers", root / "models" / "tokenizers")
    return DataConfig(shards_root=str(root / "shards"), models_dir=str(root / "models"),
                      metrics_dir=str(root / "metrics"))


def test_evaluation_refuses_probes_of_another_corpus_tokenizers_or_label_set(data_copy, body, tokenizers, tmp_path):
    from m3t.slr.checkpoint import load_slr as load

    data = data_copy
    run_train_slr(TINY_PROBE, dataclasses.replace(TINY_TRAIN, epochs=1, cache_dir=str(tmp_path / "cache")), body,
                  data, progress=False)
    cfg = SLREvaluateConfig(bootstrap=10, device="cpu")
    with pytest.raises(ValueError, match=r"^the probes were trained on corpus 'synthetic', not 'other'; rerun "
                                         r"train-slr with slr.corpus: other$"):
        run_evaluate_slr(cfg, body, data, corpus="other")
    # two checkpoints that disagree: the no-face probe saved under the full probe's name
    full = Path(data.models_dir) / "slr" / "full.pt"
    kept = full.read_bytes()
    shutil.copy(Path(data.models_dir) / "slr" / "no_face.pt", full)
    with pytest.raises(ValueError, match=r"slr/full\.pt holds variant 'no_face', not 'full'$"):
        run_evaluate_slr(cfg, body, data)
    full.write_bytes(kept)
    assert load(full).meta.variant == "full"
    # other tokenizers than those the probes were trained on
    body_tokenizer = Path(data.tokenizers_dir) / "body.pt"
    kept = body_tokenizer.read_bytes()
    torch.manual_seed(5)
    other = MotionTokenizer(TokenizerConfig(width=16, depth=1).vae_config("body", tokenizers["body"].cfg.input_dim))
    save_tokenizer(body_tokenizer, other.eval(), "body", 1, 1, "v", {})
    with pytest.raises(ValueError, match=r"are not those the probes were trained on \(digests differ\); rerun "
                                         r"train-slr$"):
        run_evaluate_slr(cfg, body, data)
    body_tokenizer.write_bytes(kept)
    # test clips whose labels the probes never saw
    test_shard = data.shards_dir("synthetic") / "test.parquet"
    kept = test_shard.read_bytes()
    from m3t.shards.io import read_shard

    shard = read_shard(test_shard)
    relabelled = [dataclasses.replace(f, clip=dataclasses.replace(f.clip, label=(f.clip.label + 40)))
                  for f in shard.clips if f.clip.label is not None]
    write_shard(test_shard, relabelled, body.layout)
    with pytest.raises(ValueError, match=r"^test clips of corpus 'synthetic' have labels \[40, 41, 42, 43\] the "
                                         r"probes were not trained with; rerun train-slr$"):
        run_evaluate_slr(cfg, body, data)
    test_shard.write_bytes(kept)
    assert run_evaluate_slr(cfg, body, data).summary["clips"] == len([f for f in shard.clips if f.clip.label is not None])


def test_evaluation_encodes_a_batch_at_a_time_and_scores_as_the_whole_split(corpus, tokenizers, body):
    """iter_examples reads a clip only once the example before it is taken; logits of batches drawn from it, with
    their features let go, equal the logits of the whole split held (one process: the same batches)."""
    from m3t.slr.features import example_batches, iter_examples, without_features
    from m3t.slr.train import predict_logits

    clips = [fitted(sc, body) for sc in isolated(corpus)]
    short = dataclasses.replace(clips[1], clip=dataclasses.replace(clips[1].clip, id="too-short"),
                                params={k: v[:5] for k, v in clips[1].params.items()})
    clips.insert(2, short)  # skipped: the batches after it are cut from the kept examples, as the held list is
    labels = sorted({c.clip.label for c in clips})
    index = {label: i for i, label in enumerate(labels)}
    encoders, trimmer = FrozenEncoders(tokenizers), Trimmer(body, TINY_PROBE.trim)
    probe = SLRProbe(TINY_PROBE, ProbeDims(encoders.width, len(labels), STREAM_ORDER))
    pulled = []

    def source():
        for c in clips:
            pulled.append(c.clip.id)
            yield c

    held = build_examples(clips, index, trimmer, encoders, STREAM_ORDER, 32, bad_clips="skip", skipped=[])
    stream = iter_examples(source(), index, trimmer, encoders, STREAM_ORDER, 32, bad_clips="skip", skipped=[])
    assert pulled == [] and next(stream).clip.id == clips[0].clip.id and pulled == [clips[0].clip.id]
    assert next(stream).clip.id == clips[1].clip.id and len(pulled) == 2
    logits, kept = [], []
    for batch in example_batches(iter_examples(iter(clips), index, trimmer, encoders, STREAM_ORDER, 32,
                                               bad_clips="skip", skipped=[]), 4):
        logits.append(predict_logits(probe, batch, 4))
        kept += [without_features(e) for e in batch]
    assert [len(x) for x in logits] == [4] * (len(held) // 4) + ([len(held) % 4] if len(held) % 4 else [])
    assert torch.equal(torch.cat(logits), predict_logits(probe, held, 4))
    assert [(e.clip.id, e.target, e.window) for e in kept] == [(e.clip.id, e.target, e.window) for e in held]
    assert "too-short" not in [e.clip.id for e in kept] and all(e.features == {} for e in kept)
