"""Tokenizer invariants: FSQ grid, VQ reset, VAE shapes and gradients, mirroring, padding, checkpoints,
token shards, codebook statistics and the ablation table. Fast, CPU-only."""
from __future__ import annotations

import dataclasses

import math

import numpy as np
import pytest
import torch

from m3t.body.rotations import mirror_rotations
from m3t.corpora.clip import Clip
from m3t.experiment import RunRecord
from m3t.metrics.codebook import codebook_stats, token_counts
from m3t.shards.schema import ShardFormatError
from m3t.shards.tokens import TokenClip, TokenInfo, read_token_shard, write_token_shard
from m3t.tokenizers.ablation import ablation_table, dvc_command, sweep_settings
from m3t.tokenizers.checkpoint import load_tokenizer, save_tokenizer
from m3t.tokenizers.data import GROUPS, WindowSampler, clip_sequences, from_canonical, pad_to_multiple, to_canonical
from m3t.tokenizers.evaluate import encode_clip, reconstruct_clip
from m3t.tokenizers.fsq import FSQ
from m3t.tokenizers.config import TokenizerConfig, VAEConfig
from m3t.tokenizers.vae import MotionTokenizer, count_parameters
from m3t.training import lr_factor
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
    assert dvc_command(settings[0])[:4] == ["dvc", "exp", "run", "--temp"]
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
