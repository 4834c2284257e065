"""One way to validate parameters at the boundary: each check names the owner, the field and the
bad value.

Parameter dataclasses call :func:`check_int` / :func:`check_number` from ``__post_init__`` so that
every message reads the same: ``RayIlmParams.max_range_m must be > 0, got -1.0``.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

__all__ = ["check_int", "check_number", "check_mass", "check_choice"]


def _label(owner: Any, name: str) -> str:
    prefix = owner if isinstance(owner, str) else type(owner).__name__
    return f"{prefix}.{name}" if prefix else name


def _value(owner: Any, name: str, value: Any) -> Any:
    return getattr(owner, name) if value is _MISSING else value


_MISSING = object()


def check_int(
    owner: Any, name: str, value: Any = _MISSING, *, min: int | None = None, max: int | None = None
) -> int:
    """An integer (not a bool) within ``[min, max]``; returns it as ``int``."""
    v = _value(owner, name, value)
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise ValueError(f"{_label(owner, name)} must be an integer, got {v!r}")
    if min is not None and v < min:
        raise ValueError(f"{_label(owner, name)} must be >= {min}, got {v!r}")
    if max is not None and v > max:
        raise ValueError(f"{_label(owner, name)} must be <= {max}, got {v!r}")
    return int(v)


def check_number(
    owner: Any,
    name: str,
    value: Any = _MISSING,
    *,
    min: float | None = None,
    max: float | None = None,
    min_open: bool = False,
    max_open: bool = False,
) -> float:
    """A finite real number within the given bounds (closed unless ``*_open``); returns it as
    ``float``."""
    v = _value(owner, name, value)
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v):
        raise ValueError(f"{_label(owner, name)} must be a finite number, got {v!r}")
    if min is not None and (v <= min if min_open else v < min):
        raise ValueError(
            f"{_label(owner, name)} must be {'>' if min_open else '>='} {min}, got {v!r}"
        )
    if max is not None and (v >= max if max_open else v > max):
        raise ValueError(
            f"{_label(owner, name)} must be {'<' if max_open else '<='} {max}, got {v!r}"
        )
    return float(v)


def check_mass(owner: Any, name: str, value: Any = _MISSING) -> float:
    """A mass in [0, 1]."""
    return check_number(owner, name, value, min=0.0, max=1.0)


def check_choice(owner: Any, name: str, value: Any = _MISSING, *, choices: tuple) -> Any:
    """One of ``choices``."""
    v = _value(owner, name, value)
    if v not in choices:
        raise ValueError(f"{_label(owner, name)} must be one of {choices}, got {v!r}")
    return v
