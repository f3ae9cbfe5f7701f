"""Decoding a back-translation model: greedy, or a small beam search with JoeyNMT's length penalty
``((5 + length) / 6) ** alpha`` (SL-T's ``translation_beam_alphas``), and :func:`translate`, which turns motion
into sentences for any caller. A clip with no frames gets the empty sentence without running the model.

Axis legend: B batch, T frames, D input dim, K decoded tokens, V text vocabulary.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from m3t.backtranslation.data import pad_frames
from m3t.backtranslation.model import SignToText
from m3t.backtranslation.text import TextProcessor
from m3t.vocabulary import BOS, EOS, Vocabulary


def _cut(ids: Sequence[int], eos: int) -> list[int]:
    ids = list(ids)
    return ids[: ids.index(eos)] if eos in ids else ids


@torch.no_grad()
def greedy_decode(model: SignToText, frames: torch.Tensor, frame_mask: torch.Tensor, bos: int, eos: int,
                  max_len: int) -> list[list[int]]:
    """frames (B, T, D), frame_mask (B, T) -> per clip the token ids before EOS (at most ``max_len`` - 1)."""
    memory = model.encode(frames, frame_mask)
    ys = torch.full((frames.shape[0], 1), bos, dtype=torch.long, device=frames.device)  # (B, 1)
    done = torch.zeros(frames.shape[0], dtype=torch.bool, device=frames.device)
    for _ in range(max_len):
        step = model.decode(memory, frame_mask, ys)[:, -1].argmax(-1)  # (B,)
        step = torch.where(done, torch.full_like(step, eos), step)
        ys = torch.cat([ys, step[:, None]], dim=1)
        done |= step == eos
        if bool(done.all()):
            break
    return [_cut(row[1:], eos) for row in ys.tolist()]


@torch.no_grad()
def beam_decode(model: SignToText, frames: torch.Tensor, frame_mask: torch.Tensor, bos: int, eos: int,
                max_len: int, beam_size: int, alpha: float = 1.0) -> list[list[int]]:
    """Beam search, one clip at a time: of the 2 x beam best extensions, an EOS among the first ``beam_size``
    finishes a hypothesis and the best ``beam_size`` others stay alive (as Hugging Face's beam search); stops when
    no alive hypothesis can still beat the best finished one (log-probabilities only fall) or at ``max_len``.
    Hypotheses are ranked by log-probability / length penalty."""
    memory = model.encode(frames, frame_mask)
    penalty = lambda n: ((5.0 + n) / 6.0) ** alpha  # noqa: E731 - n: tokens incl. EOS
    out = []
    for b in range(frames.shape[0]):
        alive: list[tuple[list[int], float]] = [([bos], 0.0)]
        finished: list[tuple[list[int], float]] = []
        for _ in range(max_len):
            seqs = torch.tensor([s for s, _ in alive], device=frames.device)  # (n, k)
            n = len(alive)
            logp = model.decode(memory[b: b + 1].expand(n, -1, -1), frame_mask[b: b + 1].expand(n, -1),
                                seqs)[:, -1].log_softmax(-1)  # (n, V)
            scores = torch.tensor([s for _, s in alive], device=frames.device)[:, None] + logp
            top = scores.flatten().topk(min(2 * beam_size, scores.numel()))
            alive = []
            for rank, (value, index) in enumerate(zip(top.values.tolist(), top.indices.tolist())):
                row, token = divmod(index, logp.shape[1])
                seq = [*seqs[row].tolist(), token]
                if token == eos:
                    if rank < beam_size:  # an ending outside the beam's best is not a hypothesis of the beam
                        finished.append((seq[1:-1], value / penalty(len(seq) - 1)))
                elif len(alive) < beam_size:
                    alive.append((seq, value))
            if not alive:
                break
            if finished:  # log-probabilities only fall: stop once no alive hypothesis can still win
                length = len(alive[0][0])  # tokens incl. BOS = tokens incl. EOS at the next step
                bound = max(max(v / penalty(length), v / penalty(max_len)) for _, v in alive)
                if max(f[1] for f in finished) >= bound:
                    break
        if not finished:  # nothing ended within max_len: the best unfinished ones compete
            finished = [(s[1:], v / penalty(len(s))) for s, v in alive]
        out.append(max(finished, key=lambda f: f[1])[0])
    return out


def translate(model: SignToText, vocab: Vocabulary, processor: TextProcessor, frames: Sequence[np.ndarray],
              beam_size: int = 1, alpha: float = 1.0, batch_size: int = 16) -> list[str]:
    """Sentences of per-clip (T_i, D) inputs (cut to the model's ``max_frames``); T_i = 0 gives ``""``."""
    model.eval()
    device = next(model.parameters()).device
    bos, eos, max_len = vocab.stoi[BOS], vocab.stoi[EOS], model.cfg.max_text_tokens
    out = [""] * len(frames)
    todo = [i for i, f in enumerate(frames) if len(f)]
    for start in range(0, len(todo), batch_size):
        rows = todo[start: start + batch_size]
        x, mask = pad_frames([np.asarray(frames[i], dtype=np.float32)[: model.cfg.max_frames] for i in rows])
        x, mask = x.to(device), mask.to(device)
        if beam_size > 1:
            ids = beam_decode(model, x, mask, bos, eos, max_len, beam_size, alpha)
        else:
            ids = greedy_decode(model, x, mask, bos, eos, max_len)
        for i, seq in zip(rows, ids):
            out[i] = processor.join(vocab.decode(seq))
    return out
