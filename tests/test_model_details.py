"""Behaviour details of the tokenizers, the SMLM and the codebook metrics that the coarser tests do not pin down:
the tokenisation stage end to end on a tiny shard (token values, rejected clips, summaries, reruns, every
corpus), the SMLM evaluator's batching, progress output, decoding and scoring, the training step's defaults
(no clipping unless asked, the batch's masks reach the model), the clips a token shard cannot give as examples
(and why), the reduced mBART embedding and text tokenizers (specials, id mapping, errors naming the tokenizer),
the training loops' progress bars, the window sampler's equal DDP shares and whole-frame crops, stream groups
and layout checks, tokenizer checkpoints, the tokenizer's normalisation (floor, mapping back) and mirrored
decoder, the VQ quantiser's settings, region keypoints, the codebook histogram's bars, a padded batch's logits
(equal to each example's alone), training refusing an absent CUDA device, the tokenizer checkpoint's step count,
the sampler's seed and rank share, boolean window masks, and the reconstruction probe's frame cap.
Written to pin behaviours that mutation testing of the library found unchecked. Tiny untrained models only.

The fitted shards here are the project's own Parquet format (:mod:`m3t.shards.io`) over a small hand-made
layout of the four motion streams, so no body model is needed to tokenise.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import re
from typing import ClassVar

import numpy as np
import pytest
import torch

from m3t.body.protocol import Modality, ModalityLayout
from m3t.body.rotations import identity_6d, mirror_rotations
from m3t.corpora.clip import Clip
from m3t.shards.folders import DataConfig
from m3t.shards.io import write_shard
from m3t.shards.schema import FittedClip
from m3t.shards.tokens import TokenInfo, read_token_shard
from m3t.tokenizers.checkpoint import save_tokenizer
from m3t.tokenizers.config import TokenizerConfig, VAEConfig
from m3t.tokenizers.data import GROUPS, STREAMS, WindowSampler
from m3t.tokenizers.evaluate import encode_clip
from m3t.tokenizers.tokenize import load_tokenizers, run_tokenize, tokenize_clip, tokenize_corpus
from m3t.tokenizers.vae import MotionTokenizer

TINY_TOKENIZER = TokenizerConfig(width=8, depth=2, dilation_growth=3)
LAYOUT = ModalityLayout(
    (Modality("body", "rotation6d", ("spine", "neck")),
     Modality("left_hand", "rotation6d", ("wrist.L",), mirror_of="right_hand"),
     Modality("right_hand", "rotation6d", ("wrist.R",), mirror_of="left_hand"),
     Modality("face", "scalar", ("jaw", "smile", "blink"), bounds=(0.0, 1.0))),
    ("height", "weight"))
DIMS = {"body": LAYOUT.dims["body"], "hand": LAYOUT.dims["right_hand"], "face": LAYOUT.dims["face"]}

TINY_VAE = VAEConfig(input_dim=3, levels=(5, 5, 4), width=8, depth=1)  # the tokenizer-training tests' model


def tiny_face_clips(count: int) -> list[np.ndarray]:
    """``count`` random 16-frame clips of ``TINY_VAE``'s 3-dim stream, seed 0."""
    rng = np.random.default_rng(0)
    return [rng.normal(size=(16, 3)).astype(np.float32) for _ in range(count)]


def tiny_train_cfg(cache_dir, epochs: int, batch_size: int, windows_per_clip: int = 1, **extra):
    """The tokenizer-training tests' config: 8-frame windows, one warm-up epoch, on the CPU unless ``extra``
    names a device."""
    from m3t.tokenizers.config import TokenizerTrainConfig

    return TokenizerTrainConfig(cache_dir=str(cache_dir), epochs=epochs, warmup_epochs=1, batch_size=batch_size,
                                window=8, windows_per_clip=windows_per_clip, **{"device": "cpu", **extra})

def tiny_tokenizers(dims: dict[str, int] = DIMS, seed: int = 0) -> dict[str, MotionTokenizer]:
    """Untrained tokenizers of the three groups, with non-trivial normalisation statistics."""
    torch.manual_seed(seed)
    models = {}
    for group, dim in dims.items():
        model = MotionTokenizer(TINY_TOKENIZER.vae_config(group, dim)).eval()
        model.set_normalisation(0.1 * torch.randn(dim), 0.5 + torch.rand(dim))
        models[group] = model
    return models


def fitted(cid: str, split: str, frames: int, seed: int, corpus: str = "synthetic") -> FittedClip:
    """A fitted clip of the tiny layout: rotations near the identity, face values in [0, 1]."""
    rng = np.random.default_rng(seed)
    params = {}
    for m in LAYOUT.modalities:
        if m.kind == "rotation6d":
            base = np.tile(identity_6d(len(m.labels)).numpy().reshape(-1), (frames, 1))
            params[m.name] = (base + 0.2 * rng.standard_normal((frames, m.dim))).astype(np.float32)
        else:
            params[m.name] = rng.random((frames, m.dim)).astype(np.float32)
    clip = Clip(cid, corpus, split, "ASL", "s1", f"sentence {seed}", "G", f"{cid}.npz", 25.0)
    return FittedClip(clip, "k", params, np.zeros(2, np.float32), {}, {}, "tiny")


NO_FACE = ModalityLayout(LAYOUT.modalities[:3], LAYOUT.identity_labels)
"""A layout without the face stream: a shard fitted with another body model."""


def write_tiny_shards(folder, corpus: str = "synthetic", faceless_dev: bool = True):
    """train: 3 clips (one of 2 frames, shorter than a token), dev: 1 clip (without a face stream when
    ``faceless_dev``: it cannot be tokenised), test: 2 clips; returns {split: [FittedClip]} as written."""
    folder.mkdir(parents=True, exist_ok=True)
    splits = {"train": [fitted(f"{corpus}-a", "train", 9, 1, corpus), fitted(f"{corpus}-b", "train", 2, 2, corpus),
                        fitted(f"{corpus}-c", "train", 16, 3, corpus)],
              "dev": [fitted(f"{corpus}-d", "dev", 7, 4, corpus)],
              "test": [fitted(f"{corpus}-e", "test", 12, 5, corpus), fitted(f"{corpus}-f", "test", 5, 6, corpus)]}
    for split, clips in splits.items():
        layout = NO_FACE if split == "dev" and faceless_dev else LAYOUT
        for clip in clips:
            for name in set(clip.params) - set(layout.names):
                del clip.params[name]
        write_shard(folder / f"{split}.parquet", clips, layout)
    return splits


def tiny_info(models: dict[str, MotionTokenizer]) -> TokenInfo:
    return TokenInfo({s.name: models[g].codebook_size for g, ss in GROUPS.items() for s in ss}, 4,
                     {s.name: g for g, ss in GROUPS.items() for s in ss})


# ---------------------------------------------------------------- tokenisation stage


def test_tokenize_clip_encodes_each_stream_with_its_group_and_mirrors_the_left_hand():
    models = tiny_tokenizers()
    clip = fitted("c1", "train", 10, seed=7)
    out = tokenize_clip(models, clip)
    assert out.clip == clip.clip and out.num_frames == 10 and out.num_tokens == 3  # ceil(10 / 4)
    assert list(out.tokens) == [s.name for s in STREAMS] == ["body", "left_hand", "right_hand", "face"]
    p = clip.params
    assert np.array_equal(out.tokens["body"], encode_clip(models["body"], p["body"]))
    assert np.array_equal(out.tokens["right_hand"], encode_clip(models["hand"], p["right_hand"]))
    left = mirror_rotations(torch.from_numpy(p["left_hand"]))
    assert np.array_equal(out.tokens["left_hand"], encode_clip(models["hand"], left))
    assert np.array_equal(out.tokens["face"], encode_clip(models["face"], p["face"]))
    for stream in STREAMS:
        tokens = out.tokens[stream.name]
        assert tokens.dtype == np.int64 and tokens.shape == (3,)
        assert 0 <= tokens.min() and tokens.max() < models["hand" if "hand" in stream.name else stream.name].codebook_size
    # the hand tokenizer is not the body's: feeding the wrong group would not even fit the dims
    assert models["hand"].cfg.input_dim != models["body"].cfg.input_dim


def test_tokenize_clip_names_a_clip_with_non_finite_parameters():
    clip = fitted("broken-7", "dev", 6, seed=1)
    clip.params["left_hand"][2, 0] = np.inf
    with pytest.raises(ValueError, match=r"clip 'broken-7', modality 'left_hand'.*NaN or inf"):
        tokenize_clip(tiny_tokenizers(), clip)


def test_tokenize_corpus_writes_every_split_rejects_bad_clips_and_summarises(tmp_path):
    models = tiny_tokenizers()
    info = tiny_info(models)
    written = write_tiny_shards(tmp_path / "shards")
    out = tmp_path / "tokens" / "nested" / "synthetic"  # parents created
    summary = tokenize_corpus(models, info, tmp_path / "shards", out)
    assert summary == {
        "train_clips": 3, "train_tokens_per_stream": 3 + 1 + 4,
        "dev_clips": 0, "dev_tokens_per_stream": 0,
        "test_clips": 2, "test_tokens_per_stream": 3 + 2,
        "rejected": 1,
        "mean_tokens_per_clip": pytest.approx(np.mean([8 / 3, 5 / 2])),  # splits without clips left out
    }
    for split in ("train", "dev", "test"):
        shard = read_token_shard(out / f"{split}.parquet")
        assert shard.info == info
        kept = [c for c in written[split] if "face" in c.params]
        assert [c.clip.id for c in shard.clips] == [c.clip.id for c in kept]
        for tc, clip in zip(shard.clips, kept):
            assert tc.num_frames == clip.num_frames
            expected = tokenize_clip(models, clip)
            for stream in STREAMS:
                assert np.array_equal(tc.tokens[stream.name], expected.tokens[stream.name]), (clip.clip.id, stream)
    rejected = [json.loads(line) for line in (out / "rejected.jsonl").read_text().splitlines()]
    assert len(rejected) == 1
    assert rejected[0]["clip_id"] == "synthetic-d" and rejected[0]["split"] == "dev"
    assert rejected[0]["reason"] == "KeyError: 'face'"
    assert json.loads((out / "summary.json").read_text()) == summary
    # a rerun into the same folder replaces the outputs
    assert tokenize_corpus(models, info, tmp_path / "shards", out) == summary


def test_tokenize_corpus_of_only_rejected_clips_reports_zero_tokens(tmp_path):
    models = tiny_tokenizers()
    folder = tmp_path / "shards"
    folder.mkdir()
    for split in ("train", "dev", "test"):
        clip = fitted(f"bad-{split}", split, 5, seed=2)
        del clip.params["face"]
        write_shard(folder / f"{split}.parquet", [clip], NO_FACE)
    summary = tokenize_corpus(models, tiny_info(models), folder, tmp_path / "out")
    assert summary["rejected"] == 3 and summary["mean_tokens_per_clip"] == 0.0
    assert all(summary[f"{s}_clips"] == 0 for s in ("train", "dev", "test"))
    assert read_token_shard(tmp_path / "out" / "test.parquet").clips == ()


def _save_tokenizers(folder, models: dict[str, MotionTokenizer]) -> None:
    for group, model in models.items():
        save_tokenizer(folder / f"{group}.pt", model, group, 1, 10, "data-v1", {"val_vpe_mm": 1.0})


def test_run_tokenize_writes_the_token_shards_of_every_training_corpus(tmp_path):
    models = tiny_tokenizers(seed=3)
    data = DataConfig(train_corpora=("alpha", "beta"), shards_root=str(tmp_path / "shards"),
                      tokens_root=str(tmp_path / "tokens"), models_dir=str(tmp_path / "models"))
    data.tokenizers_dir.mkdir(parents=True)
    _save_tokenizers(data.tokenizers_dir, models)
    written = {c: write_tiny_shards(data.shards_dir(c), c, faceless_dev=(c == "beta")) for c in data.train_corpora}
    summaries = run_tokenize(data)
    assert list(summaries) == ["alpha", "beta"]
    assert summaries["alpha"]["rejected"] == 0 and summaries["beta"]["rejected"] == 1
    assert summaries["alpha"]["dev_clips"] == 1 and summaries["beta"]["dev_clips"] == 0
    _, info = load_tokenizers(data.tokenizers_dir)
    assert info.downsample == 4 and info.streams["left_hand"] == info.streams["right_hand"] == 180
    assert info.tokenizers["left_hand"] == info.tokenizers["right_hand"] != info.tokenizers["body"]
    for corpus in data.train_corpora:
        folder = data.tokens_dir(corpus)
        assert sorted(p.name for p in folder.iterdir()) == ["dev.parquet", "rejected.jsonl", "summary.json",
                                                             "test.parquet", "train.parquet"]
        shard = read_token_shard(folder / "train.parquet")
        assert shard.info == info
        assert [c.clip.id for c in shard.clips] == [c.clip.id for c in written[corpus]["train"]]
        first = written[corpus]["train"][0]
        assert np.array_equal(shard.clips[0].tokens["body"], encode_clip(models["body"], first.params["body"]))


def test_load_tokenizers_refuses_tokenizers_of_different_downsampling(tmp_path):
    models = tiny_tokenizers()
    models["face"] = MotionTokenizer(VAEConfig(input_dim=DIMS["face"], levels=(6, 6, 6), width=8, depth=1,
                                               down_stages=3))
    _save_tokenizers(tmp_path, models)
    with pytest.raises(ValueError, match=r"different factors \[4, 8\]"):
        load_tokenizers(tmp_path)


# ---------------------------------------------------------------- tokenizer training data and architecture


@pytest.mark.parametrize("items, world_size", [(5, 2), (7, 3), (6, 3), (1, 2), (10, 4)])
def test_window_sampler_gives_every_rank_equal_shares_that_cover_every_crop(items, world_size):
    # one window-long sequence per item, filled with its index: each crop says which item it is
    seqs = [np.full((4, 1), float(i), np.float32) for i in range(items)]
    per_rank = -(-items // world_size)
    seen = []
    for rank in range(world_size):
        sampler = WindowSampler(seqs, window=4, batch_size=2, per_sequence=1, seed=5, rank=rank, world_size=world_size)
        batches = list(sampler.epoch(0))
        assert len(batches) == len(sampler) == -(-per_rank // 2)
        crops = [int(x[0, 0, 0]) for xs, _ in batches for x in xs.split(1)]
        assert len(crops) == per_rank, f"rank {rank} of {world_size}"
        assert all(mask.all() for _, mask in batches)
        seen += crops
    assert set(seen) == set(range(items))
    # the shares are padded to equal length by wrapping round the epoch's order: no item is repeated more
    # often than that needs (with fewer items than ranks, each rank still gets one)
    assert max(seen.count(i) for i in range(items)) == -(-per_rank * world_size // items)
    single = WindowSampler(seqs, window=4, batch_size=items, per_sequence=1, seed=5)
    (xs, _), = list(single.epoch(0))
    assert sorted(int(v) for v in xs[:, 0, 0]) == list(range(items))


def test_set_normalisation_floors_only_near_constant_dims():
    model = MotionTokenizer(VAEConfig(input_dim=4, levels=(5, 5, 4), width=8, depth=1))
    model.set_normalisation(torch.tensor([1.0, -2.0, 0.5, 0.0]), torch.tensor([0.0, 0.004, 0.5, 3.0]))
    assert torch.allclose(model.std, torch.tensor([0.01, 0.01, 0.5, 3.0]))
    assert torch.equal(model.mean, torch.tensor([1.0, -2.0, 0.5, 0.0]))
    model.set_normalisation(torch.zeros(4), torch.tensor([0.0, 0.2, 0.5, 3.0]), floor=0.3)
    assert torch.allclose(model.std, torch.tensor([0.3, 0.3, 0.5, 3.0]))
    # the statistics map the decoder's standardised output back to parameters
    codes = torch.zeros(1, 2, 3)
    raw = model.decoder(codes.transpose(1, 2)).transpose(1, 2)
    assert torch.allclose(model.decode_codes(codes), raw * model.std)


@pytest.mark.parametrize("depth, growth, stages", [(3, 3, 2), (2, 2, 1), (1, 3, 3)])
def test_decoder_mirrors_the_encoder_with_reversed_dilations(depth, growth, stages):
    cfg = VAEConfig(input_dim=5, levels=(5, 5, 4), width=8, depth=depth, dilation_growth=growth, down_stages=stages)
    model = MotionTokenizer(cfg)

    def dilations(stack):
        return [[block.conv1.dilation[0] for block in m] for m in stack if isinstance(m, torch.nn.Sequential)]

    forward = [growth**i for i in range(depth)]
    assert dilations(model.encoder) == [forward] * stages
    assert dilations(model.decoder) == [forward[::-1]] * stages
    ups = [m for m in model.decoder if isinstance(m, torch.nn.Upsample)]
    assert len(ups) == stages and all(u.scale_factor == 2 and u.mode == "nearest" for u in ups)
    assert model.decode(torch.zeros(2, 3, dtype=torch.long)).shape == (2, 3 * 2**stages, 5)


# ---------------------------------------------------------------- SMLM training step and evaluator

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


# ---------------------------------------------------------------- metrics: region keypoints, codebook histogram


def test_region_keypoints_pose_exactly_the_regions_vertices_from_a_well_formed_correspondence(body):
    from m3t.metrics.vertices import region_keypoints, region_vertices

    class Recording:
        """The body model, recording the correspondences it is handed."""

        def __init__(self, inner):
            self.inner, self.seen = inner, []

        def keypoint_set(self, corr):
            self.seen.append(corr)
            return self.inner.keypoint_set(corr)

    region = np.array([12, 3000, 7, 9000])
    recording = Recording(body)
    keypoints = region_keypoints(recording, region.tolist())
    (corr,) = recording.seen
    assert len(corr.names) == len(corr.kind) == len(corr.index) == 4
    assert len(set(corr.names)) == 4 and all(isinstance(n, str) for n in corr.names)
    assert corr.valid.all() and (corr.kind == 0).all() and np.array_equal(corr.index, region)
    params = body.rest_params(3)
    params["body"] = params["body"] + 0.1 * torch.randn(3, params["body"].shape[1], generator=torch.Generator().manual_seed(0))
    identity = body.default_identity()
    dense = body.forward(params, identity).vertices[:, region]
    got = region_vertices(body, params, identity, keypoints, chunk=2)  # chunks of frames give the same result
    assert got.shape == (3, 4, 3)
    assert torch.allclose(got, dense, atol=1e-5)


def test_token_histogram_draws_one_unit_bar_per_code_and_its_rank_order(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    from m3t.metrics.codebook import plot_token_histogram

    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # keep the figure to look at
    counts = np.array([3, 0, 7, 1, 0])
    path = plot_token_histogram(counts, "face (fsq, 5 codes)", tmp_path / "plots" / "face.png")
    assert path == tmp_path / "plots" / "face.png" and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (fig,) = figures
    by_index, by_rank = fig.axes
    for axis, heights in ((by_index, counts), (by_rank, [7, 3, 1, 0, 0])):
        bars = axis.patches
        assert [b.get_height() for b in bars] == list(heights)
        assert [b.get_x() + b.get_width() / 2 for b in bars] == pytest.approx(range(5))
        assert [b.get_width() for b in bars] == pytest.approx([1.0] * 5), "adjacent codes' bars must not overlap"
    assert by_index.get_xlabel() == "code index" and by_rank.get_xlabel() == "code rank"
    title = fig.get_suptitle()
    assert title.startswith("face (fsq, 5 codes)") and "60.0% used" in title and f"{np.std(counts):.1f}" in title
    monkeypatch.undo()
    plt.close(fig)


# ---------------------------------------------------------------- SMLM examples, evaluator generation and scoring


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


def test_evaluator_scores_generated_tokens_per_clip_overall_and_per_group(evaluator, smlm_parts, monkeypatch):
    """The evaluator's part of scoring: what it hands the motion scorer (decoded predictions, the rest pose for an
    empty one, groups, identities) and the rows and summary it builds from the scores (the scorer's own numbers
    are pinned in test_scorer.py; here a recording stand-in returns known ones)."""
    from m3t.metrics.scorer import ClipScore, MotionScores
    from m3t.metrics.text import translation_metrics_by_language
    from m3t.smlm.evaluate import SELECTION_METRIC
    from m3t.smlm.generate import GeneratedMotion
    from m3t.smlm.vocab import MOTION_STREAMS

    class RecordingScorer:
        def __init__(self):
            self.calls = []

        def score(self, pairs):
            self.calls.append(list(pairs))
            per_clip = [ClipScore(p.clip_id, p.group, len(next(iter(p.prediction.values()), [])),
                                  {"dtw_jpe_body_m": 0.1 * (k + 1), "dtw_jpe_hand_m": 0.02 * (k + 1)})
                        for k, p in enumerate(pairs)]
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
        "synthetic/ASL/dtw_jpe_body_m": 0.2, "synthetic/CSL/dtw_jpe_body_m": 0.4,
        **text_metrics,
    }
    assert report.generated is generated and report.translations == translations

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
    assert nothing.per_clip == [] and scorer.calls[-1] == []
    assert {k: v for k, v in nothing.summary.items() if not k.startswith("translation")} == {
        "stopped_rate": 0.0, "empty_rate": 0.0, "mean_steps": 0.0, SELECTION_METRIC: float("inf")}


# ---------------------------------------------------------------- SMLM: reduced embedding, text tokenizers


def test_keeping_embedding_rows_gathers_them_and_leaves_the_pad_row_untrained():
    """:func:`m3t.smlm.model.keep_embedding_rows` on an in-memory mBART (``MBartModel``: its scaled word
    embedding shared by encoder and decoder, pad id 1 as in mbart-large-cc25)."""
    from transformers import MBartConfig, MBartModel

    from m3t.smlm.model import keep_embedding_rows

    torch.manual_seed(0)
    config = MBartConfig(vocab_size=20, d_model=8, encoder_layers=1, decoder_layers=1, encoder_attention_heads=2,
                         decoder_attention_heads=2, encoder_ffn_dim=16, decoder_ffn_dim=16, max_position_embeddings=32,
                         scale_embedding=True, pad_token_id=1)
    backbone = MBartModel(config)
    old = backbone.get_input_embeddings()
    before = old.weight.detach().clone()
    rows = (0, 1, 2, 3, 7, 11)
    with pytest.raises(ValueError, match=r"pretrained id 20 but the checkpoint in models/mbart has 20 embedding rows: "
                                         r"smlm\.text_model_path and smlm\.pretrained_path must be the same mBART"):
        keep_embedding_rows(backbone, rows + (20,), 1, "models/mbart")
    assert backbone.get_input_embeddings() is old, "a refused reduction leaves the model as it was"

    keep_embedding_rows(backbone, rows, 1, "models/mbart")
    emb = backbone.get_input_embeddings()
    assert type(emb) is type(old) and emb.num_embeddings == len(rows) and emb.embedding_dim == 8
    assert emb.embed_scale == old.embed_scale == pytest.approx(8 ** 0.5)
    assert torch.equal(emb.weight, before[list(rows)])
    assert backbone.encoder.embed_tokens is emb and backbone.decoder.embed_tokens is emb
    assert backbone.config.vocab_size == len(rows) and backbone.config.pad_token_id == 1
    assert emb.padding_idx == 1
    ids = torch.tensor([[0, 4, 5, 2, 1, 1]])  # two pads at the end
    out = backbone(input_ids=ids, attention_mask=(ids != 1).long(), decoder_input_ids=ids[:, :4])
    out.last_hidden_state.sum().backward()
    grad = emb.weight.grad
    assert torch.count_nonzero(grad[1]) == 0, "the pad row gets no gradient: it stays the pretrained pad"
    assert all(torch.count_nonzero(grad[i]) > 0 for i in (0, 2, 4, 5))


def test_training_the_text_tokenizer_keeps_sentencepieces_log_off_stderr(capfd):
    import sentencepiece as spm

    from m3t.smlm.vocab import SentencePieceText, VocabularyError

    spm.set_min_log_level(0)  # the library's default: an earlier training in this process may have raised it
    capfd.readouterr()
    text = SentencePieceText.train(["the friend buys a red car", "  ", "", "my father drinks water"], 40)
    captured = capfd.readouterr()
    assert captured.err == "" and captured.out == "", "the stage log stays readable: no trainer chatter"
    assert (text.pad_id, text.bos_id, text.eos_id, text.unk_id) == (0, 1, 2, 3)
    assert 4 < text.size <= 40  # vocab_size is an upper bound on a small corpus
    ids = text.encode("my father drinks water")
    assert text.decode([text.bos_id, *ids, text.eos_id, text.pad_id]) == "my father drinks water"
    with pytest.raises(VocabularyError, match="the corpus has no non-empty text"):
        SentencePieceText.train(["", "   "], 40)


@pytest.fixture(scope="module")
def mbart_tokenizer_dir(tmp_path_factory):
    """The tokenizer files of a facebook/mbart-large-cc25 folder, tiny: a SentencePiece BPE
    ``sentencepiece.bpe.model`` and a ``tokenizer_config.json`` naming ``MBartTokenizer`` (``transformers`` then
    gives mBART's ids: ``<s>`` 0, ``<pad>`` 1, ``</s>`` 2, ``<unk>`` 3, the pieces shifted by one, then the 25
    language codes ``ar_AR`` .. ``zh_CN`` and ``<mask>``), as the stand-in of test_smlm_reduced_vocab.py, without
    the model weights."""
    import io

    import sentencepiece as spm

    folder = tmp_path_factory.mktemp("mbart-tokenizer")
    texts = ["the friend buys a red car today", "morgen regnet es im norden", "zwölf grad in bayern",
             "cars and books", "am tag scheint die sonne"]
    buffer = io.BytesIO()
    spm.SentencePieceTrainer.train(sentence_iterator=iter(texts * 4), model_writer=buffer, vocab_size=60,
                                   model_type="bpe", hard_vocab_limit=False, minloglevel=2, num_threads=1)
    (folder / "sentencepiece.bpe.model").write_bytes(buffer.getvalue())
    (folder / "tokenizer_config.json").write_text(json.dumps({"tokenizer_class": "MBartTokenizer"}))
    return folder


def test_pretrained_mbart_text_decodes_without_its_special_tokens(mbart_tokenizer_dir):
    from m3t.smlm.vocab import PretrainedMBartText

    text = PretrainedMBartText(mbart_tokenizer_dir)
    assert (text.bos_id, text.pad_id, text.eos_id, text.unk_id) == (0, 1, 2, 3)
    assert text.path == str(mbart_tokenizer_dir) and text.model_proto == b""
    ids = text.encode("the friend buys a red car")
    assert ids and min(ids) > 3, "encoded without <s> / </s>"
    assert text.piece(text.eos_id) == "</s>" and text.piece(text.pad_id) == "<pad>"
    generated = [text.bos_id, *ids, text.eos_id, text.pad_id, text.pad_id]  # as a padded generation comes back
    assert text.decode(generated) == "the friend buys a red car"
    assert text.decode(np.array(generated, dtype=np.int64)) == "the friend buys a red car"


def test_reduced_text_refuses_ids_outside_the_tokenizer_and_names_it(mbart_tokenizer_dir):
    from m3t.smlm.vocab import PretrainedMBartText, ReducedText, VocabularyError

    base = PretrainedMBartText(mbart_tokenizer_dir)
    last = base.size - 1

    def message(kept):
        with pytest.raises(VocabularyError) as info:
            ReducedText(base, kept)
        return str(info.value)

    for kept, shown in (([-1, 0, 1, 2, 3], "5 ids from (-1,) to (3,)"),  # a negative id
                        ([0, 1, 2, 3, base.size], f"5 ids from (0,) to ({base.size},)"),  # one past the end
                        ([0, 2, 1, 3], "4 ids from (0,) to (3,)"),  # not ascending
                        ([0, 1, 2, 2, 3], "5 ids from (0,) to (3,)"),  # a repeat
                        ([], "0 ids from () to ()")):
        assert message(kept) == (
            f"the reduced text vocabulary must list ascending, distinct ids of the tokenizer in {mbart_tokenizer_dir} "
            f"(0 .. {last}); got {shown}: the checkpoint was made with another mBART tokenizer"), kept
    assert message([0, 2, 3, 9]) == "the reduced text vocabulary lacks the special token(s) ['pad']"
    assert message([1, 3, 9]) == "the reduced text vocabulary lacks the special token(s) ['bos', 'eos']"

    reduced = ReducedText.from_texts(base, ["the friend buys a red car", "", "  "])
    assert reduced.kept[:4] == (0, 1, 2, 3) and reduced.kept[-1] <= last
    assert (reduced.bos_id, reduced.pad_id, reduced.eos_id, reduced.unk_id) == (0, 1, 2, 3)
    ids = reduced.encode("the friend buys a red car")
    assert max(ids) < reduced.size and reduced.decode(ids) == "the friend buys a red car"
    with pytest.raises(VocabularyError, match="the training corpus has no non-empty text"):
        ReducedText.from_texts(base, ["", " "])


def test_reduced_text_decodes_every_id_in_range_through_the_mapping_and_drops_the_others():
    """Reduced id ``i`` is pretrained id ``kept[i]``, the first one included; ids outside the reduced
    vocabulary (a generation's stray values) are dropped. The base here is a tokenizer whose first ids are
    ordinary pieces (its specials at 4 .. 7), so that a lost id 0 shows."""
    from m3t.smlm.vocab import ReducedText

    class Pieces:
        path, size, model_proto = "pieces", 10, b""
        pad_id, bos_id, eos_id, unk_id = 4, 5, 6, 7

        def decode(self, ids):
            return " ".join(f"p{i}" for i in ids)

        def piece(self, i):
            return f"p{i}"

    reduced = ReducedText(Pieces(), [0, 2, 4, 5, 6, 7, 9])
    assert reduced.size == 7 and (reduced.pad_id, reduced.bos_id, reduced.eos_id, reduced.unk_id) == (2, 3, 4, 5)
    assert reduced.decode([0, 1, 6]) == "p0 p2 p9"
    assert reduced.decode([0, 7, -1, 1, 99, 6]) == "p0 p2 p9"
    assert reduced.decode(np.array([6, 0])) == "p9 p0"
    assert [reduced.piece(i) for i in (0, 1, 6)] == ["p0", "p2", "p9"]


# ---------------------------------------------------------------- tokenizers: streams, layouts, sampling, checkpoints


def test_every_stream_belongs_to_one_group_and_an_unknown_stream_is_named():
    from m3t.tokenizers.data import group_of

    assert {s.name: group_of(s.name) for s in STREAMS} == {
        "body": "body", "left_hand": "hand", "right_hand": "hand", "face": "face"}
    with pytest.raises(KeyError) as info:
        group_of("torso")
    assert info.value.args[0] == ("no tokenizer group serves stream 'torso'; streams: "
                                  "['body', 'left_hand', 'right_hand', 'face']")


def test_check_layout_gives_the_groups_dim_or_says_what_the_body_model_lacks():
    from m3t.tokenizers.data import check_layout

    assert {g: check_layout(LAYOUT, g) for g in GROUPS} == {"body": 12, "hand": 6, "face": 3}

    def message(layout, group):
        with pytest.raises(ValueError) as info:
            check_layout(layout, group)
        return str(info.value)

    assert message(NO_FACE, "face") == ("tokenizer group 'face' needs modality 'face'; the body model's layout has "
                                        "['body', 'left_hand', 'right_hand']")
    assert message(LAYOUT, "torso") == "tokenizer group 'torso' unknown; allowed: body, hand, face"
    body, _, right, face = LAYOUT.modalities
    two_bone_left = Modality("left_hand", "rotation6d", ("wrist.L", "thumb.L"), mirror_of="right_hand")
    assert message(ModalityLayout((body, two_bone_left, right, face), ()), "hand") == (
        "streams of group 'hand' have different dims [6, 12]")
    scalar_left = Modality("left_hand", "scalar", ("a", "b", "c", "d", "e", "f"))
    assert message(ModalityLayout((body, scalar_left, right, face), ()), "hand") == (
        "modality 'left_hand' must be rotation6d to be mirrored")


def test_random_crops_are_whole_start_frames_inside_each_sequence_and_replayable():
    lengths = (5, 16, 17, 40)
    seqs = [np.zeros((n, 2), np.float32) for n in lengths]
    sampler = WindowSampler(seqs, window=8, batch_size=3, per_sequence=3, seed=11)
    items, starts = sampler.crops(0)
    assert items.shape == starts.shape == (3 * len(seqs),)
    assert np.issubdtype(starts.dtype, np.integer), "start frames index the sequence"
    assert sorted(items.tolist()) == sorted(list(range(len(seqs))) * 3)
    for item, start in zip(items, starts):
        assert 0 <= start <= max(lengths[item] - 8, 0), (item, start)
        assert len(seqs[item][start: start + 8]) == min(8, lengths[item])
    again_items, again_starts = sampler.crops(0)
    assert np.array_equal(again_items, items) and np.array_equal(again_starts, starts), "an epoch replays exactly"
    other = sampler.crops(1)
    assert not (np.array_equal(other[0], items) and np.array_equal(other[1], starts))
    assert (starts[items == 3] != starts[items == 3][0]).any(), "crops of a long sequence start anywhere"


def test_tokenizer_checkpoint_keeps_its_metrics_and_training_state(tmp_path):
    from m3t.tokenizers.checkpoint import load_tokenizer

    model = tiny_tokenizers()["face"]
    state = {"epoch": 4, "history": [{"epoch": 4, "train_loss": 0.5}]}
    save_tokenizer(tmp_path / "face.last.pt", model, "face", 4, 40, "data-v2", {"val_vpe_mm": 3.5, "epoch": 4}, state)
    loaded = load_tokenizer(tmp_path / "face.last.pt")
    assert (loaded.group, loaded.epoch, loaded.step, loaded.data_version) == ("face", 4, 40, "data-v2")
    assert loaded.metrics == {"val_vpe_mm": 3.5, "epoch": 4} and isinstance(loaded.metrics, dict)
    assert loaded.train_state == state
    assert torch.equal(loaded.model.mean, model.mean) and torch.equal(loaded.model.std, model.std)
    assert not loaded.model.training
    save_tokenizer(tmp_path / "face.pt", model, "face", 4, 40, "data-v2", {})
    best = load_tokenizer(tmp_path / "face.pt")
    assert best.metrics == {} and best.train_state is None  # only the resumable checkpoint carries a state


def test_decoded_parameters_are_the_decoders_output_mapped_back_by_the_training_statistics():
    torch.manual_seed(0)
    model = MotionTokenizer(VAEConfig(input_dim=4, levels=(5, 5, 4), width=8, depth=1)).eval()
    mean, std = torch.tensor([1.0, -2.0, 0.5, 30.0]), torch.tensor([0.5, 2.0, 1.0, 4.0])
    model.set_normalisation(mean, std)
    indices = torch.tensor([[0, 17, 99]])
    codes = model.quantizer.indices_to_codes(indices)
    raw = model.decoder(codes.transpose(1, 2)).transpose(1, 2)  # the decoder works in standardised units
    decoded = model.decode(indices)
    assert decoded.shape == (1, 12, 4)
    assert torch.allclose(decoded, raw * std + mean, atol=1e-6)
    assert torch.allclose(model.decode_codes(codes), decoded)
    # the encoder sees the same standardisation: parameters shifted and scaled with the statistics encode alike
    x = torch.randn(1, 8, 4)
    plain = MotionTokenizer(model.cfg).eval()
    plain.load_state_dict({**model.state_dict(), "mean": torch.zeros(4), "std": torch.ones(4)})
    assert torch.allclose(model.encode_latents(x * std + mean), plain.encode_latents(x), atol=1e-5)


def test_vq_tokenizer_uses_the_configured_commitment_weight_and_ema_decay():
    cfg = VAEConfig(input_dim=3, levels=(2, 3), quantizer="vq", width=8, depth=1, vq_code_dim=4, vq_decay=0.5,
                    vq_beta=0.3)
    torch.manual_seed(1)
    model = MotionTokenizer(cfg)
    vq = model.quantizer
    assert (vq.codebook_size, vq.dim) == (6, 4) and model.codebook_size == 6
    codebook = torch.randn(6, 4)
    vq.codebook.copy_(codebook)
    vq.ema_sum.copy_(10.0 * codebook)
    vq.ema_count.fill_(10.0)  # well above the reset threshold: no code is reset by one update
    vq.initialised.fill_(True)
    x = torch.randn(2, 8, 3)

    model.eval()
    out = model(x)
    flat = out.latents.detach().reshape(-1, 4)
    expected = torch.cdist(flat, codebook).argmin(dim=1)
    assert torch.equal(out.indices.reshape(-1), expected)
    assert out.quant_loss.item() == pytest.approx(0.3 * ((flat - codebook[expected]) ** 2).mean().item(), rel=1e-5)
    assert torch.equal(vq.codebook, codebook), "no codebook update outside training"

    model.train()
    out = model(x)
    counts = torch.bincount(out.indices.reshape(-1), minlength=6).float()
    sums = torch.zeros(6, 4).index_add_(0, out.indices.reshape(-1), out.latents.reshape(-1, 4).detach())
    assert torch.allclose(vq.ema_count, 0.5 * 10.0 + 0.5 * counts)
    assert torch.allclose(vq.codebook, (0.5 * 10.0 * codebook + 0.5 * sums) / vq.ema_count[:, None], atol=1e-6)
    assert vq.last_resets == 0


# ---------------------------------------------------------------- progress bars of the training loops


def test_tokenizer_training_shows_its_epoch_bar_only_on_the_main_rank_and_when_asked(tmp_path, capfd):
    from m3t.runtime import DistributedContext
    from m3t.tokenizers.train import train_tokenizer

    torch.set_num_threads(1)
    seqs = tiny_face_clips(3)
    model_cfg = TINY_VAE

    def train(name, **kwargs):
        cfg = tiny_train_cfg(tmp_path / name, 2, 4)
        capfd.readouterr()
        result = train_tokenizer("face", model_cfg, cfg, seqs, None, "v", **kwargs)
        return result, capfd.readouterr().err

    result, err = train("shown")
    assert len(result.history) == 2
    assert re.search(r"(^|\r)tokenizer:face: +100%.* 2/2 ", err), "the bar names the group and counts epochs"
    _, err = train("quiet", progress=False)
    assert "tokenizer:face" not in err
    _, err = train("rank1", dist_ctx=DistributedContext(rank=1))  # trains, keeps no history: rank 0 records
    assert "tokenizer:face" not in err, "only rank 0 draws the bar"


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


def test_batch_perplexity_is_the_exponential_of_the_code_entropy():
    from m3t.tokenizers.fsq import batch_perplexity

    assert batch_perplexity(torch.tensor([0, 1, 2, 3]), 8).item() == pytest.approx(4.0)
    assert batch_perplexity(torch.tensor([[5, 5], [5, 5]]), 8).item() == pytest.approx(1.0)
    # p = (3/4, 1/4): exp(-(3/4 ln 3/4 + 1/4 ln 1/4))
    expected = float(np.exp(-(0.75 * np.log(0.75) + 0.25 * np.log(0.25))))
    assert batch_perplexity(torch.tensor([1, 1, 1, 6]), 8).item() == pytest.approx(expected, rel=1e-5)
    assert batch_perplexity(torch.zeros(0, dtype=torch.long), 8).item() == pytest.approx(1.0)


def test_fsq_refuses_bad_levels_keeps_no_state_and_names_a_channel_mismatch():
    from m3t.tokenizers.fsq import FSQ

    for bad in ((), (5, 1), (1,), (0, 4)):
        with pytest.raises(ValueError, match=re.escape(f"FSQ levels must be integers >= 2, got {bad}")):
            FSQ(bad)
    fsq = FSQ((5, 4, 3))
    assert fsq.codebook_size == 60 and fsq.dim == 3
    assert fsq.state_dict() == {}  # everything is rebuilt from the levels in the config
    fsq.load_state_dict({})  # an old checkpoint without buffers loads
    with pytest.raises(ValueError, match=r"^FSQ with 3 levels got latents with 2 channels$"):
        fsq(torch.zeros(4, 7, 2))
    out = fsq(torch.zeros(4, 7, 3))
    assert out.indices.shape == (4, 7)


def test_vq_names_its_code_dim_and_the_latents_channels_on_a_mismatch():
    from m3t.tokenizers.vq import EMAVQ

    vq = EMAVQ(8, 4)
    with pytest.raises(ValueError, match=r"^VQ with code dim 4 got latents with 3 channels$"):
        vq(torch.zeros(2, 5, 3))


def test_tokenizer_training_refuses_a_window_the_downsampling_does_not_divide(tmp_path):
    from m3t.tokenizers.config import TokenizerTrainConfig
    from m3t.tokenizers.train import train_tokenizer

    model_cfg = TINY_VAE
    cfg = TokenizerTrainConfig(cache_dir=str(tmp_path), window=model_cfg.downsample * 3 + 1, device="cpu")
    message = (f"tokenizer_train.window ({cfg.window}) must be a multiple of the downsampling factor "
               f"{model_cfg.downsample}")
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        train_tokenizer("face", model_cfg, cfg, [np.zeros((16, 3), dtype=np.float32)], None, "v")
    assert not any(tmp_path.iterdir())  # refused before anything is written


def test_only_the_main_rank_records_and_saves_a_tokenizer_run(tmp_path):
    from m3t.runtime import DistributedContext
    from m3t.tokenizers.train import train_tokenizer

    torch.set_num_threads(1)
    seqs = tiny_face_clips(3)
    model_cfg = TINY_VAE
    cfg = tiny_train_cfg(tmp_path / "rank1", 1, 4)
    result = train_tokenizer("face", model_cfg, cfg, seqs, None, "v", dist_ctx=DistributedContext(rank=1),
                             progress=False)
    assert result.history == [] and not result.best
    assert not result.best_path.exists() and not result.last_path.exists()
    cfg = tiny_train_cfg(tmp_path / "rank0", 1, 4)
    result = train_tokenizer("face", model_cfg, cfg, seqs, None, "v", progress=False)
    assert [sorted(k for k in r if k.startswith("train_recon")) for r in result.history] == [["train_recon_mse"]]
    assert result.best_path.exists() and result.last_path.exists()


def test_a_tokenizer_with_a_probe_keeps_the_epoch_of_lowest_validation_error(tmp_path):
    from m3t.tokenizers.train import train_tokenizer

    class _Probe:  # stands in for the reconstruction probe: a fixed vertex error per evaluation
        def __init__(self):
            self.values = iter([1.0, 9.0, 9.0])

        def measure(self, model):
            return {"vpe_mm": next(self.values)}

    torch.set_num_threads(1)
    seqs = tiny_face_clips(3)
    model_cfg = TINY_VAE
    cfg = tiny_train_cfg(tmp_path, 3, 4, eval_every=1)
    result = train_tokenizer("face", model_cfg, cfg, seqs, _Probe(), "v", progress=False)
    assert [r["val_vpe_mm"] for r in result.history] == [1.0, 9.0, 9.0]
    assert result.best["epoch"] == 1 and result.best["val_vpe_mm"] == 1.0
    # the training loss went down after the first epoch, yet the validation error decides
    assert min(r["train_recon_mse"] for r in result.history) < result.history[0]["train_recon_mse"]


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


def test_a_reduced_vocabulary_over_a_tokenizer_without_a_path_still_explains_the_refusal():
    from m3t.smlm.vocab import ReducedText, VocabularyError

    class Loaded:  # a tokenizer object that does not know where it was loaded from
        size, model_proto = 10, b""
        pad_id, bos_id, eos_id, unk_id = 0, 1, 2, 3

    with pytest.raises(VocabularyError) as info:
        ReducedText(Loaded(), [0, 1, 2, 3, 12])
    assert str(info.value) == ("the reduced text vocabulary must list ascending, distinct ids of the tokenizer in ? "
                               "(0 .. 9); got 5 ids from (0,) to (12,): the checkpoint was made with another mBART "
                               "tokenizer")


def test_a_sentencepiece_model_without_a_pad_id_is_refused():
    import io

    import sentencepiece as spm

    from m3t.smlm.vocab import SentencePieceText, VocabularyError

    buffer = io.BytesIO()
    spm.SentencePieceTrainer.train(sentence_iterator=iter(["the friend buys a red car", "my father drinks water"]),
                                   model_writer=buffer, vocab_size=30, model_type="unigram", hard_vocab_limit=False,
                                   minloglevel=2, num_threads=1)  # SentencePiece's default: no pad id (-1)
    with pytest.raises(VocabularyError, match="model must define pad, bos, eos and unk ids"):
        SentencePieceText(buffer.getvalue())


def test_vq_defaults_are_the_papers_and_one_training_step_is_an_ema_update_by_hand():
    """T2M-GPT / SOKE's VQ (M3T's VQ baseline): decay 0.99 and commitment weight 0.02 by default, as in the
    ``tokenizer`` config; a training step moves each code's EMA statistics by ``decay`` and the loss is
    ``beta * mse(z, q)`` against the codebook before the update."""
    from m3t.tokenizers.vq import EMAVQ

    vq = EMAVQ(4, 3)
    cfg = TokenizerConfig()
    assert (vq.decay, vq.beta, vq.reset_threshold) == (cfg.vq_decay, cfg.vq_beta, 1.0) == (0.99, 0.02, 1.0)
    codebook = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    vq.codebook.copy_(codebook)
    vq.ema_sum.copy_(5.0 * codebook)
    vq.ema_count.fill_(5.0)
    vq.initialised.fill_(True)
    z = torch.tensor([[0.1, 0.0, 0.0], [0.9, 0.1, 0.0], [1.1, 0.0, 0.0], [0.0, 0.8, 0.1]])
    vq.train()
    out = vq(z)
    assert out.indices.tolist() == [0, 1, 1, 2]
    assert out.loss.item() == pytest.approx(0.02 * ((z - codebook[[0, 1, 1, 2]]) ** 2).mean().item(), rel=1e-6)
    counts = torch.tensor([1.0, 2.0, 1.0, 0.0])
    sums = torch.stack([z[0], z[1] + z[2], z[3], torch.zeros(3)])
    torch.testing.assert_close(vq.ema_count, 0.99 * 5.0 + 0.01 * counts)
    torch.testing.assert_close(vq.ema_sum, 0.99 * 5.0 * codebook + 0.01 * sums)
    torch.testing.assert_close(vq.codebook,
                               (0.99 * 5.0 * codebook + 0.01 * sums) / (0.99 * 5.0 + 0.01 * counts)[:, None])
    assert vq.last_resets == 0


def test_tokenizer_config_passes_its_settings_to_each_groups_vae():
    cfg = TokenizerConfig(levels_body=(3, 2), levels_hand=(5,), levels_face=(2, 2, 2), quantizer="vq", width=16,
                          depth=3, down_stages=1, dilation_growth=2, vq_code_dim=7, vq_decay=0.5, vq_beta=0.25)
    for group, levels in (("body", (3, 2)), ("hand", (5,)), ("face", (2, 2, 2))):
        vae = cfg.vae_config(group, 11)
        assert (vae.input_dim, vae.levels, vae.quantizer, vae.width, vae.depth, vae.down_stages,
                vae.dilation_growth, vae.vq_code_dim, vae.vq_decay, vae.vq_beta) == (
            11, levels, "vq", 16, 3, 1, 2, 7, 0.5, 0.25)


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


def test_tokenizer_epoch_record_is_the_mean_of_its_steps_statistics(tmp_path, monkeypatch):
    import m3t.tokenizers.train as train_module

    seen: list[dict[str, float]] = []
    real_step = train_module.train_step

    def recording_step(*args, **kwargs):
        stats = real_step(*args, **kwargs)
        seen.append(stats)
        return stats

    monkeypatch.setattr(train_module, "train_step", recording_step)
    torch.set_num_threads(1)
    seqs = tiny_face_clips(3)
    cfg = tiny_train_cfg(tmp_path, 2, 2, windows_per_clip=2)
    result = train_module.train_tokenizer("face", TINY_VAE, cfg,
                                          seqs, None, "v", progress=False)
    steps = len(seen) // 2
    assert steps >= 2 and len(seen) == 2 * steps and len(result.history) == 2
    for epoch, record in enumerate(result.history):
        window = seen[epoch * steps:(epoch + 1) * steps]
        for key in ("loss", "recon_mse", "perplexity"):
            assert record[f"train_{key}"] == pytest.approx(sum(s[key] for s in window) / steps, rel=1e-9), key


class _rest_RecordingDDP(torch.nn.Module):
    """Stands in for DistributedDataParallel (which needs a process group): wraps the model like it does."""

    wrapped: ClassVar[list] = []

    def __init__(self, module):
        super().__init__()
        self.module = module
        _rest_RecordingDDP.wrapped.append(module)

    def forward(self, *args, **kwargs):
        return self.module(*args, **kwargs)


@pytest.mark.parametrize("world_size", [1, 2])
def test_tokenizer_training_wraps_the_model_for_data_parallel_only_across_ranks(tmp_path, monkeypatch, world_size):
    import m3t.tokenizers.train as train_module
    from m3t.runtime import DistributedContext

    nets = []
    real_step = train_module.train_step

    def recording_step(net, *args, **kwargs):
        nets.append(net)
        return real_step(net, *args, **kwargs)

    _rest_RecordingDDP.wrapped = []
    monkeypatch.setattr(train_module, "DistributedDataParallel", _rest_RecordingDDP)
    monkeypatch.setattr(train_module, "train_step", recording_step)
    torch.set_num_threads(1)
    seqs = tiny_face_clips(4)
    cfg = tiny_train_cfg(tmp_path, 1, 2)
    result = train_module.train_tokenizer("face", TINY_VAE, cfg,
                                          seqs, None, "v", dist_ctx=DistributedContext(0, world_size), progress=False)
    assert nets, "at least one training step"
    if world_size == 1:
        assert _rest_RecordingDDP.wrapped == [] and all(net is result.model for net in nets)
    else:  # every step goes through the one data-parallel wrapper of the returned model
        assert _rest_RecordingDDP.wrapped == [result.model]
        assert all(isinstance(net, _rest_RecordingDDP) and net.module is result.model for net in nets)


# ------------------------------------------------------------ padding, devices, step counts, sampler seeds, probe cap


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


def test_tokenizer_checkpoints_count_every_optimiser_step_of_every_epoch(tmp_path):
    from m3t.tokenizers.checkpoint import load_tokenizer
    from m3t.tokenizers.train import train_tokenizer

    torch.set_num_threads(1)
    seqs = tiny_face_clips(5)
    cfg = tiny_train_cfg(tmp_path, 2, 2)
    result = train_tokenizer("face", TINY_VAE, cfg, seqs, None,
                             "v", progress=False)
    steps = len(WindowSampler(seqs, 8, 2, 1))
    assert steps == 3  # 5 crops in batches of 2
    for path in (result.last_path, result.best_path):
        loaded = load_tokenizer(path)
        assert (loaded.epoch, loaded.step) == (2, 2 * steps), path.name


def test_tokenizer_training_draws_its_windows_from_the_configured_seed_and_its_ranks_share(tmp_path, monkeypatch):
    import m3t.tokenizers.train as train_module
    from m3t.runtime import DistributedContext

    samplers = []

    class RecordingSampler(WindowSampler):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            samplers.append(self)

    _rest_RecordingDDP.wrapped = []
    monkeypatch.setattr(train_module, "DistributedDataParallel", _rest_RecordingDDP)
    monkeypatch.setattr(train_module, "WindowSampler", RecordingSampler)
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    seqs = [rng.normal(size=(16 + 3 * i, 3)).astype(np.float32) for i in range(4)]
    cfg = tiny_train_cfg(tmp_path, 1, 2, 2, seed=7, device="cuda")  # across ranks: the group's device
    result = train_module.train_tokenizer("face", TINY_VAE, cfg,
                                          seqs, None, "v", dist_ctx=DistributedContext(1, 2), progress=False)
    assert next(result.model.parameters()).device == torch.device("cpu")
    (sampler,) = samplers
    assert (sampler.seed, sampler.rank, sampler.world_size) == (7, 1, 2)
    assert (sampler.window, sampler.batch_size, sampler.per_sequence) == (8, 2, 2)
    assert all(a is b for a, b in zip(sampler.sequences, seqs)) and len(sampler.sequences) == 4


def test_window_sampler_masks_are_boolean_and_mark_the_real_frames_of_a_short_sequence():
    seqs = [np.arange(10, dtype=np.float32).reshape(5, 2), np.ones((12, 2), np.float32)]
    sampler = WindowSampler(seqs, 8, 2, per_sequence=1)
    (x, mask), = list(sampler.epoch(0))
    assert mask.dtype == torch.bool and mask.shape == (2, 8)
    items, _ = sampler.crops(0)
    short = int(np.flatnonzero(items == 0)[0])
    assert mask[short].tolist() == [True] * 5 + [False] * 3 and mask[1 - short].all()
    assert torch.equal(x[short, 5:], torch.tensor([[8.0, 9.0]] * 3)), "padding repeats the last frame"
    assert torch.equal(x[short][mask[short]], torch.from_numpy(seqs[0])), "a boolean mask selects the real frames"


@pytest.mark.parametrize("max_frames, kept", [(2000, 2), (2001, 3), (999, 1), (1000, 1), (1, 1), (0, 3)])
def test_probe_takes_clips_in_order_until_they_reach_max_frames(body, max_frames, kept):
    from m3t.tokenizers.evaluate import ReconstructionProbe

    clips = [fitted("c1", "dev", 1000, 1), fitted("c2", "dev", 1000, 2), fitted("c3", "dev", 500, 3)]
    probe = ReconstructionProbe(body, "face", clips, max_frames=max_frames, cache_frames=0)  # nothing posed
    assert [c.clip.id for c in probe.clips] == ["c1", "c2", "c3"][:kept]
    assert len(probe._inputs) == kept and all(truth is None for *_, truth in probe._inputs)
