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
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from evgrid.geometry import SE2, GridSpec
from evgrid.grid import EvidentialMap, MapWindow, Warper, warp_window, window_affine
from evgrid.kernels import (
    _BLOCK,
    RULE_DEEP_DISC,
    RULE_DEEP_REPLACE,
    RULE_DEMPSTER,
    RULE_FUSED,
    _k_blocks,
    _k_deep_disc_into,
    _k_deep_replace_into,
    _k_dempster_into,
    _k_fused_into,
    _k_informative,
    _k_spans,
    _k_warp_update,
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
MAP_NAMES: tuple[str, ...] = (
    "ray_ilm",
    "deep_acc",
    "deep_replace",
    "deep_disc",
    "ray_irm",
    "fused",
)
#: The three inverse sensor models that feed them.
ISM_NAMES: tuple[str, ...] = ("ray_ilm", "ray_irm", "deep_irm")

# Default lower limit on the deep ISM's unknown mass; the paper gives no value
# (docs/decisions.md#default-lower-limit-on-unknown-mass).
# Chosen by `evgrid sweep-m-u-min` on simulated validation scenes (seeds 4, 9, 14, 19) with the
# shipped Ev-Net: the highest limit whose deep_disc mIoU is within 0.01 of the best (0.494 vs
# 0.495 at 0.1); at >= 0.5 a cell known only to the deep IRM can never be classified free or
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
            raise ValueError(
                f"map and ISM views must be float32 (h, w, 3), got {a.dtype} {a.shape}"
            )
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
        got = (
            f"{spans.dtype} {spans.shape}"
            if isinstance(spans, np.ndarray)
            else type(spans).__name__
        )
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
    cell: np.ndarray,
    ilm: np.ndarray,
    params: FusionParams = FusionParams(),
    spans: np.ndarray | None = None,
) -> int:
    """``map = map (+)_D ray ILM``, in place on ``(h, w, 3)`` float32 views."""
    _check_views(cell, ilm)
    return int(_k_dempster_into(*_pair(cell, ilm, spans)))


def update_deep_acc(
    cell: np.ndarray,
    deep: np.ndarray,
    params: FusionParams = FusionParams(),
    spans: np.ndarray | None = None,
) -> int:
    """``map = map (+)_D deep IRM`` (paper: deep IRM (acc.)), in place."""
    _check_views(cell, deep)
    return int(_k_dempster_into(*_pair(cell, deep, spans)))


def update_deep_replace(
    cell: np.ndarray,
    deep: np.ndarray,
    params: FusionParams = FusionParams(),
    spans: np.ndarray | None = None,
) -> int:
    """Replace a cell by ``limit_unknown(deep IRM, m_u_min)`` where that is less unknown (paper: deep IRM (replace))."""
    _check_views(cell, deep)
    return int(_k_deep_replace_into(*_pair(cell, deep, spans), float(params.m_u_min)))


def update_deep_disc(
    cell: np.ndarray,
    deep: np.ndarray,
    params: FusionParams = FusionParams(),
    spans: np.ndarray | None = None,
) -> int:
    """``map = map (+)_Y (gamma (x) limit_unknown(deep IRM))`` (paper eqs. (29), (35); deep IRM (disc.)), in place."""
    _check_views(cell, deep)
    return int(
        _k_deep_disc_into(*_pair(cell, deep, spans), float(params.m_u_min), float(params.alpha))
    )


def update_ray_irm(
    cell: np.ndarray,
    irm: np.ndarray,
    params: FusionParams = FusionParams(),
    spans: np.ndarray | None = None,
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
    return int(
        _k_fused_into(
            fm,
            mrs,
            fd,
            drs,
            fi,
            irs,
            h,
            w,
            _row_spans(spans, h, w),
            float(params.m_u_min),
            float(params.alpha),
        )
    )


@dataclass(frozen=True, slots=True)
class UpdateRule:
    """One map of Table I: its name, the ISMs it reads (in argument order) and its update function."""

    name: str
    isms: tuple[str, ...]
    update: Callable[..., int]


# The one-pass kernel's code for each rule (evgrid.kernels._k_warp_update).
_KERNEL_RULE = {
    "ray_ilm": RULE_DEMPSTER,
    "deep_acc": RULE_DEMPSTER,
    "deep_replace": RULE_DEEP_REPLACE,
    "deep_disc": RULE_DEEP_DISC,
    "ray_irm": RULE_DEMPSTER,
    "fused": RULE_FUSED,
}

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

    :meth:`update` loads each ISM grid once (checked, into the padded copy of its
    :class:`~evgrid.grid.Warper`) and then visits each covered map cell once: it samples every
    ISM there as the warp would (bilinearly) and applies every map's rule, so no warped window
    is written and read back. :meth:`warp` and :meth:`update_windows` do the same in two passes
    through whole warped windows (the extra map sets of the ``m_u_min`` sweep share them); both
    give the same maps.

    Invalid ISM cells never reach a map: ``n_rejected[ism]`` counts the cells of the local ISM
    grids that were not masses and were taken as vacuous (no information), and
    ``n_rejected_cells[map]`` the window cells that a map's update rule rejected (non-zero only
    for windows that did not come from :meth:`warp`).
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
            n: EvidentialMap(
                self.grid,
                tile_cells,
                {"rule": n, "m_u_min": self.params.m_u_min, "alpha": self.params.alpha},
            )
            for n in self.names
        }
        self.required_isms: tuple[str, ...] = tuple(
            i for i in ISM_NAMES if any(i in RULES[n].isms for n in self.names)
        )
        # one loader / warper per ISM: its checked, padded copy of the local grid is what the
        # one-pass update samples
        self._warpers = {i: Warper(self.grid, i) for i in self.required_isms}
        slot = {i: s for s, i in enumerate(self.required_isms)}
        # per map: its rule's kernel code and the slots of the ISMs it reads
        self._rules = np.array(
            [
                (_KERNEL_RULE[m], slot[RULES[m].isms[0]], slot[RULES[m].isms[-1]])
                for m in self.names
            ],
            dtype=np.int64,
        )
        self._bufs = np.empty((len(self.required_isms), 3 * int(tile_cells)), dtype=np.float32)
        side = int(np.ceil(self.grid.n_cells * np.sqrt(2.0))) + 4
        self._spans = np.zeros((side, 2), dtype=np.int64)
        self.n_updates = 0
        self.n_rejected_cells: dict[str, int] = {m: 0 for m in self.names}

    @property
    def n_rejected(self) -> dict[str, int]:
        """Per ISM, the cells of its local grids that were not masses and were taken as vacuous."""
        return {i: w.n_rejected for i, w in self._warpers.items()}

    def __getitem__(self, name: str) -> EvidentialMap:
        return self.maps[name]

    def load(self, isms: Mapping[str, np.ndarray]) -> None:
        """Take the local ISM grids ``(n, n, 3)`` of one step; cells that are not masses become vacuous (counted)."""
        missing = [i for i in self.required_isms if i not in isms]
        if missing:
            raise ValueError(f"missing ISM grid(s) {missing}; these maps need {self.required_isms}")
        for name, warper in self._warpers.items():
            warper.load(isms[name])

    def update(self, pose: SE2, isms: Mapping[str, np.ndarray]) -> dict[str, int]:
        """Fuse one time step: local ISM grids keyed by ISM name, taken at ego ``pose`` in the first pose's frame.

        Returns, per map, the window cells its rule rejected (always 0 here: invalid ISM cells
        are made vacuous on loading and counted in ``n_rejected``).
        """
        self.load(isms)
        return self.update_loaded(pose)

    def update_loaded(self, pose: SE2) -> dict[str, int]:
        """Fuse the ISM grids of the last :meth:`load`, taken at ego ``pose``, into every map in one pass."""
        grid, n = self.grid, self.grid.n_cells
        r0, c0, h, w = warp_window(grid, pose)
        affine = window_affine(grid, pose, r0, c0)
        spans = self._spans[:h]
        _k_spans(*affine, n, h, w, spans)
        nb = (h + _BLOCK - 1) // _BLOCK
        jl, jh = np.empty(nb, np.int64), np.empty(nb, np.int64)
        _k_blocks(spans, h, w, jl, jh)
        informative = np.zeros(
            (len(self.required_isms), nb, (w + _BLOCK - 1) // _BLOCK + 1), dtype=np.bool_
        )
        warpers = tuple(self._warpers.values())
        for s, warper in enumerate(warpers):
            _k_informative(warper.coarse, n, *affine, h, jl, jh, informative[s])
        maps = [self.maps[m] for m in self.names]
        ts = maps[0].tile_cells
        rejected = np.zeros(len(maps), dtype=np.int64)
        src = tuple(warper.source for warper in warpers)
        for key, tr, tc, wr, wc in maps[0]._pieces(r0, c0, h, w):
            piece = spans[wr]
            rows_on = np.flatnonzero(
                np.minimum(piece[:, 1], wc.stop) > np.maximum(piece[:, 0], wc.start)
            )
            if len(rows_on) == 0:
                continue
            a, b = int(rows_on[0]), int(rows_on[-1]) + 1  # the piece's rows with covered cells
            tiles = [m._tile(key) for m in maps]
            _k_warp_update(
                src,
                3 * (n + 3),
                n,
                informative,
                jl,
                *affine,
                spans,
                wr.start + a,
                wr.start + b,
                wc.start,
                wc.stop,
                tuple(t.reshape(-1) for t, _ in tiles),
                tuple(c.reshape(-1) for _, c in tiles),
                ts,
                tr.start + a,
                tc.start,
                self._rules,
                float(self.params.m_u_min),
                float(self.params.alpha),
                self._bufs,
                rejected,
            )
        self.n_updates += 1
        out = {m: int(r) for m, r in zip(self.names, rejected)}
        for m, r in out.items():
            self.n_rejected_cells[m] += r
        return out

    def warp(self, pose: SE2, isms: Mapping[str, np.ndarray]) -> dict[str, MapWindow]:
        """Every required local ISM grid ``(n, n, 3)`` at ``pose`` warped into a whole map window (buffers reused next call)."""
        self.load(isms)
        return self.warp_loaded(pose)

    def warp_loaded(self, pose: SE2) -> dict[str, MapWindow]:
        """The windows of the ISM grids of the last :meth:`load` at ``pose`` (see :meth:`warp`)."""
        return {name: warper.warp_loaded(pose) for name, warper in self._warpers.items()}

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
                any_w,
                lambda cell, *views, spans, _u=rule.update: _u(cell, *views, params, spans),
                *arrays,
                pass_spans=True,
            )
            if n and self.n_rejected_cells[name] == 0:
                logger.warning(
                    "%s: the update rule rejected %d window cell(s) that are not masses; "
                    "counted in MapSet.n_rejected_cells",
                    name,
                    n,
                )
            self.n_rejected_cells[name] += n
        self.n_updates += 1
        return rejected
