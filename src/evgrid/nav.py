"""The navigation map: the lidar's evidence, the radar and the prior filling what it did not see.

``nav`` is a function of two maps of the same set, the lidar map L (``ray_ilm``) and the fused
map F, cell by cell and over a small neighbourhood (docs/equations.md#the-navigation-map):

* a cell is *clear* when no cell within ``margin_m`` of it (a square of ``2 r + 1`` cells,
  ``r = round(margin_m / resolution)``) holds lidar occupied mass (``m_o(L) > 0``: the lidar saw a
  return there) or fused occupied mass above ``occupied_min``;
* F' is F with its free mass counted as unknown where the cell is not clear, and its occupied
  mass counted as unknown where the lidar's evidence is free-dominant (``m_f(L) > m_o(L)``);
* ``nav = L (+)_D F'`` (Dempster's rule, paper eq. (5)); where L is a gated copy (the dynamic
  score's gate), a cell the ungated lidar map holds occupied-dominant keeps no free mass.

So a cell the lidar saw occupied is never freed by the radar or the prior, nor are the cells
around it, and the lidar's free space stays free. nav keeps no memory of its own: it is
computed from L and F when it is read, over the cells their updates changed since the last
read (:func:`refresh`), which keeps its cost off the per-update path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from evgrid.grid import EvidentialMap
from evgrid.kernels import nav_cells
from evgrid.validation import check_number

__all__ = ["NavParams", "nav_dense", "refresh"]

# Defaults chosen with benchmarks/nav_map.py on simulated scenes (seeds 4, 9, 14; docs/speed.md):
# half a metre keeps the radar's free cones off the lidar's returns and the cells beside them
# (the lidar's rays are sparse at range, walls show gaps between returns), and fused occupied
# mass above 0.1 is a radar or prior obstacle that the radar must not free around either.
NAV_MARGIN_M_DEFAULT = 0.5
NAV_OCCUPIED_MIN_DEFAULT = 0.1


@dataclass(frozen=True, slots=True)
class NavParams:
    """The navigation map's clearance: ``margin_m`` (m, >= 0) around any lidar return or any
    fused occupied mass above ``occupied_min`` (in (0, 1]; 1 ignores the fused map's
    occupied mass) within which the fused map's free mass is not taken."""

    margin_m: float = NAV_MARGIN_M_DEFAULT
    occupied_min: float = NAV_OCCUPIED_MIN_DEFAULT
    # cells the dynamic score calls moving block like a return (with the score on)
    avoid_moving: bool = True

    def __post_init__(self) -> None:
        check_number(self, "margin_m", min=0.0, max=100.0)
        check_number(self, "occupied_min", min=0.0, max=1.0, min_open=True)
        if not isinstance(self.avoid_moving, bool):
            raise ValueError(
                f"NavParams.avoid_moving must be true or false, got {self.avoid_moving!r}"
            )

    def margin_cells(self, resolution: float) -> int:
        """The margin in whole cells at ``resolution`` (m per cell)."""
        return int(round(self.margin_m / resolution))


def _check_map_view(name: str, a: np.ndarray) -> None:
    if not isinstance(a, np.ndarray) or a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.float32:
        got = f"{a.dtype} {a.shape}" if isinstance(a, np.ndarray) else type(a).__name__
        raise ValueError(f"nav: {name} must be a float32 (h, w, 3) array, got {got}")


def nav_dense(
    lidar_map: np.ndarray,
    fused_map: np.ndarray,
    margin_cells: int = 0,
    occupied_min: float = 1.0,
    moving: np.ndarray | None = None,
    moving_min: float = math.inf,
    plain: np.ndarray | None = None,
) -> np.ndarray:
    """nav of dense ``(h, w, 3)`` float32 lidar and fused maps (cells beyond the edges are
    vacuous); ``margin_cells`` 0 and ``occupied_min`` 1 look at each cell alone. ``moving``
    ``(h, w)``: a dynamic score per cell; cells above ``moving_min`` block like a return.
    ``plain``: the ungated lidar map when ``lidar_map`` is a gated copy (the gate): a cell it
    calls occupied-dominant keeps no free mass."""
    _check_map_view("lidar_map", lidar_map)
    _check_map_view("fused_map", fused_map)
    for name, other in (("fused map", fused_map), ("ungated lidar map", plain)):
        if other is not None and other.shape != lidar_map.shape:
            raise ValueError(
                f"nav: the lidar map {lidar_map.shape} and {name} {other.shape} differ in shape"
            )
    if plain is not None:
        _check_map_view("plain", plain)
    if isinstance(margin_cells, bool) or not isinstance(margin_cells, (int, np.integer)):
        raise TypeError(f"nav: margin_cells must be an int, got {margin_cells!r}")
    if margin_cells < 0:
        raise ValueError(f"nav: margin_cells must be >= 0, got {margin_cells}")
    r = int(margin_cells)
    h, w = lidar_map.shape[:2]
    pad = ((r, r), (r, r), (0, 0))
    vac = ((0.0, 0.0), (0.0, 0.0), (0.0, 1.0))  # vacuous beyond the edges: m_u = 1
    lp = np.pad(lidar_map, pad, constant_values=vac)
    fp = np.pad(fused_map, pad, constant_values=vac)
    pp = lp if plain is None else np.pad(plain, pad, constant_values=vac)
    mp = np.zeros((h + 2 * r, w + 2 * r), np.float32)
    if moving is not None:
        if np.shape(moving) != (h, w):
            raise ValueError(f"nav: moving must have shape {(h, w)}, got {np.shape(moving)}")
        mp[r : r + h, r : r + w] = moving
    out = np.empty((h, w, 3), np.float32)
    nav_cells(lp, fp, mp, pp, plain is not None, out, r, float(occupied_min), float(moving_min))
    return out


def refresh(
    nav: EvidentialMap,
    lidar: EvidentialMap,
    fused: EvidentialMap,
    box: tuple[int, int, int, int],
    margin_cells: int,
    occupied_min: float,
    moving_min: float = math.inf,
    plain: EvidentialMap | None = None,
) -> None:
    """Recompute ``nav`` where the cells ``box`` (r0, c0, h, w) of ``lidar`` or ``fused`` changed:
    over the box grown by the margin, reading the two maps over the box grown by twice it. With
    a finite ``moving_min``, cells whose dynamic score (the larger of the two maps') exceeds it
    block the fused map's free mass like a lidar return. ``plain``: the ungated lidar map when
    ``lidar`` is a gated copy (see :func:`nav_dense`)."""
    r = int(margin_cells)
    r0, c0, h, w = box
    r0, c0, h, w = r0 - r, c0 - r, h + 2 * r, w + 2 * r  # the cells whose nav can change
    read = (r0 - r, c0 - r, h + 2 * r, w + 2 * r)
    lm, lcov = lidar.read(*read)
    fm, fcov = fused.read(*read)
    moving = np.zeros(read[2:], np.float32)
    if math.isfinite(moving_min):
        for m in (lidar, fused):
            if m.dynamic:
                np.maximum(moving, m.read_dynamic(*read), out=moving)
    out = np.empty((h, w, 3), np.float32)
    pm = lm if plain is None else plain.read(*read)[0]
    nav_cells(lm, fm, moving, pm, plain is not None, out, r, float(occupied_min), float(moving_min))
    cov = (lcov | fcov)[r : r + h, r : r + w]
    for key, tr, tc, wr, wc in nav.pieces(r0, c0, h, w):
        piece = cov[wr, wc]
        if key not in nav.tiles and not piece.any():
            continue
        tile, tcov = nav.tile(key)
        tile[tr, tc] = out[wr, wc]  # vacuous where neither map is covered, as L and F are there
        tcov[tr, tc] |= piece
