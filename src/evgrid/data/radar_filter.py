"""Which radar detections count: the validity fields of the ARS 408 cluster list.

nuScenes radar ``.pcd`` files hold every cluster the sensor reported; the devkit's
``RadarPointCloud.from_file`` drops by default those whose ``invalid_state`` is not 0 (valid),
whose ``dyn_prop`` is not in 0-6 (7: "stopped") or whose ``ambig_state`` is not 3 (unambiguous
Doppler). evgrid's loaders keep everything (docs/conventions.md#sensor-data); a
:class:`RadarFilter` decides, and the same filter must be used to train Ev-Net and to map with
it (the checkpoint records it; :func:`check_trained_filter` warns on a mismatch).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from evgrid.data.frame import RadarSweep, radar_column

__all__ = ["RadarFilter", "RADAR_FILTER_MODES", "check_trained_filter"]

logger = logging.getLogger(__name__)

RADAR_FILTER_MODES: tuple[str, ...] = ("none", "nuscenes", "custom")

#: The devkit's defaults (nuscenes-devkit 1.2.0, RadarPointCloud.from_file).
_NUSCENES = {"invalid_state": (0,), "dyn_prop": tuple(range(7)), "ambig_state": (3,)}


@dataclass(frozen=True, slots=True)
class RadarFilter:
    """Keep detections whose ``invalid_state``, ``dyn_prop`` and ``ambig_state`` are in the given sets.

    ``mode`` "none" keeps all; "nuscenes" uses the devkit's default sets (the fields given here
    are ignored); "custom" uses the sets given, where ``None`` accepts any value.
    """

    mode: str = "none"
    invalid_state: tuple[int, ...] | None = None
    dyn_prop: tuple[int, ...] | None = None
    ambig_state: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if self.mode not in RADAR_FILTER_MODES:
            raise ValueError(
                f"RadarFilter.mode must be one of {RADAR_FILTER_MODES}, got {self.mode!r}"
            )
        for name in _NUSCENES:
            v = getattr(self, name)
            if v is None:
                continue
            if not isinstance(v, tuple) or not all(
                isinstance(x, int) and not isinstance(x, bool) for x in v
            ):
                raise ValueError(
                    f"RadarFilter.{name} must be a tuple of integers or None, got {v!r}"
                )

    @classmethod
    def named(cls, name: str) -> RadarFilter:
        """``"none"`` or ``"nuscenes"`` (the command line's choices)."""
        if name not in ("none", "nuscenes"):
            raise ValueError(f"radar filter must be 'none' or 'nuscenes', got {name!r}")
        return cls(name)

    def sets(self) -> dict[str, tuple[int, ...] | None]:
        """The accepted values of each field (None: any)."""
        if self.mode == "none":
            return {k: None for k in _NUSCENES}
        if self.mode == "nuscenes":
            return dict(_NUSCENES)
        return {k: getattr(self, k) for k in _NUSCENES}

    @property
    def is_identity(self) -> bool:
        """Whether the filter keeps every detection."""
        return all(v is None for v in self.sets().values())

    def describe(self) -> str:
        """A name for logs: ``none``, ``nuscenes`` or ``custom(field=values, ...)``."""
        if self.mode != "custom":
            return self.mode
        parts = [f"{k}={list(v)}" for k, v in self.sets().items() if v is not None]
        return f"custom({', '.join(parts)})"

    def keep(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask of the ``(n, 12)`` radar points (``RADAR_COLUMNS``) that pass."""
        ok = np.ones(len(points), dtype=bool)
        for name, allowed in self.sets().items():
            if allowed is not None:
                ok &= np.isin(np.rint(points[:, radar_column(name)]).astype(np.int64), allowed)
        return ok

    def __call__(self, sweep: RadarSweep) -> tuple[RadarSweep, int]:
        """(the sweep with only the passing detections, how many were dropped); the same sweep if none."""
        if self.is_identity or len(sweep.points) == 0:
            return sweep, 0
        ok = self.keep(sweep.points)
        n = int(len(ok) - ok.sum())
        if n == 0:
            return sweep, 0
        return RadarSweep(
            sweep.points[ok], sweep.sensor_to_ego, sweep.ego_pose, sweep.timestamp, sweep.channel
        ), n

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON (lists for the sets), as stored in checkpoints (evgrid.serial)."""
        from evgrid.serial import to_dict

        return to_dict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RadarFilter:
        """Inverse of :meth:`to_dict` (evgrid.serial; missing fields take their defaults)."""
        from evgrid.serial import from_dict

        return from_dict(cls, d)


def check_trained_filter(
    used: RadarFilter, extra: dict[str, Any] | None, checkpoint: str = "the checkpoint"
) -> bool:
    """Warn (and return False) if ``used`` differs from the filter a checkpoint's metadata says it
    was trained with; a checkpoint that records none was trained unfiltered."""
    rec = (extra or {}).get("radar_filter")
    trained = RadarFilter.from_dict(rec) if isinstance(rec, dict) else RadarFilter()
    if trained.sets() == used.sets():
        return True
    logger.warning(
        "radar filter %r differs from the one %s was trained with (%r); the deep IRM sees other detections "
        "than in training",
        used.describe(),
        checkpoint,
        trained.describe(),
    )
    return False
