"""Sign Motion Language Model (M3T Sec. 3.3, App. 0.D.2): an mBART encoder-decoder over the joint
text + motion vocabulary, with fused motion inputs and five linear output heads.

- **Input fusion.** One position per time step: the embeddings of the step's four motion tokens
  (body, left hand, right hand, face) are averaged with equal weights. Prompts are fused the same way
  (``<ASL_B>``, ``<ASL_LH>``, ... -> one prompt position), and so is the end of a motion sequence.
- **Heads.** ``text`` (the spoken-language ids), ``body``, ``left_hand``, ``right_hand``, ``face``
  (codes + EOS); each reads the decoder's last hidden state and predicts only its own vocabulary.
- **Production** (text -> motion): text ids into the encoder, fused motion into the decoder, the four
  motion heads. **Translation** (motion -> text): fused motion into the encoder, text into the decoder,
  the text head. Both share every parameter.

The backbone is ``transformers``' ``MBartModel``: built from :class:`SMLMConfig` (small presets train on a
CPU), or loaded from a local mbart-large-cc25 checkpoint (``pretrained_path``) and resized to the joint
vocabulary. Embeddings go through MBart's own (scaled) embedding module, so pretrained weights see the
inputs they were trained on. With a reduced text vocabulary (``smlm.reduce_text_vocab``) the pretrained
rows are first gathered through :attr:`SMLMDims.pretrained_text_ids`.

The text head is a linear layer of its own (not tied to the embedding, unlike mBART's ``lm_head``), started
from the pretrained text rows: M3T App. 0.D.2 lists it among the five heads it introduces, and with a text
vocabulary reduced to the three corpora (~20k ids) an untied head gives the paper's 396M, a tied one 375M
(``tests/smlm/test_smlm_reduced_vocab.py`` counts both).

Axis legend: B batch, L text positions, U motion steps, S = 4 motion streams, D hidden size.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from m3t.smlm.config import SMLMConfig
from m3t.smlm.vocab import MBART_FILES, MBART_HOWTO, MOTION_STREAMS, SignVocabulary

HEADS = ("text", *MOTION_STREAMS)


@dataclass(frozen=True)
class SMLMDims:
    """The data-dependent sizes: vocabulary, heads and special ids (from :class:`SignVocabulary`);
    ``pretrained_text_ids``: the pretrained embedding row of each text id of a reduced vocabulary, () when the
    text ids are the pretrained ones (used only when weights are loaded from ``pretrained_path``)."""

    vocab_size: int
    head_sizes: dict[str, int]
    pad_id: int
    eos_id: int
    pretrained_text_ids: tuple[int, ...] = ()

    @classmethod
    def from_vocabulary(cls, vocab: SignVocabulary) -> SMLMDims:
        return cls(len(vocab), {h: vocab.head_size(h) for h in HEADS}, vocab.pad_id, vocab.eos_id,
                   tuple(vocab.pretrained_text_ids))


@dataclass
class DecoderOutput:
    hidden: torch.Tensor  # (B, U, D)
    cache: object | None  # transformers Cache for the next step


def _mbart_config(cfg: SMLMConfig, dims: SMLMDims):
    from transformers import MBartConfig

    return MBartConfig(
        vocab_size=dims.vocab_size, d_model=cfg.d_model, encoder_layers=cfg.encoder_layers,
        decoder_layers=cfg.decoder_layers, encoder_attention_heads=cfg.attention_heads,
        decoder_attention_heads=cfg.attention_heads, encoder_ffn_dim=cfg.ffn_dim, decoder_ffn_dim=cfg.ffn_dim,
        dropout=cfg.dropout, attention_dropout=cfg.dropout, activation_dropout=0.0,
        max_position_embeddings=max(cfg.max_text_tokens, cfg.max_motion_tokens) + 4,
        pad_token_id=dims.pad_id, eos_token_id=dims.eos_id, bos_token_id=dims.eos_id,
        decoder_start_token_id=dims.eos_id, scale_embedding=True,
        # MBartModel has no output layer: tying only makes the encoder's and decoder's token tables the shared
        # one, as in mbart-large-cc25 (untied, transformers 5 keeps two unused copies of the whole table)
        tie_word_embeddings=True)


def load_backbone(cfg: SMLMConfig, dims: SMLMDims, backbone_config: dict | None = None) -> nn.Module:
    """A fresh MBart from ``cfg``, the local pretrained one, or (``backbone_config``, from a checkpoint) the
    exact architecture a checkpoint was trained with, weights to be loaded by the caller."""
    from transformers import MBartConfig, MBartModel

    if backbone_config is not None:
        return MBartModel(MBartConfig.from_dict(backbone_config))
    if not cfg.pretrained_path:
        return MBartModel(_mbart_config(cfg, dims))
    path = Path(cfg.pretrained_path)
    weights = [n for n in ("model.safetensors", "pytorch_model.bin") if (path / n).exists()]
    if not (path / "config.json").exists() or not weights:
        missing = "config.json" if not (path / "config.json").exists() else "model.safetensors / pytorch_model.bin"
        raise FileNotFoundError(
            f"no mBART checkpoint in {path} ({missing} missing): expected the folder of facebook/mbart-large-cc25 "
            f"(the paper preset's models/mbart-large-cc25) with {MBART_FILES}; {MBART_HOWTO}, then set "
            "smlm.pretrained_path and smlm.text_model_path to it; or set both to '' for a random init")
    backbone = MBartModel.from_pretrained(str(path), local_files_only=True)
    if backbone.config.d_model != cfg.d_model:
        raise ValueError(f"smlm.d_model is {cfg.d_model} but the checkpoint in {path} has {backbone.config.d_model}; "
                         "use the paper preset (d_model 1024) with mbart-large-cc25")
    if dims.pretrained_text_ids:
        keep_embedding_rows(backbone, dims.pretrained_text_ids, dims.pad_id, path)
    backbone.resize_token_embeddings(dims.vocab_size)  # prompt and motion rows appended
    return backbone


def keep_embedding_rows(backbone: nn.Module, rows: tuple[int, ...], pad_id: int, source: Path | str = "?") -> None:
    """Replace the (V, D) shared embedding by its rows ``rows`` -> (len(rows), D), in that order."""
    old = backbone.get_input_embeddings()
    index = torch.as_tensor(rows, dtype=torch.long)
    if index.numel() and int(index.max()) >= old.num_embeddings:
        raise ValueError(f"the reduced text vocabulary uses pretrained id {int(index.max())} but the checkpoint in "
                         f"{source} has {old.num_embeddings} embedding rows: smlm.text_model_path and "
                         "smlm.pretrained_path must be the same mBART folder")
    new = type(old)(len(rows), old.embedding_dim, pad_id, embed_scale=old.embed_scale)
    with torch.no_grad():
        new.weight.copy_(old.weight[index.to(old.weight.device)])
    backbone.set_input_embeddings(new.to(old.weight.device))
    backbone.config.vocab_size = len(rows)
    backbone.config.pad_token_id = pad_id


class SignMotionLM(nn.Module):
    def __init__(self, cfg: SMLMConfig, dims: SMLMDims, backbone_config: dict | None = None):
        super().__init__()
        self.cfg, self.dims = cfg, dims
        self.backbone = load_backbone(cfg, dims, backbone_config)
        d = self.backbone.config.d_model
        self.heads = nn.ModuleDict({h: nn.Linear(d, n, bias=False) for h, n in dims.head_sizes.items()})
        if cfg.pretrained_path and backbone_config is None:  # the text head starts as mBART's tied output projection over the text ids
            with torch.no_grad():
                rows = self.backbone.get_input_embeddings().weight[: dims.head_sizes["text"]]
                self.heads["text"].weight.copy_(rows)

    # ---- embeddings ----------------------------------------------------------------------------
    def embed(self, ids: torch.Tensor) -> torch.Tensor:
        """(B, L) global ids -> (B, L, D), MBart's scaled embedding."""
        return self.backbone.get_input_embeddings()(ids)

    def embed_fused(self, ids: torch.Tensor) -> torch.Tensor:
        """(B, U, S) global ids of the S streams of each step -> (B, U, D): the equal-weight average."""
        return self.embed(ids).mean(dim=2)

    # ---- encoder / decoder -----------------------------------------------------------------------
    def encode(self, embeds: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(B, L, D) input embeddings + (B, L) mask -> (B, L, D) encoder states."""
        return self.backbone.get_encoder()(inputs_embeds=embeds, attention_mask=mask).last_hidden_state

    def decode(self, embeds: torch.Tensor, memory: torch.Tensor, memory_mask: torch.Tensor,
               mask: torch.Tensor | None = None, cache: object | None = None, use_cache: bool = False) -> DecoderOutput:
        """(B, U, D) decoder input embeddings (only the new steps when ``cache`` is given) -> hidden states."""
        out = self.backbone.get_decoder()(
            inputs_embeds=embeds, attention_mask=mask, encoder_hidden_states=memory,
            encoder_attention_mask=memory_mask, past_key_values=cache, use_cache=use_cache)
        return DecoderOutput(out.last_hidden_state, out.past_key_values if use_cache else None)

    def logits(self, hidden: torch.Tensor, heads: tuple[str, ...]) -> dict[str, torch.Tensor]:
        """(B, U, D) -> {head: (B, U, classes of that head)}."""
        return {h: self.heads[h](hidden) for h in heads}

    # ---- the two tasks (teacher forcing) -----------------------------------------------------------
    def production(self, text_ids: torch.Tensor, text_mask: torch.Tensor, motion_in: torch.Tensor,
                   motion_mask: torch.Tensor) -> dict[str, torch.Tensor]:
        """text (B, L) -> logits of the four motion heads at every decoder step (B, U, C_m + 1)."""
        memory = self.encode(self.embed(text_ids), text_mask)
        hidden = self.decode(self.embed_fused(motion_in), memory, text_mask, motion_mask).hidden
        return self.logits(hidden, MOTION_STREAMS)

    def translation(self, motion_ids: torch.Tensor, motion_mask: torch.Tensor, text_in: torch.Tensor,
                    text_mask: torch.Tensor) -> torch.Tensor:
        """fused motion (B, U, S) -> text logits (B, L, T)."""
        memory = self.encode(self.embed_fused(motion_ids), motion_mask)
        hidden = self.decode(self.embed(text_in), memory, motion_mask, text_mask).hidden
        return self.heads["text"](hidden)
