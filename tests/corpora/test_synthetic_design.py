"""The study design of the synthetic corpus (``synthetic_corpus`` options of the ``study`` preset): held-out
compositions, unseen signers, the isolated split cycle, the natural face, long-tailed glosses, and the production
models leaving isolated signs out (``data.production_skip_kinds``)."""
from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
import pytest

from m3t.corpora.config import SyntheticCorpusConfig
from m3t.corpora.synthetic import generate_corpus
from m3t.corpora.synthetic_design import held_out_splits
from m3t.corpora.synthetic_lexicon import build_lexicon, make_sentence, zipf_weights
from m3t.shards.folders import DataConfig

BASE = SyntheticCorpusConfig(num_signs=12, confusing_pairs=2, num_signers=3, isolated_per_sign=1,
                             sentences_per_language=20, frames_per_sign=8, transition_frames=3, hold_frames=2)
STUDY = dataclasses.replace(BASE, sentence_split="held_out", face_model="natural", gloss_zipf=1.0,
                            sentence_splits=("train", "test", "train", "dev", "train", "test", "train"))


@pytest.fixture(scope="module")
def study(body):
    return generate_corpus(STUDY, body)


def _sentences(clips):
    return [c for c in clips if c.clip.get("kind") == "sentence"]


def test_held_out_test_sentences_are_new_compositions_of_seen_glosses(study):
    sentences = _sentences(study)
    by_split = {s: [frozenset(c.clip.gloss.split()) for c in sentences if c.clip.split == s]
                for s in ("train", "dev", "test")}
    assert len(by_split["test"]) >= 5 and len(by_split["dev"]) >= 1
    train = set(by_split["train"])
    seen = frozenset().union(*train)
    for split in ("dev", "test"):
        assert not train & set(by_split[split])  # no dev / test composition (in any language) is a train one
        assert all(k <= seen for k in by_split[split])  # every concept was signed in a train sentence
    assert not {c.clip.text for c in sentences if c.clip.split == "test"} & {
        c.clip.text for c in sentences if c.clip.split == "train"}


def test_held_out_splits_moves_compositions_with_unseen_concepts_to_train():
    glosses = [["A", "B"], ["A", "B"], ["C", "D"], ["A", "C"], ["B", "D"], ["E", "A"]]
    splits = held_out_splits(glosses, np.random.default_rng(0), ("test", "train"))
    assert splits[0] == splits[1]  # one composition, one split
    train = frozenset().union(*(frozenset(g) for g, s in zip(glosses, splits) if s == "train"))
    assert all(frozenset(g) <= train for g, s in zip(glosses, splits) if s == "test")
    assert "test" in splits and splits[5] == "train"  # E is in no other sentence: it must be trained on


def test_the_default_cycle_puts_one_sentence_on_both_sides(body):
    # the reason for the held-out design: the embedded default's cycle split repeats train sentences in test
    clips = _sentences(generate_corpus(dataclasses.replace(BASE, sentences_per_language=30), body))
    train = {frozenset(c.clip.gloss.split()) for c in clips if c.clip.split == "train"}
    assert any(frozenset(c.clip.gloss.split()) in train for c in clips if c.clip.split == "test")


def test_unseen_signers_sign_only_test_clips_and_are_tagged(body):
    clips = generate_corpus(dataclasses.replace(STUDY, held_out_signers=1), body)
    unseen = [c for c in clips if c.clip.signer == "signer02"]
    assert unseen and all(c.clip.split == "test" and c.clip.get("signer_seen") == "false" for c in unseen)
    assert {c.clip.get("signer_seen") for c in clips if c.clip.signer != "signer02"} == {"true"}
    assert any(c.clip.get("kind") == "sentence" for c in unseen)
    with pytest.raises(ValueError, match="held_out_signers=3"):
        generate_corpus(dataclasses.replace(STUDY, held_out_signers=3), body)


def test_the_isolated_cycle_sets_the_test_clips_per_class(body):
    cfg = dataclasses.replace(BASE, num_signs=8, confusing_pairs=1, isolated_per_sign=4, sentences_per_language=3,
                              isolated_splits=("train", "test", "train", "dev", "train", "test"))
    clips = [c for c in generate_corpus(cfg, body) if c.clip.label is not None]
    per_class = Counter((c.clip.label, c.clip.split) for c in clips)
    assert {per_class[(label, "test")] for label in range(8)} == {4}  # 12 clips per sign, 2 of every 6 to test
    assert {per_class[(label, "train")] for label in range(8)} == {6}
    with pytest.raises(ValueError, match="isolated_splits"):
        generate_corpus(dataclasses.replace(cfg, isolated_splits=("dev", "test")), body)
    with pytest.raises(ValueError, match="face_model"):
        generate_corpus(dataclasses.replace(cfg, face_model="smiley"), body)


def test_the_natural_face_is_mostly_neutral_with_brief_events_and_keeps_the_pairs_apart(body, study):
    lexical = generate_corpus(dataclasses.replace(STUDY, face_model="lexical"), body)
    natural_face = np.concatenate([c.params["face"] for c in study])
    lexical_face = np.concatenate([c.params["face"] for c in lexical])
    assert natural_face.shape == lexical_face.shape  # the face never changes the timing
    for c, other in zip(study, lexical):
        for m in ("body", "left_hand", "right_hand"):
            np.testing.assert_array_equal(c.params[m], other.params[m])
    # near-neutral most of the time: the typical frame's strongest action is small, the events are in the tail
    peak = natural_face.max(axis=1)
    assert np.median(peak) < 0.3 and np.percentile(peak, 99) > 0.6
    # idle motion: every action moves a little (lexical faces are exactly 0 outside events) ...
    assert (lexical_face == 0).mean() > 0.5 and (natural_face == 0).mean() < 0.05
    # ... with a decaying spectrum: a few actions carry most of the variance
    var = np.sort(natural_face.var(axis=0))[::-1]
    assert var[:5].sum() > 0.5 * var.sum()
    # spontaneous blinks happen in sentences whatever the signs' own eye patterns
    labels = body.layout["face"].labels
    blink = labels.index("eyeBlinkLeft")
    assert sum(c.params["face"][:, blink].max() > 0.7 for c in _sentences(study)) >= 3
    # confusing pairs (lexical non-manuals) still differ in the face in every session
    iso = [c for c in study if c.clip.get("group") == "confusing"]
    by = {}
    for c in iso:
        by.setdefault((c.clip.get("pair"), c.clip.signer), []).append(c)
    for a, b in by.values():
        assert np.abs(a.params["face"] - b.params["face"]).max() > 0.2


def test_long_tailed_glosses(body, study):
    lexicon = build_lexicon(12, 2, np.random.default_rng(0))
    weights = zipf_weights(lexicon, 1.0, np.random.default_rng(1))
    rng = np.random.default_rng(2)
    counts = Counter(g for _ in range(600) for g in make_sentence(lexicon, "ASL-SYN", 4, rng, weights)[1])
    verbs = [s.gloss for s in lexicon if s.gloss in counts and weights[s.gloss]]
    top, bottom = max(verbs, key=weights.get), min(verbs, key=weights.get)
    assert counts[top] > 2 * counts[bottom]  # drawn in proportion to 1 / rank
    uniform = Counter(g for _ in range(600) for g in make_sentence(lexicon, "ASL-SYN", 4, rng)[1])
    assert max(uniform.values()) < max(counts.values())


def test_production_models_leave_the_isolated_signs_out(study):
    data = DataConfig(production_skip_kinds=("isolated",))
    kept = data.for_production(study)
    assert kept and all(c.clip.get("kind") == "sentence" for c in kept)
    assert len(kept) == len(_sentences(study))
    assert DataConfig().for_production(study) == list(study)
    assert data.production_version("abc") != DataConfig().production_version("abc") == "abc"


def _twin_splits(clips) -> Counter:
    """For each test clip of a confusing sign: the split of its manual twin (same pair, signer and session)."""
    sessions: dict[tuple, dict[int, str]] = {}
    for c in clips:
        if c.clip.get("group") == "confusing":
            sessions.setdefault((c.clip.get("pair"), c.clip.signer, c.clip.id.rsplit("-", 1)[1]), {})[
                c.clip.label] = c.clip.split
    out = Counter()
    for by_label in sessions.values():
        a, b = sorted(by_label)
        out.update(by_label[twin] for me, twin in ((a, b), (b, a)) if by_label[me] == "test")
    return out


def test_twins_share_a_split_so_no_test_clip_has_its_manual_twin_in_train(body):
    cfg = dataclasses.replace(BASE, num_signs=8, confusing_pairs=2, isolated_per_sign=2, sentences_per_language=3,
                              isolated_splits=("train", "test", "train", "dev", "train", "test"))
    apart = _twin_splits(generate_corpus(cfg, body))
    assert apart["train"] > 0  # shifted by label, a test clip's identical manual twin is trained on
    together = _twin_splits(generate_corpus(dataclasses.replace(cfg, twins_share_split=True), body))
    assert together["test"] > 0 and set(together) == {"test"}
