"""Where scenes come from, as small picklable descriptions (so one process per scene can load its
own).

* :class:`SimSource` - the built-in simulator, by seed (the default when no dataset is given);
* :class:`SimFilesSource` - scenes written by ``evgrid simulate`` (``.npz`` folder);
* :class:`NuScenesSource` - nuScenes (or a simulated dataset in its layout) through the devkit;
* :class:`BagSource` - a robot recording (ROS 1/2 bag or MCAP) read as its rig file says.

Each source names its recordings' fixed frame (:meth:`fixed_frame`: the frame its ego poses
are given in), the frame maps are built and exported in (docs/conventions.md#map-frame).
"""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from evgrid.data.frame import Scene
from evgrid_sim.radar_variants import RadarRanges, RadarVariant

__all__ = [
    "SceneSource",
    "SimSource",
    "SimFilesSource",
    "NuScenesSource",
    "BagSource",
    "SceneIndexError",
    "source_to_dict",
    "source_from_dict",
    "scenes_of",
    "fixed_frame_of",
]

#: The simulator's fixed frame: its towns' ``world`` coordinates, where its ego poses lie.
SIM_FIXED_FRAME = "world"
#: nuScenes' ego poses are in its ``global`` frame (the map's).
NUSCENES_FIXED_FRAME = "global"


class SceneSource(Protocol):
    """Names scenes and loads one by name."""

    def names(self) -> list[str]: ...

    def load(self, name: str) -> Scene: ...

    def fixed_frame(self) -> str: ...


@dataclass(frozen=True)
class SimSource:
    """Simulated scenes of the given seeds (``duration_s`` seconds each).

    The radar is the calibrated one, or ``radar`` for every scene, or one drawn per scene from
    ``radar_ranges`` (what Ev-Net trains on); the town and drive of a seed stay the same.
    """

    seeds: tuple[int, ...]
    duration_s: float = 20.0
    radar: RadarVariant | None = None
    radar_ranges: RadarRanges | None = None

    def __post_init__(self) -> None:
        if self.radar is not None and self.radar_ranges is not None:
            raise ValueError("SimSource takes radar or radar_ranges, not both")

    @classmethod
    def split(
        cls,
        split: str,
        n: int,
        first_seed: int = 0,
        duration_s: float = 20.0,
        radar: RadarVariant | None = None,
        radar_ranges: RadarRanges | None = None,
    ) -> SimSource:
        """The first ``n`` seeds from ``first_seed`` on that belong to ``split`` (``train`` or
        ``val``)."""
        if split not in ("train", "val"):
            raise ValueError(f"split must be 'train' or 'val', got {split!r}")
        from evgrid_sim.scene import sim_split

        seeds, s = [], first_seed
        while len(seeds) < n:
            if sim_split(s) == split:
                seeds.append(s)
            s += 1
        return cls(tuple(seeds), duration_s, radar, radar_ranges)

    def config(self, seed: int):
        """The simulator's configuration of scene ``seed``."""
        from evgrid_sim import SimConfig

        config = SimConfig(duration_s=self.duration_s)
        radar = self.radar_ranges.draw(seed) if self.radar_ranges is not None else self.radar
        return radar.apply(config) if radar is not None else config

    def names(self) -> list[str]:
        from evgrid_sim.scene import scene_name

        return [scene_name(s) for s in self.seeds]

    def load(self, name: str) -> Scene:
        from evgrid_sim import simulate_scene

        by_name = dict(zip(self.names(), self.seeds))
        if name not in by_name:
            raise KeyError(f"no simulated scene {name!r} among {sorted(by_name)}")
        return simulate_scene(by_name[name], self.config(by_name[name]))

    def fixed_frame(self) -> str:
        """The frame of the ego poses: the simulated town's."""
        return SIM_FIXED_FRAME


class SceneIndexError(ValueError):
    """A folder of simulated scenes whose ``index.json`` is missing a scene or cannot be read."""


@dataclass(frozen=True)
class SimFilesSource:
    """Scenes written by ``evgrid simulate --format npz`` into ``folder`` (optionally one split)."""

    folder: str
    split: str | None = None

    def _index(self) -> list[dict]:
        path = Path(self.folder) / "index.json"
        if not path.is_file():
            raise FileNotFoundError(
                f"{path} not found: write scenes with `evgrid simulate --out {self.folder}` first"
            )
        try:
            entries = json.loads(path.read_text())["scenes"]
            ok = isinstance(entries, list) and all(
                isinstance(e, dict) and {"name", "file"} <= set(e) for e in entries
            )
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as e:
            raise SceneIndexError(
                f"{path}: not a scene index of `evgrid simulate` ({type(e).__name__}: {e})"
            ) from None
        if not ok:
            raise SceneIndexError(
                f"{path}: 'scenes' must be a list of {{name, file, split}} entries"
            )
        return [e for e in entries if self.split is None or e.get("split") == self.split]

    def names(self) -> list[str]:
        return [e["name"] for e in self._index()]

    def why_empty(self) -> str:
        """What the folder holds, when the split asked for has no scenes there."""
        splits: dict[str, int] = {}
        for e in SimFilesSource(self.folder)._index():
            splits[str(e.get("split"))] = splits.get(str(e.get("split")), 0) + 1
        held = ", ".join(f"{n} {s}" for s, n in sorted(splits.items())) or "no scenes"
        return (
            f"{self.folder} has no scenes of split {self.split!r}; it holds {held} "
            "(--split all maps every scene)"
        )

    def load(self, name: str) -> Scene:
        from evgrid_sim.store import load_sim_scene

        for e in self._index():
            if e["name"] == name:
                return load_sim_scene(Path(self.folder) / e["file"])
        raise SceneIndexError(
            f"no scene {name!r} in {self.folder}/index.json; it has {self.names()}"
        )

    def fixed_frame(self) -> str:
        """The frame of the ego poses: the simulated town's."""
        return SIM_FIXED_FRAME


@functools.lru_cache(maxsize=2)
def _nuscenes_scenes(
    dataroot: str, version: str, split: str | None, names: tuple[str, ...] | None
) -> dict:
    from evgrid.data.nuscenes import load_nuscenes

    scenes = load_nuscenes(
        dataroot, version, split=split, scene_names=list(names) if names else None
    )
    return {s.name: s for s in scenes}


@dataclass(frozen=True)
class NuScenesSource:
    """nuScenes scenes of a split (or the named ones) under ``dataroot``; see
    :func:`evgrid.data.load_nuscenes`."""

    dataroot: str
    version: str = "v1.0-trainval"
    split: str | None = "val"
    scene_names: tuple[str, ...] | None = None

    def names(self) -> list[str]:
        return list(_nuscenes_scenes(self.dataroot, self.version, self.split, self.scene_names))

    def load(self, name: str) -> Scene:
        scenes = _nuscenes_scenes(self.dataroot, self.version, self.split, self.scene_names)
        if name not in scenes:
            raise KeyError(f"no nuScenes scene {name!r} in split {self.split!r}")
        return scenes[name]

    def fixed_frame(self) -> str:
        """nuScenes' global frame, where its ego poses lie."""
        return NUSCENES_FIXED_FRAME

    def dropped(self) -> dict[str, str]:
        """Scenes of the split (or named) that the loader left out, each with why."""
        from evgrid.data.nuscenes import nuscenes_splits

        wanted = set(self.scene_names or ())
        if self.split is not None:
            try:
                splits = nuscenes_splits(Path(self.dataroot), self.version)
            except (OSError, ValueError, ImportError):  # no split table: loading will say why
                return {}
            split = set(splits.get(self.split, ()))
            wanted = split & wanted if self.scene_names else split
        kept = set(self.names())
        # the loader's only reason to leave a scene out (paper: scenes that barely move)
        why = "its vehicle travels less than 1 m (left out as in the paper)"
        return {n: why for n in sorted(wanted - kept)}


@dataclass(frozen=True)
class BagSource:
    """Recordings (``.bag``, ``.mcap`` or ROS 2 bag folders) sharing one rig file; one scene each,
    see
    :func:`evgrid.data.bag.load_bag`. ``paths`` may be one path. A single recording is named by the
    rig file's ``scene`` (else its file name), several by their file names."""

    paths: tuple[str, ...]
    rig: str

    def __post_init__(self) -> None:
        paths = (self.paths,) if isinstance(self.paths, (str, os.PathLike)) else tuple(self.paths)
        if not paths:
            raise ValueError("BagSource needs at least one recording")
        object.__setattr__(self, "paths", tuple(str(p) for p in paths))

    def _by_name(self) -> dict[str, str]:
        from evgrid.data.bag import load_rig

        if len(self.paths) == 1:
            return {load_rig(self.rig).scene or Path(self.paths[0]).stem: self.paths[0]}
        out: dict[str, str] = {}
        for p in self.paths:
            name = Path(p).stem
            out[name if name not in out else f"{name}-{len(out)}"] = p
        return out

    def names(self) -> list[str]:
        return list(self._by_name())

    def load(self, name: str) -> Scene:
        from evgrid.data.bag import load_bag

        by_name = self._by_name()
        if name not in by_name:
            raise KeyError(f"no scene {name!r} among the recordings; they are {list(by_name)}")
        return load_bag(by_name[name], self.rig)

    def fixed_frame(self) -> str:
        """The rig's ``world_frame`` (default ``odom``): the frame its ego poses are read in."""
        from evgrid.data.bag import load_rig

        return load_rig(self.rig).world_frame


def scenes_of(source: SceneSource, names: Sequence[str] | None = None) -> list[str]:
    """The names to run: all of the source's, or those asked for (checked)."""
    known = source.names()
    if not known:
        why = getattr(source, "why_empty", None)
        raise ValueError(why() if why else f"no scenes to map in {source}")
    if names is None:
        return known
    missing = [n for n in names if n not in known]
    if missing:
        raise KeyError(
            f"unknown scene(s) {missing}; available: {known[:10]}"
            + (" ..." if len(known) > 10 else "")
        )
    return list(names)


def fixed_frame_of(source: object, scene: object = None) -> str:
    """The fixed frame of a source's recordings (its :meth:`fixed_frame`); for a scene alone,
    its rig's ``world_frame`` (recordings) or its ``fixed_frame``; else the simulator's
    ``world``."""
    said = getattr(source, "fixed_frame", None)
    if callable(said):
        return str(said())
    rig = getattr(scene, "rig", None)
    if rig is not None and getattr(rig, "world_frame", None):
        return str(rig.world_frame)
    return str(getattr(scene, "fixed_frame", None) or SIM_FIXED_FRAME)


def _kinds() -> dict[str, type]:
    return {
        "sim": SimSource,
        "sim_files": SimFilesSource,
        "nuscenes": NuScenesSource,
        "bag": BagSource,
    }


def source_to_dict(source: SceneSource) -> dict | None:
    """A source as plain JSON (``{"kind": ..., fields}``) for a run's config.json; None for
    sources of other kinds."""
    from evgrid.serial import to_dict

    for kind, cls in _kinds().items():
        if type(source) is cls:
            return {"kind": kind, **to_dict(source)}
    return None


def source_from_dict(d: dict) -> SceneSource:
    """Inverse of :func:`source_to_dict`; raises ConfigError naming the bad field."""
    from evgrid.serial import ConfigError, from_dict

    kinds = _kinds()
    if not isinstance(d, dict) or d.get("kind") not in kinds:
        raise ConfigError(
            f"config source: 'kind' must be one of {sorted(kinds)}, "
            f"got {d.get('kind') if isinstance(d, dict) else d!r}"
        )
    fields = {k: v for k, v in d.items() if k != "kind"}
    return from_dict(kinds[d["kind"]], fields, f"config source ({d['kind']})")
