"""nav2 / map_server maps: a PGM image and its YAML, from the pignistic occupancy probability.

Each cell is classified from its masses ``[m_f, m_o, m_u]``:

* unknown where the cell was never observed or ``m_u > unknown_mass`` (default 0.5): too
  little evidence either way;
* otherwise by ``P(occ) = m_o + m_u / 2`` (the pignistic probability, paper eq. (13)):
  occupied if ``P(occ) > occupied_thresh`` (0.65), free if ``P(occ) < free_thresh`` (0.196),
  unknown in between.

The image is written as map_saver writes trinary maps (occupied 0, free 254, unknown 205) with
``negate: 0`` and the same thresholds in the YAML, so map_server's trinary rule
(``p = (255 - pixel) / 255``; occupied if ``p > occupied_thresh``, free if ``p < free_thresh``,
else unknown) gives back exactly these classes. Image rows run top-down (the first row is the
largest y); ``origin`` is the map-frame pose of the lower-left pixel's outer corner.

:class:`Nav2Exporter` writes the navigation map as ``map.pgm`` + ``map.yaml`` (map_saver's
names), other maps beside it, and says in the YAML's comments which map it is and where the
map frame lies in the recording's fixed frame (the first ego pose there).
"""

from __future__ import annotations

import errno
import logging
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from evgrid.export._files import refuse_empty, refuse_existing, write_all
from evgrid.export._place import MapPlacement
from evgrid.grid import EvidentialMap
from evgrid.validation import check_number

log = logging.getLogger(__name__)

__all__ = [
    "Nav2Thresholds",
    "classify",
    "map_to_occupancy",
    "write_nav2",
    "read_nav2",
    "FREE",
    "OCCUPIED",
    "UNKNOWN",
    "PIXEL",
    "Nav2Exporter",
    "Nav2Params",
    "NAV2_STEM",
    "nav2_files",
    "occupancy_values",
    "OCCUPANCY_VALUES",
]

#: map_saver's file names: ``map.pgm`` + ``map.yaml``.
NAV2_STEM = "map"

#: Classes (the values of nav_msgs/OccupancyGrid for a trinary map).
FREE, OCCUPIED, UNKNOWN = 0, 100, -1
#: Pixel of each class in the PGM (map_saver's values).
PIXEL = {FREE: 254, OCCUPIED: 0, UNKNOWN: 205}


@dataclass(frozen=True)
class Nav2Thresholds:
    """Where a cell counts as occupied, free or unknown (see the module's docstring)."""

    occupied_thresh: float = 0.65
    free_thresh: float = 0.196
    unknown_mass: float = 0.5

    def __post_init__(self) -> None:
        check_number(self, "occupied_thresh", min=0.0, max=1.0)
        check_number(self, "free_thresh", min=0.0, max=1.0)
        check_number(self, "unknown_mass", min=0.0, max=1.0)
        if not self.free_thresh < self.occupied_thresh:
            raise ValueError(
                f"Nav2Thresholds: free_thresh {self.free_thresh} must be below occupied_thresh "
                f"{self.occupied_thresh}"
            )


def classify(
    masses: np.ndarray, covered: np.ndarray | None = None, th: Nav2Thresholds = Nav2Thresholds()
) -> np.ndarray:
    """Masses ``(..., 3)`` -> int8 classes FREE / OCCUPIED / UNKNOWN (see the module's
    docstring)."""
    m = np.asarray(masses, dtype=np.float32)
    p = m[..., 1] + 0.5 * m[..., 2]  # pignistic P(occ), eq. (13)
    out = np.full(m.shape[:-1], UNKNOWN, dtype=np.int8)
    known = m[..., 2] <= th.unknown_mass
    if covered is not None:
        known &= covered
    out[known & (p > th.occupied_thresh)] = OCCUPIED
    out[known & (p < th.free_thresh)] = FREE
    return out


def classify_map(
    m: EvidentialMap, r0: int, c0: int, h: int, w: int, th: Nav2Thresholds = Nav2Thresholds()
) -> np.ndarray:
    """:func:`classify` of map cells ``[r0:r0+h, c0:c0+w]``, tile by tile: one byte a cell in
    memory, never the masses of the whole box (tiles on disk are read one at a time)."""
    out = np.full((h, w), UNKNOWN, dtype=np.int8)
    for key, tr, tc, wr, wc in m.pieces(r0, c0, h, w):
        t = m.tiles.get(key)
        if t is not None:
            out[wr, wc] = classify(t[tr, tc], m.covered_tiles[key][tr, tc], th)
    return out


def _class_value_bounds(th: Nav2Thresholds) -> tuple[int, int]:
    """The largest OccupancyGrid value read as free and the smallest read as occupied.

    A consumer of an OccupancyGrid applies the thresholds to ``value / 100`` (map_server's rule
    with ``p = value / 100``): free if below ``free_thresh``, occupied if above
    ``occupied_thresh``. Rounding ``100 P(occ)`` alone would put a cell with P just above 0.65
    at 65, read back as not occupied; clamping each class into its own range keeps every value
    in agreement with its class.
    """
    free_max = math.ceil(100.0 * th.free_thresh)
    while free_max > 0 and not free_max / 100.0 < th.free_thresh:
        free_max -= 1
    occ_min = math.floor(100.0 * th.occupied_thresh)
    while occ_min < 100 and not occ_min / 100.0 > th.occupied_thresh:
        occ_min += 1
    return free_max, occ_min


#: How OccupancyGrid values are made (:func:`occupancy_values`).
OCCUPANCY_VALUES = ("trinary", "scale")


def occupancy_values(
    masses: np.ndarray,
    covered: np.ndarray | None = None,
    th: Nav2Thresholds = Nav2Thresholds(),
    mode: str = "trinary",
) -> np.ndarray:
    """``nav_msgs/OccupancyGrid`` values (int8) of masses ``(..., 3)``, agreeing with
    :func:`classify` at the thresholds.

    ``trinary``: 0 free, 100 occupied, -1 unknown, the values map_server publishes for the
    nav2 export's trinary map. ``scale``: ``round(100 P(occ))`` (confidence by shade), clamped
    into each class's range, so that ``value / 100`` against the same thresholds gives back the
    class (free at most ``ceil(100 free_thresh) - 1``, occupied at least
    ``floor(100 occupied_thresh) + 1``); unknown -1.
    """
    if mode not in OCCUPANCY_VALUES:
        raise ValueError(f"occupancy values must be one of {OCCUPANCY_VALUES}, got {mode!r}")
    m = np.asarray(masses, dtype=np.float32)
    cls = classify(m, covered, th)
    if mode == "trinary":
        return cls
    free_max, occ_min = _class_value_bounds(th)
    val = np.clip(np.rint(100.0 * (m[..., 1] + 0.5 * m[..., 2])), 0, 100).astype(np.int8)
    val = np.where(cls == FREE, np.minimum(val, free_max), val)
    val = np.where(cls == OCCUPIED, np.maximum(val, occ_min), val)
    val[cls == UNKNOWN] = UNKNOWN
    return val.astype(np.int8)


def map_to_occupancy(
    masses: np.ndarray, r0: int, c0: int, resolution: float
) -> tuple[np.ndarray, tuple[float, float]]:
    """Re-index map-grid arrays ``a[R - r0, C - c0]`` in ROS order: ``out[j, i]`` with i along
    +x, j along +y.

    Returns the array and the map-frame (x, y) of the outer corner of its cell [0, 0]. evgrid's
    map rows grow towards -x and columns towards -y (:mod:`evgrid.geometry`), so both axes flip
    and swap.
    """
    a = np.asarray(masses)
    h, w = a.shape[:2]
    out = np.ascontiguousarray(np.swapaxes(a[::-1, ::-1], 0, 1))
    return out, (-(r0 + h) * resolution, -(c0 + w) * resolution)


def _read_pgm(path: Path) -> np.ndarray:
    data = Path(path).read_bytes()
    tokens, pos = [], 0
    while len(tokens) < 4:  # magic, width, height, maxval; '#' comments allowed between
        m = re.compile(rb"\s*(#[^\n]*\n\s*)*(\S+)").match(data, pos)
        if m is None:
            raise ValueError(f"{path}: not a PGM file")
        tokens.append(m.group(2))
        pos = m.end()
    if tokens[0] != b"P5" or int(tokens[3]) > 255:
        raise ValueError(
            f"{path}: only 8-bit binary PGM (P5) is read, got {tokens[0]!r} maxval {tokens[3]!r}"
        )
    w, h = int(tokens[1]), int(tokens[2])
    pos += 1  # one whitespace byte ends the header
    return np.frombuffer(data[pos : pos + w * h], dtype=np.uint8).reshape(h, w)


def nav2_files(
    m: EvidentialMap,
    stem: Path,
    th: Nav2Thresholds = Nav2Thresholds(),
    comments: Sequence[str] = (),
) -> dict[Path, bytes]:
    """The PGM and YAML of a map as bytes, keyed by their paths ``<stem>.pgm``, ``<stem>.yaml``.

    ``comments`` are extra ``#`` lines for the YAML (map_server reads only its keys).
    """
    refuse_empty({stem.name: m}, stem)
    r0, c0, h, w = m.covered_bounds()
    ox, oy = -(r0 + h) * m.grid.resolution, -(c0 + w) * m.grid.resolution  # map_to_occupancy's
    pgm, yml = stem.with_name(stem.name + ".pgm"), stem.with_name(stem.name + ".yaml")
    lines = [
        f"image: {pgm.name}",
        "mode: trinary",
        f"resolution: {m.grid.resolution!r}",
        f"origin: [{ox!r}, {oy!r}, 0.0]",
        "negate: 0",
        f"occupied_thresh: {th.occupied_thresh!r}",
        f"free_thresh: {th.free_thresh!r}",
        f"# evgrid: P(occ) = m_o + m_u/2; unknown where never observed or m_u > "
        f"{th.unknown_mass!r}",
        *(f"# {c}" for c in comments),
    ]
    return {
        pgm: partial(_write_pgm, m, (r0, c0, h, w), th),
        yml: ("\n".join(lines) + "\n").encode(),
    }


def _write_pgm(m: EvidentialMap, box: tuple[int, int, int, int], th: Nav2Thresholds, f) -> None:
    """The PGM of map cells ``box``, written in bands of image rows, one tile column of the map
    each, so that its memory does not grow with the map. Image rows run top-down (the first is
    the largest y, the map's column ``c0``); image row ``y``, pixel ``i`` is map cell
    ``(r0 + h - 1 - i, c0 + y)`` (:func:`map_to_occupancy`, flipped top-down)."""
    r0, c0, h, w = box
    f.write(f"P5\n{h} {w}\n255\n".encode())
    lut = np.zeros(256, np.uint8)
    for cls in (FREE, OCCUPIED, UNKNOWN):
        lut[np.array(cls, np.int8).view(np.uint8)] = PIXEL[cls]
    ts = m.tile_cells
    y = 0
    while y < w:
        b = min(w - y, ts - (c0 + y) % ts)  # to the end of this tile column
        band = classify_map(m, r0, c0 + y, h, b, th)  # (h, b)
        f.write(np.ascontiguousarray(lut[band.view(np.uint8)][::-1].T).tobytes())
        y += b


def write_nav2(
    m: EvidentialMap,
    path: str | os.PathLike,
    th: Nav2Thresholds = Nav2Thresholds(),
    overwrite: bool = False,
    comments: Sequence[str] = (),
) -> tuple[Path, Path]:
    """Write ``<path>.pgm`` and ``<path>.yaml`` (map_server's format) of the map's observed area.

    ``path`` is a file stem (a ``.pgm`` or ``.yaml`` suffix is dropped) or a folder, which gets
    ``map.pgm`` + ``map.yaml`` (map_saver's names). Existing files are refused unless
    ``overwrite``; both files are written under temporary names and renamed together.
    """
    stem = Path(path)
    if str(path).endswith(os.sep) or stem.is_dir():
        stem = stem / NAV2_STEM
    elif stem.suffix in (".yaml", ".pgm"):
        stem = stem.with_suffix("")
    pgm, yml = write_all(nav2_files(m, stem, th, comments), overwrite)
    return pgm, yml


def read_nav2(yaml_path: str | os.PathLike) -> tuple[np.ndarray, float, tuple[float, float, float]]:
    """Load a map as map_server does: (OccupancyGrid data ``(height, width)`` int8 rows
    bottom-up, resolution, origin).

    Implements the ``trinary`` and ``scale`` modes' rule for 8-bit grey images:
    ``p = (255 - v) / 255`` (``v / 255`` with ``negate``); occupied (100) if
    ``p > occupied_thresh``, free (0) if ``p < free_thresh``, else unknown (-1) in trinary mode
    or ``99 * (p - free) / (occ - free)`` in scale mode.
    """
    from evgrid.ros import require

    yaml = require("yaml")
    yaml_path = Path(yaml_path)
    d = yaml.safe_load(yaml_path.read_text())
    img = _read_pgm(yaml_path.parent / d["image"]).astype(np.float64)
    p = img / 255.0 if int(d.get("negate", 0)) else (255.0 - img) / 255.0
    occ_t, free_t = float(d["occupied_thresh"]), float(d["free_thresh"])
    mode = d.get("mode", "trinary")
    out = np.full(img.shape, UNKNOWN, dtype=np.int8)
    if mode == "scale":
        mid = (p >= free_t) & (p <= occ_t)
        out[mid] = np.rint(99.0 * (p[mid] - free_t) / (occ_t - free_t)).astype(np.int8)
    elif mode != "trinary":
        raise ValueError(f"{yaml_path}: mode {mode!r} is not read here (trinary or scale)")
    out[p > occ_t] = OCCUPIED
    out[p < free_t] = FREE
    origin = tuple(float(v) for v in d["origin"])
    if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
        raise ValueError(f"{yaml_path}: origin must be [x, y, yaw], got {d['origin']!r}")
    return out[::-1].copy(), float(d["resolution"]), origin  # OccupancyGrid rows run bottom-up


@dataclass(frozen=True)
class Nav2Params:
    """What the nav2 export writes.

    ``maps``: other maps written beside the navigation map, as ``NAME.pgm`` + ``NAME.yaml``.
    ``navigation``: the maps to look for, in order, for ``map.pgm`` + ``map.yaml`` (the
    navigation map ``nav`` when the map set has it, else ``fused``: radar-only rigs, with a
    note in the YAML and the log; else the lidar map, for runs that asked for neither).
    ``map_frame`` / ``fixed_frame`` name the frames in the YAML's comment (the map frame and
    the recording's fixed frame, e.g. the rig's ``world_frame``).
    """

    maps: tuple[str, ...] = ()
    navigation: tuple[str, ...] = ("nav", "fused", "ray_ilm")
    thresholds: Nav2Thresholds = Nav2Thresholds()
    map_frame: str = "map"
    fixed_frame: str = "odom"

    def __post_init__(self) -> None:
        for key in ("maps", "navigation"):
            v = getattr(self, key)
            if isinstance(v, str) or not all(isinstance(n, str) and n for n in v):
                raise ValueError(f"Nav2Params.{key} must be a tuple of map names, got {v!r}")
            object.__setattr__(self, key, tuple(v))
        if not self.navigation:
            raise ValueError("Nav2Params.navigation must name at least one map")
        if not isinstance(self.thresholds, Nav2Thresholds):
            raise ValueError(
                f"Nav2Params.thresholds must be Nav2Thresholds, got {self.thresholds!r}"
            )


class Nav2Exporter:
    """Observer that writes the final navigation map as ``<folder>/map.pgm`` + ``map.yaml``
    (map_saver's names) and the maps of ``params.maps`` as ``<folder>/NAME.pgm`` + ``.yaml``,
    at :meth:`close`.

    The folder is created or written into; existing files are refused unless ``overwrite``
    (checked at the start, so a long run does not fail at its end, and again when writing).
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        params: Nav2Params = Nav2Params(),
        overwrite: bool = False,
    ):
        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise NotADirectoryError(
                errno.ENOTDIR, f"{self.folder}: the nav2 export needs a folder", str(self.folder)
            )
        self.params = params
        self.overwrite = overwrite
        refuse_existing(
            [
                self.folder / f"{n}{ext}"
                for n in (NAV2_STEM, *params.maps)
                for ext in (".pgm", ".yaml")
            ],
            overwrite,
        )
        self._maps: dict[str, EvidentialMap] = {}
        self.placement: MapPlacement | None = None
        self.navigation: str | None = None  # the map written as map.*

    def on_update(self, update) -> None:
        maps = update.maps.maps
        if self.placement is None:
            missing = [n for n in self.params.maps if n not in maps]
            if missing:
                raise ValueError(
                    f"nav2 export: no map {missing} in this run; it has {sorted(maps)}"
                )
            found = [n for n in self.params.navigation if n in maps]
            if not found:
                raise ValueError(
                    f"nav2 export: none of the navigation maps {list(self.params.navigation)} "
                    f"is in this run (it has {sorted(maps)})"
                )
            self.navigation = found[0]
            if self.navigation != self.params.navigation[0]:
                log.info(
                    "nav2 export: map.pgm is the %s map (no %s map in this run: a radar-only "
                    "rig); see docs/ros.md for its limits",
                    self.navigation,
                    self.params.navigation[0],
                )
            self.placement = MapPlacement.from_update(
                update, self.params.map_frame, self.params.fixed_frame
            )
        self._maps = maps

    def _comments(self, name: str) -> list[str]:
        notes = self.placement.comments() if self.placement else []
        if name == self.navigation and name != self.params.navigation[0]:
            why = (
                "e.g. a radar-only rig; radar free space can pass through walls"
                if name == "fused"
                else "the maps of this run were chosen without it"
            )
            notes.insert(
                0,
                f"the navigation map: '{name}' (this run has no '{self.params.navigation[0]}' "
                f"map: {why})",
            )
        elif name == self.navigation:
            notes.insert(0, f"the navigation map: '{name}'")
        return notes

    def abort(self) -> None:
        """Drop the run's maps: nothing is written (the files are written only at
        :meth:`close`, all of them or none)."""
        self._maps = {}
        self.navigation = None

    def close(self) -> list[Path]:
        """Write the maps; returns the files written (none if no update came)."""
        if self.navigation is None:
            return []
        files: dict[Path, bytes] = {}
        for stem, name in ((NAV2_STEM, self.navigation), *((n, n) for n in self.params.maps)):
            files.update(
                nav2_files(
                    self._maps[name],
                    self.folder / stem,
                    self.params.thresholds,
                    self._comments(name),
                )
            )
        return write_all(files, self.overwrite)
