"""The nuScenes loader: the same frames as the simulator, read through the official devkit.

Needs the ``nuscenes`` extra (nuscenes-devkit 1.2.0), imported only
when a dataset is opened. What it yields, per scene:

* one :class:`~evgrid.data.frame.Frame` per ``LIDAR_TOP`` sample_data of the scene, in
  time order (the chain of ``prev``/``next`` pointers, kept to the sample_data whose sample
  belongs to the scene); ``is_keyframe`` is the sample_data's ``is_key_frame``;
* every radar channel the scene's samples carry (any names, any number), each radar sweep
  (same chain rule, per channel) going to the first frame whose lidar timestamp is >= its own,
  in the chain's order; sweeps after the scene's last lidar sweep are dropped. Nothing is
  re-sorted or removed: ``NuScenesScene.stats`` counts what a recording got wrong (sweeps
  missing, repeated, out of order, after the end) and the mapper skips and counts the
  repeated and late ones;
* radar points are read *unfiltered*: all 18 fields are parsed, the 12 of
  ``RADAR_COLUMNS`` kept, and no ``invalid_state``/``dyn_prop``/``ambig_state`` filter is
  applied (the devkit's ``RadarPointCloud.from_file`` filters by default): the validity
  fields are in the points, and filtering is left to consumers;
* lidar points keep all five columns (the devkit's reader drops the ring);
* ``occupancy`` is ``None`` (nuScenes has no true occupancy raster).

Scenes are selected by split: ``DATAROOT/<version>/splits.json`` (written for simulated
data by ``evgrid simulate --format nuscenes``) if it names the split, otherwise the official
``nuscenes.utils.splits.create_splits_scenes()``. As in the paper, scenes whose ego vehicle
never gets ``min_travel_m`` (1 m) away from its first pose are left out.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import stat
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.data.frame import LIDAR_CHANNEL, Frame, LidarSweep, RadarSweep
from evgrid.data.nuscenes_format import (
    radar_pcd_to_columns,
    read_lidar_bin,
    read_radar_pcd_with_stats,
)
from evgrid.data.sweeps import GapCounter, channel_order
from evgrid.geometry import SE3
from evgrid.io import READ_LIMITS, InputFileError, load_json_bounded, size_text
from evgrid.package import install_hint

__all__ = [
    "load_nuscenes",
    "nuscenes_splits",
    "NuScenesScene",
    "NuScenesScenes",
    "NuScenesError",
    "NuScenesDataError",
    "NUSCENES_DOWNLOAD_URL",
]

logger = logging.getLogger(__name__)

NUSCENES_DOWNLOAD_URL = "https://www.nuscenes.org/download"


class NuScenesError(RuntimeError):
    """The dataset or the devkit is missing or not laid out as expected."""


class NuScenesDataError(ValueError):
    """A damaged table or sensor file; the message names the file (and the record and key)."""


#: The keys evgrid (and the devkit's indexes) read from each table's records.
REQUIRED_KEYS: dict[str, tuple[str, ...]] = {
    "scene": ("token", "name", "first_sample_token"),
    "sample": ("token", "scene_token", "timestamp", "prev", "next"),
    "sample_data": (
        "token",
        "sample_token",
        "ego_pose_token",
        "calibrated_sensor_token",
        "timestamp",
        "filename",
        "is_key_frame",
        "prev",
        "next",
    ),
    "ego_pose": ("token", "translation", "rotation"),
    "calibrated_sensor": ("token", "sensor_token", "translation", "rotation"),
    "sensor": ("token", "channel", "modality"),
}

#: A lidar file this much smaller than the median of its scene's is taken as cut short.
SHORT_SWEEP_FRACTION = 0.5


def check_records(table_file: Path, records: Any) -> None:
    """:class:`NuScenesDataError` naming the file, the record's token and the key, for the first
    record of ``records`` (the table in ``table_file``) that lacks a key evgrid reads."""
    keys = REQUIRED_KEYS.get(table_file.stem, ())
    if not isinstance(records, list):
        raise NuScenesDataError(f"{table_file}: must hold a list of records")
    need = set(keys)
    for i, rec in enumerate(records):
        if isinstance(rec, dict) and need <= rec.keys():  # one C-level test a record
            continue
        if not isinstance(rec, dict):
            raise NuScenesDataError(f"{table_file}: record {i} is not a JSON object")
        for k in keys:
            if k not in rec:
                who = f"token {rec['token']!r}" if "token" in rec else f"number {i}"
                raise NuScenesDataError(f"{table_file}: record {who} has no key {k!r}")


def _diagnose(table_root: Path, err: Exception) -> NuScenesDataError | None:
    """After the devkit failed to load ``table_root``: the error naming the damaged table
    (a JSON file cut short, a record missing a key), or None when none is found."""
    for name in REQUIRED_KEYS:
        f = table_root / f"{name}.json"
        if not f.is_file():
            continue
        try:
            records = load_json_bounded(f, "nuScenes table")
        except InputFileError as e:
            return NuScenesDataError(str(e))
        except json.JSONDecodeError as e:
            return NuScenesDataError(
                f"{f}: not valid JSON at line {e.lineno} column {e.colno} ({e.msg}); the file "
                "is cut short or damaged"
            )
        try:
            check_records(f, records)
        except NuScenesDataError as e:
            return e
    return None


def _devkit() -> Any:
    try:
        from nuscenes.nuscenes import NuScenes
    except ImportError as e:
        raise NuScenesError(
            f"reading nuScenes needs the nuScenes devkit: {install_hint('nuscenes')} "
            f"(nuscenes-devkit==1.2.0); import failed with: {e}"
        ) from e
    return NuScenes


def _check_layout(dataroot: Path, version: str) -> None:
    hint = (
        f"download {version} from {NUSCENES_DOWNLOAD_URL} (the metadata and the lidar and radar "
        f"blobs) and unpack it so that {dataroot / version / 'scene.json'} exists"
    )
    if not dataroot.is_dir():
        raise FileNotFoundError(f"nuScenes dataroot {str(dataroot)!r} does not exist: {hint}")
    if not (dataroot / version).is_dir():
        present = sorted(
            p.name for p in dataroot.iterdir() if p.is_dir() and p.name.startswith("v1.0")
        )
        raise FileNotFoundError(
            f"nuScenes version folder {str(dataroot / version)!r} does not exist"
            + (f" (found {present})" if present else "")
            + f": {hint}"
        )
    if not (dataroot / version / "scene.json").is_file():
        raise FileNotFoundError(f"{str(dataroot / version / 'scene.json')!r} is missing: {hint}")


def nuscenes_splits(dataroot: str | os.PathLike, version: str) -> dict[str, list[str]]:
    """Split name -> scene names: the official lists, overridden by ``<version>/splits.json``."""
    splits: dict[str, list[str]] = {}
    try:
        from nuscenes.utils.splits import create_splits_scenes

        splits.update({k: list(v) for k, v in create_splits_scenes().items()})
    except ImportError as e:
        raise NuScenesError(
            f"reading nuScenes splits needs the devkit: {install_hint('nuscenes')} ({e})"
        ) from e
    custom = Path(dataroot) / version / "splits.json"
    if custom.is_file():
        try:
            data = load_json_bounded(custom, "nuScenes table")
        except ValueError as e:  # too large or deep, or not JSON
            raise NuScenesError(f"{str(custom)!r}: not a readable splits file ({e})") from None
        if not isinstance(data, dict) or not all(isinstance(v, list) for v in data.values()):
            raise NuScenesError(f"{str(custom)!r} must map split names to lists of scene names")
        splits.update({str(k): [str(s) for s in v] for k, v in data.items()})
    return splits


class NuScenesScene:
    """One nuScenes scene as a :class:`~evgrid.data.frame.Scene`; files are read lazily per
    frame."""

    def __init__(self, nusc: Any, scene_record: dict) -> None:
        self.nusc = nusc
        self.record = scene_record
        self.name: str = scene_record["name"]
        self.token: str = scene_record["token"]
        self._lidar_bytes: float | None = None
        first = nusc.get("sample", scene_record["first_sample_token"])
        self.lidar_tokens = self._chain(first["data"][LIDAR_CHANNEL])
        self.lidar_timestamps = np.array(
            [nusc.get("sample_data", t)["timestamp"] for t in self.lidar_tokens], dtype=np.int64
        )
        # Radar sweep tokens per frame, per channel, in the chain's order.
        n = len(self.lidar_tokens)
        #: The scene's radar channels (nuScenes' order, then by name).
        heads = self._radar_heads(first)
        self.radar_channels: tuple[str, ...] = tuple(sorted(heads, key=channel_order))
        self._radar: list[dict[str, list[str]]] = [
            {c: [] for c in self.radar_channels} for _ in range(n)
        ]
        #: What the recording got wrong, summed over sensors (see the module docstring).
        self.stats: dict[str, int] = {
            "lidar_sweeps": n,
            "lidar_sweeps_missing": 0,
            "radar_sweeps": 0,
            "radar_sweeps_missing": 0,
            "radar_sweeps_duplicate": 0,
            "radar_sweeps_out_of_order": 0,
            "radar_sweeps_after_end": 0,
        }
        lidar_gaps = GapCounter()
        for t in self.lidar_timestamps:
            lidar_gaps.add(int(t))
        self.stats["lidar_sweeps_missing"] = lidar_gaps.n_missing
        for ch in self.radar_channels:
            self._assign_radar(ch, heads[ch])

    def _assign_radar(self, ch: str, head: str) -> None:
        """Give each sweep of radar channel ``ch`` (its chain from token ``head``) to the first
        lidar frame at or after it, counting duplicates, sweeps out of order, gaps and sweeps
        after the last frame in :attr:`stats`."""
        n = len(self.lidar_tokens)
        gaps, newest, seen = GapCounter(), None, set()
        for tok in self._chain(head):
            ts = int(self.nusc.get("sample_data", tok)["timestamp"])
            self.stats["radar_sweeps"] += 1
            if ts in seen:
                self.stats["radar_sweeps_duplicate"] += 1
            elif newest is not None and ts < newest:
                self.stats["radar_sweeps_out_of_order"] += 1
            else:
                gaps.add(ts)
            seen.add(ts)
            newest = ts if newest is None else max(newest, ts)
            i = int(np.searchsorted(self.lidar_timestamps, ts, side="left"))
            if i < n:
                self._radar[i][ch].append(tok)
            else:
                self.stats["radar_sweeps_after_end"] += 1
        self.stats["radar_sweeps_missing"] += gaps.n_missing

    def _radar_heads(self, first: dict) -> dict[str, str]:
        """A sample_data token of each radar channel that any sample of the scene carries."""
        heads: dict[str, str] = {}
        sample = first
        while True:
            for ch, tok in sample["data"].items():
                if (
                    ch not in heads
                    and self.nusc.get("sample_data", tok)["sensor_modality"] == "radar"
                ):
                    heads[ch] = tok
            if not sample["next"]:
                return heads
            sample = self.nusc.get("sample", sample["next"])

    def _in_scene(self, sd_token: str) -> bool:
        sd = self.nusc.get("sample_data", sd_token)
        return self.nusc.get("sample", sd["sample_token"])["scene_token"] == self.token

    def _chain(self, token: str) -> list[str]:
        """All sample_data of one sensor in this scene, in time order, around ``token``."""
        sd = self.nusc.get("sample_data", token)
        while sd["prev"] and self._in_scene(sd["prev"]):
            sd = self.nusc.get("sample_data", sd["prev"])
        out = [sd["token"]]
        while sd["next"] and self._in_scene(sd["next"]):
            sd = self.nusc.get("sample_data", sd["next"])
            out.append(sd["token"])
        return out

    def __len__(self) -> int:
        return len(self.lidar_tokens)

    def __iter__(self) -> Iterator[Frame]:
        """The frames; one whose lidar file or ego pose is damaged is skipped, counted
        (``stats["frames_damaged"]``) and logged naming the file and record."""
        self.stats["frames_damaged"] = 0
        skipped = 0  # since the last frame yielded: the mapper counts their gap as theirs
        for i in range(len(self)):
            try:
                frame = self.frame(i)
            except NuScenesDataError as e:
                self.stats["frames_damaged"] += 1
                skipped += 1
                logger.warning("scene %r frame %d: %s; frame skipped", self.name, i, e)
                continue
            yield dataclasses.replace(frame, lidar_skipped=skipped) if skipped else frame
            skipped = 0

    def __repr__(self) -> str:
        return f"NuScenesScene({self.name!r}, {len(self)} frames)"

    def _table(self, name: str) -> Path:
        return Path(self.nusc.dataroot) / self.nusc.version / f"{name}.json"

    def _poses(self, sd: dict) -> tuple[SE3, SE3]:
        """(sensor_to_ego, ego_pose) of a sample_data; NuScenesDataError naming the record for a
        pose that is not finite or not a rotation."""
        cs = self.nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
        ep = self.nusc.get("ego_pose", sd["ego_pose_token"])
        out = []
        for table, rec in (("calibrated_sensor", cs), ("ego_pose", ep)):
            try:
                out.append(SE3.from_quaternion(rec["rotation"], rec["translation"]))
            except (ValueError, TypeError) as e:
                raise NuScenesDataError(
                    f"{self._table(table)}: record {rec['token']!r} (sample_data "
                    f"{sd['token']!r}, t = {sd['timestamp']} us): {e} (translation "
                    f"{rec['translation']}, rotation {rec['rotation']})"
                ) from None
        return out[0], out[1]

    def ego_translations(self) -> np.ndarray:
        """Ego positions (m, global) of every lidar sample_data, ``(n, 3)`` (NaN where the
        record is not finite)."""
        out = np.empty((len(self), 3))
        for i, tok in enumerate(self.lidar_tokens):
            sd = self.nusc.get("sample_data", tok)
            out[i] = self.nusc.get("ego_pose", sd["ego_pose_token"])["translation"]
        return out

    def travel_m(self) -> float:
        """How far (m) the ego gets from its first finite pose during the scene."""
        t = self.ego_translations()
        t = t[np.isfinite(t).all(axis=1)]
        return float(np.max(np.hypot(t[:, 0] - t[0, 0], t[:, 1] - t[0, 1]))) if len(t) else 0.0

    def _median_lidar_bytes(self) -> float:
        if self._lidar_bytes is None:
            sizes = []
            for tok in self.lidar_tokens:
                f = os.path.join(self.nusc.dataroot, self.nusc.get("sample_data", tok)["filename"])
                if os.path.isfile(f):
                    sizes.append(os.path.getsize(f))
            self._lidar_bytes = float(np.median(sizes)) if sizes else 0.0
        return self._lidar_bytes

    def _read_lidar(self, path: str) -> np.ndarray:
        """A lidar file's points; NuScenesDataError naming the file when it is empty, cut
        inside a point, or less than half the size of the scene's typical sweep (cut at a point
        boundary: no file format tells that from a small sweep, its neighbours do)."""
        try:
            pts = read_lidar_bin(path)
        except ValueError as e:
            raise NuScenesDataError(str(e)) from None
        if len(pts) == 0:
            raise NuScenesDataError(f"{path}: the lidar file is empty (0 bytes)")
        median = self._median_lidar_bytes()
        if 20 * len(pts) < SHORT_SWEEP_FRACTION * median:
            raise NuScenesDataError(
                f"{path}: {len(pts)} points, less than {SHORT_SWEEP_FRACTION:g} of the "
                f"{median / 20:.0f} of the scene's median sweep; the file is cut short"
            )
        return pts

    def frame(self, i: int) -> Frame:
        """Frame ``i`` (reads the lidar file and the radar files of its sweeps)."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame index {i} out of range for a scene of {len(self)} frames")
        nusc = self.nusc
        sd = nusc.get("sample_data", self.lidar_tokens[i])
        s2e, pose = self._poses(sd)
        pts = self._read_lidar(os.path.join(nusc.dataroot, sd["filename"]))
        lidar = LidarSweep(pts, s2e, pose, int(sd["timestamp"]), LIDAR_CHANNEL)
        radar: dict[str, tuple[RadarSweep, ...]] = {}
        for ch in self.radar_channels:
            sweeps = []
            for tok in self._radar[i][ch]:
                rsd = nusc.get("sample_data", tok)
                try:
                    rs2e, rpose = self._poses(rsd)
                except NuScenesDataError as e:  # one radar sweep lost, not the frame
                    self.stats["radar_sweeps_bad_pose"] = (
                        self.stats.get("radar_sweeps_bad_pose", 0) + 1
                    )
                    logger.warning("scene %r: %s; radar sweep dropped", self.name, e)
                    continue
                rec, n_bad = read_radar_pcd_with_stats(os.path.join(nusc.dataroot, rsd["filename"]))
                self.stats["radar_records_dropped"] = (
                    self.stats.get("radar_records_dropped", 0) + n_bad
                )
                sweeps.append(
                    RadarSweep(radar_pcd_to_columns(rec), rs2e, rpose, int(rsd["timestamp"]), ch)
                )
            radar[ch] = tuple(sweeps)
        return Frame(
            scene=self.name,
            index=i,
            timestamp=int(sd["timestamp"]),
            ego_pose=pose,
            is_keyframe=bool(sd["is_key_frame"]),
            lidar=lidar,
            radar=radar,
            occupancy=None,
        )


class NuScenesScenes(list):
    """The scenes :func:`load_nuscenes` returns (a list), with ``dropped``: the name of each
    scene left out, and why, for the run to print."""

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.dropped: dict[str, str] = {}


def _check_table_sizes(table_root: Path) -> None:
    """The devkit reads each table whole: one that is no regular file (a device never ends) or
    larger than READ_LIMITS["nuScenes table"] is refused naming it, before the devkit opens it."""
    limit = READ_LIMITS["nuScenes table"]
    for f in sorted(table_root.glob("*.json")):
        st = f.stat()
        if not stat.S_ISREG(st.st_mode):
            raise NuScenesDataError(f"{f}: not a regular file; a nuScenes table is a JSON file")
        if st.st_size > limit:
            raise NuScenesDataError(
                f"{f}: {st.st_size:,} bytes, more than the {size_text(limit)} a nuScenes "
                "table may hold; is it the right file?"
            )


def _open(NuScenes: Any, root: Path, version: str, verbose: bool) -> Any:
    """The devkit's database, its tables checked; NuScenesDataError naming the damaged table
    file (JSON cut short), record and key instead of the devkit's bare errors."""
    table_root = root / version
    _check_table_sizes(table_root)
    try:
        nusc = NuScenes(version=version, dataroot=str(root), verbose=verbose)
    except (ValueError, RecursionError, KeyError, TypeError) as e:
        found = _diagnose(table_root, e)
        if found is not None:
            raise found from None
        raise NuScenesDataError(
            f"{table_root}: the nuScenes devkit cannot read the tables: {type(e).__name__} {e}"
        ) from None
    for name in REQUIRED_KEYS:
        check_records(table_root / f"{name}.json", getattr(nusc, name))
    return nusc


def _wanted_scenes(
    root: Path, version: str, split: str | None, scene_names: Sequence[str] | None
) -> set[str] | None:
    """The names of the scenes of ``split`` among ``scene_names`` (either may be None: no
    restriction); None: every scene."""
    wanted: set[str] | None = None
    if split is not None:
        splits = nuscenes_splits(root, version)
        if split not in splits:
            raise ValueError(f"unknown split {split!r}; known splits: {sorted(splits)}")
        wanted = set(splits[split])
    if scene_names is not None:
        names = set(scene_names)
        wanted = names if wanted is None else wanted & names
    return wanted


def load_nuscenes(
    dataroot: str | os.PathLike,
    version: str = "v1.0-trainval",
    split: str | None = "val",
    scene_names: Sequence[str] | None = None,
    min_travel_m: float = 1.0,
    verbose: bool = False,
) -> list[NuScenesScene]:
    """The scenes of a split (or the named scenes; ``split=None`` and no names: all scenes) whose
    ego travels at least ``min_travel_m`` metres, in the tables' order; the others are logged
    and listed, with the reason, in the result's ``dropped``."""
    if not (min_travel_m >= 0.0):
        raise ValueError(
            f"min_travel_m must be a non-negative distance in metres, got {min_travel_m!r}"
        )
    root = Path(dataroot)
    _check_layout(root, version)
    NuScenes = _devkit()
    wanted = _wanted_scenes(root, version, split, scene_names)
    nusc = _open(NuScenes, root, version, verbose)
    if scene_names is not None:
        missing = sorted(set(scene_names) - {s["name"] for s in nusc.scene})
        if missing:
            raise ValueError(f"scenes {missing} are not in {str(root / version)!r}")
    out = NuScenesScenes()
    for rec in nusc.scene:
        if wanted is not None and rec["name"] not in wanted:
            continue
        sc = NuScenesScene(nusc, rec)
        travel = sc.travel_m()
        if travel < min_travel_m:
            why = (
                f"the vehicle never gets {min_travel_m:g} m from its first pose (at most "
                f"{travel:.2f} m): a scene standing still has nothing to map (paper sec. VI)"
            )
            out.dropped[sc.name] = why
            logger.warning("nuScenes scene %r dropped: %s", sc.name, why)
            continue
        out.append(sc)
    if split is not None and not out and not wanted & {s["name"] for s in nusc.scene}:
        raise ValueError(
            f"split {split!r} names none of the {len(nusc.scene)} scenes in "
            f"{str(root / version)!r} (a {version} database with a {split!r} split from another "
            "version?)"
        )
    return out
