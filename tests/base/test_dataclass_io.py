"""Mapping -> dataclass conversion: types checked and converted, errors naming the dotted key."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from m3t.camera import Camera
from m3t.dataclass_io import DataclassError, build_dataclass


@dataclass(frozen=True)
class Inner:
    margin: int = 2
    mode: Literal["mean", "cls"] = "mean"

    def __post_init__(self) -> None:
        if self.margin < 0:
            raise ValueError(f"margin: expected >= 0, got {self.margin}")


@dataclass(frozen=True)
class Outer:
    size: int
    rate: float = 0.5
    name: str = ""
    levels: tuple[int, ...] = ()
    pair: tuple[str, int] = ("a", 1)
    heads: dict[str, int] = field(default_factory=dict)
    limit: int | None = None
    inner: Inner = field(default_factory=Inner)


def test_converts_lists_ints_and_nested_mappings():
    built = build_dataclass(Outer, {"size": 3, "rate": 1, "levels": [5, 5, 4], "pair": ["b", 2],
                                    "heads": {"x": 1}, "inner": {"mode": "cls"}}, "config")
    assert built == Outer(3, 1.0, "", (5, 5, 4), ("b", 2), {"x": 1}, None, Inner(2, "cls"))
    assert type(built.rate) is float and type(built.levels) is tuple and isinstance(built.inner, Inner)
    assert build_dataclass(Outer, {"size": 1, "limit": None}, "config").limit is None
    assert build_dataclass(Outer, {"size": 1, "limit": 7}, "config").limit == 7


@pytest.mark.parametrize(("values", "message"), [
    ({"size": "two"}, "config.size: expected an integer, got str 'two'"),
    ({"size": True}, "config.size: expected an integer, got bool True"),
    ({"size": 1, "rate": "fast"}, "config.rate: expected a number, got str 'fast'"),
    ({"size": 1, "levels": [5, "x"]}, "config.levels[1]: expected an integer, got str 'x'"),
    ({"size": 1, "levels": 5}, "config.levels: expected a list, got int 5"),
    ({"size": 1, "pair": ["a"]}, "config.pair: expected 2 items, got 1"),
    ({"size": 1, "heads": {"x": 1.5}}, "config.heads.x: expected an integer, got float 1.5"),
    ({"size": 1, "limit": "many"}, "config.limit: 'many' matches none of ['int', 'NoneType']"),
    ({"size": 1, "inner": {"margin": "two"}}, "config.inner.margin: expected an integer, got str 'two'"),
    ({"size": 1, "inner": {"mode": "max"}}, "config.inner.mode: 'max' is not allowed; expected one of 'mean', 'cls'"),
    ({"size": 1, "inner": {"margin": -1}}, "config.inner: margin: expected >= 0, got -1"),
    ({"size": 1, "inner": [1]}, "config.inner: expected a mapping of keys, got list"),
])
def test_wrong_values_name_the_dotted_key(values, message):
    with pytest.raises(DataclassError) as err:
        build_dataclass(Outer, values, "config")
    assert str(err.value) == message


def test_unknown_keys_are_rejected_with_the_allowed_ones_unless_ignored():
    with pytest.raises(DataclassError, match=r"^unknown key\(s\) config.inner.depth; allowed keys in "
                                             r"'config.inner': margin, mode$"):
        build_dataclass(Outer, {"size": 1, "inner": {"depth": 3}}, "config")
    assert build_dataclass(Inner, {"margin": 4, "stale": 1}, "trim", ignore_unknown=True) == Inner(4)


def test_missing_keys_take_defaults_and_the_callers_error_class_is_raised():
    assert build_dataclass(Inner, None, "trim") == Inner()

    class OwnError(ValueError):
        pass

    with pytest.raises(OwnError, match=r"^config.inner.margin: expected an integer"):
        build_dataclass(Outer, {"size": 1, "inner": {"margin": 1.5}}, "config", error=OwnError)


def test_camera_round_trips_through_its_dict():
    camera = Camera(500.0, 500.0, 256.0, 256.0, ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
                    (0.0, 0.1, 2.5), 512, 512)
    assert Camera.from_dict(camera.as_dict()) == camera
    with pytest.raises(DataclassError, match=r"camera.rotation\[1\]: expected 3 items, got 2"):
        Camera.from_dict({**camera.as_dict(), "rotation": [[1, 0, 0], [0, 1], [0, 0, 1]]})
