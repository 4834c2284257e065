"""Compiled numba kernels of the evidential algebra, the map update rules and the warp.

All per-cell formulas and every kernel that inlines them live in this one module: numba's
on-disk cache is invalidated only when the jitted function's own file changes, so kernels in
another module would keep stale copies of an edited formula. The one-pass map update
(:func:`warp_update`) inlines both the warp's sampling and the rules.

Kernels take ``(h, w, 3)`` float32 views as a flat buffer and a row stride (see
:func:`rows`), loop rows, and are branch-free with ``error_model="numpy"`` so that LLVM
vectorises them (numba's default error model guards every division with a branch).

Masses are checked where they enter: a cell with NaN or inf, a negative mass, or masses not
summing to 1 within ``MASS_ATOL`` is invalid (:func:`_valid_cell`). The combination kernels
count invalid input cells; the in-place map kernels leave the map cell under an invalid ISM
cell untouched and return how many they rejected. These kernels are compiled without the
``nnan``/``ninf`` fast-math flags, under which LLVM may assume that no value is NaN and fold the
checks away; the other flags (and so vectorisation and the results for valid cells) are kept.

The names that :mod:`evgrid.mass`, :mod:`evgrid.grid` and :mod:`evgrid.fusion` use are public
(``__all__``); everything with a leading underscore is private to this module.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

__all__ = [
    "MASS_ATOL",
    "BLOCK",
    "COARSE",
    "RULE_DEMPSTER",
    "RULE_DEEP_REPLACE",
    "RULE_DEEP_DISC",
    "RULE_FUSED",
    "RULE_NAV",
    "DYNAMIC_RULES",
    "rows",
    "count_invalid",
    "dempster_rows",
    "yager_rows",
    "gamma_rows",
    "update_rows",
    "coarse_blocks",
    "load_padded",
    "window_spans",
    "band_columns",
    "informative_blocks",
    "warp_rows",
    "warp_update",
    "PassSources",
    "WindowAffine",
    "TilePiece",
    "MapTiles",
    "RuleTable",
    "DopplerDiscs",
    "nav_cells",
]

# --- per-cell formulas (float64 scalars in, normalised float64 triple out) ---------------------

_JIT = dict(cache=True, fastmath=True, error_model="numpy")
# fast math without nnan/ninf: comparisons keep their IEEE meaning for NaN and inf
_CHECKED = dict(
    cache=True, fastmath={"nsz", "arcp", "contract", "afn", "reassoc"}, error_model="numpy"
)
# The warp's sampling: no fused multiply-adds, no reassociation, and compiled once, not inlined,
# so every kernel that samples (warp_rows's windows, warp_update's one pass) rounds alike and
# gives the same masses bit for bit
_EXACT = dict(cache=True, fastmath={"nsz", "arcp", "afn"}, error_model="numpy")
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
    # normalises. Total conflict (1 - K = 0) is undefined: vacuous
    # (docs/decisions.md#total-conflict).
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
    e = z * (
        1.0
        + z
        * (
            1.0 / 2
            + z
            * (
                1.0 / 6
                + z
                * (
                    1.0 / 24
                    + z
                    * (
                        1.0 / 120
                        + z
                        * (
                            1.0 / 720
                            + z
                            * (
                                1.0 / 5040
                                + z
                                * (
                                    1.0 / 40320
                                    + z
                                    * (1.0 / 362880 + z * (1.0 / 3628800 + z * (1.0 / 39916800)))
                                )
                            )
                        )
                    )
                )
            )
        )
    )
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


@numba.njit(inline="always", **_JIT)
def _combine_rows(a, ars, b, brs, out, ors, h, w, yager):
    # out = a (+) b cell by cell: Yager's rule (eq. (6)) if ``yager``, else Dempster's (eq. (5))
    for i in range(h):
        ra, rb, ro = (
            a[i * ars : i * ars + 3 * w],
            b[i * brs : i * brs + 3 * w],
            out[i * ors : i * ors + 3 * w],
        )
        for j in range(w):
            p = 3 * j
            f1, o1, u1 = np.float64(ra[p]), np.float64(ra[p + 1]), np.float64(ra[p + 2])
            f2, o2, u2 = np.float64(rb[p]), np.float64(rb[p + 1]), np.float64(rb[p + 2])
            if yager:
                f, o, u = _yager_cell(f1, o1, u1, f2, o2, u2)
            else:
                f, o, u = _dempster_cell(f1, o1, u1, f2, o2, u2)
            ro[p] = f
            ro[p + 1] = o
            ro[p + 2] = u


@numba.njit(**_JIT)
def dempster_rows(a, ars, b, brs, out, ors, h, w):
    _combine_rows(a, ars, b, brs, out, ors, h, w, False)


@numba.njit(**_JIT)
def yager_rows(a, ars, b, brs, out, ors, h, w):
    _combine_rows(a, ars, b, brs, out, ors, h, w, True)


@numba.njit(**_JIT)
def gamma_rows(a, ars, b, brs, m_u_min, alpha, out, h, w):
    for i in range(h):
        ra, rb, ro = (
            a[i * ars : i * ars + 3 * w],
            b[i * brs : i * brs + 3 * w],
            out[i * w : (i + 1) * w],
        )
        for j in range(w):
            p = 3 * j
            f1, o1, u1 = _normalise_cell(
                np.float64(ra[p]), np.float64(ra[p + 1]), np.float64(ra[p + 2])
            )
            f2, o2, u2 = _normalise_cell(
                np.float64(rb[p]), np.float64(rb[p + 1]), np.float64(rb[p + 2])
            )
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
def count_invalid(a, ars, h, w):
    # Number of cells that are not masses (see _valid_cell): one read of the grid, no writes.
    # (A loop that only counts vectorises with the count inside it.)
    n = 0
    for i in range(h):
        ra = a[i * ars : i * ars + 3 * w]
        for j in range(w):
            p = 3 * j
            ok = _valid_cell(np.float64(ra[p]), np.float64(ra[p + 1]), np.float64(ra[p + 2]))
            n += 0 if ok else 1
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
    flat = np.lib.stride_tricks.as_strided(
        v, shape=((h - 1) * rs + 3 * w,), strides=(4,), writeable=v.flags.writeable
    )
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


# Each rule on one row of cells: map cells mp_ and ISM cells ism_ (3 floats a cell, n cells);
# bad[j] flags invalid ISM cells; returns their number. The kernels below loop rows over them.


@numba.njit(inline="always", **_CHECKED)
def _ism_cell(ism_, p):
    # The ISM cell at flat index p of a row as float64 masses and whether they are masses
    # (_valid_cell): how every rule opens a cell.
    f, o, u = np.float64(ism_[p]), np.float64(ism_[p + 1]), np.float64(ism_[p + 2])
    return f, o, u, _valid_cell(f, o, u)


@numba.njit(inline="always", **_JIT)
def _conflict_split(f1, o1, f2, o2):
    # The conflict K = f1 o2 + o1 f2 of Dempster's rule (paper eq. (7)), map 1 and ISM 2, split
    # by direction (Moras, Cherfaoui, Bonnifait 2011): free then occupied is something that
    # arrived, occupied then free something that left (docs/equations.md#the-dynamic-score).
    return f1 * o2, o1 * f2


@numba.njit(inline="always", **_JIT)
def _gated(s, gate, f2, o2, u2, ok):
    # The gate (docs/equations.md#the-gate): a cell whose score s exceeds the threshold ``gate``
    # (> 0; 0 is no gate) sheds its occupied mass before a Dempster step whose valid,
    # informative ISM cell does not say occupied (m_o <= m_f), so what a mover left goes free.
    return gate > 0.0 and s > gate and ok and u2 < 1.0 and o2 <= f2


@numba.njit(inline="always", **_CHECKED)
def _score_cell(s, decay, f1, o1, u1, f2, o2, u2, ok, gate):
    # One cell's dynamic score s <- decay s + K_arr + K_left (an invalid ISM cell adds nothing)
    # and the gate on the new score (_gated): the score to keep, 0 where the valid, informative
    # ISM says free now (m_f > m_o: whatever moved there is gone), and the map cell's (m_o, m_u)
    # to combine, its occupied mass moved to unknown where gated.
    arrived, left = _conflict_split(f1, o1, f2, o2)
    s = decay * s + (arrived + left if ok else 0.0)
    g = _gated(s, gate, f2, o2, u2, ok)
    kept = (f2 <= o2) | (u2 >= 1.0) | (not ok)  # not seen free now; bitwise: one vector select
    return s * kept, (0.0 if g else o1), (u1 + o1 if g else u1)


@numba.njit(inline="always", **_CHECKED)
def _dempster_row(mp_, ism_, bad, n, s_, decay, scored, gate):
    # map <- map (+)_D ISM, paper eq. (5): the ray_ilm, deep_acc and ray_irm maps. With
    # ``scored`` (a constant where inlined), also the dynamic score s_ <- decay s_ + K_arr +
    # K_left from the same map and ISM cells (see _score_cell), and with ``gate`` > 0 the
    # gate on the new score (_gated): one loop over the cells.
    for j in range(n):
        p = 3 * j
        f1, o1, u1 = np.float64(mp_[p]), np.float64(mp_[p + 1]), np.float64(mp_[p + 2])
        f2, o2, u2, ok = _ism_cell(ism_, p)
        bad[j] = 0 if ok else 1
        if scored:
            s, o1, u1 = _score_cell(np.float64(s_[j]), decay, f1, o1, u1, f2, o2, u2, ok, gate)
            s_[j] = s
        f, o, u = _dempster_cell(f1, o1, u1, f2, o2, u2)
        keep = u2 >= 1.0 or not ok
        mp_[p] = f1 if keep else f
        mp_[p + 1] = o1 if keep else o
        mp_[p + 2] = u1 if keep else u
    return _row_sum(bad, n)


@numba.njit(inline="always", **_CHECKED)
def _deep_replace_row(mp_, ism_, bad, n, m_u_min):
    # deep_replace: the replace update the paper describes after eq. (23), on the prediction
    # limited by eq. (15); a cell takes it where it is strictly less unknown
    # (docs/decisions.md#the-six-maps).
    for j in range(n):
        p = 3 * j
        f2, o2, u2, ok = _ism_cell(ism_, p)
        bad[j] = 0 if ok else 1
        f, o, u = _normalise_cell(f2, o2, u2)
        f, o, u = _limit_unknown_cell(f, o, u, m_u_min)
        f1, o1, u1 = np.float64(mp_[p]), np.float64(mp_[p + 1]), np.float64(mp_[p + 2])
        take = (u < u1) and (ism_[p + 2] < 1.0) and ok
        mp_[p] = f if take else f1
        mp_[p + 1] = o if take else o1
        mp_[p + 2] = u if take else u1
    return _row_sum(bad, n)


@numba.njit(inline="always", **_CHECKED)
def _deep_disc_row(mp_, ism_, bad, n, m_u_min, alpha):
    # deep_disc: paper eq. (29) with eqs. (15), (8) and (35), see _deep_disc_cell.
    for j in range(n):
        p = 3 * j
        f1, o1, u1 = np.float64(mp_[p]), np.float64(mp_[p + 1]), np.float64(mp_[p + 2])
        f2, o2, u2, ok = _ism_cell(ism_, p)
        bad[j] = 0 if ok else 1
        f, o, u = _deep_disc_cell(f1, o1, u1, f2, o2, u2, m_u_min, alpha)
        keep = u2 >= 1.0 or not ok
        mp_[p] = f1 if keep else f
        mp_[p + 1] = o1 if keep else o
        mp_[p + 2] = u1 if keep else u
    return _row_sum(bad, n)


@numba.njit(inline="always", **_CHECKED)
def _fused_row(mp_, deep_, irm_, bad, n, m_u_min, alpha, s_, decay, scored, gate):
    # fused: the deep_disc step (paper eq. (29) with eqs. (15), (8), (35)) with the deep IRM,
    # then Dempster (eq. (5)) with the ray IRM of the same step (docs/decisions.md#the-six-maps).
    # An invalid cell of either ISM skips that ISM's step only; both count. With ``scored`` (a
    # constant where inlined), first the dynamic score s_ <- decay s_ + K_arr + K_left of the
    # map cell before the whole update and the ray IRM cell of the Dempster step, and with
    # ``gate`` > 0 the gate on the new score (_gated) before both steps: one loop over the cells.
    for j in range(n):
        p = 3 * j
        f1, o1, u1 = np.float64(mp_[p]), np.float64(mp_[p + 1]), np.float64(mp_[p + 2])
        fr, or_, ur, ok_r = _ism_cell(irm_, p)
        if scored:
            s, o1, u1 = _score_cell(np.float64(s_[j]), decay, f1, o1, u1, fr, or_, ur, ok_r, gate)
            s_[j] = s
            # the gated cell as the map holds it (float32), as when the gate wrote it first
            u1 = np.float64(np.float32(u1))
        fd, od, ud, ok_d = _ism_cell(deep_, p)
        f, o, u = _deep_disc_cell(f1, o1, u1, fd, od, ud, m_u_min, alpha)
        keep = ud >= 1.0 or not ok_d
        f = f1 if keep else f
        o = o1 if keep else o
        u = u1 if keep else u
        bad[j] = (0 if ok_d else 1) + (0 if ok_r else 1)
        f2, o2, u2 = _dempster_cell(f, o, u, fr, or_, ur)
        keep = ur >= 1.0 or not ok_r
        mp_[p] = f if keep else f2
        mp_[p + 1] = o if keep else o2
        mp_[p + 2] = u if keep else u2
    return _row_sum(bad, n)


@numba.njit(inline="always", **_CHECKED)
def _disc_cells(runs, k0, k1, lo, hi, a, b, du_dj, dv_dj, srs, dj, dp):
    # The Doppler cue's cells of a row whose cells [lo, hi) are at padded source positions (a + j
    # du_dj, b + j dv_dj): dj[c] = j - lo for the cells j of runs [k0, k1) (columns [runs[k, 0],
    # runs[k, 1])), dp[c] the flat index of the source cell nearest to cell j (the same in every
    # ISM's padded grid); returns their number. Computed once per row for every map and ISM.
    c = 0
    for k in range(k0, k1):
        for j in range(max(runs[k, 0], lo), min(runs[k, 1], hi)):
            dj[c] = j - lo
            dp[c] = int(np.rint(a + j * du_dj)) * srs + 3 * int(np.rint(b + j * dv_dj))
            c += 1
    return c


@numba.njit(inline="always", **_CHECKED)
def _disc_weights(src, dp, nd, dw):
    # dw[c] = 1 - m_f / (m_f + m_o) of the ISM cell src[dp[c]:] (1 where vacuous or invalid: a
    # padded grid holds invalid cells as vacuous), c < nd: once per row and ISM.
    for c in range(nd):
        f, o = np.float64(src[dp[c]]), np.float64(src[dp[c] + 1])
        dw[c] = o / (o + f) if f > 0.0 else 1.0


@numba.njit(inline="always", **_CHECKED)
def _doppler_row(s_, dj, dw, nd, mu):
    # The Doppler cue (docs/equations.md#the-doppler-cue) on a row's score cells s_: s <- s + mu
    # (1 - m_f / (m_f + m_o)) of the source cell nearest to each disc cell (_disc_cells and
    # _disc_weights of the map's ISM).
    for c in range(nd):
        s_[dj[c]] = np.float64(s_[dj[c]]) + mu * dw[c]


#: Kernel codes of the update rules; :data:`evgrid.fusion.RULES` says which map uses which.
#: RULE_NAV is not a row of the pass: nav is computed from two maps by nav_cells when read.
RULE_DEMPSTER, RULE_DEEP_REPLACE, RULE_DEEP_DISC, RULE_FUSED, RULE_NAV = 0, 1, 2, 3, 4
#: The rules with a Dempster step (eq. (5)) on an ISM, whose conflict feeds the dynamic score.
DYNAMIC_RULES = (RULE_DEMPSTER, RULE_FUSED)


@numba.njit(inline="always", **_CHECKED)
def _rule_row(code, mp_, a, b, bad, n, m_u_min, alpha):
    # One row of a map updated by the rule of ``code`` from rows ``a`` and ``b`` (the first and
    # last input of the rule: the same row for one-input rules); returns the rejected cells.
    if code == RULE_DEMPSTER:
        return _dempster_row(mp_, a, bad, n, a, 0.0, False, 0.0)
    elif code == RULE_DEEP_REPLACE:
        return _deep_replace_row(mp_, a, bad, n, m_u_min)
    elif code == RULE_DEEP_DISC:
        return _deep_disc_row(mp_, a, bad, n, m_u_min, alpha)
    return _fused_row(mp_, a, b, bad, n, m_u_min, alpha, a, 0.0, False, 0.0)


@numba.njit(**_CHECKED)
def update_rows(code, mp, mrs, a, ars, b, brs, h, w, spans, m_u_min, alpha):
    """Update the ``(h, w)`` map view ``mp`` in place by rule ``code`` from the views ``a``, ``b``.

    Views travel as (flat buffer, row stride) (see :func:`rows`); row i is updated on columns
    ``spans[i, 0]:spans[i, 1]`` only (clamped to [0, w]). Returns the invalid input cells
    rejected (their map cells are left untouched).
    """
    n_bad = 0
    bad = np.zeros(w, np.uint8)
    for i in range(h):
        lo, hi = _span(spans, i, w)
        n_bad += _rule_row(
            code,
            mp[i * mrs + 3 * lo : i * mrs + 3 * hi],
            a[i * ars + 3 * lo : i * ars + 3 * hi],
            b[i * brs + 3 * lo : i * brs + 3 * hi],
            bad,
            hi - lo,
            m_u_min,
            alpha,
        )
    return n_bad


# --- the navigation map: two maps of the same set and their neighbourhood -----------------------


@numba.njit(inline="always", **_JIT)
def _nav_cell(fl, ol, ul, ff, of, uf, clear, held):
    # F' = F with its free mass as unknown unless the cell is clear, and its occupied mass as
    # unknown where the lidar's evidence is free-dominant; then L (+)_D F', eq. (5). ``held``:
    # the ungated lidar map says occupied (m_o > m_f) where L is a gated copy: the gate may
    # take the cell to unknown, never to free (docs/equations.md#the-gate).
    f2 = ff if clear else 0.0
    o2 = 0.0 if fl > ol else of
    u2 = uf + (ff - f2) + (of - o2)
    f, o, u = _dempster_cell(fl, ol, ul, f2, o2, u2)
    return (0.0, o, u + f) if held else (f, o, u)


@numba.njit(**_CHECKED)
def nav_cells(lidar, fused, moving, plain, held, out, r, occupied_min, moving_min):
    """The navigation map (evgrid.nav) of the cells ``r`` in from every edge of the dense lidar
    and fused maps ``(h + 2r, w + 2r, 3)``, into ``out`` ``(h, w, 3)``: a cell is clear when no
    cell within ``r`` cells (a square) holds lidar occupied mass, fused occupied mass above
    ``occupied_min``, or a dynamic score ``moving`` ``(h + 2r, w + 2r)`` above ``moving_min``.
    With ``held``, ``lidar`` is a gated copy and ``plain`` the ungated lidar map: a cell that
    ``plain`` calls occupied-dominant keeps no free mass (without, ``plain`` is not read)."""
    # blocking cells are counted in an integral image: each cell's clearance is four reads
    hh, ww = lidar.shape[0], lidar.shape[1]
    acc = np.zeros((hh + 1, ww + 1), np.int32)
    for i in range(hh):
        run = 0
        for j in range(ww):
            if lidar[i, j, 1] > 0.0 or fused[i, j, 1] > occupied_min or moving[i, j] > moving_min:
                run += 1
            acc[i + 1, j + 1] = acc[i, j + 1] + run
    d = 2 * r + 1
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            n = acc[i + d, j + d] - acc[i, j + d] - acc[i + d, j] + acc[i, j]
            a, b = i + r, j + r
            f, o, u = _nav_cell(
                np.float64(lidar[a, b, 0]),
                np.float64(lidar[a, b, 1]),
                np.float64(lidar[a, b, 2]),
                np.float64(fused[a, b, 0]),
                np.float64(fused[a, b, 1]),
                np.float64(fused[a, b, 2]),
                n == 0,
                held and plain[a, b, 1] > plain[a, b, 0],
            )
            out[i, j, 0] = f
            out[i, j, 1] = o
            out[i, j, 2] = u


# --- the warp: a local grid resampled into the map (evgrid.grid) ---------------------------------
# Map cell (i, j) of a window samples the local grid at continuous (row, col) position
# (u, v) = (u00 + i du_di + j du_dj, v00 + i dv_di + j dv_dj), bilinearly. The local grid is
# read from a padded copy with a vacuous border (local (r, c) is src[r + 1, c + 1]; one row and
# column before, two after, as a snapped index may reach n + 1), so sampling anywhere in
# (-1, n) needs no bounds checks. Fractions within _SNAP of 0 or 1 are snapped, so identity,
# whole-cell and quarter-turn warps copy cells exactly. Weights are float32, positions float64.

# Fractional source positions closer than this to a whole cell (in cells) are snapped to it.
_SNAP = 1e-6
# Window rows are visited in bands of BLOCK rows and, within a band, blocks of BLOCK columns
# from the band's first covered column, which keeps the rotated source footprint in cache at
# any yaw; a block whose footprint holds only vacuous cells is written vacuous, unsampled.
BLOCK = 32
COARSE = 8  # side of the source blocks whose vacuousness is checked before sampling
_AHEAD = 2  # rows ahead whose source lines are prefetched (see _prefetch_span)


@intrinsic
def _prefetch(typingctx, arr, idx):
    """A hint to bring ``arr[idx]`` (a 1-D array) into the caches (``llvm.prefetch``: read, keep);
    never faults."""

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        ptr = builder.bitcast(builder.gep(ary.data, [args[1]]), ir.IntType(8).as_pointer())
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [ir.IntType(8).as_pointer(), i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0i8")
        builder.call(fn, [ptr, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return types.void(arr, idx), codegen


@numba.njit(**_JIT)
def coarse_blocks(src, coarse):
    """coarse[a, b] = any cell of src block [8a, 8a + 8) x [8b, 8b + 8) is not vacuous."""
    # branch-free (a running min per block): a branch per cell mispredicts on scattered cells
    n_r, n_c = src.shape[0], src.shape[1]
    u_min = np.empty(coarse.shape[1], dtype=np.float32)
    for a in range(coarse.shape[0]):
        u_min[:] = 1.0
        for r in range(a * COARSE, min(n_r, (a + 1) * COARSE)):
            for c in range(n_c):
                b = c // COARSE
                u_min[b] = min(u_min[b], src[r, c, 2])
        for b in range(coarse.shape[1]):
            coarse[a, b] = u_min[b] < 1.0


@numba.njit(**_CHECKED)
def load_padded(local, src):
    """src[1:n+1, 1:n+1] = local with invalid cells (see _valid_cell) made vacuous; returns their
    number."""
    n_bad = 0
    for r in range(local.shape[0]):
        for c in range(local.shape[1]):
            f, o, u = (
                np.float64(local[r, c, 0]),
                np.float64(local[r, c, 1]),
                np.float64(local[r, c, 2]),
            )
            ok = _valid_cell(f, o, u)
            n_bad += 0 if ok else 1
            src[r + 1, c + 1, 0] = local[r, c, 0] if ok else 0.0
            src[r + 1, c + 1, 1] = local[r, c, 1] if ok else 0.0
            src[r + 1, c + 1, 2] = local[r, c, 2] if ok else 1.0
    return n_bad


@numba.njit(**_JIT)
def _row_range(a, d, n, w):
    """Columns j in [0, w) (padded by one either side) where -1 < a + j d < n; (0, 0) if none."""
    if d == 0.0:
        return (0, w) if (a > -1.0 and a < n) else (0, 0)
    t1 = (-1.0 - a) / d
    t2 = (n - a) / d
    lo = max(-2.0, min(float(w), min(t1, t2)))  # clamped before int(): d may be ~1e-17
    hi = max(-2.0, min(float(w), max(t1, t2)))
    return max(0, int(math.floor(lo)) - 1), min(w, int(math.floor(hi)) + 2)


@numba.njit(**_JIT)
def window_spans(u00, v00, du_di, du_dj, dv_di, dv_dj, n, h, w, spans):
    """spans[i] = columns of row i whose local position (u, v) lies in (-1, n)^2."""
    nf = float(n)
    for i in range(h):
        a = u00 + i * du_di
        b = v00 + i * dv_di
        l1, h1 = _row_range(a, du_dj, nf, w)
        l2, h2 = _row_range(b, dv_dj, nf, w)
        lo = max(l1, l2)
        hi = min(h1, h2)
        # the analytic range is padded; settle its ends on the exact test (the set is convex)
        while lo < hi:
            u = a + lo * du_dj
            v = b + lo * dv_dj
            if u > -1.0 and v > -1.0 and u < nf and v < nf:
                break
            lo += 1
        while hi > lo:
            u = a + (hi - 1) * du_dj
            v = b + (hi - 1) * dv_dj
            if u > -1.0 and v > -1.0 and u < nf and v < nf:
                break
            hi -= 1
        spans[i, 0] = lo if hi > lo else 0
        spans[i, 1] = hi if hi > lo else 0


@numba.njit(**_JIT)
def band_columns(spans, h, w, jl, jh):
    """jl[b], jh[b]: the covered columns [jl, jh) of band b (rows [32 b, 32 b + 32)); (w, 0) if
    none."""
    for bi in range(0, h, BLOCK):
        lo = w
        hi = 0
        for i in range(bi, min(h, bi + BLOCK)):
            if spans[i, 1] > spans[i, 0]:
                lo = min(lo, spans[i, 0])
                hi = max(hi, spans[i, 1])
        jl[bi // BLOCK] = lo
        jh[bi // BLOCK] = hi


@numba.njit(inline="always", **_JIT)
def _block_informative(coarse, n, u00, v00, du_di, du_dj, dv_di, dv_dj, bi, i1, bj, j1):
    # Whether the source footprint of window block [bi, i1) x [bj, j1) (padded indices: the box
    # of its corners' images) holds a cell that is not vacuous.
    ulo = 1e30
    uhi = -1e30
    vlo = 1e30
    vhi = -1e30
    for ci in (bi, i1 - 1):
        for cj in (bj, j1 - 1):
            u = u00 + ci * du_di + cj * du_dj + 1.0
            v = v00 + ci * dv_di + cj * dv_dj + 1.0
            ulo = min(ulo, u)
            uhi = max(uhi, u)
            vlo = min(vlo, v)
            vhi = max(vhi, v)
    n_cr, n_cc = coarse.shape[0], coarse.shape[1]
    a0 = max(0, int(max(ulo, 0.0)) - 1) // COARSE
    a1 = min(n_cr - 1, (int(min(max(uhi, 0.0), n + 2.0)) + 2) // COARSE)
    b0 = max(0, int(max(vlo, 0.0)) - 1) // COARSE
    b1 = min(n_cc - 1, (int(min(max(vhi, 0.0), n + 2.0)) + 2) // COARSE)
    informative = False
    for a in range(a0, a1 + 1):
        for b in range(b0, b1 + 1):
            informative = informative or coarse[a, b]
    return informative


@numba.njit(inline="always", **_JIT)
def _fill_vacuous(ro, o0, m):
    for k in range(m):
        ro[o0 + 3 * k] = 0.0
        ro[o0 + 3 * k + 1] = 0.0
        ro[o0 + 3 * k + 2] = 1.0


@numba.njit(**_EXACT)
def _positions(srs, n, u00, v00, du_di, du_dj, dv_di, dv_dj, i, j0, j2, idx, frac):
    # idx[k], frac[2 k : 2 k + 2], k < j2 - j0 (<= BLOCK): where window cell (i, j0 + k)
    # samples every local grid (the same affine for all): the flat index of its top-left padded
    # source cell and the fractions.
    a = u00 + i * du_di + 1.0  # the row's padded source position (see the warp above)
    b = v00 + i * dv_di + 1.0
    for k in range(j2 - j0):
        t = a + (j0 + k) * du_dj
        s = b + (j0 + k) * dv_dj
        iu = min(int(t), n)  # t in (0, n + 1): floor; min() guards a rounding at the edge
        iv = min(int(s), n)
        fu = t - iu
        fv = s - iv
        # snap near-integer positions to the cell (a quarter-turn's cos is 6e-17, not 0), so
        # identity, whole-cell and quarter-turn warps copy cells exactly
        up = fu > 1.0 - _SNAP
        iu = iu + 1 if up else iu
        fu = 0.0 if (up or fu < _SNAP) else fu
        up = fv > 1.0 - _SNAP
        iv = iv + 1 if up else iv
        fv = 0.0 if (up or fv < _SNAP) else fv
        frac[2 * k] = np.float32(fu)
        frac[2 * k + 1] = np.float32(fv)
        idx[k] = iu * srs + 3 * iv


@numba.njit(**_EXACT)
def _gather(src, srs, m, ro, o0, idx, frac):
    # ro[o0 + 3 k + c], k < m: the bilinear samples of src at the positions of _positions
    one = np.float32(1.0)
    for k in range(m):
        fu = frac[2 * k]
        fv = frac[2 * k + 1]
        gu = one - fu
        gv = one - fv
        p = idx[k]
        q = p + srs
        o = o0 + 3 * k
        for c in range(3):
            ro[o + c] = gu * (gv * src[p + c] + fv * src[p + 3 + c]) + fu * (
                gv * src[q + c] + fv * src[q + 3 + c]
            )


@numba.njit(inline="always", **_JIT)
def _sample_span(src, srs, n, affine, i, j0, j2, ro, o0, idx, frac):
    # ro[o0 + 3 k + c], k < j2 - j0: the bilinear samples of window cells (i, j0) ... (i, j2 - 1)
    # of the window of ``affine`` (WindowAffine's fields)
    u00, v00, du_di, du_dj, dv_di, dv_dj = affine
    _positions(srs, n, u00, v00, du_di, du_dj, dv_di, dv_dj, i, j0, j2, idx, frac)
    _gather(src, srs, j2 - j0, ro, o0, idx, frac)


@numba.njit(inline="always", **_JIT)
def _prefetch_span(src, informative, srs, n, a, b, du_dj, dv_dj, j0, j2):
    # Ask for the lines of each informative source (src[s] with informative[s]) that window
    # cells j0 ... j2 - 1 of the row at (a, b) (the row _AHEAD rows on) will sample, while this
    # one is worked: off the quarter turns, a row's samples cross source rows, which the
    # hardware prefetcher does not follow, and a cold source line costs a memory latency (2x
    # slower at 10 and 45 degrees without this; warp_rows's 32 x 32 blocks keep their footprint
    # in cache instead). One hint per two cells.
    top = len(src[0]) - 1
    for j in range(j0, j2, 2):
        iu = min(max(int(a + j * du_dj), 0), n + 1)
        iv = min(max(int(b + j * dv_dj), 0), n + 1)
        p = iu * srs + 3 * iv
        for s in range(len(src)):
            if informative[s]:
                _prefetch(src[s], p)
                _prefetch(src[s], min(p + srs, top))


@numba.njit(**_JIT)
def warp_rows(
    src, srs, coarse, n, u00, v00, du_di, du_dj, dv_di, dv_dj, out, ors, covered, crs, h, w, spans
):
    # The window (h, w) written whole: sampled masses on covered cells, vacuous elsewhere.
    affine = (u00, v00, du_di, du_dj, dv_di, dv_dj)
    window_spans(u00, v00, du_di, du_dj, dv_di, dv_dj, n, h, w, spans)
    idx = np.empty(BLOCK, dtype=np.int64)
    frac = np.empty(2 * BLOCK, dtype=np.float32)
    for i in range(h):
        ro = out[i * ors : i * ors + 3 * w]
        cv = covered[i * crs : i * crs + w]
        lo, hi = spans[i, 0], spans[i, 1]
        _fill_vacuous(ro, 0, lo)
        _fill_vacuous(ro, 3 * hi, w - hi)
        cv[:lo] = False
        cv[lo:hi] = True
        cv[hi:] = False
    jl = np.empty((h + BLOCK - 1) // BLOCK, np.int64)
    jh = np.empty_like(jl)
    band_columns(spans, h, w, jl, jh)
    for bi in range(0, h, BLOCK):
        i1 = min(h, bi + BLOCK)
        for bj in range(jl[bi // BLOCK], jh[bi // BLOCK], BLOCK):
            j1 = min(jh[bi // BLOCK], bj + BLOCK)
            informative = _block_informative(
                coarse, n, u00, v00, du_di, du_dj, dv_di, dv_dj, bi, i1, bj, j1
            )
            for i in range(bi, i1):
                ro = out[i * ors : i * ors + 3 * w]
                j0 = max(bj, spans[i, 0])
                j2 = min(j1, spans[i, 1])
                if j2 <= j0:
                    continue
                if informative:
                    _sample_span(src, srs, n, affine, i, j0, j2, ro, 3 * j0, idx, frac)
                else:
                    _fill_vacuous(ro, 3 * j0, j2 - j0)


@numba.njit(**_JIT)
def informative_blocks(coarse, n, u00, v00, du_di, du_dj, dv_di, dv_dj, h, jl, jh, out):
    """out[b, k]: whether block k (columns jl[b] + 32 k ...) of band b is informative (see
    warp_rows)."""
    for bi in range(0, h, BLOCK):
        b = bi // BLOCK
        i1 = min(h, bi + BLOCK)
        for bj in range(jl[b], jh[b], BLOCK):
            j1 = min(jh[b], bj + BLOCK)
            out[b, (bj - jl[b]) // BLOCK] = _block_informative(
                coarse, n, u00, v00, du_di, du_dj, dv_di, dv_dj, bi, i1, bj, j1
            )


#: The padded ISM grids one pass samples (:func:`warp_update`): ``src`` a tuple of the flat
#: padded local grids (one per ISM slot, :func:`load_padded`), their row stride ``srs`` and side
#: ``n``, ``informative`` ``(isms, bands, blocks)`` (:func:`informative_blocks`) and each band's
#: first block column ``jl`` (:func:`band_columns`).
PassSources = namedtuple("PassSources", "src srs n informative jl")
#: A window's affine map: window cell (i, j) samples source position (u00 + i du_di + j du_dj,
#: v00 + i dv_di + j dv_dj) (:func:`evgrid.grid.window_affine`).
WindowAffine = namedtuple("WindowAffine", "u00 v00 du_di du_dj dv_di dv_dj")
#: One tile piece of a window: window rows [wa, wb) and columns [wc0, wc1) (within the window's
#: ``spans``, :func:`window_spans`) are tile cells (tr0 + i - wa, tc0 + j - wc0).
TilePiece = namedtuple("TilePiece", "spans wa wb wc0 wc1 tr0 tc0")
#: The piece's tile of every row of the pass, flat: ``masses`` (3 floats a cell), ``covered``,
#: ``scores`` (the dynamic layer, empty for a map that keeps none), tiles of ``side`` cells a side.
MapTiles = namedtuple("MapTiles", "masses covered scores side")
#: The pass's rule table (:meth:`evgrid.fusion.MapSet._plan`): per row ``codes`` (kernel code,
#: first input, last input, Doppler disc set) and ``params`` (m_u_min, alpha, decay, gate,
#: Doppler mass).
RuleTable = namedtuple("RuleTable", "codes params")
#: The Doppler cue's discs in the window (:func:`evgrid.doppler.disc_runs`): window row i of
#: disc set q covers ``runs[ptr[q, i]:ptr[q, i + 1]]``.
DopplerDiscs = namedtuple("DopplerDiscs", "ptr runs")


@numba.njit(inline="always", **_CHECKED)
def _sample_isms(sources, affine, i, lo, hi, a, b, bufs, idx, frac):
    # Window row i's covered cells [lo, hi) from every ISM into its row buffer bufs[s], exactly
    # as warp_rows writes them: block by block, an uninformative block vacuous, the positions
    # computed once for every ISM; then the source lines of the row _AHEAD rows on are
    # prefetched (_prefetch_span). (a, b): the row's padded source position.
    src, srs, n, informative, jl = sources
    u00, v00, du_di, du_dj, dv_di, dv_dj = affine
    band = i // BLOCK
    j = lo
    while j < hi:
        k = (j - jl[band]) // BLOCK
        j1 = min(hi, jl[band] + (k + 1) * BLOCK)
        located = False
        for s in range(len(src)):
            if informative[s, band, k]:
                if not located:
                    _positions(srs, n, u00, v00, du_di, du_dj, dv_di, dv_dj, i, j, j1, idx, frac)
                    located = True
                _gather(src[s], srs, j1 - j, bufs[s], 3 * (j - lo), idx, frac)
            else:
                _fill_vacuous(bufs[s], 3 * (j - lo), j1 - j)
        if located:
            a1, b1 = a + _AHEAD * du_di, b + _AHEAD * dv_di
            _prefetch_span(src, informative[:, band, k], srs, n, a1, b1, du_dj, dv_dj, j, j1)
        j = j1


@numba.njit(inline="always", **_CHECKED)
def _cue_scratch(isms, ts):
    # The Doppler cue's scratch for rows of up to ts cells (_doppler_cue): a row's disc cells,
    # their source cells, their weights per ISM and the disc set each ISM's weights are of.
    dw = np.empty((isms, ts), np.float64)
    return np.empty(ts, np.int64), np.empty(ts, np.int64), dw, np.empty(isms, np.int64)


@numba.njit(inline="always", **_CHECKED)
def _doppler_cue(s_, q, y, i, lo, hi, a, b, mu, sources, affine, discs, seen, cue):
    # The Doppler cue of disc set q, mass mu, on window row i's score cells s_ (after the gate:
    # it counts from the next update on), weighted by ISM slot y. The row's disc cells and their
    # source cells (_disc_cells) are found once for every map (seen: the disc set found last and
    # its number of cells), their weights (_disc_weights) once per ISM (wrow[y]: the disc set
    # whose weights dw[y] hold, -1: none yet). Returns the new ``seen``.
    dj, dp, dw, wrow = cue
    dq, nd = seen
    if q != dq:
        k0, k1 = discs.ptr[q, i], discs.ptr[q, i + 1]
        du_dj, dv_dj, srs = affine.du_dj, affine.dv_dj, sources.srs
        nd = _disc_cells(discs.runs, k0, k1, lo, hi, a, b, du_dj, dv_dj, srs, dj, dp)
        dq = q
        wrow[:] = -1
    if wrow[y] != q:
        _disc_weights(sources.src[y], dp, nd, dw[y])
        wrow[y] = q
    _doppler_row(s_, dj, dw[y], nd, mu)
    return dq, nd


@numba.njit(**_CHECKED)
def warp_update(sources, affine, piece, tiles, table, discs, bufs, rejected):
    # One tile piece of a window, every map at once (PassSources, WindowAffine, TilePiece,
    # MapTiles, RuleTable, DopplerDiscs): each window row's covered cells are sampled from each
    # ISM exactly as warp_rows writes them, into a row buffer per ISM (bufs), and each row k of
    # the rule table runs its map's rule on those buffers, the same masses as warping whole
    # windows and updating from them, without writing or re-reading the windows; rejected[k]
    # counts the cells it rejected. A row with decay > 0 (a rule of DYNAMIC_RULES) also scores
    # the cells (from the map cells before the update) and gates them (gate > 0); a scored row
    # with a Doppler cue (codes[k, 3] = q >= 0) then adds it. The rule dispatch stays in this
    # loop, on the tables unpacked here: moved into an inlined function, or read through the
    # named tuples, the rules' row loops compiled slower (numba 0.68; docs/speed.md).
    masses, covered, scores, ts = tiles
    codes, params = table
    spans, wa, wb, wc0, wc1, tr0, tc0 = piece
    idx, frac = np.empty(BLOCK, dtype=np.int64), np.empty(2 * BLOCK, dtype=np.float32)
    bad = np.zeros(ts, np.uint8)
    cue = _cue_scratch(len(sources.src), ts)
    for i in range(wa, wb):
        lo, hi = max(spans[i, 0], wc0), min(spans[i, 1], wc1)
        if hi <= lo:
            continue
        a = affine.u00 + i * affine.du_di + 1.0  # the row's padded source position
        b = affine.v00 + i * affine.dv_di + 1.0
        _sample_isms(sources, affine, i, lo, hi, a, b, bufs, idx, frac)
        m = hi - lo
        t = (tr0 + i - wa) * ts + tc0 + lo - wc0  # the row's first cell in the tiles
        seen = (-1, 0)
        for k in range(len(masses)):
            mp_ = masses[k][3 * t : 3 * (t + m)]
            code, x, y, q = codes[k, 0], codes[k, 1], codes[k, 2], codes[k, 3]
            decay, gate = params[k, 2], params[k, 3]
            if decay > 0.0 and code == RULE_DEMPSTER:  # the score in the rule's own loop
                s_ = scores[k][t : t + m]
                rejected[k] += _dempster_row(mp_, bufs[x], bad, m, s_, decay, True, gate)
            elif decay > 0.0:  # fused: the last input is the ISM of the Dempster step
                m_u_min, alpha, s_ = params[k, 0], params[k, 1], scores[k][t : t + m]
                rejected[k] += _fused_row(
                    mp_, bufs[x], bufs[y], bad, m, m_u_min, alpha, s_, decay, True, gate
                )
            else:
                m_u_min, alpha = params[k, 0], params[k, 1]
                rejected[k] += _rule_row(code, mp_, bufs[x], bufs[y], bad, m, m_u_min, alpha)
            covered[k][t : t + m] = True
            if q >= 0 and discs.ptr[q, i + 1] > discs.ptr[q, i]:
                s_, mu = scores[k][t : t + m], params[k, 4]
                seen = _doppler_cue(
                    s_, q, y, i, lo, hi, a, b, mu, sources, affine, discs, seen, cue
                )
