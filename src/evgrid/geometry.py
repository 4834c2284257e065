"""Frames, grid indexing and rigid poses: every convention of evgrid is defined here, once.

Frames
    The ego frame is the nuScenes one: origin at the rear axle on the ground, x forward,
    y left, z up, metres. Sensor frames are given by a ``sensor_to_ego`` pose; the global
    frame by the ``ego_pose`` (ego -> global) of each timestamp.

Local grid (one ISM output)
    ``GridSpec(n_cells, length_m)``: a square of ``n_cells x n_cells`` cells covering
    ``length_m x length_m`` metres centred on the ego origin. An array ``a[row, col]`` is
    the bird's-eye view seen from above with the vehicle heading *up*:

    * row 0 is the front edge (largest x), rows grow backwards (towards -x);
    * column 0 is the left edge (largest y), columns grow to the right (towards -y);
    * cell ``(r, c)`` has its centre at ``x = (n/2 - r - 0.5) * res``,
      ``y = (n/2 - c - 0.5) * res`` with ``res = length_m / n_cells`` metres.

    Continuous indices ``(u, v)`` put cell centres at integers: ``u = n/2 - 0.5 - x/res``.

Map grid (the first pose's frame)
    The same orientation and resolution, unbounded integer indices ``(R, C)`` with the cell
    centre at ``x = -(R + 0.5) * res``, ``y = -(C + 0.5) * res`` in the frame of the first
    ego pose. A local grid at the identity pose lies exactly on map cells
    ``R = r - n/2``, ``C = c - n/2``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from evgrid.validation import check_int, check_number

#: Poses farther than this (m) from the map frame's origin are refused: real fixed frames such
#: as UTM reach 1e7 m, and beyond 1e8 m float64 positions lose the grid's resolution.
MAX_POSE_M = 1e8

__all__ = ["GridSpec", "SE2", "SE3", "quaternion_to_matrix", "matrix_to_quaternion"]


@dataclass(frozen=True, slots=True)
class GridSpec:
    """A square local grid: ``n_cells`` cells a side over ``length_m`` metres, ego at the centre."""

    n_cells: int = 512
    length_m: float = 40.0

    def __post_init__(self) -> None:
        if check_int(self, "n_cells", min=2) % 2:
            raise ValueError(
                "GridSpec.n_cells must be even (the ego vehicle sits on a cell corner), "
                f"got {self.n_cells!r}"
            )
        check_number(self, "length_m", min=0.0, min_open=True)

    @property
    def resolution(self) -> float:
        """Cell edge length in metres (0.078125 m for the default 512 cells over 40 m)."""
        return self.length_m / self.n_cells

    @property
    def shape(self) -> tuple[int, int]:
        """Array shape ``(rows, cols)`` of a local grid."""
        return (self.n_cells, self.n_cells)

    @property
    def half_extent(self) -> float:
        """Distance in metres from the ego origin to the grid's edge along x or y."""
        return self.length_m / 2.0

    # --- local grid <-> ego-frame metres ---------------------------------------------------
    def xy_to_uv(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ego-frame metres -> continuous local indices (row u, col v); cell centres at integers."""
        c0 = self.n_cells / 2.0 - 0.5
        res = self.resolution
        return c0 - np.asarray(x) / res, c0 - np.asarray(y) / res

    def xy_to_cell(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ego-frame metres -> integer local (row, col) of the containing cell (may be outside)."""
        # The same expression as every compiled kernel: floor(n/2 - x * (1/res)).
        half = self.n_cells / 2.0
        inv_res = 1.0 / self.resolution
        rows = np.floor(half - np.asarray(x, dtype=np.float64) * inv_res).astype(np.int64)
        cols = np.floor(half - np.asarray(y, dtype=np.float64) * inv_res).astype(np.int64)
        return rows, cols

    def cell_to_xy(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Local (row, col) -> ego-frame metres of the cell centre."""
        c0 = self.n_cells / 2.0 - 0.5
        res = self.resolution
        return (c0 - np.asarray(rows, dtype=np.float64)) * res, (
            c0 - np.asarray(cols, dtype=np.float64)
        ) * res

    def contains_cell(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Boolean mask of local (row, col) indices that lie inside the grid."""
        n = self.n_cells
        rows = np.asarray(rows)
        cols = np.asarray(cols)
        return (rows >= 0) & (rows < n) & (cols >= 0) & (cols < n)

    # --- map grid <-> first-pose-frame metres ----------------------------------------------
    def map_cell_to_xy(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map (R, C) -> metres of the cell centre in the first pose's frame."""
        res = self.resolution
        return -(np.asarray(rows, dtype=np.float64) + 0.5) * res, -(
            np.asarray(cols, dtype=np.float64) + 0.5
        ) * res

    def map_xy_to_cell(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Metres in the first pose's frame -> integer map (R, C) of the containing cell."""
        res = self.resolution
        rows = np.floor(-np.asarray(x, dtype=np.float64) / res).astype(np.int64)
        cols = np.floor(-np.asarray(y, dtype=np.float64) / res).astype(np.int64)
        return rows, cols

    def to_dict(self) -> dict[str, float | int]:
        """Plain-JSON form (evgrid.serial, the serialiser of every parameter dataclass)."""
        from evgrid.serial import to_dict

        return to_dict(self)

    @classmethod
    def from_dict(cls, d: dict) -> GridSpec:
        """Inverse of :meth:`to_dict`; a missing or bad field is a ValueError naming it."""
        from evgrid.serial import from_dict

        return from_dict(cls, d, "GridSpec", required=("n_cells", "length_m"))


def quaternion_to_matrix(q: Sequence[float]) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` (the nuScenes order) -> 3x3 rotation matrix."""
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(n) or n < 1e-12:
        raise ValueError(f"quaternion must be finite and non-zero, got {list(q)!r}")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix -> unit quaternion ``[w, x, y, z]`` with ``w >= 0``."""
    r = np.asarray(r, dtype=np.float64)
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return -q if q[0] < 0 else q


@dataclass(frozen=True, slots=True)
class SE2:
    """A planar rigid transform: rotate by ``yaw`` (rad, counter-clockwise) then translate (m)."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.x, self.y, self.yaw)):
            raise ValueError(
                f"SE2 needs finite x, y, yaw, got ({self.x!r}, {self.y!r}, {self.yaw!r})"
            )

    @classmethod
    def _unchecked(cls, x: float, y: float, yaw: float) -> SE2:
        # Poses computed from valid poses are valid: the hot path skips __post_init__.
        p = object.__new__(cls)
        object.__setattr__(p, "x", x)
        object.__setattr__(p, "y", y)
        object.__setattr__(p, "yaw", yaw)
        return p

    def matrix(self) -> np.ndarray:
        """3x3 homogeneous matrix."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, self.x], [s, c, self.y], [0.0, 0.0, 1.0]])

    def __matmul__(self, other: SE2) -> SE2:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return SE2._unchecked(
            self.x + c * other.x - s * other.y,
            self.y + s * other.x + c * other.y,
            math.remainder(self.yaw + other.yaw, 2 * math.pi),
        )

    def inverse(self) -> SE2:
        """The transform that undoes this one."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return SE2._unchecked(-(c * self.x + s * self.y), -(-s * self.x + c * self.y), -self.yaw)

    def apply(self, xy: np.ndarray) -> np.ndarray:
        """Transform ``(n, 2)`` points in metres."""
        xy = np.asarray(xy, dtype=np.float64)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        out = np.empty_like(xy)
        out[..., 0] = c * xy[..., 0] - s * xy[..., 1] + self.x
        out[..., 1] = s * xy[..., 0] + c * xy[..., 1] + self.y
        return out


_HOMOGENEOUS = np.eye(4)
_HOMOGENEOUS.flags.writeable = False


@dataclass(frozen=True, slots=True, eq=False)
class SE3:
    """A rigid transform ``p' = R p + t`` (metres); as ``sensor_to_ego`` or ``ego_pose`` (ego ->
    global).

    The constructor validates (user data comes in here); poses composed from valid poses
    (``@``, :meth:`inverse`, :meth:`identity`, :meth:`from_se2`) are built unchecked, as a
    mapping update composes tens of them.
    """

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=np.float64)
        t = np.asarray(self.translation, dtype=np.float64).reshape(-1)
        if r.shape != (3, 3) or t.shape != (3,):
            raise ValueError(
                f"SE3 needs a 3x3 rotation and a 3-vector, got {r.shape} and {t.shape}"
            )
        if not (np.isfinite(r).all() and np.isfinite(t).all()):
            raise ValueError("SE3 rotation and translation must be finite")
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-6):
            raise ValueError("SE3 rotation is not orthonormal")
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)

    @classmethod
    def _unchecked(cls, rotation: np.ndarray, translation: np.ndarray) -> SE3:
        # float64 arrays of shapes (3, 3) and (3,) computed from valid poses
        p = object.__new__(cls)
        object.__setattr__(p, "rotation", rotation)
        object.__setattr__(p, "translation", translation)
        return p

    @classmethod
    def identity(cls) -> SE3:
        """The identity transform."""
        return cls._unchecked(np.eye(3), np.zeros(3))

    @classmethod
    def from_quaternion(cls, q_wxyz: Sequence[float], t: Sequence[float]) -> SE3:
        """From a nuScenes-style ``rotation`` ``[w, x, y, z]`` and ``translation`` (m)."""
        return cls(quaternion_to_matrix(q_wxyz), np.asarray(t, dtype=np.float64))

    @classmethod
    def from_se2(cls, p: SE2, z: float = 0.0) -> SE3:
        """Lift a planar pose to 3-D at height ``z`` metres."""
        if not math.isfinite(z):
            raise ValueError(f"SE3.from_se2 needs a finite height z, got {z!r}")
        c, s = math.cos(p.yaw), math.sin(p.yaw)
        return cls._unchecked(
            np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.array([p.x, p.y, float(z)])
        )

    @classmethod
    def from_matrix(cls, m: np.ndarray) -> SE3:
        """From a 4x4 homogeneous matrix."""
        m = np.asarray(m, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"SE3.from_matrix needs a 4x4 matrix, got {m.shape}")
        return cls(m[:3, :3], m[:3, 3])

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix."""
        m = _HOMOGENEOUS.copy()  # cheaper than np.eye, called per sweep on the hot path
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m

    def quaternion(self) -> np.ndarray:
        """Rotation as ``[w, x, y, z]``."""
        return matrix_to_quaternion(self.rotation)

    def __matmul__(self, other: SE3) -> SE3:
        if not isinstance(other, SE3):
            return NotImplemented
        return SE3._unchecked(
            self.rotation @ other.rotation, self.rotation @ other.translation + self.translation
        )

    def inverse(self) -> SE3:
        """The transform that undoes this one."""
        rt = self.rotation.T
        return SE3._unchecked(rt, -(rt @ self.translation))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform ``(n, 3)`` points (float64 out)."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.rotation.T + self.translation

    @property
    def yaw(self) -> float:
        """Heading in radians: the angle of the rotated x axis in the xy plane."""
        return math.atan2(self.rotation[1, 0], self.rotation[0, 0])

    def to_se2(self) -> SE2:
        """The planar part (x, y, yaw) that drives the 2-D map warp."""
        return SE2._unchecked(float(self.translation[0]), float(self.translation[1]), self.yaw)

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, SE3)
            and np.array_equal(self.rotation, other.rotation)
            and np.array_equal(self.translation, other.translation)
        )

    def __repr__(self) -> str:
        t = ", ".join(f"{v:.3f}" for v in self.translation)
        return f"SE3(t=[{t}], yaw={math.degrees(self.yaw):.2f} deg)"
