"""The evidential algebra on the frame {free, occupied}: masses ``[m_f, m_o, m_u]`` (sec. III).

Every public function takes arrays of shape ``(..., 3)`` (masses) or ``(..., 2)`` (evidence)
and broadcasts over the leading axes; outputs are float32. Masses are dimensionless, each in
[0, 1], summing to 1. The combination rules run as compiled numba kernels; their per-cell
formulas (``_*_cell`` in :mod:`evgrid.kernels`) are shared with the map update rules in
:mod:`evgrid.fusion`. Equation numbers are the paper's (docs/equations.md).

Numerics: every kernel works in float64 and renormalises its output by its own sum, which
equals the paper's ``1 - K`` (Dempster) or ``1`` (Yager) in exact arithmetic. This keeps any
chain of updates on the simplex in float32.

Every function checks its mass arguments first (one compiled pass) and raises ValueError
naming the argument when a cell holds NaN or inf, a negative mass, or masses not summing to 1
within 1e-5; nothing is written then. Renormalising an invalid input would hide the error.
"""

from __future__ import annotations

import math

import numpy as np

from evgrid.kernels import MASS_ATOL, count_invalid, dempster_rows, gamma_rows, rows, yager_rows

__all__ = [
    "VACUOUS",
    "validate",
    "conflict",
    "dempster",
    "yager",
    "discount",
    "limit_unknown",
    "from_evidence",
    "pignistic_occupied",
    "deep_discount_factor",
    "vacuous",
]

#: The vacuous mass [m_f, m_o, m_u] = [0, 0, 1]: no information.
VACUOUS = np.array([0.0, 0.0, 1.0], dtype=np.float32)

_SUM_ATOL = MASS_ATOL


def vacuous(shape: tuple[int, ...]) -> np.ndarray:
    """A float32 mass grid of ``shape + (3,)`` holding the vacuous mass everywhere."""
    m = np.zeros(tuple(shape) + (3,), dtype=np.float32)
    m[..., 2] = 1.0
    return m


def validate(m: np.ndarray, name: str = "m", atol: float = _SUM_ATOL) -> np.ndarray:
    """Check that ``m`` is a mass array ``(..., 3)``; raise ValueError naming the problem."""
    a = np.asarray(m)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(
            f"{name}: the last axis must be [m_f, m_o, m_u] of length 3, got shape {a.shape}"
        )
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"{name}: masses must be floating point, got dtype {a.dtype}")
    if not np.isfinite(a).all():
        bad = int((~np.isfinite(a)).any(axis=-1).sum())
        raise ValueError(f"{name}: {bad} cell(s) hold NaN or inf")
    if (a < 0).any():
        raise ValueError(f"{name}: negative mass (min {float(a.min()):.3g})")
    if (a > 1).any():
        raise ValueError(f"{name}: mass above 1 (max {float(a.max()):.6g})")
    s = a.sum(axis=-1, dtype=np.float64)
    off = np.abs(s - 1.0)
    if (off > atol).any():
        raise ValueError(
            f"{name}: masses must sum to 1 within {atol:g}, "
            f"worst sum {float(s.flat[int(off.argmax())]):.6g}"
        )
    return a


def _masses32(m: np.ndarray, name: str) -> np.ndarray:
    """``m`` as a C-contiguous float32 mass array ``(..., 3)``; ValueError naming ``name`` if it is
    not one."""
    a = np.asarray(m)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(
            f"{name}: the last axis must be [m_f, m_o, m_u] of length 3, got shape {a.shape}"
        )
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name}: masses must be real numbers, got dtype {a.dtype}")
    a = np.ascontiguousarray(a, dtype=np.float32)
    flat, rs, h, w = rows(a.reshape(1, -1, 3))
    if count_invalid(flat, rs, h, w):
        validate(a, name)  # says what is wrong
        raise ValueError(f"{name}: not a mass array (NaN, inf, negative, or not summing to 1)")
    return a


def _pair3d(
    m1: np.ndarray, m2: np.ndarray, names: tuple[str, str] = ("m1", "m2")
) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    a = _masses32(m1, names[0])
    b = _masses32(m2, names[1])
    shape = np.broadcast_shapes(a.shape, b.shape)
    a3 = np.ascontiguousarray(
        np.broadcast_to(a, shape) if a.shape != shape else a, dtype=np.float32
    )
    b3 = np.ascontiguousarray(
        np.broadcast_to(b, shape) if b.shape != shape else b, dtype=np.float32
    )
    a3, b3 = a3.reshape(1, -1, 3), b3.reshape(1, -1, 3)
    return a3, b3, shape


def _combine(kernel, m1: np.ndarray, m2: np.ndarray, out: np.ndarray | None) -> np.ndarray:
    a, b, shape = _pair3d(m1, m2)
    if out is None:
        res = np.empty(shape, dtype=np.float32)
    else:
        if out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ValueError(
                f"out must be a C-contiguous float32 array of shape {shape}, "
                f"got {out.shape} {out.dtype}"
            )
        res = out
    fa, ars, h, w = rows(a)
    fb, brs, _, _ = rows(b)
    fo, ors, _, _ = rows(res.reshape(1, -1, 3))
    kernel(fa, ars, fb, brs, fo, ors, h, w)
    return res


def conflict(m1: np.ndarray, m2: np.ndarray) -> np.ndarray:
    """Conflict ``K = m_f1 m_o2 + m_o1 m_f2`` (paper eq. (7)), shape ``(...)``."""
    a = _masses32(m1, "m1")
    b = _masses32(m2, "m2")
    return (a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0]).astype(np.float32)


def dempster(m1: np.ndarray, m2: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Dempster's rule ``m1 (+)_D m2`` (paper eq. (5)).

    Total conflict gives [0, 0, 1] (docs/decisions.md#total-conflict).
    """
    return _combine(dempster_rows, m1, m2, out)


def yager(m1: np.ndarray, m2: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Yager's rule ``m1 (+)_Y m2`` (paper eq. (6)): the conflict K goes to m_u."""
    return _combine(yager_rows, m1, m2, out)


def _check_unit(name: str, v: np.ndarray | float) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if not np.isfinite(a).all() or (a < 0).any() or (a > 1).any():
        raise ValueError(f"{name} must lie in [0, 1], got {v!r}")
    return a


def discount(m: np.ndarray, gamma: np.ndarray | float) -> np.ndarray:
    """Discounting ``gamma (x) m = [g m_f, g m_o, 1 - g + g m_u]`` (eq. (8)), gamma in [0, 1]."""
    _masses32(m, "m")
    a = np.asarray(m, dtype=np.float64)
    g = _check_unit("gamma", gamma)
    out = np.stack([g * a[..., 0], g * a[..., 1], 1.0 - g + g * a[..., 2]], axis=-1)
    return out.astype(np.float32)


def limit_unknown(m: np.ndarray, m_u_min: float) -> np.ndarray:
    """Lower limit on unknown mass ``m (box+) m_u_min`` (paper eqs. (15)-(16)).

    Raises m_u to at least ``m_u_min``, taking the difference from m_f and m_o in proportion,
    so their ratio is kept. A cell with ``m_f + m_o = 0`` is returned unchanged
    (docs/decisions.md#box-plus-on-a-vacuous-mass).
    """
    _check_unit("m_u_min", m_u_min)
    _masses32(m, "m")
    a = np.asarray(m, dtype=np.float64)
    d = np.maximum(0.0, float(m_u_min) - a[..., 2])
    s = a[..., 0] + a[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = np.where(s > 0, d / np.where(s > 0, s, 1.0), 0.0)
    d = np.where(s > 0, d, 0.0)
    out = np.stack([(1 - alpha) * a[..., 0], (1 - alpha) * a[..., 1], a[..., 2] + d], axis=-1)
    return out.astype(np.float32)


def from_evidence(e: np.ndarray) -> np.ndarray:
    """Subjective-logic masses from evidence ``[e_f, e_o] >= 0``: ``[e_f/S, e_o/S, 2/S]`` with
    ``S = 2 + e_f + e_o``.

    Paper eqs. (9), (10) and (14). Evidence 0 is accepted (the paper says strictly positive):
    it is the vacuous mass, and a network's softplus output can underflow to 0. Evidence so
    large that S overflows (about 1e308) still gives a mass: ``[1e308, 1e308]`` is
    ``[0.5, 0.5, 0]``.
    """
    a = np.asarray(e, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != 2:
        raise ValueError(f"e: the last axis must be [e_f, e_o] of length 2, got shape {a.shape}")
    if not np.isfinite(a).all() or (a < 0).any():
        raise ValueError("e: evidence must be finite and non-negative")
    with np.errstate(over="ignore"):
        s = 2.0 + a[..., 0] + a[..., 1]
    out = np.stack([a[..., 0] / s, a[..., 1] / s, 2.0 / s], axis=-1)
    over = ~np.isfinite(s)
    if over.any():
        # S overflows float64 only for evidence near 1e308, where e / S would be 0 / 0 = [0, 0,
        # 0]: scale by the larger evidence first (the same masses in exact arithmetic)
        b = a[over]
        t = b.max(axis=-1, keepdims=True)
        b = b / t
        st = 2.0 / t[..., 0] + b[..., 0] + b[..., 1]
        out[over] = np.stack([b[..., 0] / st, b[..., 1] / st, (2.0 / t[..., 0]) / st], axis=-1)
    return out.astype(np.float32)


def pignistic_occupied(m: np.ndarray) -> np.ndarray:
    """Occupancy probability ``p_o = m_o + m_u / 2`` (paper eq. (13)), shape ``(...)``."""
    a = _masses32(m, "m")
    return (a[..., 1] + 0.5 * a[..., 2]).astype(np.float32)


def deep_discount_factor(
    m_map: np.ndarray, m_pred: np.ndarray, m_u_min: float, alpha: float = 10.0
) -> np.ndarray:
    """Discount factor gamma in [0, 1] for a deep-ISM prediction (paper eq. (35)), shape ``(...)``.

    ``gamma = min(tanh(alpha * max(0, m_u_map - m_u_pred)), (m_u_map - m_u_min) / (m_u_map
    (1 - m_u_pred) - K0))``, the bound applying where its denominator is positive; ``m_pred``
    is expected to be limited to ``m_u_min`` already. The bound is exact where the paper's is
    not, and the gain uses eq. (35)'s sign (docs/decisions.md#exact-gamma-bound).
    """
    _check_unit("m_u_min", m_u_min)
    if not (math.isfinite(alpha) and alpha >= 0):
        raise ValueError(f"alpha must be finite and >= 0, got {alpha!r}")
    a, b, shape = _pair3d(m_map, m_pred, ("m_map", "m_pred"))
    out = np.empty(shape[:-1], dtype=np.float32)
    fa, ars, h, w = rows(a)
    fb, brs, _, _ = rows(b)
    gamma_rows(fa, ars, fb, brs, float(m_u_min), float(alpha), out.reshape(-1), h, w)
    return out
