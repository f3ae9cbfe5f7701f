"""The tokenisation stage (:mod:`m3t.tokenizers.tokenize`) end to end on a tiny shard: token values, rejected clips,
summaries, reruns, every training corpus, tokenizers of different downsampling refused. The fitted shards here are
the project's own Parquet format (:mod:`m3t.shards.io`) over a small hand-made layout of the four motion streams, so
no body model is needed to tokenise. Written to pin behaviours that mutation testing found unchecked; tiny untrained
models only.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from builders import DIMS, LAYOUT, NO_FACE, tiny_tokenizers

from m3t.body.rotations import identity_6d, mirror_rotations
from m3t.corpora.clip import Clip
from m3t.shards.folders import DataConfig
from m3t.shards.io import write_shard
from m3t.shards.schema import FittedClip
from m3t.shards.tokens import TokenInfo, read_token_shard
from m3t.tokenizers.checkpoint import save_tokenizer
from m3t.tokenizers.config import VAEConfig
from m3t.tokenizers.data import GROUPS, STREAMS
from m3t.tokenizers.evaluate import encode_clip
from m3t.tokenizers.tokenize import (
    load_tokenizers,
    run_tokenize,
    tokenize_clip,
    tokenize_corpus,
)
from m3t.tokenizers.vae import MotionTokenizer


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


def test_tokenize_on_a_local_dask_cluster_writes_the_in_process_bytes(tmp_path, monkeypatch):
    """fit_corpus.executor: dask tokenises the row groups on a LocalCluster of 2 one-thread workers (started
    and closed for the run): every file equals the in-process run's, byte for byte (the rejected clip too); a
    worker that sees other tokenizers than the run refuses, naming the folder."""
    from m3t.fitting.config import FitCorpusConfig
    from m3t.shards import io as shard_io
    from m3t.tokenizers import tokenize as tokenize_module

    monkeypatch.setattr(shard_io, "ROW_GROUP_FRAMES", 10)  # several row groups: several tasks per shard
    models = tiny_tokenizers(seed=5)
    runs = {}
    for name in ("here", "dask"):
        data = DataConfig(train_corpora=("alpha",), shards_root=str(tmp_path / "shards"),
                          tokens_root=str(tmp_path / name), models_dir=str(tmp_path / "models"))
        if name == "here":
            data.tokenizers_dir.mkdir(parents=True)
            _save_tokenizers(data.tokenizers_dir, models)
            write_tiny_shards(data.shards_dir("alpha"), "alpha")
        run = FitCorpusConfig(executor="dask", workers=2) if name == "dask" else FitCorpusConfig(executor="local")
        runs[name] = (run_tokenize(data, run), data.tokens_dir("alpha"))
    import pyarrow.parquet as pq

    assert pq.ParquetFile(tmp_path / "shards" / "alpha" / "train.parquet").num_row_groups == 3
    (summary, here), (dask_summary, there) = runs["here"], runs["dask"]
    assert summary == dask_summary and summary["alpha"]["rejected"] == 1
    assert sorted(p.name for p in there.iterdir()) == sorted(p.name for p in here.iterdir())
    for path in here.iterdir():
        assert (there / path.name).read_bytes() == path.read_bytes(), path.name
    with pytest.raises(RuntimeError, match="seen by this worker differ from those of the run"):
        tokenize_module.tokenize_on_worker(str(tmp_path / "models" / "tokenizers"), {"body": "other"}, [], "train")


def test_load_tokenizers_refuses_tokenizers_of_different_downsampling(tmp_path):
    models = tiny_tokenizers()
    models["face"] = MotionTokenizer(VAEConfig(input_dim=DIMS["face"], levels=(6, 6, 6), width=8, depth=1,
                                               down_stages=3))
    _save_tokenizers(tmp_path, models)
    with pytest.raises(ValueError, match=r"different factors \[4, 8\]"):
        load_tokenizers(tmp_path)


@pytest.mark.parametrize("max_frames, kept", [(2000, 2), (2001, 3), (999, 1), (1000, 1), (1, 1), (0, 3)])
def test_probe_takes_clips_in_order_until_they_reach_max_frames(body, max_frames, kept):
    from m3t.tokenizers.evaluate import ReconstructionProbe

    clips = [fitted("c1", "dev", 1000, 1), fitted("c2", "dev", 1000, 2), fitted("c3", "dev", 500, 3)]
    probe = ReconstructionProbe(body, "face", clips, max_frames=max_frames, cache_frames=0)  # nothing posed
    assert [c.clip.id for c in probe.clips] == ["c1", "c2", "c3"][:kept]
    assert len(probe._inputs) == kept and all(truth is None for *_, truth in probe._inputs)
