"""The simulator's own file format: one ``.npz`` per scene, readable with numpy alone.

The lidar points are stored uncompressed (noisy float32 hardly compresses: deflate saves a
third at three times the write time); all other arrays are deflated. About 265 MB a 20 s scene.

Arrays in the file (``n`` frames, ``k`` keyframes, ``m_c`` sweeps of radar ``c``):

==============================  ==============================================================
``meta``                        JSON text: format, version, name, seed, environment, config,
                                column names, channel names
``timestamps``                  (n,) int64 lidar timestamps, us
``ego_poses``                   (n, 4, 4) float64 ego -> global at each frame (odometry)
``true_poses``                  (n, 3) float64 true x, y (m), yaw (rad)
``is_keyframe``                 (n,) bool
``lidar_points``                (sum, 5) float32, ``LIDAR_COLUMNS``, frames concatenated
``lidar_offsets``               (n + 1,) int64: frame i is ``lidar_points[off[i]:off[i+1]]``
``lidar_sensor_to_ego``         (4, 4) float64
``occupancy``                   (k, N, N) uint8 true occupancy of the keyframes
``radar_<C>_timestamps``        (m_c,) int64
``radar_<C>_ego_poses``         (m_c, 4, 4) float64
``radar_<C>_points``            (sum, 12) float32, ``RADAR_COLUMNS``
``radar_<C>_offsets``           (m_c + 1,) int64
``radar_<C>_labels``            (sum,) uint8: 0 real, 1 clutter, 2 ghost
``radar_<C>_frame``             (m_c,) int64: the frame each sweep belongs to
``radar_<C>_sensor_to_ego``     (4, 4) float64
``world_boxes``                 (s, 8) float64 static boxes (``raycast.BOX_COLUMNS``)
``world_classes``               (s,) int32 (``materials.CLASS_NAMES`` in meta)
==============================  ==============================================================
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from evgrid.data import frame as contract
from evgrid.data.frame import LIDAR_CHANNEL, RADAR_CHANNELS, Frame, LidarSweep, RadarSweep
from evgrid.geometry import SE3
from evgrid.io import atomic_open
from evgrid_sim.materials import CLASS_NAMES
from evgrid_sim.scene import SimScene

__all__ = ["save_sim_scene", "load_sim_scene", "StoredScene", "SceneFileError", "SIM_NPZ_FORMAT"]

SIM_NPZ_FORMAT = "evgrid-sim-npz"
_VERSION = 1


def _offsets(chunks: list[np.ndarray]) -> np.ndarray:
    """Where each chunk begins in their concatenation, and the total (len(chunks) + 1)."""
    return np.concatenate([[0], np.cumsum([len(c) for c in chunks])]).astype(np.int64)


def _scene_meta(scene: SimScene, channels: tuple[str, ...]) -> dict:
    """The scene file's ``meta`` record: format, version, the scene's name, seed and config,
    channels, columns and class names."""
    return {
        "format": SIM_NPZ_FORMAT,
        "version": _VERSION,
        "name": scene.name,
        "seed": scene.seed,
        "environment": scene.world.environment,
        "config": scene.config.to_dict(),
        "lidar_channel": LIDAR_CHANNEL,
        "radar_channels": list(channels),
        "lidar_columns": list(contract.LIDAR_COLUMNS),
        "radar_columns": list(contract.RADAR_COLUMNS),
        "class_names": list(CLASS_NAMES),
    }


def _radar_arrays(ch: str, r: dict[str, list], sensor_to_ego: np.ndarray) -> dict[str, np.ndarray]:
    """The arrays of radar channel ``ch`` from its sweeps' lists ``r`` (timestamps, ego poses,
    points, labels, frame index)."""
    return {
        f"radar_{ch}_timestamps": np.asarray(r["ts"], dtype=np.int64),
        f"radar_{ch}_ego_poses": np.asarray(r["poses"], dtype=np.float64).reshape(-1, 4, 4),
        f"radar_{ch}_points": (
            np.concatenate(r["pts"]) if r["pts"] else np.zeros((0, 12), np.float32)
        ),
        f"radar_{ch}_offsets": _offsets(r["pts"]),
        f"radar_{ch}_labels": (
            np.concatenate(r["labels"]) if r["labels"] else np.zeros(0, np.uint8)
        ),
        f"radar_{ch}_frame": np.asarray(r["frame"], dtype=np.int64),
        f"radar_{ch}_sensor_to_ego": sensor_to_ego,
    }


def _simulate_frames(
    scene: SimScene, channels: tuple[str, ...], on_frame: Callable[[int], None] | None
) -> tuple:
    """Every frame of ``scene`` simulated and gathered: the lidar points per frame, ego poses,
    keyframe flags, the keyframes' occupancy, the lidar's mounting, per radar channel the
    lists of its sweeps (timestamps, ego poses, points, labels, frame) and its mounting."""
    n = len(scene)
    lidar: list[np.ndarray] = []
    poses = np.empty((n, 4, 4))
    kf = np.zeros(n, dtype=bool)
    occ: list[np.ndarray] = []
    radar: dict[str, dict[str, list]] = {
        c: {"ts": [], "poses": [], "pts": [], "labels": [], "frame": []} for c in channels
    }
    lidar_s2e = None
    radar_s2e: dict[str, np.ndarray] = {}
    for i, f in enumerate(scene):
        lidar.append(f.lidar.points)
        poses[i] = f.ego_pose.matrix()
        lidar_s2e = f.lidar.sensor_to_ego.matrix()
        kf[i] = f.is_keyframe
        if f.is_keyframe:
            occ.append(f.occupancy)
        for ch, sweeps in f.radar.items():
            for s in sweeps:
                r = radar[ch]
                r["ts"].append(s.timestamp)
                r["poses"].append(s.ego_pose.matrix())
                r["pts"].append(s.points)
                r["labels"].append(scene.radar_labels(ch, s.timestamp))
                r["frame"].append(i)
                radar_s2e[ch] = s.sensor_to_ego.matrix()
        if on_frame is not None:
            on_frame(i)

    return lidar, poses, kf, occ, lidar_s2e, radar, radar_s2e


def save_sim_scene(
    scene: SimScene, path: str | os.PathLike, on_frame: Callable[[int], None] | None = None
) -> Path:
    """Simulate every frame of ``scene`` and write it to ``path`` (``.npz``, atomically); returns
    the path."""
    if not isinstance(scene, SimScene):
        raise TypeError(f"save_sim_scene needs a SimScene, got {type(scene).__name__}")
    path = Path(path)
    if path.suffix != ".npz":
        raise ValueError(f"the simulator's scene files end in .npz, got {str(path)!r}")
    channels = tuple(scene.radar_channels)
    lidar, poses, kf, occ, lidar_s2e, radar, radar_s2e = _simulate_frames(scene, channels, on_frame)
    meta = _scene_meta(scene, channels)
    g = scene.config.grid
    arrays: dict[str, np.ndarray] = {
        "meta": np.array(json.dumps(meta)),
        "timestamps": np.asarray(scene.lidar_timestamps, dtype=np.int64),
        "ego_poses": poses,
        "true_poses": scene.true_poses(),
        "is_keyframe": kf,
        "lidar_points": np.concatenate(lidar) if lidar else np.zeros((0, 5), np.float32),
        "lidar_offsets": _offsets(lidar),
        "lidar_sensor_to_ego": lidar_s2e if lidar_s2e is not None else np.eye(4),
        "occupancy": np.stack(occ) if occ else np.zeros((0, g.n_cells, g.n_cells), np.uint8),
        "world_boxes": scene.world.boxes,
        "world_classes": scene.world.classes,
    }
    for ch, r in radar.items():
        arrays.update(_radar_arrays(ch, r, radar_s2e.get(ch, np.eye(4))))
    with atomic_open(path, "wb") as fobj:
        _write_npz(fobj, arrays, stored={"lidar_points"})
    return path


def _write_npz(fobj, arrays: dict[str, np.ndarray], stored: set[str]) -> None:
    """An ``.npz`` (zip of ``.npy``) that ``np.load`` reads, deflating every array but those in
    ``stored``: noisy float32 lidar coordinates barely compress and would triple the write time."""
    with zipfile.ZipFile(fobj, "w", allowZip64=True) as zf:
        for name, arr in arrays.items():
            method = zipfile.ZIP_STORED if name in stored else zipfile.ZIP_DEFLATED
            info = zipfile.ZipInfo(
                name + ".npy", date_time=(1980, 1, 1, 0, 0, 0)
            )  # fixed: same seed, same bytes
            info.compress_type = method
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(arr), allow_pickle=False)


class StoredScene:
    """A scene read back from a ``.npz`` written by :func:`save_sim_scene` (a ``Scene``)."""

    def __init__(self, path: Path, data: dict[str, np.ndarray], meta: dict) -> None:
        self.path = path
        self.meta = meta
        self.name: str = meta["name"]
        self.seed: int = int(meta["seed"])
        self._d = data
        self._kf_index = {int(i): k for k, i in enumerate(np.nonzero(data["is_keyframe"])[0])}
        self._radar_by_frame: dict[str, list[list[int]]] = {}
        n = len(self)
        #: The rig's radar channels.
        self.radar_channels: tuple[str, ...] = tuple(meta.get("radar_channels", RADAR_CHANNELS))
        for ch in self.radar_channels:
            per: list[list[int]] = [[] for _ in range(n)]
            for j, fi in enumerate(data[f"radar_{ch}_frame"]):
                per[int(fi)].append(j)
            self._radar_by_frame[ch] = per

    def __len__(self) -> int:
        return int(self._d["timestamps"].shape[0])

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.frame(i)

    def __repr__(self) -> str:
        return f"StoredScene({self.name!r}, {len(self)} frames, from {str(self.path)!r})"

    @property
    def true_poses(self) -> np.ndarray:
        """True ego poses (x, y, yaw) of every frame, ``(n, 3)``."""
        return self._d["true_poses"]

    @property
    def world_boxes(self) -> np.ndarray:
        """Static boxes of the world (global frame), ``(s, 8)``."""
        return self._d["world_boxes"]

    @property
    def world_classes(self) -> np.ndarray:
        """Class id of each static box."""
        return self._d["world_classes"]

    def _radar(self, ch: str, j: int) -> RadarSweep:
        d = self._d
        off = d[f"radar_{ch}_offsets"]
        return RadarSweep(
            d[f"radar_{ch}_points"][off[j] : off[j + 1]],
            SE3.from_matrix(d[f"radar_{ch}_sensor_to_ego"]),
            SE3.from_matrix(d[f"radar_{ch}_ego_poses"][j]),
            int(d[f"radar_{ch}_timestamps"][j]),
            ch,
        )

    def radar_labels(self, channel: str, timestamp_us: int) -> np.ndarray:
        """Ground-truth labels (0 real, 1 clutter, 2 ghost) of the radar sweep at a timestamp."""
        if channel not in self.radar_channels:
            raise ValueError(
                f"unknown radar channel {channel!r}; channels are {self.radar_channels}"
            )
        d = self._d
        hits = np.nonzero(d[f"radar_{channel}_timestamps"] == int(timestamp_us))[0]
        if len(hits) == 0:
            raise KeyError(f"no {channel} sweep at timestamp {timestamp_us}")
        j = int(hits[0])
        off = d[f"radar_{channel}_offsets"]
        return d[f"radar_{channel}_labels"][off[j] : off[j + 1]]

    def frame(self, i: int) -> Frame:
        """Frame ``i``."""
        n = len(self)
        if not 0 <= i < n:
            raise IndexError(f"frame index {i} out of range for a scene of {n} frames")
        d = self._d
        off = d["lidar_offsets"]
        pose = SE3.from_matrix(d["ego_poses"][i])
        lidar = LidarSweep(
            d["lidar_points"][off[i] : off[i + 1]],
            SE3.from_matrix(d["lidar_sensor_to_ego"]),
            pose,
            int(d["timestamps"][i]),
            LIDAR_CHANNEL,
        )
        radar = {
            ch: tuple(self._radar(ch, j) for j in self._radar_by_frame[ch][i])
            for ch in self.radar_channels
        }
        kf = bool(d["is_keyframe"][i])
        return Frame(
            scene=self.name,
            index=i,
            timestamp=int(d["timestamps"][i]),
            ego_pose=pose,
            is_keyframe=kf,
            lidar=lidar,
            radar=radar,
            occupancy=d["occupancy"][self._kf_index[i]] if kf else None,
        )


class SceneFileError(ValueError):
    """A simulated scene file that cannot be used (empty, truncated, corrupt, foreign or
    inconsistent)."""


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of an ``.npz``; SceneFileError naming the file (and the array) for anything
    unreadable."""
    if path.stat().st_size == 0:
        raise SceneFileError(
            f"{path}: the scene file is empty (0 bytes); simulate it again with `evgrid simulate`"
        )
    try:
        z = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as e:
        raise SceneFileError(
            f"{path}: not a readable .npz scene file, truncated or corrupt ({e})"
        ) from e
    if not isinstance(z, np.lib.npyio.NpzFile):
        z_shape = getattr(z, "shape", None)
        raise SceneFileError(f"{path}: a single .npy array {z_shape}, not an .npz scene file")
    data: dict[str, np.ndarray] = {}
    with z:
        for k in z.files:
            try:
                data[k] = z[k]
            except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError) as e:
                raise SceneFileError(f"{path}: array {k!r} is truncated or corrupt ({e})") from e
    return data


def _require(
    path: Path, d: dict[str, np.ndarray], name: str, shape: tuple, kind: str
) -> np.ndarray:
    """Array ``name`` with ``shape`` (None for any length) of numpy kind ``kind``; SceneFileError
    otherwise."""
    a = d.get(name)
    if a is None:
        raise SceneFileError(
            f"{path}: array {name!r} is missing; the file is not a complete evgrid scene"
        )
    if (
        a.ndim != len(shape)
        or any(want is not None and got != want for got, want in zip(a.shape, shape))
        or a.dtype.kind not in kind
    ):
        want = "(" + ", ".join("n" if w is None else str(w) for w in shape) + ")"
        raise SceneFileError(
            f"{path}: array {name!r} has shape {a.shape} dtype {a.dtype}, expected {want} of kind "
            f"{kind!r}"
        )
    return a


def _check_offsets(path: Path, name: str, off: np.ndarray, n_items: int, total: int) -> None:
    if (
        len(off) != n_items + 1
        or (len(off) and (off[0] != 0 or off[-1] != total))
        or (np.diff(off) < 0).any()
    ):
        raise SceneFileError(
            f"{path}: array {name!r} does not index its {total} points in {n_items} pieces; the "
            "file is corrupt"
        )


def _check_scene_arrays(path: Path, d: dict[str, np.ndarray]) -> None:
    """Every array StoredScene reads, with consistent shapes, so that a broken file fails here,
    named."""
    n = len(_require(path, d, "timestamps", (None,), "i"))
    _require(path, d, "ego_poses", (n, 4, 4), "f")
    _require(path, d, "true_poses", (n, 3), "f")
    kf = _require(path, d, "is_keyframe", (n,), "b")
    pts = _require(path, d, "lidar_points", (None, len(contract.LIDAR_COLUMNS)), "f")
    _check_offsets(
        path, "lidar_offsets", _require(path, d, "lidar_offsets", (None,), "i"), n, len(pts)
    )
    _require(path, d, "lidar_sensor_to_ego", (4, 4), "f")
    occ = _require(path, d, "occupancy", (None, None, None), "u")
    if len(occ) != int(kf.sum()):
        raise SceneFileError(
            f"{path}: array 'occupancy' holds {len(occ)} keyframes, 'is_keyframe' marks "
            f"{int(kf.sum())}"
        )
    for ch in RADAR_CHANNELS:
        m = len(_require(path, d, f"radar_{ch}_timestamps", (None,), "i"))
        _require(path, d, f"radar_{ch}_ego_poses", (m, 4, 4), "f")
        rp = _require(path, d, f"radar_{ch}_points", (None, len(contract.RADAR_COLUMNS)), "f")
        _check_offsets(
            path,
            f"radar_{ch}_offsets",
            _require(path, d, f"radar_{ch}_offsets", (None,), "i"),
            m,
            len(rp),
        )
        _require(path, d, f"radar_{ch}_labels", (len(rp),), "u")
        fr = _require(path, d, f"radar_{ch}_frame", (m,), "i")
        if m and (fr.min() < 0 or fr.max() >= n):
            raise SceneFileError(f"{path}: array 'radar_{ch}_frame' names frames outside [0, {n})")
        _require(path, d, f"radar_{ch}_sensor_to_ego", (4, 4), "f")
    _require(path, d, "world_boxes", (None, None), "f")
    _require(path, d, "world_classes", (None,), "i")


def load_sim_scene(path: str | os.PathLike) -> StoredScene:
    """Read a scene written by :func:`save_sim_scene` (or ``evgrid simulate``) into memory.

    Raises :class:`SceneFileError` (a ValueError) naming the file and what is wrong with it.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"no simulated scene file at {str(path)!r} (write one with `evgrid simulate --out DIR`)"
        )
    data = _read_arrays(path)
    if "meta" not in data:
        raise SceneFileError(f"{path}: not an evgrid simulated scene (no 'meta' array)")
    try:
        meta = json.loads(str(data["meta"]))
    except ValueError as e:
        raise SceneFileError(f"{path}: array 'meta' is not JSON ({e})") from e
    if not isinstance(meta, dict):
        raise SceneFileError(f"{path}: array 'meta' must hold a JSON object")
    if meta.get("format") != SIM_NPZ_FORMAT:
        raise SceneFileError(f"{path}: format {meta.get('format')!r}, expected {SIM_NPZ_FORMAT!r}")
    if meta.get("version") != _VERSION:
        raise SceneFileError(
            f"{path}: version {meta.get('version')!r} of the format; this evgrid reads version "
            f"{_VERSION}"
        )
    if (
        not isinstance(meta.get("name"), str)
        or isinstance(meta.get("seed"), bool)
        or not isinstance(meta.get("seed"), int)
    ):
        raise SceneFileError(
            f"{path}: meta fields 'name' (text) and 'seed' (integer) are missing or invalid"
        )
    _check_scene_arrays(path, data)
    return StoredScene(path, data, meta)
