"""tokenize: fitted shards + trained tokenizers -> token shards (one per split), for the language models.

Every clip of every split is encoded by the three selected tokenizers (left hands mirrored into right
hands for the shared hand tokenizer), giving four time-aligned streams per clip. A clip that cannot be
tokenised (non-finite parameters, a stream missing) is listed in ``rejected.jsonl`` with its reason and
the others go on. Clips shorter than one token window are edge-padded to one token.

Run as a DVC stage: ``python -m m3t.stages.tokenize``.
"""
from __future__ import annotations

import argparse
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t.shards.tokens import TokenClip, TokenInfo, write_token_shard
from m3t.stages.train_tokenizers import SPLITS, load_split
from m3t.tokenizers.checkpoint import load_tokenizer
from m3t.tokenizers.data import GROUPS, STREAMS, clip_sequences
from m3t.tokenizers.evaluate import encode_clip
from m3t.tokenizers.vae import MotionTokenizer


@dataclass(frozen=True)
class TokenizeConfig:
    tokenizers_dir: str = "models/tokenizers"
    shards_dir: str = "data/shards/synthetic"
    out_dir: str = "data/tokens/synthetic"


def load_tokenizers(tokenizers_dir: str | Path) -> tuple[dict[str, MotionTokenizer], TokenInfo]:
    """The three group tokenizers and the token-shard info (codebook sizes, downsampling, digests)."""
    models, digests = {}, {}
    for group in GROUPS:
        path = Path(tokenizers_dir) / f"{group}.pt"
        models[group] = load_tokenizer(path).model
        digests[group] = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    factors = {m.cfg.downsample for m in models.values()}
    if len(factors) != 1:
        raise ValueError(f"tokenizers in {tokenizers_dir} downsample by different factors {sorted(factors)}; "
                         "the token streams would not align in time; retrain them with one tokenizer.down_stages")
    info = TokenInfo({s.name: models[g].codebook_size for g, streams in GROUPS.items() for s in streams},
                     factors.pop(), {s.name: digests[g] for g, streams in GROUPS.items() for s in streams})
    return models, info


def tokenize_clip(models: dict[str, MotionTokenizer], fitted) -> TokenClip:
    tokens = {}
    for group, streams in GROUPS.items():
        for stream, values in zip(streams, clip_sequences(fitted.params, group, fitted.clip.id)):
            tokens[stream.name] = encode_clip(models[group], values)
    return TokenClip(fitted.clip, fitted.num_frames, {s.name: tokens[s.name] for s in STREAMS})


def run_tokenize(cfg: TokenizeConfig) -> dict[str, float]:
    models, info = load_tokenizers(cfg.tokenizers_dir)
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rejected, summary = [], {}
    for split in SPLITS:
        clips = []
        for fitted in load_split(cfg.shards_dir, split):
            try:
                clips.append(tokenize_clip(models, fitted))
            except (ValueError, KeyError) as exc:
                rejected.append({"clip_id": fitted.clip.id, "split": split, "reason": f"{type(exc).__name__}: {exc}"})
        write_token_shard(out / f"{split}.parquet", clips, info)
        summary[f"{split}_clips"] = len(clips)
        summary[f"{split}_tokens_per_stream"] = int(sum(c.num_tokens for c in clips))
    summary["rejected"] = len(rejected)
    summary["mean_tokens_per_clip"] = float(np.mean([summary[f"{s}_tokens_per_stream"] / max(summary[f"{s}_clips"], 1)
                                                     for s in SPLITS if summary[f"{s}_clips"]] or [0.0]))
    (out / "rejected.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rejected))
    (out / "summary.json").write_text(json.dumps(summary, indent=2, sort_keys=True))
    return summary


def main(argv: list[str] | None = None) -> dict:
    from m3t.config import load_params

    parser = argparse.ArgumentParser(description="tokenize: fitted shards -> token shards")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--preset", default="default")
    args = parser.parse_args(argv)
    summary = run_tokenize(load_params(args.params, preset=args.preset).tokenize)
    print(json.dumps(summary, indent=2, sort_keys=True))
    return summary


if __name__ == "__main__":
    main()
