"""The SMLM stages end to end on tiny shards: train-smlm -> generate-smlm -> evaluate-smlm (with the generated
motion back-translated by a tiny judge) through the Prefect flow, then the Tab. 1 table from MLflow."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pandas as pd
import pytest
import yaml
from pose_format import Pose

from m3t.backtranslation.pipeline import run_train_backtranslation
from m3t.config import load_params
from m3t.experiment import to_dict
from m3t.experiment import fetch_runs
from m3t.shards.tokens import read_token_shard
from m3t.smlm.table import production_table
from m3t.tokenizers.pipeline import run_train_tokenizers
from m3t.tokenizers.tokenize import run_tokenize
from test_tokenizer_training import shards_dir  # noqa: F401 - the tiny fitted shards fixture

ROOT = Path(__file__).resolve().parents[1]


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
    if summary["empty_rate"] < 1.0:  # an untrained model may end at once; otherwise every metric is there
        for key in ("dtw_jpe_body_m", "dtw_pa_jpe_body_m", "dtw_jpe_hand_m", "dtw_pa_jpe_hand_m", "dtw_vpe_face_m"):
            assert math.isfinite(summary[key]) and summary[key] >= 0, key
        poses = sorted((tmp_path / "gen" / "synthetic" / "pose").glob("*.pose"))
        assert poses and Pose.read(poses[0].read_bytes()).body.data.shape[2] == 576  # pose-format's holistic: 33 + 468 + 2 x 21 + 33 world
        # the first render_clips generated clips: body surface side by side, and the skeleton overlay
        renders = sorted(p.name for p in (tmp_path / "gen" / "synthetic" / "renders").iterdir())
        assert renders == [f"{poses[0].stem}.mp4", f"{poses[0].stem}_skeleton.mp4"]
    assert 0 <= summary["translation_bleu4"] <= 100
    # every test clip is scored: none cut or unscorable here, and each back-translated by the judge
    assert summary["clips_scored"] == len(test_ids) and summary["clips_unscorable"] == 0
    judged = pd.read_csv(tmp_path / "metrics" / "smlm" / "backtranslation.csv")
    assert list(judged["clip_id"]) == test_ids
    assert 0 <= summary["bt/slt_bleu4"] <= 100 and summary["bt/slt/ASL-SYN/sentences"] == len(test_ids)
    records = fetch_runs(params.experiment, stage="evaluate-smlm")
    assert records and records[0].tags["variant"] == "production + translation"
    table = production_table(records)
    assert "production + translation" in table and "PA body" in table
