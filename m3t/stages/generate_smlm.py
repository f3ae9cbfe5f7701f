"""generate-smlm: the trained SMLM on one split -> generated motion tokens, translations, ``.pose`` files and
side-by-side skeleton GIFs.

For every clip of ``smlm_generate.split``: production (its text -> motion tokens, greedy, KV cache) and
translation (its ground-truth motion tokens -> text). Writes into ``out_dir``: ``generated.parquet`` (a token
shard of the generated streams, ``num_frames`` = steps x 4), ``translations.jsonl``, ``pose/<clip>.pose``
(the generated motion through the frozen tokenizer decoders and the body model) and ``renders/<clip>.gif``
(fitted vs generated) for the first ``render_clips`` clips. Clips the vocabulary cannot take (unknown
language, text over the limit) are listed in ``skipped.jsonl``.

Run as a DVC stage: ``python -m m3t.stages.generate_smlm``.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

from m3t.body.protocol import BodyModel
from m3t.render.posefile import export_pose
from m3t.render.reconstruction import render_reconstruction
from m3t.shards.tokens import TokenClip, TokenInfo, write_token_shard
from m3t.smlm.checkpoint import LoadedSMLM, load_smlm
from m3t.smlm.evaluate import SMLMEvaluator
from m3t.stages.tokenize import load_tokenizers
from m3t.stages.train_smlm import load_tokens, references, split_examples


@dataclass(frozen=True)
class GenerateConfig:
    """``smlm_generate`` section: what generate-smlm and evaluate-smlm read."""

    checkpoint: str = "models/smlm/smlm.pt"
    tokenizers_dir: str = "models/tokenizers"
    tokens_dir: str = "data/tokens/synthetic"
    shards_dir: str = "data/shards/synthetic"
    split: str = "test"
    out_dir: str = "data/generated/synthetic"
    metrics_dir: str = "metrics/smlm"  # evaluate-smlm's output
    batch_size: int = 16
    render_clips: int = 2
    export_pose: bool = True


@dataclass
class GenerationSetup:
    loaded: LoadedSMLM  # the checkpoint: model, vocabulary, training settings
    evaluator: SMLMEvaluator  # the split's clips, their references and the frozen tokenizers
    info: TokenInfo  # the tokenizers' streams, codebook sizes and downsampling
    skipped: list[dict]  # clips of the split the vocabulary cannot take, with reasons


def evaluator_for(cfg: GenerateConfig, body: BodyModel, device: str = "cpu") -> GenerationSetup:
    loaded = load_smlm(cfg.checkpoint, device)
    tokenizers, info = load_tokenizers(cfg.tokenizers_dir)
    skipped: list[dict] = []
    examples = split_examples(load_tokens(cfg.tokens_dir, cfg.split), loaded.vocab, loaded.model.cfg, skipped)
    evaluator = SMLMEvaluator(body, tokenizers, loaded.vocab, examples, references(cfg.shards_dir, cfg.split),
                              batch_size=cfg.batch_size)
    return GenerationSetup(loaded, evaluator, info, skipped)


def run_generate(cfg: GenerateConfig, body: BodyModel, progress: bool = True) -> dict[str, float]:
    from tqdm.auto import tqdm

    setup = evaluator_for(cfg, body)
    loaded, evaluator, info, skipped = setup.loaded, setup.evaluator, setup.info, setup.skipped
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    generated = evaluator.generate(loaded.model)
    translations = evaluator.translate(loaded.model)
    clips = []
    for example in evaluator.examples:
        g = generated[example.clip_id]
        steps = len(g.tokens["body"])
        clips.append(TokenClip(evaluator.references[example.clip_id].clip, steps * info.downsample,
                               {s: g.tokens[s] for s in info.streams}))
    write_token_shard(out / "generated.parquet", clips, info)
    (out / "translations.jsonl").write_text("".join(
        json.dumps({"clip_id": e.clip_id, "language": e.language, "reference": e.text,
                    "hypothesis": translations[e.clip_id]}, ensure_ascii=False) + "\n" for e in evaluator.examples))
    (out / "skipped.jsonl").write_text("".join(json.dumps(r) + "\n" for r in skipped))
    rendered = 0
    for example in tqdm(evaluator.examples, desc="generate-smlm: export", disable=not progress):
        g, ref = generated[example.clip_id], evaluator.references[example.clip_id]
        if not g.tokens["body"].size:
            continue
        params = evaluator.motion_params(g)
        if cfg.export_pose:
            export_pose(out / "pose" / f"{example.clip_id}.pose", body, params, ref.identity, ref.clip.fps)
        if rendered < cfg.render_clips:
            render_reconstruction(body, ref, params, out / "renders" / f"{example.clip_id}.gif",
                                  title=f"{example.clip_id} ({example.language})", labels=("fitted", "generated"))
            rendered += 1
    return {"clips": float(len(clips)), "skipped": float(len(skipped)),
            "stopped_rate": float(sum(generated[e.clip_id].stopped for e in evaluator.examples) / max(len(clips), 1))}


def main(argv: list[str] | None = None) -> dict:
    from m3t.body.factory import load_body_model
    from m3t.config import load_params

    parser = argparse.ArgumentParser(description="generate-smlm: SMLM -> generated motion, translations, .pose")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--preset", default="default")
    args = parser.parse_args(argv)
    params = load_params(args.params, preset=args.preset)
    summary = run_generate(params.smlm_generate, load_body_model(params.body))
    print(json.dumps(summary, indent=2, sort_keys=True))
    return summary


if __name__ == "__main__":
    main()
