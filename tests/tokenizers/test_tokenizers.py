"""Tokenizer invariants: FSQ grid, VQ reset, VAE shapes and gradients, mirroring, padding, checkpoints,
token shards, codebook statistics and the ablation table. Fast, CPU-only."""
from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest
import torch
from builders import LAYOUT, NO_FACE, tiny_tokenizers

from m3t.body.protocol import Modality, ModalityLayout
from m3t.body.rotations import mirror_rotations
from m3t.corpora.clip import Clip
from m3t.experiment import RunRecord
from m3t.metrics.codebook import codebook_stats, token_counts
from m3t.optimizer import lr_factor
from m3t.shards.schema import ShardFormatError
from m3t.shards.tokens import TokenClip, TokenInfo, read_token_shard, write_token_shard
from m3t.tokenizers.ablation import ablation_table, sweep_settings
from m3t.tokenizers.checkpoint import load_tokenizer, save_tokenizer
from m3t.tokenizers.config import TokenizerConfig, VAEConfig
from m3t.tokenizers.data import (
    GROUPS,
    STREAMS,
    WindowSampler,
    clip_sequences,
    from_canonical,
    pad_to_multiple,
    to_canonical,
)
from m3t.tokenizers.evaluate import encode_clip, reconstruct_clip
from m3t.tokenizers.fsq import FSQ
from m3t.tokenizers.vae import MotionTokenizer, count_parameters
from m3t.tokenizers.vq import EMAVQ, PlainVQ

PAPER_LEVELS = [(5, 5, 4), (6, 6, 5), (6, 6, 6)]


@pytest.mark.parametrize("levels", PAPER_LEVELS)
def test_fsq_indices_codes_round_trip_and_every_index_reachable(levels):
    fsq = FSQ(levels)
    assert fsq.codebook_size == math.prod(levels)
    every = torch.arange(fsq.codebook_size)
    codes = fsq.indices_to_codes(every)
    assert torch.equal(fsq.codes_to_indices(codes), every)
    # quantising the codes' preimages lands exactly on them: every index is reachable from latents
    latents = torch.atanh((codes * fsq._half_width + torch.where(fsq._levels % 2 == 0, 0.5, 0.0))
                          / ((fsq._levels - 1) * (1 + fsq.eps) / 2)) - torch.atanh(
        torch.where(fsq._levels % 2 == 0, 0.5, 0.0) / ((fsq._levels - 1) * (1 + fsq.eps) / 2))
    out = fsq(latents)
    assert torch.equal(out.indices, every)
    assert torch.equal(out.codes, codes)


@pytest.mark.parametrize("levels", PAPER_LEVELS)
def test_fsq_has_exactly_l_levels_per_channel(levels):
    fsq = FSQ(levels)
    z = torch.linspace(-20, 20, 20001)[:, None].expand(-1, len(levels))
    codes = fsq(z).codes
    for i, level in enumerate(levels):
        assert len(torch.unique(codes[:, i])) == level
    assert codes.abs().max() <= 1.0 + 1e-6


def test_fsq_rejects_out_of_range_indices():
    with pytest.raises(ValueError, match=r"\[0, 100\)"):
        FSQ((5, 5, 4)).indices_to_codes(torch.tensor([100]))


@pytest.mark.parametrize("quantizer", ["fsq", "vq", "vq_ema", "vq_plain"])
def test_vae_shapes_and_straight_through_gradient_reaches_the_encoder(quantizer):
    torch.manual_seed(0)
    cfg = VAEConfig(input_dim=12, levels=(5, 5, 4), quantizer=quantizer, width=16, depth=2, vq_code_dim=4)
    model = MotionTokenizer(cfg)
    x = torch.randn(3, 32, 12)
    out = model(x)
    assert out.recon.shape == x.shape
    assert out.indices.shape == (3, 8) and out.indices.dtype == torch.int64  # T / 4 tokens
    assert model.hidden(x).shape == (3, 8, 16)
    assert int(out.indices.max()) < 100
    (out.recon - x).pow(2).mean().add(out.quant_loss).backward()
    assert model.encoder[0].weight.grad is not None and model.encoder[0].weight.grad.abs().sum() > 0
    assert model.to_latent.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="multiple of 4"):
        model(torch.randn(1, 30, 12))


def test_decode_of_encode_matches_forward():
    torch.manual_seed(1)
    model = MotionTokenizer(VAEConfig(input_dim=6, levels=(6, 6, 5), width=16, depth=2)).eval()
    x = torch.randn(2, 16, 6)
    assert torch.allclose(model.decode(model.encode(x)), model(x).recon, atol=1e-5)


def test_vq_dead_codes_are_reset_to_batch_latents():
    torch.manual_seed(0)
    vq = EMAVQ(codebook_size=8, dim=2, decay=0.5)
    vq.train()
    data = torch.randn(64, 2)
    vq(data)  # initialises the codebook from the data
    vq.codebook[:4] = 100.0  # four codes far from every latent: never chosen -> counts decay below 1
    vq.ema_sum[:4] = 100.0
    resets = 0
    for _ in range(6):  # EMA counts of the unused codes halve every step until they fall below 1
        vq(data)
        if vq.last_resets:  # the codes reset in this step sit exactly on latents of the batch
            on_data = torch.cdist(vq.codebook, data).min(dim=1).values < 1e-5
            assert int(on_data.sum()) >= vq.last_resets
        resets += vq.last_resets
    assert resets >= 4
    assert (vq.codebook.abs() < 10).all(), "no code is left stranded far from the data"


def test_vq_without_reset_leaves_dead_codes_where_they_died():
    torch.manual_seed(0)
    vq = EMAVQ(codebook_size=8, dim=2, decay=0.5, reset=False)
    vq.train()
    data = torch.randn(64, 2)
    vq(data)
    vq.codebook[:4] = 100.0  # the same stranded codes as above: never chosen again
    vq.ema_sum[:4] = 100.0 * vq.ema_count[:4, None]
    for _ in range(40):  # long enough for their counts to underflow the division (0.5^40)
        out = vq(data)
    assert vq.last_resets == 0 and torch.equal(vq.codebook[:4], torch.full((4, 2), 100.0))
    assert int(out.indices.max()) >= 4 and int(out.indices.min()) >= 4  # only the live codes are chosen
    assert torch.isfinite(vq.codebook).all()


def test_plain_vq_learns_its_codebook_by_gradient_and_resets_nothing():
    torch.manual_seed(0)
    vq = PlainVQ(codebook_size=4, dim=2, beta=0.25)
    vq.train()
    data = torch.randn(32, 2) + 3.0
    vq(data)  # initialised from the first batch, like the EMA codebooks
    assert [name for name, _ in vq.named_parameters()] == ["codebook"]
    with torch.no_grad():
        vq.codebook[0] = -50.0  # one code far from the data: nothing brings it back
    start = vq.codebook.detach().clone()
    optim = torch.optim.SGD(vq.parameters(), lr=1.0)
    for _ in range(300):
        optim.zero_grad()
        vq(data).loss.backward()
        optim.step()
    assert torch.equal(vq.codebook[0].detach(), start[0])  # never chosen: no codebook-loss gradient
    indices = vq.nearest(data)
    used = indices.unique()
    assert 0 not in used.tolist()
    # the chosen codes settled on the mean of their latents (the minimiser of the codebook loss): k-means steps
    for k in used.tolist():
        mean = data[indices == k].mean(0)
        assert torch.allclose(vq.codebook[k].detach(), mean, atol=0.05)
    # the straight-through codes carry the encoder's gradient; indices_to_codes carries none
    assert not vq.indices_to_codes(used).requires_grad


def test_vq_eval_does_not_touch_the_codebook():
    vq = EMAVQ(4, 2)
    vq.train()
    vq(torch.randn(16, 2))
    before = vq.codebook.clone()
    vq.eval()
    out = vq(torch.randn(16, 2))
    assert torch.equal(vq.codebook, before)
    assert torch.allclose(out.codes, vq.indices_to_codes(out.indices), atol=1e-6)


def test_hand_group_mirrors_left_hands_with_the_body_models_mirror(body):
    left = mirror_rotations(body.rest_params(5)["right_hand"] + 0.05 * torch.randn(5, 90))
    params = {**{k: v.numpy() for k, v in body.rest_params(5).items()}, "left_hand": left.numpy()}
    right_seq, left_seq = clip_sequences(params, "hand")
    assert [s.name for s in GROUPS["hand"]] == ["right_hand", "left_hand"]
    assert np.allclose(left_seq, mirror_rotations(left).numpy())
    assert torch.allclose(from_canonical(to_canonical(left, GROUPS["hand"][1]), GROUPS["hand"][1]), left)
    # geometric check: a left hand posed as the mirror of the right hand is the right hand reflected in x
    pose = body.rest_params(1)
    pose["right_hand"] = pose["right_hand"] + 0.3 * torch.randn(1, 90)
    pose["left_hand"] = mirror_rotations(pose["right_hand"])
    joints = body.forward(pose, body.default_identity()).joints[0]
    names = body.joint_names
    right = [i for i, n in enumerate(names) if n.endswith(".R") and n.startswith("finger")]
    left_of = [names.index(names[i][:-2] + ".L") for i in right]
    mirrored = joints[left_of] * torch.tensor([-1.0, 1.0, 1.0])
    assert (mirrored - joints[right]).norm(dim=-1).max() < 0.01  # within 1 cm (Anny is nearly symmetric)


def test_short_clips_are_padded_and_bad_clips_named():
    model = MotionTokenizer(VAEConfig(input_dim=4, levels=(5, 5, 4), width=8, depth=1)).eval()
    assert encode_clip(model, np.zeros((2, 4), np.float32)).shape == (1,)
    assert encode_clip(model, np.zeros((9, 4), np.float32)).shape == (3,)
    assert reconstruct_clip(model, np.zeros((9, 4), np.float32)).shape == (9, 4)
    padded = pad_to_multiple(torch.arange(3.0).reshape(1, 3, 1), 4, minimum=8)
    assert padded.shape == (1, 8, 1) and padded[0, -1, 0] == 2.0
    with pytest.raises(ValueError, match="empty"):
        pad_to_multiple(torch.zeros(1, 0, 4), 4)
    with pytest.raises(ValueError, match="clip 'bad'.*NaN"):
        clip_sequences({"face": np.full((4, 3), np.nan, np.float32)}, "face", "bad")


def test_window_sampler_masks_padding_and_replays_an_epoch():
    seqs = [np.arange(10, dtype=np.float32).reshape(5, 2), np.ones((40, 2), np.float32)]
    sampler = WindowSampler(seqs, window=8, batch_size=2, per_sequence=3, seed=3)
    batches = list(sampler.epoch(0))
    assert len(batches) == len(sampler) == 3
    for x, mask in batches:
        assert x.shape[1:] == (8, 2)
        short = mask.sum(1) == 5
        assert torch.all(x[short][:, 5:] == x[short][:, 4:5])  # padding repeats the last frame
    again = list(sampler.epoch(0))
    assert all(torch.equal(a[0], b[0]) for a, b in zip(batches, again))
    ranks = [list(WindowSampler(seqs, 8, 2, 3, 3, rank=r, world_size=2).epoch(0)) for r in range(2)]
    assert len(ranks[0]) == len(ranks[1])


def test_lr_schedule_warms_up_then_decays_to_the_floor():
    factors = [lr_factor(s, 10, 100, 0.01) for s in range(100)]
    assert factors[0] == pytest.approx(0.1) and factors[9] == pytest.approx(1.0)
    assert all(a >= b for a, b in zip(factors[10:], factors[11:]))
    assert lr_factor(100, 10, 100, 0.01) == pytest.approx(0.01)


@pytest.mark.parametrize("input_dim", [60, 90, 108, 72, 52])
def test_paper_preset_has_about_120m_parameters(input_dim):
    from m3t.config import load_params

    tok = load_params("params.yaml", preset="paper").tokenizer
    with torch.device("meta"):
        model = MotionTokenizer(tok.vae_config("body", input_dim))
    assert abs(count_parameters(model) - 120e6) / 120e6 < 0.05
    assert abs(count_parameters(model.encoder) - count_parameters(model.decoder)) / count_parameters(model) < 0.05


def test_checkpoint_rebuilds_the_model_from_the_file_alone(tmp_path):
    torch.manual_seed(0)
    cfg = TokenizerConfig(width=16, depth=2).vae_config("face", 7)
    model = MotionTokenizer(cfg).eval()
    model.set_normalisation(torch.randn(7), torch.rand(7) + 0.5)
    path = save_tokenizer(tmp_path / "face.pt", model, "face", 3, 30, "abc", {"val_vpe_mm": 1.0})
    loaded = load_tokenizer(path)
    x = torch.randn(1, 8, 7)
    assert loaded.group == "face" and loaded.data_version == "abc" and loaded.model.cfg == cfg
    assert torch.equal(loaded.model(x).recon, model(x).recon)
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="junk.pt"):
        load_tokenizer(tmp_path / "junk.pt")
    with pytest.raises(FileNotFoundError, match="dvc repro"):
        load_tokenizer(tmp_path / "missing.pt")


def _clip(cid: str, split: str = "train") -> Clip:
    return Clip(cid, "synthetic", split, "ASL-SYN", "s1", "hello", "HELLO", f"{cid}.npz", 25.0)


def test_token_shard_round_trip_and_validation(tmp_path):
    info = TokenInfo({"body": 100, "face": 216}, 4, {"body": "d1", "face": "d2"})
    clips = [TokenClip(_clip("a"), 9, {"body": np.array([1, 2, 99]), "face": np.array([0, 215, 3])}),
             TokenClip(_clip("b"), 4, {"body": np.array([5]), "face": np.array([7])})]
    path = write_token_shard(tmp_path / "train.parquet", clips, info)
    shard = read_token_shard(path)
    assert shard.info == info
    assert [c.clip for c in shard.clips] == [c.clip for c in clips]
    assert np.array_equal(shard.clips[0].tokens["face"], [0, 215, 3])
    with pytest.raises(ValueError, match="clip 'c'.*expected ceil\\(9 / 4\\) = 3"):
        write_token_shard(tmp_path / "x.parquet", [TokenClip(_clip("c"), 9, {"body": np.array([1]), "face": np.array([1])})], info)
    with pytest.raises(ValueError, match="outside"):
        write_token_shard(tmp_path / "x.parquet", [TokenClip(_clip("d"), 4, {"body": np.array([100]), "face": np.array([1])})], info)
    assert not (tmp_path / "x.parquet").exists()
    with pytest.raises(ShardFormatError, match="token shard"):
        import pyarrow as pa
        import pyarrow.parquet as pq

        pq.write_table(pa.table({"a": [1]}), tmp_path / "plain.parquet")
        read_token_shard(tmp_path / "plain.parquet")


def test_codebook_statistics():
    counts = token_counts([np.array([0, 0, 1]), np.array([[3, 3], [3, 3]])], 5)
    assert counts.tolist() == [2, 1, 0, 4, 0]
    stats = codebook_stats(counts)
    assert stats["utilisation_pct"] == pytest.approx(60.0)
    assert stats["count_sd"] == pytest.approx(np.std([2, 1, 0, 4, 0]))
    assert codebook_stats(np.full(8, 5))["perplexity"] == pytest.approx(8.0)
    with pytest.raises(ValueError, match="out of range"):
        token_counts([np.array([5])], 5)


def test_ablation_sweep_and_table():
    settings = sweep_settings(base_width=64)
    assert {"tokenizer.quantizer": "vq", "tokenizer_train.batch_size": 16, "tokenizer.width": 64} in settings
    assert {"tokenizer.quantizer": "vq_plain", "tokenizer_train.batch_size": 16, "tokenizer.width": 64} in settings
    assert len(settings) == 4 + 3 + 2
    assert len(sweep_settings(64, full=True)) == 4 * 4 * 3
    def record(q, bs, w, util, status="FINISHED"):
        params = {"tokenizer.quantizer": q, "tokenizer_train.batch_size": str(bs), "tokenizer.width": str(w)}
        metrics = {f"{g}/utilisation_pct": util for g in ("body", "hand", "face")} | {"face/test_pa_vpe_mm": 1.5}
        return RunRecord("id", "train-tokenizers", 0, status, params, metrics, None)
    table = ablation_table([record("fsq", 16, 64, 99.0), record("fsq", 16, 64, 10.0), record("vq_plain", 16, 64, 60.0),
                            record("vq", 16, 64, 70.0), record("fsq", 32, 64, 50.0, status="FAILED")])
    lines = table.splitlines()
    assert len(lines) == 5  # header, rule, VQ rows (strong first), newest FSQ row; the failed run is left out
    assert lines[2].startswith("| VQ | 16 | 64 | 1 |") and "70.0" in lines[2]
    assert lines[3].startswith("| VQ_PLAIN | 16 | 64 | 1 |") and "60.0" in lines[3]
    assert "99.0" in lines[4] and "10.0" not in lines[4] and "1.50" in lines[4]
    assert "ppl/K body" in lines[0] and "tokens/K face" in lines[0]
    # several seeds of one setting: mean +- SD over the newest run of each seed
    seeded = [dataclasses.replace(record("vq", 16, 64, util), params={**record("vq", 16, 64, util).params,
                                                                      "tokenizer_train.seed": str(seed)})
              for seed, util in ((0, 60.0), (1, 70.0), (2, 80.0))]
    row = ablation_table(seeded).splitlines()[2]
    assert row.startswith("| VQ | 16 | 64 | 3 |") and "70.0 +- 8.2" in row


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
