"""Training one back-translation model (one sign language; M3T App. 0.D.4): Adam, translation cross-entropy plus
``gloss_ctc_weight`` x the gloss CTC loss (SL-T's joint recognition + translation), the learning rate cut by
``lr_factor`` when validation BLEU-4 has not improved for ``lr_patience`` validations (ReduceLROnPlateau, mode
max), and the checkpoint with the best validation BLEU-4 kept as ``best``. Validation decodes the dev split
greedily and scores it under definition "slt" (:mod:`m3t.metrics.text`; per character for Chinese).

Selection ``val_selection`` = BLEU-4 + 1e-6 x ROUGE-L: BLEU-4, with ties broken by ROUGE-L (on a small dev split
BLEU-4 is often 0 for many validations; the first of them would otherwise be kept). Without a dev split the last
epoch is kept. A resumable ``last`` is written (at most every 30 s and at the end) through
:class:`m3t.training.EpochTail`: a run killed part-way and started again with the same config, vocabulary and data
continues the same loss curve (:func:`run_key` names it).

Axis legend: B batch, T frames, K text tokens, G gloss classes.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F

from m3t.backtranslation.checkpoint import load_backtranslation, save_backtranslation
from m3t.backtranslation.config import BackTranslationConfig, BackTranslationTrainConfig
from m3t.backtranslation.data import (
    IGNORE,
    Batch,
    InputSpec,
    LanguageCorpus,
    collate,
    feature_statistics,
)
from m3t.backtranslation.decode import translate
from m3t.backtranslation.model import BackTranslationDims, SignToText
from m3t.checkpoints import run_digest
from m3t.metrics.text import slt_translation_metrics
from m3t.optimizer import PlateauSchedule, adam, optimizer_step
from m3t.runtime import autocast
from m3t.training import (
    EpochTail,
    Selection,
    TrainRun,
    epoch_batches,
    run_epochs,
    scalar_settings,
    start_training,
)

TRAIN_VERSION = "backtranslation-v1"  # part of the resume key: bump when older training state becomes invalid
DECODE_ONLY = ("beam_size", "length_penalty", "languages")  # model-section keys a trained model does not depend on


def losses(model: SignToText, batch: Batch, ctc_weight: float, smoothing: float = 0.0) -> dict[str, torch.Tensor]:
    """``{"loss", "translation_loss"[, "gloss_ctc_loss"]}``; CTC only over clips with a gloss."""
    text_mask = batch.text_out != IGNORE  # (B, K) real tokens (the same positions in text_in)
    out = model(batch.frames, batch.frame_mask, batch.text_in, text_mask)
    translation = F.cross_entropy(out.text_logits.flatten(0, 1).float(), batch.text_out.flatten(),
                                  ignore_index=IGNORE, label_smoothing=smoothing)
    result = {"loss": translation, "translation_loss": translation}
    rows = batch.gloss_lengths > 0
    if out.gloss_logits is not None and ctc_weight > 0 and bool(rows.any()):
        log_probs = out.gloss_logits[rows].float().log_softmax(-1).transpose(0, 1)  # (T, B', G)
        ctc = F.ctc_loss(log_probs, batch.glosses[rows], batch.frame_mask[rows].sum(1), batch.gloss_lengths[rows],
                         blank=0, reduction="mean", zero_infinity=True)
        result.update(loss=translation + ctc_weight * ctc, gloss_ctc_loss=ctc)
    return result


def train_step(model: SignToText, batch: Batch, optim: torch.optim.Optimizer, schedule: PlateauSchedule,
               ctc_weight: float, precision: str = "fp32", grad_clip: float = 0.0,
               smoothing: float = 0.0) -> dict[str, float]:
    device = next(model.parameters()).device
    with autocast(device, precision):
        out = losses(model, batch.to(device), ctc_weight, smoothing)
    optimizer_step(out["loss"], model, optim, schedule, grad_clip)
    return {k: v.item() for k, v in out.items()}


def validate(model: SignToText, corpus: LanguageCorpus) -> dict[str, float]:
    """Greedy decoding of the dev split, scored under definition "slt"; adds ``selection`` (module docstring)."""
    hyps = translate(model, corpus.text_vocab, corpus.processor, [s.frames for s in corpus.dev])
    scores = slt_translation_metrics(hyps, [s.reference for s in corpus.dev], corpus.language)
    scores["selection"] = scores["bleu4"] + 1e-6 * scores["rouge_l"]
    return scores


def run_key(model_cfg: BackTranslationConfig, cfg: BackTranslationTrainConfig, corpus: LanguageCorpus,
            spec: InputSpec, data_version: str) -> str:
    """What a resumable ``last`` must agree on: code version, model and training settings (not where files go,
    the device or decode-time settings), language, vocabularies, input layout and data."""
    model = {k: v for k, v in dataclasses.asdict(model_cfg).items() if k not in DECODE_ONLY}
    settings = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("cache_dir", "device", "workers")}
    gloss = None if corpus.gloss_vocab is None else corpus.gloss_vocab.to_dict()
    return run_digest(TRAIN_VERSION, corpus.language, model, settings, corpus.text_vocab.to_dict(), gloss,
                            spec.to_dict(), data_version)


def train_backtranslation(
    model_cfg: BackTranslationConfig,
    cfg: BackTranslationTrainConfig,
    corpus: LanguageCorpus,
    spec: InputSpec,
    data_version: str,
    best_path: str | Path,
    last_path: str | Path | None = None,
    on_epoch: Callable[[dict[str, float], int], None] | None = None,
    progress: bool = True,
    stop_after_epochs: int | None = None,
) -> TrainRun:
    """Train ``corpus.language``'s model; ``last_path``: the resumable checkpoint (continued when it exists;
    name it by :func:`run_key`); ``stop_after_epochs``: train at most that many more epochs."""
    if not corpus.train:
        raise ValueError(f"language {corpus.language!r}: no training clip")
    device = start_training(cfg.device, cfg.seed)
    gloss_classes = len(corpus.gloss_vocab) if corpus.gloss_vocab is not None and model_cfg.gloss_ctc_weight > 0 else 0
    model = SignToText(model_cfg, BackTranslationDims(spec.dim, len(corpus.text_vocab), gloss_classes))
    model.set_feature_statistics(*(torch.as_tensor(a) for a in feature_statistics(corpus.train)))
    model.to(device)
    optim = adam(model.parameters(), device, lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)
    schedule = PlateauSchedule(optim, "max", cfg.lr_factor, cfg.lr_patience, cfg.min_lr)
    settings = scalar_settings(cfg)

    def evaluate() -> dict[str, float]:
        scores = validate(model, corpus)
        schedule.observe(scores["bleu4"])  # the paper's plateau metric
        return scores

    tail = EpochTail(
        cfg.epochs, cfg.eval_every,
        Selection("val_selection", "max") if corpus.dev else Selection("epoch", "max"), optim, schedule,
        save=lambda path, epoch, step, record, state: save_backtranslation(
            path, model, corpus.language, spec, corpus.processor, corpus.text_vocab, corpus.gloss_vocab,
            corpus.gloss_source, epoch, step, data_version, record, settings, state),
        best_path=best_path, last_path=last_path, evaluate=evaluate if corpus.dev else None, on_epoch=on_epoch)
    resumed_from_epoch = tail.resume_saved(model, lambda p: load_backtranslation(p, device),
                                           f"the {corpus.language!r} judge")
    run_epochs(tail, model, lambda epoch: epoch_batches(corpus.train, cfg.batch_size, cfg.seed, epoch),
               lambda samples: train_step(model, collate(samples, corpus.text_vocab), optim, schedule,
                                          model_cfg.gloss_ctc_weight, cfg.precision, cfg.grad_clip,
                                          cfg.label_smoothing),
               f"backtranslation {corpus.language}", progress, stop_after_epochs)
    return tail.result(model, resumed_from_epoch)
