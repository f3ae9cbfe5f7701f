"""params.yaml reads in pipeline order, so a newcomer finds each section where the pipeline needs it."""
from __future__ import annotations

from pathlib import Path

import yaml

from m3t.config import SECTIONS

ROOT = Path(__file__).resolve().parents[2]
LEADING = ("data", "experiment")  # cross-cutting: every stage's folders, and where runs are logged


def pipeline_order(stages: dict) -> list[str]:
    """Sections in the order dvc.yaml's stages first read them (a stage's params list in its own order)."""
    order: list[str] = []
    for stage in stages.values():
        for key in stage.get("params", []):  # dotted keys of params.yaml (this project names no other file)
            section = str(key).split(".")[0]
            if section not in order:
                order.append(section)
    return order


def expected_order(stages: dict) -> list[str]:
    return [*LEADING, *(s for s in pipeline_order(stages) if s not in LEADING)]


def test_params_yaml_sections_are_in_pipeline_order():
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    found = list(yaml.safe_load((ROOT / "params.yaml").read_text()))
    expected = expected_order(stages)
    assert found == expected, ("params.yaml sections out of pipeline order; move them so they read\n  "
                               + ", ".join(expected))


def test_every_section_is_read_by_a_stage_or_leads():
    """A section no stage reads and that is not cross-cutting would have no place in the order."""
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    assert sorted(expected_order(stages)) == sorted(SECTIONS)


def test_order_check_catches_a_swapped_section():
    stages = {"a": {"params": ["body", "fitting.iters"]}, "b": {"params": ["tokenizer", "body.model"]}}
    assert pipeline_order(stages) == ["body", "fitting", "tokenizer"]
    stages = {"a": {"params": ["fitting"]}, "b": {"params": ["body", "fitting"]}}
    assert expected_order(stages) == ["data", "experiment", "fitting", "body"]
