"""The ray casting inverse radar model, "ray IRM" (paper sec. V-B; docs/decisions.md#ray-irm), after
Werber et al. 2015.

Input: the last N = 10 sweeps of each of the 5 radars. Every sweep is moved into the
*current* ego frame from its own sensor position at its own time::

    global = sweep.ego_pose o sweep.sensor_to_ego o p,    local = current_ego_pose^-1 o global

and the cone apex is the sensor origin moved the same way. Radar points are projected onto the
ground plane (z dropped, no height filter: the paper names none). For every detection, a
*cone* of ``opening_angle_deg`` (2 degrees) leaves its sweep's sensor position towards it.

1. Barriers: the far segment of every cone, its *cap* (the arc of radius = the detection's
   range spanning the cone's opening), is rasterised as the cells the arc passes through
   (one cell deep). Every ray of the cone crosses the arc inside one of them, so none
   slips past its own cap.
2. Free space: every cone is cast again and marks the cells it touches m_f = 0.3, but it
   stops at the first barrier cell of ANY cone it meets, its own cap included. "Stops" is
   per ray of the cone: the part of a cone behind a barrier is shadowed, the rest goes on
   (paper Fig. 2, b.2.1). The cone is the exact continuous sector, not a bundle of sampled
   rays: a cell is free when some ray of the cone enters it, inside the cone's range,
   before having entered a barrier cell (barrier cells themselves are not marked). This is
   computed per sensor position with an exact shadow-casting column sweep (see
   ``_k_cast_task``), so cones have no gaps at any range.
3. The barriers are dropped; the cells of all the sweeps' detections get m_o = 0.5.

Decisions the paper leaves open (documented here once):

* a cell both touched by a cone (step 2) and holding a detection (step 3) is occupied
  [0, m_o, 1 - m_o]: step 3 comes last in the paper. Since a detection cell is its own
  cone's cap, this only happens where a detection lies in a sensor's own cell;
* a barrier in the cell of the cone's own apex does not stop the cone (as in the ray ILM);
* caps and cone parts outside the local grid are not represented; cones whose sensor
  position lies outside the grid (old sweeps at high speed) therefore enter it stopped only
  by their own range, not by barriers outside the grid;
* a cell marked free by any cone and never occupied is [m_f, 0, 1 - m_f]; no evidence is
  accumulated between cones or sweeps inside one ISM output.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass

import numba
import numpy as np

from evgrid.data.frame import RadarSweep
from evgrid.data.sweeps import last_sweeps
from evgrid.geometry import SE3, GridSpec
from evgrid.ism import _common
from evgrid.validation import check_int, check_mass, check_number

__all__ = ["RayIrmParams", "ray_irm", "ray_irm_with_stats", "ray_irm_xy"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class RayIrmParams:
    """Parameters of the ray IRM; the defaults are the paper's (sec. V-B)."""

    n_sweeps: int = 10
    opening_angle_deg: float = 2.0
    m_free: float = 0.3
    m_occupied: float = 0.5

    def __post_init__(self) -> None:
        check_int(self, "n_sweeps", min=1)
        check_number(self, "opening_angle_deg", min=0.0, max=180.0, min_open=True, max_open=True)
        check_mass(self, "m_free")
        check_mass(self, "m_occupied")


_DEFAULT_GRID = GridSpec()
_DEFAULT_PARAMS = RayIrmParams()
_QUARTER = math.pi / 4.0
# Slope intervals narrower than this are dropped: only float noise makes them.
_EPS_SLOPE = 1e-12


# --- kernels ------------------------------------------------------------------------------------
# Coordinates inside the kernels are continuous cell coordinates (u, v): u = n/2 - x/res,
# v = n/2 - y/res (geometry.py), so cell (r, c) is the square [r, r+1) x [c, c+1).


@numba.njit(cache=True)
def _k_transform(pts, sweep_of, mats, half, inv_res, det_uv, ok):
    """Move points (sensor frame, metres) into the grid's (u, v); returns the non-finite count."""
    n_dropped = 0
    for i in range(pts.shape[0]):
        finite, x, y, z = _common.point_xyz(pts, i)
        if not finite:
            n_dropped += 1
            ok[i] = False
            continue
        k = sweep_of[i]  # (index, not a view: views cost reference counting per point)
        gx = mats[k, 0, 0] * x + mats[k, 0, 1] * y + mats[k, 0, 2] * z + mats[k, 0, 3]
        gy = mats[k, 1, 0] * x + mats[k, 1, 1] * y + mats[k, 1, 2] * z + mats[k, 1, 3]
        det_uv[i, 0] = half - gx * inv_res
        det_uv[i, 1] = half - gy * inv_res
        ok[i] = True
    return n_dropped


@numba.njit(cache=True, inline="always")
def _set_barrier(barrier, brow, bcol, r, c):
    """Mark barrier cell (r, c) in the byte grid and in the row-wise and column-wise bitmaps."""
    barrier[r, c] = 1
    one = np.uint64(1)
    brow[r, c >> 6] |= one << np.uint64(c & 63)
    bcol[c, r >> 6] |= one << np.uint64(r & 63)


@numba.njit(cache=True, inline="always")
def _word_mask(w, g0, g1):
    """The bits of uint64 word w that lie in bits g0..g1 (inclusive) of a row of words."""
    full = np.uint64(0xFFFFFFFFFFFFFFFF)
    m = full
    if w == g0 >> 6:
        m &= full << np.uint64(g0 & 63)
    if w == g1 >> 6:
        m &= full >> np.uint64(63 - (g1 & 63))
    return m


@numba.njit(cache=True, inline="always")
def _any_bits(bits, row, g0, g1):
    """Whether any bit g0..g1 (inclusive, 0 <= g0 <= g1) of uint64 word row ``bits[row]`` is set."""
    for w in range(g0 >> 6, (g1 >> 6) + 1):
        if bits[row, w] & _word_mask(w, g0, g1):
            return True
    return False


@numba.njit(cache=True, inline="always")
def _set_bits(bits, row, g0, g1):
    """Set bits g0..g1 (inclusive, 0 <= g0 <= g1) of uint64 word row ``bits[row]``."""
    for w in range(g0 >> 6, (g1 >> 6) + 1):
        bits[row, w] |= _word_mask(w, g0, g1)


@numba.njit(cache=True, inline="always")
def _cap_box(au, av, eu, ev, r, rc, rs, cos_h):
    """Bounding box (u_lo, u_hi, v_lo, v_hi) of the cap arc of :func:`_mark_cap` (rc = r cos h,
    rs = r sin h): both end points, plus the circle's extremes where the arc holds them."""
    pu = -ev
    pv = eu
    u1 = au + rc * eu - rs * pu
    u2 = au + rc * eu + rs * pu
    v1 = av + rc * ev - rs * pv
    v2 = av + rc * ev + rs * pv
    u_lo = min(u1, u2)
    u_hi = max(u1, u2)
    v_lo = min(v1, v2)
    v_hi = max(v1, v2)
    if eu >= cos_h:
        u_hi = au + r
    if eu <= -cos_h:
        u_lo = au - r
    if ev >= cos_h:
        v_hi = av + r
    if ev <= -cos_h:
        v_lo = av - r
    return u_lo, u_hi, v_lo, v_hi


@numba.njit(cache=True, inline="always")
def _cap_crossings(buf, m, au, av, eu, ev, r2, rc, ku0, ku1, kv0, kv1):
    """Append to ``buf`` (m held) s = e x w of each crossing of the cap arc with the grid lines
    u = ku0 .. ku1 and v = kv0 .. kv1 (circle-line intersections, kept where w . e > r cos h);
    returns the new m."""
    for k in range(ku0, ku1 + 1):
        x = k - au
        q = r2 - x * x
        if q < 0.0:
            continue
        y = math.sqrt(q)
        for wv in (y, -y):
            if x * eu + wv * ev > rc:
                buf[m] = eu * wv - ev * x
                m += 1
    for k in range(kv0, kv1 + 1):
        y = k - av
        q = r2 - y * y
        if q < 0.0:
            continue
        x = math.sqrt(q)
        for wu in (x, -x):
            if wu * eu + y * ev > rc:
                buf[m] = eu * y - ev * wu
                m += 1
    return m


@numba.njit(cache=True, inline="always")
def _sort_head(buf, m):
    """Sort buf[:m] in place by insertion: a cap crosses a handful of grid lines."""
    for i in range(1, m):
        x = buf[i]
        j = i - 1
        while j >= 0 and buf[j] > x:
            buf[j + 1] = buf[j]
            j -= 1
        buf[j + 1] = x


@numba.njit(cache=True)
def _mark_cap(barrier, brow, bcol, au, av, du, dv, cos_h, sin_h, buf):
    """Step 1: mark the cells the cap arc passes through, exactly.

    The arc: apex + w, |w| = r = |(du, dv)|, at most h from the direction e = (du, dv) / r;
    with p = e turned by +90 degrees, w = r (cos b e + sin b p) for |b| <= h. Its crossings
    with the grid lines u = k and v = k (circle-line intersections, kept where
    w . e >= r cos h) split it into pieces that each lie in one cell; the crossings are
    ordered by s = e x w = r sin b, and the cell of each piece's middle is marked.
    """
    n_r, n_c = barrier.shape
    r2 = du * du + dv * dv
    r = math.sqrt(r2)
    if r < 1e-9 or not r < 1e12:
        # no cap at the apex; a cap 1e12 cells away cannot touch the grid (or is inf/NaN)
        return buf
    eu = du / r
    ev = dv / r
    rc = r * cos_h
    rs = r * sin_h
    pu = -ev  # p = e turned by +90 degrees
    pv = eu
    u_lo, u_hi, v_lo, v_hi = _cap_box(au, av, eu, ev, r, rc, rs, cos_h)
    if u_hi < 0.0 or u_lo >= n_r or v_hi < 0.0 or v_lo >= n_c:
        return buf
    ku0 = int(math.ceil(u_lo))
    ku1 = int(math.floor(u_hi))
    kv0 = int(math.ceil(v_lo))
    kv1 = int(math.floor(v_hi))
    need = 2 * (max(ku1 - ku0 + 1, 0) + max(kv1 - kv0 + 1, 0)) + 2
    if buf.shape[0] < need:
        buf = np.empty(2 * need, dtype=np.float64)
    buf[0] = -rs
    buf[1] = rs
    m = _cap_crossings(buf, 2, au, av, eu, ev, r2, rc, ku0, ku1, kv0, kv1)
    _sort_head(buf, m)
    for i in range(m - 1):
        if buf[i + 1] <= buf[i]:
            continue
        sm = 0.5 * (buf[i] + buf[i + 1])
        cm = math.sqrt(max(r2 - sm * sm, 0.0))
        cu = math.floor(au + cm * eu + sm * pu)
        cv = math.floor(av + cm * ev + sm * pv)
        if cu >= 0 and cu < n_r and cv >= 0 and cv < n_c:
            _set_barrier(barrier, brow, bcol, int(cu), int(cv))
    return buf


@numba.njit(cache=True)
def _k_caps(det_uv, ok, det_apex, apex_uv, h, barrier, brow, bcol):
    buf = np.empty(64, dtype=np.float64)
    cos_h = math.cos(h)
    sin_h = math.sin(h)
    for i in range(det_uv.shape[0]):
        if not ok[i]:
            continue
        a = det_apex[i]
        au = apex_uv[a, 0]
        av = apex_uv[a, 1]
        buf = _mark_cap(
            barrier, brow, bcol, au, av, det_uv[i, 0] - au, det_uv[i, 1] - av, cos_h, sin_h, buf
        )


@numba.njit(cache=True, inline="always")
def _octant_frame(o):
    """(swap, sa, sb) of octant o: local a = sa * major, b = sb * minor; major is v when swap."""
    if o == 0:
        return False, 1, 1
    if o == 1:
        return True, 1, 1
    if o == 2:
        return True, 1, -1
    if o == 3:
        return False, -1, 1
    if o == 4:
        return False, -1, -1
    if o == 5:
        return True, -1, -1
    if o == 6:
        return True, -1, 1
    return False, 1, -1


@numba.njit(cache=True, inline="always")
def _slope_vec(o, x, y):
    """Local slope db/da in [0, 1] of the direction (x, y) (in (u, v)) seen in octant o."""
    swap, sa, sb = _octant_frame(o)
    if swap:
        da = sa * y
        db = sb * x
    else:
        da = sa * x
        db = sb * y
    if da <= 0.0:
        return 1.0
    s = db / da
    if s < 0.0:
        return 0.0
    if s > 1.0:
        return 1.0
    return s


@numba.njit(cache=True, inline="always")
def _octant_of(x, y):
    """Octant floor(atan2(y, x) / 45 degrees) of the direction (x, y), without trigonometry."""
    if y >= 0.0:
        if x > 0.0:
            return 0 if y < x else 1
        return 2 if y > -x else 3
    if x < 0.0:
        return 4 if -y < -x else 5
    return 6 if -y > x else 7


@numba.njit(cache=True, inline="always")
def _add_piece(pieces, m, a, o, s1, s2, r):
    """Record piece ``m``: apex ``a``, octant ``o``, slopes between s1 and s2, range ``r``;
    its sort key groups the pieces by (apex, octant), then by lower slope."""
    p_key, p_apex, p_oct, p_lo, p_hi, p_r = pieces
    p_apex[m] = a
    p_oct[m] = o
    p_lo[m] = min(s1, s2)
    p_hi[m] = max(s1, s2)
    p_r[m] = r
    p_key[m] = (a * 8 + o) + 0.5 * p_lo[m]
    return m + 1


@numba.njit(cache=True, inline="always")
def _narrow_pieces(pieces, m, a, eu, ev, cos_h, sin_h, r):
    """Record the octant pieces of a cone narrower than an octant (apex ``a``, unit direction
    (eu, ev), range ``r``): it spans one octant or two adjacent ones, split with vector algebra,
    its edges being e turned by -h and +h. -> the new m, or -1 where its edges are not in one
    octant or two adjacent ones (the cone is then walked as a wide one, :func:`_wide_pieces`)."""
    x1 = cos_h * eu + sin_h * ev
    y1 = cos_h * ev - sin_h * eu
    x2 = cos_h * eu - sin_h * ev
    y2 = cos_h * ev + sin_h * eu
    o1 = _octant_of(x1, y1)
    o2 = _octant_of(x2, y2)
    if not (o1 == o2 or o2 == (o1 + 1) % 8):
        return -1
    # the boundary between o1 and o1 + 1 has slope 1 in o1 when o1 is even, else 0, and the same
    # slope seen from o1 + 1
    bnd = 1.0 if o1 % 2 == 0 else 0.0
    for q in range(2 if o1 != o2 else 1):
        if o1 == o2:
            o = o1
            s1 = _slope_vec(o, x1, y1)
            s2 = _slope_vec(o, x2, y2)
        elif q == 0:
            o = o1
            s1 = _slope_vec(o, x1, y1)
            s2 = bnd
        else:
            o = o2
            s1 = bnd
            s2 = _slope_vec(o, x2, y2)
        m = _add_piece(pieces, m, a, o, s1, s2, r)
    return m


@numba.njit(cache=True, inline="always")
def _wide_pieces(pieces, m, a, phi, h, r):
    """Record the octant pieces of a cone of apex ``a``, direction ``phi`` (rad), half-angle
    ``h`` and range ``r``, walking its angles across the octant boundaries; -> the new m."""
    start = phi - h
    if start < 0.0:
        start += 2.0 * math.pi
    end = start + 2.0 * h
    k = int(math.floor(start / _QUARTER))
    x = start
    while x < end:
        bnd = (k + 1) * _QUARTER
        y = min(end, bnd)
        if y > x:
            o = k % 8
            s1 = _slope_vec(o, math.cos(x), math.sin(x))
            s2 = _slope_vec(o, math.cos(y), math.sin(y))
            m = _add_piece(pieces, m, a, o, s1, s2, r)
        x = y
        k += 1
    return m


@numba.njit(cache=True)
def _k_pieces(det_uv, ok, det_apex, apex_uv, h):
    """Split every cone into octant pieces of slope intervals -> (number of pieces, pieces =
    (key, apex, octant, lower slope, upper slope, range in cells))."""
    n = det_uv.shape[0]
    max_pieces = int(2.0 * h / _QUARTER) + 2
    cos_h = math.cos(h)
    sin_h = math.sin(h)
    narrow = 2.0 * h < _QUARTER
    pieces = (
        np.empty(n * max_pieces, dtype=np.float64),
        np.empty(n * max_pieces, dtype=np.int64),
        np.empty(n * max_pieces, dtype=np.int64),
        np.empty(n * max_pieces, dtype=np.float64),
        np.empty(n * max_pieces, dtype=np.float64),
        np.empty(n * max_pieces, dtype=np.float64),
    )
    m = 0
    for i in range(n):
        if not ok[i]:
            continue
        a = det_apex[i]
        du = det_uv[i, 0] - apex_uv[a, 0]
        dv = det_uv[i, 1] - apex_uv[a, 1]
        r = math.sqrt(du * du + dv * dv)
        if r < 1e-9:
            continue
        # Ranges only bound the cone's walk: clamp absurd ones (1e12 cells) so that r * r
        # stays finite in the cast.
        r = min(r, 1e12)
        if narrow:
            m1 = _narrow_pieces(pieces, m, a, du / r, dv / r, cos_h, sin_h, r)
            if m1 >= 0:
                m = m1
                continue
        m = _wide_pieces(pieces, m, a, math.atan2(dv, du), h, r)
    return m, pieces


@numba.njit(cache=True)
def _k_tasks(det_uv, ok, det_apex, apex_uv, h):
    """Split every cone into octant pieces of slope intervals; merge them per (apex, octant).

    Returns (task_apex, task_octant, task_start (T + 1), iv_lo, iv_hi, iv_r): task t owns
    the merged, sorted, disjoint intervals iv[task_start[t]:task_start[t + 1]]; iv_r is the
    largest cone range (cells) in the interval.
    """
    m, pieces = _k_pieces(det_uv, ok, det_apex, apex_uv, h)
    p_key, p_apex, p_oct, p_lo, p_hi, p_r = pieces
    order = np.argsort(p_key[:m])
    t_apex = np.empty(m, dtype=np.int64)
    t_oct = np.empty(m, dtype=np.int64)
    t_start = np.empty(m + 1, dtype=np.int64)
    iv_lo = np.empty(m, dtype=np.float64)
    iv_hi = np.empty(m, dtype=np.float64)
    iv_r = np.empty(m, dtype=np.float64)
    n_t = 0
    n_iv = 0
    for q in range(m):
        p = order[q]
        if n_t == 0 or p_apex[p] != t_apex[n_t - 1] or p_oct[p] != t_oct[n_t - 1]:
            t_apex[n_t] = p_apex[p]
            t_oct[n_t] = p_oct[p]
            t_start[n_t] = n_iv
            n_t += 1
        elif p_lo[p] <= iv_hi[n_iv - 1]:
            # overlaps the previous interval of this task: merge
            if p_hi[p] > iv_hi[n_iv - 1]:
                iv_hi[n_iv - 1] = p_hi[p]
            if p_r[p] > iv_r[n_iv - 1]:
                iv_r[n_iv - 1] = p_r[p]
            continue
        iv_lo[n_iv] = p_lo[p]
        iv_hi[n_iv] = p_hi[p]
        iv_r[n_iv] = p_r[p]
        n_iv += 1
    t_start[n_t] = n_iv
    return t_apex[:n_t], t_oct[:n_t], t_start[: n_t + 1], iv_lo[:n_iv], iv_hi[:n_iv], iv_r[:n_iv]


@numba.njit(cache=True, inline="always")
def _octant_grid(barrier, brow, bcol, frow, fcol, au, av, o):
    """Octant o's local frame at apex (au, av): (swap, sa, sb) (:func:`_octant_frame`), the
    apex (a0, b0), the local index ranges [i_lo, i_hi] x [j_lo, j_hi] covering the grid (a grid
    index g is i = g where sa > 0, else i = -g - 1; likewise j) and the barrier and free bitmaps
    whose rows run along b."""
    n_r, n_c = barrier.shape
    swap, sa, sb = _octant_frame(o)
    if swap:
        a0, b0, n_a, n_b, bbits, fbits = sa * av, sb * au, n_c, n_r, bcol, fcol
    else:
        a0, b0, n_a, n_b, bbits, fbits = sa * au, sb * av, n_r, n_c, brow, frow
    i_lo = 0 if sa > 0 else -n_a
    j_lo = 0 if sb > 0 else -n_b
    return swap, sa, sb, a0, b0, i_lo, i_lo + n_a - 1, j_lo, j_lo + n_b - 1, bbits, fbits


@numba.njit(cache=True, inline="always")
def _open_set(lo0, hi0, r0):
    """The sweep's open slope intervals iv[buffer, field, k] (fields lo, hi, range; buffers
    cur / nxt swap every column), buffer 0 holding the task's; -> (iv, their number, the
    largest range)."""
    n = lo0.shape[0]
    iv = np.empty((2, 3, n + 64), dtype=np.float64)
    r_max = 0.0
    for k in range(n):
        iv[0, 0, k] = lo0[k]
        iv[0, 1, k] = hi0[k]
        iv[0, 2, k] = r0[k]
        r_max = max(r_max, r0[k])
    return iv, n, r_max


@numba.njit(cache=True)
def _grown(iv, need):
    """``iv`` copied into a buffer pair that holds at least ``need`` intervals each (rare: not
    inlined, so that the sweep's loop stays small)."""
    grown = np.empty((2, 3, max(2 * iv.shape[2], need)), dtype=np.float64)
    grown[:, :, : iv.shape[2]] = iv
    return grown


@numba.njit(cache=True, inline="always")
def _push_open(iv, buf, n, lo, hi, rr):
    """Append the open interval [lo, hi) of range rr to buffer ``buf`` (n held); -> n + 1."""
    iv[buf, 0, n] = lo
    iv[buf, 1, n] = hi
    iv[buf, 2, n] = rr
    return n + 1


# The sweep's loops stay in one function: their state (the open slope intervals in two swapped
# buffers, the column's cell range, the bitmap words) lives in locals that LLVM keeps in
# registers; split into functions (even inlined ones, numba 0.68), the cast ran twice as slow.
@numba.njit(cache=True)
def _k_cast_task(barrier, brow, bcol, frow, fcol, au, av, o, lo0, hi0, r0):
    """Step 2 for one sensor position and one octant: exact shadow casting of slope intervals.

    In the octant's local frame (a = major axis, b = minor axis, both growing away from the
    apex; slopes db/da in [0, 1]) the cells are swept column by column (a = i .. i + 1); a
    ray of slope s crosses column i in increasing b. The open slope intervals (sorted,
    disjoint) live in ``iv[cur]``. In column i, cell (i, j) is touched by the slopes
    [(j - b0) / (i + 1 - a0), (j + 1 - b0) / (i - a0)]; an open cell inside the range is
    marked free; a barrier cell removes its slopes from the open set (for the rest of the
    column too, since a ray crosses a column in increasing j). The range limit of an
    interval (the largest cone range in it) only matters outside the grid: inside, every
    cone's own cap stops it. Most column runs hold no barrier: the bitmaps ``brow`` /
    ``bcol`` tell that in a few word operations, and the run is then marked free in one go
    in the free bitmap of the same orientation (``frow`` / ``fcol``). No array views are
    made inside the loops: each costs reference counting.
    """
    frame = _octant_grid(barrier, brow, bcol, frow, fcol, au, av, o)
    swap, sa, sb, a0, b0, i_lo_g, i_hi_g, j_lo_g, j_hi_g, bbits, fbits = frame
    i_apex = int(math.floor(a0))
    j_apex = int(math.floor(b0))
    iv, n_cur, r_max = _open_set(lo0, hi0, r0)
    cur = 0
    for i in range(max(i_apex, i_lo_g), i_hi_g + 1):
        near = i - a0
        if near >= r_max or n_cur == 0:
            break
        far = i + 1.0 - a0
        inv_far = 1.0 / far
        inv_near = 1.0 / near if near > 0.0 else np.inf
        near_c = near if near > 0.0 else 0.0
        gi = i if sa > 0 else -i - 1
        nxt = 1 - cur
        n_nxt = 0
        for k in range(n_cur):
            lo = iv[cur, 0, k]
            hi = iv[cur, 1, k]
            rr = iv[cur, 2, k]
            if near >= rr:
                continue
            j0 = int(math.floor(b0 + lo * near_c))
            if j0 > j_hi_g:
                continue  # these rays have left the grid for good (b only grows)
            j1 = int(math.ceil(b0 + hi * far)) - 1
            # cells whose nearest point is within range: j - b0 < sqrt(r^2 - near^2)
            jr = int(math.ceil(b0 + math.sqrt(rr * rr - near_c * near_c))) - 1
            jj0 = max(j0, j_lo_g)
            jj1 = min(j1, j_hi_g, jr)
            need = n_nxt + max(jj1 - jj0, 0) + 3  # room for up to jj1 - jj0 + 2 more intervals
            if need > iv.shape[2]:
                iv = _grown(iv, need)
            cl = lo
            if jj0 <= jj1:
                g0, g1 = (jj0, jj1) if sb > 0 else (-jj1 - 1, -jj0 - 1)
                if not _any_bits(bbits, gi, g0, g1):
                    # fast path: no barrier in this run of cells, all of it is free
                    _set_bits(fbits, gi, g0, g1)
                else:
                    for j in range(jj0, jj1 + 1):
                        c_hi = (j + 1.0 - b0) * inv_near
                        if c_hi <= cl:
                            continue
                        gj = j if sb > 0 else -j - 1
                        is_bar = (barrier[gj, gi] if swap else barrier[gi, gj]) != 0
                        if is_bar and not (i == i_apex and j == j_apex):
                            c_lo = min((j - b0) * inv_far, hi)
                            if c_lo - cl > _EPS_SLOPE:
                                n_nxt = _push_open(iv, nxt, n_nxt, cl, c_lo, rr)
                            if c_hi > cl:
                                cl = c_hi
                            if cl >= hi:
                                break
                        else:
                            fbits[gi, gj >> 6] |= np.uint64(1) << np.uint64(gj & 63)
            if hi - cl > _EPS_SLOPE:
                n_nxt = _push_open(iv, nxt, n_nxt, cl, hi, rr)
        cur = nxt
        n_cur = n_nxt


@numba.njit(cache=True, inline="always")
def _cast_one(t, barrier, brow, bcol, frow_w, fcol_w, apex_uv, tasks):
    """Task ``t`` of ``tasks`` (as :func:`_k_tasks` returns them) into one worker's bitmaps."""
    t_apex, t_oct, t_start, iv_lo, iv_hi, iv_r = tasks
    a = t_apex[t]
    s0 = t_start[t]
    s1 = t_start[t + 1]
    au = apex_uv[a, 0]
    av = apex_uv[a, 1]
    lo, hi, r = iv_lo[s0:s1], iv_hi[s0:s1], iv_r[s0:s1]
    _k_cast_task(barrier, brow, bcol, frow_w, fcol_w, au, av, t_oct[t], lo, hi, r)


@numba.njit(cache=True)
def _k_cast(barrier, brow, bcol, frow, fcol, apex_uv, tasks):
    for t in range(tasks[0].shape[0]):
        _cast_one(t, barrier, brow, bcol, frow[0], fcol[0], apex_uv, tasks)


@numba.njit(cache=True, parallel=True)
def _k_cast_par(barrier, brow, bcol, frow, fcol, apex_uv, tasks):
    # Worker w takes tasks w, w + W, w + 2W, ... and owns free bitmaps frow[w], fcol[w]
    # (bit OR into shared words would race); they are OR-ed together afterwards.
    n_w = frow.shape[0]
    for w in numba.prange(n_w):
        for t in range(w, tasks[0].shape[0], n_w):
            _cast_one(t, barrier, brow, bcol, frow[w], fcol[w], apex_uv, tasks)


@numba.njit(cache=True)
def _k_merge_free(frow, fcol, labels):
    """labels[r, c] = FREE where any worker's row-wise or column-wise free bitmap has the
    cell."""
    n_r, n_c = labels.shape
    for w in range(1, frow.shape[0]):
        frow[0] |= frow[w]
        fcol[0] |= fcol[w]
    fr = frow[0]
    fc = fcol[0]
    one = np.uint64(1)
    for r in range(n_r):
        wr = r >> 6
        br = np.uint64(r & 63)
        for c in range(n_c):
            bit = ((fr[r, c >> 6] >> np.uint64(c & 63)) | (fc[c, wr] >> br)) & one
            if bit:
                labels[r, c] = _common.FREE


@numba.njit(cache=True)
def _k_mark_detections(det_uv, ok, labels):
    """Step 3: detection cells are occupied, over any free mark (detections win)."""
    n_r, n_c = labels.shape
    n_used = 0
    for i in range(det_uv.shape[0]):
        if not ok[i]:
            continue
        n_used += 1
        fr = math.floor(det_uv[i, 0])
        fc = math.floor(det_uv[i, 1])
        if fr >= 0 and fr < n_r and fc >= 0 and fc < n_c:
            labels[int(fr), int(fc)] = _common.OCCUPIED
    return n_used


# --- the model on prepared detections ---------------------------------------------------------


def _irm_core(
    det_uv: np.ndarray,
    ok: np.ndarray,
    det_apex: np.ndarray,
    apex_uv: np.ndarray,
    grid: GridSpec,
    params: RayIrmParams,
    threads: int,
    out: np.ndarray | None,
) -> tuple[np.ndarray, int]:
    """Steps 1-3 on detections and apexes in continuous cell coordinates -> (masses, n_used)."""
    h = math.radians(params.opening_angle_deg) / 2.0
    barrier = _common.label_scratch(grid, "irm_barrier", fill=0)
    labels = _common.label_scratch(grid, "irm_labels")
    brow, bcol = _common.bit_scratch(grid, "irm_barrier_bits")
    frow, fcol = _common.bit_scratch(grid, "irm_free_bits", threads)
    if det_uv.shape[0]:
        _k_caps(det_uv, ok, det_apex, apex_uv, h, barrier, brow[0], bcol[0])
        tasks = _k_tasks(det_uv, ok, det_apex, apex_uv, h)
        if threads > 1:
            with _common.numba_threads(threads):
                _k_cast_par(barrier, brow[0], bcol[0], frow, fcol, apex_uv, tasks)
        else:
            _k_cast(barrier, brow[0], bcol[0], frow, fcol, apex_uv, tasks)
        _k_merge_free(frow, fcol, labels)
    n_used = int(_k_mark_detections(det_uv, ok, labels))
    masses = _common.labels_to_masses(labels, params.m_free, params.m_occupied, out, threads)
    return masses, n_used


def ray_irm_with_stats(
    sweeps: Iterable[RadarSweep],
    ego_pose: SE3,
    *,
    grid: GridSpec = _DEFAULT_GRID,
    params: RayIrmParams = _DEFAULT_PARAMS,
    threads: int = 1,
    out: np.ndarray | None = None,
) -> _common.IsmResult:
    """Ray IRM (paper sec. V-B) with point counts: masses ``(n, n, 3)`` float32 in the frame of
    ``ego_pose`` (metres).

    ``sweeps``: radar sweeps (any order, e.g. a :class:`RadarBuffer`); of each channel the
    last ``params.n_sweeps`` by timestamp are used. ``ego_pose``: the current ego pose
    (ego -> global) whose ego frame the grid is. ``threads > 1`` casts the cones on that
    many numba threads. NaN/inf points are dropped, counted and logged once per call.
    """
    threads = _common.check_ism_args("ray_irm", grid, params, RayIrmParams, threads, out)
    if not isinstance(ego_pose, SE3):
        raise TypeError(f"ray_irm: ego_pose must be an SE3, got {type(ego_pose).__name__}")
    used = last_sweeps(sweeps, params.n_sweeps)
    n = grid.n_cells
    inv_res = 1.0 / grid.resolution
    half = n / 2.0
    cur_inv = ego_pose.inverse().matrix()
    mats = np.empty((len(used), 3, 4), dtype=np.float64)
    apex_xy = np.empty((len(used), 2), dtype=np.float64)
    for k, s in enumerate(used):
        # local = current_ego_pose^-1 o sweep.ego_pose o sensor_to_ego (paper sec. V-B: own
        # position, own time)
        m = cur_inv @ s.ego_pose.matrix() @ s.sensor_to_ego.matrix()
        mats[k] = m[:3, :]
        apex_xy[k] = m[:2, 3]
    counts = np.array([s.points.shape[0] for s in used], dtype=np.int64)
    if counts.sum():
        pts = np.concatenate([s.points[:, :3] for s in used], axis=0)
    else:
        pts = np.empty((0, 3), dtype=np.float32)
    sweep_of = np.repeat(np.arange(len(used), dtype=np.int64), counts)
    det_uv = np.empty((pts.shape[0], 2), dtype=np.float64)
    ok = np.empty(pts.shape[0], dtype=np.bool_)
    n_dropped = (
        int(_k_transform(pts, sweep_of, mats, half, inv_res, det_uv, ok)) if pts.shape[0] else 0
    )
    # Sweeps from the very same position (a standing vehicle) share one apex.
    if len(used):
        uniq, inverse = np.unique(apex_xy, axis=0, return_inverse=True)
        det_apex = np.ascontiguousarray(inverse.reshape(-1)[sweep_of])
    else:
        uniq = np.empty((0, 2))
        det_apex = np.empty(0, dtype=np.int64)
    apex_uv = np.ascontiguousarray(
        np.stack([half - uniq[:, 0] * inv_res, half - uniq[:, 1] * inv_res], axis=1)
    )
    n_points = int(pts.shape[0])
    _common.log_dropped(logger, "ray_irm", n_dropped, n_points)
    masses, n_used = _irm_core(det_uv, ok, det_apex, apex_uv, grid, params, threads, out)
    return _common.IsmResult(masses, n_points, n_dropped, n_used)


def ray_irm(sweeps: Iterable[RadarSweep], ego_pose: SE3, **options) -> np.ndarray:
    """Ray IRM (paper sec. V-B): masses ``(n, n, 3)`` float32 [m_f, m_o, m_u] in the frame of
    ``ego_pose``; the options (``grid``, ``params``, ``threads``, ``out``) of
    :func:`ray_irm_with_stats`, which also counts the points."""
    return ray_irm_with_stats(sweeps, ego_pose, **options).masses


def ray_irm_xy(
    detections_xy: np.ndarray,
    origins_xy: np.ndarray,
    *,
    params: RayIrmParams = _DEFAULT_PARAMS,
    grid: GridSpec = _DEFAULT_GRID,
    threads: int = 1,
    out: np.ndarray | None = None,
) -> _common.IsmResult:
    """Ray IRM on detections already in the grid's frame: ``detections_xy`` ``(n, 2)`` m, cone
    apexes ``origins_xy`` ``(n, 2)`` or ``(2,)`` m.

    ``params.n_sweeps`` plays no part here: every detection given is used.
    """
    threads = _common.check_ism_args("ray_irm_xy", grid, params, RayIrmParams, threads, out)
    det = _common.as_points(detections_xy, 2, "ray_irm_xy", max_cols=2)
    if det.shape[1] != 2:
        raise ValueError(f"ray_irm_xy: detections_xy must have shape (n, 2), got {det.shape}")
    org = np.asarray(origins_xy, dtype=np.float64)
    if org.shape == (2,):
        org = np.broadcast_to(org, det.shape)
    if org.shape != det.shape:
        raise ValueError(
            f"ray_irm_xy: origins_xy must have shape (2,) or {det.shape}, got {org.shape}"
        )
    if not np.isfinite(org).all():
        raise ValueError("ray_irm_xy: origins_xy must be finite")
    n = grid.n_cells
    inv_res = 1.0 / grid.resolution
    half = n / 2.0
    ok = np.isfinite(det).all(axis=1)
    n_dropped = int((~ok).sum())
    det_uv = np.ascontiguousarray(half - det.astype(np.float64) * inv_res)
    det_uv[~ok] = 0.0
    if det.shape[0]:
        uniq, inverse = np.unique(org, axis=0, return_inverse=True)
    else:
        uniq, inverse = np.empty((0, 2)), np.empty(0, dtype=np.int64)
    apex_uv = np.ascontiguousarray(half - uniq * inv_res)
    _common.log_dropped(logger, "ray_irm_xy", n_dropped, int(det.shape[0]))
    masses, n_used = _irm_core(
        det_uv,
        ok,
        np.ascontiguousarray(inverse.reshape(-1).astype(np.int64)),
        apex_uv,
        grid,
        params,
        threads,
        out,
    )
    return _common.IsmResult(masses, int(det.shape[0]), n_dropped, n_used)
