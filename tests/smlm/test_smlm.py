"""Sign Motion Language Model: vocabulary, fused inputs, heads, both tasks overfitting, greedy decoding
(EOS, cache), checkpoints, bad inputs, DDP on gloo and bf16."""
from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from m3t.corpora.clip import Clip
from m3t.runtime import DistributedContext
from m3t.shards.tokens import TokenClip, TokenInfo, TokenShard
from m3t.smlm.checkpoint import load_smlm, save_smlm
from m3t.smlm.data import IGNORE, Example, examples_from_shard, production_batch, translation_batch
from m3t.smlm.generate import generate_motion, translate
from m3t.smlm.config import SMLMConfig, SMLMTrainConfig
from m3t.smlm.model import SignMotionLM, SMLMDims
from m3t.smlm.train import run_key, train_smlm, train_step
from m3t.smlm.vocab import MOTION_STREAMS, SignVocabulary, VocabularyError, build_vocabulary
from precision_steps import bf16_and_fp32_steps

CODEBOOKS = {"body": 100, "right_hand": 180, "left_hand": 180, "face": 216}
SENTENCES = {
    "ASL": ["the friend buys a red car", "my father drinks water", "the child reads the book today"],
    "CSL": ["我 的 朋友 买 车", "老师 今天 读 书"],
}
TINY = SMLMConfig(d_model=64, encoder_layers=1, decoder_layers=1, attention_heads=4, ffn_dim=128, dropout=0.0,
                  max_text_tokens=24, max_motion_tokens=40, text_vocab_size=120)


@pytest.fixture(scope="module")
def vocab() -> SignVocabulary:
    texts = [t for ts in SENTENCES.values() for t in ts]
    return build_vocabulary(texts, SENTENCES, CODEBOOKS, TINY.text_vocab_size)


def make_examples(vocab: SignVocabulary, seed: int = 0) -> list[Example]:
    rng = np.random.default_rng(seed)
    out = []
    for language, texts in SENTENCES.items():
        for i, text in enumerate(texts):
            steps = int(rng.integers(3, 9))
            motion = np.stack([rng.integers(0, CODEBOOKS[s], steps) for s in MOTION_STREAMS], axis=1)
            out.append(Example(f"{language}{i}", language, text, np.asarray(vocab.encode_text(text, 24)), motion))
    return out


def test_vocabulary_round_trip_and_layout(vocab):
    assert len(vocab) == vocab.text_size + 2 * 5 + sum(CODEBOOKS.values())
    for stream, tag in (("body", "b"), ("left_hand", "lh"), ("right_hand", "rh"), ("face", "f")):
        for code in (0, 7, CODEBOOKS[stream] - 1):
            token = f"<{tag}_{code}>"
            assert vocab.token(vocab.token_id(token)) == token
        assert vocab.motion_ids(stream, np.array([CODEBOOKS[stream]]))[0] == vocab.eos_id  # head EOS class
    ids = {vocab.token_id(f"<{lang}_{m}>") for lang in ("ASL", "CSL") for m in ("TXT", "B", "LH", "RH", "F")}
    assert len(ids) == 10 and min(ids) == vocab.text_size
    every = [vocab.token(i) for i in range(vocab.text_size, len(vocab))]
    assert len(set(every)) == len(every), "every prompt / motion id has its own token"
    for text in SENTENCES["ASL"] + SENTENCES["CSL"]:
        assert vocab.decode_text(vocab.encode_text(text, 64)).replace(" ", "") == text.replace(" ", "")
    restored = SignVocabulary.from_dict(vocab.to_dict())
    assert restored.encode_text("my father", 64) == vocab.encode_text("my father", 64) and len(restored) == len(vocab)


@pytest.mark.parametrize("bad, message", [("", "empty text"), ("   ", "empty text"),
                                          ("word " * 200, "longer than the limit")])
def test_bad_text_is_refused(vocab, bad, message):
    with pytest.raises(VocabularyError, match=message):
        vocab.encode_text(bad, 24)


def test_unknown_language_and_out_of_codebook_are_refused(vocab):
    with pytest.raises(VocabularyError, match="unknown language 'BSL'"):
        vocab.prompt_id("BSL", "B")
    with pytest.raises(VocabularyError, match="outside"):
        vocab.motion_ids("body", np.array([101]))
    model = SignMotionLM(TINY, SMLMDims.from_vocabulary(vocab))
    with pytest.raises(VocabularyError, match="unknown language"):
        generate_motion(model, vocab, ["the friend"], ["BSL"])
    with pytest.raises(VocabularyError, match="empty"):
        generate_motion(model, vocab, [""], ["ASL"])
    with pytest.raises(VocabularyError, match="longer than the limit"):
        generate_motion(model, vocab, ["the friend buys " * 20], ["ASL"])


def test_fused_embedding_is_the_mean_of_the_stream_embeddings_and_heads_own_their_vocabulary(vocab):
    model = SignMotionLM(TINY, SMLMDims.from_vocabulary(vocab)).eval()
    examples = make_examples(vocab)[:3]
    batch = production_batch(examples, vocab)
    fused = model.embed_fused(batch.motion_in)
    assert fused.shape == (3, batch.motion_in.shape[1], TINY.d_model)
    by_hand = torch.stack([model.embed(batch.motion_in[..., k]) for k in range(4)]).mean(0)
    assert torch.allclose(fused, by_hand, atol=1e-6)
    logits = model.production(batch.text_ids, batch.text_mask, batch.motion_in, batch.motion_mask)
    assert {s: v.shape[-1] for s, v in logits.items()} == {s: CODEBOOKS[s] + 1 for s in MOTION_STREAMS}
    t = translation_batch(examples, vocab)
    assert model.translation(t.motion_ids, t.motion_mask, t.text_in, t.text_mask).shape[-1] == vocab.text_size
    # targets: the motion codes then one EOS class per stream, padding ignored
    first = examples[0]
    u = len(first.motion)
    assert torch.equal(batch.targets[0, :u], torch.from_numpy(first.motion))
    assert batch.targets[0, u].tolist() == [CODEBOOKS[s] for s in MOTION_STREAMS]
    assert (batch.targets[0, u + 1:] == IGNORE).all()


@pytest.fixture(scope="module")
def overfit(vocab, tmp_path_factory):
    examples = make_examples(vocab)
    cfg = SMLMTrainConfig(epochs=120, batch_size=5, lr=3e-3, min_lr=1e-4, eval_every=10_000, device="cpu")
    path = tmp_path_factory.mktemp("smlm") / "best.pt"
    result = train_smlm(TINY, cfg, vocab, examples, None, "v", path, progress=False)
    return result, examples, path


def test_tiny_model_overfits_both_directions(overfit, vocab):
    result, examples, _ = overfit
    model = result.model
    generated = generate_motion(model, vocab, [e.text for e in examples], [e.language for e in examples])
    for g, e in zip(generated, examples):
        assert g.stopped
        got = np.stack([g.tokens[s] for s in MOTION_STREAMS], axis=1)
        assert got.shape == e.motion.shape and np.array_equal(got, e.motion), e.clip_id
    texts = translate(model, vocab, [e.motion for e in examples], [e.language for e in examples])
    assert [t.replace(" ", "") for t in texts] == [e.text.replace(" ", "") for e in examples]


def test_cached_and_uncached_decoding_pick_the_same_tokens(overfit, vocab):
    result, examples, _ = overfit
    torch.manual_seed(1)
    fresh = SignMotionLM(TINY, SMLMDims.from_vocabulary(vocab))  # untrained: long, unstructured outputs
    for model in (result.model, fresh):
        texts, langs = [e.text for e in examples], [e.language for e in examples]
        a = generate_motion(model, vocab, texts, langs, max_steps=30, use_cache=True)
        b = generate_motion(model, vocab, texts, langs, max_steps=30, use_cache=False)
        for x, y in zip(a, b):
            assert x.stopped == y.stopped
            assert all(np.array_equal(x.tokens[s], y.tokens[s]) for s in MOTION_STREAMS)
        motions = [e.motion for e in examples]
        assert translate(model, vocab, motions, langs, use_cache=True) == translate(model, vocab, motions, langs, use_cache=False)


class _EosAfter(torch.nn.Module):
    """A face head that emits EOS from step ``k`` on (counts its calls) and a fixed code before."""

    def __init__(self, classes: int, k: int):
        super().__init__()
        self.classes, self.k, self.calls = classes, k, 0

    def forward(self, hidden):
        logits = torch.zeros(*hidden.shape[:-1], self.classes)
        logits[..., self.classes - 1 if self.calls >= self.k else 3] = 1.0
        self.calls += 1
        return logits


def test_generation_stops_when_any_stream_emits_eos(vocab):
    model = SignMotionLM(TINY, SMLMDims.from_vocabulary(vocab))
    for stream in MOTION_STREAMS:  # only the face ever ends, at step 5
        model.heads[stream] = _EosAfter(CODEBOOKS[stream] + 1, k=5 if stream == "face" else 10_000)
    (g,) = generate_motion(model, vocab, ["the friend"], ["ASL"], max_steps=30)
    assert g.stopped and all(len(t) == 5 for t in g.tokens.values())
    assert all((t == 3).all() for t in g.tokens.values())
    for stream in MOTION_STREAMS:  # nothing ends: the step limit does, and says so
        model.heads[stream] = _EosAfter(CODEBOOKS[stream] + 1, k=10_000)
    (g,) = generate_motion(model, vocab, ["the friend"], ["ASL"], max_steps=7)
    assert not g.stopped and all(len(t) == 7 for t in g.tokens.values())


def test_checkpoint_rebuilds_the_model_and_vocabulary(overfit, vocab, tmp_path):
    result, examples, best = overfit
    path = save_smlm(tmp_path / "m.pt", result.model, vocab, 3, 30, "v", {"x": 1.0}, {"translation_objective": True})
    loaded = load_smlm(path)
    assert loaded.train_config == {"translation_objective": True} and loaded.epoch == 3
    texts, langs = [e.text for e in examples], [e.language for e in examples]
    a = generate_motion(result.model, vocab, texts, langs)
    b = generate_motion(loaded.model, loaded.vocab, texts, langs)
    assert all(np.array_equal(x.tokens[s], y.tokens[s]) for x, y in zip(a, b) for s in MOTION_STREAMS)
    assert load_smlm(best).epoch == 120  # without an evaluator the last epoch is the one kept
    with pytest.raises(ValueError, match="not a readable SMLM checkpoint"):
        (tmp_path / "junk.pt").write_bytes(b"junk")
        load_smlm(tmp_path / "junk.pt")


@pytest.mark.slow
def test_killed_training_resumes_on_the_same_loss_curve(vocab, tmp_path):
    """A ``last`` checkpoint carries weights, optimiser, schedule and RNG: two epochs, a stop, then the rest
    give the run an uninterrupted training gives (dropout on, so the restored RNG matters)."""
    examples = make_examples(vocab)
    model_cfg = dataclasses.replace(TINY, dropout=0.1)
    cfg = SMLMTrainConfig(epochs=5, batch_size=2, lr=3e-3, warmup_steps=3, device="cpu")
    straight = train_smlm(model_cfg, cfg, vocab, examples, None, "v", tmp_path / "a.pt", progress=False,
                          last_path=tmp_path / "a.last.pt")
    part = train_smlm(model_cfg, cfg, vocab, examples, None, "v", tmp_path / "b.pt", progress=False,
                      last_path=tmp_path / "b.last.pt", stop_after_epochs=2)
    assert len(part.history) == 2 and load_smlm(tmp_path / "b.last.pt").train_state["epoch"] == 2
    resumed = train_smlm(model_cfg, cfg, vocab, examples, None, "v", tmp_path / "b.pt", progress=False,
                         last_path=tmp_path / "b.last.pt")
    assert resumed.resumed_from_epoch == 2 and len(resumed.history) == 5
    losses = lambda r: [h.get("train_production_loss", 0.0) + h.get("train_translation_loss", 0.0)  # noqa: E731
                        for h in r.history]
    assert np.allclose(losses(resumed), losses(straight), rtol=1e-5, atol=1e-7)
    for (name, a), b in zip(straight.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-6), name
    assert load_smlm(tmp_path / "b.pt").epoch == load_smlm(tmp_path / "a.pt").epoch == 5


def test_run_key_changes_with_what_the_run_depends_on(vocab):
    cfg = SMLMTrainConfig(device="cpu")
    key = run_key(TINY, cfg, vocab, "v")
    assert key == run_key(TINY, dataclasses.replace(cfg, device="cuda", cache_dir="elsewhere"), vocab, "v")
    assert key != run_key(TINY, dataclasses.replace(cfg, lr=1e-3), vocab, "v")
    assert key != run_key(dataclasses.replace(TINY, d_model=32), cfg, vocab, "v")
    assert key != run_key(TINY, cfg, vocab, "w")


@pytest.mark.slow
def test_production_only_never_trains_the_text_head(vocab, tmp_path):
    examples = make_examples(vocab)
    cfg = SMLMTrainConfig(epochs=3, batch_size=2, translation_objective=False, device="cpu", weight_decay=0.0)
    torch.manual_seed(0)
    before = SignMotionLM(TINY, SMLMDims.from_vocabulary(vocab)).heads["text"].weight.detach().clone()
    result = train_smlm(TINY, cfg, vocab, examples, None, "v", tmp_path / "b.pt", progress=False)
    assert torch.equal(result.model.heads["text"].weight, before)
    assert "train_translation_loss" not in result.history[-1] and "train_production_loss" in result.history[-1]


def test_added_translation_steps_keep_every_production_step_of_the_objective_free_run(vocab, monkeypatch):
    """translation_steps shared: a translation batch replaces a production step (production gets ~1 - p of the
    epoch); added: each chunk is a production step, followed by a translation step on the same chunk with
    probability p / (1 - p): production gets every step the objective-free run gets."""
    from m3t.smlm.data import ProductionBatch, TranslationBatch
    from m3t.smlm.train import epoch_batches, optimizer_steps_per_epoch

    examples = make_examples(vocab) * 4
    n = -(-len(examples) // 2)  # chunks of 2 examples: the objective-free run's steps
    base = SMLMTrainConfig(batch_size=2, device="cpu")
    kinds = lambda cfg, epoch=0: [type(b) for b in epoch_batches(examples, vocab, cfg, epoch)]  # noqa: E731
    off = kinds(dataclasses.replace(base, translation_objective=False))
    assert off == [ProductionBatch] * n
    shared = kinds(base)
    assert len(shared) == n and 0 < shared.count(TranslationBatch) < n  # steps taken from production
    added = kinds(dataclasses.replace(base, translation_steps="added"))  # p = 0.5: one translation per production
    assert added == [ProductionBatch, TranslationBatch] * n
    quarter = [kinds(dataclasses.replace(base, translation_steps="added", translation_prob=0.25), e) for e in range(20)]
    assert all(k.count(ProductionBatch) == n for k in quarter)
    share = sum(k.count(TranslationBatch) for k in quarter) / sum(len(k) for k in quarter)
    assert 0.18 < share < 0.32  # p = 0.25 of all steps, on average
    # a translation step trains on the chunk of the production step it follows
    import m3t.smlm.train as train_module

    seen = []
    monkeypatch.setattr(train_module, "production_batch", lambda chunk, v: seen.append(("p", [id(e) for e in chunk])))
    monkeypatch.setattr(train_module, "translation_batch", lambda chunk, v: seen.append(("t", [id(e) for e in chunk])))
    list(epoch_batches(examples, vocab, dataclasses.replace(base, translation_steps="added"), 0))
    assert [k for k, _ in seen] == ["p", "t"] * n and all(seen[i][1] == seen[i + 1][1] for i in range(0, 2 * n, 2))
    assert optimizer_steps_per_epoch(len(examples), dataclasses.replace(base, translation_steps="added"), 1) == 2 * n
    assert optimizer_steps_per_epoch(len(examples), base, 1) == n
    assert optimizer_steps_per_epoch(len(examples), dataclasses.replace(base, translation_objective=False,
                                                                        translation_steps="added"), 1) == n
    with pytest.raises(ValueError, match="translation_prob 0.6 with translation_steps added"):
        SMLMTrainConfig(translation_steps="added", translation_prob=0.6)
    with pytest.raises(ValueError, match="translation_steps 'both' unknown"):
        SMLMTrainConfig(translation_steps="both")


def test_bf16_autocast_step_on_cpu(vocab):
    """bf16 really runs the heads in bfloat16 (their logits are bf16, the loss is near the fp32 loss of the same
    model and batch but not bit-equal to it); a silently disabled autocast fails here."""
    torch.manual_seed(0)
    model = SignMotionLM(TINY, SMLMDims.from_vocabulary(vocab))
    twin = copy.deepcopy(model)
    batch = production_batch(make_examples(vocab)[:2], vocab)
    before = model.heads["body"].weight.detach().clone()
    steps = bf16_and_fp32_steps(model, twin, batch, train_step, lambda m: m.heads["body"], torch.optim.AdamW)
    for precision, (_, dtypes) in steps.items():
        assert dtypes == [torch.bfloat16 if precision == "bf16" else torch.float32], precision
    stats = {precision: s for precision, (s, _) in steps.items()}
    assert math.isfinite(stats["bf16"]["production_loss"])
    assert stats["bf16"]["production_loss"] != stats["fp32"]["production_loss"]
    assert stats["bf16"]["production_loss"] == pytest.approx(stats["fp32"]["production_loss"], rel=0.05)
    assert not torch.equal(before, model.heads["body"].weight)


def _ddp_worker(rank: int, world: int, rdv: str, out: str) -> None:
    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=f"file://{rdv}", rank=rank, world_size=world)
    try:
        texts = [t for ts in SENTENCES.values() for t in ts]
        vocab = build_vocabulary(texts, SENTENCES, CODEBOOKS, TINY.text_vocab_size)
        examples = make_examples(vocab)
        cfg = SMLMTrainConfig(epochs=3, batch_size=1, device="cpu")
        ctx = DistributedContext(rank, world, torch.device("cpu"))
        result = train_smlm(TINY, cfg, vocab, examples, None, "v", f"{out}/best.pt", dist_ctx=ctx, progress=False)
        torch.save(result.model.state_dict(), f"{out}/rank{rank}.pt")
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
def test_data_parallel_on_gloo_keeps_ranks_in_sync(tmp_path):
    import torch.multiprocessing as mp

    mp.spawn(_ddp_worker, args=(2, str(tmp_path / "rdv"), str(tmp_path)), nprocs=2, join=True)
    a, b = (torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(2))
    for name in a:
        assert torch.allclose(a[name], b[name], atol=1e-6), name
    assert (tmp_path / "best.pt").exists(), "rank 0 saves"


def test_over_length_clips_are_skipped_for_training_and_cut_for_evaluation(vocab):
    text = SENTENCES["ASL"][2]  # "the child reads the book today"
    rng = np.random.default_rng(0)
    tokens = {s: rng.integers(0, CODEBOOKS[s], 12) for s in MOTION_STREAMS}
    clip = Clip("long", "toy", "test", "ASL", "s", text, "G", "x", 25.0)
    shard = TokenShard(Path("x.parquet"), TokenInfo(CODEBOOKS, 4, {}), (TokenClip(clip, 48, tokens),))
    full = vocab.encode_text(text, None)
    assert len(full) > 3

    found, skipped = examples_from_shard(shard, vocab, 3, 10)
    assert found == [] and "smlm.max_text_tokens = 3" in skipped[0]["reason"] and "12 motion steps" in skipped[0]["reason"]

    cut: list[dict] = []
    found, skipped = examples_from_shard(shard, vocab, 3, 10, cut)
    assert skipped == [] and [c["clip_id"] for c in cut] == ["long"] and "kept, cut to the limit" in cut[0]["reason"]
    assert found[0].text_ids.tolist() == full[:3] and found[0].motion.shape == (10, len(MOTION_STREAMS))
    assert found[0].motion[:, 0].tolist() == tokens[MOTION_STREAMS[0]][:10].tolist()


def test_every_id_has_a_token_name_and_one_past_the_end_is_refused(vocab):
    names = [vocab.token(i) for i in range(len(vocab))]
    assert len(set(names)) == len(names)  # one name per id: text pieces, prompts, then each stream's codes
    last = MOTION_STREAMS[-1]
    assert names[-1] == vocab.token(int(vocab.motion_ids(last, np.array([vocab.codebooks[last] - 1]))[0]))
    with pytest.raises(VocabularyError, match=f"id {len(vocab)} outside the vocabulary of {len(vocab)} tokens"):
        vocab.token(len(vocab))
