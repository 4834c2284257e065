"""The tf tree over time: ego poses and extrinsics looked up at any stamp, interpolated."""

from __future__ import annotations

import bisect
import logging
import math

import numpy as np

from evgrid.geometry import SE3

__all__ = ["TransformBuffer"]

logger = logging.getLogger(__name__)


class TransformBuffer:
    """The tf tree over time: per child frame its parent and samples; static edges apart.

    :meth:`lookup` gives the pose of a frame in an ancestor frame at a time, interpolating
    every dynamic edge on the way (and returning a stored sample itself when the time is one).

    tf allows a frame one parent. A frame that a recording gives a second (dynamic) parent,
    such as ``map -> base_link`` beside ``odom -> base_link``, keeps each parent's samples
    apart (mixing them would jump between two poses); it is logged once and counted in
    :attr:`second_parents` (child -> {parent: samples}), and a lookup climbs through the parent
    from which the frame asked for is reached, the first one when both reach it.
    """

    def __init__(self, max_gap_us: int = 100_000):
        self.max_gap_us = max_gap_us
        # child -> {parent: (stamps, samples)}, parents in the order they appeared
        self._dyn: dict[str, dict[str, tuple[list[int], list[tuple]]]] = {}
        self._static: dict[str, tuple[str, SE3]] = {}
        self._arrays: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.second_parents: dict[str, dict[str, int]] = {}

    def add(
        self,
        parent: str,
        child: str,
        t_us: int,
        translation: tuple,
        q_xyzw: tuple,
        static: bool = False,
    ) -> bool:
        """One transform: the pose of ``child`` in ``parent``; False, and nothing stored, when it
        is not finite or its quaternion has no length (tf2 refuses such input the same way, so
        the caller counts the sample and the lookups interpolate over it)."""
        sample = np.array([*translation, *q_xyzw], dtype=np.float64)
        if not np.isfinite(sample).all() or not np.linalg.norm(sample[3:]) > 0:
            return False
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if static:
            from evgrid.ros import transform_to_se3

            self._static[child] = (parent, transform_to_se3(translation, q_xyzw))
            return True
        edges = self._dyn.setdefault(child, {})
        if parent not in edges and edges:
            first = next(iter(edges))
            logger.warning(
                "tf: frame %r has a second parent %r besides %r (first at stamp %d us); tf "
                "allows one parent a frame: their samples are kept apart, and a lookup uses the "
                "parent that leads to the frame it asks for",
                child,
                parent,
                first,
                int(t_us),
            )
        if parent != next(iter(edges), parent):
            seconds = self.second_parents.setdefault(child, {})
            seconds[parent] = seconds.get(parent, 0) + 1
        ts, vals = edges.setdefault(parent, ([], []))
        ts.append(int(t_us))
        vals.append((*translation, *q_xyzw))
        self._arrays.pop((child, parent), None)
        return True

    def forget_before(self, t_us: int) -> None:
        """Drop the dynamic samples older than ``t_us`` except the last one before it (a live
        tree stays bounded; lookups at ``t_us`` or later give what they gave before)."""
        for child, edges in self._dyn.items():
            for parent, (ts, vals) in edges.items():
                k = bisect.bisect_left(ts, t_us) - 1 if ts == sorted(ts) else 0
                if k > 0:
                    del ts[:k], vals[:k]
                    self._arrays.pop((child, parent), None)

    def frames(self) -> set[str]:
        """Every frame named as a child or a parent."""
        out = set(self._dyn) | set(self._static)
        out |= {p for edges in self._dyn.values() for p in edges}
        out |= {p for p, _ in self._static.values()}
        return out

    def _edge(self, child: str, parent: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a = self._arrays.get((child, parent))
        if a is None:
            ts, vals = self._dyn[child][parent]
            t = np.asarray(ts, dtype=np.int64)
            v = np.asarray(vals, dtype=np.float64)
            order = np.argsort(t, kind="stable")
            t, v = t[order], v[order]
            a = self._arrays[(child, parent)] = (t, v[:, :3], v[:, 3:])
        return a

    def parent(self, child: str) -> str | None:
        """The parent frame of ``child`` (dynamic edges first, the first parent seen), or None
        for a root."""
        child = child.lstrip("/")
        if child in self._dyn:
            return next(iter(self._dyn[child]))
        if child in self._static:
            return self._static[child][0]
        return None

    def _parents(self, frame: str) -> list[str]:
        out = list(self._dyn.get(frame, ()))
        if frame in self._static and not out:
            out.append(self._static[frame][0])
        return out

    def _parent_toward(self, frame: str, target: str) -> str | None:
        """The parent of ``frame`` to climb through towards ``target``: the first from which
        ``target`` is reached (the first parent when none is)."""
        parents = self._parents(frame)
        if len(parents) > 1:
            for p in parents:
                if self._reaches(p, target):
                    return p
        return parents[0] if parents else None

    def _reaches(self, frame: str, target: str) -> bool:
        todo, seen = [frame], set()
        while todo:
            f = todo.pop()
            if f == target:
                return True
            if f not in seen:
                seen.add(f)
                todo.extend(self._parents(f))
        return False

    def _sample(self, child: str, parent: str, t_us: int) -> SE3 | None:
        from evgrid.ros import transform_to_se3

        ts, trans, quat = self._edge(child, parent)
        i = int(np.searchsorted(ts, t_us))
        if i < len(ts) and ts[i] == t_us:
            return transform_to_se3(trans[i], quat[i])
        if i == 0:
            return transform_to_se3(trans[0], quat[0]) if ts[0] - t_us <= self.max_gap_us else None
        if i == len(ts):
            return (
                transform_to_se3(trans[-1], quat[-1]) if t_us - ts[-1] <= self.max_gap_us else None
            )
        f = (t_us - ts[i - 1]) / (ts[i] - ts[i - 1])
        tr = (1 - f) * trans[i - 1] + f * trans[i]
        return transform_to_se3(tr, _slerp(quat[i - 1], quat[i], f))

    def span(self, target: str, source: str) -> tuple[int, int] | None:
        """Times (us) over which every dynamic transform from ``source`` up to ``target`` has
        samples."""
        lo, hi = -(2**62), 2**62
        target, frame, seen = target.lstrip("/"), source.lstrip("/"), set()
        while frame != target:
            if frame in seen:
                return None
            seen.add(frame)
            parent = self._parent_toward(frame, target)
            if parent is None:
                return None
            if frame in self._dyn:
                ts = self._edge(frame, parent)[0]
                lo, hi = max(lo, int(ts[0])), min(hi, int(ts[-1]))
            frame = parent
        return lo, hi

    def lookup(self, target: str, source: str, t_us: int) -> SE3 | None:
        """Pose of ``source`` in ``target`` at ``t_us`` (None: no chain, or the time is off the
        track)."""
        target, frame = target.lstrip("/"), source.lstrip("/")
        pose: SE3 | None = None
        seen = set()
        while frame != target:
            if frame in seen:
                return None
            seen.add(frame)
            parent = self._parent_toward(frame, target)
            if parent is None:
                return None
            if frame in self._dyn:
                step = self._sample(frame, parent, t_us)
                if step is None:
                    return None
            else:
                step = self._static[frame][1]
            pose = step if pose is None else step @ pose
            frame = parent
        return pose if pose is not None else SE3.identity()


def _slerp(q0: np.ndarray, q1: np.ndarray, f: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (x, y, z, w); yaw-only pairs stay yaw-only."""
    if q0[0] == q0[1] == q1[0] == q1[1] == 0.0:  # planar: interpolate the yaw itself
        y0, y1 = 2 * math.atan2(q0[2], q0[3]), 2 * math.atan2(q1[2], q1[3])
        y = y0 + f * math.remainder(y1 - y0, 2 * math.pi)
        return np.array([0.0, 0.0, math.sin(y / 2), math.cos(y / 2)])
    a = q0 / np.linalg.norm(q0)
    b = q1 / np.linalg.norm(q1)
    d = float(a @ b)
    if d < 0:
        b, d = -b, -d
    if d > 0.9995:
        q = a + f * (b - a)
        return q / np.linalg.norm(q)
    th = math.acos(d)
    return (math.sin((1 - f) * th) * a + math.sin(f * th) * b) / math.sin(th)
