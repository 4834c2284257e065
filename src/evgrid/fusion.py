"""The six map update rules of the paper's Table I, and a set of maps updated in one pass.

Each rule updates map cells in place from ISM masses on the same cells (both ``(h, w, 3)``
views, see :meth:`evgrid.grid.EvidentialMap.apply`):

==============  ==========================================================================
``ray_ilm``     map = map (+)_D ray ILM (the reference)
``deep_acc``    map = map (+)_D deep IRM
``deep_replace`` m = limit_unknown(deep IRM, m_u_min); cell := m where m_u(m) < m_u(map)
``deep_disc``   m = limit_unknown(deep IRM, m_u_min); map = map (+)_Y (gamma (x) m)
``ray_irm``     map = map (+)_D ray IRM
``fused``       the deep_disc step, then map = map (+)_D ray IRM
==============  ==========================================================================

ISM cells that are vacuous leave a map cell unchanged under every rule, so kernels skip them.
ISM cells that are not masses (NaN or inf, a negative mass, a sum off 1 by more than
``evgrid.kernels.MASS_ATOL``) leave it unchanged too: each rule returns how many it rejected,
and :class:`MapSet` counts them (docs/hostile-input.md). The paper's equations behind each rule:
docs/equations.md#the-six-maps-of-table-i.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np

from evgrid.geometry import SE2, GridSpec
from evgrid.grid import EvidentialMap, MapWindow, Warper
from evgrid.kernels import (
    _k_count_invalid,
    _k_deep_disc_into,
    _k_deep_replace_into,
    _k_dempster_into,
    _k_fused_into,
    _k_vacate_invalid,
    rows,
)
from evgrid.validation import check_number

__all__ = [
    "MAP_NAMES",
    "ISM_NAMES",
    "FusionParams",
    "UpdateRule",
    "RULES",
    "update_ray_ilm",
    "update_deep_acc",
    "update_deep_replace",
    "update_deep_disc",
    "update_ray_irm",
    "update_fused",
    "MapSet",
]

#: The six maps of the paper's Table I, in its order.
MAP_NAMES: tuple[str, ...] = ("ray_ilm", "deep_acc", "deep_replace", "deep_disc", "ray_irm", "fused")
#: The three inverse sensor models that feed them.
ISM_NAMES: tuple[str, ...] = ("ray_ilm", "ray_irm", "deep_irm")

# Default lower limit on the deep ISM's unknown mass; the paper gives no value
# (docs/decisions.md#default-lower-limit-on-unknown-mass).
# Chosen by `evgrid sweep-m-u-min` on simulated validation scenes (seeds 4, 9, 14, 19) with the
# shipped Ev-Net: the highest limit whose deep_disc mIoU is within 0.01 of the best (0.528 vs
# 0.530 at 0.05); at >= 0.5 a cell known only to the deep IRM can never be classified free or
# occupied (deep_disc free mIoU drops from 0.76 to 0), below 0.3 the prior is less clearly
# apart from verified space for no gain.
M_U_MIN_DEFAULT = 0.3
ALPHA_DEFAULT = 10.0  # paper, section IV-D, eq. (28)

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class FusionParams:
    """Parameters of the deep-ISM rules: ``m_u_min`` (unitless, [0, 1)) and ``alpha`` (gain of tanh, >= 0)."""

    m_u_min: float = M_U_MIN_DEFAULT
    alpha: float = ALPHA_DEFAULT

    def __post_init__(self) -> None:
        check_number(self, "m_u_min", min=0.0, max=1.0, max_open=True)
        check_number(self, "alpha", min=0.0)


# --- public rules ----------------------------------------------------------------------------

def _check_views(cell: np.ndarray, *isms: np.ndarray) -> None:
    for a in (cell, *isms):
        if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.float32:
            raise ValueError(f"map and ISM views must be float32 (h, w, 3), got {a.dtype} {a.shape}")
        if a.shape != cell.shape:
            raise ValueError(f"ISM view shape {a.shape} differs from the map view's {cell.shape}")
    if not cell.flags.writeable:
        raise ValueError("the map view must be writeable (updates are in place)")


def _row_spans(spans: np.ndarray | None, h: int, w: int) -> np.ndarray:
    """Columns to update per row, ``(h, 2)`` int64 ``[lo, hi)``; None means whole rows."""
    if spans is None:
        out = np.empty((h, 2), dtype=np.int64)
        out[:, 0] = 0
        out[:, 1] = w
        return out
    if not isinstance(spans, np.ndarray) or spans.shape != (h, 2) or spans.dtype != np.int64:
        got = f"{spans.dtype} {spans.shape}" if isinstance(spans, np.ndarray) else type(spans).__name__
        raise ValueError(f"spans must be an int64 array of shape {(h, 2)}, got {got}")
    return spans  # kernels clamp each [lo, hi) to [0, w]


def _pair(cell: np.ndarray, ism: np.ndarray, spans: np.ndarray | None) -> tuple:
    fm, mrs, h, w = rows(cell)
    fi, irs, _, _ = rows(ism)
    return fm, mrs, fi, irs, h, w, _row_spans(spans, h, w)


# Each rule updates ``cell`` in place from ISM views of the same shape. ``spans`` (optional,
# ``(h, 2)`` int64) limits row i to columns ``spans[i, 0]:spans[i, 1]``: the covered cells of
# a warped window (:attr:`evgrid.grid.MapWindow.spans`); cells outside are left untouched.
# Each returns the number of invalid ISM cells it rejected (their map cells are left untouched).

def update_ray_ilm(
    cell: np.ndarray, ilm: np.ndarray, params: FusionParams = FusionParams(), spans: np.ndarray | None = None
) -> int:
    """``map = map (+)_D ray ILM``, in place on ``(h, w, 3)`` float32 views."""
    _check_views(cell, ilm)
    return int(_k_dempster_into(*_pair(cell, ilm, spans)))


def update_deep_acc(
    cell: np.ndarray, deep: np.ndarray, params: FusionParams = FusionParams(), spans: np.ndarray | None = None
) -> int:
    """``map = map (+)_D deep IRM`` (paper: deep IRM (acc.)), in place."""
    _check_views(cell, deep)
    return int(_k_dempster_into(*_pair(cell, deep, spans)))


def update_deep_replace(
    cell: np.ndarray, deep: np.ndarray, params: FusionParams = FusionParams(), spans: np.ndarray | None = None
) -> int:
    """Replace a cell by ``limit_unknown(deep IRM, m_u_min)`` where that is less unknown (paper: deep IRM (replace))."""
    _check_views(cell, deep)
    return int(_k_deep_replace_into(*_pair(cell, deep, spans), float(params.m_u_min)))


def update_deep_disc(
    cell: np.ndarray, deep: np.ndarray, params: FusionParams = FusionParams(), spans: np.ndarray | None = None
) -> int:
    """``map = map (+)_Y (gamma (x) limit_unknown(deep IRM))`` (paper eqs. (29), (35); deep IRM (disc.)), in place."""
    _check_views(cell, deep)
    return int(_k_deep_disc_into(*_pair(cell, deep, spans), float(params.m_u_min), float(params.alpha)))


def update_ray_irm(
    cell: np.ndarray, irm: np.ndarray, params: FusionParams = FusionParams(), spans: np.ndarray | None = None
) -> int:
    """``map = map (+)_D ray IRM``, in place."""
    _check_views(cell, irm)
    return int(_k_dempster_into(*_pair(cell, irm, spans)))


def update_fused(
    cell: np.ndarray,
    deep: np.ndarray,
    irm: np.ndarray,
    params: FusionParams = FusionParams(),
    spans: np.ndarray | None = None,
) -> int:
    """The deep_disc step with the deep IRM, then ``map (+)_D ray IRM`` (paper: fused IRM), in place.

    An invalid cell of one ISM skips that ISM's step on the cell; the count is over both ISMs.
    """
    _check_views(cell, deep, irm)
    fm, mrs, h, w = rows(cell)
    fd, drs, _, _ = rows(deep)
    fi, irs, _, _ = rows(irm)
    return int(_k_fused_into(fm, mrs, fd, drs, fi, irs, h, w, _row_spans(spans, h, w), float(params.m_u_min), float(params.alpha)))


@dataclass(frozen=True, slots=True)
class UpdateRule:
    """One map of Table I: its name, the ISMs it reads (in argument order) and its update function."""

    name: str
    isms: tuple[str, ...]
    update: Callable[..., int]


RULES: dict[str, UpdateRule] = {
    "ray_ilm": UpdateRule("ray_ilm", ("ray_ilm",), update_ray_ilm),
    "deep_acc": UpdateRule("deep_acc", ("deep_irm",), update_deep_acc),
    "deep_replace": UpdateRule("deep_replace", ("deep_irm",), update_deep_replace),
    "deep_disc": UpdateRule("deep_disc", ("deep_irm",), update_deep_disc),
    "ray_irm": UpdateRule("ray_irm", ("ray_irm",), update_ray_irm),
    "fused": UpdateRule("fused", ("deep_irm", "ray_irm"), update_fused),
}


class MapSet:
    """Several maps of Table I over one scene, in the first pose's frame, updated in one pass.

    Each ISM needed by any map is warped once per update and shared by the maps that read it.

    Invalid ISM cells never reach a map: ``n_rejected[ism]`` counts the cells of the local ISM
    grids given to :meth:`warp` that were not masses and were taken as vacuous (no
    information), and ``n_rejected_cells[map]`` the window cells that a map's update rule
    rejected (non-zero only for windows that did not come from :meth:`warp`).
    """

    def __init__(
        self,
        grid: GridSpec | None = None,
        params: FusionParams | None = None,
        names: tuple[str, ...] = MAP_NAMES,
        tile_cells: int = 256,
    ):
        unknown = [n for n in names if n not in RULES]
        if unknown or not names:
            raise ValueError(f"unknown map name(s) {unknown}; choose from {MAP_NAMES}")
        self.grid = grid or GridSpec()
        self.params = params or FusionParams()
        self.names = tuple(names)
        self.maps: dict[str, EvidentialMap] = {
            n: EvidentialMap(self.grid, tile_cells, {"rule": n, "m_u_min": self.params.m_u_min, "alpha": self.params.alpha})
            for n in self.names
        }
        self.required_isms: tuple[str, ...] = tuple(i for i in ISM_NAMES if any(i in RULES[n].isms for n in self.names))
        self._warpers = {i: Warper(self.grid) for i in self.required_isms}
        self.n_updates = 0
        self.n_rejected: dict[str, int] = {i: 0 for i in self.required_isms}
        self.n_rejected_cells: dict[str, int] = {n: 0 for n in self.names}

    def __getitem__(self, name: str) -> EvidentialMap:
        return self.maps[name]

    def warp(self, pose: SE2, isms: Mapping[str, np.ndarray]) -> dict[str, MapWindow]:
        """Warp every required local ISM grid ``(n, n, 3)`` at ``pose`` into map windows (views reused next call)."""
        missing = [i for i in self.required_isms if i not in isms]
        if missing:
            raise ValueError(f"missing ISM grid(s) {missing}; these maps need {self.required_isms}")
        return {i: self._warpers[i].warp(self._checked(i, isms[i]), pose) for i in self.required_isms}

    def _checked(self, name: str, local: np.ndarray) -> np.ndarray:
        """``local``, or a copy whose invalid cells are vacuous (counted in ``n_rejected``).

        Checked before the warp: its bilinear mix would blend an invalid cell into its
        neighbours, where a negative mass can hide inside a valid-looking sum.
        """
        a = np.asarray(local)
        if a.ndim != 3 or a.shape[2] != 3 or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            return a  # the warp reports what is wrong
        a = np.ascontiguousarray(a, dtype=np.float32)  # what the warp reads anyway
        flat, rs, h, w = rows(a)
        if _k_count_invalid(flat, rs, h, w) == 0:
            return a
        a = a.copy()  # never write into the caller's grid
        flat, rs, h, w = rows(a)
        n_bad = int(_k_vacate_invalid(flat, rs, h, w))
        if self.n_rejected[name] == 0:
            logger.warning("%s: %d cell(s) of the local grid are not masses (NaN, inf, negative or not summing to 1); "
                           "they are taken as vacuous and counted in MapSet.n_rejected", name, n_bad)
        self.n_rejected[name] += n_bad
        return a

    def update(self, pose: SE2, isms: Mapping[str, np.ndarray]) -> dict[str, int]:
        """Fuse one time step: local ISM grids keyed by ISM name, taken at ego ``pose`` in the first pose's frame.

        Returns, per map, the window cells its rule rejected (see :meth:`update_windows`).
        """
        windows = self.warp(pose, isms)
        return self.update_windows(windows)

    def update_windows(self, windows: Mapping[str, MapWindow]) -> dict[str, int]:
        """Fuse already-warped ISM windows (all from the same pose) into every map.

        Window cells that are not masses leave their map cells untouched; returns how many each
        map's rule rejected in this step (also added to ``n_rejected_cells``).
        """
        any_w = next(iter(windows.values()))
        rejected: dict[str, int] = {}
        for name in self.names:
            rule = RULES[name]
            arrays = tuple(windows[i].masses for i in rule.isms)
            params = self.params
            rejected[name] = n = self.maps[name].apply(
                any_w, lambda cell, *views, spans, _u=rule.update: _u(cell, *views, params, spans), *arrays, pass_spans=True
            )
            if n and self.n_rejected_cells[name] == 0:
                logger.warning("%s: the update rule rejected %d window cell(s) that are not masses; "
                               "counted in MapSet.n_rejected_cells", name, n)
            self.n_rejected_cells[name] += n
        self.n_updates += 1
        return rejected
