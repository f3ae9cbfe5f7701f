"""The pipeline after fitting at How2Sign's size: peak memory, throughput and wall time of every stage at about
1,000, 5,000 and 31,000 clips, in one run.

**The corpus.** How2Sign's sentence clips: 35,191 of them (31,128 train / 1,741 dev / 2,322 test, Duarte et al.,
CVPR 2021, Tab. 2), about 79 hours, i.e. a mean of 8.1 s = 194 frames at its 24 fps. Each arm draws clip lengths
from a log-normal of that mean (sigma 0.6, an assumption: the paper gives no spread; 24 to 1,200 frames) and
splits its clips in How2Sign's proportions, so the largest arm (31,000 clips) has 2,045 test clips. The clips
**enter without fitting**, as the generator's ground-truth Anny parameters written as shards (the embedded body
model; SMPL-FX would need the licensed files): a pool of sentences of the embedded synthetic corpus's design
(its lexicon, three languages, its signers) is synthesised once, and a clip is a run of pool sentences of one
language and signer until its drawn length is reached (each sentence starts and ends at rest, so the run is
continuous); its text is their texts joined. The pool repeats, the clips do not (own ids, own lengths, own order).

**The stages**, each in a fresh interpreter whose peak resident memory is the kernel's ``ru_maxrss`` of that
process (``os.wait4``), on the arm's own folders (the pipeline's are not touched):

==================  ========================================================================================
import              the ground-truth parameters -> ``train`` / ``dev`` / ``test`` shards (the bench's own writer,
                    :class:`m3t.shards.io.ShardWriter`; what fit-corpus's import writes)
tokenize            :func:`m3t.tokenizers.tokenize.run_tokenize` with the embedded pipeline's tokenizers
train_smlm          the SMLM trained for ``--steps`` optimiser steps (the trainer's own batches and step,
                    :func:`m3t.smlm.train.epoch_batches` / :func:`~m3t.smlm.train.train_step`) on the whole
                    train split's tokens, vocabulary trained on its text, then saved as ``smlm.pt``
generate            :func:`m3t.smlm.generate_run.run_generate` on the test split (no renders, no ``.pose`` export)
evaluate            :func:`m3t.smlm.evaluate_run.run_evaluate`: DTW scoring and the back-translation judges (the
                    embedded pipeline's) of every generated test clip
probe_features      the recognition probe's input (:func:`m3t.slr.features.iter_examples`: trimmed, encoded by
                    the frozen tokenizer encoders) of every test clip, a batch at a time as evaluate-slr
                    encodes them, each clip labelled by its first sign (the probe's corpus is of isolated
                    signs; the features are computed alike)
==================  ========================================================================================

Per stage and arm: ``wall_s``, ``peak_rss_mb``, ``clips`` / ``frames`` processed and their rates. The summary
compares the largest arm with the smallest: the goal is peak RSS at most 1.5x and under 16 GB, throughput within
20 %. A stage that runs past ``--stage-timeout`` is killed and recorded as stopped (what it took, where it stopped).

    python benchmarks/bench_scale.py [--arms 1000 5000 31000] [--steps 200] [--stage-timeout 7200]
        [--work .cache/bench_scale] [--keep] [--out benchmarks/results/scale.json]

Stages can be run again on arms kept by an earlier run (``--keep``), e.g. after a change to them:
``--reuse --stages generate evaluate --merge <earlier result>`` keeps the arms' folders, runs only those stages
and takes the other rows from the earlier result (``reran`` in the output says which rows are new).

Needs the embedded pipeline's tokenizers and back-translation judges (``dvc repro train-tokenizers
train-backtranslation``). Disk: about 1.2 KB per frame of shards (7 GB at 31,000 clips); an arm's folders are
removed after it unless ``--keep``.
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import os
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from report import cpu_model, run_measured, write_and_log

STAGES = ("import", "tokenize", "train_smlm", "generate", "evaluate", "probe_features")
HOW2SIGN_SPLITS = {"train": 31128, "dev": 1741, "test": 2322}  # clips per split, Duarte et al. 2021
HOW2SIGN_MEAN_FRAMES = 194.0  # ~79 h over 35,191 clips at 24 fps
LENGTH_SIGMA, MIN_FRAMES, MAX_FRAMES = 0.6, 24, 1200
POOL_SENTENCES = 240  # per language
CORPUS = "scale"
GOAL_RSS_RATIO, GOAL_RSS_MB, GOAL_RATE_RATIO = 1.5, 16 * 1024, 0.8


# ------------------------------------------------------------------------------------------ the arm's folders
def data_config(arm_dir: Path):
    from m3t.shards.folders import DataConfig

    return DataConfig(train_corpora=(CORPUS,), shards_root=str(arm_dir / "shards"), tokens_root=str(arm_dir / "tokens"),
                      models_dir=str(arm_dir / "models"), generated_dir=str(arm_dir / "generated"),
                      metrics_dir=str(arm_dir / "metrics"))


def prepare_arm(arm_dir: Path, models: Path) -> None:
    """The arm's models folder: links to the pipeline's tokenizers and judges (read only)."""
    (arm_dir / "models" / "smlm").mkdir(parents=True, exist_ok=True)
    for name in ("tokenizers", "backtranslation"):
        source = models / name
        if not (source / "languages.json").exists() and not (source / "body.pt").exists():
            raise FileNotFoundError(f"{source} has no trained models; run `dvc repro train-tokenizers "
                                    f"train-backtranslation` first")
        link = arm_dir / "models" / name
        if not link.exists():
            link.symlink_to(source.resolve(), target_is_directory=True)


# ------------------------------------------------------------------------------------------ corpus
def clip_lengths(n: int, seed: int) -> np.ndarray:
    """(n,) frames per clip: log-normal with How2Sign's mean, clipped to [MIN_FRAMES, MAX_FRAMES]."""
    mu = np.log(HOW2SIGN_MEAN_FRAMES) - LENGTH_SIGMA ** 2 / 2
    lengths = np.random.default_rng([seed, 1]).lognormal(mu, LENGTH_SIGMA, n)
    return np.clip(np.round(lengths), MIN_FRAMES, MAX_FRAMES).astype(np.int64)


def split_counts(n: int) -> dict[str, int]:
    total = sum(HOW2SIGN_SPLITS.values())
    dev, test = (round(n * HOW2SIGN_SPLITS[s] / total) for s in ("dev", "test"))
    return {"train": n - dev - test, "dev": dev, "test": test}


def sentence_pool(params, seed: int) -> list[dict]:
    """Synthesised sentences of the embedded corpus's design: params, text, language, signer, first sign."""
    from m3t.body.factory import load_body_model
    from m3t.corpora.synthetic import _performance, _signers
    from m3t.corpora.synthetic_calibration import calibrate
    from m3t.corpora.synthetic_lexicon import build_lexicon, make_sentence
    from m3t.corpora.synthetic_motion import Synthesiser

    cfg = params.synthetic_corpus
    body = load_body_model(params.body)
    rng = np.random.default_rng([seed, 2])
    lexicon = build_lexicon(cfg.num_signs, cfg.confusing_pairs, np.random.default_rng(cfg.seed))
    by_gloss = {s.gloss: s for s in lexicon}
    signers = _signers(cfg, np.random.default_rng([seed, 3]))
    synth = Synthesiser(body, calibrate(body), cfg)
    pool = []
    for language in cfg.languages:
        for _ in range(POOL_SENTENCES):
            text, glosses = make_sentence(lexicon, language, int(rng.integers(cfg.min_glosses, cfg.max_glosses + 1)), rng)
            signer = signers[int(rng.integers(len(signers)))]
            motion = synth.synthesise([by_gloss[g] for g in glosses], _performance(signer, rng, cfg.performance_jitter))
            pool.append({"params": motion, "text": text, "language": language, "signer": signer,
                         "gloss": " ".join(glosses)})
    return pool


def write_corpus(arm_dir: Path, clips: int, seed: int) -> dict:
    """The arm's shards, written split by split in row groups (never the whole corpus in memory)."""
    from m3t.config import load_params
    from m3t.corpora.clip import Clip
    from m3t.shards.io import ShardWriter
    from m3t.shards.schema import FittedClip

    params = load_params(ROOT / "params.yaml")
    pool = sentence_pool(params, seed)
    layout_source = ROOT / params.data.shards_root / params.data.train_corpora[0] / "train.parquet"
    from m3t.shards.io import shard_layout

    layout = shard_layout(layout_source)
    lengths = clip_lengths(clips, seed)
    rng = np.random.default_rng([seed, 4])
    languages = sorted({p["language"] for p in pool})
    by_language = {lang: [p for p in pool if p["language"] == lang] for lang in languages}
    out = arm_dir / "shards" / CORPUS
    out.mkdir(parents=True, exist_ok=True)
    index, frames_total = 0, 0
    for split, count in split_counts(clips).items():
        with ShardWriter(out / f"{split}.parquet", layout) as writer:
            batch = []
            for _ in range(count):
                target = int(lengths[index])
                language = languages[int(rng.integers(len(languages)))]
                choices = by_language[language]
                first = choices[int(rng.integers(len(choices)))]
                pieces = [first]
                while sum(len(p["params"]["face"]) for p in pieces) < target:
                    same = [p for p in choices if p["signer"].id == first["signer"].id]
                    pieces.append(same[int(rng.integers(len(same)))])
                motion = {k: np.concatenate([p["params"][k] for p in pieces])[:target] for k in layout.names}
                joiner = "" if language == "CSL-SYN" else ". "
                clip = Clip(id=f"scale-{index:06d}", corpus=CORPUS, split=split, language=language,
                            signer=first["signer"].id, text=joiner.join(p["text"] for p in pieces),
                            gloss=" ".join(p["gloss"] for p in pieces), media="", fps=params.synthetic_corpus.fps,
                            extra=(("kind", "sentence"),))
                batch.append(FittedClip(clip=clip, key=clip.id, params=motion,
                                        identity=first["signer"].identity.astype(np.float32), camera={},
                                        metrics={}, body_model=params.body.model))
                index += 1
                frames_total += target
                if len(batch) == 256:
                    writer.write(batch)
                    batch = []
            if batch:
                writer.write(batch)
    return {"clips": clips, "frames": frames_total, "splits": split_counts(clips)}


# ------------------------------------------------------------------------------------------ stages (child side)
def shard_frames(data, split: str) -> int:
    """Frames of a split's shard, from its ``num_frames`` column alone."""
    import pyarrow.parquet as pq

    return sum(int(pq.read_table(d / f"{split}.parquet", columns=["num_frames"]).column(0).to_numpy().sum())
               for d in data.shards_dirs)


def stage_import(arm_dir: Path, args) -> dict:
    return write_corpus(arm_dir, args.clips, args.seed)


def stage_tokenize(arm_dir: Path, args) -> dict:
    from m3t.tokenizers.tokenize import run_tokenize

    data = data_config(arm_dir)
    summary = run_tokenize(data)[CORPUS]
    clips = sum(int(summary[f"{s}_clips"]) for s in HOW2SIGN_SPLITS)
    return {"clips": clips, "frames": sum(shard_frames(data, s) for s in HOW2SIGN_SPLITS),
            "rejected": int(summary["rejected"])}


def stage_train_smlm(arm_dir: Path, args) -> dict:
    import torch

    from m3t.config import load_params
    from m3t.optimizer import adam, warmup_cosine
    from m3t.smlm.checkpoint import save_smlm
    from m3t.smlm.model import SignMotionLM, SMLMDims
    from m3t.smlm.pipeline import load_tokens, split_examples, vocabulary_for
    from m3t.smlm.train import epoch_batches, train_step

    params = load_params(ROOT / "params.yaml")
    model_cfg, cfg = params.smlm, params.smlm_train
    data = data_config(arm_dir)
    shards = load_tokens(data, "train")
    vocab = vocabulary_for(model_cfg, shards)
    skipped: list[dict] = []
    train = split_examples(shards, vocab, model_cfg, skipped)
    torch.manual_seed(cfg.seed)
    model = SignMotionLM(model_cfg, SMLMDims.from_vocabulary(vocab))
    optim = adam(model.parameters(), "cpu", decoupled=True, lr=cfg.lr, weight_decay=cfg.weight_decay)
    scheduler = warmup_cosine(optim, 1, args.steps, cfg.warmup_steps, "steps", cfg.min_lr)
    steps, epoch, started = 0, 0, time.perf_counter()
    model.train()
    while steps < args.steps:
        for batch in epoch_batches(train, vocab, cfg, epoch):
            train_step(model, batch, optim, scheduler, cfg.precision, cfg.grad_clip, cfg.label_smoothing)
            steps += 1
            if steps == args.steps:
                break
        epoch += 1
    step_s = time.perf_counter() - started
    save_smlm(data.smlm_dir / "smlm.pt", model, vocab, epoch, steps, "bench-scale", {},
              dataclasses.asdict(cfg))
    return {"clips": steps * cfg.batch_size, "steps": steps, "train_examples": len(train),
            "skipped": len(skipped), "steps_per_s": steps / step_s, "step_seconds": step_s}


def _generate_cfg():
    from m3t.smlm.config import GenerateConfig

    return GenerateConfig(split="test", render_clips=0, export_pose=False)


def stage_generate(arm_dir: Path, args) -> dict:
    from m3t.body.factory import load_body_model
    from m3t.config import load_params
    from m3t.shards.tokens import read_token_shard
    from m3t.smlm.generate_run import run_generate

    data = data_config(arm_dir)
    summary = run_generate(_generate_cfg(), data, load_body_model(load_params(ROOT / "params.yaml").body),
                           progress=False)
    frames = int(sum(c.num_frames for c in read_token_shard(data.generated / "generated.parquet").clips))
    return {"clips": int(summary["clips"]), "frames": frames, "stopped_rate": summary["stopped_rate"]}


def stage_evaluate(arm_dir: Path, args) -> dict:
    from m3t.body.factory import load_body_model
    from m3t.config import load_params
    from m3t.smlm.evaluate_run import run_evaluate

    params = load_params(ROOT / "params.yaml")
    report, _ = run_evaluate(_generate_cfg(), data_config(arm_dir), load_body_model(params.body),
                             params.backtranslation)
    frames = int(sum(r["steps"] for r in report.per_clip)) * 4  # generated frames: 4 per motion step
    keep = ("dtw_jpe_body_m", "dtw_jpe_hand_m", "bt/bleu4", "bt/rouge_l", "bt/clips")
    return {"clips": int(report.summary["clips_scored"]), "frames": frames,
            **{k: report.summary[k] for k in keep if k in report.summary}}


def stage_probe_features(arm_dir: Path, args) -> dict:
    from m3t.body.factory import load_body_model
    from m3t.config import load_params
    from m3t.shards.io import iter_split
    from m3t.slr.features import FrozenEncoders, example_batches, iter_examples
    from m3t.slr.trim import Trimmer
    from m3t.tokenizers.tokenize import load_tokenizers

    params = load_params(ROOT / "params.yaml")
    data = data_config(arm_dir)
    models, _ = load_tokenizers(data.tokenizers_dir)
    encoders = FrozenEncoders(models)
    trimmer = Trimmer(load_body_model(params.body), params.slr.trim)
    skipped: list[dict] = []
    # sentence clips carry no label: each is labelled by its first sign (an isolated-sign corpus's label), the
    # classes from a metadata pass; the clips are then encoded a batch at a time, as evaluate-slr encodes them
    glosses = sorted({c.clip.gloss.split()[0] for c in iter_split(data.shards_dirs, "test", modalities=[])})
    index = {gloss: n for n, gloss in enumerate(glosses)}
    counted = {"clips": 0, "frames": 0}

    def labelled():
        for c in iter_split(data.shards_dirs, "test"):
            counted["clips"] += 1
            counted["frames"] += c.num_frames
            yield dataclasses.replace(c, clip=dataclasses.replace(c.clip, label=index[c.clip.gloss.split()[0]]))

    encoded = 0
    for batch in example_batches(iter_examples(labelled(), {i: i for i in range(len(glosses))}, trimmer, encoders,
                                               ("body", "left_hand", "right_hand", "face"), params.slr.max_steps,
                                               bad_clips="skip", skipped=skipped), params.slr_evaluate.batch_size):
        encoded += len(batch)
    return {**counted, "encoded": encoded, "skipped": len(skipped)}


STAGE_FUNCTIONS = {name: globals()[f"stage_{name}"] for name in STAGES}


def child(args) -> None:
    torch_threads = os.environ.get("BENCH_THREADS")
    if torch_threads:
        import torch

        torch.set_num_threads(int(torch_threads))
    result = STAGE_FUNCTIONS[args.stage](Path(args.arm_dir), args)
    Path(args.result).write_text(json.dumps(result))


# ------------------------------------------------------------------------------------------ parent side
def run_stage(stage: str, arm_dir: Path, clips: int, args) -> dict:
    """One stage in a fresh interpreter: its result, wall time and peak RSS (or where it stopped)."""
    result_path = arm_dir / f"{stage}.result.json"
    result_path.unlink(missing_ok=True)
    command = [sys.executable, __file__, "--stage", stage, "--arm-dir", str(arm_dir), "--clips", str(clips),
               "--steps", str(args.steps), "--seed", str(args.seed), "--result", str(result_path)]
    log = arm_dir / f"{stage}.log"
    exit_status, peak_mb, wall, killed = run_measured(command, log, args.stage_timeout, ROOT)
    row = {"wall_s": round(wall, 1), "peak_rss_mb": round(peak_mb, 1)}
    if not result_path.exists():
        row.update(stopped=True, exit_status=exit_status, log_tail=log.read_text().splitlines()[-15:],
                   timed_out=killed)
        return row
    result = json.loads(result_path.read_text())
    row.update(result)
    if result.get("clips"):
        row["clips_per_s"] = round(result["clips"] / wall, 3)
    if result.get("frames"):
        row["frames_per_s"] = round(result["frames"] / wall, 1)
    return row


def summarise(arms: dict[str, dict]) -> dict:
    """Largest arm against the smallest, per stage: peak RSS ratio and throughput ratio (wall rates: fixed start-up
    costs included, which favour the larger arm), plus the marginal rate between consecutive arms (extra items over
    extra seconds: start-up costs cancel), and whether the goals hold."""
    sizes = sorted(arms, key=int)
    small, large = arms[sizes[0]], arms[sizes[-1]]
    out = {}
    for stage in STAGES:
        a, b = small.get(stage, {}), large.get(stage, {})
        if not a or not b or a.get("stopped") or b.get("stopped"):
            out[stage] = {"compared": False}
            continue
        rate = "steps_per_s" if stage == "train_smlm" else "frames_per_s"
        item = "steps" if stage == "train_smlm" else "frames"
        rss_ratio = b["peak_rss_mb"] / a["peak_rss_mb"]
        rate_ratio = b[rate] / a[rate] if a.get(rate) else float("nan")
        marginal = {}
        for lo, hi in itertools.pairwise(sizes):
            x, y = arms[lo].get(stage, {}), arms[hi].get(stage, {})
            if x and y and not x.get("stopped") and not y.get("stopped") and y["wall_s"] > x["wall_s"]:
                marginal[f"{lo}->{hi}"] = round((y.get(item, 0) - x.get(item, 0)) / (y["wall_s"] - x["wall_s"]), 2)
        out[stage] = {"rss_ratio": round(rss_ratio, 3), "peak_rss_mb_largest": b["peak_rss_mb"], "rate": rate,
                      "rate_ratio": round(rate_ratio, 3), f"marginal_{item}_per_s": marginal,
                      "rss_goal_met": bool(rss_ratio <= GOAL_RSS_RATIO and b["peak_rss_mb"] < GOAL_RSS_MB),
                      "rate_goal_met": bool(rate_ratio >= GOAL_RATE_RATIO)}
    return out


def host() -> dict:
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "python": platform.python_version()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--arms", type=int, nargs="+", default=[1000, 5000, 31000])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--stage-timeout", type=float, default=7200.0)
    parser.add_argument("--work", default=str(ROOT / ".cache" / "bench_scale"))
    parser.add_argument("--models", default=str(ROOT / "models"))
    parser.add_argument("--keep", action="store_true")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "scale.json"))
    parser.add_argument("--stages", nargs="+", choices=STAGES, default=list(STAGES))
    parser.add_argument("--reuse", action="store_true", help="run --stages on the arms' kept folders")
    parser.add_argument("--merge", help="an earlier result whose rows the stages not run keep")
    parser.add_argument("--stage", choices=STAGES, help=argparse.SUPPRESS)
    parser.add_argument("--arm-dir", help=argparse.SUPPRESS)
    parser.add_argument("--clips", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--result", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.stage:
        child(args)
        return
    earlier = json.loads(Path(args.merge).read_text()) if args.merge else {}
    arms: dict[str, dict] = {size: dict(rows) for size, rows in earlier.get("arms", {}).items()}
    reran: dict[str, list[str]] = {}
    partial = Path(args.out).with_suffix(".partial.json")  # every finished stage, should the run be cut short

    def result() -> dict:
        out = {"host": host(), "date": time.strftime("%Y-%m-%d"), "steps": args.steps,
               "corpus": {"mean_frames": HOW2SIGN_MEAN_FRAMES, "sigma": LENGTH_SIGMA, "splits": HOW2SIGN_SPLITS,
                          "entered_as": "generator ground-truth Anny parameters written as shards (no fitting)"},
               "arms": arms, "largest_vs_smallest": summarise(arms)}
        if args.merge:
            out.update(merged_from={"date": earlier.get("date"), "host": earlier.get("host")}, reran=reran)
        return out

    for clips in sorted(args.arms):
        arm_dir = Path(args.work) / f"arm-{clips}"
        if args.reuse:
            if not (arm_dir / "shards").is_dir():
                raise SystemExit(f"--reuse: {arm_dir} holds no kept arm; run it with --keep first")
        else:
            shutil.rmtree(arm_dir, ignore_errors=True)
            arm_dir.mkdir(parents=True)
            prepare_arm(arm_dir, Path(args.models))
        arms.setdefault(str(clips), {})
        for stage in (s for s in STAGES if s in args.stages):
            print(f"[{time.strftime('%H:%M:%S')}] arm {clips}: {stage}", flush=True)
            row = run_stage(stage, arm_dir, clips, args)
            arms[str(clips)][stage] = row
            reran.setdefault(str(clips), []).append(stage)
            print(json.dumps(row), flush=True)
            partial.write_text(json.dumps(result(), indent=2))
            if row.get("stopped"):
                print(f"arm {clips}: {stage} stopped; the arm's later stages need its output", flush=True)
                break
        if not args.keep:
            shutil.rmtree(arm_dir, ignore_errors=True)
    write_and_log(result(), args.out, "bench-scale")
    partial.unlink(missing_ok=True)


if __name__ == "__main__":
    main()
