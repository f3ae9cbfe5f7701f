"""Shard format round trip, versioning, atomic writes, length bucketing and padding (no body model needed)."""
from __future__ import annotations

import json
import math

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from torch.utils.data import DataLoader

from m3t.body.protocol import Modality, ModalityLayout
from m3t.corpora.clip import Clip
from m3t.shards import (
    SCHEMA_VERSION,
    FittedClip,
    LengthBucketSampler,
    ShardDataset,
    ShardFormatError,
    arrow_schema,
    collate_motion,
    read_shard,
    shard_layout,
    write_shard,
)

LAYOUT = ModalityLayout(
    modalities=(
        Modality("body", "rotation6d", ("pelvis", "spine")),  # dim 12
        Modality("left_hand", "rotation6d", ("l_wrist",), mirror_of="right_hand"),  # dim 6
        Modality("right_hand", "rotation6d", ("r_wrist",), mirror_of="left_hand"),  # dim 6
        Modality("face", "scalar", ("jaw_open", "smile", "brow_up")),  # dim 3
    ),
    identity_labels=("height", "weight", "age", "muscle"),
)


def make_clip(i: int, frames: int, rng: np.random.Generator, label: int | None = None) -> FittedClip:
    clip = Clip(
        id=f"clip-{i:04d}",
        corpus="toy",
        split="train" if i % 3 else "dev",
        language="DGS",
        signer=f"s{i % 4}",
        text=f"Sätze {i}",
        gloss="HALLO WELT",
        media=f"videos/{i}.mp4",
        fps=25.0 if i % 2 else 29.97,
        label=label,
        extra=(("session", str(i)), ("camera", "front")),
    )
    return FittedClip(
        clip=clip,
        key=f"sha256:{i:064x}",
        params={m.name: rng.standard_normal((frames, m.dim)).astype(np.float32) for m in LAYOUT.modalities},
        identity=rng.standard_normal(LAYOUT.identity_dim).astype(np.float32),
        camera={"focal": [1000.0, 1000.0], "center": [640.0, 360.0], "model": "pinhole"},
        metrics={"reproj_px": 1.5 + i, "joint_mm": math.nan} if i % 2 else {},
        body_model="anny",
    )


@pytest.fixture
def clips() -> list[FittedClip]:
    rng = np.random.default_rng(0)
    return [make_clip(i, frames=5 + 7 * i, rng=rng, label=None if i % 2 else i) for i in range(6)]


def test_round_trip_is_exact(tmp_path, clips):
    path = write_shard(tmp_path / "a.parquet", clips, LAYOUT)
    shard = read_shard(path)
    assert shard.layout == LAYOUT
    assert shard_layout(path) == LAYOUT
    assert len(shard) == len(clips)
    np.testing.assert_array_equal(shard.lengths, [c.num_frames for c in clips])
    for got, want in zip(shard.clips, clips):
        assert got.clip == want.clip  # every Clip field, label None vs int and extra included
        assert got.key == want.key and got.body_model == want.body_model and got.camera == want.camera
        assert got.metrics.keys() == want.metrics.keys()
        for k, v in want.metrics.items():
            assert got.metrics[k] == v or (math.isnan(got.metrics[k]) and math.isnan(v))
        assert got.identity.dtype == np.float32
        np.testing.assert_array_equal(got.identity, want.identity)
        assert got.params.keys() == want.params.keys()
        for name, arr in want.params.items():
            assert got.params[name].dtype == np.float32 and got.params[name].shape == arr.shape
            np.testing.assert_array_equal(got.params[name], arr)
    labels = [c.clip.label for c in shard.clips]
    assert labels[0] == 0 and labels[1] is None


def test_read_subset_of_modalities(tmp_path, clips):
    path = write_shard(tmp_path / "a.parquet", clips, LAYOUT)
    shard = read_shard(path, modalities=["face"])
    assert shard.layout == LAYOUT and set(shard.clips[2].params) == {"face"}
    np.testing.assert_array_equal(shard.clips[2].params["face"], clips[2].params["face"])
    with pytest.raises(KeyError, match="no modality 'tail'"):
        read_shard(path, modalities=["tail"])


def test_schema_is_self_describing(tmp_path, clips):
    schema = arrow_schema(LAYOUT)
    assert schema.field("face").type.value_type.list_size == 3
    assert schema.field("identity").type.list_size == LAYOUT.identity_dim
    path = write_shard(tmp_path / "a.parquet", clips, LAYOUT)
    meta = pq.read_schema(path).metadata
    assert meta[b"m3t.schema_version"] == str(SCHEMA_VERSION).encode()
    layout = json.loads(meta[b"m3t.layout"])
    assert [m["name"] for m in layout["modalities"]] == list(LAYOUT.names)
    assert [m["dim"] for m in layout["modalities"]] == [12, 6, 6, 3]
    assert layout["identity_labels"] == list(LAYOUT.identity_labels)


def test_wrong_or_missing_version_names_the_file(tmp_path, clips):
    path = write_shard(tmp_path / "a.parquet", clips, LAYOUT)
    table = pq.read_table(path)
    old = tmp_path / "old.parquet"
    pq.write_table(table.replace_schema_metadata({**table.schema.metadata, b"m3t.schema_version": b"99"}), old)
    with pytest.raises(ShardFormatError, match=r"old\.parquet.*version 99.*version 1"):
        read_shard(old)
    with pytest.raises(ShardFormatError, match=r"old\.parquet"):
        shard_layout(old)
    bare = tmp_path / "bare.parquet"
    pq.write_table(table.replace_schema_metadata(None), bare)
    with pytest.raises(ShardFormatError, match=r"bare\.parquet.*no m3t\.schema_version"):
        read_shard(bare)
    with pytest.raises(FileNotFoundError, match="missing.parquet"):
        read_shard(tmp_path / "missing.parquet")


def test_layout_mismatch_names_clip_and_modality(tmp_path, clips):
    bad = clips[3]
    params = dict(bad.params, face=np.zeros((bad.num_frames, 5), np.float32))
    broken = FittedClip(bad.clip, bad.key, params, bad.identity, bad.camera, bad.metrics, bad.body_model)
    with pytest.raises(ValueError, match=r"clip 'clip-0003', modality 'face'.*\(T, 3\)"):
        write_shard(tmp_path / "a.parquet", [*clips[:3], broken], LAYOUT)
    short = dict(bad.params, body=bad.params["body"][:-1])
    with pytest.raises(ValueError, match=r"clip 'clip-0003', modality '\w+'.*frames"):
        write_shard(tmp_path / "a.parquet", [FittedClip(bad.clip, bad.key, short, bad.identity, {}, {}, "anny")], LAYOUT)
    missing = {k: v for k, v in bad.params.items() if k != "left_hand"}
    with pytest.raises(ValueError, match=r"clip 'clip-0003'.*missing \['left_hand'\]"):
        write_shard(tmp_path / "a.parquet", [FittedClip(bad.clip, bad.key, missing, bad.identity, {}, {}, "anny")], LAYOUT)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("existing", [True, False])
def test_write_is_atomic(tmp_path, clips, monkeypatch, existing):
    dest = tmp_path / "a.parquet"
    if existing:
        write_shard(dest, clips[:2], LAYOUT)
    before = dest.read_bytes() if existing else None
    seen_tmp = []

    def explode(self, *args, **kwargs):
        seen_tmp.extend(p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp"))
        raise RuntimeError("disk full")

    monkeypatch.setattr(pq.ParquetWriter, "write_table", explode)
    with pytest.raises(RuntimeError, match="disk full"):
        write_shard(dest, clips, LAYOUT)
    assert seen_tmp, "the writer should have been writing to a temp file"
    assert sorted(p.name for p in tmp_path.iterdir()) == (["a.parquet"] if existing else [])
    if existing:
        assert dest.read_bytes() == before
        monkeypatch.undo()
        assert len(read_shard(dest)) == 2


def sampler_lengths(n: int = 1000, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).integers(10, 500, size=n)


def test_sampler_covers_each_index_once_with_similar_lengths():
    lengths = sampler_lengths()
    sampler = LengthBucketSampler(lengths, batch_size=16, seed=3)
    batches = list(sampler)
    assert len(batches) == len(sampler) == 63
    flat = [i for b in batches for i in b]
    assert sorted(flat) == list(range(len(lengths)))
    assert sorted(len(b) for b in batches) == [1000 % 16] + [16] * 62
    spread = np.median([lengths[b].max() - lengths[b].min() for b in batches])
    assert spread < 0.1 * (lengths.max() - lengths.min())
    dropped = list(LengthBucketSampler(lengths, batch_size=16, seed=3, drop_last=True))
    assert len(dropped) == 62 and all(len(b) == 16 for b in dropped)


def test_sampler_is_deterministic_per_seed():
    lengths = sampler_lengths()
    a = list(LengthBucketSampler(lengths, batch_size=8, seed=7))
    assert a == list(LengthBucketSampler(lengths, batch_size=8, seed=7))
    assert a != list(LengthBucketSampler(lengths, batch_size=8, seed=8))
    sampler = LengthBucketSampler(lengths, batch_size=8, seed=7)
    sampler.set_epoch(1)
    assert list(sampler) != a
    ordered = list(LengthBucketSampler(lengths, batch_size=8, shuffle=False))
    assert [i for b in ordered for i in b] == list(np.argsort(lengths, kind="stable"))


def test_dataset_collate_and_dataloader(tmp_path):
    rng = np.random.default_rng(5)
    frames = rng.integers(3, 40, size=30)
    made = [make_clip(i, int(t), rng) for i, t in enumerate(frames)]
    write_shard(tmp_path / "a.parquet", made[:20], LAYOUT)
    write_shard(tmp_path / "b.parquet", made[20:], LAYOUT)
    ds = ShardDataset([tmp_path / "a.parquet", tmp_path / "b.parquet"], modalities=["body", "face"])
    assert len(ds) == 30 and ds.modalities == ("body", "face")
    np.testing.assert_array_equal(ds.lengths, frames)
    item = ds[25]
    assert item.clip_id == "clip-0025" and item.length == frames[25]
    assert set(item.params) == {"body", "face"} and item.params["body"].shape == (frames[25], 12)
    assert item.metadata["shard"].endswith("b.parquet") and item.metadata["extra"]["camera"] == "front"
    torch.testing.assert_close(item.identity, torch.from_numpy(made[25].identity))

    batch = collate_motion([ds[i] for i in (0, 1, 2)])
    assert batch.mask.shape == (3, int(frames[:3].max())) and batch.mask.dtype == torch.bool
    assert batch.lengths.tolist() == frames[:3].tolist()
    assert batch.mask.sum(1).tolist() == frames[:3].tolist()
    assert torch.equal(batch.mask, torch.arange(batch.mask.shape[1])[None] < batch.lengths[:, None])
    for b in range(3):
        t = int(frames[b])
        torch.testing.assert_close(batch.params["face"][b, :t], torch.from_numpy(made[b].params["face"]))
        assert not batch.params["face"][b, t:].any()

    sampler = LengthBucketSampler(ds.lengths, batch_size=4, seed=0)
    loader = DataLoader(ds, batch_sampler=sampler, collate_fn=collate_motion)
    ids = []
    for batch in loader:
        assert batch.params["body"].shape == (len(batch.clip_ids), int(batch.lengths.max()), 12)
        assert batch.identity.shape == (len(batch.clip_ids), LAYOUT.identity_dim)
        ids.extend(batch.clip_ids)
    assert sorted(ids) == sorted(c.clip.id for c in made)


def test_dataset_rejects_duplicate_clips(tmp_path, clips):
    write_shard(tmp_path / "a.parquet", clips, LAYOUT)
    write_shard(tmp_path / "b.parquet", clips[:1], LAYOUT)
    with pytest.raises(ValueError, match=r"clip 'clip-0000' is in both .*a\.parquet and .*b\.parquet"):
        ShardDataset([tmp_path / "a.parquet", tmp_path / "b.parquet"])


@pytest.mark.parametrize("batch_size, chunk_batches", [(0, 50), (8, 0)])
def test_sampler_refuses_an_empty_batch_or_chunk(batch_size, chunk_batches):
    message = rf"batch_size \({batch_size}\) and chunk_batches \({chunk_batches}\) must be >= 1"
    with pytest.raises(ValueError, match=message):
        LengthBucketSampler([5, 6, 7], batch_size=batch_size, chunk_batches=chunk_batches)
