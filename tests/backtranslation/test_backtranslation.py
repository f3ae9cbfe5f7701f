"""Back-translation: overfitting tiny clips to exact text (greedy and beam), the 240-d SignSparK input, checkpoints,
exact resume, Chinese and pseudo-gloss text processing, and the pipeline's training and scoring (empty generations
scored, unknown languages refused)."""
from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest
import torch
from float_order import assert_close_json, assert_close_numbers, assert_close_weights

from m3t.backtranslation.checkpoint import load_backtranslation
from m3t.backtranslation.config import BackTranslationConfig, BackTranslationTrainConfig
from m3t.backtranslation.data import InputSpec, language_corpus
from m3t.backtranslation.decode import translate
from m3t.backtranslation.pipeline import (
    backtranslate,
    run_evaluate_backtranslation,
    run_train_backtranslation,
    train_and_log,
)
from m3t.backtranslation.smplx240 import SMPLX240_DIM, to_smplx240
from m3t.backtranslation.text import PseudoGlosser, TextProcessor
from m3t.backtranslation.train import train_backtranslation
from m3t.body.anny_body import BODY_BONES, hand_bones
from m3t.body.protocol import Modality, ModalityLayout
from m3t.body.rotations import matrix_to_6d
from m3t.body.smplfx_build import BODY_POSE_JOINTS, hand_joint_names
from m3t.corpora.clip import Clip
from m3t.experiment import ExperimentConfig
from m3t.metrics.text import slt_translation_metrics
from m3t.shards.folders import DataConfig
from m3t.shards.io import write_shard
from m3t.shards.schema import FittedClip

# a small layout whose streams are declared out of STREAM_ORDER (the input must follow STREAM_ORDER)
LAYOUT = ModalityLayout((Modality("face", "scalar", ("a", "b", "c")), Modality("body", "rotation6d", ("j0", "j1")),
                         Modality("left_hand", "rotation6d", ("l0",)), Modality("right_hand", "rotation6d", ("r0",))),
                        ("beta0",))
TEXTS = {"ASL-SYN": ["The friend buys a red car.", "My father drinks water", "the child reads the book today",
                     "we eat bread"],
         "CSL-SYN": ["我的朋友买车。", "老师今天读书。", "我们吃面包。"]}
TINY = BackTranslationConfig(d_model=32, encoder_layers=1, decoder_layers=1, attention_heads=2, ffn_dim=64,
                             dropout=0.0, max_text_tokens=12)
FAST = BackTranslationTrainConfig(epochs=60, batch_size=4, lr=3e-3, weight_decay=0.0, label_smoothing=0.0,
                                  eval_every=20, device="cpu")


def fitted(split: str, language: str = "ASL-SYN", seed: int = 0, label: int | None = None,
           texts: list[str] | None = None) -> list[FittedClip]:
    """One clip per sentence of ``language``: random parameters of 8..13 frames, glosses on every other clip."""
    rng = np.random.default_rng(seed)
    out = []
    for i, text in enumerate(texts or TEXTS[language]):
        frames = int(rng.integers(8, 14))
        params = {m.name: rng.normal(size=(frames, m.dim)).astype(np.float32) for m in LAYOUT.modalities}
        gloss = " ".join(w.upper() for w in text.split()[:2]) if i % 2 and language == "ASL-SYN" else ""
        clip = Clip(f"{language.lower()}-{split}{i}", "fake", split, language, "s0", text, gloss, "m", 25.0, label)
        out.append(FittedClip(clip, "k", params, np.zeros(1, np.float32), {}, {}, "fake"))
    return out


@pytest.fixture(scope="module")
def spec() -> InputSpec:
    return InputSpec.from_layout("model", LAYOUT, "fake")


@pytest.fixture(scope="module")
def trained(spec, tmp_path_factory):
    """The tiny model overfitted on four English clips (dev = train)."""
    clips = fitted("train")
    corpus = language_corpus("ASL-SYN", clips, clips, spec, TINY)
    path = tmp_path_factory.mktemp("bt") / "asl.pt"
    return corpus, train_backtranslation(TINY, FAST, corpus, spec, "v", path, progress=False)


def test_input_follows_stream_order_and_names_bad_clips(spec):
    assert [n for n, _ in spec.streams] == ["body", "left_hand", "right_hand", "face"] and spec.dim == 27
    params = fitted("train")[0].params
    x = spec.features(params, "c0")
    assert np.array_equal(x[:, :12], params["body"]) and np.array_equal(x[:, -3:], params["face"])
    with pytest.raises(ValueError, match="clip 'c9': no 'face' parameters"):
        spec.features({k: v for k, v in params.items() if k != "face"}, "c9")
    with pytest.raises(ValueError, match="clip 'c9', modality 'body': shape"):
        spec.features({**params, "body": params["body"][:, :6]}, "c9")


@pytest.mark.slow
def test_overfits_tiny_clips_to_exact_text(trained):
    corpus, result = trained
    frames = [s.frames for s in corpus.train]
    expected = ["the friend buys a red car .", "my father drinks water", "the child reads the book today",
                "we eat bread"]
    assert [s.reference for s in corpus.train] == expected
    assert translate(result.model, corpus.text_vocab, corpus.processor, frames) == expected
    assert translate(result.model, corpus.text_vocab, corpus.processor, frames, beam_size=3) == expected
    assert result.best["val_bleu4"] == pytest.approx(100.0) and result.best["val_rouge_l"] == pytest.approx(100.0)
    assert "train_gloss_ctc_loss" in result.history[-1]  # glosses on two of the clips: the CTC head trains
    assert corpus.gloss_source.startswith("annotated (2 clips), ")  # the others: pseudo-glosses


@pytest.mark.slow
def test_checkpoint_rebuilds_model_vocabulary_and_layout(trained, tmp_path):
    corpus, result = trained
    loaded = load_backtranslation(result.best_path)  # read with weights_only=True
    assert loaded.language == "ASL-SYN" and loaded.spec == InputSpec.from_layout("model", LAYOUT, "fake")
    assert loaded.text_vocab.itos == corpus.text_vocab.itos and loaded.gloss_vocab.itos == corpus.gloss_vocab.itos
    assert loaded.processor == corpus.processor and loaded.epoch == result.best["epoch"]
    torch.load(result.best_path, weights_only=True)
    frames = [s.frames for s in corpus.train]
    assert translate(loaded.model, loaded.text_vocab, loaded.processor, frames) == \
        translate(result.model, corpus.text_vocab, corpus.processor, frames)
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable back-translation checkpoint"):
        load_backtranslation(tmp_path / "junk.pt")
    torch.save({"format": "m3t-smlm-v1"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="expected 'm3t-backtranslation-v1'"):
        load_backtranslation(tmp_path / "other.pt")
    with pytest.raises(FileNotFoundError, match="dvc repro train-backtranslation"):
        load_backtranslation(tmp_path / "missing.pt")


@pytest.mark.slow
def test_killed_training_resumes_on_the_same_loss_curve(spec, tmp_path):
    """Weights, Adam, the plateau schedule and the RNG come back from ``last``: 3 epochs, a stop, then the rest
    equal an uninterrupted run (dropout on, so the restored RNG matters)."""
    clips = fitted("train")
    corpus = language_corpus("ASL-SYN", clips, clips[:2], spec, TINY)
    model_cfg = dataclasses.replace(TINY, dropout=0.2)
    cfg = dataclasses.replace(FAST, epochs=6, eval_every=2, lr_patience=0, lr_factor=0.5, batch_size=2)
    straight = train_backtranslation(model_cfg, cfg, corpus, spec, "v", tmp_path / "a.pt", tmp_path / "a.last.pt",
                                     progress=False)
    part = train_backtranslation(model_cfg, cfg, corpus, spec, "v", tmp_path / "b.pt", tmp_path / "b.last.pt",
                                 progress=False, stop_after_epochs=3)
    assert len(part.history) == 3 and load_backtranslation(tmp_path / "b.last.pt").train_state["epoch"] == 3
    resumed = train_backtranslation(model_cfg, cfg, corpus, spec, "v", tmp_path / "b.pt", tmp_path / "b.last.pt",
                                    progress=False)
    assert resumed.resumed_from_epoch == 3 and len(resumed.history) == 6
    for key in ("train_loss", "lr", "val_bleu1", "val_rouge_l"):
        assert np.allclose([h.get(key, 0.0) for h in resumed.history], [h.get(key, 0.0) for h in straight.history],
                           rtol=1e-5, atol=1e-7), key
    for (name, a), b in zip(straight.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-6), name


def test_chinese_is_segmented_by_jieba_and_scored_per_character():
    processor = TextProcessor.for_language("CSL-SYN")
    assert processor.chinese and processor.tokens("我们 吃面包。") == ["我们", "吃", "面包", "。"]
    assert processor.reference("我们 吃面包。") == "我们吃面包。"
    english = TextProcessor.for_language("ASL")
    assert english.tokens("Don't buy 3.5 cars, friend!") == ["don't", "buy", "3.5", "cars", ",", "friend", "!"]
    out = slt_translation_metrics(["我们吃面包"], ["我们吃面包。"], "CSL-SYN")  # 5 of 6 characters, no 。
    assert out["bleu1"] == pytest.approx(100 * 5 * np.exp(1 - 6 / 5) / 5) and "word_bleu4" in out


def test_pseudo_glosses_keep_content_words():
    glosser = PseudoGlosser("ASL")
    if glosser.method.startswith("sign2gpt-pos"):  # a POS tagger is installed: lemmas of content words
        assert glosser("The men are buying new cars in the city.") == ["man", "buy", "new", "car", "city"]
        return
    assert glosser.method == "stop-word fallback (en; no POS tagger installed)"
    assert glosser("The men are buying new cars in the city.") == ["men", "buying", "new", "cars", "city"]
    assert glosser("I will not go there, she said.") == ["i", "go", "there", "she", "said"]
    assert PseudoGlosser("XYZ").method.startswith("all words")


def test_smplx240_takes_signspark_joints_in_their_order_as_row_6d():
    layout = ModalityLayout((Modality("body", "rotation6d", BODY_POSE_JOINTS),
                             Modality("left_hand", "rotation6d", hand_joint_names("left")),
                             Modality("right_hand", "rotation6d", hand_joint_names("right")),
                             Modality("face", "scalar", ("e0",))), ("beta0",))
    frames = 3
    params = {m.name: np.tile(np.array([1, 0, 0, 0, 1, 0], np.float32), (frames, m.dim // 6)) if m.kind == "rotation6d"
              else np.zeros((frames, m.dim), np.float32) for m in layout.modalities}
    angle = torch.tensor(0.4)
    rz = torch.tensor([[torch.cos(angle), -torch.sin(angle), 0], [torch.sin(angle), torch.cos(angle), 0], [0, 0, 1.0]])
    rx = torch.tensor([[1.0, 0, 0], [0, torch.cos(angle), -torch.sin(angle)], [0, torch.sin(angle), torch.cos(angle)]])
    rot = rz @ rx  # not symmetric: its row 6D and column 6D differ
    rows_6d = rot[:2, :].reshape(6).numpy()
    assert not np.allclose(rows_6d, matrix_to_6d(rot).numpy())
    params["body"][:, 6:12] = matrix_to_6d(rot).numpy()  # our body index 1 = "head"
    params["right_hand"][:, -6:] = matrix_to_6d(rot).numpy()  # right_thumb3
    x = to_smplx240(params, layout, "smplfx")
    assert x.shape == (frames, SMPLX240_DIM) == (frames, 240)
    # SignSparK body order: neck, left_collar, right_collar, head, ... -> the head is its 4th joint
    assert np.allclose(x[:, 18:24], rows_6d, atol=1e-6)
    assert np.allclose(x[:, 234:240], rows_6d, atol=1e-6)
    identity = np.array([1, 0, 0, 0, 1, 0], np.float32)
    untouched = np.delete(x, np.r_[18:24, 234:240], axis=1).reshape(frames, -1, 6)
    assert np.allclose(untouched, identity, atol=1e-6)
    assert to_smplx240({k: v[:0] for k, v in params.items()}, layout).shape == (0, 240)
    spec = InputSpec.from_layout("smplx240", layout, "smplfx")  # the face is not read: it may be absent
    assert spec.dim == 240 and np.array_equal(spec.features({k: v for k, v in params.items() if k != "face"}, "c"), x)


def test_smplx240_refuses_a_layout_without_smplx_joints():
    anny = ModalityLayout((Modality("body", "rotation6d", BODY_BONES),
                           Modality("left_hand", "rotation6d", hand_bones("L")),
                           Modality("right_hand", "rotation6d", hand_bones("R"))), ("p0",))
    with pytest.raises(ValueError, match=r"the anny body layout cannot give .* lacks the SMPL-X joints body: neck"):
        InputSpec.from_layout("smplx240", anny, "anny")


# ------------------------------------------------------------------------------------------------ pipeline
@pytest.fixture(scope="module")
def shards_data(tmp_path_factory) -> DataConfig:
    """Shards of corpus ``fake``: ASL-SYN and CSL-SYN sentences, and an isolated sign in every split."""
    root = tmp_path_factory.mktemp("bt-pipeline")
    (root / "shards" / "fake").mkdir(parents=True)
    for split, seed in (("train", 0), ("dev", 1), ("test", 2)):
        clips = fitted(split, "ASL-SYN", seed) + fitted(split, "CSL-SYN", seed)
        clips += fitted(split, "ISO-SYN", seed, label=0, texts=["friend"])
        write_shard(root / "shards" / "fake" / f"{split}.parquet", clips, LAYOUT)
    return DataConfig(train_corpora=("fake",), shards_root=str(root / "shards"), models_dir=str(root / "models"),
                      metrics_dir=str(root / "metrics"))


@pytest.fixture(scope="module")
def pipeline_models(shards_data, tmp_path_factory) -> dict:
    cfg = dataclasses.replace(FAST, epochs=4, eval_every=2, cache_dir=str(tmp_path_factory.mktemp("cache")))
    return train_and_log(TINY, cfg, shards_data, ExperimentConfig(enabled=False), progress=False)


def test_training_logs_its_files_params_curves_and_gloss_sources_to_mlflow(shards_data, tmp_path):
    from m3t.experiment import fetch_runs

    data = dataclasses.replace(shards_data, models_dir=str(tmp_path / "models"))
    experiment = ExperimentConfig(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}",
                                  artifact_dir=str(tmp_path / "mlruns"))
    cfg = dataclasses.replace(FAST, epochs=2, eval_every=1, cache_dir=str(tmp_path / "cache"))
    report = train_and_log(TINY, cfg, data, experiment, progress=False)
    run = fetch_runs(experiment, stage="train-backtranslation")[0]
    assert sorted(p.name for p in run.artifact_dir.iterdir()) == ["languages.json", "metrics.json", "skipped.jsonl"]
    described = json.loads((data.backtranslation_dir / "languages.json").read_text())
    assert {k: v for k, v in run.tags.items() if k.startswith("gloss_source/")} == {
        f"gloss_source/{lang}": d["gloss_source"] for lang, d in described.items()}
    assert (run.tags["corpus"], run.tags["input_layout"], run.tags["seed"]) == ("fake", TINY.input_layout, str(cfg.seed))
    assert run.metrics["ASL-SYN/train_clips"] == report["ASL-SYN/train_clips"] == 4
    assert run.metrics["ASL-SYN/best_epoch"] == report["ASL-SYN/best_epoch"] >= 1
    assert "ASL-SYN/train_loss" in run.metrics and "CSL-SYN/train_loss" in run.metrics  # the per-epoch records
    assert run.params["backtranslation.d_model"] == "32" and run.params["backtranslation_train.epochs"] == "2"


def test_the_gloss_source_names_each_source_with_its_clips_only_when_there_are_several(spec):
    clips = fitted("train")  # glosses annotated on every other clip; the rest get pseudo-glosses
    mixed = language_corpus("ASL-SYN", clips, [], spec, TINY)
    glosser = PseudoGlosser("ASL-SYN").method
    assert mixed.gloss_source == ", ".join(sorted(["annotated (2 clips)", f"{glosser} (2 clips)"]))
    annotated = language_corpus("ASL-SYN", clips, [], spec, dataclasses.replace(TINY, pseudo_glosses=False))
    assert annotated.gloss_source == ", ".join(sorted(["annotated (2 clips)", "none (2 clips)"]))
    only = language_corpus("ASL-SYN", [c for i, c in enumerate(clips) if i % 2], [], spec, TINY)
    assert only.gloss_source == "annotated"  # one source: its name alone
    assert language_corpus("ASL-SYN", clips, [], spec,
                           dataclasses.replace(TINY, gloss_ctc_weight=0.0)).gloss_source == "none"
    with pytest.raises(ValueError, match=r"backtranslation.gloss_ctc_weight: expected >= 0, got -1"):
        BackTranslationConfig(gloss_ctc_weight=-1)


def test_pipeline_trains_one_model_per_language(shards_data, pipeline_models):
    out = shards_data.backtranslation_dir
    assert sorted(p.name for p in out.glob("*.pt")) == ["ASL-SYN.pt", "CSL-SYN.pt"]
    assert pipeline_models["ASL-SYN/train_clips"] == 4 and pipeline_models["CSL-SYN/train_clips"] == 3
    described = json.loads((out / "languages.json").read_text())
    assert described["CSL-SYN"]["scoring"] == "slt, per char" and described["ASL-SYN"]["input"].startswith("model")
    skipped = [json.loads(line) for line in (out / "skipped.jsonl").read_text().splitlines()]
    assert {s["language"] for s in skipped} == {"ISO-SYN"} and "isolated sign" in skipped[0]["reason"]
    assert json.loads((out / "metrics.json").read_text()) == pytest.approx(pipeline_models)


@pytest.mark.slow
def test_languages_trained_in_worker_processes_equal_one_process_on_their_threads(shards_data, tmp_path):
    """``backtranslation_train.workers: 2`` trains ASL-SYN and CSL-SYN in two spawned processes of one thread each
    (this process has two): checkpoints, metrics.json, languages.json, skipped.jsonl and the per-epoch records
    are those of one process that trains the languages one after another on one thread, up to float rounding
    (:mod:`float_order`)."""
    from m3t.training_jobs import worker_split

    runs = {}
    for workers, threads in ((1, 1), (2, 2)):
        torch.set_num_threads(threads)  # conftest restores the count
        root = tmp_path / f"workers{workers}"
        data = dataclasses.replace(shards_data, models_dir=str(root / "models"))
        cfg = dataclasses.replace(FAST, epochs=4, eval_every=2, cache_dir=str(root / "cache"), workers=workers)
        assert worker_split(cfg.workers, 2, cfg.device) == ((1, 0) if workers == 1 else (2, 1))
        records: list = []
        report = run_train_backtranslation(TINY, cfg, data, progress=False, on_epoch=lambda language, record, epoch,
                                           out=records: out.append((language, epoch, record)))
        runs[workers] = (report, records, data.backtranslation_dir)
    (one, one_records, one_dir), (two, two_records, two_dir) = runs[1], runs[2]
    # equal up to float rounding (tests/float_order.py)
    assert_close_numbers(one, two, "report")
    assert_close_numbers(one_records, two_records, "records")
    assert len(one_records) == 2 * 4
    for name in ("metrics.json", "languages.json", "skipped.jsonl"):
        assert_close_json(one_dir / name, two_dir / name)
    for name in ("ASL-SYN.pt", "CSL-SYN.pt"):
        assert_close_weights(one_dir, two_dir, name)


def test_empty_generation_is_scored_zero_and_counted(shards_data, pipeline_models):
    clips = {c.clip.id: c for c in fitted("test", "ASL-SYN", 2) + fitted("test", "CSL-SYN", 2)}
    params = {cid: (c.clip.language, c.params) for cid, c in clips.items()}
    empty_id = "asl-syn-test0"
    params[empty_id] = ("ASL-SYN", {k: v[:0] for k, v in clips[empty_id].params.items()})
    report = backtranslate(shards_data.backtranslation_dir, params, {cid: c.clip.text for cid, c in clips.items()})
    row = next(r for r in report.per_clip if r["clip_id"] == empty_id)
    assert report.hypotheses[empty_id] == "" and row["frames"] == 0
    assert row["bleu1"] == row["bleu4"] == row["rouge_l"] == 0.0
    assert report.summary["slt/ASL-SYN/sentences"] == 4 and report.summary["slt/ASL-SYN/empty_generations"] == 1
    assert report.summary["slt/CSL-SYN/sentences"] == 3 and "slt/CSL-SYN/word_bleu4" in report.summary
    with pytest.raises(ValueError, match="clip 'x1': no back-translation model for language 'BSL'"):
        backtranslate(shards_data.backtranslation_dir, {"x1": ("BSL", clips[empty_id].params)}, {"x1": "hello"})
    with pytest.raises(ValueError, match="clip 'x2': empty reference sentence"):
        backtranslate(shards_data.backtranslation_dir, {"x2": ("ASL-SYN", clips[empty_id].params)}, {"x2": " "})


def test_ground_truth_upper_bound_is_written(shards_data, pipeline_models):
    report = run_evaluate_backtranslation(TINY, shards_data)
    out = shards_data.metrics("backtranslation")
    summary = json.loads((out / "metrics.json").read_text())
    assert summary["skipped_clips"] == 1 and summary["slt/ASL-SYN/sentences"] == 4
    rows = list(csv.DictReader((out / "per_clip.csv").open(encoding="utf-8")))
    assert len(rows) == 7 == len(report.per_clip) and rows[0]["reference"] == "the friend buys a red car ."


def test_missing_models_name_the_stage(tmp_path):
    with pytest.raises(FileNotFoundError, match="dvc repro train-backtranslation"):
        backtranslate(tmp_path, {"c": ("ASL", {})}, {"c": "hello"})


def test_smplx240_pipeline_refuses_the_fake_layout(shards_data, tmp_path):
    cfg = dataclasses.replace(FAST, epochs=1, cache_dir=str(tmp_path))
    with pytest.raises(ValueError, match="the fake body layout cannot give SignSparK's 240-d"):
        run_train_backtranslation(dataclasses.replace(TINY, input_layout="smplx240"), cfg, shards_data)


def test_bf16_autocast_trains_on_cpu(spec, tmp_path):
    """bf16 really runs the linear layers in bfloat16 (outputs seen by a forward hook), and its epoch loss is
    near the fp32 loss of the same seed but not bit-equal to it; a silently disabled autocast fails here."""
    from torch.nn.modules.module import register_module_forward_hook

    clips = fitted("train")
    corpus = language_corpus("ASL-SYN", clips, [], spec, TINY)
    losses = {}
    for precision in ("bf16", "fp32"):
        cfg = dataclasses.replace(FAST, epochs=1, precision=precision)
        dtypes = set()
        hook = register_module_forward_hook(
            lambda mod, args, out: dtypes.add(out.dtype) if isinstance(mod, torch.nn.Linear) else None)
        try:
            result = train_backtranslation(TINY, cfg, corpus, spec, "v", tmp_path / f"{precision}.pt", progress=False)
        finally:
            hook.remove()
        assert dtypes == {torch.bfloat16 if precision == "bf16" else torch.float32}, precision
        losses[precision] = result.history[-1]["train_loss"]
        assert np.isfinite(losses[precision]) and result.best["epoch"] == 1  # no dev: the last epoch
    assert losses["bf16"] != losses["fp32"]
    assert losses["bf16"] == pytest.approx(losses["fp32"], rel=0.05)


def test_bt_table_rows_ground_truth_then_variants_and_names_its_definition():
    from m3t.backtranslation.table import GT_ROW, backtranslation_table
    from m3t.experiment import RunRecord

    def run(stage, metrics, status="FINISHED", variant=None, start=0):
        return RunRecord(f"r{start}", stage, start, status, {}, metrics, None, {"variant": variant} if variant else {})

    gt = [run("evaluate-backtranslation", {"slt/ASL/bleu4": 11.5, "slt/ASL/rouge_l": 30.0, "slt/CSL/bleu4": 7.0,
                                           "slt/CSL/rouge_l": 27.0})]
    smlm = [run("evaluate-smlm", {"bt/slt/ASL/bleu4": 9.0, "bt/slt/ASL/rouge_l": 25.0}, variant="production + translation", start=3),
            run("evaluate-smlm", {"bt/slt/ASL/bleu4": 1.0}, variant="production + translation", start=2),  # older
            run("evaluate-smlm", {"bt/slt/ASL/bleu4": 5.0, "bt/slt/ASL/rouge_l": 20.0}, variant="production only", start=1),
            run("evaluate-smlm", {"dtw_jpe_body_m": 1.0}, variant="no judge", start=0)]  # no bt/ metrics: no row
    table = backtranslation_table(gt, smlm)
    assert "definition 'slt'" in table and "beta 1.2" in table
    assert "| motion | ASL R | ASL B4 | CSL R | CSL B4 |" in table  # ROUGE-L then BLEU-4 per language
    rows = [line for line in table.splitlines() if line.startswith("| ") and not line.startswith("| motion |")]
    assert [r.split(" | ")[0].strip("| ") for r in rows] == [GT_ROW, "SMLM, production only", "SMLM, production + translation"]
    assert rows[0].split(" | ")[1:] == ["30.00", "11.50", "27.00", "7.00 |"]
    assert rows[2].split(" | ")[1:3] == ["25.00", "9.00"] and rows[2].endswith("- | - |")  # newest run; no CSL
    assert "no finished" in backtranslation_table([], [])
