"""SignSparK_BT's released back-translation models as a judge: their model directory read as it is, their network
rebuilt under their parameter names (their ``state_dict`` loads with ``strict=True``), their decoding and text rule.

Source: SignSparK_BT (github.com/JianHe0628/SignSparK_BT, Apache-2.0; read and re-implemented, nothing pasted):

- **Model directory** (``signspark_bt/inference.py`` ``make_back_translation_model``, ``tools/download_models.py``,
  ``training/trainer.py`` ``_save_checkpoint`` / ``train``): ``config.yaml`` (the training config), ``best.ckpt``
  (else the highest ``<step>.ckpt``), ``txt.vocab`` and ``gls.vocab`` (else ``data.txt_vocab`` / ``data.gls_vocab``
  of the config). A checkpoint is ``torch.save`` of ``{steps, total_txt_tokens, total_gls_tokens, best_ckpt_score,
  best_all_ckpt_scores, best_ckpt_iteration, model_state, optimizer_state, scheduler_state}``; a vocabulary file
  holds one token per line, read as the specials (text ``<unk> <pad> <s> </s>``, gloss ``<si> <unk> <pad>``) then
  the file's tokens, each kept once (``data/vocabulary.py``).
- **Network** (``model/model.py`` ``build_model``, ``embeddings.py``, ``encoders.py``, ``decoders.py``): frames
  (B, T, 240) -> ``sgn_embed`` (linear ``ln``, ``norm`` (batch / layer / group), activation (softsign), optional
  scale) -> + ``pe`` -> pre-norm encoder layers -> LayerNorm -> memory; text -> ``txt_embed`` (``lut``, norm,
  activation) -> + ``pe`` -> pre-norm decoder layers -> LayerNorm -> ``output_layer`` (no bias); a CTC head
  ``gloss_output_layer`` when trained with ``recognition_loss_weight > 0``. The layers come from their
  ``model/transformer_layers.py``, which follows SL-T's ``signjoey/transformer_layers.py`` (neccam/slt; the
  release derives from it and uses its class and attribute names, ``src_src_att``, ``trg_trg_att``, ...):
  LayerNorm eps 1e-6, feed-forward ``pwff_layer`` = Linear (index 0), ReLU, dropout, Linear (index 3), and a
  sinusoidal ``pe`` buffer of 5000 positions that is part of the state dict.
- **Decoding** (``inference.py`` ``back_translate``, ``model/search.py``): batches of 32 in input order; beam size
  and alpha from the config (``testing``, else ``training``, ``eval_translation_beam_size`` / ``_alpha``; released:
  3 and -1), at most ``training.translation_max_output_length`` tokens (released: 30); greedy below beam 2, else
  JoeyNMT's beam search; tokens cut at the first ``</s>`` and joined with single spaces; no frames -> ``""``.
- **References** (``cli.py`` ``_normalize``, ``data/lmdb_dataset.py`` ``normalize_text``): with
  ``normalize_punctuation`` (default on; off for CSL-Daily) every ``.`` and ``,`` is removed and `` .`` appended,
  then lower-cased, tokenised (whitespace, jieba, or characters) and joined with single spaces.

Departures: inference only - the norms always use their running statistics over every frame (their eval path),
no dropout; checkpoints are read with ``weights_only=True``, allowing numpy scalars (their validation scores hold
numpy WER values) and nothing else.

Axis legend: B batch, T frames, F input features (240), L text tokens, D hidden size, H heads, V text vocabulary,
K beam.
"""
from __future__ import annotations

import math
import os
import pickle
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

from m3t.backtranslation.signspark_model import (
    ACTIVATIONS,
    SignSparkBT,
    SignSparkConfig,
)
from m3t.declared import check_zip

TEXT_SPECIALS = ("<unk>", "<pad>", "<s>", "</s>")
GLOSS_SPECIALS = ("<si>", "<unk>", "<pad>")
# the released models' data.dataset -> the sign language this project's corpus adapters give their clips
DATASET_LANGUAGE = {"PHOENIX-2014T": "DGS", "CSL-Daily": "CSL", "How2Sign": "ASL"}
INFERENCE_BATCH = 32  # their back_translate's sequences per forward pass
# numpy scalars as numpy 2 and numpy 1 pickle them (their checkpoints' validation scores): the scalar, its dtype
NUMPY_SCALARS = [np.dtype, np._core.multiarray.scalar, (np._core.multiarray.scalar, "numpy.core.multiarray.scalar"),
                 *(type(np.dtype(code)) for code in "?bhilqBHILQefdg")]
MODEL_FILES = "config.yaml, best.ckpt, txt.vocab and gls.vocab"


class SignSparkCheckpointError(ValueError):
    """A path that is not a complete, consistent SignSparK_BT model directory."""


@dataclass(frozen=True)
class SignSparkDecoding:
    beam_size: int = 1
    alpha: float = -1.0  # length penalty ((5 + step) / 6) ** alpha; -1: none
    max_output_length: int = 30


@dataclass(frozen=True)
class SignSparkText:
    """Their text pipeline (``data`` section), applied to reference sentences."""

    level: str = "word"
    tokenizer: str = "whitespace"
    lowercase: bool = True
    normalize_punctuation: bool = True

    def reference(self, sentence: str) -> str:
        if self.normalize_punctuation:
            sentence = sentence.replace(".", "").replace(",", "") + " ."
        if self.lowercase:
            sentence = sentence.lower()
        sentence = sentence.strip()
        if self.level == "char":
            tokens = list(sentence)
        elif self.tokenizer == "jieba":
            from m3t.metrics.text import tokenize

            tokens = tokenize(sentence, "zh")
        else:
            tokens = sentence.split()
        return " ".join(tokens)


# ------------------------------------------------------------------------------------------------- loading
@dataclass(frozen=True)
class LoadedSignSpark:
    model: SignSparkBT
    text_vocab: tuple[str, ...]  # index -> token
    decoding: SignSparkDecoding
    text: SignSparkText
    language: str  # the sign language of its clips, as this project's corpora name it
    dataset: str
    checkpoint: Path


def _model_dir_and_checkpoint(path: Path) -> tuple[Path, Path]:
    if path.is_file():
        return path.parent, path
    if not path.is_dir():
        raise FileNotFoundError(f"{path} does not exist; a SignSparK_BT model directory holds {MODEL_FILES}")
    if (path / "best.ckpt").is_file():
        return path, path / "best.ckpt"
    numbered = sorted((int(p.stem), p) for p in path.glob("*.ckpt") if p.stem.isdigit())
    if not numbered:
        raise SignSparkCheckpointError(f"{path}: no best.ckpt nor <step>.ckpt; a SignSparK_BT model directory holds "
                                       f"{MODEL_FILES}")
    return path, numbered[-1][1]


def _read_config(folder: Path) -> dict:
    path = folder / "config.yaml"
    if not path.is_file():
        raise SignSparkCheckpointError(f"{folder}: no config.yaml; a SignSparK_BT model directory holds "
                                       f"{MODEL_FILES} (tools/download_models.py fetches all four)")
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise SignSparkCheckpointError(f"{path}: not valid YAML ({exc})") from exc
    model = raw.get("model") if isinstance(raw, dict) else None
    if not isinstance(model, dict) or not all(isinstance(model.get(k), dict) for k in ("encoder", "decoder")) \
            or not isinstance(raw.get("data"), dict):
        raise SignSparkCheckpointError(f"{path}: not a SignSparK_BT config (expected sections data, model.encoder, "
                                       "model.decoder)")
    return raw


def is_signspark_judge(path: str | os.PathLike) -> bool:
    """Whether ``path`` (a directory, or a checkpoint file inside one) is a SignSparK_BT model, by its config."""
    path = Path(path)
    try:
        _read_config(path.parent if path.is_file() else path)
    except (SignSparkCheckpointError, OSError, UnicodeDecodeError):
        return False
    return True


def read_vocabulary(path: Path, specials: Sequence[str]) -> tuple[str, ...]:
    """Their vocabulary file: the specials, then one token per line, each token kept once, in order."""
    tokens = [line.strip("\n") for line in path.read_text(encoding="utf-8").splitlines(keepends=True)]
    return tuple(dict.fromkeys([*specials, *tokens]))


def _vocabulary(folder: Path, data: Mapping, field: str, specials: Sequence[str]) -> tuple[str, ...]:
    path = folder / f"{field}.vocab"
    if not path.is_file() and data.get(f"{field}_vocab"):
        path = Path(os.path.expanduser(os.path.expandvars(str(data[f"{field}_vocab"]))))
    if not path.is_file():
        raise SignSparkCheckpointError(f"{folder}: no {field}.vocab (nor data.{field}_vocab in its config.yaml); "
                                       f"bring the {field}.vocab released beside the checkpoint")
    return read_vocabulary(path, specials)


def _embedding_choices(section: Mapping, where: str) -> tuple[str | None, str | None, float | None]:
    norm, activation = section.get("norm_type"), section.get("activation_type")
    if norm not in (None, "batch", "layer", "group"):
        raise SignSparkCheckpointError(f"{where}.norm_type {norm!r}: expected batch, layer or group")
    if activation is not None and activation not in ACTIVATIONS:
        raise SignSparkCheckpointError(f"{where}.activation_type {activation!r}: expected one of "
                                       f"{', '.join(ACTIVATIONS)}")
    scale = None
    if section.get("scale", False):
        scale = float(section.get("scale_factor") or math.sqrt(section["embedding_dim"]))
    return norm, activation, scale


def config_from_yaml(raw: Mapping, text_vocab: Sequence[str], gloss_vocab: Sequence[str] | None,
                     where: str = "config.yaml") -> SignSparkConfig:
    """A :class:`SignSparkConfig` from their config (defaults of their classes where a key is absent)."""
    enc, dec = raw["model"]["encoder"], raw["model"]["decoder"]
    sizes = {}
    for side, section in (("encoder", enc), ("decoder", dec)):
        if section.get("type", "transformer") != "transformer":
            raise SignSparkCheckpointError(f"{where}: model.{side}.type {section['type']!r}; the release is "
                                           "transformer only")
        for key in ("num_heads", "embeddings"):
            if key not in section:
                raise SignSparkCheckpointError(f"{where}: model.{side}.{key} missing")
        sizes[f"model.{side}.embeddings.embedding_dim"] = section["embeddings"].get("embedding_dim")
        sizes[f"model.{side}.hidden_size"] = section.get("hidden_size", 512)
    if len(set(sizes.values())) != 1 or not isinstance(sizes["model.encoder.hidden_size"], int) \
            or sizes["model.encoder.hidden_size"] % 2 or sizes["model.encoder.hidden_size"] % enc["num_heads"] \
            or sizes["model.encoder.hidden_size"] % dec["num_heads"]:
        raise SignSparkCheckpointError(f"{where}: {sizes} must be one even size divisible by the heads "
                                       "(their encoder, decoder and attention need it)")
    feature = raw["data"].get("feature_size", 240)
    sign, text = (_embedding_choices(s["embeddings"], f"{where}: model.{n}.embeddings")
                  for n, s in (("encoder", enc), ("decoder", dec)))
    return SignSparkConfig(
        feature_size=int(sum(feature) if isinstance(feature, list) else feature),
        hidden_size=sizes["model.encoder.hidden_size"], text_vocab_size=len(text_vocab),
        gloss_vocab_size=len(gloss_vocab) if gloss_vocab is not None else None,
        encoder_layers=enc.get("num_layers", 8), encoder_heads=enc["num_heads"],
        encoder_ff_size=enc.get("ff_size", 2048), decoder_layers=dec.get("num_layers", 4),
        decoder_heads=dec["num_heads"], decoder_ff_size=dec.get("ff_size", 2048),
        sign_norm=sign[0], sign_activation=sign[1], sign_scale=sign[2],
        text_norm=text[0], text_activation=text[1], text_scale=text[2],
        text_padding_idx=text_vocab.index("<pad>"), tied_softmax=bool(raw["model"].get("tied_softmax", False)))


def _read_checkpoint(path: Path) -> dict:
    try:
        check_zip(path)  # torch's reader allocates each record's declared size
        with torch.serialization.safe_globals(NUMPY_SCALARS):
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        found = [line.strip() for line in str(exc).splitlines() if "global" in line.lower() or "got <" in line]
        raise SignSparkCheckpointError(f"{path}: holds objects other than tensors, numbers and numpy scalars "
                                       f"({(found or [str(exc)])[-1]}); not a SignSparK_BT checkpoint") from exc
    except Exception as exc:  # any unreadable file gets the same answer
        raise SignSparkCheckpointError(f"{path}: not a readable torch checkpoint "
                                       f"({type(exc).__name__}: {exc})") from exc
    if not isinstance(payload, dict) or not isinstance(payload.get("model_state"), Mapping):
        found = sorted(map(str, payload)) if isinstance(payload, dict) else type(payload).__name__
        raise SignSparkCheckpointError(f"{path}: not a SignSparK_BT checkpoint (no model_state; found {found})")
    return payload


def _listed(keys: Sequence[str], limit: int = 8) -> str:
    return ", ".join(keys[:limit]) + (f" and {len(keys) - limit} more" if len(keys) > limit else "")


def _check_state(model: SignSparkBT, state: Mapping, path: Path, vocab_files: str) -> None:
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    shapes = [f"{k} {tuple(state[k].shape)} (expected {tuple(v.shape)})" for k, v in expected.items()
              if k in state and tuple(getattr(state[k], "shape", ())) != tuple(v.shape)]
    if missing or unexpected or shapes:
        parts = [f"missing keys {_listed(missing)}" if missing else "",
                 f"unexpected keys {_listed(unexpected)}" if unexpected else "",
                 f"other shapes: {_listed(shapes)}" if shapes else ""]
        raise SignSparkCheckpointError(f"{path}: model_state does not match the model that config.yaml and "
                                       f"{vocab_files} describe: {'; '.join(p for p in parts if p)}")


def load_signspark(path: str | os.PathLike, language: str | None = None,
                   device: str | torch.device = "cpu") -> LoadedSignSpark:
    """A released SignSparK_BT model: ``path`` is its directory (or a checkpoint in it); ``language``: the sign
    language its clips carry here (default: from ``data.dataset``, :data:`DATASET_LANGUAGE`)."""
    folder, ckpt = _model_dir_and_checkpoint(Path(path))
    raw = _read_config(folder)
    data, training = raw["data"], raw.get("training") or {}
    if training.get("translation_loss_weight", 1.0) <= 0:
        raise SignSparkCheckpointError(f"{folder / 'config.yaml'}: training.translation_loss_weight is 0, a "
                                       "recognition-only model: it has no text decoder to back-translate with")
    text_vocab = _vocabulary(folder, data, "txt", TEXT_SPECIALS)
    recognition = training.get("recognition_loss_weight", 1.0) > 0
    gloss_vocab = _vocabulary(folder, data, "gls", GLOSS_SPECIALS) if recognition else None
    cfg = config_from_yaml(raw, text_vocab, gloss_vocab, str(folder / "config.yaml"))
    dataset = data.get("dataset", "")
    dataset = dataset[0] if isinstance(dataset, list) and len(dataset) == 1 else dataset
    language = language or DATASET_LANGUAGE.get(str(dataset))
    if not language:
        raise SignSparkCheckpointError(f"{folder / 'config.yaml'}: data.dataset {dataset!r} is none of the released "
                                       f"models' ({', '.join(DATASET_LANGUAGE)}); name the sign language its "
                                       "clips carry (load_signspark(path, language=...))")
    testing = raw.get("testing") or {}
    decoding = SignSparkDecoding(
        int(testing.get("eval_translation_beam_size", training.get("eval_translation_beam_size", 1))),
        float(testing.get("eval_translation_beam_alpha", training.get("eval_translation_beam_alpha", -1))),
        int(training.get("translation_max_output_length") or 0))
    if decoding.max_output_length < 1:
        raise SignSparkCheckpointError(f"{folder / 'config.yaml'}: training.translation_max_output_length missing "
                                       "or < 1; their decoding needs it")
    model = SignSparkBT(cfg)
    payload = _read_checkpoint(ckpt)
    state = payload["model_state"]
    sizes = {"txt_embed.lut.weight": ("txt.vocab", len(text_vocab)),
             "gloss_output_layer.weight": ("gls.vocab", len(gloss_vocab or ()))}
    for key, (name, size) in sizes.items():
        if key in state and key in model.state_dict() and state[key].shape[0] != size:
            raise SignSparkCheckpointError(f"{ckpt}: {key} has {state[key].shape[0]} rows but {name} gives {size} "
                                           f"tokens (with its specials): not the {name} this model was trained with")
    _check_state(model, state, ckpt, "txt.vocab" + (" and gls.vocab" if recognition else ""))
    model.load_state_dict(state, strict=True)
    model.to(device).eval()
    text = SignSparkText(str(data.get("level", "word")), str(data.get("tokenizer", "whitespace")),
                         bool(data.get("txt_lowercase", True)), bool(data.get("normalize_punctuation", True)))
    return LoadedSignSpark(model, text_vocab, decoding, text, language, str(dataset), ckpt)


# ------------------------------------------------------------------------------------------------- decoding
@torch.no_grad()
def _greedy(model: SignSparkBT, memory: torch.Tensor, mask: torch.Tensor, bos: int, eos: int,
            max_len: int) -> list[list[int]]:
    """memory (B, T, D), mask (B, T) -> per clip the ids after BOS (their transformer_greedy)."""
    ys = torch.full((memory.shape[0], 1), bos, dtype=torch.long, device=memory.device)  # (B, 1)
    finished = torch.zeros(memory.shape[0], dtype=torch.bool, device=memory.device)
    for _ in range(max_len):
        _, word = torch.max(model.decode(memory, mask, ys)[:, -1], dim=1)  # (B,)
        ys = torch.cat([ys, word[:, None]], dim=1)
        finished |= word == eos
        if bool(finished.all()):
            break
    return ys[:, 1:].tolist()


@torch.no_grad()
def _beam(model: SignSparkBT, memory: torch.Tensor, mask: torch.Tensor, bos: int, eos: int, max_len: int,
          size: int, alpha: float) -> list[int]:
    """Their beam search for one clip (memory (1, T, D), mask (1, T)): the ``size`` best extensions of all beams
    stay alive, an ended beam included (it is collected as a hypothesis unless it already ended before); when the
    best beam ends, or at ``max_len``, every beam is collected and the best collected hypothesis (by its
    length-penalised score, first collected on ties) is the output."""
    vocab = model.cfg.text_vocab_size
    memory, mask = memory.expand(size, -1, -1), mask.expand(size, -1)
    alive = torch.full((size, 1), bos, dtype=torch.long, device=memory.device)  # (K, 1 + step)
    beam_log_probs = torch.full((size,), float("-inf"), device=memory.device)
    beam_log_probs[0] = 0.0  # only the first beam is live at the start
    hypotheses: list[tuple[float, list[int]]] = []
    for step in range(max_len):
        log_probs = model.decode(memory, mask, alive)[:, -1].log_softmax(-1) + beam_log_probs[:, None]  # (K, V)
        penalty = ((5.0 + (step + 1)) / 6.0) ** alpha if alpha > -1 else 1.0
        scores, ids = (log_probs / penalty).reshape(1, -1).topk(size, dim=-1)  # flattened (beam, word)
        scores, ids = scores[0], ids[0]
        beam_log_probs = scores * penalty if alpha > -1 else scores.clone()
        origin, word = ids.div(vocab, rounding_mode="floor"), ids.fmod(vocab)
        alive = torch.cat([alive[origin], word[:, None]], dim=1)
        ended = word == eos
        if step + 1 == max_len or bool(ended[0]):
            ended[:] = True
        for j in ended.nonzero().flatten().tolist():
            if int((alive[j, 1:] == eos).sum()) < 2:
                hypotheses.append((float(scores[j]), alive[j, 1:].tolist()))
        if bool(ended[0]):
            return max(hypotheses, key=lambda h: h[0])[1]  # the first collected on ties, as their stable sort
    raise AssertionError("unreachable: every beam ends at max_len")


def _sentence(ids: Sequence[int], vocab: Sequence[str]) -> str:
    tokens = []
    for i in ids:
        if vocab[i] == "</s>":
            break
        tokens.append(vocab[i])
    return " ".join(tokens)


def translate(judge: LoadedSignSpark, poses: Sequence[np.ndarray], batch_size: int = INFERENCE_BATCH) -> list[str]:
    """Sentences of (T_i, 240) inputs (:func:`m3t.backtranslation.smplx240.to_smplx240`), in order, decoded as
    their ``back_translate`` decodes (module doc); T_i = 0 gives ``""``."""
    model, vocab, dec = judge.model, judge.text_vocab, judge.decoding
    model.eval()
    device = next(model.parameters()).device
    for n, pose in enumerate(poses):
        if np.ndim(pose) != 2 or np.shape(pose)[1] != model.cfg.feature_size:
            raise ValueError(f"pose {n}: shape {np.shape(pose)}, expected (T, {model.cfg.feature_size}) SMPL-X "
                             "features (body 60 + left hand 90 + right hand 90)")
    bos, eos = vocab.index("<s>"), vocab.index("</s>")
    out = [""] * len(poses)
    todo = [i for i, pose in enumerate(poses) if len(pose)]
    for start in range(0, len(todo), batch_size):
        rows = todo[start: start + batch_size]
        lengths = torch.tensor([len(poses[i]) for i in rows])
        frames = torch.zeros(len(rows), int(lengths.max()), model.cfg.feature_size)  # (B, T, F), zero padded
        for b, i in enumerate(rows):
            frames[b, : lengths[b]] = torch.as_tensor(np.asarray(poses[i], dtype=np.float32))
        mask = (torch.arange(frames.shape[1])[None] < lengths[:, None]).to(device)  # (B, T)
        with torch.no_grad():
            memory = model.encode(frames.to(device), mask)
        if dec.beam_size < 2:
            ids = _greedy(model, memory, mask, bos, eos, dec.max_output_length)
        else:
            ids = [_beam(model, memory[b: b + 1], mask[b: b + 1], bos, eos, dec.max_output_length, dec.beam_size,
                         dec.alpha) for b in range(len(rows))]
        for i, seq in zip(rows, ids):
            out[i] = _sentence(seq, vocab)
    return out
