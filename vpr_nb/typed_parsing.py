"""A value read by its type: the text of ``--set section.key=value`` (or JSON data) as a dataclass field's type.

:func:`parse_value` dispatches on the type: a scalar converter (bool, int, float, str) gives the value or
None when it does not fit (:data:`_SCALARS`); tuples, dicts and ``X | None`` parse their parts with
:func:`parse_value` again (:data:`_COMPOUND`). Used by :mod:`vpr_nb.config` for every field of a run config.
"""
from __future__ import annotations

import copy
import json
import types
import typing

import numpy as np


def _number(value):
    """The number a ``--set`` text spells (an int if it can be), else the value itself; None for a bool."""
    if isinstance(value, str):
        for kind in (int, float):
            try:
                return kind(value.strip())
            except ValueError:
                pass
    return None if isinstance(value, (bool, np.bool_)) else value


def _to_bool(v):
    if isinstance(v, (bool, np.bool_)) or (isinstance(v, int) and v in (0, 1)):
        return bool(v)
    text = v.strip().lower() if isinstance(v, str) else None
    return True if text in ("true", "yes", "on", "1") else False if text in ("false", "no", "off", "0") else None


def _to_int(v):
    n = _number(v)
    return int(n) if isinstance(n, (int, np.integer)) or (isinstance(n, float) and n.is_integer()) else None


def _to_float(v):
    n = _number(v)
    return float(n) if isinstance(n, (int, float, np.integer, np.floating)) else None


def _parse_tuple(value, args, where):
    if isinstance(value, str):
        try:
            value = json.loads(value.strip())
        except json.JSONDecodeError:
            value = [v for v in value.strip().strip("()[]").split(",") if v.strip()]
        if isinstance(value, (int, float, str)):
            value = [value]
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{where} must be a list, e.g. [1,5,10], got {value!r}")
    if not args:
        return tuple(value)
    if len(args) == 2 and args[1] is Ellipsis:
        args = (args[0],) * len(value)
    if len(value) != len(args):
        raise ValueError(f"{where} must have {len(args)} entries, got {list(value)!r}")
    return tuple(parse_value(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))


def _parse_dict(value, args, where):
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except json.JSONDecodeError:
            raise ValueError(f"{where} must be a JSON object, e.g. '{{\"width\": 8}}', got {value!r}") from None
    if not isinstance(value, dict):
        raise ValueError(f"{where} must be a dict (a JSON object), got {value!r}")
    return copy.deepcopy(value)


def _parse_optional(value, args, where):
    """``X | None``: None (also the text none / null / empty) if allowed, else the first type that parses."""
    if type(None) in args and (value is None or (isinstance(value, str) and value.strip().lower() in ("none", "null", ""))):
        return None
    errors = []
    for a in args:
        if a is not type(None):
            try:
                return parse_value(value, a, where)
            except ValueError as e:
                errors.append(str(e))
    raise ValueError(errors[0] if errors else f"{where}: cannot parse {value!r}")


_SCALARS = {bool: (_to_bool, "true or false"), int: (_to_int, "an integer"), float: (_to_float, "a number"),
            str: (lambda v: v if isinstance(v, str) else None, "a string")}
_COMPOUND = {tuple: _parse_tuple, dict: _parse_dict, typing.Union: _parse_optional, types.UnionType: _parse_optional}


def parse_value(value, tp, where: str):
    """``value`` (a Python value, or the text of ``--set``) as type ``tp``; ValueError naming ``where``."""
    kind, args = typing.get_origin(tp) or tp, typing.get_args(tp)
    if kind in _SCALARS:
        convert, what = _SCALARS[kind]
        out = convert(value)
        if out is None:
            raise ValueError(f"{where} must be {what}, got {value!r}")
        return out
    if kind in _COMPOUND:
        return _COMPOUND[kind](value, args, where)
    raise ValueError(f"{where}: unsupported field type {tp!r}")


__all__ = ["parse_value"]
