"""A rerun recording (``.rrd``) or live viewer of a mapping run: maps, current ISMs, trajectory (``pip install 'evgrid[rerun]'``).

Entities: ``maps/NAME`` (a window of ``window_m`` metres around the vehicle, RGB = m_f, m_o, m_u
as in every evgrid figure), ``isms/NAME`` (the local ISM grids of the update), ``trajectory``
(ego positions in the map frame, metres) and ``ego`` (the current position), on the timeline
``time`` (the frames' timestamps) and ``update`` (the update's number); pictures at keyframes
unless asked for at every update. At :meth:`close`,
``final/NAME`` holds each whole map.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.grid import EvidentialMap

__all__ = ["RerunRecorder", "write_map_rrd"]


def _rr() -> Any:
    from evgrid.ros import require

    return require("rerun", "rerun")


def _whole(m: EvidentialMap, max_cells: int = 2048) -> np.ndarray:
    from evgrid.render import masses_to_rgb, sample_map

    r0, c0, h, w = m.covered_bounds()
    step = max(1, -(-max(h, w) // max_cells))
    return masses_to_rgb(sample_map(m, r0, c0, h, w, step)[0])


class RerunRecorder:
    """Observer that logs each update to rerun: to ``path`` (``.rrd``) or, with ``path=None``, a spawned viewer.

    ``keyframes_only`` limits the map and ISM pictures to keyframes (the trajectory is logged at
    every update; a live viewer may want every update); ``window_m`` and ``step`` size the
    pictures (cells read: ``(window_m / res / step)^2``, ISMs at every ``step``-th cell).
    """

    def __init__(
        self,
        path: str | os.PathLike | None = None,
        window_m: float = 80.0,
        step: int = 2,
        keyframes_only: bool = True,
        isms: bool = True,
    ):
        rr = _rr()
        self.rr = rr
        self.rec = rr.RecordingStream("evgrid")
        self.path = Path(path) if path is not None else None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(self.path))
        else:
            self.rec.spawn()
        self.window_m = window_m
        self.step = step
        self.keyframes_only = keyframes_only
        self.isms = isms
        self.trajectory: list[tuple[float, float]] = []
        self._maps: dict[str, EvidentialMap] = {}
        self._n = 0

    def on_update(self, update: Any) -> None:
        from evgrid.render import masses_to_rgb, sample_map

        rr, rec = self.rr, self.rec
        rec.set_time("time", timestamp=update.frame.timestamp * 1e-6)
        rec.set_time("update", sequence=self._n)
        self._n += 1
        self.trajectory.append((update.pose.x, update.pose.y))
        rec.log("trajectory", rr.LineStrips2D([np.asarray(self.trajectory)]))
        rec.log("ego", rr.Points2D([self.trajectory[-1]], radii=1.0))
        self._maps = update.maps.maps
        if self.keyframes_only and not update.frame.is_keyframe:
            return
        if self.isms:
            for name, ism in update.isms.items():
                rec.log(f"isms/{name}", rr.Image(masses_to_rgb(ism[:: self.step, :: self.step])))
        for name, m in update.maps.maps.items():
            n = int(round(self.window_m / m.grid.resolution))
            rc, cc = m.grid.map_xy_to_cell(update.pose.x, update.pose.y)
            pic = masses_to_rgb(
                sample_map(m, int(rc) - n // 2, int(cc) - n // 2, n, n, self.step)[0]
            )
            rec.log(f"maps/{name}", rr.Image(pic))

    def close(self) -> Path | None:
        """Log the whole final maps and flush; returns the ``.rrd`` path (None for a live viewer)."""
        for name, m in self._maps.items():
            if m.covered_bounds()[2]:
                self.rec.log(f"final/{name}", self.rr.Image(_whole(m)))
        self.rec.flush()
        if self.path is not None:
            self.rec.disconnect()
        return self.path


def write_map_rrd(m: EvidentialMap, path: str | os.PathLike, name: str | None = None) -> Path:
    """One saved map as a rerun recording (entity ``final/NAME``)."""
    rr = _rr()
    rec = rr.RecordingStream("evgrid")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec.save(str(path))
    rec.log(f"final/{name or m.metadata.get('rule', 'map')}", rr.Image(_whole(m)))
    rec.flush()
    rec.disconnect()
    return path
