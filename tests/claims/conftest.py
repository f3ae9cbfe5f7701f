"""The claims' list rebuilt for every test of this folder.

:data:`m3t.claims.definitions.CLAIMS` is built when the module is first imported: each claim's collector is a
closure made then by a factory of :mod:`m3t.claims.collectors`. A test that reads the list made at import checks
the factories as they were then, not as they are while the test runs (mutation testing, which imports the
package once and then varies one function at a time, saw every change inside a factory survive). Rebuilding the
list per test makes the tests check the code that runs.
"""
from __future__ import annotations

import importlib

import pytest

import m3t.claims.definitions
import m3t.claims.verdicts


@pytest.fixture(autouse=True)
def claims_built_now(request, monkeypatch):
    fresh = importlib.reload(m3t.claims.definitions).CLAIMS
    for module in (request.module, m3t.claims.verdicts):
        if hasattr(module, "CLAIMS"):
            monkeypatch.setattr(module, "CLAIMS", fresh)
    defaults = m3t.claims.verdicts.claims_table.__defaults__  # (min_seeds, claims, seed); None when wrapped
    if defaults is not None:
        monkeypatch.setattr(m3t.claims.verdicts.claims_table, "__defaults__", (defaults[0], fresh, defaults[2]))
    return fresh
