"""Word vocabularies of the text-conditioned models (back-translation, SGSA / PT): token <-> id with special
tokens first, built on a train split and stored in checkpoints (``to_dict`` / ``from_dict``)."""
from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Sequence

PAD, UNK, BOS, EOS = "<pad>", "<unk>", "<bos>", "<eos>"
BLANK = "<blank>"  # CTC blank, id 0 of the gloss vocabulary


class Vocabulary:
    """Token <-> id; ``specials`` first (ids 0..), then the tokens in order of frequency, ties alphabetical."""

    def __init__(self, tokens: Sequence[str], specials: Sequence[str]):
        self.itos = list(specials) + [t for t in tokens if t not in specials]
        self.stoi = {t: i for i, t in enumerate(self.itos)}
        self.specials = tuple(specials)
        if len(self.stoi) != len(self.itos):
            raise ValueError("vocabulary has a duplicate token")

    @classmethod
    def build(cls, sentences: Iterable[Sequence[str]], specials: Sequence[str], min_frequency: int = 1) -> Vocabulary:
        counts = Counter(t for s in sentences for t in s)
        kept = sorted((t for t, c in counts.items() if c >= min_frequency), key=lambda t: (-counts[t], t))
        return cls(kept, specials)

    def __len__(self) -> int:
        return len(self.itos)

    def encode(self, tokens: Sequence[str]) -> list[int]:
        unk = self.stoi.get(UNK, 0)
        return [self.stoi.get(t, unk) for t in tokens]

    def decode(self, ids: Iterable[int]) -> list[str]:
        return [self.itos[i] for i in ids if self.itos[i] not in self.specials]

    def to_dict(self) -> dict:
        return {"specials": list(self.specials), "tokens": self.itos[len(self.specials):]}

    @classmethod
    def from_dict(cls, raw: dict) -> Vocabulary:
        return cls(list(raw["tokens"]), list(raw["specials"]))


def text_vocabulary(sentences: Iterable[Sequence[str]], min_frequency: int = 1) -> Vocabulary:
    """Words of the train split; ids 0-3 are ``<pad> <unk> <bos> <eos>``."""
    return Vocabulary.build(sentences, (PAD, UNK, BOS, EOS), min_frequency)


def gloss_vocabulary(glosses: Iterable[Sequence[str]]) -> Vocabulary:
    """Glosses of the train split; id 0 is the CTC blank, 1 ``<unk>``."""
    return Vocabulary.build(glosses, (BLANK, UNK))
