"""Numba kernels: ray casting against 2.5-D boxes and the ground, and box rasterisation.

Every obstacle is an oriented box: a rectangle footprint (centre, yaw, half length along its
heading, half width) extruded from ``z_min`` to ``z_max``. Boxes are packed in a float64
``(n, 8)`` array with the columns ``BOX_COLUMNS``. Static boxes are found through a uniform
2-D grid index (cells of a few metres), walked along each ray with a DDA; moving boxes are
few and tested by brute force.

The lidar kernel exploits that the 32 beams of a firing share one azimuth: the footprint
walk is done once per azimuth and each box met is intersected with all beams at once (a beam
is a line ``z = z0 + slope * t`` over the horizontal distance ``t``).

Randomness inside kernels (vegetation penetration, porous fences) comes from a counter-based
hash of (seed, firing, beam, box), so results do not depend on evaluation order.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = [
    "BOX_COLUMNS",
    "pack_boxes",
    "build_index",
    "lidar_cast",
    "radar_cast",
    "rasterize_boxes",
    "hash_uniform",
    "GridIndex",
]

#: Columns of a packed box array.
BOX_COLUMNS: tuple[str, ...] = (
    "cx",
    "cy",
    "cos_yaw",
    "sin_yaw",
    "half_length",
    "half_width",
    "z_min",
    "z_max",
)

#: Ray ids written by the kernels besides box indices.
HIT_GROUND = -1
HIT_NONE = -2

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_G1 = np.uint64(0x9E3779B97F4A7C15)
_G2 = np.uint64(0xC2B2AE3D27D4EB4F)
_G3 = np.uint64(0x165667B19E3779F9)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)


def pack_boxes(
    cx: np.ndarray,
    cy: np.ndarray,
    yaw: np.ndarray,
    hl: np.ndarray,
    hw: np.ndarray,
    zmin: np.ndarray,
    zmax: np.ndarray,
) -> np.ndarray:
    """Pack box parameters (m, rad) into the ``(n, 8)`` float64 layout of ``BOX_COLUMNS``."""
    out = np.empty((len(np.atleast_1d(cx)), 8), dtype=np.float64)
    out[:, 0] = cx
    out[:, 1] = cy
    out[:, 2] = np.cos(yaw)
    out[:, 3] = np.sin(yaw)
    out[:, 4] = hl
    out[:, 5] = hw
    out[:, 6] = zmin
    out[:, 7] = zmax
    return out


@numba.njit(cache=True)
def _mix64(x: np.uint64) -> np.uint64:
    x = (x ^ (x >> _S30)) * _M1
    x = (x ^ (x >> _S27)) * _M2
    return x ^ (x >> _S31)


@numba.njit(cache=True)
def hash_uniform(seed: np.uint64, a: int, b: int, c: int) -> float:
    """A uniform number in [0, 1) from a counter-based hash of four integers (a, b, c >= 0)."""
    h = _mix64(seed ^ (np.uint64(a) * _G1))
    h = _mix64(h ^ (np.uint64(b) * _G2))
    h = _mix64(h ^ (np.uint64(c) * _G3))
    return float(h >> _S11) * (1.0 / 9007199254740992.0)


class GridIndex:
    """A uniform 2-D grid over the static boxes' footprints: ``start``/``items`` in CSR layout."""

    def __init__(self, boxes: np.ndarray, cell: float = 4.0) -> None:
        if boxes.shape[0] == 0:
            self.x0, self.y0, self.nx, self.ny = 0.0, 0.0, 1, 1
            self.cell = float(cell)
            self.start = np.zeros(2, dtype=np.int64)
            self.items = np.zeros(0, dtype=np.int64)
            return
        ext = np.abs(boxes[:, 2:3]) * boxes[:, 4:5] + np.abs(boxes[:, 3:4]) * boxes[:, 5:6]
        exty = np.abs(boxes[:, 3:4]) * boxes[:, 4:5] + np.abs(boxes[:, 2:3]) * boxes[:, 5:6]
        xmin = boxes[:, 0] - ext[:, 0]
        xmax = boxes[:, 0] + ext[:, 0]
        ymin = boxes[:, 1] - exty[:, 0]
        ymax = boxes[:, 1] + exty[:, 0]
        self.cell = float(cell)
        self.x0 = float(xmin.min()) - cell
        self.y0 = float(ymin.min()) - cell
        self.nx = int(math.ceil((xmax.max() - self.x0) / cell)) + 2
        self.ny = int(math.ceil((ymax.max() - self.y0) / cell)) + 2
        self.start, self.items = build_index(
            xmin, ymin, xmax, ymax, self.x0, self.y0, self.cell, self.nx, self.ny
        )


@numba.njit(cache=True, inline="always")
def _index_cells(b, xmin, ymin, xmax, ymax, x0, y0, cell, nx, ny):
    """The index cells (i0, i1, j0, j1, inclusive) that box ``b``'s bounding rectangle touches."""
    i0 = max(int((xmin[b] - x0) / cell), 0)
    i1 = min(int((xmax[b] - x0) / cell), nx - 1)
    j0 = max(int((ymin[b] - y0) / cell), 0)
    j1 = min(int((ymax[b] - y0) / cell), ny - 1)
    return i0, i1, j0, j1


@numba.njit(cache=True)
def build_index(
    xmin: np.ndarray,
    ymin: np.ndarray,
    xmax: np.ndarray,
    ymax: np.ndarray,
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
) -> tuple[np.ndarray, np.ndarray]:
    """CSR lists of the boxes whose bounding rectangles touch each grid cell (ix * ny + iy)."""
    n = xmin.shape[0]
    counts = np.zeros(nx * ny + 1, dtype=np.int64)
    for b in range(n):
        i0, i1, j0, j1 = _index_cells(b, xmin, ymin, xmax, ymax, x0, y0, cell, nx, ny)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                counts[i * ny + j + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    items = np.empty(start[-1], dtype=np.int64)
    for b in range(n):
        i0, i1, j0, j1 = _index_cells(b, xmin, ymin, xmax, ymax, x0, y0, cell, nx, ny)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                c = i * ny + j
                items[fill[c]] = b
                fill[c] += 1
    return start, items


@numba.njit(cache=True, inline="always")
def _slab(p: float, d: float, half: float) -> tuple[bool, float, float]:
    """One slab |p + t d| <= half of a box, in box coordinates: (missed, t entering, t leaving)."""
    if abs(d) < 1e-12:  # parallel to the slab: inside it for every t, or never
        return abs(p) > half, -1e30, 1e30
    a = (-half - p) / d
    b = (half - p) / d
    return False, min(a, b), max(a, b)


@numba.njit(cache=True)
def _slab2d(
    ox: float, oy: float, dx: float, dy: float, box: np.ndarray
) -> tuple[float, float, int, float, float]:
    """Footprint entry/exit distances of a 2-D ray (unit direction), the entered face's axis
    (0: the box's length axis, 1: width axis) and the ray direction in box coordinates."""
    c = box[2]
    s = box[3]
    rx = ox - box[0]
    ry = oy - box[1]
    lx = c * rx + s * ry
    ly = -s * rx + c * ry
    ldx = c * dx + s * dy
    ldy = -s * dx + c * dy
    t_in = -1e30
    t_out = 1e30
    axis = -1
    for k in range(2):
        miss, a, b = _slab(lx, ldx, box[4]) if k == 0 else _slab(ly, ldy, box[5])
        if miss:
            return 1.0, -1.0, -1, ldx, ldy
        if a > t_in:
            t_in = a
            axis = k
        t_out = min(t_out, b)
    return t_in, t_out, axis, ldx, ldy


@numba.njit(cache=True, inline="always")
def _off_ray(ox: float, oy: float, dx: float, dy: float, box: np.ndarray) -> bool:
    """Bounding-circle rejection: whether ``box`` lies wholly behind or beside the ray."""
    qx = box[0] - ox
    qy = box[1] - oy
    rad = box[4] + box[5]
    return qx * dx + qy * dy < -rad or abs(qy * dx - qx * dy) > rad


@numba.njit(cache=True)
def _lidar_box(ray, box: np.ndarray, klass: int, box_id: int, materials, beams, best) -> None:
    """Intersect one box with all beams of a firing, keeping each beam's nearest hit.

    ``ray`` = (ox, oy, oz, dx, dy, seed, col); ``materials`` = (density, pass_prob) per class;
    ``beams`` = (slopes, cos_e, sin_abs_e); ``best`` = (t, id, cos) per beam, updated in place.
    """
    ox, oy, oz, dx, dy, seed, col = ray
    density, pass_prob = materials
    slopes, cos_e, sin_abs_e = beams
    best_t, best_id, best_c = best
    t_in, t_out, axis, ldx, ldy = _slab2d(ox, oy, dx, dy, box)
    t0 = t_in if t_in > 0.0 else 0.0
    if t_out < t0:
        return
    inside = t_in < 0.0
    face_h = abs(ldx) if axis == 0 else abs(ldy)
    zmin = box[6]
    zmax = box[7]
    dens = density[klass]
    pp = pass_prob[klass]
    for j in range(slopes.shape[0]):
        if t0 >= best_t[j]:
            continue
        sl = slopes[j]
        z0 = oz + sl * t0
        if zmin <= z0 <= zmax:
            if inside:
                continue  # the sensor is inside this volume: no surface to hit
            th = t0
            cv = face_h * cos_e[j]
        elif z0 > zmax and sl < 0.0:
            th = (zmax - oz) / sl
            if th > t_out:
                continue
            cv = sin_abs_e[j]
        elif z0 < zmin and sl > 0.0:
            th = (zmin - oz) / sl
            if th > t_out:
                continue
            cv = sin_abs_e[j]
        else:
            continue
        if th >= best_t[j]:
            continue
        if dens > 0.0:
            # Foliage: the beam is stopped after an exponential depth, or leaves the volume.
            te = t_out
            if sl < 0.0:
                te = min(te, (zmin - oz) / sl)
            elif sl > 0.0:
                te = min(te, (zmax - oz) / sl)
            u = hash_uniform(seed, col, j, box_id)
            th = th - math.log(1.0 - u) / dens * cos_e[j]
            if th > te or th >= best_t[j]:
                continue
            cv = 0.7  # leaves face every way
        elif pp > 0.0:
            if hash_uniform(seed, col, j, box_id) < pp:
                continue
        best_t[j] = th
        best_id[j] = box_id
        best_c[j] = cv


@numba.njit(cache=True, inline="always")
def _dda_start(ox, oy, dx, dy, t_end, gx0, gy0, gx1, gy1, cell, gnx, gny):
    """Clip the ray o + t d, t in [0, t_end], to the index rectangle and set up the cell walk.

    Returns (t0, t1, ix, iy, stepx, stepy, tmx, tmy, tdx, tdy) of Amanatides & Woo; the ray
    misses the rectangle where t0 > t1.
    """
    t0 = 0.0
    t1 = t_end
    if abs(dx) < 1e-12:
        if ox < gx0 or ox > gx1:
            t1 = -1.0
    else:
        a = (gx0 - ox) / dx
        b = (gx1 - ox) / dx
        if a > b:
            a, b = b, a
        t0 = max(t0, a)
        t1 = min(t1, b)
    if abs(dy) < 1e-12:
        if oy < gy0 or oy > gy1:
            t1 = -1.0
    else:
        a = (gy0 - oy) / dy
        b = (gy1 - oy) / dy
        if a > b:
            a, b = b, a
        t0 = max(t0, a)
        t1 = min(t1, b)
    px = ox + dx * t0
    py = oy + dy * t0
    ix = min(max(int((px - gx0) / cell), 0), gnx - 1)
    iy = min(max(int((py - gy0) / cell), 0), gny - 1)
    if dx > 1e-12:
        stepx = 1
        tmx = (gx0 + (ix + 1) * cell - ox) / dx
        tdx = cell / dx
    elif dx < -1e-12:
        stepx = -1
        tmx = (gx0 + ix * cell - ox) / dx
        tdx = -cell / dx
    else:
        stepx = 0
        tmx = 1e30
        tdx = 1e30
    if dy > 1e-12:
        stepy = 1
        tmy = (gy0 + (iy + 1) * cell - oy) / dy
        tdy = cell / dy
    elif dy < -1e-12:
        stepy = -1
        tmy = (gy0 + iy * cell - oy) / dy
        tdy = -cell / dy
    else:
        stepy = 0
        tmy = 1e30
        tdy = 1e30
    return t0, t1, ix, iy, stepx, stepy, tmx, tmy, tdx, tdy


@numba.njit(cache=True, inline="always")
def _dda_step(ix, iy, stepx, stepy, tmx, tmy, tdx, tdy, gnx, gny):
    """One cell step of the walk -> (t where the next cell is entered, ix, iy, tmx, tmy, left).

    ``left``: the walk has left the index rectangle.
    """
    if tmx < tmy:
        tcur = tmx
        tmx += tdx
        ix += stepx
        return tcur, ix, iy, tmx, tmy, ix < 0 or ix >= gnx
    tcur = tmy
    tmy += tdy
    iy += stepy
    return tcur, ix, iy, tmx, tmy, iy < 0 or iy >= gny


@numba.njit(cache=True, inline="always")
def _max_reach(best_t: np.ndarray) -> float:
    """The farthest any beam of a firing may still find something (m)."""
    tlim = 0.0
    for j in range(best_t.shape[0]):
        tlim = max(tlim, best_t[j])
    return tlim


@numba.njit(cache=True)
def _lidar_start(oz: float, max_h: np.ndarray, beams, best) -> None:
    """Start every beam of a firing at its reach, or at the ground where it meets it first."""
    slopes, cos_e, sin_abs_e = beams
    best_t, best_id, best_c = best
    for j in range(slopes.shape[0]):
        best_t[j] = max_h[j]
        best_id[j] = HIT_NONE
        best_c[j] = 0.0
        if slopes[j] < 0.0:
            tg = oz / -slopes[j]
            if tg < max_h[j]:
                best_t[j] = tg
                best_id[j] = HIT_GROUND
                best_c[j] = sin_abs_e[j]


@numba.njit(cache=True)
def _lidar_walk(ray, scene, stamp: np.ndarray, materials, beams, best) -> None:
    """Walk the static index along a firing's footprint (Amanatides & Woo) up to the farthest
    beam's current hit, intersecting each box met once with all beams."""
    ox, oy, oz, dx, dy, seed, col = ray
    boxes, classes, idx_start, idx_items, gx0, gy0, cell, gnx, gny, dboxes, dclasses = scene
    tlim = _max_reach(best[0])
    t0, t1, ix, iy, stepx, stepy, tmx, tmy, tdx, tdy = _dda_start(
        ox, oy, dx, dy, tlim, gx0, gy0, gx0 + gnx * cell, gy0 + gny * cell, cell, gnx, gny
    )
    if t0 > t1:
        return
    tcur = t0
    while tcur <= tlim:
        c = ix * gny + iy
        for p in range(idx_start[c], idx_start[c + 1]):
            b = idx_items[p]
            if stamp[b] == col:
                continue
            stamp[b] = col
            _lidar_box(ray, boxes[b], classes[b], b, materials, beams, best)
        tlim = _max_reach(best[0])
        tcur, ix, iy, tmx, tmy, left = _dda_step(ix, iy, stepx, stepy, tmx, tmy, tdx, tdy, gnx, gny)
        if left:
            break


@numba.njit(cache=True)
def lidar_cast(
    origin, az: np.ndarray, slopes: np.ndarray, max_h: np.ndarray, scene, materials, seed, out
) -> None:
    """Cast a rotating multi-beam lidar from ``origin`` = (ox, oy, oz) (m, global frame).

    ``az`` (global azimuths, rad) x ``slopes`` (tan of beam elevations) rays; ``max_h`` the
    horizontal reach of each beam (m). ``scene``: :meth:`World.cast_scene`; ``materials`` =
    (density, pass probability) per class; ``seed`` the hash seed of the sweep. Writes into
    ``out`` = (t, id, cos), per ray, the horizontal hit distance (m), what was hit (static box
    index, ``n_static + k`` for moving box k, -1 ground, -2 nothing) and the cosine of the
    incidence angle.
    """
    ox, oy, oz = origin
    boxes, dboxes, dclasses = scene[0], scene[9], scene[10]
    out_t, out_id, out_cos = out
    nb = slopes.shape[0]
    n = boxes.shape[0]
    stamp = np.full(n, -1, dtype=np.int64)
    cos_e = np.empty(nb)
    sin_abs_e = np.empty(nb)
    for j in range(nb):
        cos_e[j] = 1.0 / math.sqrt(1.0 + slopes[j] * slopes[j])
        sin_abs_e[j] = abs(slopes[j]) * cos_e[j]
    beams = (slopes, cos_e, sin_abs_e)
    best = (np.empty(nb), np.empty(nb, dtype=np.int64), np.empty(nb))
    for col in range(az.shape[0]):
        ray = (ox, oy, oz, math.cos(az[col]), math.sin(az[col]), seed, col)
        _lidar_start(oz, max_h, beams, best)
        for k in range(dboxes.shape[0]):
            # Bounding-circle rejection first: most moving objects are far from most rays.
            if not _off_ray(ox, oy, ray[3], ray[4], dboxes[k]):
                _lidar_box(ray, dboxes[k], dclasses[k], n + k, materials, beams, best)
        _lidar_walk(ray, scene, stamp, materials, beams, best)
        for j in range(nb):
            out_t[col, j] = best[0][j]
            out_id[col, j] = best[1][j]
            out_cos[col, j] = best[2][j]


@numba.njit(cache=True)
def _radar_box(ray, box: np.ndarray, box_id: int, out) -> None:
    """Insert one box's footprint entry into ray ``r``'s distance-sorted hits, if it is met.

    ``ray`` = (ox, oy, oz, dx, dy, tmax, tan_beta, r); ``out`` = (t, id, cos, nx, ny).
    """
    ox, oy, oz, dx, dy, tmax, tan_beta, r = ray
    out_t, out_id, out_cos, out_nx, out_ny = out
    t_in, t_out, axis, ldx, ldy = _slab2d(ox, oy, dx, dy, box)
    if t_in < 0.0 or t_out < t_in or t_in > tmax:
        return  # behind, missed, too far, or the sensor is inside the footprint
    # The beam's vertical opening at that distance must overlap the box's height range.
    if box[6] > oz + tan_beta * t_in or box[7] < oz - tan_beta * t_in:
        return
    k_last = out_t.shape[1] - 1
    if t_in >= out_t[r, k_last]:
        return
    if axis == 0:
        lnx = -1.0 if ldx > 0 else 1.0
        lny = 0.0
        cv = abs(ldx)
    else:
        lnx = 0.0
        lny = -1.0 if ldy > 0 else 1.0
        cv = abs(ldy)
    c = box[2]
    s = box[3]
    i = k_last
    while i > 0 and out_t[r, i - 1] > t_in:
        out_t[r, i] = out_t[r, i - 1]
        out_id[r, i] = out_id[r, i - 1]
        out_cos[r, i] = out_cos[r, i - 1]
        out_nx[r, i] = out_nx[r, i - 1]
        out_ny[r, i] = out_ny[r, i - 1]
        i -= 1
    out_t[r, i] = t_in
    out_id[r, i] = box_id
    out_cos[r, i] = cv
    out_nx[r, i] = c * lnx - s * lny
    out_ny[r, i] = s * lnx + c * lny


@numba.njit(cache=True, inline="always")
def _opaque_hit(h: int, scene, opaque: np.ndarray) -> bool:
    """Whether hit ``h`` (static index, or ``n_static + k`` for moving box k) stops a beam."""
    classes, dclasses = scene[1], scene[10]
    n = scene[0].shape[0]
    kk = classes[h] if h < n else dclasses[h - n]
    return opaque[kk]


@numba.njit(cache=True)
def _radar_walk(ray, exclude: int, scene, stamp: np.ndarray, opaque: np.ndarray, out) -> None:
    """Walk the static index along one beam (Amanatides & Woo) until its first opaque hit or
    a full hit buffer, inserting each box met once."""
    ox, oy, oz, dx, dy, tmax, tan_beta, r = ray
    boxes, classes, idx_start, idx_items, gx0, gy0, cell, gnx, gny, dboxes, dclasses = scene
    out_t, out_id = out[0], out[1]
    K = out_t.shape[1]
    t0, t1, ix, iy, stepx, stepy, tmx, tmy, tdx, tdy = _dda_start(
        ox, oy, dx, dy, tmax, gx0, gy0, gx0 + gnx * cell, gy0 + gny * cell, cell, gnx, gny
    )
    if t0 > t1:
        return
    tcur = t0
    while tcur <= t1:
        c = ix * gny + iy
        for p in range(idx_start[c], idx_start[c + 1]):
            b = idx_items[p]
            if stamp[b] == r or b == exclude:
                continue
            stamp[b] = r
            _radar_box(ray, boxes[b], b, out)
        # Nothing beyond the first opaque hit, or beyond a full buffer, can matter.
        lim = out_t[r, K - 1]
        for k in range(K):
            h = out_id[r, k]
            if h < 0:
                break
            if _opaque_hit(h, scene, opaque):
                lim = out_t[r, k]
                break
        if tcur > lim:
            break
        tcur, ix, iy, tmx, tmy, left = _dda_step(ix, iy, stepx, stepy, tmx, tmy, tdx, tdy, gnx, gny)
        if left:
            break


@numba.njit(cache=True)
def _radar_drop_occluded(r: int, scene, opaque: np.ndarray, out) -> None:
    """Drop ray ``r``'s hits behind its first opaque one (kept only while searching)."""
    out_t, out_id = out[0], out[1]
    cut = False
    for k in range(out_t.shape[1]):
        h = out_id[r, k]
        if h < 0:
            break
        if cut:
            out_t[r, k] = np.inf
            out_id[r, k] = -1
            continue
        if _opaque_hit(h, scene, opaque):
            cut = True


@numba.njit(cache=True)
def radar_cast(rays, exclude: np.ndarray, tan_beta: float, scene, opaque: np.ndarray, out) -> None:
    """Cast horizontal radar beams: ``rays`` = (ox, oy, oz, dx, dy, tmax) arrays, per ray its
    origin, unit 2-D direction and reach (m).

    Keeps, sorted by distance, the ``K = out[0].shape[1]`` nearest footprint entries whose
    height range meets the beam's vertical opening (``tan_beta``), up to the first opaque
    object. Writes into ``out`` = (t, id, cos, nx, ny) the distance (m, inf where fewer hits),
    box id (static index, ``n + k`` for moving box k, -1 none), cosine of incidence and the
    entered face's outward normal. ``scene``: :meth:`World.cast_scene`. ``exclude`` names one
    box per ray to ignore (the mirror of a bounced ray), or -1.
    """
    ox, oy, oz, dx, dy, tmax = rays
    dboxes = scene[9]
    n = scene[0].shape[0]
    stamp = np.full(n, -1, dtype=np.int64)
    for r in range(ox.shape[0]):
        out[0][r, :] = np.inf
        out[1][r, :] = -1
        out[2][r, :] = 0.0
        out[3][r, :] = 0.0
        out[4][r, :] = 0.0
        ray = (ox[r], oy[r], oz[r], dx[r], dy[r], tmax[r], tan_beta, r)
        for k in range(dboxes.shape[0]):
            if n + k != exclude[r] and not _off_ray(ox[r], oy[r], dx[r], dy[r], dboxes[k]):
                _radar_box(ray, dboxes[k], n + k, out)
        _radar_walk(ray, exclude[r], scene, stamp, opaque, out)
        _radar_drop_occluded(r, scene, opaque, out)


@numba.njit(cache=True)
def rasterize_boxes(
    boxes: np.ndarray, labels: np.ndarray, n: int, res: float, out: np.ndarray
) -> None:
    """Mark the cells of an ``(n, n)`` ego-centred grid whose centres lie in each box footprint.

    ``boxes`` are in the ego frame (packed layout). A footprint thinner than a cell counts as
    one cell thick (its half extents are raised to half a cell), so poles and fences are not
    lost between cell centres. ``out`` keeps the largest label written to a cell.
    """
    half = n / 2.0
    for b in range(boxes.shape[0]):
        cx = boxes[b, 0]
        cy = boxes[b, 1]
        c = boxes[b, 2]
        s = boxes[b, 3]
        hl = max(boxes[b, 4], 0.5 * res)
        hw = max(boxes[b, 5], 0.5 * res)
        ex = abs(c) * hl + abs(s) * hw
        ey = abs(s) * hl + abs(c) * hw
        r0 = max(int(math.floor(half - (cx + ex) / res)), 0)
        r1 = min(int(math.floor(half - (cx - ex) / res)), n - 1)
        c0 = max(int(math.floor(half - (cy + ey) / res)), 0)
        c1 = min(int(math.floor(half - (cy - ey) / res)), n - 1)
        lab = labels[b]
        for row in range(r0, r1 + 1):
            x = (half - row - 0.5) * res - cx
            for col in range(c0, c1 + 1):
                y = (half - col - 0.5) * res - cy
                lx = c * x + s * y
                ly = -s * x + c * y
                if abs(lx) <= hl and abs(ly) <= hw and out[row, col] < lab:
                    out[row, col] = lab
