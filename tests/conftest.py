"""Shared fixtures: one Anny body model per session (built once into the project cache)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

for _key, _value in {
    # MKL's results depend on the memory alignment of its operands (a batch's layout, another process's heap): its
    # strict conditional-numerical-reproducibility mode makes them alignment-independent, so one computation run on
    # this host at the same thread count in two processes gives the same bits. Across thread counts it does not
    # (float_order.py says what is compared how). Read when MKL starts: before torch.
    "MKL_CBWR": "AUTO,STRICT",
    "DO_NOT_TRACK": "true",
    "MLFLOW_DISABLE_TELEMETRY": "true",
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "DVC_NO_ANALYTICS": "1",
}.items():
    os.environ.setdefault(_key, _value)


@pytest.fixture(scope="session")
def body():
    from m3t.body.anny_body import AnnyBody

    return AnnyBody()


@pytest.fixture(scope="session")
def fx_files(tmp_path_factory):
    """The synthetic SMPL-X / FLAME stand-in files (:mod:`smplfx_fixtures`), written once per test run."""
    from smplfx_fixtures import ensure_fixture_files

    return ensure_fixture_files(tmp_path_factory)


@pytest.fixture(scope="session")
def fx(fx_files):
    """The SMPL-FX model built from the synthetic SMPL-X / FLAME stand-in files (:mod:`smplfx_fixtures`)."""
    from smplfx_fixtures import fixture_body

    return fixture_body(fx_files)


@pytest.fixture(scope="module")
def truth(fx):
    """Ground truth of a ``fusion_fixtures.T``-frame SMPL-FX clip with its trackers' identities."""
    from fusion_fixtures import T, ground_truth

    return ground_truth(fx, frames=T, seed=7)


@pytest.fixture(scope="session")
def tiny_workspace(body, tmp_path_factory):
    """A tiny pipeline's workspace with real MLflow runs (:mod:`tiny_pipeline`): tokenizers, judge, SMLM."""
    from tiny_pipeline import build_workspace

    return build_workspace(tmp_path_factory.mktemp("workspace"), body)


@pytest.fixture(scope="module")
def shards_dir(body, tmp_path_factory) -> Path:
    """train / dev / test shards of smooth synthetic motion (3 .. 1 clips of 18 .. 41 frames), in the folder of
    corpus ``synthetic`` under a shards root (``data.shards_root`` = its parent)."""
    from builders import SPLITS
    from tiny_pipeline import write_shards

    return write_shards(tmp_path_factory.mktemp("shards") / "synthetic", body, SPLITS, text=lambda seed: "t")


@pytest.fixture(autouse=True)
def _torch_threads_restored():
    """A test that sets torch's thread count (for speed or determinism) does not change it for the tests after
    it: results of the float reductions, and so of short trainings, depend on it."""
    import torch

    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


# Markers of whole modules, by basename (unique over tests/; registered in pyproject.toml, `--strict-markers`):
# what each module starts or runs.
# `pytest -m "not slow"` is the fast lane; single slow tests of otherwise fast modules carry @pytest.mark.slow.
MODULE_MARKS: dict[str, tuple[str, ...]] = {
    "test_services": ("slow", "services"),
    "test_nightly": ("slow", "services", "e2e"),
    "test_mlflow_ui": ("slow", "services", "browser"),
    "test_dashboard_browser": ("slow", "browser", "e2e"),
    "test_browser_driver": ("slow", "browser"),
    "test_cluster": ("slow", "services"),
    "test_pipeline": ("slow", "e2e"),
    "test_smlm_pipeline": ("slow", "e2e"),
    "test_sgsa_pipeline": ("slow", "e2e"),
    "test_slr_mlflow": ("slow", "e2e"),
    "test_fusion_flow": ("slow", "e2e"),
    "test_determinism": ("slow", "e2e"),
    "test_faults": ("slow", "e2e"),
    "test_arithmetic": ("slow", "e2e"),
    "test_study": ("slow", "e2e"),
    "test_dashboard": ("slow", "e2e"),
    "test_score_pipeline": ("slow", "e2e"),  # scores the tiny pipeline's outputs
    "test_produce_pipeline": ("slow", "e2e"),  # produces from the tiny pipeline's checkpoints
    "test_baselines_pipeline": ("slow", "e2e"),  # evaluate-baselines on the tiny pipeline
    "test_translate_pipeline": ("slow", "e2e"),  # translates with the tiny pipeline's checkpoints
    "test_synthetic": ("slow",),       # generates whole corpora
    "test_synthetic_design": ("slow",),  # generates the study corpus
    "test_fit_batches": ("slow",),     # fits signer batches to convergence
    "test_experiment": ("slow",),      # opens fresh MLflow stores
}
# Fixtures that run pipeline stages or train models (by name, over every module): every test that uses one is
# slow whatever its module. tiny_workspace: the tiny pipeline with MLflow runs; shards_dir: a fitted tiny corpus;
# tokenizers / data (SLR): trained tokenizers and a probe corpus; overfit (SMLM), trained_pt / trained_sgsa: trained
# models.
SLOW_FIXTURES = frozenset({"tiny_workspace", "shards_dir", "tokenizers", "data", "overfit", "trained_pt",
                           "trained_sgsa"})


def pytest_collection_modifyitems(config, items):
    for item in items:
        module = item.module.__name__.rsplit(".", 1)[-1] if item.module else ""
        names = set(MODULE_MARKS.get(module, ()))
        if SLOW_FIXTURES & set(getattr(item, "fixturenames", ())):
            names.add("slow")
        for name in sorted(names):
            item.add_marker(getattr(pytest.mark, name))
