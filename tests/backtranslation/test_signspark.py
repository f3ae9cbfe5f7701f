"""SignSparK_BT's released back-translation models as a judge (:mod:`m3t.backtranslation.signspark`): their model
directory loaded strictly, the network checked against a forward pass written out here in numpy, decoding of a
model whose weights force a known sentence, refusals of wrong directories, and ``score_parameter_shards`` with
such a judge on SMPL-FX stand-in parameters (and on Anny's, refused per clip).

Expected values never come from the module under test: the checkpoint's keys and shapes are listed here from
SignSparK_BT's own code (see :func:`published_shapes`), the reference forward pass uses only the saved tensors,
and the scores come from :func:`m3t.metrics.definitions.text_metrics` on sentences decoded independently.
"""
from __future__ import annotations

import copy
import math
from pathlib import Path, PurePosixPath

import numpy as np
import pytest
import torch
import yaml

from m3t.backtranslation.signspark import (
    SignSparkCheckpointError,
    SignSparkConfig,
    SignSparkText,
    config_from_yaml,
    is_signspark_judge,
    load_signspark,
    read_vocabulary,
    translate,
)
from m3t.backtranslation.smplx240 import smplx240_index, to_smplx240
from m3t.corpora.clip import Clip
from m3t.metrics.definitions import text_metrics
from m3t.scoring.params import score_parameter_shards
from m3t.shards.io import write_shard
from m3t.shards.schema import FittedClip

WORDS = ["der", "regen", "kommt", "morgen", ".", "sonne", "scheint", "die"]
TEXT_VOCAB = ["<unk>", "<pad>", "<s>", "</s>", *WORDS]  # as their Vocabulary.to_file writes itos
GLOSS_VOCAB = ["<si>", "<unk>", "<pad>", "REGEN", "MORGEN", "SONNE"]
# their configs/phoenix14t.yaml, sizes made small (released: embedding_dim / hidden_size 512, ff_size 1024,
# 3 layers and 8 heads on both sides)
CONFIG = {
    "name": "bt_phoenix14t",
    "data": {"base_path": "${DATA_ROOT}/lmdb", "dataset": "PHOENIX-2014T", "version": "phoenix_2014_trans",
             "feature_size": 240, "level": "word", "tokenizer": "whitespace", "txt_lowercase": True,
             "max_sent_length": 400, "max_sgn_length": 300},
    "testing": {"recognition_beam_sizes": [1], "translation_beam_sizes": [1, 2, 3, 4, 5],
                "translation_beam_alphas": [-1, 0, 1, 2, 3]},
    "training": {"model_dir": "./checkpoints/bt_phoenix14t", "recognition_loss_weight": 1.0,
                 "translation_loss_weight": 1.0, "eval_metric": "bleu", "eval_translation_beam_size": 3,
                 "eval_translation_beam_alpha": -1, "translation_max_output_length": 30, "use_cuda": True},
    "model": {"initializer": "xavier", "tied_softmax": False,
              "encoder": {"type": "transformer", "num_layers": 2, "num_heads": 2,
                          "embeddings": {"embedding_dim": 16, "scale": False, "dropout": 0.1, "norm_type": "batch",
                                         "activation_type": "softsign"},
                          "hidden_size": 16, "ff_size": 24, "dropout": 0.1},
              "decoder": {"type": "transformer", "num_layers": 2, "num_heads": 2,
                          "embeddings": {"embedding_dim": 16, "scale": False, "dropout": 0.1, "norm_type": "batch",
                                         "activation_type": "softsign"},
                          "hidden_size": 16, "ff_size": 24, "dropout": 0.1}},
}


# ------------------------------------------------------------------------------------------------- their layout
def published_shapes(cfg: dict, n_txt: int, n_gls: int | None) -> dict[str, tuple[int, ...]]:
    """Every ``model_state`` key of their ``SignModel`` with its shape, in their registration order.

    Layout read from SignSparK_BT (github.com/JianHe0628/SignSparK_BT): ``signspark_bt/model/model.py``
    (``SignModel.__init__``: encoder, decoder, sgn_embed, txt_embed, gloss_output_layer), ``model/encoders.py``
    (layers, layer_norm, pe), ``model/decoders.py`` (layers, pe, layer_norm, output_layer without bias),
    ``model/embeddings.py`` (``ln`` / ``lut``, then ``MaskedNorm`` holding ``norm``), and the layers of SL-T's
    ``signjoey/transformer_layers.py`` (neccam/slt) that their ``transformer_layers.py`` follows: ``layer_norm``,
    ``src_src_att`` / ``trg_trg_att`` / ``src_trg_att`` with ``k_layer v_layer q_layer output_layer``,
    ``feed_forward.layer_norm`` and ``feed_forward.pwff_layer.0`` / ``.3``, ``x_layer_norm``,
    ``dec_layer_norm``, buffer ``pe.pe`` (1, 5000, D). With their default config (configs/phoenix14t.yaml) a real
    key is ``encoder.layers.0.src_src_att.k_layer.weight`` of shape (512, 512),
    ``decoder.layers.2.feed_forward.pwff_layer.3.weight`` (512, 1024), ``sgn_embed.ln.weight`` (512, 240).
    """
    enc, dec = cfg["model"]["encoder"], cfg["model"]["decoder"]
    d, f = enc["hidden_size"], cfg["data"]["feature_size"]
    out: dict[str, tuple[int, ...]] = {}

    def linear(name: str, n_out: int, n_in: int, bias: bool = True) -> None:
        out[f"{name}.weight"] = (n_out, n_in)
        if bias:
            out[f"{name}.bias"] = (n_out,)

    def layer_norm(name: str) -> None:
        out[f"{name}.weight"], out[f"{name}.bias"] = (d,), (d,)

    def attention(name: str) -> None:
        for part in ("k_layer", "v_layer", "q_layer", "output_layer"):
            linear(f"{name}.{part}", d, d)

    def feed_forward(name: str, ff: int) -> None:
        layer_norm(f"{name}.layer_norm")
        linear(f"{name}.pwff_layer.0", ff, d)
        linear(f"{name}.pwff_layer.3", d, ff)

    def batch_norm(name: str) -> None:
        for part in ("weight", "bias", "running_mean", "running_var"):
            out[f"{name}.{part}"] = (d,)
        out[f"{name}.num_batches_tracked"] = ()

    for i in range(enc["num_layers"]):
        layer_norm(f"encoder.layers.{i}.layer_norm")
        attention(f"encoder.layers.{i}.src_src_att")
        feed_forward(f"encoder.layers.{i}.feed_forward", enc["ff_size"])
    layer_norm("encoder.layer_norm")
    out["encoder.pe.pe"] = (1, 5000, d)
    for i in range(dec["num_layers"]):
        attention(f"decoder.layers.{i}.trg_trg_att")
        attention(f"decoder.layers.{i}.src_trg_att")
        feed_forward(f"decoder.layers.{i}.feed_forward", dec["ff_size"])
        layer_norm(f"decoder.layers.{i}.x_layer_norm")
        layer_norm(f"decoder.layers.{i}.dec_layer_norm")
    out["decoder.pe.pe"] = (1, 5000, d)
    layer_norm("decoder.layer_norm")
    linear("decoder.output_layer", n_txt, d, bias=False)
    linear("sgn_embed.ln", d, f)
    batch_norm("sgn_embed.norm.norm")
    out["txt_embed.lut.weight"] = (n_txt, d)
    batch_norm("txt_embed.norm.norm")
    if n_gls is not None:
        linear("gloss_output_layer", n_gls, d)
    return out


def their_positions(d: int, length: int = 5000) -> np.ndarray:
    """(1, length, d): SL-T's PositionalEncoding, sin on even and cos on odd channels."""
    position = np.arange(length, dtype=np.float64)[:, None]
    rate = np.exp(np.arange(0, d, 2, dtype=np.float64) * -(math.log(10000.0) / d))
    pe = np.zeros((length, d))
    pe[:, 0::2], pe[:, 1::2] = np.sin(position * rate), np.cos(position * rate)
    return pe[None].astype(np.float32)


def random_state(cfg: dict, n_txt: int = len(TEXT_VOCAB), n_gls: int | None = len(GLOSS_VOCAB),
                 seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    state = {}
    for key, shape in published_shapes(cfg, n_txt, n_gls).items():
        if key.endswith(".pe"):
            state[key] = torch.from_numpy(their_positions(shape[-1], shape[1]))
        elif key.endswith("num_batches_tracked"):
            state[key] = torch.tensor(1234)
        elif key.endswith("running_var"):
            state[key] = 0.5 + torch.rand(shape, generator=g)
        elif "layer_norm" in key and key.endswith("weight"):
            state[key] = 1.0 + 0.1 * torch.randn(shape, generator=g)
        else:
            state[key] = 0.4 * torch.randn(shape, generator=g)
    return state


def write_model_dir(folder: Path, cfg: dict = CONFIG, state: dict | None = None, txt: list[str] = TEXT_VOCAB,
                    gls: list[str] | None = GLOSS_VOCAB, checkpoint: str = "best.ckpt") -> Path:
    """A model directory as their training writes it and tools/download_models.py fetches it: ``config.yaml``
    (``helpers.save_config``: yaml.safe_dump, indent 4, keys in order), ``txt.vocab`` / ``gls.vocab``
    (``Vocabulary.to_file``: one itos token per line) and the checkpoint of ``TrainManager._save_checkpoint``
    (training/trainer.py): ``{steps, total_txt_tokens, total_gls_tokens, best_ckpt_score, best_all_ckpt_scores,
    best_ckpt_iteration, model_state, optimizer_state, scheduler_state}``; the validation scores hold numpy WER
    values, as their ``metrics.wer_list`` returns them."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg, indent=4, default_flow_style=False, sort_keys=False,
                                                       width=1000), encoding="utf-8")
    (folder / "txt.vocab").write_text("".join(f"{t}\n" for t in txt), encoding="utf-8")
    if gls is not None:
        (folder / "gls.vocab").write_text("".join(f"{t}\n" for t in gls), encoding="utf-8")
    weight = torch.zeros(3, requires_grad=True)
    optimizer = torch.optim.Adam([weight], lr=5e-4, betas=(0.9, 0.998), weight_decay=1e-3)
    weight.sum().backward()
    optimizer.step()
    scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(optimizer, mode="max", factor=0.8, patience=3)
    scheduler.step(12.5)
    wer = {"wer": np.float64(61.5), "del_rate": np.float64(20.0), "ins_rate": np.float64(1.5),
           "sub_rate": np.float64(40.0)}
    scores = {"wer": wer["wer"], "wer_scores": wer, "bleu": 12.5,
              "bleu_scores": {"bleu1": 35.0, "bleu2": 22.0, "bleu3": 16.0, "bleu4": 12.5}, "chrf": 33.0,
              "rouge": 35.5}
    torch.save({"steps": 4200, "total_txt_tokens": 91000, "total_gls_tokens": 60000, "best_ckpt_score": 12.5,
                "best_all_ckpt_scores": scores, "best_ckpt_iteration": 4200,
                "model_state": random_state(cfg) if state is None else state,
                "optimizer_state": optimizer.state_dict(), "scheduler_state": scheduler.state_dict()},
               folder / checkpoint)
    return folder


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return write_model_dir(tmp_path_factory.mktemp("signspark") / "PHOENIX-2014T")


# ------------------------------------------------------------------------------------------------- loading
def test_the_default_config_gives_their_keys_and_shapes():
    real = copy.deepcopy(CONFIG)
    for side in ("encoder", "decoder"):
        real["model"][side].update(num_layers=3, num_heads=8, hidden_size=512, ff_size=1024)
        real["model"][side]["embeddings"]["embedding_dim"] = 512
    from m3t.backtranslation.signspark import SignSparkBT

    model = SignSparkBT(config_from_yaml(real, TEXT_VOCAB, GLOSS_VOCAB))
    mine = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert mine == published_shapes(real, len(TEXT_VOCAB), len(GLOSS_VOCAB))
    assert mine["encoder.layers.0.src_src_att.k_layer.weight"] == (512, 512)
    assert mine["decoder.layers.2.feed_forward.pwff_layer.3.weight"] == (512, 1024)
    assert mine["sgn_embed.ln.weight"] == (512, 240) and mine["encoder.pe.pe"] == (1, 5000, 512)


def test_their_model_directory_loads_strictly(model_dir):
    loaded = load_signspark(model_dir)
    assert is_signspark_judge(model_dir) and is_signspark_judge(model_dir / "best.ckpt")
    assert loaded.language == "DGS" and loaded.dataset == "PHOENIX-2014T"
    assert loaded.checkpoint == model_dir / "best.ckpt" and loaded.text_vocab == tuple(TEXT_VOCAB)
    assert (loaded.decoding.beam_size, loaded.decoding.alpha, loaded.decoding.max_output_length) == (3, -1.0, 30)
    assert loaded.model.cfg == SignSparkConfig(
        feature_size=240, hidden_size=16, text_vocab_size=12, gloss_vocab_size=6, encoder_layers=2, encoder_heads=2,
        encoder_ff_size=24, decoder_layers=2, decoder_heads=2, decoder_ff_size=24, sign_norm="batch",
        sign_activation="softsign", text_norm="batch", text_activation="softsign")
    saved = torch.load(model_dir / "best.ckpt", weights_only=False)["model_state"]
    state = loaded.model.state_dict()
    assert list(state) != [] and set(state) == set(saved)
    assert all(torch.equal(state[k], saved[k]) for k in saved)
    assert not loaded.model.training


def test_vocabulary_files_read_as_theirs(tmp_path):
    (tmp_path / "a.vocab").write_text("<unk>\n<pad>\n<s>\n</s>\nregen\nsonne\nregen\n", encoding="utf-8")
    assert read_vocabulary(tmp_path / "a.vocab", ("<unk>", "<pad>", "<s>", "</s>")) == (
        "<unk>", "<pad>", "<s>", "</s>", "regen", "sonne")
    (tmp_path / "b.vocab").write_text("REGEN\nSONNE\n", encoding="utf-8")  # specials missing: prepended
    assert read_vocabulary(tmp_path / "b.vocab", ("<si>", "<unk>", "<pad>")) == ("<si>", "<unk>", "<pad>", "REGEN",
                                                                                 "SONNE")


def test_the_highest_numbered_checkpoint_without_best(tmp_path):
    folder = write_model_dir(tmp_path / "m", checkpoint="100.ckpt")
    write_model_dir(folder, checkpoint="300.ckpt")
    assert load_signspark(folder).checkpoint == folder / "300.ckpt"


# ------------------------------------------------------------------------------------------------- forward pass
def _ln(x, w, b, eps):
    return (x - x.mean(-1, keepdims=True)) / np.sqrt(x.var(-1, keepdims=True) + eps) * w + b


def reference_logits(s: dict[str, np.ndarray], frames: np.ndarray, lengths: list[int], tokens: np.ndarray,
                     heads: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Memory (B, T, D) and word logits (B, L, V) of the saved tensors ``s``, in float64: linear, batch norm with
    running statistics, softsign, positions, pre-norm layers (attention per head, masked), final norms."""
    def linear(x, name, bias=True):
        return x @ s[f"{name}.weight"].T + (s[f"{name}.bias"] if bias else 0.0)

    def attention(name, kv, q, allowed):  # allowed: (B or 1, N, M)
        k, v, qq = linear(kv, f"{name}.k_layer"), linear(kv, f"{name}.v_layer"), linear(q, f"{name}.q_layer")
        d = q.shape[-1] // heads
        out = np.zeros(q.shape)
        for h in range(heads):
            part = slice(h * d, (h + 1) * d)
            scores = np.where(allowed, qq[..., part] @ k[..., part].transpose(0, 2, 1) / math.sqrt(d), -np.inf)
            weights = np.exp(scores - scores.max(-1, keepdims=True))
            out[..., part] = weights / weights.sum(-1, keepdims=True) @ v[..., part]
        return linear(out, f"{name}.output_layer")

    def feed_forward(name, x):
        h = _ln(x, s[f"{name}.layer_norm.weight"], s[f"{name}.layer_norm.bias"], 1e-6)
        return linear(np.maximum(linear(h, f"{name}.pwff_layer.0"), 0), f"{name}.pwff_layer.3") + x

    def embed(x, name):
        x = (x - s[f"{name}.norm.norm.running_mean"]) / np.sqrt(s[f"{name}.norm.norm.running_var"] + 1e-5)
        x = x * s[f"{name}.norm.norm.weight"] + s[f"{name}.norm.norm.bias"]
        return x / (1 + np.abs(x))

    frame_ok = np.arange(frames.shape[1])[None] < np.array(lengths)[:, None]  # (B, T)
    x = embed(linear(frames, "sgn_embed.ln"), "sgn_embed") + s["encoder.pe.pe"][:, : frames.shape[1]]
    for i in range(2):
        name = f"encoder.layers.{i}"
        h = _ln(x, s[f"{name}.layer_norm.weight"], s[f"{name}.layer_norm.bias"], 1e-6)
        x = feed_forward(f"{name}.feed_forward", attention(f"{name}.src_src_att", h, h, frame_ok[:, None]) + x)
    memory = _ln(x, s["encoder.layer_norm.weight"], s["encoder.layer_norm.bias"], 1e-6)
    causal = np.tril(np.ones((tokens.shape[1], tokens.shape[1]), bool))[None]
    y = embed(s["txt_embed.lut.weight"][tokens], "txt_embed") + s["decoder.pe.pe"][:, : tokens.shape[1]]
    for i in range(2):
        name = f"decoder.layers.{i}"
        h = _ln(y, s[f"{name}.x_layer_norm.weight"], s[f"{name}.x_layer_norm.bias"], 1e-6)
        h1 = attention(f"{name}.trg_trg_att", h, h, causal) + y
        h2 = attention(f"{name}.src_trg_att", memory,
                       _ln(h1, s[f"{name}.dec_layer_norm.weight"], s[f"{name}.dec_layer_norm.bias"], 1e-6),
                       frame_ok[:, None])
        y = feed_forward(f"{name}.feed_forward", h2 + h1)
    y = _ln(y, s["decoder.layer_norm.weight"], s["decoder.layer_norm.bias"], 1e-6)
    return memory, linear(y, "decoder.output_layer", bias=False)


def test_the_loaded_model_computes_their_forward_pass(model_dir):
    loaded = load_signspark(model_dir)
    saved = torch.load(model_dir / "best.ckpt", weights_only=False)["model_state"]
    s = {k: v.double().numpy() for k, v in saved.items()}
    rng = np.random.default_rng(3)
    lengths = [7, 4]
    frames = rng.normal(size=(2, 7, 240))
    frames[1, 4:] = 0.0  # padding, as their batches pad
    tokens = np.array([[2, 4, 5, 9], [2, 11, 3, 1]])
    memory, logits = reference_logits(s, frames, lengths, tokens)
    mask = torch.tensor([[True] * 7, [True] * 4 + [False] * 3])
    with torch.no_grad():
        got_memory = loaded.model.encode(torch.tensor(frames, dtype=torch.float32), mask)
        got = loaded.model.decode(got_memory, mask, torch.tensor(tokens))
    assert np.allclose(got_memory.numpy(), memory, atol=2e-5)
    assert np.allclose(got.numpy(), logits, atol=5e-5)
    assert np.abs(logits[0, 1] - logits[0, 2]).max() > 0.1  # the reference is not degenerate
    # a token only sees those before it: changing the last token leaves the earlier logits alone
    later = tokens.copy()
    later[:, -1] = 7
    with torch.no_grad():
        again = loaded.model.decode(got_memory, mask, torch.tensor(later))
    assert torch.allclose(again[:, :-1], got[:, :-1], atol=1e-6)


# ------------------------------------------------------------------------------------------------- decoding
def forced_state(sentence: list[str], seed: int = 1) -> dict[str, torch.Tensor]:
    """Random weights, except that the decoder's layers add nothing (zero attention outputs and feed-forward
    outputs leave the residual stream), every word embeds alike and the final norm has unit gain: the features
    at step p are then LN(pe_p + e), and ``output_layer`` row ``sentence[p]`` (then ``</s>``) is 10 times them,
    so each step's best word is known and far ahead."""
    state = random_state(CONFIG, seed=seed)
    for key in state:
        if key.startswith("decoder.layers.") and (".output_layer." in key or ".pwff_layer.3." in key):
            state[key] = torch.zeros_like(state[key])
    state["decoder.layer_norm.weight"], state["decoder.layer_norm.bias"] = torch.ones(16), torch.zeros(16)
    state["txt_embed.lut.weight"] = state["txt_embed.lut.weight"][4].expand(len(TEXT_VOCAB), -1).clone()
    s = {k: v.double().numpy() for k, v in state.items()}
    x = (s["txt_embed.lut.weight"][0] - s["txt_embed.norm.norm.running_mean"]) / np.sqrt(
        s["txt_embed.norm.norm.running_var"] + 1e-5) * s["txt_embed.norm.norm.weight"] + s["txt_embed.norm.norm.bias"]
    e = x / (1 + np.abs(x))
    out = np.zeros((len(TEXT_VOCAB), 16))
    for p, word in enumerate([*sentence, "</s>"]):
        out[TEXT_VOCAB.index(word)] = 10 * _ln(s["decoder.pe.pe"][0, p] + e, 1.0, 0.0, 1e-6)
    state["decoder.output_layer.weight"] = torch.tensor(out, dtype=torch.float32)
    return state


@pytest.mark.parametrize("beam,alpha", [(1, -1), (3, -1), (3, 1.0)])
def test_a_model_forced_to_a_sentence_decodes_it(tmp_path, beam, alpha):
    cfg = copy.deepcopy(CONFIG)
    cfg["training"].update(eval_translation_beam_size=beam, eval_translation_beam_alpha=alpha)
    sentence = ["der", "regen", "kommt", "morgen", "."]
    loaded = load_signspark(write_model_dir(tmp_path / "forced", cfg, forced_state(sentence)))
    poses = [np.random.default_rng(0).normal(size=(9, 240)), np.zeros((0, 240)), np.ones((3, 240))]
    assert translate(loaded, poses) == ["der regen kommt morgen .", "", "der regen kommt morgen ."]
    short = load_signspark(write_model_dir(tmp_path / "short", {**cfg, "training": {
        **cfg["training"], "translation_max_output_length": 2}}, forced_state(sentence)))
    assert translate(short, poses[:1]) == ["der regen"]  # cut at the maximum length, as theirs
    with pytest.raises(ValueError, match=r"pose 0: shape \(4, 239\), expected \(T, 240\)"):
        translate(loaded, [np.zeros((4, 239))])


def test_beam_search_finds_the_likelier_sentence_greedy_misses(tmp_path):
    """Word probabilities set per (previous word, step) through ``output_layer`` (decoder layers adding nothing,
    as in :func:`forced_state`, so the features of a step are LN(pe_step + embedding of the previous word)):
    greedy takes "der" (0.55) then "regen" (0.5), p = 0.275; "die" (0.44) then ``</s>`` (0.98), p = 0.43, is
    likelier, and a beam of 2 or 3 returns it."""
    table = {("<s>", 0): {"der": 0.55, "die": 0.44}, ("der", 1): {"regen": 0.5, "sonne": 0.49},
             ("die", 1): {"</s>": 0.98}, ("regen", 2): {"</s>": 0.99}, ("sonne", 2): {"</s>": 0.99}}
    state = forced_state([], seed=2)
    state["txt_embed.lut.weight"] = random_state(CONFIG, seed=5)["txt_embed.lut.weight"]  # words embed apart
    s = {k: v.double().numpy() for k, v in state.items()}
    x = (s["txt_embed.lut.weight"] - s["txt_embed.norm.norm.running_mean"]) / np.sqrt(
        s["txt_embed.norm.norm.running_var"] + 1e-5) * s["txt_embed.norm.norm.weight"] + s["txt_embed.norm.norm.bias"]
    embedded = x / (1 + np.abs(x))
    features, logits = [], []
    for (previous, step), probs in table.items():
        features.append(_ln(s["decoder.pe.pe"][0, step] + embedded[TEXT_VOCAB.index(previous)], 1.0, 0.0, 1e-6))
        rest = (1 - sum(probs.values())) / (len(TEXT_VOCAB) - len(probs))
        logits.append([math.log(probs.get(word, rest)) for word in TEXT_VOCAB])
    weight = np.linalg.lstsq(np.array(features), np.array(logits), rcond=None)[0].T  # (V, D): exact, 5 <= D
    assert np.allclose(np.array(features) @ weight.T, logits, atol=1e-9)
    state["decoder.output_layer.weight"] = torch.tensor(weight, dtype=torch.float32)
    pose = [np.random.default_rng(1).normal(size=(6, 240))]
    for beam, expected in ((1, "der regen"), (2, "die"), (3, "die")):
        cfg = copy.deepcopy(CONFIG)
        cfg["training"]["eval_translation_beam_size"] = beam
        assert translate(load_signspark(write_model_dir(tmp_path / str(beam), cfg, state)), pose) == [expected]


def test_reference_sentences_follow_their_text_rule():
    assert SignSparkText().reference("Der Regen, kommt  morgen.") == "der regen kommt morgen ."
    assert SignSparkText(normalize_punctuation=False, lowercase=False).reference("Der Regen.") == "Der Regen."
    assert SignSparkText(level="char", normalize_punctuation=False).reference("ab") == "a b"


# ------------------------------------------------------------------------------------------------- refusals
def test_wrong_model_directories_are_refused_by_name(model_dir, tmp_path):
    bare = write_model_dir(tmp_path / "no_txt", gls=None)
    (bare / "txt.vocab").unlink()
    with pytest.raises(SignSparkCheckpointError, match=rf"{bare}: no txt\.vocab \(nor data\.txt_vocab in its "
                                                       r"config\.yaml\); bring the txt\.vocab released beside"):
        load_signspark(bare)
    no_gls = write_model_dir(tmp_path / "no_gls", gls=None)
    with pytest.raises(SignSparkCheckpointError, match=r"no gls\.vocab"):
        load_signspark(no_gls)

    state = random_state(CONFIG)
    del state["encoder.layers.1.src_src_att.k_layer.bias"]
    state["encoder.layers.1.src_src_att.extra"] = torch.zeros(1)
    broken = write_model_dir(tmp_path / "keys", state=state)
    with pytest.raises(SignSparkCheckpointError) as err:
        load_signspark(broken)
    assert str(err.value) == (
        f"{broken / 'best.ckpt'}: model_state does not match the model that config.yaml and txt.vocab and gls.vocab "
        "describe: missing keys encoder.layers.1.src_src_att.k_layer.bias; unexpected keys "
        "encoder.layers.1.src_src_att.extra")

    other_vocab = write_model_dir(tmp_path / "vocab", txt=[*TEXT_VOCAB, "wind"], state=random_state(CONFIG))
    with pytest.raises(SignSparkCheckpointError, match=r"best\.ckpt: txt_embed\.lut\.weight has 12 rows but txt\.vocab "
                                                       r"gives 13 tokens \(with its specials\): not the txt\.vocab"):
        load_signspark(other_vocab)

    ours = write_model_dir(tmp_path / "ours")
    torch.save({"format": "m3t-backtranslation-v1", "state_dict": {}}, ours / "best.ckpt")
    with pytest.raises(SignSparkCheckpointError, match=r"not a SignSparK_BT checkpoint \(no model_state; found "
                                                       r"\['format', 'state_dict'\]\)"):
        load_signspark(ours)
    torch.save({"model_state": {}, "path": PurePosixPath("x")}, ours / "best.ckpt")
    with pytest.raises(SignSparkCheckpointError, match=r"holds objects other than tensors, numbers and numpy "
                                                       r"scalars .*PurePosixPath"):
        load_signspark(ours)

    (tmp_path / "empty").mkdir()
    assert not is_signspark_judge(tmp_path / "empty")
    with pytest.raises(SignSparkCheckpointError, match=r"empty: no best\.ckpt nor <step>\.ckpt; a SignSparK_BT "
                                                       r"model directory holds config\.yaml, best\.ckpt, txt\.vocab"):
        load_signspark(tmp_path / "empty")
    (tmp_path / "empty" / "best.ckpt").write_bytes((model_dir / "best.ckpt").read_bytes())
    with pytest.raises(SignSparkCheckpointError, match=r"empty: no config\.yaml"):
        load_signspark(tmp_path / "empty")

    elsewhere = copy.deepcopy(CONFIG)
    elsewhere["data"]["dataset"] = "MyCorpus"
    folder = write_model_dir(tmp_path / "mine", elsewhere)
    with pytest.raises(SignSparkCheckpointError, match=r"data\.dataset 'MyCorpus' is none of the released models' "
                                                       r"\(PHOENIX-2014T, CSL-Daily, How2Sign\); name the sign "
                                                       r"language"):
        load_signspark(folder)
    assert load_signspark(folder, language="DGS-SYN").language == "DGS-SYN"


# ------------------------------------------------------------------------------------------------- scoring
def _clip(cid: str, language: str, text: str, label: int | None = None) -> Clip:
    return Clip(cid, "phoenix14t", "test", language, "s0", text, "", f"{cid}.npz", 25.0, label)


def test_score_parameter_shards_with_the_signspark_judge(fx, tmp_path, monkeypatch):
    """SMPL-FX stand-in parameters (the synthetic SMPL-X / FLAME files of conftest's ``fx``): the two DGS
    sentences are back-translated from the predictions' 240-d input (the judge sees exactly
    :func:`to_smplx240` of the predicted parameters) by a model forced to say "der regen kommt morgen ." and scored
    under slt and slrtp against the references as their text rule writes them; an ASL clip has no judge and an
    isolated sign is not back-translated, both listed with their reason."""
    from smplfx_fixtures import smplfx_motion

    from m3t.backtranslation import signspark

    judge = write_model_dir(tmp_path / "PHOENIX-2014T", state=forced_state(["der", "regen", "kommt", "morgen", "."]))
    clips = [_clip("d0", "DGS", "Der Regen kommt morgen."), _clip("d1", "DGS", "Die Sonne scheint."),
             _clip("a0", "ASL", "It rains."), _clip("i0", "DGS", "REGEN", label=3)]
    identity = fx.default_identity().numpy()

    def shard(path, seed):
        rows = [FittedClip(c, "k", {k: v.numpy() for k, v in smplfx_motion(fx, frames=10 + 3 * n, seed=seed + n)
                                    .items()}, identity, {}, {}, fx.name) for n, c in enumerate(clips)]
        write_shard(path, rows, fx.layout)
        return rows

    shard(tmp_path / "ref.parquet", 0)
    predicted = shard(tmp_path / "pred.parquet", 10)
    seen = []

    def spy(loaded, poses, *args):
        seen.extend(poses)
        return translate(loaded, poses, *args)

    monkeypatch.setattr(signspark, "translate", spy)
    report = score_parameter_shards(tmp_path / "pred.parquet", tmp_path / "ref.parquet", fx, ["slt", "slrtp"],
                                    judge=judge)
    expected_inputs = [to_smplx240(p.params, fx.layout, "smplfx") for p in predicted[:2]]
    assert len(seen) == 2 and all(np.array_equal(a, b) for a, b in zip(seen, expected_inputs))
    hyps = ["der regen kommt morgen .", "der regen kommt morgen ."]
    refs = ["der regen kommt morgen .", "die sonne scheint ."]
    assert [(r["clip"], r["language"], r["hypothesis"], r["reference"]) for r in report.sentences] == [
        ("d0", "DGS", hyps[0], refs[0]), ("d1", "DGS", hyps[1], refs[1])]
    for name in ("slt", "slrtp"):
        for key, value in text_metrics(hyps, refs, "DGS", [name]).items():
            assert report.metrics[f"{name}/DGS/{key.removeprefix(name + '_')}"] == pytest.approx(value, abs=1e-12)
    assert 0 < report.metrics["slt/DGS/bleu1"] < 100 and report.clips_scored == {"slt": 2, "slrtp": 2}
    assert {u["clip"]: u["reason"] for u in report.unscored} == {
        "a0": f"no judge for language 'ASL' in {judge} (the SignSparK_BT judge of 'DGS', trained on PHOENIX-2014T)",
        "i0": "not back-translated: isolated sign (label 3): back-translation is sentence-level"}
    assert any("SignSparK_BT" in n and "beam 3" in n for n in report.notes)


def test_anny_parameters_are_refused_per_clip(body, model_dir, tmp_path):
    from tiny_pipeline import write_shards

    write_shards(tmp_path / "ref", body, {"test": 2})
    ref = tmp_path / "ref" / "test.parquet"
    report = score_parameter_shards(ref, ref, body, ["slt"], judge=model_dir, judge_language="ASL-SYN")
    with pytest.raises(ValueError) as err:
        smplx240_index(body.layout, body.name)
    assert "lacks the SMPL-X joints body: neck" in str(err.value)
    assert report.unscored == [{"clip": c, "definition": "back-translation", "reason": str(err.value)}
                               for c in ("c0", "c1")]
    assert report.metrics == {} and report.sentences == []
