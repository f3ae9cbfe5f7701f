"""Text side of back-translation: sentence tokenisation per language (the word vocabularies are
:mod:`m3t.vocabulary`'s), and glosses for the CTC head (annotated, or pseudo-glosses for gloss-less corpora such as How2Sign).

Tokenisation (:class:`TextProcessor`, rule ``TEXT_RULE``) - the model is trained on, and references are scored as:

- every language: lower-cased (SL-T's ``txt_lowercase``);
- Chinese (:func:`m3t.metrics.text.is_chinese`, e.g. ``CSL``, ``CSL-SYN``): jieba words of the space-free text
  (M3T App. 0.D.4; SignSparK_BT ``tokenizer: jieba``); a sentence is written back without spaces;
- other languages: words (letters / digits, with inner ``' - .``: ``don't``, ``3.5``) and every other
  non-space character as its own token, so a sentence-final ``.`` or ``?`` is a word of its own, as in
  Phoenix14T's annotation; a sentence is written back with single spaces.

Pseudo-glosses (:class:`PseudoGlosser`), for clips whose corpus has no gloss: Sign2GPT's (Wong et al. 2024)
part-of-speech filter - the lower-cased lemmas of words tagged NOUN, NUM, ADV, PRON, PROPN, ADJ or VERB (the list
SignSparK_BT's ``tools/make_pseudo_glosses.py`` uses) - when spaCy and a pipeline for the spoken language are
installed. Without a tagger (this project's default install) the fallback is stated in ``method``: the
lower-cased words minus punctuation and minus the closed-class words the POS filter drops (determiners,
adpositions, conjunctions, auxiliaries, particles), listed below for English and German; no lemmatisation.
Other spoken languages keep every word.
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

from m3t.metrics.text import is_chinese, tokenize

TEXT_RULE = "m3t-bt-text-v1"
SIGN2GPT_POS = ("NOUN", "NUM", "ADV", "PRON", "PROPN", "ADJ", "VERB")
_WORD = re.compile(r"\w+(?:['\u2019\-.]\w+)*|[^\w\s]")

# sign language (or spoken language) code, or its prefix before "-" -> the spoken language of its text
SPOKEN_LANGUAGE = {"asl": "en", "bsl": "en", "auslan": "en", "en": "en", "eng": "en", "english": "en",
                   "dgs": "de", "de": "de", "deu": "de", "german": "de", "csl": "zh", "zh": "zh", "zho": "zh"}
SPACY_PIPELINES = {"en": ("en_core_web_lg", "en_core_web_md", "en_core_web_sm"),
                   "de": ("de_core_news_lg", "de_core_news_md", "de_core_news_sm"),
                   "zh": ("zh_core_web_lg", "zh_core_web_md", "zh_core_web_sm")}
# closed classes the Sign2GPT filter drops (DET, ADP, CCONJ, SCONJ, AUX, PART); pronouns and adverbs are kept
STOP_WORDS = {
    "en": frozenset("""
        a an the this that these those some any each every no
        of in on at to from by with about into onto over under above below between through during before after
        around against along among across behind beside beyond near off out up down upon within without for via
        and or but nor so yet if because although though while whereas unless until since than whether as
        be am is are was were been being have has had do does did will would shall should can could may might must
        not n't 's 'll 're 've 'd 'm to""".split()),
    "de": frozenset("""
        der die das den dem des ein eine einer eines einem einen kein keine
        in im an am auf aus bei beim mit nach von vom zu zum zur über unter vor hinter neben zwischen durch für
        gegen ohne um bis seit während
        und oder aber denn sondern dass ob weil wenn als wie
        ist sind war waren bin bist seid sein wird werden wurde wurden hat haben hatte hatten
        nicht es sich""".split()),
}


def spoken_language(language: str) -> str:
    """The spoken language (``en``, ``de``, ``zh``) of a sign language's text; ``""`` when not known."""
    code = language.lower()
    return SPOKEN_LANGUAGE.get(code) or SPOKEN_LANGUAGE.get(code.split("-")[0], "")


@dataclass(frozen=True)
class TextProcessor:
    """Tokenisation of one sign language's sentences (module docstring); stored in the checkpoint."""

    language: str
    chinese: bool
    rule: str = TEXT_RULE

    @classmethod
    def for_language(cls, language: str) -> TextProcessor:
        return cls(language, is_chinese(language))

    def tokens(self, text: str) -> list[str]:
        text = text.lower()
        if self.chinese:
            return tokenize("".join(text.split()), "zh")
        return _WORD.findall(text)

    def join(self, tokens: Sequence[str]) -> str:
        """Tokens back into a sentence (no spaces in Chinese)."""
        return ("" if self.chinese else " ").join(tokens)

    def reference(self, text: str) -> str:
        """A reference sentence as it is scored: tokenised and joined again."""
        return self.join(self.tokens(text))


# ----------------------------------------------------------------------------------------------- glosses
class PseudoGlosser:
    """Glosses from a sentence (module docstring); ``method`` says which rule was used."""

    def __init__(self, language: str):
        self.language = language
        self.spoken = spoken_language(language)
        self._processor = TextProcessor.for_language(language)
        self._nlp, pipeline = _spacy_pipeline(self.spoken)
        if self._nlp is not None:
            self.method = f"sign2gpt-pos (spacy {pipeline})"
        elif self.spoken in STOP_WORDS:
            self.method = f"stop-word fallback ({self.spoken}; no POS tagger installed)"
        else:
            self.method = "all words (no POS tagger installed, no stop-word list for this language)"

    def __call__(self, text: str) -> list[str]:
        if self._nlp is not None:
            return [t.lemma_.lower() for t in self._nlp(text) if t.pos_ in SIGN2GPT_POS]
        stop = STOP_WORDS.get(self.spoken, frozenset())
        return [t for t in self._processor.tokens(text) if t not in stop and any(c.isalnum() for c in t)]


def _spacy_pipeline(spoken: str):
    """A loaded spaCy pipeline for the spoken language and its name, or (None, "") when none is installed."""
    try:
        import spacy
    except ImportError:
        return None, ""
    for name in SPACY_PIPELINES.get(spoken, ()):
        try:
            return spacy.load(name, disable=["parser", "ner"]), name
        except OSError:  # pipeline not installed
            continue
    return None, ""


def annotated_gloss(gloss: str) -> list[str]:
    """An annotated gloss sequence: whitespace-separated, case kept (Phoenix glosses are upper case)."""
    return gloss.split()
