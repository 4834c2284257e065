"""The last N radar sweeps of each radar: the one place that rule lives.

Both radar ISMs read "the last N sweeps" of every radar (paper sec. V-B), whatever the radar's
rate and whatever its channel is called. :class:`RadarBuffer` keeps them as frames arrive and
counts what a real recording throws at it: a sweep whose timestamp its radar already delivered
(duplicate) or one older than the newest held (out of order) is skipped and counted, never
re-sorted into the past. :func:`last_sweeps` applies the same rule to any list of sweeps.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator

from evgrid.data.frame import Frame, RadarSweep, channel_order

__all__ = ["RadarBuffer", "GapCounter", "last_sweeps", "channel_order"]


def _check_n(n_sweeps: object, what: str) -> int:
    if isinstance(n_sweeps, bool) or not isinstance(n_sweeps, int) or n_sweeps < 1:
        raise ValueError(f"{what} must be an integer >= 1, got {n_sweeps!r}")
    return n_sweeps


def last_sweeps(sweeps: Iterable[RadarSweep], n_sweeps: int) -> list[RadarSweep]:
    """The last ``n_sweeps`` sweeps (by timestamp) of each channel, channel by channel, oldest
    first."""
    n = _check_n(n_sweeps, "n_sweeps")
    per: dict[str, list[RadarSweep]] = {}
    for s in sweeps:
        if not isinstance(s, RadarSweep):
            raise TypeError(f"radar sweeps must be RadarSweep objects, got {type(s).__name__}")
        per.setdefault(s.channel, []).append(s)
    out: list[RadarSweep] = []
    for ch in sorted(per, key=channel_order):
        out.extend(sorted(per[ch], key=lambda s: s.timestamp)[-n:])
    return out


class GapCounter:
    """Counts missing sweeps of one sensor from the gaps between the timestamps it delivered.

    The sensor's period is the median of its last ``window`` intervals (no rate is assumed); a
    gap longer than 1.5 periods means ``round(gap / period) - 1`` sweeps are missing.
    """

    def __init__(self, window: int = 9) -> None:
        self._last: int | None = None
        self._intervals: deque[int] = deque(maxlen=window)
        self.n_missing = 0

    @property
    def last(self) -> int | None:
        """The last timestamp added (us), None before the first."""
        return self._last

    def add(self, t_us: int) -> int:
        """Note a delivered timestamp; returns how many sweeps were missing before it. A stamp
        at or before the last one counts nothing and does not move the last one back."""
        last = self._last
        if last is not None and t_us <= last:
            return 0
        self._last = int(t_us)
        if last is None:
            return 0
        gap = int(t_us) - last
        missing = 0
        if len(self._intervals) >= 3:
            period = sorted(self._intervals)[len(self._intervals) // 2]
            if gap > 1.5 * period:
                missing = max(int(round(gap / period)) - 1, 0)
                self.n_missing += missing
                return missing  # a gap is not an interval: the period estimate stays
        self._intervals.append(gap)
        return missing


class RadarBuffer:
    """The last ``n_sweeps`` radar sweeps of each channel, fed frame by frame.

    ``update(frame)`` appends the frame's radar sweeps. Per channel, a sweep is kept only if it
    is newer than every sweep that channel delivered before: duplicates and late sweeps are
    skipped and counted in ``n_duplicate`` and ``n_out_of_order``; gaps in a channel's sweeps
    are counted in ``n_missing`` (see :class:`GapCounter`). Iterating yields the held sweeps,
    channel by channel, oldest first.
    """

    def __init__(self, n_sweeps: int = 10) -> None:
        self.n_sweeps = _check_n(n_sweeps, "RadarBuffer.n_sweeps")
        self._buf: dict[str, deque[RadarSweep]] = {}
        self._newest: dict[
            str, int
        ] = {}  # survives clear(): a late sweep after a reset is still late
        self.n_duplicate = 0
        self.n_out_of_order = 0
        self._gaps: dict[str, GapCounter] = {}

    @property
    def n_missing(self) -> int:
        """Sweeps missing between those delivered, all channels."""
        return sum(g.n_missing for g in self._gaps.values())

    def push(self, sweep: RadarSweep) -> bool:
        """Add one sweep to its channel (dropping that channel's oldest beyond ``n_sweeps``);
        False if skipped."""
        if not isinstance(sweep, RadarSweep):
            raise TypeError(f"RadarBuffer.push needs a RadarSweep, got {type(sweep).__name__}")
        newest = self._newest.get(sweep.channel)
        if newest is not None and sweep.timestamp <= newest:
            if sweep.timestamp == newest or any(
                s.timestamp == sweep.timestamp for s in self._buf.get(sweep.channel, ())
            ):
                self.n_duplicate += 1
            else:
                self.n_out_of_order += 1
            return False
        self._newest[sweep.channel] = sweep.timestamp
        self._gaps.setdefault(sweep.channel, GapCounter()).add(sweep.timestamp)
        q = self._buf.get(sweep.channel)
        if q is None:
            q = self._buf[sweep.channel] = deque(maxlen=self.n_sweeps)
        q.append(sweep)
        return True

    def update(self, frame: Frame) -> None:
        """Add all radar sweeps of ``frame``."""
        if not isinstance(frame, Frame):
            raise TypeError(f"RadarBuffer.update needs a Frame, got {type(frame).__name__}")
        for s in frame.radar_sweeps():
            self.push(s)

    def sweeps(self, n_sweeps: int | None = None) -> list[RadarSweep]:
        """The held sweeps (or only the last ``n_sweeps`` of each channel), channel by channel,
        oldest first."""
        n = self.n_sweeps if n_sweeps is None else _check_n(n_sweeps, "n_sweeps")
        return [s for ch in sorted(self._buf, key=channel_order) for s in list(self._buf[ch])[-n:]]

    @property
    def channels(self) -> tuple[str, ...]:
        """The radar channels seen so far."""
        return tuple(sorted(self._buf, key=channel_order))

    def clear(self) -> None:
        """Forget all held sweeps (at a scene change or a skipped pose jump)."""
        for q in self._buf.values():
            q.clear()

    def __iter__(self) -> Iterator[RadarSweep]:
        return iter(self.sweeps())

    def __len__(self) -> int:
        return sum(len(q) for q in self._buf.values())
