"""Compiled numba kernels of the evidential algebra and the map update rules.

All per-cell formulas and every kernel that inlines them live in this one module: numba's
on-disk cache is invalidated only when the jitted function's own file changes, so kernels in
another module would keep stale copies of an edited formula.

Kernels take ``(h, w, 3)`` float32 views as a flat buffer and a row stride (see
:func:`rows`), loop rows, and are branch-free with ``error_model="numpy"`` so that LLVM
vectorises them (numba's default error model guards every division with a branch).

Masses are checked where they enter: a cell with NaN or inf, a negative mass, or masses not
summing to 1 within ``MASS_ATOL`` is invalid (:func:`_valid_cell`). The combination kernels
count invalid input cells; the in-place map kernels leave the map cell under an invalid ISM
cell untouched and return how many they rejected. These kernels are compiled without the
``nnan``/``ninf`` fast-math flags, under which LLVM may assume that no value is NaN and fold the
checks away; the other flags (and so vectorisation and the results for valid cells) are kept.
"""

from __future__ import annotations


import numba
import numpy as np

# --- per-cell formulas (float64 scalars in, normalised float64 triple out) ---------------------

_JIT = dict(cache=True, fastmath=True, error_model="numpy")
# fast math without nnan/ninf: comparisons keep their IEEE meaning for NaN and inf
_CHECKED = dict(cache=True, fastmath={"nsz", "arcp", "contract", "afn", "reassoc"}, error_model="numpy")
_TINY = 1e-30
#: Masses of a valid cell sum to 1 within this (as evgrid.mass.validate checks).
MASS_ATOL = 1e-5


@numba.njit(inline="always", **_CHECKED)
def _valid_cell(f, o, u):
    # Paper eqs. (3)-(4): each mass >= 0, their sum 1. NaN fails every comparison and an inf
    # makes the sum miss 1, so one expression rejects both (compiled without nnan/ninf).
    return (f >= 0.0) and (o >= 0.0) and (u >= 0.0) and (abs(f + o + u - 1.0) <= MASS_ATOL)


@numba.njit(inline="always", **_JIT)
def _normalise_cell(f, o, u):
    s = f + o + u
    ok = s > _TINY
    r = 1.0 / (s if ok else 1.0)
    return (f * r if ok else 0.0), (o * r if ok else 0.0), (u * r if ok else 1.0)


@numba.njit(inline="always", **_JIT)
def _dempster_cell(f1, o1, u1, f2, o2, u2):
    # Paper eq. (5); f + o + u equals 1 - K for normalised inputs, so dividing by it
    # normalises. Total conflict (1 - K = 0) is undefined: vacuous (docs/decisions.md#total-conflict).
    f = f1 * f2 + f1 * u2 + u1 * f2
    o = o1 * o2 + o1 * u2 + u1 * o2
    u = u1 * u2
    return _normalise_cell(f, o, u)


@numba.njit(inline="always", **_JIT)
def _yager_cell(f1, o1, u1, f2, o2, u2):
    # Paper eq. (6): the conflict K (eq. (7)) goes to the unknown mass.
    k = f1 * o2 + o1 * f2
    f = f1 * f2 + f1 * u2 + u1 * f2
    o = o1 * o2 + o1 * u2 + u1 * o2
    u = u1 * u2 + k
    return _normalise_cell(f, o, u)


@numba.njit(inline="always", **_JIT)
def _limit_unknown_cell(f, o, u, m_u_min):
    # Paper eqs. (15)-(16): move Delta = max(0, m_u_min - m_u) into m_u, taking it
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
    # Paper eq. (35) with the exact bound (docs/decisions.md#exact-gamma-bound): gamma =
    # min(tanh(alpha * max(0, m_u_map - m_u_pred)), exact bound), in [0, 1].
    # The paper's bound holds K fixed; K scales with gamma, so the exact bound is
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
    # deep_disc, paper eq. (29): m = limit_unknown(pred), eq. (15); map <- map (+)_Y (gamma (x) m).
    fn, on, un = _normalise_cell(f1, o1, u1)
    f2, o2, u2 = _normalise_cell(f2, o2, u2)
    f2, o2, u2 = _limit_unknown_cell(f2, o2, u2, m_u_min)
    g = _gamma_cell(fn, on, un, f2, o2, u2, m_u_min, alpha)
    # Paper eq. (8), then Yager (eq. (6)).
    f, o, u = _yager_cell(fn, on, un, g * f2, g * o2, 1.0 - g + g * u2)
    # gamma = 0 adds nothing: keep the cell bit-exact, as renormalising a float32 cell that sits
    # on m_u_min could move it one ulp below the limit.
    keep = g <= 0.0
    return (f1 if keep else f), (o1 if keep else o), (u1 if keep else u)


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


@numba.njit(inline="always", **_JIT)
def _row_sum(bad, n):
    # The update kernels flag invalid cells per row and sum the flags after it: a running count
    # inside their cell loops would keep LLVM from vectorising them (a fifth of deep_disc's time).
    s = 0
    for j in range(n):
        s += bad[j]
    return s


@numba.njit(**_CHECKED)
def _k_count_invalid(a, ars, h, w):
    # Number of cells that are not masses (see _valid_cell): one read of the grid, no writes.
    # (A loop that only counts vectorises with the count inside it.)
    n = 0
    for i in range(h):
        ra = a[i * ars:i * ars + 3 * w]
        for j in range(w):
            p = 3 * j
            ok = _valid_cell(np.float64(ra[p]), np.float64(ra[p + 1]), np.float64(ra[p + 2]))
            n += 0 if ok else 1
    return n


@numba.njit(**_CHECKED)
def _k_vacate_invalid(a, ars, h, w):
    # Invalid cells become vacuous (no information), in place; returns how many there were.
    n = 0
    for i in range(h):
        ra = a[i * ars:i * ars + 3 * w]
        for j in range(w):
            p = 3 * j
            ok = _valid_cell(np.float64(ra[p]), np.float64(ra[p + 1]), np.float64(ra[p + 2]))
            n += 0 if ok else 1
            ra[p] = ra[p] if ok else 0.0
            ra[p + 1] = ra[p + 1] if ok else 0.0
            ra[p + 2] = ra[p + 2] if ok else 1.0
    return n


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


# --- in-place kernels over rows (see rows() above) ---------------------------------------------
# Cells where the ISM is vacuous or invalid (_valid_cell) keep their old value exactly (a
# select, not a branch, so the loops vectorise); each kernel returns the number of invalid ISM
# cells it rejected. Only columns spans[i, 0]:spans[i, 1] of row i are visited (the cells a
# warped window covers); ends are clamped to [0, w], so any spans are memory-safe.

@numba.njit(inline="always", **_JIT)
def _span(spans, i, w):
    lo = min(max(spans[i, 0], 0), w)
    hi = min(max(spans[i, 1], lo), w)
    return lo, hi


@numba.njit(**_CHECKED)
def _k_dempster_into(mp, mrs, ism, irs, h, w, spans):
    # map <- map (+)_D ISM, paper eq. (5): the ray_ilm, deep_acc and ray_irm maps.
    n_bad = 0
    bad = np.zeros(w, np.uint8)
    for i in range(h):
        lo, hi = _span(spans, i, w)
        mp_, ism_ = mp[i * mrs + 3 * lo:i * mrs + 3 * hi], ism[i * irs + 3 * lo:i * irs + 3 * hi]
        for j in range(hi - lo):
            p = 3 * j
            f1, o1, u1 = np.float64(mp_[p]), np.float64(mp_[p + 1]), np.float64(mp_[p + 2])
            f2, o2, u2 = np.float64(ism_[p]), np.float64(ism_[p + 1]), np.float64(ism_[p + 2])
            ok = _valid_cell(f2, o2, u2)
            bad[j] = 0 if ok else 1
            f, o, u = _dempster_cell(f1, o1, u1, f2, o2, u2)
            keep = u2 >= 1.0 or not ok
            mp_[p] = f1 if keep else f
            mp_[p + 1] = o1 if keep else o
            mp_[p + 2] = u1 if keep else u
        n_bad += _row_sum(bad, hi - lo)
    return n_bad


@numba.njit(**_CHECKED)
def _k_deep_replace_into(mp, mrs, ism, irs, h, w, spans, m_u_min):
    # deep_replace: the replace update the paper describes after eq. (23), on the prediction
    # limited by eq. (15); a cell takes it where it is strictly less unknown
    # (docs/decisions.md#the-six-maps).
    n_bad = 0
    bad = np.zeros(w, np.uint8)
    for i in range(h):
        lo, hi = _span(spans, i, w)
        mp_, ism_ = mp[i * mrs + 3 * lo:i * mrs + 3 * hi], ism[i * irs + 3 * lo:i * irs + 3 * hi]
        for j in range(hi - lo):
            p = 3 * j
            f2, o2, u2 = np.float64(ism_[p]), np.float64(ism_[p + 1]), np.float64(ism_[p + 2])
            ok = _valid_cell(f2, o2, u2)
            bad[j] = 0 if ok else 1
            f, o, u = _normalise_cell(f2, o2, u2)
            f, o, u = _limit_unknown_cell(f, o, u, m_u_min)
            f1, o1, u1 = np.float64(mp_[p]), np.float64(mp_[p + 1]), np.float64(mp_[p + 2])
            take = (u < u1) and (ism_[p + 2] < 1.0) and ok
            mp_[p] = f if take else f1
            mp_[p + 1] = o if take else o1
            mp_[p + 2] = u if take else u1
        n_bad += _row_sum(bad, hi - lo)
    return n_bad


@numba.njit(**_CHECKED)
def _k_deep_disc_into(mp, mrs, ism, irs, h, w, spans, m_u_min, alpha):
    # deep_disc: paper eq. (29) with eqs. (15), (8) and (35), see _deep_disc_cell.
    n_bad = 0
    bad = np.zeros(w, np.uint8)
    for i in range(h):
        lo, hi = _span(spans, i, w)
        mp_, ism_ = mp[i * mrs + 3 * lo:i * mrs + 3 * hi], ism[i * irs + 3 * lo:i * irs + 3 * hi]
        for j in range(hi - lo):
            p = 3 * j
            f1, o1, u1 = np.float64(mp_[p]), np.float64(mp_[p + 1]), np.float64(mp_[p + 2])
            f2, o2, u2 = np.float64(ism_[p]), np.float64(ism_[p + 1]), np.float64(ism_[p + 2])
            ok = _valid_cell(f2, o2, u2)
            bad[j] = 0 if ok else 1
            f, o, u = _deep_disc_cell(f1, o1, u1, f2, o2, u2, m_u_min, alpha)
            keep = u2 >= 1.0 or not ok
            mp_[p] = f1 if keep else f
            mp_[p + 1] = o1 if keep else o
            mp_[p + 2] = u1 if keep else u
        n_bad += _row_sum(bad, hi - lo)
    return n_bad


@numba.njit(**_CHECKED)
def _k_fused_into(mp, mrs, deep, drs, irm, irs, h, w, spans, m_u_min, alpha):
    # fused: the deep_disc step (paper eq. (29) with eqs. (15), (8), (35)) with the deep IRM,
    # then Dempster (eq. (5)) with the ray IRM of the same step (docs/decisions.md#the-six-maps).
    # An invalid cell of either ISM skips that ISM's step only; both count.
    n_bad = 0
    bad = np.zeros(w, np.uint8)
    for i in range(h):
        lo, hi = _span(spans, i, w)
        mp_ = mp[i * mrs + 3 * lo:i * mrs + 3 * hi]
        deep_ = deep[i * drs + 3 * lo:i * drs + 3 * hi]
        irm_ = irm[i * irs + 3 * lo:i * irs + 3 * hi]
        for j in range(hi - lo):
            p = 3 * j
            f1, o1, u1 = np.float64(mp_[p]), np.float64(mp_[p + 1]), np.float64(mp_[p + 2])
            fd, od, ud = np.float64(deep_[p]), np.float64(deep_[p + 1]), np.float64(deep_[p + 2])
            ok_d = _valid_cell(fd, od, ud)
            f, o, u = _deep_disc_cell(f1, o1, u1, fd, od, ud, m_u_min, alpha)
            keep = ud >= 1.0 or not ok_d
            f = f1 if keep else f
            o = o1 if keep else o
            u = u1 if keep else u
            fr, or_, ur = np.float64(irm_[p]), np.float64(irm_[p + 1]), np.float64(irm_[p + 2])
            ok_r = _valid_cell(fr, or_, ur)
            bad[j] = (0 if ok_d else 1) + (0 if ok_r else 1)
            f2, o2, u2 = _dempster_cell(f, o, u, fr, or_, ur)
            keep = ur >= 1.0 or not ok_r
            mp_[p] = f if keep else f2
            mp_[p + 1] = o if keep else o2
            mp_[p + 2] = u if keep else u2
        n_bad += _row_sum(bad, hi - lo)
    return n_bad
