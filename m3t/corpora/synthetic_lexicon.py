"""Lexicon and grammar of the embedded synthetic sign corpus.

Concepts carry a word per spoken language and a part of speech; each synthetic sign language orders the
glosses of a sentence differently from its spoken language, so translation needs reordering:

- ``ASL-SYN`` (English text, SVO): gloss ``TIME OBJECT SUBJECT VERB`` (topicalised object)
- ``DGS-SYN`` (German text, verb second): gloss ``TIME SUBJECT OBJECT VERB`` (verb last, SOV)
- ``CSL-SYN`` (Chinese text in characters, SVO): gloss ``TIME SUBJECT VERB OBJECT``

Manual forms (handshape, location, movement, hands) and non-manual patterns (mouthing visemes, brows,
eyes) are drawn per sign from a seed. ``confusing`` pairs share the manual form exactly and differ only
in the face, like the NMFs-CSL confusing signs; every other sign is ``normal``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# concept -> (part of speech, English, German (with article for nouns), Chinese)
CONCEPTS: dict[str, tuple[str, str, str, str]] = {
    "I": ("person", "I", "ich", "我"),
    "YOU": ("person", "you", "du", "你"),
    "MOTHER": ("person", "the mother", "die Mutter", "妈妈"),
    "FATHER": ("person", "the father", "der Vater", "爸爸"),
    "TEACHER": ("person", "the teacher", "die Lehrerin", "老师"),
    "CHILD": ("person", "the child", "das Kind", "孩子"),
    "FRIEND": ("person", "the friend", "der Freund", "朋友"),
    "DOCTOR": ("person", "the doctor", "die Ärztin", "医生"),
    "BOOK": ("thing", "the book", "das Buch", "书"),
    "HOUSE": ("thing", "the house", "das Haus", "房子"),
    "CAR": ("thing", "the car", "das Auto", "汽车"),
    "WATER": ("thing", "the water", "das Wasser", "水"),
    "APPLE": ("thing", "the apple", "den Apfel", "苹果"),
    "SCHOOL": ("thing", "the school", "die Schule", "学校"),
    "TRAIN": ("thing", "the train", "den Zug", "火车"),
    "LETTER": ("thing", "the letter", "den Brief", "信"),
    "SEE": ("verb", "sees", "sieht", "看"),
    "LIKE": ("verb", "likes", "mag", "喜欢"),
    "WANT": ("verb", "wants", "will", "要"),
    "BUY": ("verb", "buys", "kauft", "买"),
    "READ": ("verb", "reads", "liest", "读"),
    "VISIT": ("verb", "visits", "besucht", "参观"),
    "FIND": ("verb", "finds", "findet", "找到"),
    "WASH": ("verb", "washes", "wäscht", "洗"),
    "TODAY": ("time", "today", "heute", "今天"),
    "TOMORROW": ("time", "tomorrow", "morgen", "明天"),
    "YESTERDAY": ("time", "yesterday", "gestern", "昨天"),
    "NOW": ("time", "now", "jetzt", "现在"),
}

LANGUAGES = ("ASL-SYN", "DGS-SYN", "CSL-SYN")
HANDSHAPES = {  # per-finger curl in [0, 1]: thumb, index, middle, ring, little
    "flat": (0.0, 0.0, 0.0, 0.0, 0.0),
    "fist": (0.6, 1.0, 1.0, 1.0, 1.0),
    "point": (0.6, 0.0, 1.0, 1.0, 1.0),
    "V": (0.6, 0.0, 0.0, 1.0, 1.0),
    "C": (0.3, 0.45, 0.45, 0.45, 0.45),
    "O": (0.6, 0.7, 0.7, 0.7, 0.7),
    "Y": (0.0, 1.0, 1.0, 1.0, 0.0),
    "L": (0.0, 0.0, 1.0, 1.0, 1.0),
    "W": (0.6, 0.0, 0.0, 0.0, 1.0),
    "bent": (0.2, 0.55, 0.55, 0.55, 0.55),
}
LOCATIONS = ("neutral", "neutral_high", "chest", "chin", "forehead", "cheek", "shoulder")
MOVEMENTS = ("straight", "arc", "circle", "repeat", "tap", "hold")
VISEMES = {  # facial-action weights of a mouth shape
    "a": {"jawOpen": 0.6, "mouthLowerDownLeft": 0.3, "mouthLowerDownRight": 0.3},
    "o": {"jawOpen": 0.3, "mouthFunnel": 0.6},
    "u": {"mouthPucker": 0.8, "jawOpen": 0.1},
    "i": {"mouthStretchLeft": 0.5, "mouthStretchRight": 0.5, "jawOpen": 0.15},
    "m": {"mouthClose": 0.4, "mouthPressLeft": 0.5, "mouthPressRight": 0.5},
    "f": {"mouthRollLower": 0.6, "mouthUpperUpLeft": 0.2, "mouthUpperUpRight": 0.2},
    "e": {"mouthSmileLeft": 0.5, "mouthSmileRight": 0.5, "jawOpen": 0.25},
}
BROWS = {"none": {}, "raise": {"browInnerUp": 0.7, "browOuterUpLeft": 0.5, "browOuterUpRight": 0.5},
         "furrow": {"browDownLeft": 0.7, "browDownRight": 0.7}}
EYES = {"none": {}, "squint": {"eyeSquintLeft": 0.6, "eyeSquintRight": 0.6},
        "wide": {"eyeWideLeft": 0.6, "eyeWideRight": 0.6}, "blink": {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0}}


@dataclass(frozen=True)
class SignForm:
    """One lexicon entry: manual form + non-manual pattern."""

    gloss: str
    handshape: str
    location: str
    movement: str
    two_handed: bool
    mouthing: tuple[str, ...]  # visemes over the sign
    brows: str
    eyes: str
    group: str  # "normal" | "confusing"
    pair: int  # pair id for confusing signs, -1 otherwise
    axis: tuple[float, float, float]  # movement direction (unit), body axes

    def manual(self) -> tuple:
        return (self.handshape, self.location, self.movement, self.two_handed, self.axis)


def build_lexicon(num_signs: int, confusing_pairs: int, rng: np.random.Generator) -> list[SignForm]:
    """Draw ``num_signs`` signs over the concepts; the last ``2 * confusing_pairs`` form minimal pairs."""
    glosses = list(CONCEPTS)
    if num_signs > len(glosses):
        raise ValueError(f"corpus.num_signs={num_signs} exceeds the {len(glosses)} concepts of the lexicon")
    if 2 * confusing_pairs > num_signs:
        raise ValueError(f"corpus.confusing_pairs={confusing_pairs} needs at least {2 * confusing_pairs} signs")
    order = rng.permutation(len(glosses))[:num_signs]
    chosen = [glosses[i] for i in sorted(order)]
    visemes = list(VISEMES)
    signs: list[SignForm] = []
    used_manual: set[tuple] = set()

    def draw(gloss: str, group: str, pair: int) -> SignForm:
        while True:
            axis = rng.normal(size=3)
            form = SignForm(
                gloss=gloss,
                handshape=str(rng.choice(list(HANDSHAPES))),
                location=str(rng.choice(LOCATIONS)),
                movement=str(rng.choice(MOVEMENTS)),
                two_handed=bool(rng.random() < 0.3),
                mouthing=tuple(str(v) for v in rng.choice(visemes, size=int(rng.integers(1, 4)))),
                brows=str(rng.choice(list(BROWS))),
                eyes=str(rng.choice(list(EYES))),
                group=group,
                pair=pair,
                axis=tuple(float(a) for a in axis / np.linalg.norm(axis)),
            )
            if form.manual()[:4] not in used_manual:  # normal signs differ manually
                used_manual.add(form.manual()[:4])
                return form

    normal = len(chosen) - 2 * confusing_pairs
    for gloss in chosen[:normal]:
        signs.append(draw(gloss, "normal", -1))
    for p in range(confusing_pairs):
        a, b = chosen[normal + 2 * p], chosen[normal + 2 * p + 1]
        first = draw(a, "confusing", p)
        # Same manual form, a different mouthing (and brows): only the face tells them apart.
        other_mouth = first.mouthing
        while other_mouth == first.mouthing:
            other_mouth = tuple(str(v) for v in rng.choice(visemes, size=int(rng.integers(1, 4))))
        second = SignForm(**{**first.__dict__, "gloss": b, "mouthing": other_mouth,
                             "brows": str(rng.choice([x for x in BROWS if x != first.brows]))})
        signs.extend([first, second])
    return signs


def zipf_weights(signs: list[SignForm], exponent: float, rng: np.random.Generator) -> dict[str, float]:
    """Gloss -> weight ``1 / rank^exponent``, the ranks a random order of the lexicon: sign frequency in real
    corpora is long-tailed (a few signs in most sentences, most signs rare)."""
    ranks = rng.permutation(len(signs)) + 1
    return {s.gloss: float(r) ** -exponent for s, r in zip(signs, ranks)}


def make_sentence(signs: list[SignForm], language: str, length: int, rng: np.random.Generator,
                  weights: dict[str, float] | None = None) -> tuple[str, list[str]]:
    """A sentence (text, gloss sequence) of 2..4 glosses in the language's word order; ``weights`` (gloss ->
    relative frequency) skew which sign of each part of speech is drawn (None: uniform)."""
    by_pos: dict[str, list[str]] = {}
    for s in signs:
        by_pos.setdefault(CONCEPTS[s.gloss][0], []).append(s.gloss)
    missing = [p for p in ("person", "verb") if p not in by_pos]
    if missing:
        raise ValueError(f"the lexicon has no {missing} sign; raise corpus.num_signs")

    def pick(pos: str) -> str:
        if weights is None:
            return str(rng.choice(by_pos[pos]))
        w = np.array([weights[g] for g in by_pos[pos]])
        return str(rng.choice(by_pos[pos], p=w / w.sum()))

    subj = pick("person")
    verb = pick("verb")
    obj = pick("thing") if length >= 3 and "thing" in by_pos else None
    time = pick("time") if length >= 4 and "time" in by_pos else None
    word = {"ASL-SYN": 1, "DGS-SYN": 2, "CSL-SYN": 3}[language]
    w = lambda g: CONCEPTS[g][word]  # noqa: E731
    if language == "ASL-SYN":
        text = " ".join(x for x in (w(subj), w(verb), w(obj) if obj else None, w(time) if time else None) if x)
        gloss = [g for g in (time, obj, subj, verb) if g]
    elif language == "DGS-SYN":
        first = [w(time), w(verb), w(subj)] if time else [w(subj), w(verb)]
        text = " ".join(first + ([w(obj)] if obj else []))
        gloss = [g for g in (time, subj, obj, verb) if g]
    else:
        text = "".join(w(g) for g in (time, subj, verb, obj) if g) + "。"
        gloss = [g for g in (time, subj, verb, obj) if g]
    return text[0].upper() + text[1:] if language != "CSL-SYN" else text, gloss
