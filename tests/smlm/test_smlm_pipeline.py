"""The SMLM stages end to end on tiny shards: train-smlm -> generate-smlm -> evaluate-smlm (with the generated
motion back-translated by a tiny judge) through the Prefect flow, then the Tab. 1 table from MLflow."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import sacrebleu
import yaml
from pose_format import Pose

from m3t.backtranslation.pipeline import run_train_backtranslation
from m3t.config import load_params
from m3t.experiment import fetch_runs, to_dict
from m3t.shards.tokens import read_token_shard
from m3t.smlm.table import production_table
from m3t.tokenizers.pipeline import run_train_tokenizers
from m3t.tokenizers.tokenize import run_tokenize

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tokens(shards_dir, body, tmp_path_factory):  # noqa: F811
    """Tiny tokenizers + token shards over the tiny fitted shards, and a tiny back-translation judge."""
    root = tmp_path_factory.mktemp("smlm-pipeline")
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "data": data_section(shards_dir, root), "tokenizer_train": {"cache_dir": str(root / "cache")},
        "backtranslation_train": {"cache_dir": str(root / "cache-bt")}})
    run_train_tokenizers(params.tokenizer, params.tokenizer_train, body, params.data, progress=False)
    run_tokenize(params.data)
    run_train_backtranslation(params.backtranslation, params.backtranslation_train, params.data, progress=False)
    return root


def data_section(shards_dir: Path, root: Path, out: Path | None = None) -> dict:
    """``data`` overrides: the fixture's shards, tokens and models under ``root``, outputs under ``out``."""
    out = out or root
    return {"shards_root": str(shards_dir.parent), "tokens_root": str(root / "tokens"), "models_dir": str(root / "models"),
            "generated_dir": str(out / "gen"), "metrics_dir": str(out / "metrics")}


def test_smlm_flow_trains_generates_evaluates_and_tabulates(tokens, shards_dir, tmp_path):  # noqa: F811
    from prefect.testing.utilities import prefect_test_harness

    from flows.smlm import smlm_flow

    root = tokens
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "body": {"cache_dir": str(ROOT / ".cache" / "anny")},
        "experiment": {"enabled": True, "tracking_uri": f"sqlite:///{tmp_path / 'mlflow.db'}",
                       "artifact_dir": str(tmp_path / "mlruns")},
        "data": data_section(shards_dir, root, tmp_path), "smlm_train": {"epochs": 3}})
    params_file = tmp_path / "params.yaml"
    params_file.write_text(yaml.safe_dump(to_dict(params)))
    with prefect_test_harness():
        result = smlm_flow(params_path=str(params_file))
    assert (root / "models" / "smlm" / "smlm.pt").exists()
    train = json.loads((root / "models" / "smlm" / "metrics.json").read_text())
    assert train["train_examples"] == 4 and train["best_epoch"] >= 1
    summary = result["evaluation"]
    generated = read_token_shard(tmp_path / "gen" / "synthetic" / "generated.parquet")
    test_ids = [c.clip.id for c in read_token_shard(root / "tokens" / "synthetic" / "test.parquet").clips]
    assert [c.clip.id for c in generated.clips] == test_ids
    per_clip = pd.read_csv(tmp_path / "metrics" / "smlm" / "per_clip.csv")
    assert list(per_clip["clip_id"]) == test_ids
    # An empty generation (EOS at once) is scored as the rest pose, so every motion metric is there either way;
    # it gets no .pose file and no render. The seeded tiny run generates 11 steps for its one test clip.
    steps = {c.clip.id: len(c.tokens["body"]) for c in generated.clips}
    nonempty = [c for c in test_ids if steps[c]]
    assert summary["empty_rate"] == pytest.approx(1 - len(nonempty) / len(test_ids))
    assert list(per_clip["steps"]) == [steps[c] for c in test_ids]
    assert summary["mean_steps"] == pytest.approx(np.mean([steps[c] for c in test_ids]))
    for key in ("dtw_jpe_body_m", "dtw_pa_jpe_body_m", "dtw_jpe_hand_m", "dtw_pa_jpe_hand_m", "dtw_vpe_face_m"):
        assert math.isfinite(summary[key]) and summary[key] > 0, key
        assert summary[key] == pytest.approx(per_clip[key].mean()), key  # one group: the mean over clips
    poses = sorted((tmp_path / "gen" / "synthetic" / "pose").glob("*.pose"))
    assert [p.stem for p in poses] == sorted(nonempty)
    for pose in poses:  # pose-format's holistic: 33 + 468 + 2 x 21 + 33 world points, one frame per motion frame
        assert Pose.read(pose.read_bytes()).body.data.shape[2] == 576
    # the first render_clips non-empty clips: body surface side by side, and the skeleton overlay
    renders = sorted(p.name for p in (tmp_path / "gen" / "synthetic" / "renders").glob("*.mp4"))
    shown = nonempty[: params.smlm_generate.render_clips]
    assert renders == sorted(f"{c}{suffix}.mp4" for c in shown for suffix in ("", "_skeleton"))
    # BLEU recomputed independently from the files the stages wrote. The SMLM's own translations: sacrebleu's
    # corpus BLEU with its 13a tokeniser (one language here, so the per-language mean is that language's score).
    rows = [json.loads(line) for line in (tmp_path / "gen" / "synthetic" / "translations.jsonl").read_text().splitlines()]
    assert [r["clip_id"] for r in rows] == test_ids
    bleu = sacrebleu.corpus_bleu([r["hypothesis"] for r in rows], [[r["reference"] for r in rows]], tokenize="13a")
    assert summary["translation_bleu4"] == pytest.approx(bleu.score, abs=1e-9)
    # every test clip is scored: none cut or unscorable here, and each back-translated by the judge
    assert summary["clips_scored"] == len(test_ids) and summary["clips_unscorable"] == 0
    judged = pd.read_csv(tmp_path / "metrics" / "smlm" / "backtranslation.csv", keep_default_na=False)
    assert list(judged["clip_id"]) == test_ids
    # the judge's BLEU, SL-T's settings in sacrebleu: lower-cased, whitespace tokens, floor smoothing 0, and no
    # effective order (SL-T's cumulative BLEU-4 is 0 when no hypothesis reaches a 4-gram; m3t.metrics.text)
    slt = sacrebleu.BLEU(tokenize="none", lowercase=True, smooth_method="floor", smooth_value=0.0,
                         effective_order=False)
    want = slt.corpus_score(list(judged["hypothesis"]), [list(judged["reference"])]).score
    assert summary["bt/slt_bleu4"] == pytest.approx(want, abs=1e-9)
    assert summary["bt/slt/ASL-SYN/sentences"] == len(test_ids)
    records = fetch_runs(params.experiment, stage="evaluate-smlm")
    assert records and records[0].tags["variant"] == "production + translation"
    table = production_table(records)
    assert "production + translation" in table and "PA body" in table
