"""The SMLM training step and evaluator in detail (:mod:`m3t.smlm.train`, :mod:`m3t.smlm.generate`,
:mod:`m3t.smlm.evaluate`): one unclipped step unless asked to clip, the batch's masks reaching the model, the clips
a token shard cannot give as examples (and why), the evaluator's batching, progress output, decoding and scoring,
the training loop's progress bar, steps per epoch, checkpoints, a padded batch's logits and an absent CUDA device.
Written to pin behaviours that mutation testing found unchecked; tiny untrained models only.
"""
from __future__ import annotations

import copy
import dataclasses
import re

import numpy as np
import pytest
import torch
from builders import TINY_VAE, tiny_tokenizers, tiny_train_cfg

from m3t.body.rotations import mirror_rotations
from m3t.corpora.clip import Clip
from m3t.shards.schema import FittedClip
from m3t.shards.tokens import TokenInfo

CODEBOOKS = {"body": 100, "left_hand": 180, "right_hand": 180, "face": 216}  # TINY_TOKENIZER's levels


SENTENCES = {"ASL": ["the friend buys a red car", "my father drinks water", "the child reads"],
             "CSL": ["我 的 朋友 买 车"]}


@pytest.fixture(scope="module")
def smlm_parts():
    from m3t.smlm.config import SMLMConfig
    from m3t.smlm.data import Example
    from m3t.smlm.model import SignMotionLM, SMLMDims
    from m3t.smlm.vocab import MOTION_STREAMS, build_vocabulary

    cfg = SMLMConfig(d_model=32, encoder_layers=1, decoder_layers=1, attention_heads=2, ffn_dim=64, dropout=0.0,
                     max_text_tokens=6, max_motion_tokens=6, text_vocab_size=80)
    vocab = build_vocabulary([t for ts in SENTENCES.values() for t in ts], SENTENCES, CODEBOOKS, cfg.text_vocab_size)
    rng = np.random.default_rng(0)
    examples = []
    for language, texts in SENTENCES.items():
        for i, text in enumerate(texts):
            steps = 2 + 3 * (i % 2)  # 2 and 5 steps: batches with padded motion
            motion = np.stack([rng.integers(0, CODEBOOKS[s], steps) for s in MOTION_STREAMS], axis=1)
            examples.append(Example(f"{language}{i}", language, text,
                                    np.asarray(vocab.encode_text(text, None)[:cfg.max_text_tokens]), motion))
    torch.manual_seed(0)
    model = SignMotionLM(cfg, SMLMDims.from_vocabulary(vocab)).eval()
    return model, vocab, examples


def _sgd(model, lr: float = 1.0):
    optim = torch.optim.SGD(model.parameters(), lr=lr)
    return optim, torch.optim.lr_scheduler.LambdaLR(optim, lambda step: 0.5 ** step)


@pytest.mark.parametrize("task", ["production", "translation"])
def test_train_step_takes_one_unclipped_step_unless_asked_to_clip(smlm_parts, task):
    from m3t.smlm.data import production_batch, translation_batch
    from m3t.smlm.train import task_loss, train_step

    torch.set_num_threads(1)
    model, vocab, examples = smlm_parts
    batch = (production_batch if task == "production" else translation_batch)(examples[:3], vocab)
    reference = copy.deepcopy(model)
    loss = task_loss(reference, batch)
    loss.backward()
    grads = {n: p.grad.clone() for n, p in reference.named_parameters() if p.grad is not None}
    norm = torch.cat([g.flatten() for g in grads.values()]).norm()
    assert norm > 1.0, "the check below needs a gradient that a clip at 1 would shorten"

    plain = copy.deepcopy(model)
    optim, scheduler = _sgd(plain)
    out = train_step(plain, batch, optim, scheduler)
    assert list(out) == [f"{task}_loss"] and out[f"{task}_loss"] == pytest.approx(loss.item(), rel=1e-5)
    assert scheduler.get_last_lr() == [0.5], "the LR schedule advances once per step"
    before = dict(model.named_parameters())
    for name, p in plain.named_parameters():  # SGD at lr 1: p - grad, the full gradient
        expected = before[name] - grads[name] if name in grads else before[name]
        assert torch.allclose(p, expected, atol=1e-5), name

    clipped = copy.deepcopy(model)
    optim, scheduler = _sgd(clipped)
    train_step(clipped, batch, optim, scheduler, grad_clip=0.01)
    step = torch.cat([(before[n] - p).detach().flatten() for n, p in clipped.named_parameters()]).norm()
    assert float(step) == pytest.approx(0.01, rel=1e-3)


def test_task_loss_runs_each_task_with_the_batchs_masks(smlm_parts, monkeypatch):
    from m3t.smlm.data import IGNORE, production_batch, translation_batch
    from m3t.smlm.train import production_loss, task_loss, translation_loss

    model, vocab, examples = smlm_parts
    calls = []
    for method in ("production", "translation"):
        original = getattr(model, method)

        def spy(*args, _original=original, _method=method):
            calls.append((_method, args))
            return _original(*args)

        monkeypatch.setattr(model, method, spy)
    with torch.no_grad():
        prod = production_batch(examples[:2], vocab)  # 2 and 5 steps: the first is padded
        assert (prod.targets[0, 3:] == IGNORE).all() and not prod.motion_mask[0, 3:].any()
        loss = task_loss(model, prod, smoothing=0.1)
        method, args = calls.pop()
        assert method == "production"
        for got, want in zip(args, (prod.text_ids, prod.text_mask, prod.motion_in, prod.motion_mask)):
            assert got is want
        assert torch.equal(loss, production_loss(model.production(*args), prod.targets, 0.1))
        trans = translation_batch(examples[:2], vocab)
        loss = task_loss(model, trans)
        method, args = calls.pop()
        assert method == "translation"
        for got, want in zip(args, (trans.motion_ids, trans.motion_mask, trans.text_in, trans.text_mask)):
            assert got is want
        assert torch.equal(loss, translation_loss(model.translation(*args), trans.targets))


@pytest.fixture(scope="module")
def evaluator(body, smlm_parts):
    from m3t.smlm.evaluate import SMLMEvaluator

    _, vocab, examples = smlm_parts
    dims = {"body": body.layout.dims["body"], "hand": body.layout.dims["right_hand"], "face": body.layout.dims["face"]}
    references = {}
    for k, e in enumerate(examples):
        params = {n: v.numpy() for n, v in body.rest_params(4 * len(e.motion)).items()}
        clip = Clip(e.clip_id, "synthetic", "test", e.language, "s1", e.text, "G", f"{e.clip_id}.npz", 25.0)
        references[e.clip_id] = FittedClip(clip, "k", params, body.default_identity().numpy(), {}, {}, body.name)
    return SMLMEvaluator(body, tiny_tokenizers(dims, seed=4), vocab, examples, references, batch_size=3)


def test_evaluator_translates_every_clip_in_batches_and_shows_progress_only_when_asked(evaluator, smlm_parts, capfd):
    from m3t.smlm.generate import translate

    model, vocab, examples = smlm_parts
    capfd.readouterr()
    texts = evaluator.translate(model)
    assert "translate" not in capfd.readouterr().err, "no progress bar unless asked"
    assert list(texts) == [e.clip_id for e in examples]
    for start in (0, 3):  # batches of 3: [0, 1, 2] and [3]
        chunk = examples[start: start + 3]
        expected = translate(model, vocab, [e.motion for e in chunk], [e.language for e in chunk])
        assert [texts[e.clip_id] for e in chunk] == expected
    assert evaluator.translate(model, progress=True) == texts
    err = capfd.readouterr().err
    assert "translate" in err and "4/4" in err


def test_evaluator_decodes_generated_tokens_with_the_frozen_tokenizers(evaluator, body):
    from m3t.smlm.generate import GeneratedMotion

    tokens = {"body": np.array([0, 99, 5]), "left_hand": np.array([1, 2, 179]), "right_hand": np.array([3, 4, 5]),
              "face": np.array([215, 0, 7])}
    params = evaluator.motion_params(GeneratedMotion(tokens, True))
    assert sorted(params) == sorted(body.layout.names)
    tok = evaluator.tokenizers
    as_ids = {k: torch.as_tensor(v)[None] for k, v in tokens.items()}
    assert np.allclose(params["body"], tok["body"].decode(as_ids["body"])[0].numpy(), atol=1e-6)
    assert np.allclose(params["right_hand"], tok["hand"].decode(as_ids["right_hand"])[0].numpy(), atol=1e-6)
    left = mirror_rotations(tok["hand"].decode(as_ids["left_hand"])[0])
    assert np.allclose(params["left_hand"], left.numpy(), atol=1e-6)
    assert np.allclose(params["face"], tok["face"].decode(as_ids["face"])[0].numpy(), atol=1e-6)
    assert all(v.shape == (12, body.layout.dims[k]) for k, v in params.items())


def _token_clip(cid: str, language: str, text: str, steps: int, split: str = "dev", streams=None, seed: int = 0):
    from m3t.shards.tokens import TokenClip

    rng = np.random.default_rng(seed)
    tokens = {s: rng.integers(0, CODEBOOKS[s], steps) for s in (streams or CODEBOOKS)}
    return TokenClip(Clip(cid, "synthetic", split, language, "s1", text, "G", f"{cid}.npz", 25.0), 4 * steps, tokens)


def test_examples_from_shard_skips_or_cuts_each_unusable_clip_and_says_why(smlm_parts):
    from pathlib import Path

    from m3t.shards.tokens import TokenShard
    from m3t.smlm.data import examples_from_shard
    from m3t.smlm.vocab import MOTION_STREAMS

    _, vocab, _ = smlm_parts
    long_text, short_text = SENTENCES["ASL"][0], SENTENCES["ASL"][2]
    n_long, n_short = len(vocab.encode_text(long_text, None)), len(vocab.encode_text(short_text, None))
    limit_text, limit_motion = n_short, 10
    assert n_long > limit_text
    clips = (
        _token_clip("ok", "ASL", short_text, 4, seed=1),
        _token_clip("dgs-1", "DGS", short_text, 4, seed=2),  # a language the vocabulary was not built for
        _token_clip("empty", "CSL", SENTENCES["CSL"][0], 0, split="test", seed=3),
        _token_clip("long", "ASL", long_text, 12, seed=4),  # both limits
        _token_clip("faceless", "ASL", short_text, 4, streams=["body", "left_hand", "right_hand"], seed=5),
        _token_clip("long-motion", "CSL", SENTENCES["CSL"][0], 11, seed=6),  # the motion limit only
    )
    shard = TokenShard(Path("dev.parquet"), TokenInfo(CODEBOOKS, 4, {}), clips)
    both = (f"text of {n_long} tokens > smlm.max_text_tokens = {limit_text}; "
            f"12 motion steps > smlm.max_motion_tokens = {limit_motion}")
    motion_only = f"11 motion steps > smlm.max_motion_tokens = {limit_motion}"
    unusable = [
        {"clip_id": "dgs-1", "split": "dev",
         "reason": "unknown language 'DGS'; this vocabulary knows ['ASL', 'CSL'] "
                   "(languages come from the training corpus)"},
        {"clip_id": "empty", "split": "test", "reason": "no motion tokens"},
    ]
    faceless = {"clip_id": "faceless", "split": "dev", "reason": "'face'"}

    # training: a clip over either limit is skipped with the limits it breaks
    examples, skipped = examples_from_shard(shard, vocab, limit_text, limit_motion)
    assert [e.clip_id for e in examples] == ["ok"]
    assert skipped == [unusable[0], unusable[1], {"clip_id": "long", "split": "dev", "reason": both}, faceless,
                       {"clip_id": "long-motion", "split": "dev", "reason": motion_only}]

    # evaluation: such a clip is kept, cut to the limits, and listed in ``cut``
    cut: list[dict[str, str]] = []
    examples, skipped = examples_from_shard(shard, vocab, limit_text, limit_motion, cut)
    assert skipped == [*unusable, faceless]
    assert cut == [{"clip_id": "long", "split": "dev", "reason": both + " (kept, cut to the limit)"},
                   {"clip_id": "long-motion", "split": "dev", "reason": motion_only + " (kept, cut to the limit)"}]
    by_id = {e.clip_id: e for e in examples}
    assert list(by_id) == ["ok", "long", "long-motion"]
    for tc in (clips[0], clips[3], clips[5]):
        e = by_id[tc.clip.id]
        assert (e.language, e.text) == (tc.clip.language, tc.clip.text)
        assert e.text_ids.dtype == np.int64
        assert e.text_ids.tolist() == vocab.encode_text(tc.clip.text, None)[:limit_text]
        steps = min(tc.num_tokens, limit_motion)
        assert e.motion.dtype == np.int64 and e.motion.shape == (steps, len(MOTION_STREAMS))
        for k, stream in enumerate(MOTION_STREAMS):  # columns in stream order, whatever the shard's order
            assert e.motion[:, k].tolist() == tc.tokens[stream][:steps].tolist(), (tc.clip.id, stream)


def test_evaluator_generates_every_clip_in_batches_and_shows_progress_only_when_asked(evaluator, smlm_parts, capfd):
    from m3t.smlm.generate import generate_motion

    torch.set_num_threads(1)
    model, vocab, examples = smlm_parts
    capfd.readouterr()
    generated = evaluator.generate(model)
    assert "generate" not in capfd.readouterr().err, "no progress bar unless asked"
    assert list(generated) == [e.clip_id for e in examples]
    for start in (0, 3):  # batches of 3: [0, 1, 2] and [3]
        chunk = examples[start: start + 3]
        expected = generate_motion(model, vocab, [e.text for e in chunk], [e.language for e in chunk],
                                   truncate_text=True)
        for e, want in zip(chunk, expected):
            got = generated[e.clip_id]
            assert got.stopped == want.stopped and list(got.tokens) == list(want.tokens)
            for stream in want.tokens:
                assert np.array_equal(got.tokens[stream], want.tokens[stream]), (e.clip_id, stream)
    again = evaluator.generate(model, progress=True)
    err = capfd.readouterr().err
    assert "generate" in err and "4/4" in err
    assert all(np.array_equal(again[c].tokens["body"], generated[c].tokens["body"]) for c in generated)


def test_evaluator_scores_generated_tokens_per_clip_overall_and_per_group(evaluator, smlm_parts, monkeypatch,
                                                                         tmp_path):
    """The evaluator's part of scoring: what it hands the motion scorer (decoded predictions, the rest pose for an
    empty one, groups, identities) and the rows and summary it builds from the scores (the scorer's own numbers
    are pinned in tests/metrics/test_scorer.py; here a recording stand-in returns known ones)."""
    from m3t.metrics.scorer import ClipScore, MotionScores
    from m3t.metrics.text import translation_metrics_by_language
    from m3t.smlm.evaluate import SELECTION_METRIC
    from m3t.smlm.generate import GeneratedMotion
    from m3t.smlm.vocab import MOTION_STREAMS

    class RecordingScorer:
        frame_budget = 10 ** 9  # every clip in one call (the runs the evaluator makes under a budget: below)

        def __init__(self):
            self.calls = []

        def score(self, pairs):
            self.calls.append(list(pairs))
            rank = {"ASL0": 1, "ASL1": 2, "ASL2": 3, "CSL0": 4}  # a clip's figures do not depend on its run
            per_clip = [ClipScore(p.clip_id, p.group, len(next(iter(p.prediction.values()), [])),
                                  {"dtw_jpe_body_m": 0.1 * rank[p.clip_id], "dtw_jpe_hand_m": 0.02 * rank[p.clip_id]})
                        for p in pairs]
            if not pairs:
                return MotionScores([], {}, {}, 0.0)
            overall = {"dtw_jpe_body_m": 0.25, "dtw_jpe_hand_m": 0.05}
            groups = {"synthetic/ASL": {"dtw_jpe_body_m": 0.2}, "synthetic/CSL": {"dtw_jpe_body_m": 0.4}}
            return MotionScores(per_clip, overall, groups, 0.25)

    torch.set_num_threads(1)
    _, _, examples = smlm_parts
    scorer = RecordingScorer()
    monkeypatch.setattr(evaluator, "scorer", scorer)
    steps = {"ASL0": 3, "ASL1": 0, "ASL2": 2, "CSL0": 1}  # ASL1: EOS at the first step, an empty prediction
    stopped = {"ASL0": True, "ASL1": True, "ASL2": False, "CSL0": False}
    rng = np.random.default_rng(3)
    generated = {cid: GeneratedMotion({s: rng.integers(0, CODEBOOKS[s], n) for s in MOTION_STREAMS}, stopped[cid])
                 for cid, n in steps.items()}
    translations = {"ASL0": "the friend buys a car", "ASL1": "", "ASL2": "the child reads", "CSL0": "我 的 朋友"}
    report = evaluator.score(generated, translations)

    (pairs,) = scorer.calls
    assert [p.clip_id for p in pairs] == [e.clip_id for e in examples]
    assert [p.group for p in pairs] == ["synthetic/ASL"] * 3 + ["synthetic/CSL"]
    for p in pairs:
        ref = evaluator.references[p.clip_id]
        assert p.identity is ref.identity and p.reference is None  # the stored reference points are used
        if steps[p.clip_id] == 0:
            assert p.prediction == {}, "an empty generation is scored as an empty prediction"
            continue
        expected = evaluator.motion_params(generated[p.clip_id])
        assert sorted(p.prediction) == sorted(expected)
        for k, v in expected.items():
            assert v.shape[0] == 4 * steps[p.clip_id] and np.array_equal(p.prediction[k], v), (p.clip_id, k)

    assert report.per_clip == [
        {"clip_id": "ASL0", "group": "synthetic/ASL", "steps": 3, "stopped": 1.0, "dtw_jpe_body_m": 0.1,
         "dtw_jpe_hand_m": 0.02},
        {"clip_id": "ASL1", "group": "synthetic/ASL", "steps": 0, "stopped": 1.0, "dtw_jpe_body_m": 0.2,
         "dtw_jpe_hand_m": 0.04},
        {"clip_id": "ASL2", "group": "synthetic/ASL", "steps": 2, "stopped": 0.0, "dtw_jpe_body_m": pytest.approx(0.3),
         "dtw_jpe_hand_m": 0.06},
        {"clip_id": "CSL0", "group": "synthetic/CSL", "steps": 1, "stopped": 0.0, "dtw_jpe_body_m": 0.4,
         "dtw_jpe_hand_m": 0.08},
    ]
    assert all(isinstance(r["stopped"], float) for r in report.per_clip)
    text_metrics = translation_metrics_by_language([translations[e.clip_id] for e in examples],
                                                   [e.text for e in examples], [e.language for e in examples])
    assert report.summary == {
        "dtw_jpe_body_m": 0.25, "dtw_jpe_hand_m": 0.05,
        "stopped_rate": 0.5, "empty_rate": 0.25, "mean_steps": 1.5,
        SELECTION_METRIC: pytest.approx(0.15),  # the mean of body and hand DTW-JPE
        "synthetic/ASL/dtw_jpe_body_m": pytest.approx(0.2), "synthetic/ASL/dtw_jpe_hand_m": pytest.approx(0.04),
        "synthetic/CSL/dtw_jpe_body_m": 0.4, "synthetic/CSL/dtw_jpe_hand_m": 0.08,
        **text_metrics,
    }
    assert report.generated is generated and report.translations == translations
    # a budget below every clip: each clip decoded and scored in a run of its own, the same report
    scorer.frame_budget, scorer.calls = 1, []
    assert evaluator.score(generated, translations).summary == report.summary
    assert [[p.clip_id for p in call] for call in scorer.calls] == [[e.clip_id] for e in examples]
    # a killed scoring resumes from its journal: the clips it holds are not scored again, the same report
    from m3t.journal import Journal
    from m3t.smlm.evaluate import JOURNAL_SECTION

    full = Journal(tmp_path / "full.journal", "k")
    evaluator.score(generated, translations, full)
    killed = Journal(tmp_path / "killed.journal", "k")
    killed.add(JOURNAL_SECTION, [full.done(JOURNAL_SECTION)[c] for c in ("ASL0", "ASL1")])
    scorer.calls = []
    assert evaluator.score(generated, translations, Journal(tmp_path / "killed.journal", "k")).summary == report.summary
    assert [[p.clip_id for p in call] for call in scorer.calls] == [["ASL2"], ["CSL0"]]
    assert sorted(Journal(tmp_path / "killed.journal", "k").done(JOURNAL_SECTION)) == ["ASL0", "ASL1", "ASL2", "CSL0"]

    # the remaining checks are about translations and lookups: a stand-in decoder keeps them quick
    monkeypatch.setattr(evaluator, "motion_params", lambda g: {"body": np.zeros((4 * len(g.tokens["body"]), 1))})
    without = evaluator.score(generated)  # no translations: motion only
    assert without.translations == {} and not any(k.startswith("translation") for k in without.summary)

    lost = {k: v for k, v in generated.items() if k != "CSL0"}
    with pytest.raises(KeyError, match=r"no generated motion for clips \['CSL0'\] \(of 1\); rerun the generate stage"):
        evaluator.score(lost)
    with pytest.raises(KeyError, match=r"no translation for clips \['ASL1', 'ASL2'\] \(of 2\); rerun the generate"):
        evaluator.score(generated, {"ASL0": "a", "CSL0": "b"})

    monkeypatch.setattr(evaluator, "examples", [])  # no evaluation clip at all: rates of 0, never selected
    nothing = evaluator.score({}, {})
    assert nothing.per_clip == []
    assert {k: v for k, v in nothing.summary.items() if not k.startswith("translation")} == {
        "stopped_rate": 0.0, "empty_rate": 0.0, "mean_steps": 0.0, SELECTION_METRIC: float("inf")}


def test_smlm_training_shows_its_epoch_bar_only_on_the_main_rank_and_when_asked(smlm_parts, tmp_path, capfd):
    from m3t.runtime import DistributedContext
    from m3t.smlm.config import SMLMTrainConfig
    from m3t.smlm.train import train_smlm

    torch.set_num_threads(1)
    model, vocab, examples = smlm_parts
    cfg = SMLMTrainConfig(epochs=1, batch_size=4, warmup_steps=1, device="cpu")

    def train(name, **kwargs):
        capfd.readouterr()
        result = train_smlm(model.cfg, cfg, vocab, examples, None, "v", tmp_path / f"{name}.pt", **kwargs)
        return result, capfd.readouterr().err

    result, err = train("shown")
    assert len(result.history) == 1
    assert re.search(r"(^|\r)smlm: +100%.* 1/1 ", err), "the bar names the model and counts epochs"
    _, err = train("quiet", progress=False)
    assert "smlm" not in err
    # another rank (here without a process group, so no epoch is run: a rank's share needs its peers)
    result, err = train("rank1", dist_ctx=DistributedContext(rank=1), stop_after_epochs=0)
    assert result.history == [] and "smlm" not in err, "only rank 0 draws the bar"


# ------------------------------------------------------------------------------------------------ quantisers, steps
def test_generation_refuses_an_empty_batch_and_unmatched_languages_before_touching_the_model():
    from m3t.smlm.generate import generate_motion, translate
    from m3t.smlm.vocab import VocabularyError

    class _Vocab:
        def check_language(self, language):
            if language != "DGS":
                raise VocabularyError(f"unknown language {language!r}")

    for run in (generate_motion, translate):
        with pytest.raises(VocabularyError, match="^nothing to generate: the input list is empty$"):
            run(None, _Vocab(), [], [])
        with pytest.raises(ValueError, match="^2 inputs but 1 languages; give one language per input$"):
            run(None, _Vocab(), ["a", "b"], ["DGS"])
        with pytest.raises(VocabularyError, match="unknown language 'BSL'"):
            run(None, _Vocab(), ["a", "b"], ["DGS", "BSL"])


def test_steps_per_epoch_split_whole_batches_evenly_across_ranks():
    from m3t.smlm.train import steps_per_epoch

    assert steps_per_epoch(10, 3) == 4 and type(steps_per_epoch(10, 3)) is int
    assert steps_per_epoch(10, 3, world_size=1) == 4
    out = steps_per_epoch(10, 3, world_size=3)
    assert out == 1 and type(out) is int  # 4 batches over 3 ranks: each rank runs 1 step
    assert steps_per_epoch(12, 3, world_size=2) == 2 and type(steps_per_epoch(12, 3, world_size=2)) is int
    assert steps_per_epoch(0, 3) == 0


def test_a_trained_smlm_checkpoint_keeps_its_step_count_and_training_settings(smlm_parts, tmp_path):
    from m3t.smlm.checkpoint import load_smlm
    from m3t.smlm.config import SMLMTrainConfig
    from m3t.smlm.train import steps_per_epoch, train_smlm

    torch.set_num_threads(1)
    model, vocab, examples = smlm_parts
    cfg = SMLMTrainConfig(epochs=2, batch_size=2, warmup_steps=1, device="cpu", lr=3e-4)
    train_smlm(model.cfg, cfg, vocab, examples, None, "data-v7", tmp_path / "best.pt", progress=False)
    loaded = load_smlm(tmp_path / "best.pt")
    assert loaded.epoch == 2 and loaded.data_version == "data-v7"
    assert loaded.step == 2 * steps_per_epoch(len(examples), 2) == 4
    settings = loaded.train_config
    assert settings["epochs"] == 2 and settings["batch_size"] == 2 and settings["lr"] == 3e-4
    assert settings["device"] == "cpu" and settings["warmup_steps"] == 1
    assert all(isinstance(v, (bool, int, float, str)) for v in settings.values())


def test_loading_a_missing_or_foreign_smlm_checkpoint_names_it_and_the_stage_to_run(tmp_path):
    from m3t.smlm.checkpoint import FORMAT as SMLM_FORMAT
    from m3t.smlm.checkpoint import load_smlm

    missing = tmp_path / "smlm" / "model.pt"
    with pytest.raises(FileNotFoundError) as err:
        load_smlm(missing)
    assert str(err.value) == f"SMLM checkpoint {missing} not found; run `dvc repro train-smlm` first"
    other = tmp_path / "tokenizer.pt"
    torch.save({"format": "m3t-tokenizer-v1", "state_dict": {}}, other)
    with pytest.raises(ValueError, match="not an m3t SMLM checkpoint") as err:
        load_smlm(other)
    assert str(other) in str(err.value) and "'m3t-tokenizer-v1'" in str(err.value)
    assert f"expected {SMLM_FORMAT!r}" in str(err.value)
    torch.save({"state_dict": {}}, other)  # no format at all: refused too, before any key is read
    with pytest.raises(ValueError, match=f"format None, expected {SMLM_FORMAT!r}"):
        load_smlm(other)


def test_padded_batch_gives_each_example_the_logits_it_gets_alone(smlm_parts):
    """Both tasks: the decoder attends to the real encoder states only, never to the padded memory."""
    from m3t.smlm.data import production_batch, translation_batch

    torch.set_num_threads(1)
    model, vocab, examples = smlm_parts
    short = dataclasses.replace(examples[2], text_ids=examples[2].text_ids[:2])  # 2 text tokens against 6
    pair = [examples[0], short]
    with torch.no_grad():
        batch = production_batch(pair, vocab)
        assert not batch.text_mask.all(), "the shorter text is padded"
        together = model.production(batch.text_ids, batch.text_mask, batch.motion_in, batch.motion_mask)
        for i, example in enumerate(pair):
            one = production_batch([example], vocab)
            alone = model.production(one.text_ids, one.text_mask, one.motion_in, one.motion_mask)
            steps = one.motion_in.shape[1]
            for head, logits in alone.items():
                assert torch.allclose(together[head][i, :steps], logits[0], atol=1e-5), (example.clip_id, head)
        pair = [examples[0], examples[1]]
        batch = translation_batch(pair, vocab)
        assert not batch.motion_mask.all(), "the shorter motion is padded"
        together = model.translation(batch.motion_ids, batch.motion_mask, batch.text_in, batch.text_mask)
        for i, example in enumerate(pair):
            one = translation_batch([example], vocab)
            alone = model.translation(one.motion_ids, one.motion_mask, one.text_in, one.text_mask)
            assert torch.allclose(together[i, :one.text_in.shape[1]], alone[0], atol=1e-5), example.clip_id


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_training_on_a_cuda_device_that_is_absent_is_refused_not_run_on_the_cpu(smlm_parts, tmp_path):
    from m3t.smlm.config import SMLMTrainConfig
    from m3t.smlm.train import train_smlm
    from m3t.tokenizers.train import train_tokenizer

    model, vocab, examples = smlm_parts
    cfg = SMLMTrainConfig(epochs=1, batch_size=4, warmup_steps=1, device="cuda")
    with pytest.raises(RuntimeError, match="device 'cuda' requested but no CUDA device is visible"):
        train_smlm(model.cfg, cfg, vocab, examples, None, "v", tmp_path / "best.pt", progress=False)
    assert not (tmp_path / "best.pt").exists()
    tok_cfg = tiny_train_cfg(tmp_path / "tok", 1, 4, device="cuda")
    with pytest.raises(RuntimeError, match="device 'cuda' requested but no CUDA device is visible"):
        train_tokenizer("face", TINY_VAE, tok_cfg,
                        [np.zeros((16, 3), dtype=np.float32)], None, "v", progress=False)


def test_scoring_on_a_local_dask_cluster_gives_the_in_process_figures(evaluator, smlm_parts, monkeypatch):
    """fit_corpus.executor: dask scores the runs on a LocalCluster of 2 one-thread workers that build the body
    model from its config: every clip's figures equal the in-process ones exactly (an empty generation too)."""
    from m3t.body.config import BodyConfig
    from m3t.fitting.cluster import open_executor
    from m3t.fitting.config import FitCorpusConfig
    from m3t.smlm.generate import GeneratedMotion
    from m3t.smlm.vocab import MOTION_STREAMS

    _, _, examples = smlm_parts
    rng = np.random.default_rng(5)
    generated = {e.clip_id: GeneratedMotion({s: rng.integers(0, CODEBOOKS[s], 2 + k % 3) for s in MOTION_STREAMS},
                                            True) for k, e in enumerate(examples)}
    generated[examples[1].clip_id] = GeneratedMotion({s: np.zeros(0, np.int64) for s in MOTION_STREAMS}, True)
    steps = {cid: len(g.tokens["body"]) for cid, g in generated.items()}
    monkeypatch.setattr(evaluator.scorer, "frame_budget", 30)  # several runs: several tasks
    here = evaluator.score_generated(generated, steps)
    with pytest.raises(ValueError, match="needs the body model's config"):
        evaluator.score_generated(generated, steps, executor=object())
    monkeypatch.setattr(evaluator, "body_config", BodyConfig())
    with open_executor(FitCorpusConfig(executor="dask", workers=2)) as executor:
        there = evaluator.score_generated(generated, steps, executor=executor)
    assert len(here.per_clip) == len(examples) and here.empty_rate > 0
    assert there.per_clip == here.per_clip and there.summary == here.summary


def test_decoding_on_a_local_dask_cluster_gives_the_in_process_tokens_and_texts(evaluator, smlm_parts, tmp_path):
    """fit_corpus.executor: dask decodes the batches on a LocalCluster of 2 one-thread workers that load the
    checkpoint from its path: the tokens (and EOS flags) and the translations equal those made here, in one thread
    as the workers run (discrete outputs of the same computation); a file with other bytes at that path is
    refused by the worker."""
    from m3t.fitting.cluster import open_executor
    from m3t.fitting.config import FitCorpusConfig
    from m3t.smlm.checkpoint import save_smlm
    from m3t.smlm.evaluate import generate_on_worker, worker_checkpoint

    model, vocab, examples = smlm_parts
    path = save_smlm(tmp_path / "smlm.pt", model, vocab, 0, 0, "v", {})
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        here, texts_here = evaluator.generate(model), evaluator.translate(model)
    finally:
        torch.set_num_threads(threads)
    with pytest.raises(ValueError, match="needs the checkpoint's path"):
        evaluator.generate(model, executor=object())
    with open_executor(FitCorpusConfig(executor="dask", workers=2)) as executor:
        there = evaluator.generate(model, executor=executor, checkpoint=path)
        texts_there = evaluator.translate(model, executor=executor, checkpoint=path)
    assert list(there) == list(here) == [e.clip_id for e in examples] and len(examples) > evaluator.batch_size
    for cid, g in here.items():
        assert there[cid].stopped == g.stopped
        assert {s: t.tolist() for s, t in there[cid].tokens.items()} == {s: t.tolist() for s, t in g.tokens.items()}
    assert texts_there == texts_here
    checkpoint = worker_checkpoint(path)
    path.write_bytes(path.read_bytes() + b"\0")
    with pytest.raises(RuntimeError, match=r"smlm.pt seen by this worker .* is not the run's"):
        generate_on_worker(checkpoint, [examples[0].text], [examples[0].language])
