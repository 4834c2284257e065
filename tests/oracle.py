"""The reference oracle of the map update: warp whole windows, then apply each rule to them.

This was evgrid's second production route (``MapSet.warp`` + ``update_windows``) until the
one-pass update (:meth:`evgrid.fusion.MapSet.update`) became the only one. It is kept here,
written from the public pieces only (:class:`evgrid.grid.Warper` for the whole windows,
:meth:`evgrid.grid.EvidentialMap.apply` and :meth:`~evgrid.grid.EvidentialMap.pieces` for the
tiles, the rules of :data:`evgrid.fusion.RULES` on dense views), so that the tests can check
that the one pass gives the same maps bit for bit.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from evgrid.fusion import ISM_NAMES, MAP_NAMES, RULES, FusionParams
from evgrid.geometry import SE2, GridSpec
from evgrid.grid import EvidentialMap, MapWindow, Warper
from evgrid.nav import NavParams, nav_dense


class TwoPassMaps:
    """Maps updated in two passes: every ISM warped into a whole window, then each rule on it."""

    def __init__(
        self,
        grid: GridSpec,
        params: FusionParams = FusionParams(),
        names: tuple[str, ...] = MAP_NAMES,
        tile_cells: int = 256,
        nav: NavParams = NavParams(),
    ):
        self.grid, self.params, self.names, self.nav = grid, params, tuple(names), nav
        needed = [m for n in self.names if RULES[n].from_maps for m in RULES[n].inputs]
        order = [n for n in self.names if not RULES[n].from_maps]
        order += [m for m in dict.fromkeys(needed) if m not in order]
        order += [n for n in self.names if RULES[n].from_maps]
        self.order = order
        self.all_maps = {n: EvidentialMap(grid, tile_cells) for n in order}
        self.maps = {n: self.all_maps[n] for n in self.names}
        isms = {i for n in self.names for i in RULES[n].isms}
        self.warpers = {i: Warper(grid, i) for i in ISM_NAMES if i in isms}
        self.n_rejected_cells = {n: 0 for n in self.names}
        self.n_updates = 0

    def __getitem__(self, name: str) -> EvidentialMap:
        return self.maps[name]

    @property
    def n_rejected(self) -> dict[str, int]:
        return {i: w.n_rejected for i, w in self.warpers.items()}

    def warp(self, pose: SE2, isms: Mapping[str, np.ndarray]) -> dict[str, MapWindow]:
        """The first pass: each ISM grid warped whole into the map at ``pose``."""
        return {i: w.warp(isms[i], pose) for i, w in self.warpers.items()}

    def update_windows(self, windows: Mapping[str, MapWindow]) -> dict[str, int]:
        """The second pass: each map's rule on the windows (all from one pose)."""
        any_w = next(iter(windows.values()))
        rejected = {}
        for name in self.order:
            rule = RULES[name]
            if rule.from_maps:
                rejected[name] = self._from_maps(name)
                continue
            arrays = tuple(windows[i].masses for i in rule.inputs)
            rejected[name] = self.all_maps[name].apply(
                any_w,
                lambda cell, *views, spans, _r=rule: _r.update(cell, *views, self.params, spans),
                *arrays,
                pass_spans=True,
            )
        for name in self.names:
            self.n_rejected_cells[name] += rejected[name]
        self.n_updates += 1
        return {n: rejected[n] for n in self.names}

    def _from_maps(self, name: str) -> int:
        # nav: recomputed over the whole of its input maps (already updated this step)
        lidar, fused = (self.all_maps[m] for m in RULES[name].inputs)
        r0, c0, h, w = lidar.bounds()
        lm, cov = lidar.read(r0, c0, h, w)
        fm, fcov = fused.read(r0, c0, h, w)
        r = self.nav.margin_cells(self.grid.resolution)
        nav = nav_dense(lm, fm, r, self.nav.occupied_min)
        out = self.all_maps[name]
        for key, tr, tc, wr, wc in out.pieces(r0, c0, h, w):
            if (cov | fcov)[wr, wc].any():
                tile, tcov = out.tile(key)
                tile[tr, tc] = nav[wr, wc]
                tcov[tr, tc] |= (cov | fcov)[wr, wc]
        return 0

    def update(self, pose: SE2, isms: Mapping[str, np.ndarray]) -> dict[str, int]:
        return self.update_windows(self.warp(pose, isms))
