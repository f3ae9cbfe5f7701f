"""The back-translation judge's training target and batches (:mod:`m3t.backtranslation.data`), on hand-made
samples: the decoder reads BOS then the sentence and is taught the sentence then EOS (padding ignored by the
loss), frames are zero-padded with a mask, features normalised by the train split's statistics, and which clips
can be examples at all. Written to pin behaviours that mutation testing found unchecked."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from m3t.backtranslation.data import (
    IGNORE,
    Sample,
    collate,
    feature_statistics,
    pad_frames,
    skip_reason,
)
from m3t.vocabulary import BOS, EOS, PAD, text_vocabulary


def sample(clip_id: str, frames: np.ndarray, text: tuple[int, ...], glosses: tuple[int, ...] = ()) -> Sample:
    return Sample(clip_id, frames.astype(np.float32), text, glosses, "ref")


def test_the_decoder_reads_bos_and_the_sentence_and_learns_the_sentence_and_eos():
    vocab = text_vocabulary([["hello", "world", "again"]])
    assert [vocab.stoi[t] for t in (PAD, BOS, EOS)] == [0, 2, 3]
    hello, world, again = vocab.encode(["hello", "world", "again"])
    batch = collate([sample("a", np.ones((2, 3)), (hello, world, again), (1, 2)),
                     sample("b", np.full((4, 3), 2.0), (world,))], vocab)
    assert batch.text_in.tolist() == [[2, hello, world, again], [2, world, 0, 0]]  # BOS + ids, PAD after
    assert batch.text_out.tolist() == [[hello, world, again, 3], [world, 3, IGNORE, IGNORE]]  # ids + EOS
    assert IGNORE == -100  # what torch's cross-entropy skips by default
    assert batch.frames.shape == (2, 4, 3) and batch.frame_mask.tolist() == [[True, True, False, False], [True] * 4]
    assert batch.frames[0, 2:].abs().sum() == 0 and batch.frames[1, 3, 0] == 2.0
    assert batch.glosses.tolist() == [[1, 2], [0, 0]] and batch.gloss_lengths.tolist() == [2, 0]


def test_pad_frames_zero_pads_to_the_longest_clip():
    frames, mask = pad_frames([np.arange(6, dtype=np.float32).reshape(3, 2), np.full((1, 2), 7.0, np.float32)])
    assert frames.tolist() == [[[0, 1], [2, 3], [4, 5]], [[7, 7], [0, 0], [0, 0]]]
    assert mask.tolist() == [[True] * 3, [True, False, False]] and mask.dtype == torch.bool


def test_feature_statistics_are_over_every_training_frame_with_a_floored_std():
    a = sample("a", np.array([[0.0, 5.0], [2.0, 5.0]]), (4,))
    b = sample("b", np.array([[4.0, 5.0]]), (4,))
    mean, std = feature_statistics([a, b])
    # column 0: frames 0, 2, 4 -> mean 2, population std sqrt(8 / 3); column 1 constant: std floored at 1e-3
    assert mean.tolist() == pytest.approx([2.0, 5.0]) and std == pytest.approx([np.sqrt(8 / 3), 1e-3], rel=1e-6)
    assert mean.dtype == np.float32 and std.dtype == np.float32


def test_only_sentence_clips_with_text_and_frames_are_examples():
    def clip(label=None, text="a sentence"):
        return SimpleNamespace(label=label, text=text)

    assert skip_reason(clip(), 10) is None
    assert skip_reason(clip(label=3), 10) == "isolated sign (label 3): back-translation is sentence-level"
    assert skip_reason(clip(label=0), 10).startswith("isolated sign (label 0)")  # label 0 is a label too
    assert skip_reason(clip(text="   "), 10) == "empty text"
    assert skip_reason(clip(), 0) == "no frames"
