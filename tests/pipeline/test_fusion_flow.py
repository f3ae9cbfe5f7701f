"""Tracker fusion inside fit-corpus, end to end through the Prefect flow: a ``.pose`` collection whose first
clip carries NLF / WiLoR / Pixel3DMM outputs beside its media (written by :mod:`fusion_fixtures` in the
trackers' published formats) and whose second clip carries none, fitted with ``body.model: smplfx`` (the
synthetic SMPL-X / FLAME stand-in files of :mod:`smplfx_fixtures`).

The clip's 2D track comes from a real lexicon ``.pose`` file (the packaged fingerspelling letters), so it
shows other motion than the tracker outputs: the test checks where each fit started from and that the
records say so, not that the fit lands on the trackers' ground truth (``tests/fitting/test_fusion.py`` measures that).
"""
from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from fusion_fixtures import ground_truth, write_nlf, write_pixel3dmm, write_wilor
from smplfx_fixtures import ensure_fixture_files, fixture_body

from m3t.config import load_params
from m3t.corpora.fingerspelling import lexicon_root
from m3t.experiment import to_dict
from m3t.fitting.per_clip import NO_EXTERNAL
from m3t.shards.io import read_shard

ROOT = Path(__file__).resolve().parents[2]


def pose_frames(path: Path) -> int:
    from pose_format import Pose

    return int(Pose.read(path.read_bytes()).body.data.shape[0])


@pytest.fixture()
def collection(tmp_path, tmp_path_factory):
    """Two ASL letter clips copied from the lexicon into an index-CSV ``.pose`` collection; ``with`` gets
    all three trackers' outputs (ground truth of as many frames as its ``.pose`` has)."""
    files = ensure_fixture_files(tmp_path_factory)
    fx = fixture_body(files)
    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        rows = [r for r in csv.DictReader(fh) if r["signed_language"] == "ase"][:2]
    root = tmp_path / "poses"
    root.mkdir()
    for name, row in zip(("with", "without"), rows):
        shutil.copyfile(lexicon_root() / row["path"], root / f"{name}.pose")
    (root / "index.csv").write_text("id,path,split,text,language,signer\n"
                                    "with,with.pose,train,a,ase,s0\nwithout,without.pose,train,b,ase,s0\n")
    truth = ground_truth(fx, frames=pose_frames(root / "with.pose"), seed=7)
    write_nlf(root / "with.nlf.npz", fx.layout, truth)
    write_wilor(root / "with.wilor.npz", truth)
    write_pixel3dmm(root / "with.pixel3dmm", truth)
    return files, root, truth


def test_fit_corpus_flow_fuses_the_clip_with_tracker_outputs(collection, tmp_path):
    from prefect.testing.utilities import prefect_test_harness

    from flows.fit_corpus import fit_corpus

    files, root, truth = collection
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "body": {"model": "smplfx", "smplx_path": str(files.smplx), "flame_path": str(files.flame),
                 "flame_correspondence_path": str(files.correspondence), "eyelids_path": str(files.eyelids)},
        "fitting": {"iterations": 20, "camera_iterations": 20},
        "corpora": {"posefile": {"root": str(root), "options": {"index": "index.csv"}}},
        "data": {"shards_root": str(tmp_path / "shards")},
        "fit_corpus": {"default_corpus": "posefile", "cache_dir": str(tmp_path / "cache"), "workers": 1,
                       "render_clips": 0}})
    params_file = tmp_path / "params.yaml"
    params_file.write_text(yaml.safe_dump(to_dict(params)))
    with prefect_test_harness():
        summary = fit_corpus(params_path=str(params_file), log_mlflow=False)
    assert summary["clips_fitted"] == 2 and summary["clips_quarantined"] == 0

    out = tmp_path / "shards" / "posefile"
    with open(out / "quality.csv", encoding="utf-8") as fh:
        records = {r["clip_id"]: r for r in csv.DictReader(fh)}
    assert records["with"]["init_source"] == "fused: nlf, wilor, pixel3dmm"
    assert records["without"]["init_source"] == NO_EXTERNAL
    assert json.loads((out / "quality.json").read_text())["init_sources"] == {"fused": 1, "rest pose": 1}

    fitted = {c.clip.id: c for c in read_shard(out / "train.parquet").clips}
    assert fitted["with"].body_model == fitted["without"].body_model == "smplfx"
    # Refinement starts from the fused initialisation: the fit keeps the trackers' FLAME expressions (which
    # the letter clip's 2D face landmarks do not pull far), while the rest-pose start is as far from them as
    # a neutral face. Measured: 0.16 after the fused start vs 0.39 for the rest pose (mean |error| of the expression).
    want = truth.params["face"].numpy()
    error = {"fused fit": float(np.abs(fitted["with"].params["face"] - want).mean()),
             "rest pose": float(np.abs(want).mean())}
    assert error["fused fit"] < 0.5 * error["rest pose"], error
