"""Mapping -> (frozen) dataclass, every value checked against its field's annotation.

``build_dataclass(SGSAConfig, payload["config"], "config")`` rejects unknown keys and wrong types with a
message naming the dotted key (``config.trim.margin: expected an integer, got str 'two'``) and what is
allowed. Supported annotations: nested dataclasses, ``Literal``, ``Optional`` / unions, ``tuple[X, ...]`` and
fixed tuples (lists become tuples), ``dict[K, V]``, ``int``, ``float`` (an int becomes a float), ``str``,
``bool`` and ``Any`` (not checked). Missing keys take the field's default; a field without one is left to the
dataclass's own ``TypeError``. Errors are ``DataclassError`` unless the caller names its own class
(``m3t.config`` raises its ``ConfigError``).
"""
from __future__ import annotations

import dataclasses
import reprlib
import types
import typing
from functools import cache
from typing import Any, Literal, TypeVar, get_args, get_origin

T = TypeVar("T")


_SHORT = reprlib.Repr()
_SHORT.maxlevel, _SHORT.maxstring, _SHORT.maxother, _SHORT.maxlong = 2, 80, 80, 40
_SHORT.maxlist = _SHORT.maxtuple = _SHORT.maxdict = _SHORT.maxset = 4
SHORT_REPR_CHARS = 200


def short_repr(value: Any) -> str:
    """``repr`` of at most :data:`SHORT_REPR_CHARS` characters whatever the value's size: error messages name a
    value, never embed a huge one (a list of millions of items in a config file)."""
    text = _SHORT.repr(value)
    return text if len(text) <= SHORT_REPR_CHARS else text[:SHORT_REPR_CHARS - 3] + "..."


class DataclassError(ValueError):
    """A mapping that does not match its dataclass; the message names the dotted key and what is allowed."""


def type_name(tp: Any) -> str:
    if get_origin(tp) is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    return getattr(tp, "__name__", str(tp))


def coerce(value: Any, tp: Any, where: str, error: type[Exception] = DataclassError) -> Any:
    """Check ``value`` against the annotation ``tp``; return it converted (lists -> tuples, int -> float,
    mappings -> dataclasses). ``where`` names the value in messages."""
    origin = get_origin(tp)
    if tp is Any:  # open-ended values (e.g. a corpus adapter's options): the caller checks them
        return value
    if dataclasses.is_dataclass(tp):
        return build_dataclass(tp, value, where, error=error)
    if origin is dict:
        if not isinstance(value, dict):
            raise error(f"{where}: expected a mapping, got {type(value).__name__} {short_repr(value)}")
        key_tp, value_tp = get_args(tp)
        return {coerce(k, key_tp, f"{where} key {short_repr(k)}", error): coerce(v, value_tp, f"{where}.{k}", error)
                for k, v in value.items()}
    if origin is Literal:
        if value not in get_args(tp):
            raise error(f"{where}: {short_repr(value)} is not allowed; expected {type_name(tp)}")
        return value
    if origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        for arg in (a for a in args if a is not type(None)):
            try:
                return coerce(value, arg, where, error)
            except error:
                continue
        raise error(f"{where}: {short_repr(value)} matches none of {[type_name(a) for a in args]}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise error(f"{where}: expected a list, got {type(value).__name__} {short_repr(value)}")
        args = get_args(tp)
        item_tp = args[0] if len(args) == 2 and args[1] is Ellipsis else None
        if item_tp is None and len(args) != len(value):
            raise error(f"{where}: expected {len(args)} items, got {len(value)}")
        return tuple(
            coerce(v, item_tp if item_tp is not None else args[i], f"{where}[{i}]", error) for i, v in enumerate(value)
        )
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise error(f"{where}: expected a number, got {type(value).__name__} {short_repr(value)}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise error(f"{where}: expected an integer, got {type(value).__name__} {short_repr(value)}")
        return value
    if tp in (str, bool):
        if not isinstance(value, tp):
            raise error(f"{where}: expected {tp.__name__}, got {type(value).__name__} {short_repr(value)}")
        return value
    raise error(f"{where}: unsupported annotation {tp!r}")  # a bug in the dataclass, not in the mapping


@cache  # functools' cache is thread-safe; a class's fields and hints never change
def _fields(cls: type) -> tuple[tuple[str, ...], dict[str, Any]]:
    return tuple(f.name for f in dataclasses.fields(cls)), typing.get_type_hints(cls)


def build_dataclass(cls: type[T], values: dict[str, Any] | None, where: str, *, ignore_unknown: bool = False,
                    error: type[Exception] = DataclassError) -> T:
    """Build ``cls`` from a mapping (``None`` = empty), checking every key and type.

    ``ignore_unknown``: skip keys ``cls`` has no field for (stored records whose writers kept extra keys) instead
    of rejecting them. A ``ValueError`` of the dataclass's own checks (``__post_init__``) is re-raised as
    ``error`` prefixed with ``where``.
    """
    values = values or {}
    if not isinstance(values, dict):
        raise error(f"{where}: expected a mapping of keys, got {type(values).__name__}")
    allowed, hints = _fields(cls)
    known = set(allowed)
    unknown = sorted(set(values) - known, key=str)  # YAML keys may be numbers or null
    if unknown and not ignore_unknown:
        raise error(f"unknown key(s) {', '.join(f'{where}.{k}' for k in unknown)}; allowed keys in '{where}': "
                    f"{', '.join(allowed)}")
    kwargs = {k: coerce(v, hints[k], f"{where}.{k}", error) for k, v in values.items() if k in known}
    try:
        return cls(**kwargs)
    except error:
        raise
    except ValueError as exc:  # the dataclass's own consistency check (__post_init__)
        raise error(f"{where}: {exc}") from exc
