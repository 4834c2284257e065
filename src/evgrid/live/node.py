"""``evgrid live``: map what a robot publishes, and publish the maps as map_server does.

Two threads. The receiver takes raw payloads from the rig's topics, decodes them with the
recording reader's type store (one decoder per message type, shared) and feeds them to
:class:`~evgrid.live.source.LiveFrames`, which makes the same frames a recording of them would
give. The mapper thread takes the newest complete frame, merging the frames it had no time for
into it (their radar sweeps are kept, their lidar sweeps dropped and counted as ``behind``), maps
it with :class:`~evgrid.mapper.OccupancyMapper` and publishes ``/map`` (the navigation map in
nav2's classes, on the nav2 export's grid) at the map rate.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.data.bag.rig import RecordingRig
from evgrid.data.frame import Frame
from evgrid.live.dds import MAP_QOS, SENSOR_QOS, TF_QOS, TF_STATIC_QOS, Graph, QosProfile
from evgrid.live.source import LiveFrames, sweep_topics

__all__ = ["LiveOptions", "LiveNode", "merge_frames", "map_cells_for"]

log = logging.getLogger(__name__)

#: The topic of the navigation map, as map_server and slam_toolbox name it.
MAP_TOPIC = "/map"
#: The ego pose (as the MCAP export names it).
POSE_TOPIC = "/evgrid/ego_pose"


@dataclass(frozen=True)
class LiveOptions:
    """What ``evgrid live`` publishes and how it reports (each field is an option).

    ``map_max_cells``: ``/map`` holds the whole observed map up to this many cells; beyond, a
    square window of ``map_window_m`` around the vehicle. ``publish``: maps also published as
    ``/evgrid/NAME/occupancy``; ``grid_map``: their mass layers as ``/evgrid/NAME/grid_map``.
    """

    map_rate_hz: float = 1.0
    map_max_cells: int = 4096 * 4096
    map_window_m: float = 200.0
    publish: tuple[str, ...] = ()
    grid_map: bool = False
    save_every_s: float = 0.0
    save_maps: bool = False
    status_every_s: float = 10.0
    silence_s: float = 2.0
    sync_wait_s: float = 0.05
    pose_wait_s: float = 1.0

    def __post_init__(self) -> None:
        from evgrid.validation import check_number

        check_number(self, "map_rate_hz", min=0.0, min_open=True)
        check_number(self, "map_window_m", min=0.0, min_open=True)
        check_number(self, "save_every_s", min=0.0)
        check_number(self, "status_every_s", min=0.0, min_open=True)
        check_number(self, "silence_s", min=0.0, min_open=True)
        if not isinstance(self.map_max_cells, int) or self.map_max_cells < 1:
            raise ValueError(
                f"map_max_cells must be a positive integer, got {self.map_max_cells!r}"
            )


def merge_frames(frames: list[Frame]) -> Frame:
    """The newest of ``frames`` carrying the radar sweeps of the older ones (oldest first) and
    their lidar sweeps as skipped (:attr:`Frame.lidar_skipped`): what a mapper that fell behind
    maps instead of them."""
    newest = frames[-1]
    if len(frames) == 1:
        return newest
    radar = {ch: tuple(s for f in frames for s in f.radar.get(ch, ())) for ch in newest.radar}
    skipped = sum(f.lidar_skipped + 1 for f in frames[:-1]) + newest.lidar_skipped
    keyframe = any(f.is_keyframe for f in frames)
    return replace(newest, radar=radar, lidar_skipped=skipped, is_keyframe=keyframe)


def map_cells_for(m: Any, x: float, y: float, max_cells: int, window_m: float) -> tuple | None:
    """The box ``(r0, c0, h, w)`` of ``m`` to publish: its observed area when it has at most
    ``max_cells`` cells, else a square of ``window_m`` around ``(x, y)`` (map frame) inside it;
    None when nothing is observed."""
    r0, c0, h, w = m.covered_bounds()
    if h == 0:
        return None
    if h * w <= max_cells:
        return r0, c0, h, w
    n = min(int(math.ceil(window_m / m.grid.resolution)), int(math.isqrt(max_cells)))
    rc, cc = (int(v) for v in m.grid.map_xy_to_cell(x, y))
    rr = min(max(rc - n // 2, r0), r0 + h - min(n, h))
    cc0 = min(max(cc - n // 2, c0), c0 + w - min(n, w))
    return rr, cc0, min(n, h), min(n, w)


def warm_up(config: Any, deep: Any, rig: RecordingRig) -> None:
    """Run the update of ``config``'s maps twice on a made-up frame with a throwaway mapper (the
    same deep IRM): the kernels' first calls compile and allocate, which would otherwise make
    the first real frames wait."""
    from evgrid.data.frame import LIDAR_COLUMNS, RADAR_COLUMNS, LidarSweep, RadarSweep
    from evgrid.geometry import SE3
    from evgrid.mapper import OccupancyMapper

    mapper = OccupancyMapper(config, deep)
    rng = np.random.default_rng(0)
    for k in range(2):
        t = 1_000_000 + 100_000 * k
        pts = np.zeros((256, len(LIDAR_COLUMNS)), dtype=np.float32)
        pts[:, :2] = rng.uniform(-20, 20, (256, 2))
        det = np.zeros((16, len(RADAR_COLUMNS)), dtype=np.float32)
        det[:, :2] = rng.uniform(-20, 20, (16, 2))
        for col, v in (("dyn_prop", 1.0), ("ambig_state", 3.0), ("pdh0", 1.0)):
            det[:, RADAR_COLUMNS.index(col)] = v
        ego = SE3.identity()
        radar = {r.channel: (RadarSweep(det, ego, ego, t, r.channel),) for r in rig.radars}
        mapper.process(Frame("warm-up", k, t, ego, True, LidarSweep(pts, ego, ego, t), radar))


class ClassRaster:
    """The nav2 classes of one map, kept up to date cell by cell: each update reclassifies only
    the cells it could change (:attr:`MapUpdate.box`), so publishing the whole map costs a copy,
    not a classification of every cell. Equal to :func:`~evgrid.export.nav2.classify` of the
    whole map (cells it never saw are unknown)."""

    def __init__(self, name: str, thresholds: Any, margin: int = 512):
        from evgrid.export.nav2 import UNKNOWN

        self.name, self.thresholds, self.margin = name, thresholds, margin
        self.r0 = self.c0 = 0
        self.classes = np.full((0, 0), UNKNOWN, dtype=np.int8)

    def _grow(self, r0: int, c0: int, h: int, w: int) -> None:
        from evgrid.export.nav2 import UNKNOWN

        a, (R0, C0), (H, W) = self.classes, (self.r0, self.c0), self.classes.shape
        if H and R0 <= r0 and C0 <= c0 and r0 + h <= R0 + H and c0 + w <= C0 + W:
            return
        g = self.margin  # grown with room, so a drive reallocates rarely
        nr0 = min(r0, R0) - g if H else r0 - g
        nc0 = min(c0, C0) - g if H else c0 - g
        nr1 = max(r0 + h, R0 + H) + g if H else r0 + h + g
        nc1 = max(c0 + w, C0 + W) + g if H else c0 + w + g
        out = np.full((nr1 - nr0, nc1 - nc0), UNKNOWN, dtype=np.int8)
        out[R0 - nr0 : R0 - nr0 + H, C0 - nc0 : C0 - nc0 + W] = a
        self.classes, self.r0, self.c0 = out, nr0, nc0

    def on_update(self, update: Any) -> None:
        from evgrid.export.nav2 import classify

        r0, c0, h, w = update.box
        self._grow(r0, c0, h, w)
        masses, cov = update.maps.maps[self.name].read(r0, c0, h, w)
        rr, cc = r0 - self.r0, c0 - self.c0
        self.classes[rr : rr + h, cc : cc + w] = classify(masses, cov, self.thresholds)

    def read(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        """The classes of the cells ``[r0:r0+h, c0:c0+w]`` (a box inside what was updated)."""
        rr, cc = r0 - self.r0, c0 - self.c0
        return self.classes[rr : rr + h, cc : cc + w]


class _Stats:
    """Counts and latencies between two status lines, and over the whole run."""

    def __init__(self) -> None:
        self.behind = 0  # frames merged into a newer one (the mapper had no time for them)
        self.published = 0
        self.latency_ms: deque[float] = deque(maxlen=10_000)  # stamp -> /map publication
        self.update_latency_ms: deque[float] = deque(maxlen=10_000)  # stamp -> map updated
        self.arrival_latency_ms: deque[float] = deque(maxlen=10_000)  # arrival -> /map
        # the run's report: the last 100,000 (about three hours of updates at 10 Hz)
        self.all_latency_ms: deque[float] = deque(maxlen=100_000)
        self.all_update_latency_ms: deque[float] = deque(maxlen=100_000)
        self.last_updates = 0
        self.last_t = time.monotonic()


def _rss_mb() -> float:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError):
        return float("nan")


def _pct(v: Any, q: float) -> float:
    return float(np.percentile(np.asarray(v), q)) if len(v) else float("nan")


class LiveNode:
    """A live mapper on a DDS graph (see the module's docstring).

    ``mapper_config`` and ``outputs`` are a run's (:class:`evgrid.config.RunConfig`); the maps
    are saved into ``out`` (``nav2/map.pgm`` + ``map.yaml`` as ``evgrid map --export nav2``
    names them; ``maps/NAME.npz`` with ``options.save_maps``) by :meth:`save`, on a stop and
    every ``options.save_every_s``. ``say`` prints the lines meant for the user (``ready``, the
    status lines).
    """

    def __init__(
        self,
        rig: RecordingRig,
        mapper_config: Any,
        outputs: Any,
        out: str | os.PathLike | None,
        options: LiveOptions = LiveOptions(),
        domain: int | None = None,
        say: Callable[[str], None] = print,
    ):
        self.rig, self.options, self.say = rig, options, say
        self.outputs = outputs
        self.out = Path(out) if out is not None else None
        if mapper_config.frame != "world":
            raise ValueError(
                f"evgrid live maps in the rig's world frame ({rig.world_frame}); "
                f"mapper.frame {mapper_config.frame!r} is for figures of recordings"
            )
        self.config = mapper_config
        self.frames = LiveFrames(rig, options.sync_wait_s, options.pose_wait_s)
        self.stats = _Stats()
        self.problems: list[str] = []
        self._graph: Graph | None = None
        self._domain = domain
        self._lock = threading.Lock()
        self._ready: deque[tuple[Frame, float]] = deque()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._last_seen: dict[str, float] = {}
        self._silent: set[str] = set()
        self._last_pub = -math.inf
        self._last_save = time.monotonic()
        self.mapper: Any = None
        self.nav: Any = None
        self._started: float | None = None  # when start() finished
        self._receiver: threading.Thread | None = None
        self._unpublished: Frame | None = None  # mapped since the last /map, and its arrival
        self._unpublished_arrival = 0.0

    # -- setup ---------------------------------------------------------------------------------

    def start(self) -> None:
        """Load the models, join the graph, subscribe and advertise; then say ``ready``."""
        from evgrid.export.nav2 import Nav2Exporter
        from evgrid.mapper import OccupancyMapper
        from evgrid.runs import _maps_the_rig_can_make

        self.config = _maps_the_rig_can_make(self.config, self.frames, self.frames.name, ("nav2",))
        self.mapper = OccupancyMapper(self.config)
        warm_up(self.config, self.mapper.deep, self.rig)
        names = self.mapper.maps.maps
        missing = [n for n in self.options.publish if n not in names]
        if missing:
            raise ValueError(f"--publish: no map {missing} in this run; it has {sorted(names)}")
        if self.out is not None:
            params = replace(
                self.outputs.nav2, map_frame=self.rig.world_frame, fixed_frame=self.rig.world_frame
            )
            self.nav = Nav2Exporter(self.out / "nav2", params, overwrite=True)
            self.mapper.observers.append(self.nav)
        self._map_name = next(
            (n for n in self.outputs.nav2.navigation if n in names), next(iter(names))
        )
        th = self.outputs.nav2.thresholds
        self.rasters = {n: ClassRaster(n, th) for n in (self._map_name, *self.options.publish)}
        self.mapper.observers += list(self.rasters.values())
        self._graph = Graph(self._domain, on_problem=self.problems.append)
        qos: Mapping[str, QosProfile] = {
            self.rig.tf_topic: TF_QOS,
            self.rig.tf_static_topic: TF_STATIC_QOS,
        }
        self.readers = [
            self._graph.reader(topic, typ, qos.get(topic, SENSOR_QOS))
            for topic, typ in sweep_topics(self.rig).items()
        ]
        self._advertise(self._graph)
        self._started = time.monotonic()
        self._receiver = threading.Thread(target=self._receive, name="evgrid-live-rx", daemon=True)
        self._receiver.start()
        self.say(
            f"evgrid live: ready on ROS_DOMAIN_ID {self._graph.domain}: mapping "
            f"{', '.join(names)} from {', '.join(sweep_topics(self.rig))}; publishing {MAP_TOPIC} "
            f"({self._map_name}) at {self.options.map_rate_hz:g} Hz"
        )

    def _advertise(self, graph: Graph) -> None:
        """The writers of the navigation map, the pose, each --publish map and (with
        --grid-map) each map's GridMap."""
        self._map_writer = graph.writer(MAP_TOPIC, "nav_msgs/msg/OccupancyGrid", MAP_QOS)
        self._pose_writer = graph.writer(
            POSE_TOPIC, "geometry_msgs/msg/PoseStamped", QosProfile(True, False, 10)
        )
        self._map_writers = {
            n: graph.writer(f"/evgrid/{n}/occupancy", "nav_msgs/msg/OccupancyGrid", MAP_QOS)
            for n in self.options.publish
        }
        self._grid_writers = (
            {
                n: graph.writer(f"/evgrid/{n}/grid_map", "grid_map_msgs/msg/GridMap", MAP_QOS)
                for n in (self._map_name, *self.options.publish)
            }
            if self.options.grid_map
            else {}
        )

    # -- receiving -----------------------------------------------------------------------------

    def _receive(self) -> None:
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
        from cyclonedds.util import duration

        from evgrid.ros import typestore

        store = typestore(2)  # the recordings' decoders: one per message type, shared
        ws = WaitSet(self._graph.participant)
        mask = SampleState.Any | ViewState.Any | InstanceState.Any
        conds = [ReadCondition(r._reader, mask) for r in self.readers]
        for c in conds:
            ws.attach(c)
        while not self._stop.is_set():
            ws.wait(duration(milliseconds=10))
            now = time.monotonic()
            got = []
            for r in self.readers:
                for payload, _ in r.take():
                    try:
                        got.append((r.topic, store.deserialize_cdr(payload, r.msgtype)))
                    except Exception as e:  # noqa: BLE001 - any damage is one malformed message
                        with self._lock:
                            self.frames.malformed(r.topic, f"{type(e).__name__}: {e}")
                    self._last_seen[r.topic] = now
            with self._lock:
                for topic, msg in got:
                    try:
                        self.frames.feed(topic, msg, now)
                    except Exception as e:  # noqa: BLE001 - one bad message, not the node
                        self.frames.malformed(topic, f"{type(e).__name__}: {e}")
                for f in self.frames.poll(time.monotonic()):
                    self._ready.append((f, now))
            if self._ready:
                self._wake.set()
        for c in conds:
            with contextlib.suppress(Exception):
                ws.detach(c)

    # -- mapping and publishing ----------------------------------------------------------------

    def step(self, timeout: float = 0.1) -> bool:
        """Map the newest complete frame (the older ones merged into it); publish when due.
        Returns whether a frame was mapped."""
        self._wake.wait(timeout)
        with self._lock:
            batch = list(self._ready)
            self._ready.clear()
            self._wake.clear()
        mapped = False
        if batch:
            self.stats.behind += len(batch) - 1
            frame = merge_frames([f for f, _ in batch])
            arrival = batch[-1][1]
            if self.mapper.process(frame):
                mapped = True
                self._record_update(frame)
                self._unpublished, self._unpublished_arrival = frame, arrival
        # due: at the map rate, the newest update (also when no frame came since: the last map
        # of a stream that stopped is published too)
        now = time.monotonic()
        if self._unpublished is not None and now - self._last_pub >= 1 / self.options.map_rate_hz:
            self.publish(self._unpublished)
            self._last_pub = now
            self._record_publication(self._unpublished, self._unpublished_arrival)
            self._unpublished = None
        self._housekeeping()
        return mapped

    def _record_update(self, frame: Frame) -> None:
        ms = time.time() * 1e3 - frame.timestamp / 1e3
        self.stats.update_latency_ms.append(ms)
        self.stats.all_update_latency_ms.append(ms)

    def _record_publication(self, frame: Frame, arrival: float) -> None:
        ms = time.time() * 1e3 - frame.timestamp / 1e3
        self.stats.latency_ms.append(ms)
        self.stats.all_latency_ms.append(ms)
        self.stats.arrival_latency_ms.append((time.monotonic() - arrival) * 1e3)
        self.stats.published += 1

    def map_message(self, name: str, t_us: int, x: float, y: float) -> tuple[Any, Any]:
        """The box published of map ``name`` and its OccupancyGrid (None, None when nothing is
        observed yet)."""
        from evgrid.export.mcap import occupancy_grid_of
        from evgrid.ros import typestore

        m = self.mapper.maps.maps[name]
        box = map_cells_for(m, x, y, self.options.map_max_cells, self.options.map_window_m)
        if box is None:
            return None, None
        cls = self.rasters[name].read(*box)
        frame = self.rig.world_frame
        return box, occupancy_grid_of(cls, box[0], box[1], m.grid.resolution, t_us, frame,
                                      typestore(2))  # fmt: skip

    def publish(self, frame: Frame) -> None:
        """``/map``, the maps of ``--publish`` (and their GridMaps) and the ego pose, now."""
        from evgrid.export.mcap import MapCells, _pose_msg, grid_map_msg
        from evgrid.ros import header, typestore, us_to_stamp

        store = typestore(2)
        t_us = int(frame.timestamp)
        pose = frame.ego_pose.to_se2()
        for name, writer in ((self._map_name, self._map_writer), *self._map_writers.items()):
            box, msg = self.map_message(name, t_us, pose.x, pose.y)
            if msg is None:
                continue
            writer.write(store.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid"))
            if name in self._grid_writers:
                cells = MapCells.read(self.mapper.maps.maps[name], box, dynamic=True)
                gm = grid_map_msg(cells, t_us, self.rig.world_frame, store)
                self._grid_writers[name].write(store.serialize_cdr(gm, "grid_map_msgs/msg/GridMap"))
        sec, ns = us_to_stamp(t_us)
        ego = store.types["geometry_msgs/msg/PoseStamped"](
            header=header(sec, ns, self.rig.world_frame, store),
            pose=_pose_msg(store, pose.x, pose.y, pose.yaw),
        )
        self._pose_writer.write(store.serialize_cdr(ego, "geometry_msgs/msg/PoseStamped"))

    # -- reporting ------------------------------------------------------------------------------

    def drops(self) -> dict[str, int]:
        """Frames and sweeps dropped or skipped so far, by reason (zeros left out)."""
        with self._lock:
            out = {k: v for k, v in self.frames.counts.items() if v}
        if self.stats.behind:
            out["frames_behind"] = self.stats.behind
        return out

    def status_line(self) -> str:
        s, now = self.stats, time.monotonic()
        n = self.mapper.n_updates
        rate = (n - s.last_updates) / max(now - s.last_t, 1e-9)
        s.last_updates, s.last_t = n, now
        drops = self.drops()
        line = (
            f"evgrid live: {rate:.1f} updates/s ({n} in all), {self.frames._n_lidar} lidar sweeps, "
            f"dropped {sum(drops.values())}"
            + (f" ({', '.join(f'{k} {v}' for k, v in sorted(drops.items()))})" if drops else "")
            + f"; latency stamp -> {MAP_TOPIC} median {_pct(s.latency_ms, 50):.0f} ms, p95 "
            f"{_pct(s.latency_ms, 95):.0f} ms (stamp -> map updated median "
            f"{_pct(s.update_latency_ms, 50):.0f} ms); memory {_rss_mb():.0f} MB"
        )
        s.latency_ms.clear()
        s.update_latency_ms.clear()
        return line

    def _housekeeping(self) -> None:
        now = time.monotonic()
        o = self.options
        for topic in sweep_topics(self.rig):
            if topic == self.rig.tf_static_topic:
                continue  # latched: one message, then silence is normal
            last = self._last_seen.get(topic, self._started)
            if now - last > o.silence_s and topic not in self._silent:
                self._silent.add(topic)
                what = "no message yet" if topic not in self._last_seen else "silent"
                log.warning(
                    "%s: %s for %.1f s (its publisher stopped, or its QoS does not match)",
                    topic,
                    what,
                    now - last,
                )
            elif now - last <= o.silence_s and topic in self._silent:
                self._silent.discard(topic)
                log.info("%s: messages again", topic)
        if now - self.stats.last_t >= o.status_every_s:
            self.say(self.status_line())
        if o.save_every_s and now - self._last_save >= o.save_every_s:
            self.save()
            self._last_save = now

    # -- saving and stopping --------------------------------------------------------------------

    def save(self) -> list[Path]:
        """Write the maps into ``out`` now (nothing before the first update)."""
        if self.out is None or self.mapper is None or not self.mapper.n_updates:
            return []
        written = list(self.nav.close()) if self.nav is not None else []
        if self.options.save_maps:
            from evgrid.grid import MapFrame, save_map

            frame = MapFrame.of(self.mapper, self.rig.world_frame)
            for name, m in self.mapper.maps.maps.items():
                written.append(save_map(m, self.out / "maps" / f"{name}.npz", frame))
        return written

    def run(self, duration_s: float | None = None) -> dict[str, Any]:
        """Map until stopped (:meth:`stop`, SIGINT, SIGTERM) or ``duration_s``; then save and
        return the run's report."""
        end = math.inf if duration_s is None else time.monotonic() + duration_s
        while not self._stop.is_set() and time.monotonic() < end:
            self.step()
        return self.close()

    def stop(self, *_: Any) -> None:
        self._stop.set()
        self._wake.set()

    def close(self) -> dict[str, Any]:
        """Stop receiving, map what is complete, save, leave the graph; the run's report."""
        self._stop.set()
        written: list[Path] = []
        if self._receiver is not None:
            self._receiver.join(timeout=2.0)
        if self._started is not None:  # a node that never started has nothing to map or save
            with self._lock:  # the frames complete when the node stopped
                for f in self.frames.poll(time.monotonic()):
                    self._ready.append((f, time.monotonic()))
            self._wake.set()
            self.step(0.0)
            written = self.save()
        if self._graph is not None:
            self._graph.close()
            self._graph = None
        s = self.stats
        return {
            "updates": self.mapper.n_updates if self.mapper else 0,
            "frames": self.mapper.n_frames if self.mapper else 0,
            "lidar_sweeps": self.frames._n_lidar,
            "dropped": self.drops(),
            "published": s.published,
            "latency_ms": {
                k: _pct(s.all_latency_ms, q) for k, q in (("median", 50), ("p95", 95), ("max", 100))
            },
            "update_latency_ms": {
                k: _pct(s.all_update_latency_ms, q)
                for k, q in (("median", 50), ("p95", 95), ("max", 100))
            },
            "problems": list(self.problems),
            "files": [str(p) for p in written],
        }


def run_live(node: LiveNode, duration_s: float | None = None) -> dict[str, Any]:
    """Start ``node`` and run it until Ctrl-C, SIGTERM or ``duration_s``; the maps are saved
    either way."""
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in old:
        signal.signal(s, node.stop)
    try:
        try:
            node.start()
        except BaseException:
            node.close()  # leaves the graph
            raise
        return node.run(duration_s)
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def report_line(r: Mapping[str, Any]) -> str:
    """What ``evgrid live`` prints when it stops: updates, drops, publications, latency, files."""
    lat = r["latency_ms"]
    return (
        f"evgrid live: stopped after {r['updates']} updates of {r['lidar_sweeps']} lidar sweeps; "
        f"dropped {sum(r['dropped'].values())} {r['dropped'] or ''}; {r['published']} /map "
        f"publications, latency median {lat['median']:.0f} ms, p95 {lat['p95']:.0f} ms"
        + "".join(f"\nwrote {f}" for f in r["files"])
    )
