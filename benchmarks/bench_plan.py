"""What a user can plan with: memory and time of a few real training steps of every paper-size model on this CPU,
extrapolated to the paper's batch sizes, and the steps of one epoch on each of the papers' corpora.

**The models** are the ``paper`` preset's (``m3t.config.load_params("params.yaml", preset="paper")``), built as
their trainers build them, with the trainers' optimisers (:func:`m3t.optimizer.adam`, LR schedules) and their own
``train_step`` (forward, loss, backward, optimiser step):

===========  ============================================================================================
tokenizer    :class:`m3t.tokenizers.vae.MotionTokenizer` of the ``hand`` group (90-d SMPL-FX hands; the body
             and face groups differ only in the first and last convolution), ``tokenizer_train.window``-frame
             windows, :func:`m3t.tokenizers.train.train_step` (Eq. 6 on standardised parameters), Adam
smlm         :class:`m3t.smlm.model.SignMotionLM` at d_model 1024, 12 + 12 layers, random init (no mBART files
             here: ``pretrained_path`` ""), the text vocabulary reduced to ``SMLM_TEXT_IDS`` mBART ids (what
             ``smlm.reduce_text_vocab`` keeps on the three corpora, estimated in
             ``tests/smlm/test_smlm_reduced_vocab.py``), :func:`m3t.smlm.train.train_step` alternating a
             production and a translation batch (``translation_prob`` 0.5), AdamW
sgsa / pt    :func:`m3t.sgsa.checkpoint.build_model` on the preset's skeleton graph (``sgsa.skeleton``) with
             Phoenix14T's vocabularies, :func:`m3t.sgsa.train.train_step` (MSE + counter + gloss CTC, noise
             augmentation), Adam with the plateau schedule; ``pt`` is the same section as the Progressive
             Transformers baseline (``SGSAConfig.for_system("pt")``)
probe        :class:`m3t.slr.model.SLRProbe` at the tokenizer width on NMFs-CSL's 1,067 classes over cached
             encoder features (the frozen encoders are not trained), :func:`m3t.slr.train.train_step`, Adam
===========  ============================================================================================

Batches are random values of the shapes a corpus gives (``LENGTHS`` says which and why): the cost of a step does
not depend on the values. Each (model, batch size) runs in a **fresh interpreter** on **one thread** (``--threads``)
for a few optimiser steps (``STEPS``). One thread, because the host is shared: two threads of one process wait
for each other whenever another job takes one of the cores, and a step's time then varied several-fold from run
to run; one thread's CPU time hardly depends on the other jobs. A run records its resident memory after the
imports and after building the model and the optimiser (``rss_built_mb``, before the first step: Adam allocates
its two moment buffers at the first step), and the wall and CPU time of every step. The parent reads the child's
peak resident memory from the kernel (``ru_maxrss`` of ``os.wait4``: ``peak_rss_mb``). Per run:
``seconds_per_step`` (wall, median of the steps after the first, which also pays one-off allocations),
``cpu_seconds_per_step`` (the same of the process's CPU time), ``fastest_seconds_per_step`` (the fastest step after
the first) and the host's 1-minute load average.

**Extrapolation.** Per model, least squares ``y = a + b * batch`` of each of those over the fit's batch sizes
(``BATCHES``), evaluated at the paper's batch (the preset's ``batch_size``); one more run at the paper batch itself
checks the prediction (``check_at_paper_batch``: measured, predicted, relative error; ``--no-check`` skips it).
Steps per epoch come from the published train splits (``CORPORA``) and the trainers' own batching rules; core
hours per epoch = steps x the CPU seconds per step at the paper batch (of that run where it finished, else of the
fit; ``hours_from`` says which), on one core of this CPU in fp32, and wall hours the same with the wall seconds:
**extrapolations from this CPU**, not GPU figures. On a GPU the memory is different too: fp32 weights, gradients
and Adam's two moments take 16 bytes per parameter (``static_gpu_gb``, arithmetic, not measured) plus activations
that grow with the batch; the CPU's allocator keeps freed blocks, so ``peak_rss_mb`` is an upper bound of what a
step needs on this CPU.

    python benchmarks/bench_plan.py [--models tokenizer smlm sgsa pt probe] [--batches smlm=1,2 ...]
        [--steps probe=10 ...] [--threads 1] [--no-check] [--run-timeout 900] [--out benchmarks/results/plan.json]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from report import cpu_model, run_measured, write_and_log

MODELS = ("tokenizer", "smlm", "sgsa", "pt", "probe")
# Batch sizes of the fit and steps per run. The small models (SGSA, PT, probe: paper batch 32 / 64) are fitted up to
# 16, where the batch's share of a step stands out of this host's noise; the SMLM's odd step count gives as many
# production as translation steps after the first. One more run at the paper batch checks the extrapolation.
BATCHES = {"tokenizer": (1, 2, 4), "smlm": (1, 2, 4), "sgsa": (1, 4, 16), "pt": (1, 4, 16), "probe": (1, 4, 16)}
STEPS = {"tokenizer": 4, "smlm": 3, "sgsa": 6, "pt": 6, "probe": 6}

# Published train splits (clips) and mean clip lengths (frames) of the papers' corpora.
CORPORA = {
    # Duarte et al., "How2Sign", CVPR 2021, Tab. 2: 31,128 / 1,741 / 2,322 sentence clips; about 79 h over 35,191
    # clips at 24 fps = 194 frames per clip
    "how2sign": {"train_clips": 31128, "mean_frames": 194.0, "fps": 24.0,
                 "source": "Duarte et al. 2021 (How2Sign, CVPR), Tab. 2; ~79 h / 35,191 clips at 24 fps"},
    # Zhou et al., "Improving Sign Language Translation with Monolingual Data by Sign Back-Translation" (CSL-Daily),
    # CVPR 2021: 18,401 train clips. The mean length is an assumption (about 4 s at 30 fps): the paper's
    # duration statistics were not re-checked for this page.
    "csl_daily": {"train_clips": 18401, "mean_frames": 120.0, "fps": 30.0,
                  "source": "Zhou et al. 2021 (CSL-Daily, CVPR): train split; mean length assumed (~4 s at 30 fps)"},
    # Camgoz et al., "Neural Sign Language Translation", CVPR 2018 (RWTH-PHOENIX-Weather 2014T): 7,096 / 519 / 642
    # clips; the release's train annotations declare 827,354 frames (116.6 per clip) and 55,247 glosses (7.8 per clip)
    "phoenix14t": {"train_clips": 7096, "mean_frames": 827354 / 7096, "fps": 25.0,
                   "source": "Camgoz et al. 2018 (Phoenix14T, CVPR); 827,354 train frames in the release's "
                             "annotations"},
    # Hu et al., "Global-local Enhancement Network for NMFs-aware Sign Language Recognition", ACM TOMM 2021:
    # 32,010 videos of 1,067 isolated signs. Its train / test split was not confirmed for this page, so an epoch
    # here is all 32,010 clips (an upper bound of the train split). The probe's input length is an assumption.
    "nmfs_csl": {"train_clips": 32010, "mean_frames": 64.0, "fps": 30.0, "classes": 1067,
                 "source": "Hu et al. 2021 (NMFs-CSL, TOMM): 32,010 videos, 1,067 signs; all clips counted (train "
                           "split not confirmed); 64 frames after trimming assumed"},
}
JOINT = ("how2sign", "csl_daily", "phoenix14t")  # the paper preset's data.train_corpora, trained jointly
MODEL_CORPORA = {"tokenizer": JOINT, "smlm": JOINT, "sgsa": JOINT, "pt": JOINT, "probe": ("nmfs_csl",)}

# Sequence lengths of one training example (the batch is padded to them).
LENGTHS = {
    # How2Sign's mean clip: 194 frames = 49 motion steps at 4 frames per step; text: 24 mBART pieces (an assumption,
    # not counted on How2Sign's text)
    "smlm": {"motion_steps": math.ceil(194 / 4), "text_tokens": 24},
    # Phoenix14T's mean clip (116.6 frames -> 117), 8 glosses (55,247 / 7,096), text: the language token + 14 words
    # (an assumption)
    "sgsa": {"frames": 117, "text_tokens": 15, "glosses": 8},
    # NMFs-CSL: 64 frames after trimming (an assumption) = 16 token steps of each of the 4 streams
    "probe": {"steps": 16},
}
# Camgoz et al. 2018: Phoenix14T's German words and glosses (the SGSA paper trains on Phoenix14T alone; a joint run
# of the three corpora has a larger text vocabulary, so more embedding rows)
PHOENIX_TEXT_VOCAB, PHOENIX_GLOSSES = 2887, 1066
SMLM_TEXT_IDS = 20_000  # mBART ids the three corpora's train text uses (tests/smlm/test_smlm_reduced_vocab.py)
SMLM_LANGUAGES = ("ASL", "CSL", "DGS")
BYTES_PER_PARAM_FP32_ADAM = 16  # weights + gradients + Adam's two moments, fp32


# ------------------------------------------------------------------------------------------ the child: one run
def rss_mb() -> float:
    """This process's resident memory now (MB)."""
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def paper_params():
    from m3t.config import load_params

    return load_params(ROOT / "params.yaml", preset="paper")


def build_tokenizer(params, batch: int):
    """The hand group's tokenizer, Adam and the warm-up + cosine schedule, as :func:`train_tokenizer` builds them."""
    import torch

    from m3t.body.smplfx import smplfx_layout
    from m3t.optimizer import adam, warmup_cosine
    from m3t.tokenizers.data import check_layout
    from m3t.tokenizers.train import train_step
    from m3t.tokenizers.vae import MotionTokenizer

    cfg = params.tokenizer_train
    dim = check_layout(smplfx_layout(), "hand")
    model = MotionTokenizer(params.tokenizer.vae_config("hand", dim))
    model.set_normalisation(torch.zeros(dim), torch.ones(dim))
    optim = adam(model.parameters(), "cpu", lr=cfg.lr)
    scheduler = warmup_cosine(optim, cfg.epochs, 1000, cfg.warmup_epochs, "epochs", cfg.min_lr)
    x, mask = torch.randn(batch, cfg.window, dim), torch.ones(batch, cfg.window, dtype=torch.bool)
    return model, lambda step: train_step(model, (x, mask), optim, scheduler, cfg.precision)


def smlm_dims(params, text_ids: int):
    """The SMLM's sizes on the three corpora's languages (:meth:`SMLMDims.from_vocabulary` of such a vocabulary):
    text ids (pad 1, eos 2 as in mbart-large-cc25), 5 prompts per language, one id per FSQ code per stream."""
    from m3t.smlm.model import SMLMDims
    from m3t.smlm.vocab import MOTION_STREAMS, PROMPT_MODALITIES

    tok = params.tokenizer
    codes = {"body": math.prod(tok.levels_body), "left_hand": math.prod(tok.levels_hand),
             "right_hand": math.prod(tok.levels_hand), "face": math.prod(tok.levels_face)}
    vocab = text_ids + len(SMLM_LANGUAGES) * len(PROMPT_MODALITIES) + sum(codes.values())
    return SMLMDims(vocab, {"text": text_ids, **{s: codes[s] + 1 for s in MOTION_STREAMS}}, 1, 2), codes


def build_smlm(params, batch: int):
    """The SMLM, AdamW and its schedule as :func:`train_smlm` builds them; a production and a translation batch of
    How2Sign's mean lengths (:mod:`m3t.smlm.data` layouts), the step alternating between them."""
    import dataclasses

    import torch

    from m3t.optimizer import adam, warmup_cosine
    from m3t.smlm.data import ProductionBatch, TranslationBatch
    from m3t.smlm.model import SignMotionLM
    from m3t.smlm.train import train_step
    from m3t.smlm.vocab import MOTION_STREAMS

    cfg, train = dataclasses.replace(params.smlm, pretrained_path="", text_model_path=""), params.smlm_train
    dims, codes = smlm_dims(params, SMLM_TEXT_IDS)
    model = SignMotionLM(cfg, dims)
    optim = adam(model.parameters(), "cpu", decoupled=True, lr=train.lr, weight_decay=train.weight_decay)
    scheduler = warmup_cosine(optim, train.epochs, 1000, train.warmup_steps, "steps", train.min_lr)
    u, k = LENGTHS["smlm"]["motion_steps"], LENGTHS["smlm"]["text_tokens"]
    first_motion = SMLM_TEXT_IDS + len(SMLM_LANGUAGES) * 5
    motion = torch.randint(first_motion, dims.vocab_size, (batch, u + 2, len(MOTION_STREAMS)))
    local = torch.stack([torch.randint(0, codes[s] + 1, (batch, u + 1)) for s in MOTION_STREAMS], dim=-1)
    text = torch.randint(4, SMLM_TEXT_IDS, (batch, k + 2))
    ones = torch.ones
    production = ProductionBatch(text, ones(batch, k + 2, dtype=torch.long), motion[:, : u + 1],
                                 ones(batch, u + 1, dtype=torch.long), local)
    translation = TranslationBatch(motion, ones(batch, u + 2, dtype=torch.long), text[:, : k + 1],
                                   ones(batch, k + 1, dtype=torch.long), text[:, 1:])
    return model, lambda step: train_step(model, translation if step % 2 else production, optim, scheduler,
                                          train.precision, train.grad_clip, train.label_smoothing)


def build_sgsa(params, batch: int, system: str):
    """SGSA (or its PT baseline), Adam and the plateau schedule as :func:`train_sgsa` builds them; a batch of
    Phoenix14T's mean lengths with noise augmentation on (as from the second epoch)."""
    import torch

    from m3t.body.skeleton import graph_for
    from m3t.optimizer import PlateauSchedule, adam
    from m3t.sgsa.checkpoint import build_model
    from m3t.sgsa.data import Batch
    from m3t.sgsa.train import train_step
    from m3t.vocabulary import gloss_vocabulary, text_vocabulary

    cfg, train = params.sgsa.for_system(system), params.sgsa_train
    graph = graph_for(cfg.skeleton, cfg.face_points)
    text_vocab = text_vocabulary([[f"w{i}" for i in range(PHOENIX_TEXT_VOCAB)]])
    gloss_vocab = gloss_vocabulary([[f"G{i}" for i in range(PHOENIX_GLOSSES)]])
    model = build_model(cfg, graph, text_vocab, gloss_vocab)
    optim = adam(model.parameters(), "cpu", lr=train.lr)
    schedule = PlateauSchedule(optim, "min", train.lr_factor, train.lr_patience, train.min_lr)
    n = LENGTHS["sgsa"]
    width = graph.width + 1
    target = torch.randn(batch, n["frames"], width)
    frames_in = torch.cat([torch.zeros(batch, 1, width), target[:, :-1]], dim=1)
    data = Batch(torch.randint(4, len(text_vocab), (batch, n["text_tokens"])),
                 torch.ones(batch, n["text_tokens"], dtype=torch.bool), frames_in, target,
                 torch.ones(batch, n["frames"], dtype=torch.bool),
                 torch.randint(2, len(gloss_vocab), (batch, n["glosses"])), torch.full((batch,), n["glosses"]))
    noise = torch.full((width,), 0.1)
    return model, lambda step: train_step(model, data, optim, schedule, cfg.gloss_weight, noise,
                                          train.counter_weight, train.grad_clip)[0]


def build_probe(params, batch: int):
    """The recognition probe, Adam and its schedule as :func:`train_slr` builds them; cached features of
    ``LENGTHS["probe"]`` token steps per stream."""
    import torch

    from m3t.optimizer import adam, warmup_cosine
    from m3t.slr.features import variant_streams
    from m3t.slr.model import ProbeDims, SLRProbe
    from m3t.slr.train import Batch, train_step

    train, streams = params.slr_train, variant_streams("full")
    dims = ProbeDims(params.tokenizer.width, CORPORA["nmfs_csl"]["classes"], streams)
    model = SLRProbe(params.slr, dims)
    optim = adam(model.parameters(), "cpu", lr=train.lr, weight_decay=train.weight_decay)
    scheduler = warmup_cosine(optim, train.epochs, 1000, train.warmup_epochs, "epochs", train.min_lr)
    steps = LENGTHS["probe"]["steps"]
    features = {s: torch.randn(batch, steps, dims.width) for s in streams}
    data = Batch(features, torch.ones(batch, steps, dtype=torch.bool), torch.randint(0, dims.num_classes, (batch,)))
    return model, lambda step: train_step(model, data, optim, scheduler, train.precision, train.grad_clip,
                                          train.label_smoothing)


def child(model_name: str, batch: int, steps: int, threads: int, result: Path) -> None:
    """One run on ``threads`` threads (0: torch's default): build, ``steps`` training steps, the figures to
    ``result`` (JSON)."""
    import torch

    if threads:
        torch.set_num_threads(threads)

    params = paper_params()
    rss_start = rss_mb()  # torch and the config imported, nothing built
    torch.manual_seed(0)
    builders = {"tokenizer": build_tokenizer, "smlm": build_smlm, "probe": build_probe,
                "sgsa": lambda p, b: build_sgsa(p, b, "sgsa"), "pt": lambda p, b: build_sgsa(p, b, "pt")}
    started = time.perf_counter()
    model, step = builders[model_name](params, batch)
    model.train()
    build_s = time.perf_counter() - started
    rss_built = rss_mb()
    seconds, cpu_seconds = [], []
    for i in range(steps):
        started, cpu_started = time.perf_counter(), time.process_time()
        step(i)
        seconds.append(time.perf_counter() - started)
        cpu_seconds.append(time.process_time() - cpu_started)  # every thread of this process

    def after_first(values: list[float]) -> float:
        return round(statistics.median(values[1:] if len(values) > 1 else values), 4)

    result.write_text(json.dumps({
        "parameters": sum(p.numel() for p in model.parameters()), "threads": torch.get_num_threads(),
        "rss_start_mb": round(rss_start, 1), "rss_built_mb": round(rss_built, 1), "build_s": round(build_s, 2),
        "rss_after_steps_mb": round(rss_mb(), 1), "step_seconds": [round(s, 4) for s in seconds],
        "step_cpu_seconds": [round(s, 4) for s in cpu_seconds], "seconds_per_step": after_first(seconds),
        "cpu_seconds_per_step": after_first(cpu_seconds),
        "fastest_seconds_per_step": round(min(seconds[1:] or seconds), 4),
        "load_average_1min": round(os.getloadavg()[0], 2)}))


# ------------------------------------------------------------------------------------------ the parent
def run(model_name: str, batch: int, steps: int, threads: int, timeout: float, work: Path) -> dict:
    """One (model, batch) in a fresh interpreter: its figures and the kernel's peak RSS of the child."""
    result = work / f"{model_name}-{batch}.json"
    log = work / f"{model_name}-{batch}.log"
    command = [sys.executable, __file__, "--child", model_name, "--batch", str(batch), "--steps", str(steps),
               "--threads", str(threads), "--result", str(result)]
    exit_status, peak_mb, _, _ = run_measured(command, log, timeout, ROOT, poll=0.2)
    row = {"batch": batch, "peak_rss_mb": round(peak_mb, 1)}
    if not result.exists():
        return {**row, "stopped": True, "exit_status": exit_status, "log_tail": log.read_text().splitlines()[-15:]}
    return {**row, **json.loads(result.read_text())}


def linear_fit(xs: list[float], ys: list[float]) -> dict | None:
    """Least squares ``y = a + b x``; None with fewer than two distinct x."""
    if len(set(xs)) < 2:
        return None
    b, a = np.polyfit(np.asarray(xs, float), np.asarray(ys, float), 1)
    residual = float(np.max(np.abs(a + b * np.asarray(xs, float) - np.asarray(ys, float))))
    return {"a": round(float(a), 4), "b": round(float(b), 4), "max_abs_residual": round(residual, 4)}


def at(fit: dict | None, x: float) -> float | None:
    return None if fit is None else fit["a"] + fit["b"] * x


TRAIN_SECTION = {"tokenizer": "tokenizer_train", "smlm": "smlm_train", "sgsa": "sgsa_train", "pt": "sgsa_train",
                 "probe": "slr_train"}


def paper_batch(params, model_name: str) -> int:
    return getattr(params, TRAIN_SECTION[model_name]).batch_size


def epoch_items(params, model_name: str, corpus: str) -> dict:
    """What one epoch of ``model_name`` passes on ``corpus``'s train split: clips, or (tokenizers) windows."""
    from m3t.tokenizers.data import GROUPS

    c, cfg = CORPORA[corpus], params.tokenizer_train
    if model_name != "tokenizer":
        return {"items": c["train_clips"], "unit": "clips"}
    # windows_per_clip 0 (the paper preset): ceil(T / window) windows per sequence (m3t.tokenizers.data.WindowSampler),
    # here with the corpus's mean T; the hand group has two sequences per clip (right hand, mirrored left hand). The
    # paper preset's face group also trains on MEAD (tokenizer_train.extra_face_shards): not counted here
    per_sequence = cfg.windows_per_clip or math.ceil(c["mean_frames"] / cfg.window)
    groups = {g: c["train_clips"] * len(streams) * per_sequence for g, streams in GROUPS.items()}
    return {"items": groups["hand"], "unit": "windows (hand group)", "windows_per_sequence": per_sequence,
            "windows_per_group": groups}


def parameter_counts(params) -> dict:
    """Parameters of the variants the runs stand for, built on the meta device (no memory): each tokenizer group,
    and the SMLM with the reduced mBART vocabulary (what the runs build) and with the preset's ``text_vocab_size``
    (the text vocabulary a run without the mBART files trains on the corpus text, at most that many ids)."""
    import dataclasses

    import torch

    from m3t.body.smplfx import smplfx_layout
    from m3t.smlm.model import SignMotionLM
    from m3t.tokenizers.data import GROUPS, check_layout
    from m3t.tokenizers.vae import MotionTokenizer

    smlm_cfg = dataclasses.replace(params.smlm, pretrained_path="", text_model_path="")
    with torch.device("meta"):
        tokenizers = {g: MotionTokenizer(params.tokenizer.vae_config(g, check_layout(smplfx_layout(), g)))
                      for g in GROUPS}
        smlm = {ids: SignMotionLM(smlm_cfg, smlm_dims(params, ids)[0])
                for ids in (SMLM_TEXT_IDS, params.smlm.text_vocab_size)}

    def count(module: torch.nn.Module) -> int:
        return sum(p.numel() for p in module.parameters())

    return {"tokenizer_groups": {g: count(m) for g, m in tokenizers.items()},
            "smlm_by_text_ids": {str(ids): count(m) for ids, m in smlm.items()}}


def round_or_none(value: float | None, digits: int = 2) -> float | None:
    return None if value is None else round(value, digits)


def per_epoch(steps: int, seconds: float | None) -> float | None:
    """Hours of ``steps`` steps of ``seconds`` each (None without a time)."""
    return None if seconds is None else round(steps * seconds / 3600, 1)


FIGURES = ("peak_rss_mb", "seconds_per_step", "cpu_seconds_per_step", "fastest_seconds_per_step")


def check(fits: dict, batch: int, row: dict | None) -> dict | None:
    """The run at the paper batch beside what the fits predicted for it (relative error of the prediction)."""
    if row is None:
        return None
    if row.get("stopped"):
        return {"batch": batch, "stopped": True, "peak_rss_mb": row["peak_rss_mb"]}
    out = {"batch": batch}
    for key in FIGURES:
        predicted = at(fits[key], batch)
        out[key] = {"measured": row[key], "predicted": None if predicted is None else round(predicted, 2),
                    "prediction_error": None if predicted is None else round(predicted / row[key] - 1, 3)}
    return out


def plan(params, measured: dict[str, list[dict]], checks: dict[str, dict]) -> dict:
    """Per model: the fits, their values at the paper batch (and the run there, where one was made), steps and
    hours per epoch per corpus (from the run at the paper batch where it finished, else from the fits)."""
    out = {}
    for name, rows in measured.items():
        ok = [r for r in rows if not r.get("stopped")]
        batch = paper_batch(params, name)
        xs = [r["batch"] for r in ok]
        fits = {key: linear_fit(xs, [r[key] for r in ok]) for key in FIGURES}
        memory, wall, cpu, fastest = (at(fits[k], batch) for k in FIGURES)
        at_paper = checks.get(name)
        if at_paper is not None and not at_paper.get("stopped"):
            wall, cpu = at_paper["seconds_per_step"], at_paper["cpu_seconds_per_step"]
        parameters = ok[0]["parameters"] if ok else None
        epochs = {}
        for corpus in MODEL_CORPORA[name]:
            items = epoch_items(params, name, corpus)
            steps = -(-items["items"] // batch)
            epochs[corpus] = {**items, "steps_per_epoch": steps,
                              "wall_hours_per_epoch_extrapolated": per_epoch(steps, wall),
                              "core_hours_per_epoch_extrapolated": per_epoch(steps, cpu)}
            if "windows_per_group" in items:  # three tokenizers, each its own epoch: the stage's steps
                all_groups = sum(-(-w // batch) for w in items["windows_per_group"].values())
                epochs[corpus].update(steps_per_epoch_all_groups=all_groups,
                                      core_hours_per_epoch_all_groups_extrapolated=per_epoch(all_groups, cpu))
        if len(MODEL_CORPORA[name]) > 1:  # the paper preset trains on the three corpora at once: one epoch passes all
            steps = sum(e["steps_per_epoch"] for e in epochs.values())
            epochs["joint"] = {"steps_per_epoch": steps, "wall_hours_per_epoch_extrapolated": per_epoch(steps, wall),
                               "core_hours_per_epoch_extrapolated": per_epoch(steps, cpu)}
            if name == "tokenizer":
                all_groups = sum(e["steps_per_epoch_all_groups"] for e in epochs.values() if e is not epochs["joint"])
                epochs["joint"].update(steps_per_epoch_all_groups=all_groups,
                                       core_hours_per_epoch_all_groups_extrapolated=per_epoch(all_groups, cpu))
        # the whole training the preset asks for: its epochs over what the model trains on (the tokenizers: all
        # three groups)
        whole = epochs["joint" if "joint" in epochs else MODEL_CORPORA[name][0]]
        preset_epochs = getattr(params, TRAIN_SECTION[name]).epochs
        core_hours = whole.get("core_hours_per_epoch_all_groups_extrapolated",
                               whole["core_hours_per_epoch_extrapolated"])
        out[name] = {
            "preset_epochs": preset_epochs,
            "core_hours_preset_training_extrapolated": round_or_none(None if core_hours is None
                                                                     else core_hours * preset_epochs, 0),
            "parameters": parameters, "paper_batch": batch, "measured_batches": xs, "fits": fits,
            "peak_rss_mb_at_paper_batch_extrapolated": None if memory is None else round(memory),
            "seconds_per_step_at_paper_batch_extrapolated": round_or_none(at(fits["seconds_per_step"], batch)),
            "cpu_seconds_per_step_at_paper_batch_extrapolated": round_or_none(at(fits["cpu_seconds_per_step"], batch)),
            "fastest_seconds_per_step_at_paper_batch_extrapolated": round_or_none(fastest),
            "check_at_paper_batch": check(fits, batch, at_paper),
            "hours_from": "the run at the paper batch" if at_paper is not None and not at_paper.get("stopped")
                          else "the fits",
            "static_gpu_gb": None if parameters is None else round(parameters * BYTES_PER_PARAM_FP32_ADAM / 1e9, 2),
            "epochs": epochs}
    return out


def host() -> dict:
    """The CPU model (``/proc/cpuinfo``), cores, Python and torch of this machine."""
    import torch

    return {"cpu": cpu_model(), "cores": os.cpu_count(), "memory_gb": round(os.sysconf("SC_PHYS_PAGES") * os.sysconf(
        "SC_PAGE_SIZE") / 2**30, 1), "python": platform.python_version(), "torch": torch.__version__,
            "torch_threads": torch.get_num_threads()}


def overrides(items: list[str]) -> dict[str, str]:
    """``["smlm=1,2", ...]`` -> ``{"smlm": "1,2"}``, every name a model's."""
    out = dict(item.split("=", 1) for item in items)
    unknown = sorted(set(out) - set(MODELS))
    if unknown:
        sys.exit(f"unknown model(s) {unknown}; allowed: {', '.join(MODELS)}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", nargs="+", choices=MODELS, default=list(MODELS))
    ap.add_argument("--batches", nargs="*", default=[], metavar="MODEL=B1,B2,..",
                    help=f"batch sizes of a model instead of {BATCHES}")
    ap.add_argument("--steps", nargs="*", default=[], metavar="MODEL=N", help=f"steps per run instead of {STEPS}")
    ap.add_argument("--no-check", action="store_true", help="no run at the paper batch (the fits only)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads of each run (0: torch's default)")
    ap.add_argument("--run-timeout", type=float, default=900.0)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "plan.json"))
    ap.add_argument("--child", choices=MODELS, help=argparse.SUPPRESS)
    ap.add_argument("--batch", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--result", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, args.batch, int(args.steps[0]), args.threads, Path(args.result))
        return
    batches = {**BATCHES, **{m: tuple(int(b) for b in v.split(",")) for m, v in overrides(args.batches).items()}}
    steps_per_run = {**STEPS, **{m: int(v) for m, v in overrides(args.steps).items()}}
    params = paper_params()
    measured: dict[str, list[dict]] = {}
    checks: dict[str, dict] = {}

    def measure(name: str, batch: int, label: str, work: Path) -> dict:
        row = run(name, batch, steps_per_run[name], args.threads, args.run_timeout, work)
        print(f"[{time.strftime('%H:%M:%S')}] {name} batch {batch} ({label}): " + json.dumps(
            {k: row.get(k) for k in ("peak_rss_mb", "rss_built_mb", *FIGURES[1:], "load_average_1min", "stopped")}),
            flush=True)
        return row

    with tempfile.TemporaryDirectory(prefix="bench-plan-") as tmp:
        for name in args.models:
            measured[name] = [measure(name, batch, "fit", Path(tmp)) for batch in batches[name]]
            if not args.no_check and paper_batch(params, name) not in batches[name]:
                checks[name] = measure(name, paper_batch(params, name), "paper batch", Path(tmp))
    models = plan(params, measured, checks)
    result = {
        "host": host(), "date": time.strftime("%Y-%m-%d"), "preset": "paper",
        "steps_per_run": {m: steps_per_run[m] for m in args.models}, "threads_per_run": args.threads,
        "method": ("fresh interpreter per (model, batch) on --threads threads; peak RSS = ru_maxrss of the child "
                   "(os.wait4); seconds per step = median of the steps after the first (wall and CPU time); "
                   "least-squares a + b * batch evaluated at the preset's batch; hours per epoch = steps per epoch x "
                   "that: an extrapolation from this CPU (fp32)"),
        "smlm_text_ids": SMLM_TEXT_IDS, "parameter_counts": parameter_counts(params), "lengths": LENGTHS,
        "corpora": CORPORA,
        "phoenix_vocabulary": {"text": PHOENIX_TEXT_VOCAB, "glosses": PHOENIX_GLOSSES},
        "models": models, "runs": measured, "paper_batch_runs": checks,
        **{f"{m}/peak_rss_mb_at_paper_batch_fit": v["peak_rss_mb_at_paper_batch_extrapolated"]
           for m, v in models.items() if v["peak_rss_mb_at_paper_batch_extrapolated"] is not None},
        **{f"{m}/{key}_at_paper_batch_run": row[key] for m, row in checks.items() if not row.get("stopped")
           for key in ("peak_rss_mb", "cpu_seconds_per_step")}}
    write_and_log(result, args.out, "benchmark-plan")


if __name__ == "__main__":
    main()
