"""Shared fixtures: one Anny body model per session (built once into the project cache)."""
from __future__ import annotations

import os

import pytest

for _key, _value in {
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
