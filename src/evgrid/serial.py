"""One serialiser for every parameter dataclass of evgrid: plain JSON out, the dataclass back.

:func:`to_dict` writes fields in order (tuples as lists, paths as strings, nested dataclasses as
objects); :func:`from_dict` reads them back by the fields' types, and an unknown key, a missing
required key or a bad value is a :class:`ConfigError` naming the field. Light on purpose (no
numpy, no numba): the parameter classes' own ``to_dict``/``from_dict`` call it.
"""

from __future__ import annotations

import dataclasses
import os
import types
import typing
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["ConfigError", "to_dict", "from_dict"]


class ConfigError(ValueError):
    """A configuration file or value that cannot be used; the message names the file and field."""


# --- one serialiser for every parameter dataclass -------------------------------------------


def to_dict(obj: Any) -> Any:
    """Plain JSON of a (nested) dataclass: fields in order, tuples as lists, paths as strings."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init}
    if isinstance(obj, Mapping):
        return {str(k): to_dict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if hasattr(obj, "item") and callable(obj.item):  # a numpy scalar
        return obj.item()
    return obj


def from_dict(cls: type, d: Any, where: str | None = None, required: Sequence[str] = ()) -> Any:
    """Build dataclass ``cls`` from plain JSON, nested dataclasses included (inverse of
    :func:`to_dict`). Unknown keys, missing ``required`` keys and bad values are
    :class:`ConfigError` naming the field; other missing keys take their defaults."""
    where = where or cls.__name__
    if not isinstance(d, Mapping):
        raise ConfigError(f"{where}: expected an object, got {d!r}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls) if f.init]
    unknown = sorted(set(d) - set(names))
    if unknown:
        raise ConfigError(f"{where}: unknown field(s) {unknown}; known: {names}")
    kwargs = {n: _convert(hints[n], d[n], f"{where}.{n}") for n in names if n in d}
    missing = [n for n in required if n not in d]
    if missing:
        raise ConfigError(f"{where}: missing section(s) {missing}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: {e}") from None


def _convert(tp: Any, v: Any, where: str) -> Any:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, v, where)
    if origin in (typing.Union, types.UnionType):
        if v is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1:
            return _convert(inner[0], v, where)
        return v
    if origin is tuple:
        if not isinstance(v, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {v!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], x, f"{where}[{i}]") for i, x in enumerate(v))
        if args and len(args) != len(v):
            raise ConfigError(f"{where}: expected {len(args)} values, got {v!r}")
        return tuple(_convert(a, x, f"{where}[{i}]") for i, (a, x) in enumerate(zip(args, v)))
    if tp is float and isinstance(v, int) and not isinstance(v, bool):
        return float(v)
    if tp in (bool, int, float, str) and not isinstance(v, tp) or (tp is int and v is True):
        raise ConfigError(f"{where}: expected {tp.__name__}, got {v!r}")
    return v
