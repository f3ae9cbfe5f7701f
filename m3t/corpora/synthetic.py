"""The embedded synthetic sign corpus: procedural signing with ground-truth body-model parameters.

Deterministic from a seed and scalable from a handful of clips to thousands; :func:`make_corpus` generates it
and writes it (the generate-corpus stage). The pieces, each in its own module:

1. *Calibration* (:mod:`m3t.corpora.synthetic_calibration`, once per corpus, with the body model): finger
   flexion axes and arm postures for every sign location.
2. *Signs* (:mod:`m3t.corpora.synthetic_lexicon`): handshape, location, movement and non-manual pattern per
   sign; sentences per synthetic sign language.
3. *Clips* (here, with :mod:`m3t.corpora.synthetic_motion` and :mod:`m3t.corpora.synthetic_face`): rest ->
   signs with smooth co-articulated transitions -> rest, per-signer identity (Anny phenotypes), speed, amplitude
   and posture, jittered per sentence and per isolated recording session (``performance_jitter``: nobody signs
   the same sign twice alike; within a session both signs of a confusing pair stay manually identical);
   isolated clips (one sign, ``label``) for recognition and sentence clips for production; a camera per clip.
   Isolated clips and sentences draw from separate random streams, so growing one part leaves the other
   unchanged.
4. *Splits*: sentences cycle through ``sentence_splits`` (default :data:`~m3t.corpora.config.SPLIT_CYCLE`,
   80 / 10 / 10); the isolated clips of each sign through ``isolated_splits`` (default 4 / 1 / 1, the cycle
   shifted by the sign's label so that the held-out signer varies), so every sign with six clips
   (``num_signers * isolated_per_sign``) is in every split and recognition is scored on every class.

The study design (held-out sentences and signers, the natural face model, gloss frequencies; all off by default,
the ``study`` preset turns them on) is described, with its reasons, in :mod:`m3t.corpora.synthetic_design`.
The written form (``clips.jsonl`` + ``motion/<id>.npz``) and its reader are in
:mod:`m3t.corpora.synthetic_storage`.
"""
from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

from m3t.body.protocol import BodyModel
from m3t.camera import Camera, look_at
from m3t.corpora.clip import Clip
from m3t.corpora.config import SyntheticCorpusConfig
from m3t.corpora.synthetic_calibration import calibrate
from m3t.corpora.synthetic_design import check_design, held_out_splits
from m3t.corpora.synthetic_face import FaceStyle
from m3t.corpora.synthetic_lexicon import (
    CONCEPTS,
    build_lexicon,
    make_sentence,
    zipf_weights,
)
from m3t.corpora.synthetic_motion import Signer, Synthesiser
from m3t.corpora.synthetic_storage import SyntheticClip, write_corpus


def _camera(rng: np.random.Generator, size: int) -> Camera:
    """Front-ish view of the upper body: small random yaw / pitch, 2.2-2.8 m away."""
    yaw, pitch = np.deg2rad(rng.uniform(-12, 12)), np.deg2rad(rng.uniform(-6, 10))
    dist = rng.uniform(2.2, 2.8)
    target = np.array([0.0, 0.0, 0.32]) + rng.normal(0, 0.02, 3)
    eye = target + dist * np.array([np.sin(yaw) * np.cos(pitch), -np.cos(yaw) * np.cos(pitch), np.sin(pitch)])
    rot = look_at(eye, target, np.array([0.0, 0.0, 1.0]))
    f = 1.9 * size  # about 0.6 m of body across half the image at 2.5 m
    return Camera(f, f, size / 2, size / 2, tuple(map(tuple, rot)), tuple((-rot @ eye).tolist()), size, size)


def _signers(cfg: SyntheticCorpusConfig, rng: np.random.Generator) -> list[Signer]:
    return [Signer(f"signer{i:02d}", rng.uniform(0.2, 0.8, 6), float(rng.uniform(0.8, 1.25)),
                   float(rng.uniform(0.8, 1.2)), rng.normal(0, np.deg2rad(3), 3)) for i in range(cfg.num_signers)]


def _performance(signer: Signer, rng: np.random.Generator, jitter: float) -> Signer:
    """One performance of ``signer``: speed and amplitude scaled by up to +-``jitter``, posture moved by ~1 deg."""
    if jitter <= 0:
        return signer
    return Signer(signer.id, signer.identity, signer.speed * float(rng.uniform(1 - jitter, 1 + jitter)),
                  signer.amplitude * float(rng.uniform(1 - jitter, 1 + jitter)),
                  signer.posture + rng.normal(0, np.deg2rad(1.0), 3))


def generate_corpus(cfg: SyntheticCorpusConfig, body: BodyModel) -> list[SyntheticClip]:
    """All clips of the corpus (isolated signs first, then sentences per language), deterministic from the seed."""
    check_design(cfg)
    rng = np.random.default_rng(cfg.seed)
    lexicon = build_lexicon(cfg.num_signs, cfg.confusing_pairs, rng)
    signers = _signers(cfg, rng)
    unseen = {s.id for s in signers[len(signers) - cfg.held_out_signers:]} if cfg.held_out_signers else set()
    seen_signers = [s for s in signers if s.id not in unseen]
    synth = Synthesiser(body, calibrate(body), cfg)
    face = (FaceStyle.draw(body.layout["face"].labels, [s.id for s in signers], np.random.default_rng([cfg.seed, 4]))
            if cfg.face_model == "natural" else None)
    clips: list[SyntheticClip] = []

    def add(clip_id, signs, signer, performance, language, text, label, extra, split, part_rng):
        if unseen:
            extra = [*extra, ("signer_seen", "false" if signer.id in unseen else "true")]
        clip = Clip(id=clip_id, corpus="synthetic", split=split, language=language, signer=signer.id, text=text,
                    gloss=" ".join(s.gloss for s in signs), media=f"motion/{clip_id}.npz", fps=cfg.fps, label=label,
                    extra=tuple(extra))
        face_rng = np.random.default_rng([cfg.seed, 5, zlib.crc32(clip_id.encode())]) if face is not None else None
        clips.append(SyntheticClip(clip, synth.synthesise(signs, performance, face, face_rng),
                                   signer.identity.astype(np.float32), _camera(part_rng, cfg.image_size)))

    isolated_rng, sentence_rng = np.random.default_rng([cfg.seed, 1]), np.random.default_rng([cfg.seed, 2])
    # the rep-th isolated recording session of each signer: one performance for every sign, so the two signs
    # of a confusing pair stay manually identical within a session
    sessions = {(s.id, rep): _performance(s, isolated_rng, cfg.performance_jitter)
                for rep in range(cfg.isolated_per_sign) for s in signers}
    cycle = cfg.isolated_splits
    first_of_pair: dict[int, int] = {}
    for label, sign in enumerate(lexicon):
        k = 0
        shift = first_of_pair.setdefault(sign.pair, label) if cfg.twins_share_split and sign.pair >= 0 else label
        for rep in range(cfg.isolated_per_sign):
            for signer in signers:
                extra = [("kind", "isolated"), ("group", sign.group), ("pair", str(sign.pair))]
                split = "test" if signer.id in unseen else cycle[(k + shift) % len(cycle)]
                add(f"iso-{sign.gloss.lower()}-{signer.id}-{rep}", [sign], signer, sessions[(signer.id, rep)], "ISO-SYN",
                    CONCEPTS[sign.gloss][1], label, extra, split, isolated_rng)
                k += 1
    by_gloss = {s.gloss: s for s in lexicon}
    weights = zipf_weights(lexicon, cfg.gloss_zipf, np.random.default_rng([cfg.seed, 3])) if cfg.gloss_zipf else None
    if cfg.sentence_split == "cycle":
        for language in cfg.languages:
            for i in range(cfg.sentences_per_language):
                length = int(sentence_rng.integers(cfg.min_glosses, cfg.max_glosses + 1))
                text, glosses = make_sentence(lexicon, language, length, sentence_rng, weights)
                signer = signers[int(sentence_rng.integers(len(signers)))]
                performance = _performance(signer, sentence_rng, cfg.performance_jitter)
                split = "test" if signer.id in unseen else cfg.sentence_splits[i % len(cfg.sentence_splits)]
                add(f"{language.lower()}-{i:04d}", [by_gloss[g] for g in glosses], signer, performance, language, text,
                    None, [("kind", "sentence")], split, sentence_rng)
        return clips
    drafts = []  # held_out: draw every sentence, split by composition, then cast the signers
    for language in cfg.languages:
        for i in range(cfg.sentences_per_language):
            length = int(sentence_rng.integers(cfg.min_glosses, cfg.max_glosses + 1))
            drafts.append((language, i, *make_sentence(lexicon, language, length, sentence_rng, weights)))
    splits = held_out_splits([d[3] for d in drafts], np.random.default_rng([cfg.seed, 6]), cfg.sentence_splits)
    for (language, i, text, glosses), split in zip(drafts, splits):
        pool = signers if split == "test" else seen_signers
        signer = pool[int(sentence_rng.integers(len(pool)))]
        performance = _performance(signer, sentence_rng, cfg.performance_jitter)
        add(f"{language.lower()}-{i:04d}", [by_gloss[g] for g in glosses], signer, performance, language, text,
            None, [("kind", "sentence")], split, sentence_rng)
    return clips


def make_corpus(cfg: SyntheticCorpusConfig, body_cfg, root: str | Path) -> dict:
    """Generate the corpus with the body model of ``body_cfg`` and write it to ``root``; returns the clip counts."""
    from m3t.body.factory import load_body_model

    clips = generate_corpus(cfg, load_body_model(body_cfg))
    write_corpus(clips, root)
    splits: dict[str, int] = {}
    for c in clips:
        splits[c.clip.split] = splits.get(c.clip.split, 0) + 1
    return {"clips": len(clips), "splits": splits}
