"""The nuScenes loader: the same frames as the simulator, read through the official devkit.

Needs the extra ``pip install 'evgrid[nuscenes]'`` (nuscenes-devkit 1.2.0), imported only
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

import json
import os
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

__all__ = [
    "load_nuscenes",
    "nuscenes_splits",
    "NuScenesScene",
    "NuScenesError",
    "NUSCENES_DOWNLOAD_URL",
]

NUSCENES_DOWNLOAD_URL = "https://www.nuscenes.org/download"


class NuScenesError(RuntimeError):
    """The dataset or the devkit is missing or not laid out as expected."""


def _devkit() -> Any:
    try:
        from nuscenes.nuscenes import NuScenes
    except ImportError as e:
        raise NuScenesError(
            "reading nuScenes needs the nuScenes devkit: pip install 'evgrid[nuscenes]' "
            f"(nuscenes-devkit==1.2.0); import failed with: {e}"
        ) from e
    return NuScenes


def _check_layout(dataroot: Path, version: str) -> None:
    hint = (
        f"download {version} from {NUSCENES_DOWNLOAD_URL} (the metadata and the lidar and radar blobs) "
        f"and unpack it so that {dataroot / version / 'scene.json'} exists"
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
            f"reading nuScenes splits needs the devkit: pip install 'evgrid[nuscenes]' ({e})"
        ) from e
    custom = Path(dataroot) / version / "splits.json"
    if custom.is_file():
        with open(custom, encoding="utf-8") as f:
            data = json.load(f)
        if not isinstance(data, dict) or not all(isinstance(v, list) for v in data.values()):
            raise NuScenesError(f"{str(custom)!r} must map split names to lists of scene names")
        splits.update({str(k): [str(s) for s in v] for k, v in data.items()})
    return splits


class NuScenesScene:
    """One nuScenes scene as a :class:`~evgrid.data.frame.Scene`; files are read lazily per frame."""

    def __init__(self, nusc: Any, scene_record: dict) -> None:
        self.nusc = nusc
        self.record = scene_record
        self.name: str = scene_record["name"]
        self.token: str = scene_record["token"]
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
            gaps, newest, seen = GapCounter(), None, set()
            for tok in self._chain(heads[ch]):
                ts = int(nusc.get("sample_data", tok)["timestamp"])
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
        for i in range(len(self)):
            yield self.frame(i)

    def __repr__(self) -> str:
        return f"NuScenesScene({self.name!r}, {len(self)} frames)"

    def _poses(self, sd: dict) -> tuple[SE3, SE3]:
        cs = self.nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
        ep = self.nusc.get("ego_pose", sd["ego_pose_token"])
        return SE3.from_quaternion(cs["rotation"], cs["translation"]), SE3.from_quaternion(
            ep["rotation"], ep["translation"]
        )

    def ego_translations(self) -> np.ndarray:
        """Ego positions (m, global) of every lidar sample_data, ``(n, 3)``."""
        out = np.empty((len(self), 3))
        for i, tok in enumerate(self.lidar_tokens):
            sd = self.nusc.get("sample_data", tok)
            out[i] = self.nusc.get("ego_pose", sd["ego_pose_token"])["translation"]
        return out

    def travel_m(self) -> float:
        """How far (m) the ego gets from its first pose during the scene."""
        t = self.ego_translations()
        return float(np.max(np.hypot(t[:, 0] - t[0, 0], t[:, 1] - t[0, 1]))) if len(t) else 0.0

    def frame(self, i: int) -> Frame:
        """Frame ``i`` (reads the lidar file and the radar files of its sweeps)."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame index {i} out of range for a scene of {len(self)} frames")
        nusc = self.nusc
        sd = nusc.get("sample_data", self.lidar_tokens[i])
        s2e, pose = self._poses(sd)
        pts = read_lidar_bin(os.path.join(nusc.dataroot, sd["filename"]))
        lidar = LidarSweep(pts, s2e, pose, int(sd["timestamp"]), LIDAR_CHANNEL)
        radar: dict[str, tuple[RadarSweep, ...]] = {}
        for ch in self.radar_channels:
            sweeps = []
            for tok in self._radar[i][ch]:
                rsd = nusc.get("sample_data", tok)
                rs2e, rpose = self._poses(rsd)
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


def load_nuscenes(
    dataroot: str | os.PathLike,
    version: str = "v1.0-trainval",
    split: str | None = "val",
    scene_names: Sequence[str] | None = None,
    min_travel_m: float = 1.0,
    verbose: bool = False,
) -> list[NuScenesScene]:
    """The scenes of a split (or the named scenes; ``split=None`` and no names: all scenes) whose
    ego travels at least ``min_travel_m`` metres, in the tables' order."""
    if not (min_travel_m >= 0.0):
        raise ValueError(
            f"min_travel_m must be a non-negative distance in metres, got {min_travel_m!r}"
        )
    root = Path(dataroot)
    _check_layout(root, version)
    NuScenes = _devkit()
    wanted: set[str] | None = None
    if split is not None:
        splits = nuscenes_splits(root, version)
        if split not in splits:
            raise ValueError(f"unknown split {split!r}; known splits: {sorted(splits)}")
        wanted = set(splits[split])
    if scene_names is not None:
        names = set(scene_names)
        wanted = names if wanted is None else wanted & names
    nusc = NuScenes(version=version, dataroot=str(root), verbose=verbose)
    if scene_names is not None:
        missing = sorted(set(scene_names) - {s["name"] for s in nusc.scene})
        if missing:
            raise ValueError(f"scenes {missing} are not in {str(root / version)!r}")
    out = []
    for rec in nusc.scene:
        if wanted is not None and rec["name"] not in wanted:
            continue
        sc = NuScenesScene(nusc, rec)
        if sc.travel_m() < min_travel_m:
            continue
        out.append(sc)
    if split is not None and not out and not wanted & {s["name"] for s in nusc.scene}:
        raise ValueError(
            f"split {split!r} names none of the {len(nusc.scene)} scenes in {str(root / version)!r} "
            f"(a {version} database with a {split!r} split from another version?)"
        )
    return out
