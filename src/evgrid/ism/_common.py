"""Shared pieces of the geometric ISMs: the result type, cell labels, thread control, buffers."""

from __future__ import annotations

import contextlib
import logging
import math
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import numba
import numpy as np

from evgrid.classes import FREE as _FREE
from evgrid.classes import OCCUPIED as _OCCUPIED
from evgrid.classes import UNKNOWN as _UNKNOWN
from evgrid.geometry import GridSpec

__all__ = ["IsmResult"]

# Cell labels of the internal uint8 grids (the classes of evgrid.classes); the ISMs turn them
# into masses at the very end.
FREE = np.uint8(_FREE)
OCCUPIED = np.uint8(_OCCUPIED)
UNKNOWN = np.uint8(_UNKNOWN)


@dataclass(frozen=True, slots=True, eq=False)
class IsmResult:
    """One ISM output: ``masses`` ``(n, n, 3)`` float32 [m_f, m_o, m_u] and point counts.

    ``n_points``: points given; ``n_dropped``: of those, dropped because x, y or z was NaN or
    inf; ``n_used``: points that became detections (finite, passing the ISM's filter; they
    may still lie outside the grid); ``n_at_origin``: finite points dropped as no return,
    within :data:`~evgrid.data.frame.NO_RETURN_RANGE_M` of the sensor (the lidar ISM).
    """

    masses: np.ndarray
    n_points: int
    n_dropped: int
    n_used: int
    n_at_origin: int = 0


def check_ism_args(
    name: str, grid: object, params: object, params_type: type, threads: int, out: object
) -> int:
    """Check the arguments every geometric ISM takes; returns ``threads`` as an int."""
    if not isinstance(grid, GridSpec):
        raise TypeError(f"{name}: grid must be a GridSpec, got {type(grid).__name__}")
    if not isinstance(params, params_type):
        raise TypeError(
            f"{name}: params must be a {params_type.__name__}, got {type(params).__name__}"
        )
    check_out(out, grid)
    return check_threads(threads)


@numba.njit(cache=True, inline="always")
def point_xyz(pts, i):
    """Point ``i``'s x, y, z as float64 and whether all three are finite."""
    x = np.float64(pts[i, 0])
    y = np.float64(pts[i, 1])
    z = np.float64(pts[i, 2])
    return math.isfinite(x) and math.isfinite(y) and math.isfinite(z), x, y, z


def check_threads(threads: int) -> int:
    """Validate a thread count; clamp it to the threads numba was started with."""
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise ValueError(f"threads must be an integer >= 1, got {threads!r}")
    return int(min(int(threads), numba.config.NUMBA_NUM_THREADS))


@contextlib.contextmanager
def numba_threads(threads: int) -> Iterator[None]:
    """Run the parallel kernels inside with ``threads`` numba threads; restore the count after."""
    prev = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        yield
    finally:
        numba.set_num_threads(prev)


@numba.njit(cache=True)
def _k_labels_to_masses(labels, lut, out):
    n_r, n_c = labels.shape
    for r in range(n_r):
        for c in range(n_c):
            k = labels[r, c]
            out[r, c, 0] = lut[k, 0]
            out[r, c, 1] = lut[k, 1]
            out[r, c, 2] = lut[k, 2]


@numba.njit(cache=True, parallel=True)
def _k_labels_to_masses_par(labels, lut, out):
    n_r, n_c = labels.shape
    for r in numba.prange(n_r):
        for c in range(n_c):
            k = labels[r, c]
            out[r, c, 0] = lut[k, 0]
            out[r, c, 1] = lut[k, 1]
            out[r, c, 2] = lut[k, 2]


def mass_lut(m_free: float, m_occupied: float) -> np.ndarray:
    """Masses of the three labels, indexed by label: FREE [m_f, 0, 1 - m_f], OCCUPIED [0, m_o, 1 -
    m_o], UNKNOWN [0, 0, 1]."""
    return np.array(
        [[m_free, 0.0, 1.0 - m_free], [0.0, m_occupied, 1.0 - m_occupied], [0.0, 0.0, 1.0]],
        dtype=np.float32,
    )


def check_out(out: np.ndarray | None, grid: GridSpec) -> None:
    """Raise ValueError unless ``out`` is None or a writeable C-contiguous float32 ``(n, n, 3)``
    array."""
    if out is None:
        return
    shape = grid.shape + (3,)
    if (
        not isinstance(out, np.ndarray)
        or out.shape != shape
        or out.dtype != np.float32
        or not out.flags.c_contiguous
        or not out.flags.writeable
    ):
        got = f"{out.shape} {out.dtype}" if isinstance(out, np.ndarray) else type(out).__name__
        raise ValueError(
            f"out must be a writeable C-contiguous float32 array of shape {shape}, got {got}"
        )


def labels_to_masses(
    labels: np.ndarray, m_free: float, m_occupied: float, out: np.ndarray | None, threads: int
) -> np.ndarray:
    """Expand a uint8 label grid to float32 masses ``(n, n, 3)``: free cells [m_free, 0,
    1 - m_free], occupied [0, m_occupied, 1 - m_occupied], the rest vacuous; into ``out`` when
    given, on ``threads`` numba threads."""
    lut = mass_lut(m_free, m_occupied)
    if out is None:
        out = np.empty(labels.shape + (3,), dtype=np.float32)
    if threads > 1:
        with numba_threads(threads):
            _k_labels_to_masses_par(labels, lut, out)
    else:
        _k_labels_to_masses(labels, lut, out)
    return out


_scratch = threading.local()


def label_scratch(grid: GridSpec, name: str, fill: int = UNKNOWN) -> np.ndarray:
    """A uint8 ``(n, n)`` grid filled with ``fill`` (default UNKNOWN), reused across calls (per
    thread).

    Reuse means no fresh pages are faulted in on every call.
    """
    key = (name, grid.n_cells)
    store = getattr(_scratch, "store", None)
    if store is None:
        store = _scratch.store = {}
    a = store.get(key)
    if a is None:
        a = store[key] = np.empty(grid.shape, dtype=np.uint8)
    a.fill(fill)
    return a


def bit_scratch(grid: GridSpec, name: str, count: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Two zeroed uint64 bitmap stacks ``(count, n, ceil(n / 64))`` reused across calls (per
    thread).

    The first holds a grid by rows (bit c of row r), the second by columns (bit r of column c).
    """
    key = (name, grid.n_cells, count)
    store = getattr(_scratch, "store", None)
    if store is None:
        store = _scratch.store = {}
    pair = store.get(key)
    if pair is None:
        w = (grid.n_cells + 63) // 64
        shape = (count, grid.n_cells, w)
        pair = store[key] = (np.zeros(shape, np.uint64), np.zeros(shape, np.uint64))
    else:
        pair[0].fill(0)
        pair[1].fill(0)
    return pair


def as_points(points: object, min_cols: int, what: str, max_cols: int | None = None) -> np.ndarray:
    """Validate a point array ``(n, >= min_cols)`` of real numbers; return it C-contiguous float32
    or float64.

    ``max_cols`` is the most columns a point layout has (default ``min_cols``): an array with
    more columns than that and at most that many rows is the devkit's ``(columns, n)`` layout,
    which would otherwise be read as a few points with n coordinates each, and is refused.
    """
    a = np.asarray(points)
    cols = min_cols if max_cols is None else max_cols
    if a.ndim == 2 and a.shape[0] <= cols < a.shape[1]:
        raise ValueError(
            f"{what}: points of shape {a.shape} look transposed (one column per point, as the "
            "nuScenes devkit "
            "stores them); pass one row per point, shape (n, "
            f"{min_cols if cols == min_cols else f'{min_cols}..{cols}'}), e.g. points.T"
        )
    if a.ndim != 2 or a.shape[1] < min_cols:
        raise ValueError(
            f"{what}: points must have shape (n, {min_cols}) or more columns, got shape {a.shape}"
        )
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{what}: points must be real numbers, got dtype {a.dtype}")
    if a.dtype != np.float32 and a.dtype != np.float64:
        a = a.astype(np.float64)
    return np.ascontiguousarray(a)


def log_dropped(logger: logging.Logger, what: str, n_dropped: int, n_points: int) -> None:
    """One warning per call when non-finite points were dropped."""
    if n_dropped:
        logger.warning(
            "%s: dropped %d of %d points with NaN or inf coordinates", what, n_dropped, n_points
        )
