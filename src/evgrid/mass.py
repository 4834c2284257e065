"""The evidential algebra on the frame {free, occupied}: masses ``[m_f, m_o, m_u]`` (paper sec. III).

Every public function takes arrays of shape ``(..., 3)`` (masses) or ``(..., 2)`` (evidence)
and broadcasts over the leading axes; outputs are float32. Masses are dimensionless, each in
[0, 1], summing to 1. The combination rules run as compiled numba kernels; the per-cell
formulas below (``_*_cell``) are shared with the map update rules in :mod:`evgrid.fusion`.

Numerics: every kernel works in float64 and renormalises its output by its own sum, which
equals the paper's ``1 - K`` (Dempster) or ``1`` (Yager) in exact arithmetic. This keeps any
chain of updates on the simplex in float32.
"""

from __future__ import annotations

import math

import numba
import numpy as np

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

_SUM_ATOL = 1e-5


def vacuous(shape: tuple[int, ...]) -> np.ndarray:
    """A float32 mass grid of ``shape + (3,)`` holding the vacuous mass everywhere."""
    m = np.zeros(tuple(shape) + (3,), dtype=np.float32)
    m[..., 2] = 1.0
    return m


def validate(m: np.ndarray, name: str = "m", atol: float = _SUM_ATOL) -> np.ndarray:
    """Check that ``m`` is a mass array ``(..., 3)``; raise ValueError naming the problem."""
    a = np.asarray(m)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"{name}: the last axis must be [m_f, m_o, m_u] of length 3, got shape {a.shape}")
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
        raise ValueError(f"{name}: masses must sum to 1 within {atol:g}, worst sum {float(s.flat[int(off.argmax())]):.6g}")
    return a


# --- per-cell formulas (float64 scalars in, normalised float64 triple out) ---------------------
# Branch-free (selects only) and compiled with error_model="numpy", so that LLVM vectorises the
# row loops below: numba's default error model guards every division with a branch.

_JIT = dict(cache=True, fastmath=True, error_model="numpy")
_TINY = 1e-30


@numba.njit(inline="always", **_JIT)
def _normalise_cell(f, o, u):
    s = f + o + u
    ok = s > _TINY
    r = 1.0 / (s if ok else 1.0)
    return (f * r if ok else 0.0), (o * r if ok else 0.0), (u * r if ok else 1.0)


@numba.njit(inline="always", **_JIT)
def _dempster_cell(f1, o1, u1, f2, o2, u2):
    # Paper eq. (dempsters_rule); f + o + u equals 1 - K for normalised inputs, so dividing by
    # it normalises. Total conflict (1 - K = 0) is undefined: vacuous (DESIGN 1).
    f = f1 * f2 + f1 * u2 + u1 * f2
    o = o1 * o2 + o1 * u2 + u1 * o2
    u = u1 * u2
    return _normalise_cell(f, o, u)


@numba.njit(inline="always", **_JIT)
def _yager_cell(f1, o1, u1, f2, o2, u2):
    # Paper eq. (yagers_rule): the conflict K goes to the unknown mass.
    k = f1 * o2 + o1 * f2
    f = f1 * f2 + f1 * u2 + u1 * f2
    o = o1 * o2 + o1 * u2 + u1 * o2
    u = u1 * u2 + k
    return _normalise_cell(f, o, u)


@numba.njit(inline="always", **_JIT)
def _limit_unknown_cell(f, o, u, m_u_min):
    # Paper eq. (lower_un_mass_limit): move Delta = max(0, m_u_min - m_u) into m_u, taking it
    # from m_f and m_o in proportion (their ratio is kept); m_f + m_o = 0 stays unchanged.
    s = f + o
    d = m_u_min - u
    d = d if (d > 0.0 and s > 0.0) else 0.0
    a = 1.0 - d / (s if s > 0.0 else 1.0)
    return f * a, o * a, u + d


@numba.njit(inline="always", **_JIT)
def _tanh_pos(y):
    # tanh(y) for y >= 0 as -e / (2 + e) with e = expm1(-2 y). expm1 of z/64 by its Taylor
    # series, then (1 + e)^2 - 1 = e (2 + e) six times: multiplications only, so it vectorises,
    # and no cancellation for small y. Absolute error < 1e-14 against math.tanh.
    y = y if y < 20.0 else 20.0
    z = y * (-2.0 / 64.0)
    e = z * (1.0 + z * (1.0 / 2 + z * (1.0 / 6 + z * (1.0 / 24 + z * (1.0 / 120 + z * (1.0 / 720 + z * (
        1.0 / 5040 + z * (1.0 / 40320 + z * (1.0 / 362880 + z * (1.0 / 3628800 + z * (1.0 / 39916800)))))))))))
    for _ in range(6):
        e = e * (2.0 + e)
    return -e / (2.0 + e)


@numba.njit(inline="always", **_JIT)
def _gamma_cell(f1, o1, u1, f2, o2, u2, m_u_min, alpha):
    # DESIGN 2: gamma = min(tanh(alpha * max(0, m_u_map - m_u_pred)), exact bound), in [0, 1].
    # The paper's bound (eq. gamma) holds K fixed; K scales with gamma, so the exact bound is
    # (m_u_map - m_u_min) / (m_u_map * (1 - m_u_pred) - K0) where that denominator is > 0.
    x = u1 - u2
    g = _tanh_pos(alpha * (x if x > 0.0 else 0.0))
    den = u1 * (1.0 - u2) - (f1 * o2 + o1 * f2)
    b = (u1 - m_u_min) / (den if den > _TINY else 1.0)
    g = b if (den > _TINY and b < g) else g
    g = g if g > 0.0 else 0.0
    return g if g < 1.0 else 1.0


@numba.njit(inline="always", **_JIT)
def _deep_disc_cell(f1, o1, u1, f2, o2, u2, m_u_min, alpha):
    # DESIGN 5, deep_disc: m = limit_unknown(pred); map <- map (+)_Y (gamma (x) m). gamma = 0
    # gives back the map cell itself.
    f1, o1, u1 = _normalise_cell(f1, o1, u1)
    f2, o2, u2 = _normalise_cell(f2, o2, u2)
    f2, o2, u2 = _limit_unknown_cell(f2, o2, u2, m_u_min)
    g = _gamma_cell(f1, o1, u1, f2, o2, u2, m_u_min, alpha)
    # Paper eq. (discount_eq), then Yager.
    return _yager_cell(f1, o1, u1, g * f2, g * o2, 1.0 - g + g * u2)


# --- kernels over rows -------------------------------------------------------------------------
# A (h, w, 3) view whose rows are contiguous travels as a flat float32 buffer and a row stride
# (elements): cell (i, j) starts at i * rs + 3 * j. See `rows()`.

@numba.njit(**_JIT)
def _k_dempster(a, ars, b, brs, out, ors, h, w):
    for i in range(h):
        ra, rb, ro = a[i * ars:i * ars + 3 * w], b[i * brs:i * brs + 3 * w], out[i * ors:i * ors + 3 * w]
        for j in range(w):
            p = 3 * j
            f, o, u = _dempster_cell(
                np.float64(ra[p]), np.float64(ra[p + 1]), np.float64(ra[p + 2]),
                np.float64(rb[p]), np.float64(rb[p + 1]), np.float64(rb[p + 2]),
            )
            ro[p] = f
            ro[p + 1] = o
            ro[p + 2] = u


@numba.njit(**_JIT)
def _k_yager(a, ars, b, brs, out, ors, h, w):
    for i in range(h):
        ra, rb, ro = a[i * ars:i * ars + 3 * w], b[i * brs:i * brs + 3 * w], out[i * ors:i * ors + 3 * w]
        for j in range(w):
            p = 3 * j
            f, o, u = _yager_cell(
                np.float64(ra[p]), np.float64(ra[p + 1]), np.float64(ra[p + 2]),
                np.float64(rb[p]), np.float64(rb[p + 1]), np.float64(rb[p + 2]),
            )
            ro[p] = f
            ro[p + 1] = o
            ro[p + 2] = u


@numba.njit(**_JIT)
def _k_gamma(a, ars, b, brs, m_u_min, alpha, out, h, w):
    for i in range(h):
        ra, rb, ro = a[i * ars:i * ars + 3 * w], b[i * brs:i * brs + 3 * w], out[i * w:(i + 1) * w]
        for j in range(w):
            p = 3 * j
            f1, o1, u1 = _normalise_cell(np.float64(ra[p]), np.float64(ra[p + 1]), np.float64(ra[p + 2]))
            f2, o2, u2 = _normalise_cell(np.float64(rb[p]), np.float64(rb[p + 1]), np.float64(rb[p + 2]))
            ro[j] = _gamma_cell(f1, o1, u1, f2, o2, u2, m_u_min, alpha)


def rows(v: np.ndarray) -> tuple[np.ndarray, int, int, int]:
    """A ``(h, w, 3)`` float32 view with contiguous rows as ``(flat buffer, row stride, h, w)``.

    The flat buffer spans the view's memory from its first to its last element (the gaps
    between rows belong to the parent array and are never touched by the kernels).
    """
    if v.ndim != 3 or v.shape[2] != 3 or v.dtype != np.float32:
        raise ValueError(f"expected a float32 (h, w, 3) array, got {v.dtype} {v.shape}")
    h, w = v.shape[0], v.shape[1]
    if h == 0 or w == 0:
        return np.zeros(0, np.float32), 0, 0, 0
    if v.strides[2] != 4 or v.strides[1] != 12 or v.strides[0] % 4 or v.strides[0] < 12 * w:
        raise ValueError(f"rows of the (h, w, 3) array must be contiguous, got strides {v.strides}")
    rs = v.strides[0] // 4 if h > 1 else 3 * w
    flat = np.lib.stride_tricks.as_strided(v, shape=((h - 1) * rs + 3 * w,), strides=(4,), writeable=v.flags.writeable)
    return flat, rs, h, w


def _pair3d(m1: np.ndarray, m2: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    a = np.asarray(m1)
    b = np.asarray(m2)
    for name, x in (("m1", a), ("m2", b)):
        if x.ndim == 0 or x.shape[-1] != 3:
            raise ValueError(f"{name}: the last axis must be [m_f, m_o, m_u] of length 3, got shape {x.shape}")
    a, b = np.broadcast_arrays(a, b)
    shape = a.shape
    a3 = np.ascontiguousarray(a, dtype=np.float32).reshape(1, -1, 3)
    b3 = np.ascontiguousarray(b, dtype=np.float32).reshape(1, -1, 3)
    return a3, b3, shape


def _combine(kernel, m1: np.ndarray, m2: np.ndarray, out: np.ndarray | None) -> np.ndarray:
    a, b, shape = _pair3d(m1, m2)
    if out is None:
        res = np.empty(shape, dtype=np.float32)
    else:
        if out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ValueError(f"out must be a C-contiguous float32 array of shape {shape}, got {out.shape} {out.dtype}")
        res = out
    fa, ars, h, w = rows(a)
    fb, brs, _, _ = rows(b)
    fo, ors, _, _ = rows(res.reshape(1, -1, 3))
    kernel(fa, ars, fb, brs, fo, ors, h, w)
    return res


def conflict(m1: np.ndarray, m2: np.ndarray) -> np.ndarray:
    """Conflict ``K = m_f1 m_o2 + m_o1 m_f2`` (paper eq. conflict), shape ``(...)``."""
    a = np.asarray(m1, dtype=np.float32)
    b = np.asarray(m2, dtype=np.float32)
    return (a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0]).astype(np.float32)


def dempster(m1: np.ndarray, m2: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Dempster's rule ``m1 (+)_D m2`` (paper eq. dempsters_rule); total conflict gives [0, 0, 1]."""
    return _combine(_k_dempster, m1, m2, out)


def yager(m1: np.ndarray, m2: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Yager's rule ``m1 (+)_Y m2`` (paper eq. yagers_rule): the conflict K goes to m_u."""
    return _combine(_k_yager, m1, m2, out)


def _check_unit(name: str, v: np.ndarray | float) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if not np.isfinite(a).all() or (a < 0).any() or (a > 1).any():
        raise ValueError(f"{name} must lie in [0, 1], got {v!r}")
    return a


def discount(m: np.ndarray, gamma: np.ndarray | float) -> np.ndarray:
    """Discounting ``gamma (x) m = [g m_f, g m_o, 1 - g + g m_u]`` (paper eq. discount_eq), gamma in [0, 1]."""
    a = np.asarray(m, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"m: the last axis must be of length 3, got shape {a.shape}")
    g = _check_unit("gamma", gamma)
    out = np.stack([g * a[..., 0], g * a[..., 1], 1.0 - g + g * a[..., 2]], axis=-1)
    return out.astype(np.float32)


def limit_unknown(m: np.ndarray, m_u_min: float) -> np.ndarray:
    """Lower limit on unknown mass ``m (box+) m_u_min`` (paper eq. lower_un_mass_limit).

    Raises m_u to at least ``m_u_min``, taking the difference from m_f and m_o in proportion,
    so their ratio is kept. A cell with ``m_f + m_o = 0`` is returned unchanged.
    """
    _check_unit("m_u_min", m_u_min)
    a = np.asarray(m, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"m: the last axis must be of length 3, got shape {a.shape}")
    d = np.maximum(0.0, float(m_u_min) - a[..., 2])
    s = a[..., 0] + a[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = np.where(s > 0, d / np.where(s > 0, s, 1.0), 0.0)
    d = np.where(s > 0, d, 0.0)
    out = np.stack([(1 - alpha) * a[..., 0], (1 - alpha) * a[..., 1], a[..., 2] + d], axis=-1)
    return out.astype(np.float32)


def from_evidence(e: np.ndarray) -> np.ndarray:
    """Subjective-logic masses from evidence ``[e_f, e_o] >= 0``: ``[e_f/S, e_o/S, 2/S]``, ``S = 2 + e_f + e_o``."""
    a = np.asarray(e, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != 2:
        raise ValueError(f"e: the last axis must be [e_f, e_o] of length 2, got shape {a.shape}")
    if not np.isfinite(a).all() or (a < 0).any():
        raise ValueError("e: evidence must be finite and non-negative")
    s = 2.0 + a[..., 0] + a[..., 1]
    return np.stack([a[..., 0] / s, a[..., 1] / s, 2.0 / s], axis=-1).astype(np.float32)


def pignistic_occupied(m: np.ndarray) -> np.ndarray:
    """Occupancy probability ``p_o = m_o + m_u / 2`` (paper eq. pignistic_prob), shape ``(...)``."""
    a = np.asarray(m, dtype=np.float32)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"m: the last axis must be of length 3, got shape {a.shape}")
    return (a[..., 1] + 0.5 * a[..., 2]).astype(np.float32)


def deep_discount_factor(
    m_map: np.ndarray, m_pred: np.ndarray, m_u_min: float, alpha: float = 10.0
) -> np.ndarray:
    """Discount factor gamma in [0, 1] for a deep-ISM prediction (paper eq. gamma, DESIGN 2), shape ``(...)``.

    ``gamma = min(tanh(alpha * max(0, m_u_map - m_u_pred)), (m_u_map - m_u_min) / (m_u_map
    (1 - m_u_pred) - K0))``, the bound applying where its denominator is positive; ``m_pred``
    is expected to be limited to ``m_u_min`` already.
    """
    _check_unit("m_u_min", m_u_min)
    if not (math.isfinite(alpha) and alpha >= 0):
        raise ValueError(f"alpha must be finite and >= 0, got {alpha!r}")
    a, b, shape = _pair3d(m_map, m_pred)
    out = np.empty(shape[:-1], dtype=np.float32)
    fa, ars, h, w = rows(a)
    fb, brs, _, _ = rows(b)
    _k_gamma(fa, ars, fb, brs, float(m_u_min), float(alpha), out.reshape(-1), h, w)
    return out
