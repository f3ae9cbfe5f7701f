"""evaluate-smlm: generated motion + translations -> M3T Tab. 1 metrics, logged to MLflow.

Scores what generate-smlm wrote (no model run here): DTW-JPE / DTW-PA-JPE body and hand, face DTW-VPE
(raw SOKE accumulated cost and the path-length-normalised variant, metres), overall and per
``<corpus>/<language>``, plus BLEU-4 / ROUGE-L of the translations. Writes ``<metrics_dir>/metrics.json``
and ``per_clip.csv``; the MLflow run is tagged with the training variant (with / without the translation
objective) so ``m3t smlm-table`` can print the Tab. 1 comparison.

Run as a DVC stage: ``python -m m3t.stages.evaluate_smlm``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd

from m3t.body.protocol import BodyModel
from m3t.shards.tokens import read_token_shard
from m3t.smlm.evaluate import EvaluationReport
from m3t.smlm.generate import GeneratedMotion
from m3t.stages.generate_smlm import GenerateConfig, evaluator_for


def variant_name(train_config: dict) -> str:
    return "production + translation" if train_config.get("translation_objective", True) else "production only"


def run_evaluate(cfg: GenerateConfig, body: BodyModel) -> tuple[EvaluationReport, dict]:
    setup = evaluator_for(cfg, body)
    loaded, evaluator = setup.loaded, setup.evaluator
    out = Path(cfg.out_dir)
    shard_path, text_path = out / "generated.parquet", out / "translations.jsonl"
    for path in (shard_path, text_path):
        if not path.exists():
            raise FileNotFoundError(f"{path} not found; run the generate-smlm stage first (dvc repro generate-smlm)")
    # generate-smlm decodes up to max_motion_tokens steps: a clip that ended earlier emitted EOS
    limit = loaded.model.cfg.max_motion_tokens
    generated = {c.clip.id: GeneratedMotion(dict(c.tokens), stopped=c.num_tokens < limit)
                 for c in read_token_shard(shard_path).clips}
    translations = {}
    for line_no, line in enumerate(text_path.read_text().splitlines(), 1):
        try:
            row = json.loads(line)
            translations[row["clip_id"]] = row["hypothesis"]
        except (json.JSONDecodeError, KeyError) as exc:
            raise ValueError(f"{text_path}, line {line_no}: not a translation record ({exc}); rerun generate-smlm") from exc
    report = evaluator.score(generated, translations)
    metrics_dir = Path(cfg.metrics_dir)
    metrics_dir.mkdir(parents=True, exist_ok=True)
    (metrics_dir / "metrics.json").write_text(json.dumps(report.summary, indent=2, sort_keys=True))
    pd.DataFrame(report.per_clip).to_csv(metrics_dir / "per_clip.csv", index=False)
    return report, loaded.train_config


def evaluate_and_log(params) -> dict[str, float]:
    from m3t.body.factory import load_body_model
    from m3t.experiment import start_run

    report, train_config = run_evaluate(params.smlm_generate, load_body_model(params.body))
    tags = {"variant": variant_name(train_config), "split": params.smlm_generate.split,
            "translation_objective": str(train_config.get("translation_objective", True))}
    with start_run(params.experiment, "evaluate-smlm", tags=tags) as run:
        run.log_params({f"smlm_train.{k}": v for k, v in train_config.items()})
        run.log_metrics({k: v for k, v in report.summary.items() if v == v and abs(v) != float("inf")})
        for name in ("metrics.json", "per_clip.csv"):
            run.log_artifact(Path(params.smlm_generate.metrics_dir) / name)
        for gif in sorted((Path(params.smlm_generate.out_dir) / "renders").glob("*.gif")):
            run.log_artifact(gif, "renders")
    return report.summary


def main(argv: list[str] | None = None) -> dict:
    from m3t.config import load_params

    parser = argparse.ArgumentParser(description="evaluate-smlm: generated motion -> DTW / BLEU metrics")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--preset", default="default")
    args = parser.parse_args(argv)
    summary = evaluate_and_log(load_params(args.params, preset=args.preset))
    print(json.dumps({k: v for k, v in summary.items() if "/" not in k}, indent=2, sort_keys=True))
    return summary


if __name__ == "__main__":
    main()
