"""The SMLM lexicon (M3T Eq. 7): spoken-language text tokens, language-modality prompts and one token per
FSQ index per motion stream, in one id space shared by the embedding table.

Layout of the global ids::

    [0, T)                 text tokens of the spoken-language tokenizer (its pad / bos / eos / unk included)
    [T, T + P)             prompts <LANG_MOD>: one per sign language x modality (TXT, B, LH, RH, F)
    then per stream        <b_i> (body), <lh_i> (left hand), <rh_i> (right hand), <f_i> (face)

The text tokenizer is either a local pretrained mBART SentencePiece model (``text_model_path``: a folder
with ``sentencepiece.bpe.model`` loaded through ``transformers``, ids kept as the checkpoint expects) or a
SentencePiece unigram model trained on the corpus text, stored inside the vocabulary itself so a
checkpoint rebuilds it from the file alone.

``reduce_text_vocab`` keeps only the pretrained ids that the training text uses (plus pad / bos / eos /
unk): mbart-large-cc25's 250,027 text ids would otherwise hold ~512M of the model's parameters in two
1024-wide tables, where M3T App. 0.D.2 counts 396M in all. The kept ids (reduced id ``i`` = pretrained id
``kept[i]``, ascending, so the specials 0-3 keep their ids) are stored in the vocabulary: encoding maps
pretrained ids to reduced ones (a piece the training text never used becomes ``<unk>``), decoding maps back,
and the model gathers its pretrained embedding rows through the same list.

Each output head predicts only its own vocabulary (local ids): the text head the T text ids, a motion
head the C_m codes of its stream plus one end-of-sequence class (local id C_m).
"""
from __future__ import annotations

import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from m3t.body.protocol import STREAM_ORDER

# Head order (the paper's 5 heads: text, then the project's one stream order) and the short names of token strings.
MOTION_STREAMS = STREAM_ORDER
STREAM_TAGS = {"body": "b", "left_hand": "lh", "right_hand": "rh", "face": "f"}
PROMPT_MODALITIES = ("TXT", "B", "LH", "RH", "F")
STREAM_PROMPT = {"body": "B", "left_hand": "LH", "right_hand": "RH", "face": "F"}
_MOTION_RE = re.compile(r"^<(b|lh|rh|f)_(\d+)>$")
# what a local mbart-large-cc25 folder (smlm.text_model_path / smlm.pretrained_path) must hold
MBART_FILES = ("config.json, sentencepiece.bpe.model (the tokenizer; tokenizer.json too if present) and the "
               "weights (model.safetensors or pytorch_model.bin)")
MBART_HOWTO = ("download it on a machine with internet (huggingface-cli download facebook/mbart-large-cc25 "
               "--local-dir models/mbart-large-cc25) and copy the folder here")


class VocabularyError(ValueError):
    """Bad input to the vocabulary: unknown language, empty text, token outside a codebook."""


class SentencePieceText:
    """Text tokenizer backed by a SentencePiece model (trained here, or pretrained when loaded by path)."""

    def __init__(self, model_proto: bytes):
        import sentencepiece as spm

        self.model_proto = bytes(model_proto)
        self._sp = spm.SentencePieceProcessor(model_proto=self.model_proto)
        self.pad_id, self.bos_id, self.eos_id, self.unk_id = (self._sp.pad_id(), self._sp.bos_id(),
                                                              self._sp.eos_id(), self._sp.unk_id())
        if min(self.pad_id, self.bos_id, self.eos_id, self.unk_id) < 0:
            raise VocabularyError("the SentencePiece model must define pad, bos, eos and unk ids")

    @classmethod
    def train(cls, texts: Iterable[str], vocab_size: int, character_coverage: float = 0.9995) -> SentencePieceText:
        """A unigram model on ``texts``; ``vocab_size`` is an upper bound (small corpora give fewer pieces)."""
        import sentencepiece as spm

        texts = [t.strip() for t in texts if t and t.strip()]
        if not texts:
            raise VocabularyError("cannot train a text tokenizer: the corpus has no non-empty text")
        buffer = io.BytesIO()
        spm.SentencePieceTrainer.train(
            sentence_iterator=iter(texts), model_writer=buffer, vocab_size=vocab_size, model_type="unigram",
            pad_id=0, bos_id=1, eos_id=2, unk_id=3, hard_vocab_limit=False, character_coverage=character_coverage,
            minloglevel=2, num_threads=1)
        return cls(buffer.getvalue())

    @property
    def size(self) -> int:
        return self._sp.get_piece_size()

    def encode(self, text: str) -> list[int]:
        return list(self._sp.encode(text))

    def decode(self, ids: Sequence[int]) -> str:
        return self._sp.decode([int(i) for i in ids if int(i) not in (self.pad_id, self.bos_id, self.eos_id)])

    def piece(self, i: int) -> str:
        return self._sp.id_to_piece(int(i))


class PretrainedMBartText:
    """The tokenizer of a local mBART checkpoint (e.g. mbart-large-cc25), ids as its embedding expects."""

    def __init__(self, path: str | Path):
        path = Path(path)
        if not path.is_dir() or not any(path.glob("sentencepiece*.model")) and not (path / "tokenizer.json").exists():
            raise VocabularyError(
                f"no mBART tokenizer in {path} (sentencepiece.bpe.model or tokenizer.json missing): expected the "
                f"folder of facebook/mbart-large-cc25 (the paper preset's models/mbart-large-cc25) with {MBART_FILES}; "
                f"{MBART_HOWTO}, "
                "or set smlm.text_model_path to '' to train a tokenizer on the corpus text")
        from transformers import AutoTokenizer

        self.path = str(path)
        self._tok = AutoTokenizer.from_pretrained(self.path, local_files_only=True)
        self.pad_id, self.bos_id = self._tok.pad_token_id, self._tok.bos_token_id
        self.eos_id, self.unk_id = self._tok.eos_token_id, self._tok.unk_token_id
        self.model_proto = b""

    @property
    def size(self) -> int:
        return len(self._tok)

    def encode(self, text: str) -> list[int]:
        return list(self._tok(text, add_special_tokens=False)["input_ids"])

    def decode(self, ids: Sequence[int]) -> str:
        return self._tok.decode([int(i) for i in ids], skip_special_tokens=True)

    def piece(self, i: int) -> str:
        return self._tok.convert_ids_to_tokens(int(i))


class ReducedText:
    """A pretrained tokenizer restricted to ``kept`` (ascending pretrained ids, the four specials included):
    reduced id ``i`` is pretrained id ``kept[i]``."""

    def __init__(self, base: PretrainedMBartText, kept: Sequence[int]):
        self.base, self.kept = base, tuple(int(i) for i in kept)
        if list(self.kept) != sorted(set(self.kept)) or not self.kept or self.kept[0] < 0 or self.kept[-1] >= base.size:
            source = getattr(base, "path", "?")
            raise VocabularyError(
                f"the reduced text vocabulary must list ascending, distinct ids of the tokenizer in {source} "
                f"(0 .. {base.size - 1}); got {len(self.kept)} ids from {self.kept[:1]} to {self.kept[-1:]}: the "
                "checkpoint was made with another mBART tokenizer")
        self._reduced = {old: new for new, old in enumerate(self.kept)}
        specials = {"pad": base.pad_id, "bos": base.bos_id, "eos": base.eos_id, "unk": base.unk_id}
        lost = [name for name, i in specials.items() if i not in self._reduced]
        if lost:
            raise VocabularyError(f"the reduced text vocabulary lacks the special token(s) {lost}")
        self.pad_id, self.bos_id, self.eos_id, self.unk_id = (self._reduced[i] for i in specials.values())
        self.model_proto = base.model_proto

    @classmethod
    def from_texts(cls, base: PretrainedMBartText, texts: Iterable[str]) -> ReducedText:
        """The specials and every id that ``texts`` encode to."""
        used = {base.pad_id, base.bos_id, base.eos_id, base.unk_id}
        count = 0
        for text in texts:
            if text and text.strip():
                used.update(base.encode(text))
                count += 1
        if not count:
            raise VocabularyError("cannot reduce the text vocabulary: the training corpus has no non-empty text")
        return cls(base, sorted(used))

    @property
    def size(self) -> int:
        return len(self.kept)

    def encode(self, text: str) -> list[int]:
        return [self._reduced.get(i, self.unk_id) for i in self.base.encode(text)]

    def decode(self, ids: Sequence[int]) -> str:
        return self.base.decode([self.kept[int(i)] for i in ids if 0 <= int(i) < self.size])

    def piece(self, i: int) -> str:
        return self.base.piece(self.kept[int(i)])


@dataclass(frozen=True)
class SignVocabulary:
    """Text tokenizer + prompts + motion tokens; ``codebooks`` maps stream -> FSQ codebook size."""

    text: SentencePieceText | PretrainedMBartText | ReducedText
    languages: tuple[str, ...]
    codebooks: dict[str, int]
    text_model_path: str = ""
    _offsets: dict[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        missing = [s for s in MOTION_STREAMS if s not in self.codebooks]
        if missing:
            raise VocabularyError(f"codebook sizes missing for streams {missing}; the token shards must carry all of "
                                  f"{list(MOTION_STREAMS)}")
        if not self.languages or len(set(self.languages)) != len(self.languages):
            raise VocabularyError(f"languages must be a non-empty list without repeats, got {self.languages}")
        offsets, start = {}, self.prompt_offset + len(self.languages) * len(PROMPT_MODALITIES)
        for stream in MOTION_STREAMS:
            offsets[stream] = start
            start += self.codebooks[stream]
        object.__setattr__(self, "_offsets", offsets)

    # ---- sizes and ids -------------------------------------------------------------------------
    @property
    def text_size(self) -> int:
        return self.text.size

    @property
    def prompt_offset(self) -> int:
        return self.text.size

    @property
    def pretrained_text_ids(self) -> tuple[int, ...]:
        """The pretrained embedding row of each text id when the vocabulary is reduced; () = the ids themselves."""
        return self.text.kept if isinstance(self.text, ReducedText) else ()

    def __len__(self) -> int:
        last = MOTION_STREAMS[-1]
        return self._offsets[last] + self.codebooks[last]

    @property
    def pad_id(self) -> int:
        return self.text.pad_id

    @property
    def eos_id(self) -> int:
        return self.text.eos_id

    def head_size(self, stream: str) -> int:
        """Classes of a head: the text ids, or a stream's codes + EOS."""
        return self.text_size if stream == "text" else self.codebooks[stream] + 1

    def check_language(self, language: str) -> None:
        if language not in self.languages:
            raise VocabularyError(f"unknown language {language!r}; this vocabulary knows {list(self.languages)} "
                                  "(languages come from the training corpus)")

    def prompt_id(self, language: str, modality: str) -> int:
        self.check_language(language)
        if modality not in PROMPT_MODALITIES:
            raise VocabularyError(f"unknown prompt modality {modality!r}; allowed {PROMPT_MODALITIES}")
        return (self.prompt_offset + self.languages.index(language) * len(PROMPT_MODALITIES)
                + PROMPT_MODALITIES.index(modality))

    def motion_ids(self, stream: str, local: np.ndarray) -> np.ndarray:
        """Head-local motion ids (codes, C_m = EOS) -> global ids (EOS -> the shared ``</s>``)."""
        local = np.asarray(local, dtype=np.int64)
        size = self.codebooks[stream]
        if local.size and (local.min() < 0 or local.max() > size):
            raise VocabularyError(f"{stream} token outside [0, {size}] (codebook {size} + EOS)")
        return np.where(local == size, self.eos_id, local + self._offsets[stream])

    # ---- text ----------------------------------------------------------------------------------
    def encode_text(self, text: str, max_tokens: int | None, truncate: bool = False) -> list[int]:
        """Text -> ids (no specials); empty text -> VocabularyError; more than ``max_tokens`` ids (None: no
        limit) -> VocabularyError, or (``truncate``) the first ``max_tokens`` ids."""
        if not isinstance(text, str) or not text.strip():
            raise VocabularyError("empty text: give a sentence to translate into sign")
        ids = self.text.encode(text)
        if max_tokens is None:
            return ids
        if truncate:
            return ids[:max_tokens]
        if len(ids) > max_tokens:
            raise VocabularyError(f"text of {len(ids)} tokens is longer than the limit of {max_tokens} "
                                  f"(smlm.max_text_tokens): {text[:60]!r}...; split it into sentences")
        return ids

    def decode_text(self, ids: Sequence[int]) -> str:
        return self.text.decode([i for i in ids if 0 <= int(i) < self.text_size])

    # ---- token strings (for inspection and the round trip) -----------------------------------------
    def token(self, i: int) -> str:
        i = int(i)
        if 0 <= i < self.text_size:
            return self.text.piece(i)
        if i < self._offsets[MOTION_STREAMS[0]]:
            k = i - self.prompt_offset
            return f"<{self.languages[k // len(PROMPT_MODALITIES)]}_{PROMPT_MODALITIES[k % len(PROMPT_MODALITIES)]}>"
        for stream in reversed(MOTION_STREAMS):
            if i >= self._offsets[stream]:
                if i - self._offsets[stream] >= self.codebooks[stream]:
                    break
                return f"<{STREAM_TAGS[stream]}_{i - self._offsets[stream]}>"
        raise VocabularyError(f"id {i} outside the vocabulary of {len(self)} tokens")

    def token_id(self, token: str) -> int:
        match = _MOTION_RE.match(token)
        if match:
            stream = next(s for s, tag in STREAM_TAGS.items() if tag == match.group(1))
            return int(self.motion_ids(stream, np.array([int(match.group(2))]))[0])
        if token.startswith("<") and token.endswith(">") and "_" in token:
            language, modality = token[1:-1].rsplit("_", 1)
            if modality in PROMPT_MODALITIES:
                return self.prompt_id(language, modality)
        raise VocabularyError(f"{token!r} is not a prompt or motion token")

    # ---- persistence -----------------------------------------------------------------------------
    def to_dict(self) -> dict:
        # a pretrained tokenizer is read from its folder (no model bytes): None, since torch's weights_only
        # loading refuses an empty bytes object
        data = {"text_model": self.text.model_proto or None, "text_model_path": self.text_model_path,
                "languages": list(self.languages), "codebooks": dict(self.codebooks)}
        if isinstance(self.text, ReducedText):  # only then: an unreduced vocabulary keeps its old run key
            data["text_ids"] = list(self.text.kept)
        return data

    @classmethod
    def from_dict(cls, data: dict) -> SignVocabulary:
        path = data.get("text_model_path", "")
        text = PretrainedMBartText(path) if path else SentencePieceText(data["text_model"])
        if data.get("text_ids"):
            text = ReducedText(text, data["text_ids"])
        return cls(text, tuple(data["languages"]), {k: int(v) for k, v in data["codebooks"].items()}, path)


def build_vocabulary(texts: Iterable[str], languages: Iterable[str], codebooks: dict[str, int], text_vocab_size: int,
                     text_model_path: str = "", reduce_text_vocab: bool = False) -> SignVocabulary:
    """The pretrained mBART tokenizer when ``text_model_path`` is set (``reduce_text_vocab``: only the ids
    ``texts`` use), else one trained on ``texts``."""
    if reduce_text_vocab and not text_model_path:
        raise VocabularyError("smlm.reduce_text_vocab keeps the pretrained mBART ids that the corpus text uses; "
                              "set smlm.text_model_path to the local mbart-large-cc25 folder, or reduce_text_vocab "
                              "to false (a tokenizer trained on the corpus text is already corpus-sized)")
    if text_model_path:
        texts = list(texts)
        text = PretrainedMBartText(text_model_path)
        if reduce_text_vocab:
            text = ReducedText.from_texts(text, texts)
    else:
        text = SentencePieceText.train(texts, text_vocab_size)
    return SignVocabulary(text, tuple(sorted(set(languages))), dict(codebooks), text_model_path)
