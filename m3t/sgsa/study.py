"""The SGSA paper's two claims, tested on the configured corpus with several seeds and intervals.

1. SGSA beats Progressive Transformers (Tab. 1: L SGSA layers vs "0 (4 SA)", both at N = inf).
2. A temporal adjacency of N = 1 beats N = inf (Tab. 2).

Each variant (PT; SGSA with the configured L at N = inf; SGSA at the configured N when it is finite) is trained once
per seed of ``seeds`` (``sgsa_train.seed``; the rest of ``sgsa`` / ``sgsa_train`` as configured; runs already in
``sgsa_train.cache_dir`` under their run key are reused), then every clip of ``split`` is generated with the
predicted counter and scored: DTW-JPE (mean of body and hands, SOKE raw cost, and its path-normalised form, which
does not grow with the generated length) and the skeleton judge's sentence-level ROUGE-L (SL-T definition) on the
sentence clips, plus corpus BLEU-4 per seed. Every model is scored twice: with its own (predicted) counter and with
the ground-truth counter (the true length; parity with published PT numbers only). A comparison is the mean over
clips of B - A, each side averaged over its seeds, with a 95 % hierarchical bootstrap interval over seeds and clips
(:func:`m3t.metrics.stats.paired`); "B better" needs the whole interval on B's side.

Axis legend: C clips, R seeds.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from m3t.atomic import write_json, write_text
from m3t.backtranslation.config import BackTranslationConfig
from m3t.backtranslation.pipeline import backtranslate
from m3t.body.protocol import BodyModel
from m3t.body.skeleton import graph_for
from m3t.metrics.stats import INCONCLUSIVE, NOT_REPRODUCED, REPRODUCED, paired, verdict_better
from m3t.reporting import markdown_table
from m3t.sgsa.checkpoint import load_sgsa
from m3t.sgsa.config import SGSAConfig, SGSATrainConfig
from m3t.sgsa.data import make_samples, vocabularies
from m3t.sgsa.evaluate import generate, score_production
from m3t.sgsa.table import in_display_units
from m3t.sgsa.train import run_key, train_sgsa
from m3t.shards.folders import DataConfig
from m3t.shards.io import production_data_version, read_production_split
from m3t.shards.skeletons import SKELETON_STREAM, skeleton_clips

LOWER_IS_BETTER = {"dtw_jpe_mean_m": True, "dtw_jpe_mean_pathnorm_m": True, "rouge_l": False}


def variants(cfg: SGSAConfig) -> dict[str, SGSAConfig]:
    """PT, SGSA at N = inf and (when configured) SGSA at its finite N, all with the configured sizes."""
    layers = max(cfg.decoder_layers, 1)
    out = {"PT": cfg.for_system("pt"),
           f"SGSA L={layers} N=inf": dataclasses.replace(cfg, decoder_layers=layers, temporal_adjacency=0)}
    if cfg.temporal_adjacency:
        out[f"SGSA L={layers} N={cfg.temporal_adjacency}"] = dataclasses.replace(cfg, decoder_layers=layers)
    return out


def run_study(model_cfg: SGSAConfig, train_cfg: SGSATrainConfig, body: BodyModel, data: DataConfig,
              seeds: list[int], out_dir: str | Path, split: str = "test", judge: BackTranslationConfig | None = None,
              progress: bool = True, counters: tuple[str, ...] = ("predicted", "ground_truth")) -> dict:
    """Train and score every variant for every seed; write ``claims.json`` and ``claims.md`` into ``out_dir``."""
    judge = judge or BackTranslationConfig()
    graph = graph_for(model_cfg.skeleton, model_cfg.face_points)
    train_clips = skeleton_clips(body, read_production_split(data, "train"), graph, progress, "skeletons: train")
    dev_clips = skeleton_clips(body, read_production_split(data, "dev"), graph, progress, "skeletons: dev")
    test_clips = skeleton_clips(body, read_production_split(data, split), graph, progress, f"skeletons: {split}")
    text_vocab, gloss_vocab = vocabularies(train_clips, model_cfg)
    train = make_samples(train_clips, text_vocab, gloss_vocab, model_cfg, training=True).samples
    dev = make_samples(dev_clips, text_vocab, gloss_vocab, model_cfg, training=False).samples
    test = make_samples(test_clips, text_vocab, gloss_vocab, model_cfg, training=False).samples
    sentences = [s for s in test if s.sentence]
    version = production_data_version(data)
    per_clip: dict[str, dict[str, dict[str, np.ndarray]]] = {c: {} for c in counters}  # counter -> variant -> (R, C)
    corpus: dict[str, dict[str, dict[str, list[float]]]] = {c: {} for c in counters}  # ... -> metric -> per seed
    for name, cfg in variants(model_cfg).items():
        rows = {c: {k: [] for k in LOWER_IS_BETTER} for c in counters}
        for c in counters:
            corpus[c][name] = {"bleu4": [], "rouge_l": [], "dtw_jpe_mean_m": [], "length_ratio": []}
        for seed in seeds:
            tcfg = dataclasses.replace(train_cfg, seed=seed)
            key = run_key(cfg, tcfg, graph, text_vocab, gloss_vocab, version)
            best = Path(tcfg.cache_dir) / f"{key}.best.pt"
            result = train_sgsa(cfg, tcfg, graph, text_vocab, gloss_vocab, train, dev, version, best,
                                Path(tcfg.cache_dir) / f"{key}.last.pt", progress=progress)
            model = load_sgsa(result.best_path).model
            for counter in counters:
                produced = generate(model, test, text_vocab, cfg.max_frames, counter)
                report = score_production(test, produced, graph, cfg.max_frames)
                by_id = {r["clip_id"]: r for r in report.per_clip}
                found = rows[counter]
                for metric, suffix in (("dtw_jpe_mean_m", "_m"), ("dtw_jpe_mean_pathnorm_m", "_pathnorm_m")):
                    found[metric].append(np.array([0.5 * (by_id[s.clip_id][f"dtw_jpe_body{suffix}"]
                                                          + by_id[s.clip_id][f"dtw_jpe_hand{suffix}"]) for s in test]))
                judged = backtranslate(data.skeleton_judge_dir,
                                       {s.clip_id: (s.language, {SKELETON_STREAM: produced[s.clip_id][:, :-1]})
                                        for s in sentences},
                                       {s.clip_id: s.clip.fitted.clip.text for s in sentences}, judge.beam_size,
                                       judge.length_penalty)
                found["rouge_l"].append(np.array([r["rouge_l"] for r in judged.per_clip]))
                seen = corpus[counter][name]
                seen["bleu4"].append(judged.summary["slt_bleu4"])
                seen["rouge_l"].append(judged.summary["slt_rouge_l"])
                seen["dtw_jpe_mean_m"].append(report.summary["dtw_jpe_mean_m"])
                seen["length_ratio"].append(report.summary["length_ratio"])
        for c in counters:
            per_clip[c][name] = {k: np.stack(v) for k, v in rows[c].items()}
    names = list(variants(model_cfg))
    comparisons = [(names[0], names[1], "SGSA beats PT (Tab. 1, N = inf)")]
    if len(names) > 2:
        comparisons.append((names[1], names[2], f"N = {model_cfg.temporal_adjacency} beats N = inf (Tab. 2)"))
    results = judge_comparisons(per_clip, comparisons, slice(None))
    summary = {"split": split, "seeds": list(seeds), "variants": {n: dataclasses.asdict(c)
                                                                  for n, c in variants(model_cfg).items()},
               "per_seed": corpus, "comparisons": results, "stability": stability(per_clip, comparisons, seeds)}
    out = Path(out_dir)
    write_json(out / "claims.json", summary)
    write_text(out / "claims.md", claims_markdown(summary))
    return summary


def judge_comparisons(per_clip: dict[str, dict[str, dict[str, np.ndarray]]],
                      comparisons: list[tuple[str, str, str]], seeds: slice | list[int]) -> list[dict]:
    """Every comparison (A, B, claim) on every metric and counter, on the seed rows ``seeds`` of the (R, C) values."""
    rng = np.random.default_rng(0)
    results = []
    for counter, by_variant in per_clip.items():
        for a, b, claim in comparisons:
            for metric, lower in LOWER_IS_BETTER.items():
                pair = paired(by_variant[a][metric][seeds], by_variant[b][metric][seeds], rng)
                verdict = {REPRODUCED: f"{b} better", NOT_REPRODUCED: f"{a} better",
                           INCONCLUSIVE: "no difference established"}[verdict_better(pair.interval, lower)]
                results.append({"claim": claim, "counter": counter, "a": a, "b": b, "metric": metric,
                                "clips": pair.clips, "mean_a": pair.mean_a, "mean_b": pair.mean_b,
                                "difference": pair.difference, "interval95": list(pair.interval), "verdict": verdict})
    return results


def stability(per_clip: dict[str, dict[str, dict[str, np.ndarray]]], comparisons: list[tuple[str, str, str]],
              seeds: list[int]) -> dict:
    """The verdicts judged again on two disjoint halves of the seeds (the first half, the rest): how many flip.
    A verdict that one retrain set gives and the other does not is not a finding. Needs >= 2 seeds."""
    if len(seeds) < 2:
        return {"halves": [], "compared": 0, "flipped": 0, "share_flipped": None, "flips": []}
    half = len(seeds) // 2
    first = judge_comparisons(per_clip, comparisons, list(range(half)))
    second = judge_comparisons(per_clip, comparisons, list(range(half, len(seeds))))
    flips = [{"claim": x["claim"], "counter": x["counter"], "metric": x["metric"], "first": x["verdict"],
              "second": y["verdict"]} for x, y in zip(first, second) if x["verdict"] != y["verdict"]]
    return {"halves": [list(seeds[:half]), list(seeds[half:])], "compared": len(first), "flipped": len(flips),
            "share_flipped": len(flips) / len(first) if first else None, "flips": flips}


def claims_markdown(summary: dict) -> str:
    lines = [f"SGSA claims on the {summary['split']} split, seeds {summary['seeds']} (paired per clip, seed-averaged; "
             "95 % hierarchical bootstrap interval over seeds and clips). DTW-JPE: SOKE raw DTW cost (and path-normalised), mean of body and "
             "hands, mm; ROUGE-L: skeleton judge, SL-T definition, sentence level.", ""]
    body = []
    for r in summary["comparisons"]:
        metric, mean_a, mean_b, difference, low, high = in_display_units(r)
        body.append([r["claim"], r["counter"], metric, r["a"], r["b"], f"{mean_a:.2f}", f"{mean_b:.2f}",
                     f"{difference:.2f}", f"[{low:.2f}, {high:.2f}]", r["verdict"]])
    lines.append(markdown_table(["claim", "counter", "metric", "A", "B", "mean A", "mean B", "B - A", "95 % interval",
                                 "verdict"], body))
    steady = summary.get("stability") or {}
    if steady.get("compared"):
        first, second = steady["halves"]
        lines += ["", f"Stability: the verdicts judged again on seeds {first} and on seeds {second} separately differ "
                      f"in {steady['flipped']} of {steady['compared']} rows ({100 * steady['share_flipped']:.0f} %)"
                      + (":" if steady["flips"] else ".")]
        lines += [f"- {f['claim']}, {f['counter']} counter, {f['metric']}: {f['first']} / {f['second']}"
                  for f in steady["flips"]]
    lines += ["", "Per seed (corpus BLEU-4 / ROUGE-L of the judge, DTW-JPE mm, generated / reference length):", ""]
    for counter, by_name in summary["per_seed"].items():
        for name, values in by_name.items():
            cells = ", ".join(f"seed {s}: B4 {b:.2f} R {r:.2f} JPE {1000 * j:.0f} len x{ratio:.2f}"
                              for s, b, r, j, ratio in zip(summary["seeds"], values["bleu4"], values["rouge_l"],
                                                           values["dtw_jpe_mean_m"], values["length_ratio"]))
            lines.append(f"- {name}, {counter} counter: {cells}")
    return "\n".join(lines) + "\n"
