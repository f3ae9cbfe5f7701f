"""Synthetic corpus: determinism, confusing vs normal signs, word orders, splits, ranges, storage."""
from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import torch

from m3t.corpora.config import SyntheticCorpusConfig
from m3t.corpora.synthetic import generate_corpus
from m3t.corpora.synthetic_lexicon import CONCEPTS, build_lexicon, make_sentence
from m3t.corpora.synthetic_storage import SyntheticCorpus, write_corpus

CFG = SyntheticCorpusConfig(num_signs=10, confusing_pairs=2, num_signers=2, sentences_per_language=3,
                            frames_per_sign=8, transition_frames=3, hold_frames=2)


@pytest.fixture(scope="module")
def corpus(body):
    return generate_corpus(CFG, body)


def test_same_seed_same_corpus_other_seed_differs(body, corpus):
    again = generate_corpus(CFG, body)
    assert [c.clip for c in again] == [c.clip for c in corpus]
    for a, b in zip(again, corpus):
        for k in a.params:
            np.testing.assert_array_equal(a.params[k], b.params[k])
    other = generate_corpus(dataclasses.replace(CFG, seed=1), body)
    assert [c.clip.text for c in other] != [c.clip.text for c in corpus]


def test_confusing_pairs_differ_only_in_the_face(body, corpus):
    iso = {(c.clip.gloss, c.clip.signer): c for c in corpus if c.clip.get("kind") == "isolated"}
    pairs: dict[str, list] = {}
    for c in iso.values():
        if c.clip.get("group") == "confusing":
            pairs.setdefault(c.clip.get("pair"), []).append(c)
    assert len(pairs) == CFG.confusing_pairs
    for members in pairs.values():
        by_signer: dict[str, list] = {}
        for c in members:
            by_signer.setdefault(c.clip.signer, []).append(c)
        for a, b in by_signer.values():
            assert a.clip.gloss != b.clip.gloss and a.clip.label != b.clip.label
            for m in ("body", "left_hand", "right_hand"):
                np.testing.assert_array_equal(a.params[m], b.params[m])
            assert a.params["face"].shape == b.params["face"].shape
            assert np.abs(a.params["face"] - b.params["face"]).max() > 0.2
    normal = [c for c in iso.values() if c.clip.get("group") == "normal" and c.clip.signer == "signer00"]
    assert len(normal) >= 2
    for i, a in enumerate(normal):
        for b in normal[i + 1:]:
            if a.params["body"].shape == b.params["body"].shape:
                manual = np.concatenate([a.params[m] - b.params[m] for m in ("body", "right_hand")], axis=1)
                assert np.abs(manual).max() > 1e-3


def test_word_orders_and_scripts():
    rng = np.random.default_rng(0)
    lexicon = build_lexicon(len(CONCEPTS), 0, rng)
    for _ in range(20):
        _, asl = make_sentence(lexicon, "ASL-SYN", 3, rng)
        _, dgs = make_sentence(lexicon, "DGS-SYN", 3, rng)
        text, csl = make_sentence(lexicon, "CSL-SYN", 3, rng)
        assert CONCEPTS[dgs[-1]][0] == "verb"  # verb last
        assert CONCEPTS[asl[-1]][0] == "verb" and CONCEPTS[asl[0]][0] == "thing"  # topicalised object
        assert CONCEPTS[csl[1]][0] == "verb" and CONCEPTS[csl[2]][0] == "thing"  # SVO
        assert re.search(r"[\u4e00-\u9fff]", text)


def test_splits_labels_and_ranges(body, corpus):
    assert {c.clip.split for c in corpus} == {"train", "dev", "test"}
    iso = [c for c in corpus if c.clip.get("kind") == "isolated"]
    assert len(iso) == CFG.num_signs * CFG.num_signers * CFG.isolated_per_sign
    assert {c.clip.label for c in iso} == set(range(CFG.num_signs))
    assert {c.clip.language for c in corpus if c.clip.get("kind") == "sentence"} == set(CFG.languages)
    for c in corpus:
        T = c.params["face"].shape[0]
        assert all(v.shape == (T, body.layout.dims[k]) for k, v in c.params.items())
        assert c.params["face"].min() >= 0 and c.params["face"].max() <= 1
        assert np.all((c.identity >= 0) & (c.identity <= 1))


def test_hands_stay_in_the_signing_space(body, corpus):
    clip = next(c for c in corpus if c.clip.get("kind") == "sentence")
    params = {k: torch.as_tensor(v) for k, v in clip.params.items()}
    joints = body.forward(params, torch.as_tensor(clip.identity)).joints
    wrist = joints[:, body.joint_names.index("wrist.R")]
    chest = joints[:, body.joint_names.index("spine01")]
    # The body faces -y: hands stay in front of the chest plane and between hip and above-head height.
    assert torch.all(wrist[:, 1] < chest[:, 1] + 0.05)
    assert torch.all((wrist[:, 2] > -0.2) & (wrist[:, 2] < 0.9))


def test_write_read_round_trip_and_errors(corpus, tmp_path):
    root = write_corpus(corpus, tmp_path / "corpus")
    reader = SyntheticCorpus(root)
    clips = reader.clips()
    assert clips == [c.clip for c in corpus]
    params, identity, camera = reader.ground_truth(clips[0])
    for k, v in corpus[0].params.items():
        np.testing.assert_array_equal(params[k], v)
    assert camera == corpus[0].camera
    assert not list(tmp_path.glob(".corpus.*"))
    (root / clips[1].media).unlink()
    with pytest.raises(FileNotFoundError, match=clips[1].id):
        reader.ground_truth(clips[1])
    (root / clips[2].media).write_bytes(b"junk")
    with pytest.raises(ValueError, match="corrupt"):
        reader.ground_truth(clips[2])


def test_every_sign_is_in_every_split_and_parts_grow_independently(body):
    """Six isolated clips per sign (3 signers x 2 sessions) split 4 / 1 / 1 per sign, so recognition is scored
    on every class; sessions differ (jittered performance); more sentences leave the isolated clips alone."""
    cfg = dataclasses.replace(CFG, num_signers=3, isolated_per_sign=2, sentences_per_language=1)
    clips = generate_corpus(cfg, body)
    iso = [c for c in clips if c.clip.get("kind") == "isolated"]
    by_label: dict[int, list[str]] = {}
    for c in iso:
        by_label.setdefault(c.clip.label, []).append(c.clip.split)
    assert len(by_label) == cfg.num_signs
    assert all(sorted(s) == ["dev", "test", "train", "train", "train", "train"] for s in by_label.values())
    assert len({c.clip.signer for c in iso if c.clip.split == "test"}) == 3  # the held-out signer varies
    sessions = {c.clip.id: c for c in iso}
    first = sessions["iso-" + iso[0].clip.gloss.lower() + "-signer00-0"]
    second = sessions["iso-" + iso[0].clip.gloss.lower() + "-signer00-1"]
    assert not np.array_equal(first.params["body"], second.params["body"])
    grown = generate_corpus(dataclasses.replace(cfg, sentences_per_language=3), body)
    for a, b in zip(iso, [c for c in grown if c.clip.get("kind") == "isolated"]):
        assert a.clip == b.clip
        np.testing.assert_array_equal(a.params["body"], b.params["body"])
