"""Shard format round trip, versioning, atomic writes, length bucketing and padding; token shards; the skeleton view
of fitted clips (the one test that needs a body model, the session's Anny ``body``)."""
from __future__ import annotations

import json
import math

import numpy as np
import pyarrow as pa
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


def test_item_metadata_is_the_clip_record_without_its_id_plus_fit_and_shard(tmp_path, clips):
    path = write_shard(tmp_path / "a.parquet", clips, LAYOUT)
    item = ShardDataset([path])[3]
    assert item.clip_id == "clip-0003" and item.length == clips[3].num_frames
    assert item.metadata == {
        "corpus": "toy", "split": "dev", "language": "DGS", "signer": "s3", "text": "Sätze 3", "gloss": "HALLO WELT",
        "media": "videos/3.mp4", "fps": 25.0, "label": None, "extra": {"session": "3", "camera": "front"},
        "key": f"sha256:{3:064x}", "body_model": "anny",
        "camera": {"focal": [1000.0, 1000.0], "center": [640.0, 360.0], "model": "pinhole"},
        "metrics": item.metadata["metrics"], "shard": str(path),
    }
    assert item.metadata["metrics"]["reproj_px"] == 4.5 and math.isnan(item.metadata["metrics"]["joint_mm"])


@pytest.mark.parametrize("non_blocking", [False, True])
def test_motion_batch_to_moves_every_tensor_and_keeps_ids_and_metadata(non_blocking):
    """``to`` is checked on PyTorch's 'meta' device, which needs no GPU."""
    from m3t.shards import MotionBatch

    lengths = torch.tensor([3, 1])
    batch = MotionBatch(clip_ids=("a", "b"), params={"body": torch.ones(2, 3, 12), "face": torch.zeros(2, 3, 3)},
                        identity=torch.ones(2, 4), mask=torch.arange(3)[None] < lengths[:, None], lengths=lengths,
                        metadata=({"split": "train"}, {"split": "dev"}))
    moved = batch.to("meta", non_blocking=non_blocking) if non_blocking else batch.to("meta")
    assert moved.clip_ids == ("a", "b") and moved.metadata == batch.metadata
    tensors = {**moved.params, "identity": moved.identity, "mask": moved.mask, "lengths": moved.lengths}
    assert {k: v.device.type for k, v in tensors.items()} == dict.fromkeys(tensors, "meta")
    before = {**batch.params, "identity": batch.identity, "mask": batch.mask, "lengths": batch.lengths}
    assert {k: (tuple(v.shape), v.dtype) for k, v in tensors.items()} == \
        {k: (tuple(v.shape), v.dtype) for k, v in before.items()}
    assert batch.identity.device.type == "cpu"  # the original batch is left where it was


def test_rewriting_an_identical_shard_leaves_the_file_untouched(tmp_path, clips):
    """A shard whose bytes would not change keeps its inode and mtime (DVC then sees no change)."""
    import os

    path = write_shard(tmp_path / "a.parquet", clips, LAYOUT)
    os.utime(path, ns=(1_000_000_000, 1_000_000_000))
    inode = path.stat().st_ino
    write_shard(path, clips, LAYOUT)
    assert path.stat().st_mtime_ns == 1_000_000_000 and path.stat().st_ino == inode
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.parquet"]
    write_shard(path, clips[:2], LAYOUT)
    assert path.stat().st_mtime_ns != 1_000_000_000 and len(read_shard(path)) == 2


def test_schema_refuses_layouts_a_shard_cannot_hold():
    from m3t.body.protocol import Modality, ModalityLayout

    twice = ModalityLayout((Modality("body", "scalar", ("a",)), Modality("body", "scalar", ("b",))), ("h",))
    with pytest.raises(ValueError, match=r"layout has duplicate modality names: \['body', 'body'\]"):
        arrow_schema(twice)
    clash = ModalityLayout((Modality("text", "scalar", ("a",)), Modality("identity", "scalar", ("b",))), ("h",))
    with pytest.raises(ValueError, match=r"modality names \['identity', 'text'\] collide with shard metadata columns "
                                         r"\[.*'body_model'.*\]; rename the modality in the body model's layout"):
        arrow_schema(clash)
    empty = ModalityLayout((Modality("body", "scalar", ("a",)), Modality("face", "scalar", ())), ())
    with pytest.raises(ValueError, match=r"layout streams \['face', 'identity'\] have dim 0; shards need every "
                                         r"modality and the identity non-empty"):
        arrow_schema(empty)


def test_shard_without_its_layout_is_named_damaged(tmp_path, clips):
    path = write_shard(tmp_path / "a.parquet", clips, LAYOUT)
    table = pq.read_table(path)
    damaged = tmp_path / "damaged.parquet"
    meta = {k: v for k, v in table.schema.metadata.items() if k != b"m3t.layout"}
    pq.write_table(table.replace_schema_metadata(meta), damaged)
    for read in (read_shard, shard_layout):
        with pytest.raises(ShardFormatError) as err:
            read(damaged)
        assert str(err.value) == f"{damaged}: no m3t.layout in the Parquet metadata; the shard is damaged"


def _token_clip(i: int, frames: int, tokens: dict):
    from m3t.shards.tokens import TokenClip

    return TokenClip(make_clip(i, frames, np.random.default_rng(i)).clip, frames,
                     {k: np.asarray(v, dtype=np.int64) for k, v in tokens.items()})


def test_token_shard_holds_codebooks_up_to_the_int16_limit(tmp_path):
    from m3t.shards.tokens import TokenInfo, read_token_shard, write_token_shard

    info = TokenInfo({"body": 32767, "face": 8}, 4, {"body": "sha256:ab"})
    clips = [_token_clip(1, 7, {"body": [32766, 0], "face": [7, 3]}), _token_clip(2, 4, {"body": [5], "face": [0]})]
    shard = read_token_shard(write_token_shard(tmp_path / "train.tokens.parquet", clips, info))
    assert shard.info == info
    assert [c.clip for c in shard.clips] == [c.clip for c in clips] and [c.num_frames for c in shard.clips] == [7, 4]
    assert shard.clips[0].tokens["body"].tolist() == [32766, 0] and shard.clips[1].tokens["face"].tolist() == [0]
    schema = pq.read_schema(tmp_path / "train.tokens.parquet")
    assert schema.names[-3:] == ["num_frames", "body", "face"]
    assert {f.name: (str(f.type), f.nullable) for f in schema if f.name in ("label", "num_frames", "body", "text")} == {
        "label": ("int64", True), "text": ("string", False), "num_frames": ("int32", False),
        "body": ("list<element: int16>", False)}
    with pytest.raises(ValueError, match="codebooks above 32767 codes do not fit the int16 token columns"):
        write_token_shard(tmp_path / "big.tokens.parquet", clips, TokenInfo({"body": 32768, "face": 8}, 4, {}))
    assert not (tmp_path / "big.tokens.parquet").exists()


def test_skeleton_clips_pose_every_clip_with_frames_in_order_without_a_progress_bar(body, capsys):
    """Uses the session's Anny ``body``: the one test here that needs a body model."""
    from m3t.body.skeleton import body_graph
    from m3t.shards.skeletons import SKELETON_STREAM, skeleton_clips

    def fitted(i: int, frames: int) -> FittedClip:
        rng = np.random.default_rng(i)
        params = {k: v.numpy() + 0.02 * rng.standard_normal(v.shape).astype(np.float32)
                  for k, v in body.rest_params(frames).items()}
        made = make_clip(i, frames, rng)
        return FittedClip(made.clip, made.key, params, body.default_identity().numpy(), {}, {}, "anny")

    graph = body_graph()
    clips = [fitted(0, 3), fitted(1, 0), fitted(2, 2)]
    out = skeleton_clips(body, clips, graph)
    assert capsys.readouterr().err == ""  # no progress bar unless asked for
    assert [s.clip_id for s in out] == ["clip-0000", "clip-0002"]  # the empty clip is left out
    for s, frames in zip(out, (3, 2)):
        assert s.points.shape == (frames, len(graph.joints), 3) and s.points.dtype == np.float64
        assert s.coords.shape == (frames, 3 * len(graph.joints)) and s.coords.dtype == np.float32
        assert 0.2 < s.scale < 0.6  # metres per unit: a mean shoulder width
        assert set(s.as_fitted().params) == {SKELETON_STREAM} and s.as_fitted().clip is s.fitted.clip
    skeleton_clips(body, clips[:1], graph, progress=True, desc="skeletons: dev")
    assert "skeletons: dev" in capsys.readouterr().err


def test_shards_of_different_body_models_are_refused_naming_both_files(tmp_path, clips):
    other_dims = ModalityLayout(
        modalities=(Modality("body", "rotation6d", ("pelvis",)),) + LAYOUT.modalities[1:],
        identity_labels=LAYOUT.identity_labels,
    )
    other_identity = ModalityLayout(modalities=LAYOUT.modalities, identity_labels=("height", "weight"))
    write_shard(tmp_path / "a.parquet", clips[:2], LAYOUT)
    narrow = [FittedClip(c.clip, c.key, {**c.params, "body": c.params["body"][:, :6]}, c.identity, c.camera, c.metrics,
                         c.body_model) for c in clips[2:4]]
    write_shard(tmp_path / "b.parquet", narrow, other_dims)
    short = [FittedClip(c.clip, c.key, c.params, c.identity[:2], c.camera, c.metrics, c.body_model) for c in clips[4:]]
    write_shard(tmp_path / "c.parquet", short, other_identity)
    with pytest.raises(ValueError) as info:
        ShardDataset([tmp_path / "a.parquet", tmp_path / "b.parquet"])
    message = str(info.value)
    assert "b.parquet: modality 'body' has dim 6, " in message and "a.parquet has 12; " in message
    assert message.endswith("shards fitted with different body models cannot be mixed")
    with pytest.raises(ValueError) as info:
        ShardDataset([tmp_path / "a.parquet", tmp_path / "c.parquet"])
    message = str(info.value)
    assert "c.parquet: identity dim 2, " in message and "a.parquet has 4; " in message
    assert message.endswith("shards fitted with different body models cannot be mixed")
    # Shards that differ only in a modality left out of the dataset can be read together.
    assert len(ShardDataset([tmp_path / "a.parquet", tmp_path / "b.parquet"], modalities=["face"])) == 4


def test_sampler_length_is_the_whole_number_of_batches_it_yields():
    for n, batch_size in ((10, 4), (12, 4), (3, 4)):
        for drop_last in (False, True):
            sampler = LengthBucketSampler(list(range(1, n + 1)), batch_size=batch_size, drop_last=drop_last)
            assert len(sampler) == len(list(sampler)) == (n // batch_size if drop_last else -(-n // batch_size))


def test_collated_batch_keeps_each_clips_metadata_in_batch_order(tmp_path, clips):
    write_shard(tmp_path / "a.parquet", clips, LAYOUT)
    ds = ShardDataset(tmp_path / "a.parquet")
    items = [ds[i] for i in (3, 0, 5)]
    batch = collate_motion(items)
    assert batch.clip_ids == ("clip-0003", "clip-0000", "clip-0005")
    assert batch.metadata == tuple(item.metadata for item in items)
    assert [m["extra"]["session"] for m in batch.metadata] == ["3", "0", "5"]
    with pytest.raises(ValueError, match="collate_motion got an empty batch"):
        collate_motion([])


def test_damaged_layout_metadata_names_the_shard_file():
    from m3t.shards.schema import LAYOUT_KEY, VERSION_KEY, check_schema_metadata

    version = str(SCHEMA_VERSION).encode()
    with pytest.raises(ShardFormatError, match=r"^fitted/x\.parquet: cannot parse the m3t\.layout metadata .*damaged"):
        check_schema_metadata({VERSION_KEY: version, LAYOUT_KEY: b"{not json"}, "fitted/x.parquet")
    with pytest.raises(ShardFormatError, match=r"^fitted/y\.parquet: no m3t\.schema_version"):
        check_schema_metadata(None, "fitted/y.parquet")


def _rest_broken_clip(case: str):

    from m3t.shards import FittedClip

    clip = make_clip(2, 4, np.random.default_rng(0))
    params, identity, camera = dict(clip.params), clip.identity, clip.camera
    if case == "missing":
        del params["left_hand"]
    elif case == "unknown":
        params["tail"] = params["face"]
    elif case == "shape":
        params["face"] = params["face"][:, :2]
    elif case == "dtype":
        params["face"] = params["face"].astype(np.int32)
    elif case == "nan":
        params["face"] = params["face"].copy()
        params["face"][1, 0] = np.nan
    elif case == "frames":
        params["face"] = params["face"][:3]
    elif case == "empty":
        params = {k: v[:0] for k, v in params.items()}
    elif case == "identity":
        identity = identity[:3]
    elif case == "camera":
        camera = {"focal": np.array([1000.0, 1000.0])}
    return FittedClip(clip.clip, clip.key, params, identity, camera, clip.metrics, clip.body_model), LAYOUT


@pytest.mark.parametrize("case, message", [
    ("missing", ("clip 'clip-0002': modalities do not match the layout (missing ['left_hand'], unknown []); layout "
                 "has ['body', 'left_hand', 'right_hand', 'face']")),
    ("unknown", ("clip 'clip-0002': modalities do not match the layout (missing [], unknown ['tail']); layout has "
                 "['body', 'left_hand', 'right_hand', 'face']")),
    ("shape", ("clip 'clip-0002', modality 'face': shape (4, 2), layout expects (T, 3); check that the clip was "
               "fitted with the same body model as the layout")),
    ("dtype", "clip 'clip-0002', modality 'face': dtype int32, expected float32"),
    ("nan", "clip 'clip-0002', modality 'face': contains NaN or inf; the fit diverged"),
    ("frames", "clip 'clip-0002', modality 'face': 3 frames, other modalities have 4"),
    ("empty", "clip 'clip-0002': has no frames; drop it before writing the shard"),
    ("identity", "clip 'clip-0002', identity: shape (3,), layout expects (4,)"),
    ("camera", ("clip 'clip-0002', camera: not JSON-serialisable (Object of type ndarray is not JSON serializable); "
                "store plain lists/floats")),
])
def test_writing_a_malformed_clip_says_which_clip_and_what_is_wrong_and_writes_nothing(tmp_path, case, message):

    from m3t.shards import write_shard

    bad, layout = _rest_broken_clip(case)
    path = tmp_path / "train.parquet"
    with pytest.raises(ValueError) as err:
        write_shard(path, [make_clip(1, 4, np.random.default_rng(1)), bad], layout)
    assert str(err.value) == message
    assert not path.exists()


@pytest.mark.parametrize("damage", [math.nan, math.inf, None])
def test_a_shard_damaged_after_writing_names_the_row_and_column_of_the_bad_value(tmp_path, clips, damage):
    """The writer refuses NaN / inf, so a non-finite or missing (null) value in a stored frame means the file was
    edited or damaged afterwards: the reader names the row holding it (not the first row) and the column, for a
    value deep in a later row as for one in row 0."""
    path = write_shard(tmp_path / "a.parquet", clips, LAYOUT)
    table = pq.read_table(path)
    for row, frame, value_index in ((3, 4, 1), (0, 0, 0)):
        column = table.column("face").to_pylist()
        column[row][frame][value_index] = damage
        damaged = table.set_column(table.schema.get_field_index("face"), table.schema.field("face"),
                                   pa.array(column, type=table.schema.field("face").type))
        out = tmp_path / f"damaged-{row}.parquet"
        pq.write_table(damaged.replace_schema_metadata(table.schema.metadata), out)
        with pytest.raises(ShardFormatError) as info:
            read_shard(out)
        assert str(info.value) == (f"{out}: row {row} (0-based), column 'face' holds NaN or inf; the shard is damaged "
                                   "(re-run the stage that wrote it)")
        assert read_shard(out, modalities=["body"]).clips[row].clip.id == clips[row].clip.id  # other columns read


def _retyped(table: pa.Table, name: str) -> tuple[pa.Table, pa.DataType]:
    """``table`` with column ``name`` replaced by one of another type: int64 where anything else belongs (floats,
    lists, text), numbers written as text where int64 belongs."""
    field = table.schema.field(name)
    wrong = pa.string() if field.type.equals(pa.int64()) else pa.int64()
    values = [str(i) for i in range(table.num_rows)] if wrong == pa.string() else list(range(table.num_rows))
    changed = table.set_column(table.schema.get_field_index(name), pa.field(name, wrong), pa.array(values, wrong))
    return changed.replace_schema_metadata(table.schema.metadata), wrong


@pytest.mark.parametrize("column", arrow_schema(LAYOUT).names)
def test_a_column_of_another_type_is_refused_naming_file_column_and_both_types(tmp_path, clips, column):
    """Every column of the shard schema: a file whose column has another Arrow type (a string where a number
    belongs, numbers where float lists belong) is refused before any row is read, naming the file, the column,
    the type found and the one expected, whichever modalities are asked for."""
    table = pq.read_table(write_shard(tmp_path / "a.parquet", clips, LAYOUT))
    damaged, wrong = _retyped(table, column)
    out = tmp_path / "retyped.parquet"
    pq.write_table(damaged, out)
    for modalities in (None, ["body"]):
        with pytest.raises(ShardFormatError) as info:
            read_shard(out, modalities=modalities)
        expected = arrow_schema(LAYOUT).field(column).type
        assert str(info.value) == (f"{out}: column {column!r} is {wrong}, expected {expected}; the shard was edited "
                                   "or not written by m3t; re-run the stage that wrote it")


def test_a_token_shard_column_of_another_type_or_missing_is_refused_naming_it(tmp_path):
    from m3t.shards.tokens import TokenInfo, read_token_shard, token_schema, write_token_shard

    info = TokenInfo({"body": 64, "face": 8}, 4, {"body": "sha256:ab"})
    clips = [_token_clip(1, 7, {"body": [3, 0], "face": [7, 3]}), _token_clip(2, 4, {"body": [5], "face": [0]})]
    path = write_token_shard(tmp_path / "train.tokens.parquet", clips, info)
    table = pq.read_table(path)
    for column in table.schema.names:
        damaged, wrong = _retyped(table, column)
        out = tmp_path / f"retyped-{column}.parquet"
        pq.write_table(damaged, out)
        with pytest.raises(ShardFormatError) as err:
            read_token_shard(out)
        assert str(err.value) == (f"{out}: column {column!r} is {wrong}, expected {token_schema(info).field(column).type}"
                                  "; the token shard was edited or not written by m3t; rerun the tokenize stage")
    out = tmp_path / "no-face.parquet"
    pq.write_table(table.drop_columns(["face"]).replace_schema_metadata(table.schema.metadata), out)
    with pytest.raises(ShardFormatError, match=f"{out}: column 'face' is missing"):
        read_token_shard(out)
