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


class TwoPassMaps:
    """Maps updated in two passes: every ISM warped into a whole window, then each rule on it."""

    def __init__(
        self,
        grid: GridSpec,
        params: FusionParams = FusionParams(),
        names: tuple[str, ...] = MAP_NAMES,
        tile_cells: int = 256,
    ):
        self.grid, self.params, self.names = grid, params, tuple(names)
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
                rejected[name] = self._from_maps(name, any_w)
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

    def _from_maps(self, name: str, window: MapWindow) -> int:
        # a rule from maps reads the same cells of its input maps, already updated this step
        rule = RULES[name]
        out = self.all_maps[name]
        spans = window.row_spans()
        h, w = window.shape
        for key, tr, tc, wr, wc in out.pieces(window.r0, window.c0, h, w):
            piece = np.clip(spans[wr] - wc.start, 0, wc.stop - wc.start)
            if not (piece[:, 1] > piece[:, 0]).any():
                continue
            tile, cov = out.tile(key)
            inputs = [self.all_maps[m].tile(key)[0][tr, tc] for m in rule.inputs]
            rule.update(tile[tr, tc], *inputs, self.params, piece)
            cov[tr, tc] |= window.covered[wr, wc]
        return 0

    def update(self, pose: SE2, isms: Mapping[str, np.ndarray]) -> dict[str, int]:
        return self.update_windows(self.warp(pose, isms))
