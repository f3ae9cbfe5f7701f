"""The SMLM with a pretrained mBART text vocabulary reduced to the training text (``smlm.reduce_text_vocab``):
the id mapping, the pretrained rows gathered through it, checkpoints that rebuild from the file, the clear
error without a local mbart folder, and the paper preset's 396M parameters (M3T App. 0.D.2)."""
from __future__ import annotations

import dataclasses
import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from m3t.config import load_params
from m3t.corpora.clip import Clip
from m3t.shards.tokens import TokenClip, TokenInfo, TokenShard
from m3t.smlm.checkpoint import load_smlm, save_smlm
from m3t.smlm.config import SMLMConfig
from m3t.smlm.data import Example, production_batch, translation_batch
from m3t.smlm.model import HEADS, SignMotionLM, SMLMDims, load_backbone
from m3t.smlm.pipeline import vocabulary_for
from m3t.smlm.vocab import MOTION_STREAMS, PROMPT_MODALITIES, SignVocabulary, VocabularyError, build_vocabulary

ROOT = Path(__file__).resolve().parents[2]
CODEBOOKS = {"body": 100, "right_hand": 180, "left_hand": 180, "face": 216}
TRAIN = {  # a few sentences per language, the training text the vocabulary is cut to
    "ASL": ["and i call them decorative elements", "the friend buys a red car today"],
    "DGS": ["morgen regnet es im norden", "am tag scheint die sonne"],
}
UNSEEN = ["zwölf grad in bayern", "我的朋友买车"]  # pieces of the tokenizer the training text never uses
D = 32


@pytest.fixture(scope="module")
def mbart_dir(tmp_path_factory) -> Path:
    """A tiny stand-in for the facebook/mbart-large-cc25 folder, with its file layout and id scheme: a
    SentencePiece BPE ``sentencepiece.bpe.model`` read by ``transformers``' ``MBartTokenizer`` (``<s>`` 0,
    ``<pad>`` 1, ``</s>`` 2, ``<unk>`` 3, then the SentencePiece pieces shifted by one, then the 25 language
    codes ``ar_AR`` .. ``zh_CN`` and ``<mask>``: 250,027 ids in the real folder, 100-odd here) and an
    ``MBartForConditionalGeneration`` saved by ``save_pretrained`` (``config.json`` + ``model.safetensors``;
    the real config: d_model 1024, 12 + 12 layers, scale_embedding true, pad 1, bos 0, eos 2; here d_model 32)."""
    import sentencepiece as spm
    from transformers import AutoTokenizer, MBartConfig, MBartForConditionalGeneration

    folder = tmp_path_factory.mktemp("mbart-large-cc25")
    texts = [t for ts in TRAIN.values() for t in ts] + UNSEEN + ["wetter vorhersage für morgen", "cars and books"]
    buffer = io.BytesIO()
    spm.SentencePieceTrainer.train(sentence_iterator=iter(texts * 4), model_writer=buffer, vocab_size=90,
                                   model_type="bpe", hard_vocab_limit=False, minloglevel=2, num_threads=1)
    (folder / "sentencepiece.bpe.model").write_bytes(buffer.getvalue())
    (folder / "tokenizer_config.json").write_text(json.dumps({"tokenizer_class": "MBartTokenizer"}))
    size = len(AutoTokenizer.from_pretrained(str(folder), local_files_only=True))
    torch.manual_seed(0)
    config = MBartConfig(vocab_size=size, d_model=D, encoder_layers=1, decoder_layers=1, encoder_attention_heads=2,
                         decoder_attention_heads=2, encoder_ffn_dim=64, decoder_ffn_dim=64, max_position_embeddings=128,
                         scale_embedding=True)
    MBartForConditionalGeneration(config).save_pretrained(str(folder))
    return folder


def tiny_cfg(folder: Path, reduce: bool = True) -> SMLMConfig:
    return SMLMConfig(d_model=D, encoder_layers=1, decoder_layers=1, attention_heads=2, ffn_dim=64, dropout=0.0,
                      max_text_tokens=24, max_motion_tokens=16, text_model_path=str(folder),
                      pretrained_path=str(folder), reduce_text_vocab=reduce)


def train_shard() -> TokenShard:
    rng = np.random.default_rng(0)
    clips = tuple(TokenClip(Clip(f"{lang}{i}", "toy", "train", lang, "s", text, "", "x", 25.0), 20,
                            {s: rng.integers(0, CODEBOOKS[s], 5) for s in MOTION_STREAMS})
                  for lang, texts in TRAIN.items() for i, text in enumerate(texts))
    return TokenShard(Path("train.parquet"), TokenInfo(CODEBOOKS, 4, {}), clips)


@pytest.fixture(scope="module")
def reduced(mbart_dir) -> SignVocabulary:
    return vocabulary_for(tiny_cfg(mbart_dir), [train_shard()])


def test_reduced_vocabulary_keeps_the_training_ids_and_maps_both_ways(mbart_dir, reduced):
    full = build_vocabulary([], TRAIN, CODEBOOKS, 1000, str(mbart_dir))
    used = sorted({i for ts in TRAIN.values() for t in ts for i in full.encode_text(t, None)} | {0, 1, 2, 3})
    assert reduced.pretrained_text_ids == tuple(used) and reduced.text_size == len(used) < full.text_size
    assert (reduced.pad_id, reduced.eos_id, reduced.text.bos_id, reduced.text.unk_id) == (1, 2, 0, 3)  # mBART's
    assert len(reduced) == reduced.text_size + 2 * len(PROMPT_MODALITIES) + sum(CODEBOOKS.values())
    for text in [t for ts in TRAIN.values() for t in ts]:
        ids = reduced.encode_text(text, None)
        assert max(ids) < reduced.text_size and 3 not in ids
        assert [used[i] for i in ids] == full.encode_text(text, None)  # reduced id -> pretrained id
        assert reduced.decode_text(ids) == full.decode_text(full.encode_text(text, None)) == text
    for text in UNSEEN:  # pieces outside the training text are <unk>, never another piece
        outside = [i for i in full.encode_text(text, None) if i not in used]
        assert outside and reduced.encode_text(text, None).count(3) >= len(outside)
    restored = SignVocabulary.from_dict(reduced.to_dict())
    assert restored.pretrained_text_ids == reduced.pretrained_text_ids and len(restored) == len(reduced)
    assert restored.encode_text(TRAIN["DGS"][0], None) == reduced.encode_text(TRAIN["DGS"][0], None)
    assert "text_ids" not in full.to_dict()  # an unreduced vocabulary keeps its old run key


def test_reduction_needs_a_pretrained_tokenizer():
    with pytest.raises(VocabularyError, match="reduce_text_vocab.*smlm.text_model_path"):
        build_vocabulary(["a b c"], ["ASL"], CODEBOOKS, 100, "", reduce_text_vocab=True)


def test_pretrained_rows_are_gathered_through_the_mapping_and_the_checkpoint_rebuilds(mbart_dir, reduced, tmp_path):
    from transformers import MBartModel

    pretrained = MBartModel.from_pretrained(str(mbart_dir)).get_input_embeddings().weight.detach()
    model = SignMotionLM(tiny_cfg(mbart_dir), SMLMDims.from_vocabulary(reduced)).eval()
    emb = model.backbone.get_input_embeddings()
    assert emb.num_embeddings == len(reduced) and model.heads["text"].out_features == reduced.text_size
    rows = pretrained[list(reduced.pretrained_text_ids)]
    assert torch.equal(emb.weight[: reduced.text_size], rows)
    assert torch.equal(model.heads["text"].weight, rows)  # the text head starts as mBART's output rows
    assert model.backbone.encoder.embed_tokens is emb and model.backbone.decoder.embed_tokens is emb
    assert emb.embed_scale == pytest.approx(D ** 0.5)  # MBart's scaled embedding kept
    examples = [Example(c.clip.id, c.clip.language, c.clip.text, np.asarray(reduced.encode_text(c.clip.text, 24)),
                        np.stack([c.tokens[s] for s in MOTION_STREAMS], axis=1)) for c in train_shard().clips]
    p = production_batch(examples, reduced)
    t = translation_batch(examples, reduced)
    with torch.no_grad():
        logits = model.production(p.text_ids, p.text_mask, p.motion_in, p.motion_mask)
        text_logits = model.translation(t.motion_ids, t.motion_mask, t.text_in, t.text_mask)
    assert logits["face"].shape[-1] == CODEBOOKS["face"] + 1 and text_logits.shape[-1] == reduced.text_size

    save_smlm(tmp_path / "smlm.pt", model, reduced, 1, 1, "v", {})
    loaded = load_smlm(tmp_path / "smlm.pt")
    assert loaded.vocab.pretrained_text_ids == reduced.pretrained_text_ids
    assert loaded.model.dims == model.dims and set(loaded.model.dims.head_sizes) == set(HEADS)
    for (name, a), b in zip(model.state_dict().items(), loaded.model.state_dict().values()):
        assert torch.equal(a, b), name
    assert loaded.vocab.decode_text(loaded.vocab.encode_text(TRAIN["ASL"][1], None)) == TRAIN["ASL"][1]


def test_unreduced_pretrained_vocabulary_keeps_every_row(mbart_dir):
    vocab = build_vocabulary([], ["ASL"], CODEBOOKS, 1000, str(mbart_dir))
    model = SignMotionLM(tiny_cfg(mbart_dir, reduce=False), SMLMDims.from_vocabulary(vocab))
    pretrained = load_backbone(tiny_cfg(mbart_dir, reduce=False), SMLMDims(vocab.text_size, {}, 1, 2))
    assert model.dims.pretrained_text_ids == ()
    assert torch.equal(model.backbone.get_input_embeddings().weight[: vocab.text_size],
                       pretrained.get_input_embeddings().weight)


def test_paper_preset_without_a_local_mbart_folder_says_what_to_download(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = load_params(ROOT / "params.yaml", preset="paper").smlm
    assert cfg.text_model_path == cfg.pretrained_path == "models/mbart-large-cc25" and cfg.reduce_text_vocab
    with pytest.raises(VocabularyError, match=r"models/mbart-large-cc25.*config\.json, sentencepiece\.bpe\.model"):
        build_vocabulary(["a b"], ["ASL"], CODEBOOKS, 100, cfg.text_model_path, cfg.reduce_text_vocab)
    (tmp_path / "models" / "mbart-large-cc25").mkdir(parents=True)
    (tmp_path / "models" / "mbart-large-cc25" / "config.json").write_text("{}")  # weights not copied
    with pytest.raises(FileNotFoundError, match=r"models/mbart-large-cc25 \(model\.safetensors / pytorch_model\.bin "
                                                r"missing\).*sentencepiece\.bpe\.model"):
        load_backbone(cfg, SMLMDims(100, {}, 1, 2))


# Text ids M3T's three corpora keep of mbart-large-cc25's 250,027 (an estimate: the corpora are not here).
# Phoenix14T's train text uses 2,454 ids (the config.json of GFSLT-VLP's mBART trimmed to it); How2Sign's
# English (a ~16k-word vocabulary) and CSL-Daily's Chinese (~2.3k characters, often merged into multi-character
# pieces) add an estimated ~12k and ~5-6k.
PAPER_TEXT_IDS = 20_000
LANGUAGES = ("ASL", "CSL", "DGS")


def paper_dims(text_ids: int) -> SMLMDims:
    tok = load_params(ROOT / "params.yaml", preset="paper").tokenizer
    codes = {"body": int(np.prod(tok.levels_body)), "left_hand": int(np.prod(tok.levels_hand)),
             "right_hand": int(np.prod(tok.levels_hand)), "face": int(np.prod(tok.levels_face))}
    vocab = text_ids + len(LANGUAGES) * len(PROMPT_MODALITIES) + sum(codes.values())
    return SMLMDims(vocab, {"text": text_ids, **{s: n + 1 for s, n in codes.items()}}, 1, 2)


def count_on_meta(text_ids: int) -> tuple[int, int]:
    """(all parameters, text head parameters) of the paper preset's SMLM, built without memory; the
    architecture from the config (position table 260 rows instead of mBART's 1,026: 1.6M fewer)."""
    cfg = dataclasses.replace(load_params(ROOT / "params.yaml", preset="paper").smlm, pretrained_path="")
    with torch.device("meta"):
        model = SignMotionLM(cfg, paper_dims(text_ids))
    return sum(p.numel() for p in model.parameters()), model.heads["text"].weight.numel()


def test_paper_preset_smlm_has_396m_parameters():
    total, text_head = count_on_meta(PAPER_TEXT_IDS)
    # measured: 395.6M with the untied text head (+1.6M for mBART's 1,026-row position tables); tied: 375.1M
    assert abs(total - 396e6) / 396e6 < 0.05, total
    assert abs(total - text_head - 396e6) / 396e6 > 0.05, "with a tied head 396M would need ~40k text ids"
    full, _ = count_on_meta(250_027)  # the whole mbart-large-cc25 vocabulary: what the preset built before
    assert full > 850e6


def test_keeping_embedding_rows_gathers_them_and_leaves_the_pad_row_untrained():
    """:func:`m3t.smlm.model.keep_embedding_rows` on an in-memory mBART (``MBartModel``: its scaled word
    embedding shared by encoder and decoder, pad id 1 as in mbart-large-cc25)."""
    from transformers import MBartConfig, MBartModel

    from m3t.smlm.model import keep_embedding_rows

    torch.manual_seed(0)
    config = MBartConfig(vocab_size=20, d_model=8, encoder_layers=1, decoder_layers=1, encoder_attention_heads=2,
                         decoder_attention_heads=2, encoder_ffn_dim=16, decoder_ffn_dim=16, max_position_embeddings=32,
                         scale_embedding=True, pad_token_id=1)
    backbone = MBartModel(config)
    old = backbone.get_input_embeddings()
    before = old.weight.detach().clone()
    rows = (0, 1, 2, 3, 7, 11)
    with pytest.raises(ValueError, match=r"pretrained id 20 but the checkpoint in models/mbart has 20 embedding rows: "
                                         r"smlm\.text_model_path and smlm\.pretrained_path must be the same mBART"):
        keep_embedding_rows(backbone, rows + (20,), 1, "models/mbart")
    assert backbone.get_input_embeddings() is old, "a refused reduction leaves the model as it was"

    keep_embedding_rows(backbone, rows, 1, "models/mbart")
    emb = backbone.get_input_embeddings()
    assert type(emb) is type(old) and emb.num_embeddings == len(rows) and emb.embedding_dim == 8
    assert emb.embed_scale == old.embed_scale == pytest.approx(8 ** 0.5)
    assert torch.equal(emb.weight, before[list(rows)])
    assert backbone.encoder.embed_tokens is emb and backbone.decoder.embed_tokens is emb
    assert backbone.config.vocab_size == len(rows) and backbone.config.pad_token_id == 1
    assert emb.padding_idx == 1
    ids = torch.tensor([[0, 4, 5, 2, 1, 1]])  # two pads at the end
    out = backbone(input_ids=ids, attention_mask=(ids != 1).long(), decoder_input_ids=ids[:, :4])
    out.last_hidden_state.sum().backward()
    grad = emb.weight.grad
    assert torch.count_nonzero(grad[1]) == 0, "the pad row gets no gradient: it stays the pretrained pad"
    assert all(torch.count_nonzero(grad[i]) > 0 for i in (0, 2, 4, 5))


def test_training_the_text_tokenizer_keeps_sentencepieces_log_off_stderr(capfd):
    import sentencepiece as spm

    from m3t.smlm.vocab import SentencePieceText, VocabularyError

    spm.set_min_log_level(0)  # the library's default: an earlier training in this process may have raised it
    capfd.readouterr()
    text = SentencePieceText.train(["the friend buys a red car", "  ", "", "my father drinks water"], 40)
    captured = capfd.readouterr()
    assert captured.err == "" and captured.out == "", "the stage log stays readable: no trainer chatter"
    assert (text.pad_id, text.bos_id, text.eos_id, text.unk_id) == (0, 1, 2, 3)
    assert 4 < text.size <= 40  # vocab_size is an upper bound on a small corpus
    ids = text.encode("my father drinks water")
    assert text.decode([text.bos_id, *ids, text.eos_id, text.pad_id]) == "my father drinks water"
    with pytest.raises(VocabularyError, match="the corpus has no non-empty text"):
        SentencePieceText.train(["", "   "], 40)


@pytest.fixture(scope="module")
def mbart_tokenizer_dir(tmp_path_factory):
    """The tokenizer files of a facebook/mbart-large-cc25 folder, tiny: a SentencePiece BPE
    ``sentencepiece.bpe.model`` and a ``tokenizer_config.json`` naming ``MBartTokenizer`` (``transformers`` then
    gives mBART's ids: ``<s>`` 0, ``<pad>`` 1, ``</s>`` 2, ``<unk>`` 3, the pieces shifted by one, then the 25
    language codes ``ar_AR`` .. ``zh_CN`` and ``<mask>``), as the stand-in of test_smlm_reduced_vocab.py, without
    the model weights."""
    import io

    import sentencepiece as spm

    folder = tmp_path_factory.mktemp("mbart-tokenizer")
    texts = ["the friend buys a red car today", "morgen regnet es im norden", "zwölf grad in bayern",
             "cars and books", "am tag scheint die sonne"]
    buffer = io.BytesIO()
    spm.SentencePieceTrainer.train(sentence_iterator=iter(texts * 4), model_writer=buffer, vocab_size=60,
                                   model_type="bpe", hard_vocab_limit=False, minloglevel=2, num_threads=1)
    (folder / "sentencepiece.bpe.model").write_bytes(buffer.getvalue())
    (folder / "tokenizer_config.json").write_text(json.dumps({"tokenizer_class": "MBartTokenizer"}))
    return folder


def test_pretrained_mbart_text_decodes_without_its_special_tokens(mbart_tokenizer_dir):
    from m3t.smlm.vocab import PretrainedMBartText

    text = PretrainedMBartText(mbart_tokenizer_dir)
    assert (text.bos_id, text.pad_id, text.eos_id, text.unk_id) == (0, 1, 2, 3)
    assert text.path == str(mbart_tokenizer_dir) and text.model_proto == b""
    ids = text.encode("the friend buys a red car")
    assert ids and min(ids) > 3, "encoded without <s> / </s>"
    assert text.piece(text.eos_id) == "</s>" and text.piece(text.pad_id) == "<pad>"
    generated = [text.bos_id, *ids, text.eos_id, text.pad_id, text.pad_id]  # as a padded generation comes back
    assert text.decode(generated) == "the friend buys a red car"
    assert text.decode(np.array(generated, dtype=np.int64)) == "the friend buys a red car"


def test_reduced_text_refuses_ids_outside_the_tokenizer_and_names_it(mbart_tokenizer_dir):
    from m3t.smlm.vocab import PretrainedMBartText, ReducedText, VocabularyError

    base = PretrainedMBartText(mbart_tokenizer_dir)
    last = base.size - 1

    def message(kept):
        with pytest.raises(VocabularyError) as info:
            ReducedText(base, kept)
        return str(info.value)

    for kept, shown in (([-1, 0, 1, 2, 3], "5 ids from (-1,) to (3,)"),  # a negative id
                        ([0, 1, 2, 3, base.size], f"5 ids from (0,) to ({base.size},)"),  # one past the end
                        ([0, 2, 1, 3], "4 ids from (0,) to (3,)"),  # not ascending
                        ([0, 1, 2, 2, 3], "5 ids from (0,) to (3,)"),  # a repeat
                        ([], "0 ids from () to ()")):
        assert message(kept) == (
            f"the reduced text vocabulary must list ascending, distinct ids of the tokenizer in {mbart_tokenizer_dir} "
            f"(0 .. {last}); got {shown}: the checkpoint was made with another mBART tokenizer"), kept
    assert message([0, 2, 3, 9]) == "the reduced text vocabulary lacks the special token(s) ['pad']"
    assert message([1, 3, 9]) == "the reduced text vocabulary lacks the special token(s) ['bos', 'eos']"

    reduced = ReducedText.from_texts(base, ["the friend buys a red car", "", "  "])
    assert reduced.kept[:4] == (0, 1, 2, 3) and reduced.kept[-1] <= last
    assert (reduced.bos_id, reduced.pad_id, reduced.eos_id, reduced.unk_id) == (0, 1, 2, 3)
    ids = reduced.encode("the friend buys a red car")
    assert max(ids) < reduced.size and reduced.decode(ids) == "the friend buys a red car"
    with pytest.raises(VocabularyError, match="the training corpus has no non-empty text"):
        ReducedText.from_texts(base, ["", " "])


def test_reduced_text_decodes_every_id_in_range_through_the_mapping_and_drops_the_others():
    """Reduced id ``i`` is pretrained id ``kept[i]``, the first one included; ids outside the reduced
    vocabulary (a generation's stray values) are dropped. The base here is a tokenizer whose first ids are
    ordinary pieces (its specials at 4 .. 7), so that a lost id 0 shows."""
    from m3t.smlm.vocab import ReducedText

    class Pieces:
        path, size, model_proto = "pieces", 10, b""
        pad_id, bos_id, eos_id, unk_id = 4, 5, 6, 7

        def decode(self, ids):
            return " ".join(f"p{i}" for i in ids)

        def piece(self, i):
            return f"p{i}"

    reduced = ReducedText(Pieces(), [0, 2, 4, 5, 6, 7, 9])
    assert reduced.size == 7 and (reduced.pad_id, reduced.bos_id, reduced.eos_id, reduced.unk_id) == (2, 3, 4, 5)
    assert reduced.decode([0, 1, 6]) == "p0 p2 p9"
    assert reduced.decode([0, 7, -1, 1, 99, 6]) == "p0 p2 p9"
    assert reduced.decode(np.array([6, 0])) == "p9 p0"
    assert [reduced.piece(i) for i in (0, 1, 6)] == ["p0", "p2", "p9"]


def test_a_reduced_vocabulary_over_a_tokenizer_without_a_path_still_explains_the_refusal():
    from m3t.smlm.vocab import ReducedText, VocabularyError

    class Loaded:  # a tokenizer object that does not know where it was loaded from
        size, model_proto = 10, b""
        pad_id, bos_id, eos_id, unk_id = 0, 1, 2, 3

    with pytest.raises(VocabularyError) as info:
        ReducedText(Loaded(), [0, 1, 2, 3, 12])
    assert str(info.value) == ("the reduced text vocabulary must list ascending, distinct ids of the tokenizer in ? "
                               "(0 .. 9); got 5 ids from (0,) to (12,): the checkpoint was made with another mBART "
                               "tokenizer")


def test_a_sentencepiece_model_without_a_pad_id_is_refused():
    import io

    import sentencepiece as spm

    from m3t.smlm.vocab import SentencePieceText, VocabularyError

    buffer = io.BytesIO()
    spm.SentencePieceTrainer.train(sentence_iterator=iter(["the friend buys a red car", "my father drinks water"]),
                                   model_writer=buffer, vocab_size=30, model_type="unigram", hard_vocab_limit=False,
                                   minloglevel=2, num_threads=1)  # SentencePiece's default: no pad id (-1)
    with pytest.raises(VocabularyError, match="model must define pad, bos, eos and unk ids"):
        SentencePieceText(buffer.getvalue())
