"""The back-translation judge's training target and batches (:mod:`m3t.backtranslation.data`), on hand-made
samples: the decoder reads BOS then the sentence and is taught the sentence then EOS (padding ignored by the
loss), frames are zero-padded with a mask, features normalised by the train split's statistics, and which clips
can be examples at all. Written to pin behaviours that mutation testing found unchecked."""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from m3t.backtranslation.data import (
    IGNORE,
    Sample,
    collate,
    feature_statistics,
    pad_frames,
    skip_reason,
)
from m3t.vocabulary import BOS, EOS, PAD, text_vocabulary


def sample(clip_id: str, frames: np.ndarray, text: tuple[int, ...], glosses: tuple[int, ...] = ()) -> Sample:
    return Sample(clip_id, frames.astype(np.float32), text, glosses, "ref")


def test_the_decoder_reads_bos_and_the_sentence_and_learns_the_sentence_and_eos():
    vocab = text_vocabulary([["hello", "world", "again"]])
    assert [vocab.stoi[t] for t in (PAD, BOS, EOS)] == [0, 2, 3]
    hello, world, again = vocab.encode(["hello", "world", "again"])
    batch = collate([sample("a", np.ones((2, 3)), (hello, world, again), (1, 2)),
                     sample("b", np.full((4, 3), 2.0), (world,))], vocab)
    assert batch.text_in.tolist() == [[2, hello, world, again], [2, world, 0, 0]]  # BOS + ids, PAD after
    assert batch.text_out.tolist() == [[hello, world, again, 3], [world, 3, IGNORE, IGNORE]]  # ids + EOS
    assert IGNORE == -100  # what torch's cross-entropy skips by default
    assert batch.frames.shape == (2, 4, 3) and batch.frame_mask.tolist() == [[True, True, False, False], [True] * 4]
    assert batch.frames[0, 2:].abs().sum() == 0 and batch.frames[1, 3, 0] == 2.0
    assert batch.glosses.tolist() == [[1, 2], [0, 0]] and batch.gloss_lengths.tolist() == [2, 0]


def test_pad_frames_zero_pads_to_the_longest_clip():
    frames, mask = pad_frames([np.arange(6, dtype=np.float32).reshape(3, 2), np.full((1, 2), 7.0, np.float32)])
    assert frames.tolist() == [[[0, 1], [2, 3], [4, 5]], [[7, 7], [0, 0], [0, 0]]]
    assert mask.tolist() == [[True] * 3, [True, False, False]] and mask.dtype == torch.bool


def test_feature_statistics_are_over_every_training_frame_with_a_floored_std():
    a = sample("a", np.array([[0.0, 5.0], [2.0, 5.0]]), (4,))
    b = sample("b", np.array([[4.0, 5.0]]), (4,))
    mean, std = feature_statistics([a, b])
    # column 0: frames 0, 2, 4 -> mean 2, population std sqrt(8 / 3); column 1 constant: std floored at 1e-3
    assert mean.tolist() == pytest.approx([2.0, 5.0]) and std == pytest.approx([np.sqrt(8 / 3), 1e-3], rel=1e-6)
    assert mean.dtype == np.float32 and std.dtype == np.float32


def test_only_sentence_clips_with_text_and_frames_are_examples():
    def clip(label=None, text="a sentence"):
        return SimpleNamespace(label=label, text=text)

    assert skip_reason(clip(), 10) is None
    assert skip_reason(clip(label=3), 10) == "isolated sign (label 3): back-translation is sentence-level"
    assert skip_reason(clip(label=0), 10).startswith("isolated sign (label 0)")  # label 0 is a label too
    assert skip_reason(clip(text="   "), 10) == "empty text"
    assert skip_reason(clip(), 0) == "no frames"


# ------------------------------------------------------------------------------------------ M3T Tab. 2 table
def test_bt_table_is_written_exactly_with_unknown_variants_after_the_known_ones_by_name():
    """The whole Markdown text: the title naming the definition, a blank line, the header ``R`` / ``B4`` per
    language (sorted), the ground truth first, then the known variants in their order, then unknown variants
    alphabetically; only ``bt/slt/`` metrics of a production run count (others, e.g. ``bt/other/``, are not
    cells), two decimals, ``-`` where a language is missing. A failed ground-truth run is no row."""
    from m3t.backtranslation.table import backtranslation_table
    from m3t.experiment import RunRecord

    def run(metrics, variant=None, status="FINISHED", start=0):
        return RunRecord(f"run{start:05d}xyz", "s", start, status, {}, metrics, None,
                         {"variant": variant} if variant else {})

    gt = [run({"slt/DGS/bleu4": 1.234, "slt/DGS/rouge_l": 2.0}, status="FAILED", start=9),
          run({"slt/DGS/bleu4": 1.0, "slt/DGS/rouge_l": 2.0, "slt/ASL/bleu4": 3.0})]
    production = [run({"bt/slt/ASL/bleu4": 4.0, "bt/slt/ASL/rouge_l": 5.0}, "zeta", start=5),
                  run({"bt/slt/ASL/bleu4": 6.0, "bt/other/ASL/rouge_l": 99.0}, "alpha", start=4),
                  run({"bt/slt/DGS/bleu4": 7.0, "bt/slt/DGS/rouge_l": 8.0}, "production + translation", start=3),
                  run({"bt/slt/ASL/rouge_l": 9.0, "bt/slt/ASL/bleu4": 10.0}, "production only", start=2)]
    title = ("Back-translation (text metrics: definition 'slt', SL-T: lower-cased whitespace tokens, BLEU-4 "
             "unsmoothed, ROUGE-L beta 1.2, Chinese per character)")
    lines = [
        title,
        "",
        "| motion | ASL R | ASL B4 | DGS R | DGS B4 |",
        "|---|---|---|---|---|",
        "| GT motion (upper bound) | - | 3.00 | 2.00 | 1.00 |",
        "| SMLM, production only | 9.00 | 10.00 | - | - |",
        "| SMLM, production + translation | - | - | 8.00 | 7.00 |",
        "| SMLM, alpha | - | 6.00 | - | - |",
        "| SMLM, zeta | 5.00 | 4.00 | - | - |"]
    assert backtranslation_table(gt, production) == "\n".join(lines)
    # a variant without a tag is named by its run id's first 8 characters; a language is a column only by BLEU-4
    only = backtranslation_table([], [run({"bt/slt/BSL/bleu4": 1.0, "bt/slt/CSL/rouge_l": 2.0}, start=7)])
    assert only.splitlines()[2:] == ["| motion | BSL R | BSL B4 |", "|---|---|---|", "| SMLM, run00007 | - | 1.00 |"]
    assert backtranslation_table([], [run({"x": 1.0})]) == (
        "no finished evaluate-backtranslation / evaluate-smlm runs with back-translation yet: "
        "run `dvc repro evaluate-smlm`")


# ------------------------------------------------------------------------------------------------ configs
@pytest.mark.parametrize("key", ["attention_heads", "encoder_layers", "decoder_layers", "max_frames",
                                 "max_text_tokens", "beam_size", "min_token_frequency"])
def test_model_config_counts_must_be_at_least_one(key):
    from m3t.backtranslation.config import BackTranslationConfig

    BackTranslationConfig(**{key: 1}, d_model=4)  # 1 is allowed
    with pytest.raises(ValueError) as err:
        BackTranslationConfig(**{key: 0})
    assert str(err.value) == f"backtranslation.{key}: expected >= 1, got 0"


def test_model_config_width_and_ctc_weight_are_checked_with_their_values():
    from m3t.backtranslation.config import BackTranslationConfig

    with pytest.raises(ValueError) as err:
        BackTranslationConfig(d_model=10, attention_heads=4)
    assert str(err.value) == "backtranslation.d_model 10 is not divisible by attention_heads 4"
    BackTranslationConfig(d_model=12, attention_heads=4, gloss_ctc_weight=0.0)  # 0 = no CTC head: allowed
    with pytest.raises(ValueError) as err:
        BackTranslationConfig(gloss_ctc_weight=-0.5)
    assert str(err.value) == "backtranslation.gloss_ctc_weight: expected >= 0, got -0.5"


@pytest.mark.parametrize("key", ["epochs", "batch_size", "eval_every", "workers"])
def test_train_config_counts_must_be_at_least_one(key):
    from m3t.backtranslation.config import BackTranslationTrainConfig

    BackTranslationTrainConfig(**{key: 1})
    with pytest.raises(ValueError) as err:
        BackTranslationTrainConfig(**{key: 0})
    assert str(err.value) == f"backtranslation_train.{key}: expected >= 1, got 0"


@pytest.mark.parametrize("factor", [0.0, 1.0, -0.1, 1.5])
def test_train_config_lr_factor_is_strictly_between_zero_and_one(factor):
    from m3t.backtranslation.config import BackTranslationTrainConfig

    BackTranslationTrainConfig(lr_factor=0.5)
    with pytest.raises(ValueError) as err:
        BackTranslationTrainConfig(lr_factor=factor)
    assert str(err.value) == f"backtranslation_train.lr_factor: expected in (0, 1), got {factor}"


# --------------------------------------------------------------------------------------------- the pipeline
def _fake_layout():
    from m3t.body.protocol import Modality, ModalityLayout

    return ModalityLayout((Modality("face", "scalar", ("a", "b")), Modality("body", "rotation6d", ("j0",)),
                           Modality("extra", "scalar", ("e",))), ("beta0",))


def _fitted(clip_id, text="hello world", language="ASL", split="train", label=None, gloss="", frames=3):
    """A FittedClip stand-in: what the pipeline and the corpus builder read of one."""
    from m3t.corpora.clip import Clip

    clip = Clip(clip_id, "fake", split, language, "s0", text, gloss, "m", 25.0, label)
    params = {"body": np.full((frames, 6), 1.0, np.float32), "face": np.full((frames, 2), 2.0, np.float32),
              "extra": np.full((frames, 1), 3.0, np.float32)}
    return SimpleNamespace(clip=clip, num_frames=frames, params=params, body_model="fake")


def test_checkpoint_names_keep_only_safe_characters():
    from m3t.backtranslation.pipeline import checkpoint_name

    assert checkpoint_name("ASL-SYN_v1.2") == "ASL-SYN_v1.2.pt"
    assert checkpoint_name("DGS/ö x") == "DGS___x.pt"


def test_languages_are_the_train_splits_sentence_languages_in_first_seen_order_or_the_configured_ones():
    from m3t.backtranslation.config import BackTranslationConfig
    from m3t.backtranslation.pipeline import _by_language, _selected_languages

    train = [_fitted("a", language="CSL"), _fitted("b", language="ISO", label=2), _fitted("c", language="ASL"),
             _fitted("d", language="CSL")]
    assert _selected_languages(BackTranslationConfig(), train) == ["CSL", "ASL"]  # ISO has isolated signs only
    assert _selected_languages(BackTranslationConfig(languages=("ASL",)), train) == ["ASL"]
    with pytest.raises(ValueError) as err:
        _selected_languages(BackTranslationConfig(languages=("ASL", "ISO", "BSL")), train)
    assert str(err.value) == ("backtranslation.languages names ['ISO', 'BSL'], which have no sentence clip in the "
                              "train split of ['ASL', 'ISO', 'BSL']; found ['CSL', 'ASL']")
    by = _by_language(train)
    assert list(by) == ["CSL", "ISO", "ASL"] and [c.clip.id for c in by["CSL"]] == ["a", "d"]


def _language_corpus(language="ASL", train_n=2, dev_n=1):
    from m3t.backtranslation.data import LanguageCorpus
    from m3t.backtranslation.text import TextProcessor
    from m3t.vocabulary import gloss_vocabulary

    vocab = text_vocabulary([["hello", "world"]])
    mk = [sample(f"c{i}", np.ones((2, 3)), (4,)) for i in range(train_n + dev_n)]
    return LanguageCorpus(language, TextProcessor.for_language(language), vocab, gloss_vocabulary([["A", "B", "C"]]),
                          "annotated", mk[:train_n], mk[train_n:], [{"clip_id": "s"}] * 3, 5)


def test_train_language_reports_its_numbers_and_description_and_copies_the_best_checkpoint(monkeypatch, tmp_path):
    """metrics.json's numbers per language (sizes, best epoch, every ``val_`` / ``train_`` number of the best
    record, nothing else), languages.json's entry, the best checkpoint copied under the language's name, and
    the trainer called with the run key's cache files. A best record without an epoch logs epoch 0."""
    from m3t.backtranslation import pipeline
    from m3t.backtranslation.config import (
        BackTranslationConfig,
        BackTranslationTrainConfig,
    )
    from m3t.backtranslation.data import InputSpec
    from m3t.backtranslation.train import run_key

    calls = []
    best_records = [{"epoch": 7, "val_bleu4": 12.5, "train_loss": 0.25, "lr": 1e-3},
                    {"val_bleu4": 1.0}]

    def fake_train(model_cfg, train_cfg, corpus, spec, version, best, last, progress, on_epoch):
        calls.append((corpus.language, version, best, last, progress, on_epoch))
        Path(best).parent.mkdir(parents=True, exist_ok=True)
        Path(best).write_bytes(b"weights of " + corpus.language.encode())
        return SimpleNamespace(best=best_records[len(calls) - 1])

    monkeypatch.setattr(pipeline, "train_backtranslation", fake_train)
    model_cfg = BackTranslationConfig()
    train_cfg = BackTranslationTrainConfig(cache_dir=str(tmp_path / "cache"))
    spec = InputSpec.from_layout("model", _fake_layout(), "fake")
    corpus = _language_corpus("ASL/x")
    hook = object()
    numbers, described = pipeline._train_language(model_cfg, train_cfg, spec, "v9", tmp_path / "out", False, corpus,
                                                  hook)
    key = run_key(model_cfg, train_cfg, corpus, spec, "v9")
    assert calls == [("ASL/x", "v9", tmp_path / "cache" / f"{key}.best.pt", tmp_path / "cache" / f"{key}.last.pt",
                      False, hook)]
    assert (tmp_path / "out" / "ASL_x.pt").read_bytes() == b"weights of ASL/x"
    assert numbers == {"ASL/x/train_clips": 2.0, "ASL/x/dev_clips": 1.0, "ASL/x/skipped_clips": 3.0,
                       "ASL/x/truncated_clips": 5.0, "ASL/x/text_vocabulary_size": 6.0,
                       "ASL/x/gloss_vocabulary_size": 5.0, "ASL/x/best_epoch": 7.0, "ASL/x/best_val_bleu4": 12.5,
                       "ASL/x/best_train_loss": 0.25}
    assert all(type(v) is float for v in numbers.values())
    assert described == {"checkpoint": "ASL_x.pt", "input": "model (body 6 + face 2 + extra 1)",
                         "text_rule": "m3t-bt-text-v1", "gloss_source": "annotated", "scoring": "slt, per word",
                         "selected_on_dev": True}
    chinese = _language_corpus("CSL", dev_n=0)
    chinese.gloss_vocab = None
    numbers, described = pipeline._train_language(model_cfg, train_cfg, spec, "v9", tmp_path / "out", True, chinese,
                                                  None)
    assert numbers["CSL/best_epoch"] == 0.0 and numbers["CSL/gloss_vocabulary_size"] == 0.0
    assert numbers["CSL/dev_clips"] == 0.0 and numbers["CSL/best_val_bleu4"] == 1.0
    assert described["scoring"] == "slt, per char" and described["selected_on_dev"] is False
    assert calls[-1][4] is True


def test_backtranslate_makes_inputs_a_block_of_batches_at_a_time(monkeypatch, tmp_path):
    """Inputs are made when their block is reached (callables called then, not up front) and every block ends
    where the decoder's batches end (empty clips are not in its batches): the same batches, hence the same
    sentences, as one call over every clip."""
    from m3t.backtranslation import pipeline
    from m3t.backtranslation.text import TextProcessor

    spec = SimpleNamespace(features=lambda params, cid: np.asarray(params["x"], np.float32))
    models = {"ASL": SimpleNamespace(spec=spec, model="m", text_vocab="v", processor=TextProcessor.for_language("ASL"))}
    monkeypatch.setattr(pipeline, "load_models", lambda folder, device: models)
    batches, made = [], []

    def fake_translate(model, vocab, processor, inputs, beam, alpha, batch):
        todo = [i for i, x in enumerate(inputs) if len(x)]
        batches.extend([len(inputs[i]) for i in todo[k: k + batch]] for k in range(0, len(todo), batch))
        return [f"w{len(x)}" if len(x) else "" for x in inputs]

    monkeypatch.setattr(pipeline, "translate", fake_translate)
    lengths = [3, 0, 4, 5, 0, 0, 6, 7, 8, 0, 9]  # 0: an empty generation

    def run(block_batches):
        monkeypatch.setattr(pipeline, "BLOCK_BATCHES", block_batches)
        batches.clear()
        clips = {f"c{i}": ("ASL", lambda n=n, i=i: made.append(i) or {"x": np.zeros((n, 1))})
                 for i, n in enumerate(lengths)}
        report = pipeline.backtranslate("models", clips, {c: "w" for c in clips}, batch_size=2)
        return report, list(batches)

    whole, whole_batches = run(100)
    made.clear()
    blocked, blocked_batches = run(1)
    assert made == list(range(len(lengths))), "each clip's motion is made once, in order"
    assert blocked_batches == whole_batches == [[3, 4], [5, 6], [7, 8], [9]]
    assert blocked.hypotheses == whole.hypotheses and blocked.per_clip == whole.per_clip

    # killed after its first block: the journal's blocks are not made again, the rest start on a batch boundary
    from m3t.journal import Journal

    full = Journal(tmp_path / "full.journal", "k")
    monkeypatch.setattr(pipeline, "BLOCK_BATCHES", 1)
    clips = {f"c{i}": ("ASL", lambda n=n: {"x": np.zeros((n, 1))}) for i, n in enumerate(lengths)}
    pipeline.backtranslate("models", clips, {c: "w" for c in clips}, batch_size=2, journal=full)
    first_block = ["c0", "c1", "c2"]  # two non-empty clips: one batch
    killed = Journal(tmp_path / "killed.journal", "k")
    killed.add(pipeline.JOURNAL_SECTION, [full.done(pipeline.JOURNAL_SECTION)[c] for c in first_block])
    batches.clear()
    resumed = pipeline.backtranslate("models", clips, {c: "w" for c in clips}, batch_size=2, journal=killed)
    assert batches == [[5, 6], [7, 8], [9]]
    assert resumed.hypotheses == whole.hypotheses and resumed.per_clip == whole.per_clip


def test_backtranslate_scores_each_clip_with_its_languages_model(monkeypatch):
    """Clips go to their language's model in batches of that language only (in clip order); the references are
    scored as the model's text rule writes them; per-clip rows carry the columns of per_clip.csv; every
    language counts its empty generations; a clip without a reference is refused naming at most five."""
    from m3t.backtranslation import pipeline
    from m3t.backtranslation.text import TextProcessor

    def loaded(language):
        spec = SimpleNamespace(features=lambda params, cid: np.asarray(params["x"], np.float32))
        return SimpleNamespace(spec=spec, model=f"model-{language}", text_vocab=f"vocab-{language}",
                               processor=TextProcessor.for_language(language))

    models = {"ASL": loaded("ASL"), "DGS": loaded("DGS"), "CSL": loaded("CSL")}  # DGS: a model without clips
    seen = []
    monkeypatch.setattr(pipeline, "load_models", lambda folder, device: seen.append((folder, device)) or models)

    def fake_translate(model, vocab, processor, inputs, beam, alpha, batch):
        seen.append((model, vocab, [len(x) for x in inputs], beam, alpha, batch))
        return ["the cat sat" if len(x) else "" for x in inputs]

    monkeypatch.setattr(pipeline, "translate", fake_translate)
    clips = {"a": ("ASL", {"x": np.zeros((3, 1))}), "b": ("CSL", {"x": np.zeros((2, 1))}),
             "c": ("ASL", {"x": np.zeros((0, 1))})}
    refs = {"a": "The cat sat.", "b": "我 吃", "c": "the cat", "unused": "x"}
    report = pipeline.backtranslate("models", clips, refs, beam_size=3, length_penalty=0.5, device="dev",
                                    batch_size=7)
    assert seen == [("models", "dev"), ("model-ASL", "vocab-ASL", [3, 0], 3, 0.5, 7),
                    ("model-CSL", "vocab-CSL", [2], 3, 0.5, 7)]
    assert report.hypotheses == {"a": "the cat sat", "c": "", "b": "the cat sat"}
    assert [(r["clip_id"], r["language"], r["frames"], r["reference"], r["hypothesis"]) for r in report.per_clip] == [
        ("a", "ASL", 3, "the cat sat .", "the cat sat"), ("b", "CSL", 2, "我吃", "the cat sat"),
        ("c", "ASL", 0, "the cat", "")]
    assert list(report.per_clip[0]) == list(pipeline.PER_CLIP_COLUMNS)
    assert report.per_clip[2]["bleu1"] == 0.0 and report.per_clip[0]["bleu1"] == pytest.approx(
        100 * np.exp(1 - 4 / 3))  # every word right, brevity penalty of 3 words for 4
    assert report.summary["slt/ASL/empty_generations"] == 1.0 and report.summary["slt/CSL/empty_generations"] == 0.0
    assert report.summary["slt/ASL/sentences"] == 2 and "slt/DGS/sentences" not in report.summary
    with pytest.raises(ValueError) as err:
        pipeline.backtranslate("models", {f"m{i}": ("ASL", {}) for i in range(7)}, {})
    assert str(err.value) == "no reference sentence for clips ['m0', 'm1', 'm2', 'm3', 'm4'] ..."
    with pytest.raises(ValueError) as err:
        pipeline.backtranslate("models", {"m0": ("ASL", {})}, {})
    assert str(err.value) == "no reference sentence for clips ['m0']"
    with pytest.raises(ValueError) as err:
        pipeline.backtranslate("here", {"q": ("BSL", {})}, {"q": "hi"})
    assert str(err.value) == ("clip 'q': no back-translation model for language 'BSL' in here (models: ['ASL', "
                              "'CSL', 'DGS']); train one with `dvc repro train-backtranslation` on a corpus of "
                              "that language")
    with pytest.raises(ValueError) as err:
        pipeline.backtranslate("here", {"q": ("ASL", {})}, {"q": " \t"})
    assert str(err.value) == "clip 'q': empty reference sentence; nothing to score against"


def test_per_clip_csv_has_the_columns_in_order():
    from m3t.backtranslation.pipeline import per_clip_csv

    text = per_clip_csv([{"clip_id": "a", "language": "ASL", "frames": 2, "reference": "x", "hypothesis": "y",
                          "bleu1": 1.5, "bleu2": 0.0, "bleu3": 0.0, "bleu4": 0.0, "rouge_l": 2.0}])
    assert text == ("clip_id,language,frames,reference,hypothesis,bleu1,bleu2,bleu3,bleu4,rouge_l\n"
                    "a,ASL,2,x,y,1.5,0.0,0.0,0.0,2.0\n")


def test_load_models_refuses_a_missing_or_empty_folder_naming_the_stage(tmp_path):
    from m3t.backtranslation.pipeline import load_models

    expected = (f"no back-translation checkpoint in {tmp_path}; run `dvc repro train-backtranslation` "
                "(python -m m3t.stages.train_backtranslation) first")
    for folder in (tmp_path, tmp_path / "absent"):
        with pytest.raises(FileNotFoundError) as err:
            load_models(folder)
        assert str(err.value) == expected.replace(str(tmp_path), str(folder))


def test_ground_truth_evaluation_skips_with_reasons_and_writes_its_files(monkeypatch, tmp_path):
    """Which clips of the split are scored (sentences of the configured languages, with frames and text), the
    skipped ones with their reason, what is handed to :func:`backtranslate`, and the three files written."""
    from m3t.backtranslation import pipeline
    from m3t.backtranslation.config import BackTranslationConfig

    clips = [_fitted("a", split="test"), _fitted("b", split="test", label=4), _fitted("c", split="test", text=" "),
             _fitted("d", split="test", frames=0), _fitted("e", split="test", language="DGS"),
             _fitted("f", split="test", text="Second one")]
    monkeypatch.setattr(pipeline, "read_production_split", lambda data, split: clips if split == "test" else [])
    got = {}

    def fake_backtranslate(folder, params, refs, beam, alpha, device):
        got.update(folder=folder, params=params, refs=refs, beam=beam, alpha=alpha, device=device)
        return pipeline.BackTranslationReport({}, [{"clip_id": "a", "language": "ASL", "frames": 3}],
                                              {"slt_bleu4": 1.5})

    monkeypatch.setattr(pipeline, "backtranslate", fake_backtranslate)
    data = SimpleNamespace(train_corpora=("fake",), backtranslation_dir=tmp_path / "models",
                           metrics=lambda name: tmp_path / "metrics" / name)
    cfg = BackTranslationConfig(languages=("ASL",), beam_size=2, length_penalty=0.7)
    report = pipeline.run_evaluate_backtranslation(cfg, data, device="meta")
    assert report.summary == {"slt_bleu4": 1.5}
    assert got["folder"] == tmp_path / "models" and (got["beam"], got["alpha"], got["device"]) == (2, 0.7, "meta")
    assert list(got["params"]) == ["a", "f"] and got["params"]["a"][0] == "ASL"
    assert got["params"]["f"][1] is clips[5].params and got["refs"] == {"a": "hello world", "f": "Second one"}
    out = tmp_path / "metrics" / "backtranslation"
    assert json.loads((out / "metrics.json").read_text()) == {"slt_bleu4": 1.5, "skipped_clips": 4.0}
    assert (out / "per_clip.csv").read_text() == (
        "clip_id,language,frames,reference,hypothesis,bleu1,bleu2,bleu3,bleu4,rouge_l\na,ASL,3,,,,,,,\n")
    skipped = [json.loads(line) for line in (out / "skipped.jsonl").read_text().splitlines()]
    assert skipped == [
        {"clip_id": "b", "split": "test", "language": "ASL",
         "reason": "isolated sign (label 4): back-translation is sentence-level"},
        {"clip_id": "c", "split": "test", "language": "ASL", "reason": "empty text"},
        {"clip_id": "d", "split": "test", "language": "ASL", "reason": "no frames"},
        {"clip_id": "e", "split": "test", "language": "DGS", "reason": "language not in backtranslation.languages"}]
    # without a language list every language's sentences are scored; with nothing to score, the split is named
    pipeline.run_evaluate_backtranslation(BackTranslationConfig(), data)
    assert list(got["params"]) == ["a", "e", "f"] and got["device"] == "cpu" and got["beam"] == 1
    with pytest.raises(ValueError) as err:
        pipeline.run_evaluate_backtranslation(BackTranslationConfig(), data, split="dev")
    assert str(err.value) == "the dev split of ['fake'] has no sentence clip to back-translate (0 skipped)"


# ------------------------------------------------------------------------------------------- input spec
def test_model_input_spec_orders_streams_describes_itself_and_round_trips():
    """``model``: STREAM_ORDER streams first, then the layout's others in its order; ``to_dict`` / ``from_dict``
    (unknown keys ignored) give the same spec; the description names the streams and dims."""
    from m3t.backtranslation.data import InputSpec
    from m3t.shards.schema import layout_to_json

    spec = InputSpec.from_layout("model", _fake_layout(), "fake")
    assert spec.streams == (("body", 6), ("face", 2), ("extra", 1)) and spec.dim == 9
    assert spec.layout == "model" and spec.layout_name == "fake"
    assert spec.source_layout == layout_to_json(_fake_layout())
    assert InputSpec.from_layout("model", _fake_layout()).layout_name == "layout"
    raw = spec.to_dict()
    assert raw == {"layout": "model", "streams": [["body", 6], ["face", 2], ["extra", 1]],
                   "source_layout": spec.source_layout, "layout_name": "fake"}
    assert InputSpec.from_dict({**raw, "future_key": 1}) == spec
    assert spec.describe() == "model (body 6 + face 2 + extra 1)"
    with pytest.raises(ValueError) as err:
        InputSpec.from_layout("skeleton", _fake_layout())
    assert str(err.value) == ("backtranslation.input_layout 'skeleton' unknown here; allowed: model, smplx240 "
                              "(skeleton inputs: InputSpec.for_skeleton)")


def test_model_features_concatenate_the_streams_and_name_the_clip_and_modality_of_bad_input():
    from m3t.backtranslation.data import InputSpec

    spec = InputSpec.from_layout("model", _fake_layout(), "fake")
    params = _fitted("c", frames=2).params
    x = spec.features({**params, "unused": np.zeros((5, 5))}, "c")
    assert x.dtype == np.float32 and x.tolist() == [[1.0] * 6 + [2.0, 2.0, 3.0]] * 2
    assert spec.features({k: v[:0] for k, v in params.items()}, "c").shape == (0, 9)
    cases = [({k: v for k, v in params.items() if k != "face"},
              ("clip 'c9': no 'face' parameters; the back-translation model reads ['body', 'extra', 'face'] "
               "(fake layout)")),
             ({**params, "face": np.zeros((2, 3))},
              "clip 'c9', modality 'face': shape (2, 3), expected (T, 2) of the fake layout the model was trained on"),
             ({**params, "face": np.zeros(4)},
              "clip 'c9', modality 'face': shape (4,), expected (T, 2) of the fake layout the model was trained on"),
             ({**params, "extra": np.zeros((3, 1))}, "clip 'c9', modality 'extra': 3 frames, other modalities 2")]
    for bad, message in cases:
        with pytest.raises(ValueError) as err:
            spec.features(bad, "c9")
        assert str(err.value) == message


def test_skeleton_input_spec_reads_one_stream_and_names_its_graph():
    from m3t.backtranslation.data import InputSpec

    graph = SimpleNamespace(width=12, name="tiny", to_dict=lambda: {"b": 1, "a": 2})
    spec = InputSpec.for_skeleton(graph)
    assert spec.layout == "skeleton" and spec.streams == (("skeleton", 12),) and spec.dim == 12
    assert spec.source_layout == '{"a": 2, "b": 1}' and spec.layout_name == "tiny"
    assert spec.describe() == "skeleton (tiny graph, 12 normalised coordinates)"
    assert spec.features({"skeleton": np.ones((2, 12))}, "c").shape == (2, 12)


def test_batches_move_every_tensor_to_the_device():
    vocab = text_vocabulary([["a"]])
    batch = collate([sample("a", np.ones((2, 3)), (4,), (1,))], vocab)
    moved = batch.to(torch.device("cpu"))
    for name in batch.__dataclass_fields__:
        assert torch.equal(getattr(moved, name), getattr(batch, name)), name
    assert batch.glosses.dtype == torch.long and batch.gloss_lengths.dtype == torch.long


# -------------------------------------------------------------------------------------- language corpus
def _corpus_cfg(**kw):
    from m3t.backtranslation.config import BackTranslationConfig

    return BackTranslationConfig(**{"pseudo_glosses": False, **kw})


def test_language_corpus_builds_vocabularies_samples_and_skips_with_reasons():
    """Train-split vocabulary (rare words -> <unk> under min_token_frequency), annotated glosses for the CTC head,
    clips cut to max_frames and counted, long training sentences skipped (dev sentences never), references as
    scored, the skipped list with split and reason."""
    from m3t.backtranslation.data import InputSpec, language_corpus

    spec = InputSpec.from_layout("model", _fake_layout(), "fake")
    train = [_fitted("t0", "The cat. The dog", gloss="CAT DOG", frames=5), _fitted("t1", "the cat", frames=2),
             _fitted("t2", "the cat sat on a mat today", frames=2), _fitted("t3", "x", label=1),
             _fitted("t4", "   ")]
    dev = [_fitted("d0", "the bird sat on a mat today", split="dev", gloss="BIRD", frames=6),
           _fitted("d1", "cat", split="dev", frames=0)]
    cfg = _corpus_cfg(max_frames=4, max_text_tokens=6, min_token_frequency=2)
    corpus = language_corpus("ASL", train, dev, spec, cfg)
    assert corpus.language == "ASL" and corpus.processor.language == "ASL"
    assert corpus.text_vocab.itos == ["<pad>", "<unk>", "<bos>", "<eos>", "the", "cat"]  # ".", "dog" seen once
    assert corpus.gloss_vocab.itos == ["<blank>", "<unk>", "CAT", "DOG"] and corpus.gloss_source == \
        "annotated (1 clips), none (1 clips)"  # pseudo-glosses off: t1 has none
    assert [s.clip_id for s in corpus.train] == ["t0", "t1"] and [s.clip_id for s in corpus.dev] == ["d0"]
    t0, t1 = corpus.train
    assert t0.text_ids == (4, 5, 1, 4, 1) and t0.gloss_ids == (2, 3) and t0.reference == "the cat . the dog"
    assert t1.gloss_ids == () and t1.text_ids == (4, 5)
    assert t0.frames.shape == (4, 9) and t1.frames.shape == (2, 9) and corpus.dev[0].frames.shape == (4, 9)
    assert corpus.truncated == 2  # t0 (5 frames) and d0 (6 frames); 4 frames would not be cut
    assert corpus.dev[0].gloss_ids == () and corpus.dev[0].reference == "the bird sat on a mat today"
    assert corpus.skipped == [
        {"clip_id": "t2", "split": "train", "language": "ASL",
         "reason": "7 text tokens; backtranslation.max_text_tokens 6 allows one fewer (+ EOS)"},
        {"clip_id": "t3", "split": "train", "language": "ASL",
         "reason": "isolated sign (label 1): back-translation is sentence-level"},
        {"clip_id": "t4", "split": "train", "language": "ASL", "reason": "empty text"},
        {"clip_id": "d1", "split": "dev", "language": "ASL", "reason": "no frames"}]
    # a sentence of max_text_tokens - 1 tokens fits with its EOS
    fits = language_corpus("ASL", [_fitted("t", "a b c d e")], [], spec, _corpus_cfg(max_text_tokens=6))
    assert [s.clip_id for s in fits.train] == ["t"] and fits.truncated == 0
    assert fits.gloss_vocab is None and fits.gloss_source == "none"
    exact = language_corpus("ASL", [_fitted("t", frames=4)], [], spec, _corpus_cfg(max_frames=4))
    assert exact.truncated == 0 and exact.train[0].frames.shape == (4, 9)


def test_language_corpus_glosses_need_a_positive_ctc_weight_and_name_mixed_sources(monkeypatch):
    from m3t.backtranslation import text
    from m3t.backtranslation.data import InputSpec, language_corpus

    monkeypatch.setattr(text, "_spacy_pipeline", lambda spoken: (None, ""))  # the stop-word fallback on any host
    spec = InputSpec.from_layout("model", _fake_layout(), "fake")
    train = [_fitted("t0", "the red car", gloss="CAR"), _fitted("t1", "a blue boat"), _fitted("t2", "the sun")]
    corpus = language_corpus("ASL", train, [], spec, _corpus_cfg(pseudo_glosses=True))
    assert corpus.gloss_source == ("annotated (1 clips), stop-word fallback (en; no POS tagger installed) (2 clips)")
    assert corpus.gloss_vocab.itos == ["<blank>", "<unk>", "CAR", "blue", "boat", "sun"]
    assert [s.gloss_ids for s in corpus.train] == [(2,), (3, 4), (5,)]
    pseudo_only = language_corpus("ASL", train[1:], [], spec, _corpus_cfg(pseudo_glosses=True))
    assert pseudo_only.gloss_source == "stop-word fallback (en; no POS tagger installed)"
    no_head = language_corpus("ASL", train, [], spec, _corpus_cfg(gloss_ctc_weight=0.0))
    assert no_head.gloss_vocab is None and no_head.gloss_source == "none"
    assert all(s.gloss_ids == () for s in no_head.train)


def test_language_corpus_without_a_usable_training_clip_names_the_reasons():
    from m3t.backtranslation.data import InputSpec, language_corpus

    spec = InputSpec.from_layout("model", _fake_layout(), "fake")
    train = [_fitted("a", label=1), _fitted("b", label=2), _fitted("c", text="")]
    with pytest.raises(ValueError) as err:
        language_corpus("ASL", train, [_fitted("d", text="", split="dev")], spec, _corpus_cfg())
    assert str(err.value) == (
        "language 'ASL': no usable training clip (3 in the train split; skipped: {'isolated sign (label 1): "
        "back-translation is sentence-level': 1, 'isolated sign (label 2): back-translation is sentence-level': 1, "
        "'empty text': 1}); drop it from backtranslation.languages or fix the corpus")


# --------------------------------------------------------------------------------------- model and decoding
def _tiny_cfg(**kw):
    from m3t.backtranslation.config import BackTranslationConfig

    return BackTranslationConfig(**{"d_model": 8, "encoder_layers": 1, "decoder_layers": 2, "attention_heads": 2,
                                    "ffn_dim": 16, "dropout": 0.25, "max_frames": 5, "max_text_tokens": 7, **kw})


def test_sign_to_text_is_built_from_its_config_and_dims():
    """Layer counts, widths, heads, dropout, pre-norm, the position table (not in the state dict) long enough for
    frames and BOS + tokens, standardisation buffers (in the state dict), Xavier-initialised matrices, and the
    gloss head only with gloss classes."""
    from m3t.backtranslation.model import BackTranslationDims, SignToText

    model = SignToText(_tiny_cfg(), BackTranslationDims(input_dim=3, text_vocab=11, gloss_vocab=4))
    assert model.positions.shape == (8, 8) and "positions" not in model.state_dict()
    assert SignToText(_tiny_cfg(max_frames=20), BackTranslationDims(3, 11)).positions.shape == (20, 8)
    assert model.feature_mean.tolist() == [0.0] * 3 and model.feature_std.tolist() == [1.0] * 3
    assert {"feature_mean", "feature_std"} <= set(model.state_dict())
    linear, norm, act = model.frame_embedding
    assert (linear.in_features, linear.out_features, norm.normalized_shape) == (3, 8, (8,))
    assert isinstance(act, torch.nn.Softsign)
    assert model.text_embedding.num_embeddings == 11 and model.text_embedding.embedding_dim == 8
    assert model.dropout.p == 0.25
    assert len(model.encoder.layers) == 1 and len(model.decoder.layers) == 2
    assert model.encoder.norm is not None and model.decoder.norm is not None
    assert model.encoder.enable_nested_tensor is False  # padded frames stay dense (pre-norm layers)
    for layer in (*model.encoder.layers, *model.decoder.layers):
        assert layer.norm_first and layer.self_attn.num_heads == 2 and layer.self_attn.batch_first
        assert (layer.linear1.in_features, layer.linear1.out_features) == (8, 16) and layer.dropout.p == 0.25
    assert (model.text_head.in_features, model.text_head.out_features) == (8, 11)
    assert (model.gloss_head.in_features, model.gloss_head.out_features) == (8, 4)
    assert SignToText(_tiny_cfg(), BackTranslationDims(3, 11)).gloss_head is None
    # Xavier uniform: matrices bounded by sqrt(6 / (fan_in + fan_out)); LayerNorm weights stay 1
    bound = np.sqrt(6 / (11 + 8))
    assert model.text_embedding.weight.abs().max() <= bound and model.text_embedding.weight.abs().max() > bound / 2
    assert torch.equal(norm.weight, torch.ones(8))


def test_sign_to_text_standardises_masks_and_shapes_its_outputs():
    from m3t.backtranslation.model import BackTranslationDims, SignToText

    torch.manual_seed(0)
    model = SignToText(_tiny_cfg(dropout=0.0), BackTranslationDims(2, 6, 3)).eval()
    model.set_feature_statistics(torch.tensor([1.0, 2.0]), torch.tensor([2.0, 4.0]))
    assert model.feature_mean.tolist() == [1.0, 2.0] and model.feature_std.tolist() == [2.0, 4.0]
    frames = torch.tensor([[[3.0, 6.0], [1.0, 2.0], [9.0, 9.0]]])
    mask = torch.tensor([[True, True, False]])
    memory = model.encode(frames, mask)
    # the same as standardised input through an untouched model; the padded frame changes nothing real
    plain = SignToText(_tiny_cfg(dropout=0.0), BackTranslationDims(2, 6, 3)).eval()
    plain.load_state_dict({**model.state_dict(), "feature_mean": torch.zeros(2), "feature_std": torch.ones(2)})
    standard = torch.tensor([[[1.0, 1.0], [0.0, 0.0], [4.0, 1.75]]])
    assert torch.allclose(memory, plain.encode(standard, mask), atol=1e-5)  # float kernels: tolerance
    other = model.encode(torch.tensor([[[3.0, 6.0], [1.0, 2.0], [-7.0, 0.0]]]), mask)
    assert torch.allclose(memory[:, :2], other[:, :2], atol=1e-5)
    out = model(frames, mask, torch.tensor([[2, 4, 5]]), torch.tensor([[True, True, True]]))
    assert out.text_logits.shape == (1, 3, 6) and out.gloss_logits.shape == (1, 3, 3)
    assert torch.allclose(out.gloss_logits, model.gloss_logits(memory), atol=1e-5)
    # causal: the logits of the first position do not see later tokens
    changed = model.decode(memory, mask, torch.tensor([[2, 1, 1]]))
    assert torch.allclose(changed[:, 0], out.text_logits[:, 0], atol=1e-5)
    assert not torch.allclose(changed[:, 2], out.text_logits[:, 2], atol=1e-5)
    assert SignToText(_tiny_cfg(), BackTranslationDims(2, 6)).gloss_logits(memory) is None


def test_cut_keeps_the_tokens_before_the_first_eos():
    from m3t.backtranslation.decode import _cut

    assert _cut((4, 5, 3, 6, 3), 3) == [4, 5] and _cut([4, 5], 3) == [4, 5] and _cut([3], 3) == []


def test_translate_batches_non_empty_clips_cut_to_max_frames_and_picks_the_decoder(monkeypatch):
    """Empty clips get "" without the model; the others go in batches of ``batch_size`` (in order, cut to
    ``max_frames``, padded with a mask), greedy for beam 1 and beam search above; ids become words by the
    vocabulary and are joined by the language's rule."""
    from m3t.backtranslation import decode
    from m3t.backtranslation.text import TextProcessor

    vocab = text_vocabulary([["hello", "world"]])
    hello, world = vocab.encode(["hello", "world"])
    model = torch.nn.Linear(1, 1)
    model.cfg = SimpleNamespace(max_text_tokens=9, max_frames=3)
    model.train()
    calls = []

    def greedy(m, x, mask, bos, eos, max_len):
        calls.append(("greedy", x.shape[:2], mask.sum(1).tolist(), bos, eos, max_len))
        return [[hello, world]] * len(x)

    def beam(m, x, mask, bos, eos, max_len, beam_size, alpha):
        calls.append(("beam", x.shape[:2], mask.sum(1).tolist(), beam_size, alpha))
        return [[world]] * len(x)

    monkeypatch.setattr(decode, "greedy_decode", greedy)
    monkeypatch.setattr(decode, "beam_decode", beam)
    frames = [np.ones((5, 1)), np.ones((0, 1)), np.ones((2, 1)), np.ones((1, 1))]
    out = decode.translate(model, vocab, TextProcessor.for_language("ASL"), frames, batch_size=2)
    assert out == ["hello world", "", "hello world", "hello world"] and not model.training
    assert calls == [("greedy", (2, 3), [3, 2], 2, 3, 9), ("greedy", (1, 1), [1], 2, 3, 9)]
    calls.clear()
    out = decode.translate(model, vocab, TextProcessor.for_language("CSL"), frames[:3], beam_size=2, alpha=0.5)
    assert out == ["world", "", "world"] and calls == [("beam", (2, 3), [3, 2], 2, 0.5)]
    assert decode.translate(model, vocab, TextProcessor.for_language("CSL"), [np.ones((0, 1))]) == [""]
    assert calls == [("beam", (2, 3), [3, 2], 2, 0.5)]


# ---------------------------------------------------------------------------------------------- training
def test_losses_are_translation_cross_entropy_plus_weighted_ctc_over_glossed_clips():
    """The translation loss ignores IGNORE targets; the CTC term (over clips with a gloss only) is added times
    its weight; without a gloss head, with weight 0 or with no glossed clip there is no CTC key."""
    import torch.nn.functional as F

    from m3t.backtranslation.model import BackTranslationOutput
    from m3t.backtranslation.train import losses

    vocab = text_vocabulary([["a", "b"]])
    batch = collate([sample("x", np.ones((3, 2)), (4, 5), (1, 2)), sample("y", np.ones((2, 2)), (5,))], vocab)
    text_logits = torch.linspace(-1, 1, 2 * 3 * 6).reshape(2, 3, 6)
    gloss_logits = torch.linspace(1, -1, 2 * 3 * 3).reshape(2, 3, 3)
    seen = {}

    def model(frames, mask, text_in, text_mask):
        seen["text_mask"] = text_mask
        return BackTranslationOutput(text_logits, gloss_logits)

    out = losses(model, batch, 0.5, smoothing=0.1)
    assert seen["text_mask"].tolist() == [[True, True, True], [True, True, False]]
    targets = batch.text_out.flatten()
    keep = targets != IGNORE
    translation = F.cross_entropy(text_logits.flatten(0, 1)[keep], targets[keep], label_smoothing=0.1)
    ctc = F.ctc_loss(gloss_logits[:1].log_softmax(-1).transpose(0, 1), torch.tensor([[1, 2]]), torch.tensor([3]),
                     torch.tensor([2]))
    assert set(out) == {"loss", "translation_loss", "gloss_ctc_loss"}
    # same kernels on the same numbers; tolerance only for summation order
    assert out["translation_loss"].item() == pytest.approx(translation.item(), rel=1e-5)
    assert out["gloss_ctc_loss"].item() == pytest.approx(ctc.item(), rel=1e-5)
    assert out["loss"].item() == pytest.approx(translation.item() + 0.5 * ctc.item(), rel=1e-5)
    assert set(losses(model, batch, 0.0)) == {"loss", "translation_loss"}
    plain = losses(model, batch, 0.5)
    assert plain["translation_loss"].item() == pytest.approx(
        F.cross_entropy(text_logits.flatten(0, 1)[keep], targets[keep]).item(), rel=1e-5)
    no_gloss = collate([sample("y", np.ones((2, 2)), (5,))], vocab)
    full = text_logits
    text_logits, gloss_logits = full[:1, :2], gloss_logits[:1, :2]
    assert set(losses(model, no_gloss, 0.5)) == {"loss", "translation_loss"}  # no clip with a gloss
    text_logits, gloss_logits = full, None  # the model (closure above) now has no gloss head
    assert set(losses(model, batch, 0.5)) == {"loss", "translation_loss"}


def test_run_key_ignores_where_files_go_the_device_and_decode_settings_only():
    from m3t.backtranslation.config import (
        BackTranslationConfig,
        BackTranslationTrainConfig,
    )
    from m3t.backtranslation.data import InputSpec
    from m3t.backtranslation.train import run_key

    spec = InputSpec.from_layout("model", _fake_layout(), "fake")
    corpus = _language_corpus("ASL")
    model, train = BackTranslationConfig(), BackTranslationTrainConfig()
    key = run_key(model, train, corpus, spec, "v1")
    assert len(key) == 16
    same = [(BackTranslationConfig(beam_size=4, length_penalty=0.2, languages=("ASL",)), train),
            (model, BackTranslationTrainConfig(cache_dir="elsewhere", device="cuda", workers=3))]
    for m, t in same:
        assert run_key(m, t, corpus, spec, "v1") == key
    other_corpus = _language_corpus("DGS")
    no_gloss = _language_corpus("ASL")
    no_gloss.gloss_vocab = None
    different = [run_key(BackTranslationConfig(d_model=32), train, corpus, spec, "v1"),
                 run_key(model, BackTranslationTrainConfig(lr=0.5), corpus, spec, "v1"),
                 run_key(model, BackTranslationTrainConfig(seed=1), corpus, spec, "v1"),
                 run_key(model, train, other_corpus, spec, "v1"), run_key(model, train, no_gloss, spec, "v1"),
                 run_key(model, train, corpus, InputSpec.from_layout("model", _fake_layout(), "other"), "v1"),
                 run_key(model, train, corpus, spec, "v2")]
    assert len({key, *different}) == 8


def test_validation_scores_the_dev_split_and_selects_by_bleu4_then_rouge(monkeypatch):
    from m3t.backtranslation import train

    corpus = _language_corpus("ASL", train_n=1, dev_n=2)
    corpus.dev = [Sample("d0", np.ones((2, 3)), (4,), (), "hello world"), Sample("d1", np.ones((1, 3)), (4,), (), "hi")]
    seen = []
    monkeypatch.setattr(train, "translate", lambda model, vocab, processor, frames: seen.append(
        (model, vocab, [len(f) for f in frames])) or ["hello world", "hello"])
    scores = train.validate("m", corpus)
    assert seen == [("m", corpus.text_vocab, [2, 1])]
    assert set(scores) == {"bleu1", "bleu2", "bleu3", "bleu4", "rouge_l", "selection"}
    assert scores["selection"] == pytest.approx(scores["bleu4"] + 1e-6 * scores["rouge_l"])
    assert scores["rouge_l"] > 0 and scores["selection"] != scores["bleu4"]


# ------------------------------------------------------------------------------------------------- text
def test_spoken_languages_by_code_or_prefix():
    from m3t.backtranslation.text import spoken_language

    assert [spoken_language(c) for c in ("ASL", "bsl-syn", "DGS", "CSL-SYN", "zh", "Auslan", "LSF", "")] == [
        "en", "en", "de", "zh", "zh", "en", "", ""]


def test_text_processor_tokenises_lower_cased_words_and_punctuation_and_joins_by_language():
    from m3t.backtranslation.text import TEXT_RULE, TextProcessor

    english = TextProcessor.for_language("ASL")
    assert (english.language, english.chinese, english.rule) == ("ASL", False, TEXT_RULE) and \
        TEXT_RULE == "m3t-bt-text-v1"
    assert english.tokens("Don't pay 3.5 EUR, ok?!") == ["don't", "pay", "3.5", "eur", ",", "ok", "?", "!"]
    assert english.join(["a", "b"]) == "a b" and english.reference(" The  CAT. ") == "the cat ."
    chinese = TextProcessor.for_language("CSL-SYN")
    assert chinese.chinese and chinese.join(["我", "们"]) == "我们"
    assert "".join(chinese.tokens("我们 吃")) == "我们吃" and chinese.reference("我 们") == "我们"


def test_pseudo_glosses_per_method(monkeypatch):
    """With a POS tagger: lower-cased lemmas of the Sign2GPT classes; without: words minus punctuation and the
    language's stop words, or every word where there is no stop-word list; ``method`` says which."""
    from m3t.backtranslation import text

    asked = []
    monkeypatch.setattr(text, "_spacy_pipeline", lambda spoken: asked.append(spoken) or (None, ""))
    english = text.PseudoGlosser("ASL")
    assert english.language == "ASL" and english.spoken == "en" and asked == ["en"]
    assert english.method == "stop-word fallback (en; no POS tagger installed)"
    assert english("The cat, sat on THE mat!") == ["cat", "sat", "mat"]
    german = text.PseudoGlosser("DGS")
    assert german("Der Hund ist nicht im Haus") == ["hund", "haus"]
    other = text.PseudoGlosser("LSF")
    assert other.method == "all words (no POS tagger installed, no stop-word list for this language)"
    assert other("Le chat, le chien.") == ["le", "chat", "le", "chien"]

    def nlp(sentence):
        return [SimpleNamespace(lemma_="Run", pos_="VERB"), SimpleNamespace(lemma_="the", pos_="DET"),
                SimpleNamespace(lemma_="Dog", pos_="NOUN")]

    monkeypatch.setattr(text, "_spacy_pipeline", lambda spoken: (nlp, "en_core_web_sm"))
    tagged = text.PseudoGlosser("ASL")
    assert tagged.method == "sign2gpt-pos (spacy en_core_web_sm)" and tagged("anything") == ["run", "dog"]
    assert text.annotated_gloss("  HOUSE  go ") == ["HOUSE", "go"]


def test_without_spacy_there_is_no_pipeline(monkeypatch):
    import builtins

    from m3t.backtranslation import text

    real_import = builtins.__import__

    def no_spacy(name, *args, **kwargs):
        if name == "spacy":
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_spacy)
    assert text._spacy_pipeline("en") == (None, "")
    fake = SimpleNamespace(loaded=[])

    def load(name, disable):
        fake.loaded.append((name, disable))
        if name != "en_core_web_md":
            raise OSError(name)
        return "pipeline"

    monkeypatch.setattr(builtins, "__import__", lambda name, *a, **k: SimpleNamespace(load=load) if name == "spacy"
                        else real_import(name, *a, **k))
    assert text._spacy_pipeline("en") == ("pipeline", "en_core_web_md")
    assert fake.loaded == [("en_core_web_lg", ["parser", "ner"]), ("en_core_web_md", ["parser", "ner"])]
    assert text._spacy_pipeline("xx") == (None, "")


# ------------------------------------------------------------------------------------------- checkpoints
def test_a_checkpoint_rebuilds_model_vocabularies_spec_and_text_rule(tmp_path):
    from m3t.backtranslation.checkpoint import (
        FORMAT,
        load_backtranslation,
        save_backtranslation,
    )
    from m3t.backtranslation.data import InputSpec
    from m3t.backtranslation.model import BackTranslationDims, SignToText
    from m3t.backtranslation.text import TextProcessor
    from m3t.vocabulary import gloss_vocabulary

    assert FORMAT == "m3t-backtranslation-v1"
    torch.manual_seed(0)
    spec = InputSpec.from_layout("model", _fake_layout(), "fake")
    vocab, glosses = text_vocabulary([["a", "b"]]), gloss_vocabulary([["A"]])
    model = SignToText(_tiny_cfg(), BackTranslationDims(spec.dim, len(vocab), len(glosses)))
    model.set_feature_statistics(torch.arange(9.0), torch.full((9,), 2.0))
    path = save_backtranslation(tmp_path / "m.pt", model, "DGS", spec, TextProcessor.for_language("DGS"), vocab,
                                glosses, "annotated", 3, 17, "data-v", {"val_bleu4": 5.0}, {"lr": 0.1})
    loaded = load_backtranslation(path)
    assert (loaded.language, loaded.spec, loaded.processor, loaded.gloss_source) == (
        "DGS", spec, TextProcessor.for_language("DGS"), "annotated")
    assert loaded.text_vocab.itos == vocab.itos and loaded.gloss_vocab.itos == glosses.itos
    assert (loaded.epoch, loaded.step, loaded.data_version, loaded.metrics) == (3, 17, "data-v", {"val_bleu4": 5.0})
    assert loaded.model.cfg == model.cfg and loaded.model.dims == model.dims and not loaded.model.training
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.model.state_dict()[key], value), key
    save_backtranslation(tmp_path / "n.pt", SignToText(_tiny_cfg(), BackTranslationDims(spec.dim, len(vocab))),
                         "ASL", spec, TextProcessor.for_language("ASL"), vocab, None, "none", 1, 1, "v", {})
    bare = load_backtranslation(tmp_path / "n.pt")
    assert bare.gloss_vocab is None and bare.model.gloss_head is None and bare.gloss_source == "none"


# ---------------------------------------------------------------------------------- the training stage
def _stage_data(tmp_path):
    return SimpleNamespace(train_corpora=("fake",), backtranslation_dir=tmp_path / "models" / "bt",
                           skeleton_judge_dir=tmp_path / "models" / "sk", metrics=lambda name: tmp_path / "m" / name,
                           shards_dirs=[tmp_path / "a", tmp_path / "b"])


def _fake_training(monkeypatch, train, dev):
    """The stage's inputs and the trainer faked: a trainer that reports one epoch and writes its best file."""
    from m3t.backtranslation import pipeline

    monkeypatch.setattr(pipeline, "read_production_split", lambda data, split: {"train": train, "dev": dev}[split])
    monkeypatch.setattr(pipeline, "_layout", lambda data: _fake_layout())
    monkeypatch.setattr(pipeline, "production_data_version", lambda data: "dv")
    trained = []

    def fake_train(model_cfg, train_cfg, corpus, spec, version, best, last, progress, on_epoch):
        trained.append((corpus.language, [s.clip_id for s in corpus.train], [s.clip_id for s in corpus.dev], spec,
                        version, progress))
        if on_epoch is not None:
            on_epoch({"train_loss": 0.5}, 1)
        Path(best).parent.mkdir(parents=True, exist_ok=True)
        Path(best).write_bytes(corpus.language.encode())
        return SimpleNamespace(best={"epoch": 1, "val_bleu4": 2.0})

    monkeypatch.setattr(pipeline, "train_backtranslation", fake_train)
    return pipeline, trained


def test_the_training_stage_trains_each_language_and_writes_its_three_files(monkeypatch, tmp_path):
    """One model per selected language (first-seen order) from its train and dev clips; clips of other languages
    skipped with their reason, then each corpus' own skips; a stale checkpoint of an earlier run removed;
    epoch records reach ``on_epoch`` with the language."""
    from m3t.backtranslation.config import (
        BackTranslationConfig,
        BackTranslationTrainConfig,
    )

    train = [_fitted("t1", language="DGS"), _fitted("t2", language="ASL"), _fitted("t3", language="BSL"),
             _fitted("t4", language="ASL", label=3), _fitted("t5", language="DGS", text="")]
    dev = [_fitted("d1", language="ASL", split="dev"), _fitted("d2", language="BSL", split="dev", label=1)]
    pipeline, trained = _fake_training(monkeypatch, train, dev)
    data = _stage_data(tmp_path)
    data.backtranslation_dir.mkdir(parents=True)
    (data.backtranslation_dir / "OLD.pt").write_bytes(b"stale")
    (data.backtranslation_dir / "notes.txt").write_text("kept")
    epochs, jobs = [], []
    real_run_jobs = pipeline.run_jobs

    def recording_run_jobs(run, corpora, names, processes, threads, on_epoch, what, setting):
        jobs.append((names, processes, threads, what, setting))  # what a dead worker's message names
        return real_run_jobs(run, corpora, names, processes, threads, on_epoch, what, setting)

    monkeypatch.setattr(pipeline, "run_jobs", recording_run_jobs)
    cfg = BackTranslationConfig(languages=("DGS", "ASL"), pseudo_glosses=False)
    train_cfg = BackTranslationTrainConfig(cache_dir=str(tmp_path / "cache"))
    report = pipeline.run_train_backtranslation(cfg, train_cfg, data, progress=False,
                                                on_epoch=lambda *args: epochs.append(args))
    assert [(t[0], t[1], t[2], t[4], t[5]) for t in trained] == [("DGS", ["t1"], [], "dv", False),
                                                                  ("ASL", ["t2"], ["d1"], "dv", False)]
    assert trained[0][3].layout == "model" and trained[0][3].layout_name == "fake"
    assert epochs == [("DGS", {"train_loss": 0.5}, 1), ("ASL", {"train_loss": 0.5}, 1)]
    assert jobs == [(["DGS", "ASL"], 1, 0, "language", "backtranslation_train.workers")]
    out = data.backtranslation_dir
    assert sorted(p.name for p in out.iterdir()) == ["ASL.pt", "DGS.pt", "languages.json", "metrics.json",
                                                     "notes.txt", "skipped.jsonl"]
    assert (out / "DGS.pt").read_bytes() == b"DGS"
    assert json.loads((out / "metrics.json").read_text()) == report
    assert list(report)[:2] == ["DGS/train_clips", "DGS/dev_clips"] and report["ASL/dev_clips"] == 1.0
    assert report["ASL/best_val_bleu4"] == 2.0 and report["DGS/skipped_clips"] == 1.0
    described = json.loads((out / "languages.json").read_text())
    assert {k: v["checkpoint"] for k, v in described.items()} == {"DGS": "DGS.pt", "ASL": "ASL.pt"}
    skipped = [json.loads(line) for line in (out / "skipped.jsonl").read_text().splitlines()]
    assert skipped == [
        {"clip_id": "t3", "split": "train", "language": "BSL", "reason": "language not in backtranslation.languages"},
        {"clip_id": "d2", "split": "dev", "language": "BSL",
         "reason": "isolated sign (label 1): back-translation is sentence-level"},
        {"clip_id": "t5", "split": "train", "language": "DGS", "reason": "empty text"},
        {"clip_id": "t4", "split": "train", "language": "ASL",
         "reason": "isolated sign (label 3): back-translation is sentence-level"}]


def test_the_training_stage_refuses_a_split_without_clips_or_sentences(monkeypatch, tmp_path):
    from m3t.backtranslation.config import (
        BackTranslationConfig,
        BackTranslationTrainConfig,
    )

    pipeline, _ = _fake_training(monkeypatch, [], [])
    with pytest.raises(ValueError) as err:
        pipeline.run_train_backtranslation(BackTranslationConfig(), BackTranslationTrainConfig(), _stage_data(tmp_path))
    assert str(err.value) == "the train split of ['fake'] has no clip"
    pipeline, _ = _fake_training(monkeypatch, [_fitted("a", label=1)], [])
    with pytest.raises(ValueError) as err:
        pipeline.run_train_backtranslation(BackTranslationConfig(), BackTranslationTrainConfig(), _stage_data(tmp_path))
    assert str(err.value) == ("the train split of ['fake'] has no sentence clip (only isolated signs); "
                              "back-translation needs sentences")


def test_the_skeleton_judge_reads_skeleton_views_into_its_own_folder(monkeypatch, tmp_path):
    from m3t.backtranslation.config import (
        BackTranslationConfig,
        BackTranslationTrainConfig,
    )

    pipeline, trained = _fake_training(monkeypatch, [_fitted("t1"), _fitted("t0", frames=0)], [])
    graph = SimpleNamespace(width=4, name="g", to_dict=dict)
    viewed = []

    class Skeleton:
        def __init__(self):
            self.graph = graph

        def view(self, clips):
            viewed.append([c.clip.id for c in clips])
            return [SimpleNamespace(clip=c.clip, num_frames=c.num_frames, body_model="fake",
                                    params={"skeleton": np.ones((c.num_frames, 4), np.float32)}) for c in clips]

    data = _stage_data(tmp_path)
    pipeline.run_train_backtranslation(BackTranslationConfig(pseudo_glosses=False), BackTranslationTrainConfig(),
                                       data, progress=False, skeleton=Skeleton())
    assert viewed == [["t1", "t0"], []] and trained[0][3].layout == "skeleton"
    assert (data.skeleton_judge_dir / "ASL.pt").exists() and not data.backtranslation_dir.exists()


def test_the_shards_must_share_one_body_layout(monkeypatch, tmp_path):
    from m3t.backtranslation import pipeline
    from m3t.body.protocol import Modality, ModalityLayout

    other = ModalityLayout((Modality("body", "rotation6d", ("j0",)),), ())
    layouts = {tmp_path / "a" / "train.parquet": _fake_layout(), tmp_path / "b" / "train.parquet": _fake_layout()}
    monkeypatch.setattr(pipeline, "shard_layout", lambda path: layouts[path])
    data = SimpleNamespace(shards_dirs=[tmp_path / "a", tmp_path / "b"], train_corpora=("a", "b"))
    assert pipeline._layout(data) == _fake_layout()
    layouts[tmp_path / "b" / "train.parquet"] = other
    with pytest.raises(ValueError) as err:
        pipeline._layout(data)
    assert str(err.value) == ("the corpora ['a', 'b'] were fitted with different body layouts; back-translation "
                              "needs one input layout (refit them with the same body model)")


class _RecordingRun:
    def __init__(self):
        self.calls = []

    def __getattr__(self, name):
        return lambda *args, **kwargs: self.calls.append((name, args, kwargs))


def test_train_and_log_logs_params_epochs_report_tags_and_files(monkeypatch, tmp_path):
    from contextlib import contextmanager

    from m3t.backtranslation import pipeline
    from m3t.backtranslation.config import (
        BackTranslationConfig,
        BackTranslationTrainConfig,
    )

    run, started = _RecordingRun(), []

    @contextmanager
    def fake_start(experiment, stage, tags, variant):
        started.append((experiment, stage, tags, variant))
        yield run

    monkeypatch.setattr(pipeline, "start_run", fake_start)
    monkeypatch.setattr(pipeline, "section_params", lambda **sections: sorted(sections))
    data = SimpleNamespace(train_corpora=("c1", "c2"), backtranslation_dir=tmp_path / "bt",
                           skeleton_judge_dir=tmp_path / "sk")

    def fake_stage(model_cfg, train_cfg, data_, progress, skeleton, on_epoch):
        out = data.backtranslation_dir if skeleton is None else data.skeleton_judge_dir
        out.mkdir(parents=True, exist_ok=True)
        (out / "languages.json").write_text(json.dumps({"ASL": {"gloss_source": "annotated"}}))
        on_epoch("ASL", {"loss": 1.0}, 3)
        return {"ASL/best_epoch": 3.0}

    monkeypatch.setattr(pipeline, "run_train_backtranslation", fake_stage)
    report = pipeline.train_and_log(BackTranslationConfig(), BackTranslationTrainConfig(seed=4), data, "exp")
    assert report == {"ASL/best_epoch": 3.0}
    assert started == [("exp", "train-backtranslation", {"input_layout": "model", "corpus": "c1,c2", "seed": "4"},
                        "model")]
    assert run.calls == [
        ("log_params", (["backtranslation", "backtranslation_train", "data"],), {}),
        ("log_metrics", ({"ASL/loss": 1.0},), {"step": 3}),
        ("log_metrics", ({"ASL/best_epoch": 3.0},), {}),
        ("set_tags", ({"gloss_source/ASL": "annotated"},), {}),
        *[("log_artifact", (tmp_path / "bt" / name,), {}) for name in ("metrics.json", "languages.json",
                                                                         "skipped.jsonl")]]
    run.calls.clear()
    skeleton = SimpleNamespace(graph=SimpleNamespace(name="g"))
    pipeline.train_and_log(BackTranslationConfig(), BackTranslationTrainConfig(), data, "exp", skeleton=skeleton)
    assert started[-1] == ("exp", "train-backtranslation-skeleton",
                           {"input_layout": "skeleton (g)", "corpus": "c1,c2", "seed": "0"}, "skeleton (g)")
    assert run.calls[-1] == ("log_artifact", (tmp_path / "sk" / "skipped.jsonl",), {})


def test_evaluate_and_log_tags_the_ground_truth_run(monkeypatch, tmp_path):
    from contextlib import contextmanager

    from m3t.backtranslation import pipeline
    from m3t.backtranslation.config import BackTranslationConfig

    run, started = _RecordingRun(), []

    @contextmanager
    def fake_start(experiment, stage, tags, variant):
        started.append((experiment, stage, tags, variant))
        yield run

    monkeypatch.setattr(pipeline, "start_run", fake_start)
    monkeypatch.setattr(pipeline, "section_params", lambda **sections: sorted(sections))
    def fake_evaluate(cfg, data, split):
        return pipeline.BackTranslationReport({}, [], {"slt_bleu4": float(len(split))})

    monkeypatch.setattr(pipeline, "run_evaluate_backtranslation", fake_evaluate)
    data = SimpleNamespace(metrics=lambda name: tmp_path / name)
    assert pipeline.evaluate_and_log(BackTranslationConfig(beam_size=3), data, "exp", split="dev") == {"slt_bleu4": 3.0}
    assert started == [("exp", "evaluate-backtranslation", {"source": "ground-truth", "split": "dev",
                                                             "text_metric_definition": "slt", "beam_size": "3"},
                        "ground truth, dev")]
    assert run.calls == [("log_params", (["backtranslation", "data"],), {}),
                         ("log_metrics", ({"slt_bleu4": 3.0},), {}),
                         *[("log_artifact", (tmp_path / "backtranslation" / name,), {})
                           for name in ("metrics.json", "per_clip.csv", "skipped.jsonl")]]
    pipeline.evaluate_and_log(BackTranslationConfig(), data, "exp")
    assert started[-1][2]["split"] == "test" and started[-1][3] == "ground truth, test"


def test_training_a_tiny_model_records_epochs_validates_and_keeps_its_checkpoints(tmp_path):
    """Two epochs on two clips: every epoch's record (training losses, lr, epoch), validation every epoch on the
    dev split with ``val_`` scores and the selection number, the best checkpoint and the resumable last one
    written and loadable with the corpus' language, settings and data version; a corpus without training clips
    is refused."""
    import dataclasses

    from m3t.backtranslation.checkpoint import load_backtranslation
    from m3t.backtranslation.config import BackTranslationTrainConfig
    from m3t.backtranslation.train import train_backtranslation

    corpus = _language_corpus("ASL", train_n=2, dev_n=1)
    corpus.train = [sample("a", np.arange(6.0).reshape(2, 3), (4, 5), (2,)), sample("b", np.ones((3, 3)), (5,))]
    corpus.dev = [Sample("d", np.ones((2, 3), np.float32), (4,), (), "hello")]
    spec = SimpleNamespace(dim=3, to_dict=lambda: {"layout": "model", "streams": [["body", 3]], "source_layout": "{}",
                                                   "layout_name": "x"})
    cfg = BackTranslationTrainConfig(epochs=2, batch_size=2, eval_every=1, device="cpu", lr_patience=1)
    epochs = []
    result = train_backtranslation(_tiny_cfg(max_text_tokens=3), cfg, corpus, spec, "dv", tmp_path / "best.pt",
                                   tmp_path / "last.pt", on_epoch=lambda record, epoch: epochs.append((epoch, record)),
                                   progress=False)
    assert [e for e, _ in epochs] == [1, 2] and len(result.history) == 2
    record = result.history[-1]
    assert {"epoch", "lr", "train_loss", "train_translation_loss", "train_gloss_ctc_loss", "val_bleu4",
            "val_rouge_l", "val_selection"} <= set(record)
    assert record["val_selection"] == pytest.approx(record["val_bleu4"] + 1e-6 * record["val_rouge_l"])
    assert result.best["epoch"] in (1, 2) and result.model.dims.gloss_vocab == 5
    torch.testing.assert_close(result.model.feature_mean, torch.tensor([1.2, 1.6, 2.0]))  # the 5 train frames' mean
    best = load_backtranslation(tmp_path / "best.pt")
    assert best.language == "ASL" and best.data_version == "dv" and best.gloss_source == "annotated"
    assert best.train_config["lr_patience"] == 1 and "cache_dir" in best.train_config
    assert (tmp_path / "last.pt").exists()
    no_ctc = train_backtranslation(_tiny_cfg(max_text_tokens=3, gloss_ctc_weight=0.0),
                                   dataclasses.replace(cfg, epochs=1), corpus, spec, "dv", tmp_path / "b2.pt",
                                   progress=False)
    assert no_ctc.model.gloss_head is None and "train_gloss_ctc_loss" not in no_ctc.history[-1]
    corpus.train = []
    with pytest.raises(ValueError) as err:
        train_backtranslation(_tiny_cfg(), cfg, corpus, spec, "dv", tmp_path / "x.pt")
    assert str(err.value) == "language 'ASL': no training clip"


def test_smplx240_names_every_missing_stream_and_joint():
    """The refusal lists, per SignSparK stream, a missing or non-rotation stream or the absent joints; a valid
    SMPL-X layout indexes each joint by its label position and describes itself as the 240-d input."""
    from m3t.backtranslation.data import InputSpec
    from m3t.backtranslation.smplx240 import SIGNSPARK_BODY, smplx240_index
    from m3t.body.protocol import Modality, ModalityLayout
    from m3t.body.smplfx_build import hand_joint_names

    body = ("extra",) + tuple(reversed(SIGNSPARK_BODY))
    layout = ModalityLayout((Modality("body", "rotation6d", body),
                             Modality("left_hand", "scalar", hand_joint_names("left")),
                             Modality("right_hand", "rotation6d", hand_joint_names("right")[1:])), ())
    with pytest.raises(ValueError) as err:
        smplx240_index(layout, "odd")
    assert str(err.value) == (
        "the odd body layout cannot give SignSparK's 240-d SMPL-X input: it lacks the SMPL-X joints left_hand: no 6D "
        f"rotation stream named 'left_hand'; right_hand: {hand_joint_names('right')[0]}. Use "
        "backtranslation.input_layout: model, or fit the corpus with an SMPL-X based body (body.model: smplfx)")
    smplx = ModalityLayout((Modality("body", "rotation6d", body),
                            Modality("left_hand", "rotation6d", hand_joint_names("left")),
                            Modality("right_hand", "rotation6d", hand_joint_names("right"))), ())
    index = smplx240_index(smplx)
    assert index["body"].tolist() == list(range(10, 0, -1)) and index["left_hand"].tolist() == list(range(15))
    spec = InputSpec.from_layout("smplx240", smplx, "smplfx")
    assert spec.describe() == "smplx240 (SignSparK_BT, 240-d)" and spec.dim == 240
    without_hands = ModalityLayout((Modality("body", "rotation6d", body),), ())
    with pytest.raises(ValueError, match="the layout body layout cannot give"):
        smplx240_index(without_hands)
