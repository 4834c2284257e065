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
largest y); ``origin`` is the map-frame pose of the lower-left pixel's outer corner. The map
frame is the first ego pose's (x forward, y left).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evgrid.grid import EvidentialMap
from evgrid.validation import check_number

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
]

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
    """Masses ``(..., 3)`` -> int8 classes FREE / OCCUPIED / UNKNOWN (see the module's docstring)."""
    m = np.asarray(masses, dtype=np.float32)
    p = m[..., 1] + 0.5 * m[..., 2]  # pignistic P(occ), eq. (13)
    out = np.full(m.shape[:-1], UNKNOWN, dtype=np.int8)
    known = m[..., 2] <= th.unknown_mass
    if covered is not None:
        known &= covered
    out[known & (p > th.occupied_thresh)] = OCCUPIED
    out[known & (p < th.free_thresh)] = FREE
    return out


def map_to_occupancy(
    masses: np.ndarray, r0: int, c0: int, resolution: float
) -> tuple[np.ndarray, tuple[float, float]]:
    """Re-index map-grid arrays ``a[R - r0, C - c0]`` in ROS order: ``out[j, i]`` with i along +x, j along +y.

    Returns the array and the map-frame (x, y) of the outer corner of its cell [0, 0]. evgrid's
    map rows grow towards -x and columns towards -y (:mod:`evgrid.geometry`), so both axes flip
    and swap.
    """
    a = np.asarray(masses)
    h, w = a.shape[:2]
    out = np.ascontiguousarray(np.swapaxes(a[::-1, ::-1], 0, 1))
    return out, (-(r0 + h) * resolution, -(c0 + w) * resolution)


def _write_pgm(path: Path, img: np.ndarray) -> None:
    h, w = img.shape
    with open(path, "wb") as f:
        f.write(f"P5\n{w} {h}\n255\n".encode())
        f.write(np.ascontiguousarray(img, dtype=np.uint8).tobytes())


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


def write_nav2(
    m: EvidentialMap, path: str | os.PathLike, th: Nav2Thresholds = Nav2Thresholds()
) -> tuple[Path, Path]:
    """Write ``<path>.pgm`` and ``<path>.yaml`` (map_server's format) of the map's observed area."""
    path = Path(path)
    stem = path.with_suffix("") if path.suffix in (".yaml", ".pgm") else path
    r0, c0, h, w = m.covered_bounds()
    if h == 0:
        raise ValueError("the map has no observed cell; nothing to export")
    masses, cov = m.read(r0, c0, h, w)
    cls, (ox, oy) = map_to_occupancy(classify(masses, cov, th), r0, c0, m.grid.resolution)
    img = np.vectorize(PIXEL.get, otypes=[np.uint8])(cls[::-1])  # image rows top-down
    pgm, yml = stem.with_suffix(".pgm"), stem.with_suffix(".yaml")
    pgm.parent.mkdir(parents=True, exist_ok=True)
    _write_pgm(pgm, img)
    yml.write_text(
        f"image: {pgm.name}\nmode: trinary\nresolution: {m.grid.resolution!r}\norigin: [{ox!r}, {oy!r}, 0.0]\n"
        f"negate: 0\noccupied_thresh: {th.occupied_thresh!r}\nfree_thresh: {th.free_thresh!r}\n"
        "# evgrid: P(occ) = m_o + m_u/2; unknown where never observed or m_u > "
        f"{th.unknown_mass!r}; map frame = the first ego pose\n"
    )
    return pgm, yml


def read_nav2(yaml_path: str | os.PathLike) -> tuple[np.ndarray, float, tuple[float, float, float]]:
    """Load a map as map_server does: (OccupancyGrid data ``(height, width)`` int8 rows bottom-up, resolution, origin).

    Implements the ``trinary`` and ``scale`` modes' rule for 8-bit grey images: ``p = (255 - v) / 255``
    (``v / 255`` with ``negate``); occupied (100) if ``p > occupied_thresh``, free (0) if
    ``p < free_thresh``, else unknown (-1) in trinary mode or ``99 * (p - free) / (occ - free)``
    in scale mode.
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


class Nav2Exporter:
    """Observer that writes each final map as ``<folder>/<NAME>.pgm`` + ``.yaml`` at :meth:`close`."""

    def __init__(
        self,
        folder: str | os.PathLike,
        maps: tuple[str, ...] | None = None,
        thresholds: Nav2Thresholds = Nav2Thresholds(),
    ):
        self.folder = Path(folder)
        self.names = maps
        self.thresholds = thresholds
        self._maps: dict[str, EvidentialMap] = {}

    def on_update(self, update) -> None:
        self._maps = update.maps.maps

    def close(self) -> list[Path]:
        """Write the maps (those observed at all); returns the files written."""
        out: list[Path] = []
        for name, m in self._maps.items():
            if (self.names is None or name in self.names) and m.covered_bounds()[2]:
                out += write_nav2(m, self.folder / name, self.thresholds)
        return out
