"""The SMLM stages end to end on tiny shards: train-smlm -> generate-smlm -> evaluate-smlm through the
Prefect flow, then the Tab. 1 table from MLflow."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pandas as pd
import pytest
import yaml
from pose_format import Pose

from m3t.config import load_params, to_dict
from m3t.experiment import fetch_runs
from m3t.shards.tokens import read_token_shard
from m3t.smlm.table import production_table
from m3t.stages.tokenize import TokenizeConfig, run_tokenize
from m3t.stages.train_tokenizers import run_train_tokenizers
from test_tokenizer_training import shards_dir  # noqa: F401 - the tiny fitted shards fixture

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tokens(shards_dir, body, tmp_path_factory):  # noqa: F811
    """Tiny tokenizers + token shards over the tiny fitted shards."""
    root = tmp_path_factory.mktemp("smlm-pipeline")
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "tokenizer_train": {"shards_dir": str(shards_dir), "out_dir": str(root / "tok"), "cache_dir": str(root / "cache")}})
    run_train_tokenizers(params.tokenizer, params.tokenizer_train, body, progress=False)
    run_tokenize(TokenizeConfig(str(root / "tok"), str(shards_dir), str(root / "tokens")))
    return root


def test_smlm_flow_trains_generates_evaluates_and_tabulates(tokens, shards_dir, tmp_path):  # noqa: F811
    from prefect.testing.utilities import prefect_test_harness

    from flows.smlm import smlm_flow

    root = tokens
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "body": {"cache_dir": str(ROOT / ".cache" / "anny")},
        "experiment": {"enabled": True, "tracking_uri": f"sqlite:///{tmp_path / 'mlflow.db'}",
                       "artifact_dir": str(tmp_path / "mlruns")},
        "smlm_train": {"tokens_dir": str(root / "tokens"), "shards_dir": str(shards_dir),
                       "tokenizers_dir": str(root / "tok"), "out_dir": str(tmp_path / "smlm"), "epochs": 3},
        "smlm_generate": {"checkpoint": str(tmp_path / "smlm" / "smlm.pt"), "tokenizers_dir": str(root / "tok"),
                          "tokens_dir": str(root / "tokens"), "shards_dir": str(shards_dir),
                          "out_dir": str(tmp_path / "gen"), "metrics_dir": str(tmp_path / "metrics")}})
    params_file = tmp_path / "params.yaml"
    params_file.write_text(yaml.safe_dump(to_dict(params)))
    with prefect_test_harness():
        result = smlm_flow(params_path=str(params_file))
    assert (tmp_path / "smlm" / "smlm.pt").exists()
    train = json.loads((tmp_path / "smlm" / "metrics.json").read_text())
    assert train["train_examples"] == 4 and train["best_epoch"] >= 1
    summary = result["evaluation"]
    generated = read_token_shard(tmp_path / "gen" / "generated.parquet")
    test_ids = [c.clip.id for c in read_token_shard(root / "tokens" / "test.parquet").clips]
    assert [c.clip.id for c in generated.clips] == test_ids
    per_clip = pd.read_csv(tmp_path / "metrics" / "per_clip.csv")
    assert list(per_clip["clip_id"]) == test_ids
    if summary["empty_rate"] < 1.0:  # an untrained model may end at once; otherwise every metric is there
        for key in ("dtw_jpe_body_m", "dtw_pa_jpe_body_m", "dtw_jpe_hand_m", "dtw_pa_jpe_hand_m", "dtw_vpe_face_m"):
            assert math.isfinite(summary[key]) and summary[key] >= 0, key
        poses = sorted((tmp_path / "gen" / "pose").glob("*.pose"))
        assert poses and Pose.read(poses[0].read_bytes()).body.data.shape[2] == 543
    assert 0 <= summary["translation_bleu4"] <= 100
    records = fetch_runs(params.experiment, stage="evaluate-smlm")
    assert records and records[0].tags["variant"] == "production + translation"
    table = production_table(records)
    assert "production + translation" in table and "PA body" in table
