"""Behaviour details of the tokenizers, the SMLM and the codebook metrics that the coarser tests do not pin down:
the tokenisation stage end to end on a tiny shard (token values, rejected clips, summaries, reruns, every
corpus), the SMLM evaluator's batching, progress output and decoding, the training step's defaults (no
clipping unless asked, the batch's masks reach the model), the window sampler's equal DDP shares, the
tokenizer's normalisation floor and mirrored decoder, region keypoints, and the codebook histogram's bars.
Written to pin behaviours that mutation testing of the library found unchecked. Tiny untrained models only.

The fitted shards here are the project's own Parquet format (:mod:`m3t.shards.io`) over a small hand-made
layout of the four motion streams, so no body model is needed to tokenise.
"""
from __future__ import annotations

import copy
import json

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
