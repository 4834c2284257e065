"""The nuScenes on-disk layout: point-cloud files and a v1.0 table writer (no devkit needed).

* Lidar ``.pcd.bin``: float32 records ``x, y, z, intensity, ring`` (what the devkit's
  ``LidarPointCloud.from_file`` reads; it keeps the first four columns).
* Radar ``.pcd``: a PCD v0.7 header and 18 packed little-endian binary fields per point,
  as the devkit's ``RadarPointCloud.from_file`` parses them. An empty sweep is written as one
  point whose x, y, z are NaN (the devkit's convention for an empty cloud). One newline byte
  follows the binary data: the devkit's parser requires bytes after the last field.
* :func:`write_nuscenes` writes scenes (any iterables of :class:`~evgrid.data.frame.Frame`)
  as ``DATAROOT/<version>/*.json`` tables plus ``samples/``, ``sweeps/`` and a placeholder
  map mask, loadable with ``NuScenes(version=..., dataroot=...)``. Keyframes become samples;
  each sample's key radar sweep is the one closest in time; non-key sample_data point to the
  next sample in time (the last sample after the last keyframe). Annotation tables are empty.
  Any set of radar channels is written (the ``sensor`` table lists those the scenes carry), and
  sweeps are chained in the order the scene delivered them, so a recording's repeated or late
  sweeps stay in the data for the loader to report.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from evgrid.data.frame import LIDAR_CHANNEL, RADAR_COLUMNS, Frame, Scene
from evgrid.data.sweeps import channel_order
from evgrid.io import atomic_open, atomic_write_bytes, write_json

logger = logging.getLogger(__name__)

__all__ = [
    "RADAR_PCD_FIELDS",
    "RADAR_PCD_DTYPE",
    "write_lidar_bin",
    "read_lidar_bin",
    "write_radar_pcd",
    "read_radar_pcd",
    "read_radar_pcd_with_stats",
    "radar_pcd_to_columns",
    "write_nuscenes",
    "NUSCENES_TABLES",
    "DEFAULT_SIM_VERSION",
]

#: The 18 fields of a nuScenes radar ``.pcd``: (name, size in bytes, PCD type).
RADAR_PCD_FIELDS: tuple[tuple[str, int, str], ...] = (
    ("x", 4, "F"),
    ("y", 4, "F"),
    ("z", 4, "F"),
    ("dyn_prop", 1, "I"),
    ("id", 2, "I"),
    ("rcs", 4, "F"),
    ("vx", 4, "F"),
    ("vy", 4, "F"),
    ("vx_comp", 4, "F"),
    ("vy_comp", 4, "F"),
    ("is_quality_valid", 1, "I"),
    ("ambig_state", 1, "I"),
    ("x_rms", 1, "I"),
    ("y_rms", 1, "I"),
    ("invalid_state", 1, "I"),
    ("pdh0", 1, "I"),
    ("vx_rms", 1, "I"),
    ("vy_rms", 1, "I"),
)
_NP_TYPE = {
    ("F", 4): "<f4",
    ("F", 8): "<f8",
    ("I", 1): "i1",
    ("I", 2): "<i2",
    ("I", 4): "<i4",
    ("U", 1): "u1",
    ("U", 2): "<u2",
    ("U", 4): "<u4",
}
#: Packed (unaligned) record dtype of the radar ``.pcd`` binary data.
RADAR_PCD_DTYPE = np.dtype([(n, _NP_TYPE[(t, s)]) for n, s, t in RADAR_PCD_FIELDS])

NUSCENES_TABLES: tuple[str, ...] = (
    "category",
    "attribute",
    "visibility",
    "instance",
    "sensor",
    "calibrated_sensor",
    "ego_pose",
    "log",
    "scene",
    "sample",
    "sample_data",
    "sample_annotation",
    "map",
)
#: Version folder name for simulated data.
DEFAULT_SIM_VERSION = "v1.0-sim"

_CATEGORIES = (
    "human.pedestrian.adult",
    "human.pedestrian.child",
    "human.pedestrian.wheelchair",
    "human.pedestrian.stroller",
    "human.pedestrian.personal_mobility",
    "human.pedestrian.police_officer",
    "human.pedestrian.construction_worker",
    "animal",
    "vehicle.car",
    "vehicle.motorcycle",
    "vehicle.bicycle",
    "vehicle.bus.bendy",
    "vehicle.bus.rigid",
    "vehicle.truck",
    "vehicle.construction",
    "vehicle.emergency.ambulance",
    "vehicle.emergency.police",
    "vehicle.trailer",
    "movable_object.barrier",
    "movable_object.trafficcone",
    "movable_object.pushable_pullable",
    "movable_object.debris",
    "static_object.bicycle_rack",
)
_ATTRIBUTES = (
    "vehicle.moving",
    "vehicle.stopped",
    "vehicle.parked",
    "cycle.with_rider",
    "cycle.without_rider",
    "pedestrian.sitting_lying_down",
    "pedestrian.standing",
    "pedestrian.moving",
)
_VISIBILITY = (
    ("v0-40", "visibility of whole object is between 0 and 40%"),
    ("v40-60", "visibility of whole object is between 40 and 60%"),
    ("v60-80", "visibility of whole object is between 60 and 80%"),
    ("v80-100", "visibility of whole object is between 80 and 100%"),
)


# --- point-cloud files ----------------------------------------------------------------------
def write_lidar_bin(path: str | os.PathLike, points: np.ndarray) -> None:
    """Write ``(n, 5)`` lidar points (x, y, z in m, intensity, ring) as a float32 ``.pcd.bin``."""
    p = np.ascontiguousarray(points, dtype=np.float32)
    if p.ndim != 2 or p.shape[1] != 5:
        raise ValueError(f"lidar points must have shape (n, 5), got {p.shape}")
    atomic_write_bytes(path, p.astype("<f4", copy=False).tobytes())


def read_lidar_bin(path: str | os.PathLike) -> np.ndarray:
    """Read a nuScenes lidar ``.pcd.bin`` -> ``(n, 5)`` float32 (x, y, z, intensity, ring)."""
    size = os.path.getsize(path)
    if size % 20:  # 5 little-endian float32 a point: a cut file must not pass as fewer points
        raise ValueError(
            f"{str(path)!r} holds {size} bytes, not a multiple of 20 (5 float32 a point: x, y, z, "
            "intensity, ring); the file is cut or not a nuScenes lidar sweep"
        )
    raw = np.fromfile(path, dtype="<f4")
    return raw.reshape(-1, 5).astype(np.float32, copy=False)


def write_radar_pcd(path: str | os.PathLike, points: np.ndarray) -> None:
    """Write ``(n, 12)`` radar points (``RADAR_COLUMNS``) as a nuScenes radar ``.pcd`` (18 fields).

    Fields outside the frame contract are synthesised: ``id`` = index, ``is_quality_valid`` = 1,
    ``x_rms``/``y_rms`` grow with range, ``vx_rms``/``vy_rms`` = 3 (ARS 408 rms codes).
    """
    p = np.asarray(points, dtype=np.float32)
    if p.ndim != 2 or p.shape[1] != len(RADAR_COLUMNS):
        raise ValueError(f"radar points must have shape (n, {len(RADAR_COLUMNS)}), got {p.shape}")
    n = p.shape[0]
    rec = np.zeros(max(n, 1), dtype=RADAR_PCD_DTYPE)
    if n == 0:
        rec["x"] = rec["y"] = rec["z"] = np.nan
    else:
        for k, name in enumerate(RADAR_COLUMNS):
            if name in ("dyn_prop", "ambig_state", "invalid_state", "pdh0"):
                rec[name] = np.rint(p[:, k]).astype(np.int8)
            else:
                rec[name] = p[:, k]
        rec["id"] = np.arange(n, dtype=np.int16)
        rec["is_quality_valid"] = 1
        rng_m = np.nan_to_num(
            np.hypot(p[:, 0], p[:, 1]), nan=0.0, posinf=620.0
        )  # rms codes only; a NaN point stays NaN
        code = np.clip(3 + (rng_m // 20).astype(np.int64), 0, 31).astype(np.int8)
        rec["x_rms"] = code
        rec["y_rms"] = code
        rec["vx_rms"] = 3
        rec["vy_rms"] = 3
    m = len(rec)
    header = "\n".join(
        [
            "# .PCD v0.7 - Point Cloud Data file format",
            "VERSION 0.7",
            "FIELDS " + " ".join(f[0] for f in RADAR_PCD_FIELDS),
            "SIZE " + " ".join(str(f[1]) for f in RADAR_PCD_FIELDS),
            "TYPE " + " ".join(f[2] for f in RADAR_PCD_FIELDS),
            "COUNT " + " ".join("1" for _ in RADAR_PCD_FIELDS),
            f"WIDTH {m}",
            "HEIGHT 1",
            "VIEWPOINT 0 0 0 1 0 0 0",
            f"POINTS {m}",
            "DATA binary",
        ]
    )
    atomic_write_bytes(path, header.encode("ascii") + b"\n" + rec.tobytes() + b"\n")


def read_radar_pcd(path: str | os.PathLike) -> np.ndarray:
    """Read a nuScenes radar ``.pcd`` (binary, any field layout its header declares) into a
    structured array with one named field per PCD field. Unfiltered, except that records with a
    non-finite position are dropped (logged with their count); empty clouds give 0 rows."""
    return read_radar_pcd_with_stats(path)[0]


def _pcd_header(blob: bytes, path: str | os.PathLike) -> tuple[dict[str, list[str]], int]:
    """A ``.pcd``'s header lines (keys upper case) up to its DATA line, and where the data
    begins."""
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = blob.find(b"\n", pos)
        if end < 0:
            raise ValueError(f"{str(path)!r}: PCD header has no DATA line")
        line = blob[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            return header, pos


def _read_pcd_records(path: str | os.PathLike) -> np.ndarray:
    """Every record of a binary ``.pcd``, its size checked exactly against the header."""
    with open(path, "rb") as f:
        blob = f.read()
    header, pos = _pcd_header(blob, path)
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT", "DATA"):
        if key not in header:
            raise ValueError(f"{str(path)!r}: PCD header lacks {key}")
    if header["DATA"][0] != "binary":
        raise ValueError(
            f"{str(path)!r}: only binary PCD data is supported, got DATA {header['DATA'][0]!r}"
        )
    counts = header.get("COUNT", ["1"] * len(header["FIELDS"]))
    if any(c != "1" for c in counts):
        raise ValueError(f"{str(path)!r}: PCD fields with COUNT != 1 are not supported")
    try:
        dtype = np.dtype(
            [
                (n, _NP_TYPE[(t, int(s))])
                for n, s, t in zip(header["FIELDS"], header["SIZE"], header["TYPE"])
            ]
        )
    except KeyError as e:
        raise ValueError(f"{str(path)!r}: unsupported PCD field type/size {e}") from None
    n = int(header["WIDTH"][0]) * int(header["HEIGHT"][0])
    need = n * dtype.itemsize
    if len(blob) - pos < need:
        raise ValueError(
            f"{str(path)!r}: header declares {n} points ({need} bytes) but {len(blob) - pos} bytes "
            "follow"
        )
    rec = np.frombuffer(blob, dtype=dtype, count=n, offset=pos)
    if blob[pos + need :].strip(b" \r\n"):  # a trailing newline is harmless; more data is not
        raise ValueError(
            f"{str(path)!r}: header declares {n} points ({need} bytes) but {len(blob) - pos} bytes "
            "follow"
        )
    return rec


def read_radar_pcd_with_stats(path: str | os.PathLike) -> tuple[np.ndarray, int]:
    """:func:`read_radar_pcd` and how many records it dropped for a non-finite position."""
    return _drop_nonfinite(_read_pcd_records(path), path)


def _drop_nonfinite(rec: np.ndarray, path: str | os.PathLike) -> tuple[np.ndarray, int]:
    """Records whose position is not finite are dropped, each alone, and counted in a warning
    (the devkit writes an empty cloud as one all-NaN record; that one is dropped silently)."""
    if not len(rec) or not {"x", "y", "z"} <= set(rec.dtype.names):
        return rec, 0
    ok = np.isfinite(rec["x"]) & np.isfinite(rec["y"]) & np.isfinite(rec["z"])
    n_bad = int(len(rec) - ok.sum())
    if n_bad and len(rec) == 1:
        return rec[:0], 0  # the devkit's empty cloud
    if n_bad:
        logger.warning(
            "%s: %d of %d radar records have a non-finite position; those records are dropped",
            path,
            n_bad,
            len(rec),
        )
    return (rec[ok] if n_bad else rec), n_bad


def radar_pcd_to_columns(rec: np.ndarray) -> np.ndarray:
    """Structured radar records -> ``(n, 12)`` float32 in ``RADAR_COLUMNS`` order."""
    out = np.empty((len(rec), len(RADAR_COLUMNS)), dtype=np.float32)
    for k, name in enumerate(RADAR_COLUMNS):
        if name not in rec.dtype.names:
            raise ValueError(f"radar .pcd lacks the field {name!r}; it has {rec.dtype.names}")
        out[:, k] = rec[name]
    return out


# --- the table writer ----------------------------------------------------------------------
def _token(*parts: object) -> str:
    """Deterministic 32-hex token (same inputs, same token, same bytes on disk)."""
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


def _placeholder_map_png() -> bytes:
    """A tiny all-background grey PNG for the ``map`` table (the devkit needs a file to exist)."""
    import zlib

    w = h = 8
    raw = b"".join(b"\x00" + bytes(w) for _ in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return len(data).to_bytes(4, "big") + tag + data + zlib.crc32(tag + data).to_bytes(4, "big")

    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([8, 0, 0, 0, 0])
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )


def _pose_record(token: str, ts: int, pose) -> dict:
    q = pose.quaternion()
    return {
        "token": token,
        "timestamp": int(ts),
        "rotation": [float(v) for v in q],
        "translation": [float(v) for v in pose.translation],
    }


def _link(records: list[dict]) -> None:
    for k, r in enumerate(records):
        r["prev"] = records[k - 1]["token"] if k > 0 else ""
        r["next"] = records[k + 1]["token"] if k + 1 < len(records) else ""


def _sample_data(token: str, cs_token: str, ts: int, is_key: bool, filename: str) -> dict:
    """One ``sample_data`` record (its sample token is set once the scene's samples are known)."""
    return {
        "token": token,
        "sample_token": "",
        "ego_pose_token": token,
        "calibrated_sensor_token": cs_token,
        "timestamp": ts,
        "fileformat": "pcd",
        "is_key_frame": is_key,
        "height": 0,
        "width": 0,
        "filename": filename,
    }


class _SceneWriter:
    """The records and point files of one scene, frame by frame."""

    def __init__(self, name: str, root: Path, tables: dict[str, list[dict]]) -> None:
        self.name = name
        self.root = root
        self.tables = tables
        self.cs_token: dict[str, str] = {}
        self.lidar_sd: list[dict] = []
        self.samples: list[dict] = []
        self.radar_sd: dict[str, list[dict]] = {}
        self.radar_pts: dict[str, list[np.ndarray]] = {}
        self.log_token = _token(name, "log")
        tables["log"].append(
            {
                "token": self.log_token,
                "logfile": name,
                "vehicle": "evgrid-sim",
                "date_captured": "2018-08-01",
                "location": "evgrid-sim",
            }
        )

    def calib(self, ch: str, s2e) -> str:
        """The scene's calibrated_sensor token of channel ``ch``, written on first use."""
        if ch not in self.cs_token:
            self.cs_token[ch] = _token(self.name, "calibrated_sensor", ch)
            self.tables["calibrated_sensor"].append(
                {
                    "token": self.cs_token[ch],
                    "sensor_token": _token("sensor", ch),
                    "translation": [float(v) for v in s2e.translation],
                    "rotation": [float(v) for v in s2e.quaternion()],
                    "camera_intrinsic": [],
                }
            )
        return self.cs_token[ch]

    def add_frame(self, i: int, frame: Frame) -> None:
        """Frame ``i``: its lidar file and record, a sample if it is a keyframe, its radar
        sweeps (whose files are written once the key sweeps are known)."""
        name = self.name
        if not isinstance(frame, Frame):
            raise TypeError(f"scene {name!r} yielded a {type(frame).__name__}, not a Frame")
        ts = int(frame.lidar.timestamp)
        sd_token = _token(name, "sample_data", LIDAR_CHANNEL, i)
        folder = "samples" if frame.is_keyframe else "sweeps"
        fname = f"{folder}/{LIDAR_CHANNEL}/{name}__{LIDAR_CHANNEL}__{ts}.pcd.bin"
        write_lidar_bin(self.root / fname, frame.lidar.points)
        self.tables["ego_pose"].append(_pose_record(sd_token, ts, frame.lidar.ego_pose))
        cs = self.calib(LIDAR_CHANNEL, frame.lidar.sensor_to_ego)
        self.lidar_sd.append(_sample_data(sd_token, cs, ts, bool(frame.is_keyframe), fname))
        if frame.is_keyframe:
            self.samples.append(
                {
                    "token": _token(name, "sample", len(self.samples)),
                    "timestamp": ts,
                    "scene_token": _token(name, "scene"),
                }
            )
        for sweep in frame.radar_sweeps():
            ch = sweep.channel
            j = len(self.radar_sd.setdefault(ch, []))
            self.radar_pts.setdefault(ch, [])
            rtok = _token(name, "sample_data", ch, j)
            self.tables["ego_pose"].append(_pose_record(rtok, sweep.timestamp, sweep.ego_pose))
            cs = self.calib(ch, sweep.sensor_to_ego)
            self.radar_sd[ch].append(_sample_data(rtok, cs, int(sweep.timestamp), False, ""))
            self.radar_pts[ch].append(sweep.points)

    def _following_sample(self, ts: int) -> str:
        k = int(np.searchsorted(self.sample_ts, ts, side="left"))
        return self.samples[min(k, len(self.samples) - 1)]["token"]

    def _radar_files(self, ch: str, recs: list[dict]) -> None:
        """Each sample's key sweep of ``ch`` is the one closest in time; then the files."""
        rts = np.array([r["timestamp"] for r in recs], dtype=np.int64)
        key_of: dict[int, int] = {}
        for k, st in enumerate(self.sample_ts):
            key_of[int(np.argmin(np.abs(rts - st)))] = k
        for j, rec in enumerate(recs):
            if j in key_of:
                rec["is_key_frame"] = True
                rec["sample_token"] = self.samples[key_of[j]]["token"]
            else:
                rec["sample_token"] = self._following_sample(rec["timestamp"])
            folder = "samples" if rec["is_key_frame"] else "sweeps"
            rec["filename"] = f"{folder}/{ch}/{self.name}__{ch}__{rec['timestamp']}.pcd"
            write_radar_pcd(self.root / rec["filename"], self.radar_pts[ch][j])

    def finish(self, description: str) -> None:
        """Tie sample_data to samples, write the radar files, chain the records, add the scene."""
        name, samples, tables = self.name, self.samples, self.tables
        if not samples:
            raise ValueError(
                f"scene {name!r} has no keyframe; nuScenes needs at least one sample a scene"
            )
        self.sample_ts = np.array([s["timestamp"] for s in samples], dtype=np.int64)
        for rec in self.lidar_sd:
            rec["sample_token"] = self._following_sample(rec["timestamp"])
            if rec["is_key_frame"]:
                k = int(np.searchsorted(self.sample_ts, rec["timestamp"]))
                rec["sample_token"] = samples[k]["token"]
        for ch in sorted(self.radar_sd, key=channel_order):
            recs = self.radar_sd[ch]
            if recs:
                self._radar_files(ch, recs)
            _link(recs)
            tables["sample_data"].extend(recs)
        _link(self.lidar_sd)
        tables["sample_data"].extend(self.lidar_sd)
        _link(samples)
        tables["sample"].extend(samples)
        tables["scene"].append(
            {
                "token": _token(name, "scene"),
                "log_token": self.log_token,
                "nbr_samples": len(samples),
                "first_sample_token": samples[0]["token"],
                "last_sample_token": samples[-1]["token"],
                "name": name,
                "description": description,
            }
        )


def _vocabulary_tables() -> dict[str, list[dict]]:
    """Empty tables, but for the category, attribute and visibility vocabularies."""
    tables: dict[str, list[dict]] = {t: [] for t in NUSCENES_TABLES}
    for name in _CATEGORIES:
        tables["category"].append(
            {"token": _token("category", name), "name": name, "description": name}
        )
    for name in _ATTRIBUTES:
        tables["attribute"].append(
            {"token": _token("attribute", name), "name": name, "description": name}
        )
    for k, (level, desc) in enumerate(_VISIBILITY):
        tables["visibility"].append({"token": str(k + 1), "level": level, "description": desc})
    return tables


def _write_splits(
    table_root: Path, splits: Mapping[str, Sequence[str]] | None, names: set[str], overwrite: bool
) -> None:
    if splits is not None:
        bad = {s: [n for n in v if n not in names] for s, v in splits.items()}
        bad = {s: v for s, v in bad.items() if v}
        if bad:
            raise ValueError(f"splits name scenes that were not written: {bad}")
        write_json(table_root / "splits.json", {k: list(v) for k, v in splits.items()})
    elif (table_root / "splits.json").exists() and overwrite:
        os.unlink(table_root / "splits.json")


def _write_scene(
    scene: Scene,
    root: Path,
    tables: dict[str, list],
    names_seen: set[str],
    on_frame: Callable[[str, int], None] | None,
    descriptions: Mapping[str, str] | None,
) -> set[str]:
    """One scene's frames and records (its name must not be in ``names_seen``, where it is
    added); returns its radar channels."""
    name = str(scene.name)
    if name in names_seen:
        raise ValueError(f"scene name {name!r} appears twice")
    names_seen.add(name)
    writer = _SceneWriter(name, root, tables)
    for i, frame in enumerate(scene):
        writer.add_frame(i, frame)
        if on_frame is not None:
            on_frame(name, i)
    writer.finish(
        (descriptions or {}).get(name)
        or str(getattr(scene, "description", ""))
        or f"evgrid scene {name}"
    )
    return set(writer.radar_sd)


def write_nuscenes(
    scenes: Iterable[Scene],
    dataroot: str | os.PathLike,
    version: str = DEFAULT_SIM_VERSION,
    splits: Mapping[str, Sequence[str]] | None = None,
    overwrite: bool = False,
    on_frame: Callable[[str, int], None] | None = None,
    descriptions: Mapping[str, str] | None = None,
) -> Path:
    """Write scenes in the nuScenes v1.0 layout under ``dataroot``; returns ``dataroot/version``.

    ``splits`` (split name -> scene names) goes to ``<version>/splits.json``, which
    :func:`evgrid.data.nuscenes.load_nuscenes` reads before the official split lists.
    ``on_frame(scene_name, frame_index)`` is called after each frame is written.
    """
    if not version or any(c in version for c in "/\\") or version in (".", ".."):
        raise ValueError(f"version must be a plain folder name like 'v1.0-sim', got {version!r}")
    root = Path(dataroot)
    table_root = root / version
    if (table_root / "scene.json").exists() and not overwrite:
        raise FileExistsError(
            f"{str(table_root)!r} already holds a nuScenes database; choose another output "
            "folder or overwrite it"
        )
    tables = _vocabulary_tables()
    radar_channels: set[str] = set()
    map_token = _token("map", version)
    map_file = f"maps/{map_token}.png"
    atomic_write_bytes(root / map_file, _placeholder_map_png())
    names_seen: set[str] = set()
    for scene in scenes:
        radar_channels.update(_write_scene(scene, root, tables, names_seen, on_frame, descriptions))
    for ch, mod in [(LIDAR_CHANNEL, "lidar")] + [
        (c, "radar") for c in sorted(radar_channels, key=channel_order)
    ]:
        tables["sensor"].append({"token": _token("sensor", ch), "channel": ch, "modality": mod})
    tables["map"].append(
        {
            "token": map_token,
            "log_tokens": [r["token"] for r in tables["log"]],
            "category": "semantic_prior",
            "filename": map_file,
        }
    )
    table_root.mkdir(parents=True, exist_ok=True)
    for t, recs in tables.items():
        with atomic_open(table_root / f"{t}.json", "w") as f:
            json.dump(recs, f, indent=0)
    _write_splits(table_root, splits, names_seen, overwrite)
    return table_root
