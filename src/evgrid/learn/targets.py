"""Ev-Net's training targets: the ray ILM of the sample's own lidar frame (the paper's, sec.
V-C), or the ray ILMs of the lidar frames around the sample, combined in its ego grid
(docs/training.md#targets, docs/decisions.md#accumulated-targets).

Targets come from the lidar only, never from a simulator's truth: a user's recordings have
none. Each frame of the window is cast straight into the sample's ego grid by
:func:`evgrid.ism.ray_ilm` (its ``reference_pose``: points and lidar origin moved with the
poses), so no grid is resampled and the rays stay exact.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from evgrid.classes import FREE, OCCUPIED, UNKNOWN
from evgrid.data.frame import LidarSweep
from evgrid.geometry import GridSpec
from evgrid.validation import check_choice, check_int, check_number

__all__ = [
    "TargetConfig",
    "TARGET_KINDS",
    "TARGET_RULES",
    "ilm_classes",
    "accumulated_classes",
    "TargetWindow",
]

#: ``TargetConfig.kind``.
TARGET_KINDS: tuple[str, ...] = ("accumulated", "single_frame")
#: ``TargetConfig.rule``.
TARGET_RULES: tuple[str, ...] = ("vote", "dempster")

_US = 1_000_000  # frame timestamps are in microseconds


@dataclass(frozen=True, slots=True)
class TargetConfig:
    """What Ev-Net learns to predict (docs/training.md#targets)."""

    #: accumulated: the lidar frames within the window, combined by rule; single_frame: the
    #: sample frame's ray ILM alone, as the paper trained (sec. V-C)
    kind: str = "accumulated"
    before_s: float = 1.0  #: the window's start before the sample (accumulated)
    after_s: float = 1.0  #: the window's end after the sample (accumulated)
    #: how the frames combine (accumulated): vote (occupied where at least occupied_share of
    #: the frames that saw the cell saw it occupied, else free) or dempster (Dempster's rule
    #: on the masses, then the larger of m_o and m_f)
    rule: str = "vote"
    occupied_share: float = 0.5  #: the vote's share of observing frames that makes a cell occupied
    #: every this many lidar frames of the window, counted from the sample (accumulated; 2
    #: halves the cost, neighbouring frames of a fast lidar seeing nearly the same)
    frame_step: int = 1

    def __post_init__(self) -> None:
        check_choice(self, "kind", choices=TARGET_KINDS)
        check_number(self, "before_s", min=0.0)
        check_number(self, "after_s", min=0.0)
        check_choice(self, "rule", choices=TARGET_RULES)
        check_number(self, "occupied_share", min=0.0, max=1.0, min_open=True)
        check_int(self, "frame_step", min=1)

    def to_dict(self) -> dict:
        """Plain-JSON form (evgrid.serial, the serialiser of every parameter dataclass)."""
        from evgrid.serial import to_dict

        return to_dict(self)


def ilm_classes(masses: np.ndarray) -> np.ndarray:
    """Target classes from ray ILM masses: m_o > 0 OCCUPIED, else m_f > 0 FREE, else UNKNOWN.

    See docs/decisions.md#ev-net-targets-and-loss.
    """
    out = np.full(masses.shape[:-1], UNKNOWN, dtype=np.uint8)
    out[masses[..., 0] > 0] = FREE
    out[masses[..., 1] > 0] = OCCUPIED
    return out


def _frame_ilms(
    sweeps: Iterable[LidarSweep], sample: LidarSweep, grid: GridSpec
) -> Iterable[np.ndarray]:
    """Each sweep's ray ILM in ``sample``'s ego grid (the sample's own sweep without a pose
    change, so that it is today's single-frame ILM bit for bit)."""
    from evgrid.ism import ray_ilm

    for s in sweeps:
        if s is sample:
            yield ray_ilm(s, grid=grid)
        else:
            yield ray_ilm(s, reference_pose=sample.ego_pose, grid=grid)


def accumulated_classes(
    sweeps: Sequence[LidarSweep], sample: LidarSweep, config: TargetConfig, grid: GridSpec
) -> np.ndarray:
    """Target classes of ``sample`` (one of ``sweeps``) from the ray ILMs of ``sweeps``, each
    cast into the sample's ego grid, combined by ``config.rule``; cells no sweep observed are
    UNKNOWN.

    ``vote``: among the sweeps that observed a cell (its single-sweep class not UNKNOWN), it is
    OCCUPIED where at least ``occupied_share`` of them call it occupied, else FREE; a car that
    drives by is occupied in few of the sweeps that see its cells, so leaves no trail.
    ``dempster``: the masses combined by Dempster's rule (paper eq. (5)); OCCUPIED where
    m_o > m_f, else FREE where m_f > 0.
    """
    ilms = _frame_ilms(sweeps, sample, grid)
    if config.rule == "vote":
        seen = np.zeros(grid.shape, dtype=np.int32)
        occupied = np.zeros(grid.shape, dtype=np.int32)
        for m in ilms:
            c = ilm_classes(m)
            seen += c != UNKNOWN
            occupied += c == OCCUPIED
        out = np.full(grid.shape, UNKNOWN, dtype=np.uint8)
        out[seen > 0] = FREE
        # integer form of occupied / seen >= share, exact for a share of 1
        out[(occupied > 0) & (occupied >= config.occupied_share * seen)] = OCCUPIED
        return out
    from evgrid.mass import dempster

    acc = None
    for m in ilms:
        acc = m if acc is None else dempster(acc, m)
    if acc is None:
        raise ValueError("accumulated_classes: no sweeps")
    f, o = acc[..., 0], acc[..., 1]
    out = np.full(grid.shape, UNKNOWN, dtype=np.uint8)
    out[f > 0] = FREE
    out[(o > 0) & (o > f)] = OCCUPIED
    return out


class TargetWindow:
    """The cleaned lidar sweeps around the pending samples, in time order: memory bounded by
    the window (``before_s + after_s``), not by the scene."""

    def __init__(self, config: TargetConfig, grid: GridSpec):
        self.config = config
        self.grid = grid
        self.before_us = round(config.before_s * _US)
        self.after_us = round(config.after_s * _US)
        self.sweeps: deque[tuple[int, LidarSweep]] = deque()  # (index in the scene, sweep)
        self._pushed = 0

    def push(self, sweep: LidarSweep) -> None:
        self.sweeps.append((self._pushed, sweep))
        self._pushed += 1

    @property
    def last(self) -> LidarSweep:
        return self.sweeps[-1][1]

    def complete_for(self, sample: LidarSweep) -> bool:
        """Whether every sweep of ``sample``'s window has arrived (a later one has)."""
        return self.last.timestamp > sample.timestamp + self.after_us

    def target(self, sample: LidarSweep) -> np.ndarray:
        """``sample``'s target classes from the sweeps within its window (every
        ``frame_step``-th from the sample on either side)."""
        lo, hi = sample.timestamp - self.before_us, sample.timestamp + self.after_us
        k = next(i for i, s in self.sweeps if s is sample)
        inside = [
            s
            for i, s in self.sweeps
            if lo <= s.timestamp <= hi and (i - k) % self.config.frame_step == 0
        ]
        return accumulated_classes(inside, sample, self.config, self.grid)

    def drop_before(self, timestamp: int) -> None:
        """Forget the sweeps that no window from ``timestamp`` on reaches."""
        while self.sweeps and self.sweeps[0][1].timestamp < timestamp - self.before_us:
            self.sweeps.popleft()
