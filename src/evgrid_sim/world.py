"""The procedural 2.5-D world: static boxes (buildings, walls, fences, vegetation, poles, parked
vehicles) and moving objects (vehicles, cyclists, pedestrians), built around the ego's route.

Everything is generated in a *city frame* (streets axis-aligned, the ego starting near the
origin) and then moved by one rigid transform into the *global frame* that poses are given in
(random orientation, coordinates in the hundreds of metres as in nuScenes).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from evgrid.geometry import SE2
from evgrid_sim import materials as M
from evgrid_sim.config import SimConfig
from evgrid_sim.raycast import GridIndex, pack_boxes
from evgrid_sim.trajectory import (
    LANE_OFFSET_M,
    Route,
    StreetGrid,
    Trajectory,
    Warp,
    _dense_path,
    build_trajectory,
    make_street_grid,
    plan_route,
)

__all__ = [
    "World",
    "Movers",
    "TownLayout",
    "generate_world",
    "plan_drive",
    "EGO_LENGTH_M",
    "EGO_WIDTH_M",
    "EGO_REAR_OVERHANG_M",
]

#: Ego vehicle footprint (a compact car; the pose is the rear axle centre, as in nuScenes).
EGO_LENGTH_M = 4.1
EGO_WIDTH_M = 1.8
EGO_REAR_OVERHANG_M = 0.7
#: Blocks and streets farther than this from the driven path are left empty (sensors reach
#: about 100 m; the maps only 20 m), metres.
_POPULATE_RADIUS_M = 110.0
#: Longest side of a static box before an irregular town's warp bends it, metres.
_PIECE_M = 10.0
#: Share of the blocks near the route given over to open squares, parking lots and parks
#: (irregular towns; urban, suburban).
_BLOCK_USE = {"urban": (0.07, 0.07, 0.06), "suburban": (0.03, 0.04, 0.12)}
#: Probability of a roundabout at a junction near the route that the route does not cross.
_ROUNDABOUT_P = 0.15
#: Expected diagonal avenues per kilometre of route (at least one chance a scene).
_AVENUES_PER_KM = 0.6
#: Farthest an avenue is built from its junction, metres.
_AVENUE_REACH_M = 400.0


@dataclass(frozen=True, eq=False)
class Movers:
    """Moving objects. Linear movers: ``position(t) = p0 + u(heading) * speed * clip(t, t_begin,
    t_end)``; followers (``follow``) drive the ego's path at ``s_ego(t + follow_lead_s) +
    follow_gap``.

    With a ``warp`` (curved towns), linear movers drive straight in the unwarped city frame and
    are bent by the warp (heading and velocity by its Jacobian), then moved by ``frame``."""

    classes: np.ndarray
    half_length: np.ndarray
    half_width: np.ndarray
    z_min: np.ndarray
    z_max: np.ndarray
    p0: np.ndarray
    heading: np.ndarray
    speed: np.ndarray
    t_begin: np.ndarray
    t_end: np.ndarray
    follow: np.ndarray
    follow_gap: np.ndarray
    follow_lead_s: np.ndarray
    warp: Warp | None = None
    #: city frame -> this frame, applied after the warp (only used with a warp).
    frame: SE2 = field(default_factory=SE2)

    def __len__(self) -> int:
        return int(self.classes.shape[0])

    @staticmethod
    def empty() -> Movers:
        """No moving objects."""
        z = np.zeros(0)
        return Movers(
            np.zeros(0, np.int32), z, z, z, z, np.zeros((0, 2)), z, z, z, z, np.zeros(0, bool), z, z
        )

    def state_at(self, t: float, traj: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Packed boxes (m, 8), velocities (m, 2) in m/s, and yaw (m,) of all movers at ``t``
        seconds."""
        m = len(self)
        tc = np.clip(t, self.t_begin, self.t_end)
        ux, uy = np.cos(self.heading), np.sin(self.heading)
        x = self.p0[:, 0] + ux * self.speed * tc
        y = self.p0[:, 1] + uy * self.speed * tc
        yaw = self.heading.copy()
        moving = (t >= self.t_begin) & (t < self.t_end)
        vx = np.where(moving, ux * self.speed, 0.0)
        vy = np.where(moving, uy * self.speed, 0.0)
        if self.warp is not None and m:
            a, b = self.warp.jacobian(x, y)
            yaw, _ = self.warp.direction(x, y, yaw)
            x, y = self.warp.apply(x, y)
            vx, vy = vx + a * vy, b * vx + vy
            c, s_ = math.cos(self.frame.yaw), math.sin(self.frame.yaw)
            x, y = self.frame.x + c * x - s_ * y, self.frame.y + s_ * x + c * y
            vx, vy = c * vx - s_ * vy, s_ * vx + c * vy
            yaw = yaw + self.frame.yaw
        if self.follow.any():
            f = np.nonzero(self.follow)[0]
            tf = t + self.follow_lead_s[f]
            s = traj.s_at(tf) + self.follow_gap[f]
            fx, fy, fyaw = traj.pose_at_s(s)
            x[f], y[f], yaw[f] = fx, fy, fyaw
            # Along the follower's own heading: the path turns between the ego's arc length
            # and the follower's (in a corner, or anywhere in a curved town).
            v = traj.speed_at(tf)
            fvx, fvy = v * np.cos(fyaw), v * np.sin(fyaw)
            vx[f], vy[f] = fvx, fvy
        boxes = (
            pack_boxes(x, y, yaw, self.half_length, self.half_width, self.z_min, self.z_max)
            if m
            else np.zeros((0, 8))
        )
        return boxes, np.stack([vx, vy], axis=1) if m else np.zeros((0, 2)), yaw

    def transformed(self, tf: SE2) -> Movers:
        """The same movers in the frame ``tf`` maps to."""
        if self.warp is not None:
            return replace(self, frame=tf @ self.frame)
        p0 = tf.apply(self.p0) if len(self) else self.p0
        return replace(self, p0=p0, heading=self.heading + tf.yaw)


@dataclass(frozen=True, eq=False)
class TownLayout:
    """The features of an irregular town, in the unwarped city frame (the warp bends them all)."""

    warp: Warp | None
    # : Diagonal avenues through a grid junction: (x, y, direction rad, half width m, curb to
    # property line m).
    avenues: list[tuple[float, float, float, float, float]] = field(default_factory=list)
    #: Blocks given over to open squares, parking lots and parks: (x0, y0, x1, y1) each, metres.
    squares: list[tuple[float, float, float, float]] = field(default_factory=list)
    parking_lots: list[tuple[float, float, float, float]] = field(default_factory=list)
    parks: list[tuple[float, float, float, float]] = field(default_factory=list)
    #: Roundabouts at junctions the ego route does not cross: (x, y, island radius m).
    roundabouts: list[tuple[float, float, float]] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        """Number of each feature."""
        return {
            k: len(getattr(self, k))
            for k in ("avenues", "squares", "parking_lots", "parks", "roundabouts")
        }


@dataclass(frozen=True, eq=False)
class World:
    """Static boxes (global frame, packed ``(n, 8)``, see ``raycast.BOX_COLUMNS``), their classes,
    per-object material variation, and the moving objects."""

    environment: str
    boxes: np.ndarray
    yaw: np.ndarray
    classes: np.ndarray
    #: Lidar reflectivity of each static box (class value with per-object variation).
    reflectivity: np.ndarray
    #: Radar RCS offset of each static box, dB.
    rcs_offset_db: np.ndarray
    movers: Movers
    mover_reflectivity: np.ndarray
    mover_rcs_offset_db: np.ndarray
    streets: StreetGrid
    #: city frame -> global frame
    city_to_global: SE2
    #: What the town holds (irregular layouts; None for the plain grid).
    layout: TownLayout | None = None
    index: GridIndex = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "index", GridIndex(self.boxes))

    @classmethod
    def from_boxes(cls, static: list[tuple], movers: Movers | None = None) -> World:
        """A hand-made world (tests, examples): boxes ``(cx, cy, yaw, length, width, z0, z1,
        class)`` in the global frame (m, rad), class materials without per-object variation, and
        ``movers`` (default none)."""
        a = np.array([s[:7] for s in static], dtype=np.float64).reshape(-1, 7)
        boxes = pack_boxes(a[:, 0], a[:, 1], a[:, 2], a[:, 3] / 2, a[:, 4] / 2, a[:, 5], a[:, 6])
        classes = np.array([s[7] for s in static], dtype=np.int32)
        mv = movers if movers is not None else Movers.empty()
        return cls(
            "urban",
            boxes,
            a[:, 2],
            classes,
            M.LIDAR_REFLECTIVITY[classes],
            np.zeros(len(classes)),
            mv,
            M.LIDAR_REFLECTIVITY[mv.classes],
            np.zeros(len(mv)),
            None,
            SE2(),
        )

    @property
    def n_static(self) -> int:
        """Number of static boxes."""
        return int(self.boxes.shape[0])

    def cast_scene(self, dyn_boxes: np.ndarray, dyn_classes: np.ndarray) -> tuple:
        """What the ray casting kernels (``raycast.lidar_cast``, ``radar_cast``) see: the static
        boxes, their classes and grid index, then the moving boxes and their classes."""
        idx = self.index
        return (
            self.boxes,
            self.classes,
            idx.start,
            idx.items,
            idx.x0,
            idx.y0,
            idx.cell,
            idx.nx,
            idx.ny,
            dyn_boxes,
            dyn_classes.astype(np.int32),
        )

    def describe(self) -> dict[str, int]:
        """Counts of static boxes and moving objects by class name."""
        out: dict[str, int] = {}
        for k, name in enumerate(M.CLASS_NAMES):
            n = int((self.classes == k).sum())
            if n:
                out[name] = n
        for k, name in enumerate(M.CLASS_NAMES):
            n = int((self.movers.classes == k).sum())
            if n:
                out["moving_" + name] = n
        return out


class _Builder:
    """Collects boxes in the city frame."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, float, float, float, float, float, float, int]] = []

    def add(
        self,
        cx: float,
        cy: float,
        yaw: float,
        hl: float,
        hw: float,
        z0: float,
        z1: float,
        klass: int,
    ) -> None:
        if hl > 0.01 and hw > 0.01 and z1 > z0:
            self.rows.append((cx, cy, yaw, hl, hw, z0, z1, klass))


@dataclass
class _Side:
    """One side of a block, facing a street: u along the side (0..length), v into the block
    (v = 0 the property line, v = -sidewalk the curb)."""

    origin: np.ndarray
    t: np.ndarray
    n: np.ndarray
    length: float
    depth: float
    sidewalk: float
    half_width: float
    parking: bool

    @property
    def yaw(self) -> float:
        return math.atan2(self.t[1], self.t[0])

    def point(self, u: float, v: float) -> np.ndarray:
        return self.origin + u * self.t + v * self.n

    def box(
        self,
        b: _Builder,
        u0: float,
        u1: float,
        v0: float,
        v1: float,
        z0: float,
        z1: float,
        klass: int,
        dyaw: float = 0.0,
    ) -> None:
        p = self.point(0.5 * (u0 + u1), 0.5 * (v0 + v1))
        b.add(
            float(p[0]),
            float(p[1]),
            self.yaw + dyaw,
            0.5 * abs(u1 - u0),
            0.5 * abs(v1 - v0),
            z0,
            z1,
            klass,
        )


def _vehicle_dims(rng: np.random.Generator, moving: bool) -> tuple[int, float, float, float, float]:
    """(class, length, width, z_min, z_max) of a random vehicle, metres."""
    r = rng.random()
    if r < 0.85:
        return M.CAR, rng.uniform(3.9, 4.9), rng.uniform(1.7, 1.95), 0.15, rng.uniform(1.4, 1.75)
    if r < 0.96 or not moving:
        return M.TRUCK, rng.uniform(5.2, 7.5), rng.uniform(2.0, 2.4), 0.3, rng.uniform(2.2, 3.1)
    return M.TRUCK, rng.uniform(10.5, 12.0), 2.5, 0.35, 3.2


def _tree(
    b: _Builder, rng: np.random.Generator, p: np.ndarray, street: bool, big: bool = False
) -> None:
    trunk = rng.uniform(0.25, 0.45)
    base = rng.uniform(3.0, 4.2) if street else rng.uniform(1.8, 3.2)
    top = base + rng.uniform(3.0, 6.0 if big else 4.5)
    side = rng.uniform(3.0, 6.5 if big else 5.0)
    b.add(
        float(p[0]),
        float(p[1]),
        rng.uniform(0, np.pi),
        0.5 * trunk,
        0.5 * trunk,
        0.0,
        base + 0.5,
        M.TRUNK,
    )
    b.add(
        float(p[0]),
        float(p[1]),
        rng.uniform(0, np.pi),
        0.5 * side,
        0.5 * side * rng.uniform(0.8, 1.0),
        base,
        top,
        M.CANOPY,
    )


def _parked_cars(b: _Builder, rng: np.random.Generator, side: _Side, empty_p: float) -> None:
    u = rng.uniform(7.0, 12.0)
    v_c = -side.sidewalk - 1.15
    while u < side.length - 9.0:
        if rng.random() < empty_p:
            u += rng.uniform(5.0, 20.0)
            continue
        k, length, width, z0, z1 = _vehicle_dims(rng, moving=False)
        if u + length > side.length - 7.0:
            break
        v = v_c + rng.uniform(-0.15, 0.15)
        side.box(
            b, u, u + length, v - width / 2, v + width / 2, z0, z1, k, dyaw=rng.normal(0, 0.03)
        )
        u += length + rng.uniform(0.6, 2.5)


def _street_furniture(
    b: _Builder, rng: np.random.Generator, side: _Side, urban: bool, density: float
) -> None:
    sw, L = side.sidewalk, side.length
    # Street lights at the curb.
    u = rng.uniform(5.0, 15.0)
    while u < L - 4.0:
        side.box(b, u - 0.12, u + 0.12, -sw + 0.25, -sw + 0.49, 0.0, rng.uniform(6.0, 8.5), M.POLE)
        u += rng.uniform(25.0, 35.0) if urban else rng.uniform(35.0, 50.0)
    # Trees in pits (urban) or in the grass strip (suburban).
    if rng.random() < (0.5 if urban else 0.65):
        u = rng.uniform(4.0, 10.0)
        while u < L - 4.0:
            _tree(b, rng, side.point(u, -sw + 0.9), street=True)
            u += rng.uniform(8.0, 14.0) if urban else rng.uniform(10.0, 20.0)
    # Sign poles with a plate on top.
    for _ in range(rng.poisson(L / (40.0 if urban else 80.0))):
        u = rng.uniform(4.0, max(L - 4.0, 4.5))
        side.box(b, u - 0.04, u + 0.04, -sw + 0.3, -sw + 0.38, 0.0, 2.6, M.POLE)
        side.box(b, u - 0.35, u + 0.35, -sw + 0.39, -sw + 0.43, 1.9, 2.6, M.POLE)
    if urban:
        # Bollards, bins, planters.
        for _ in range(rng.poisson(L / 45.0)):
            u = rng.uniform(4.0, max(L - 4.0, 4.5))
            s = rng.uniform(0.2, 0.7)
            side.box(
                b,
                u - s / 2,
                u + s / 2,
                -sw + 0.3,
                -sw + 0.3 + s,
                0.0,
                rng.uniform(0.8, 1.2),
                M.BARRIER,
            )
        # People standing at the curb (static).
        for _ in range(rng.poisson(density * L / 70.0)):
            u = rng.uniform(4.0, max(L - 4.0, 4.5))
            v = -sw + rng.uniform(1.2, 1.5)
            side.box(
                b, u - 0.25, u + 0.25, v - 0.3, v + 0.3, 0.0, rng.uniform(1.5, 1.9), M.PEDESTRIAN
            )


def _urban_side(
    b: _Builder, rng: np.random.Generator, side: _Side, density: float, irregular: bool = False
) -> None:
    max_depth = max(side.depth / 2.0 - 1.0, 8.0)
    if rng.random() < 0.12:
        _lot_behind_wall(b, rng, side, density, max_depth)
    else:
        _building_row(b, rng, side, max_depth, irregular)
    _street_furniture(b, rng, side, urban=True, density=density)
    if side.parking:
        _parked_cars(b, rng, side, empty_p=0.22 / max(density, 0.2))


def _lot_behind_wall(
    b: _Builder, rng: np.random.Generator, side: _Side, density: float, max_depth: float
) -> None:
    """A parking lot or plaza behind a low wall, trees, a row of parked cars, and (on a deep
    block) a building at the back."""
    L = side.length
    u = 0.0
    while u < L:
        seg = rng.uniform(6.0, 20.0)
        side.box(b, u, min(u + seg, L), 0.1, 0.4, 0.0, rng.uniform(0.8, 1.4), M.WALL)
        u += seg + rng.uniform(3.0, 6.0)
    for _ in range(rng.integers(2, 7)):
        _tree(
            b,
            rng,
            side.point(rng.uniform(3.0, L - 3.0), rng.uniform(3.0, min(max_depth, 20.0))),
            street=False,
            big=True,
        )
    v_row = rng.uniform(6.0, 10.0)
    u = 5.0
    while u < L - 5.0:
        if rng.random() < 0.7 * min(density, 1.3):
            k, length, width, z0, z1 = _vehicle_dims(rng, moving=False)
            side.box(b, u, u + width, v_row, v_row + length, z0, z1, k)
        u += rng.uniform(2.5, 3.2)
    if max_depth > 25.0:
        side.box(
            b,
            0.0,
            L,
            22.0,
            min(22.0 + rng.uniform(10.0, 20.0), max_depth),
            0.0,
            rng.uniform(8.0, 30.0),
            M.BUILDING,
        )


def _building_row(
    b: _Builder, rng: np.random.Generator, side: _Side, max_depth: float, irregular: bool
) -> None:
    """Buildings along the street, set back or not, with gaps closed by a wall or a fence."""
    L = side.length
    u = 0.0
    while u < L - 2.0:
        if rng.random() < 0.12:
            gap = rng.uniform(2.5, 7.0)
            if rng.random() < 0.5:
                klass = M.WALL if rng.random() < 0.5 else M.FENCE
                thick = 0.25 if klass == M.WALL else 0.06
                side.box(
                    b, u, min(u + gap, L), 0.05, 0.05 + thick, 0.0, rng.uniform(1.8, 3.0), klass
                )
            u += gap
            continue
        w = rng.uniform(8.0, 30.0)
        setback = (
            0.0
            if rng.random() < (0.45 if irregular else 0.7)
            else rng.uniform(0.5, 4.5 if irregular else 3.0)
        )
        depth = min(rng.uniform(12.0, 28.0), max_depth - setback)
        h = float(np.clip(rng.lognormal(math.log(14.0), 0.5), 5.0, 60.0))
        if irregular:
            _irregular_building(b, rng, side, u, min(u + w, L), setback, depth, h)
        else:
            side.box(b, u, min(u + w, L), setback, setback + depth, 0.0, h, M.BUILDING)
        u += w


def _irregular_building(
    b: _Builder,
    rng: np.random.Generator,
    side: _Side,
    u0: float,
    u1: float,
    v0: float,
    depth: float,
    h: float,
) -> None:
    """A building that is not one box: a courtyard block, a stepped facade, or a slightly skewed
    box."""
    w = u1 - u0
    r = rng.random()
    if r < 0.25 and w > 16.0 and depth > 15.0:
        # Courtyard: front wing, two side wings, back wing around an open yard.
        front, wing = rng.uniform(6.0, 9.0), rng.uniform(4.0, 6.0)
        side.box(b, u0, u1, v0, v0 + front, 0.0, h, M.BUILDING)
        side.box(b, u0, u0 + wing, v0 + front, v0 + depth, 0.0, h, M.BUILDING)
        side.box(b, u1 - wing, u1, v0 + front, v0 + depth, 0.0, h, M.BUILDING)
        side.box(
            b,
            u0 + wing,
            u1 - wing,
            v0 + depth - wing,
            v0 + depth,
            0.0,
            h * rng.uniform(0.6, 1.0),
            M.BUILDING,
        )
    elif r < 0.55 and w > 10.0:
        # Stepped: two parts of different setback, depth and height.
        cut = u0 + w * rng.uniform(0.35, 0.65)
        for a, c in ((u0, cut), (cut, u1)):
            v = v0 + rng.uniform(0.0, 2.5)
            side.box(
                b,
                a,
                c,
                v,
                v + depth * rng.uniform(0.6, 1.0),
                0.0,
                h * rng.uniform(0.6, 1.3),
                M.BUILDING,
            )
    else:
        # A box a little off the street's direction (kept behind the property line).
        dyaw = float(rng.normal(0.0, 0.04))
        lift = 0.5 * w * abs(math.sin(dyaw)) + 0.1
        side.box(b, u0, u1, v0 + lift, v0 + lift + depth, 0.0, h, M.BUILDING, dyaw=dyaw)


def _suburban_side(
    b: _Builder, rng: np.random.Generator, side: _Side, density: float, irregular: bool = False
) -> None:
    L = side.length
    u = rng.uniform(0.0, 5.0)
    while u < L - 10.0:
        lot = rng.uniform(16.0, 26.0)
        end = min(u + lot, L)
        lot = end - u
        setback, hw_, hd, uc = _house(b, rng, side, u, end, lot)
        drive = u + rng.uniform(1.0, max(lot - 5.0, 1.5))
        _lot_fences(b, rng, side, u, end, drive, setback, hd)
        if setback > 6.0 and rng.random() < 0.45 * min(density, 1.5):
            k, length, width, z0, z1 = _vehicle_dims(rng, moving=False)
            length = min(length, setback - 1.5)
            v0 = rng.uniform(0.8, setback - length - 0.5) if setback - length - 0.5 > 0.8 else 0.8
            side.box(
                b, drive + 1.75 - width / 2, drive + 1.75 + width / 2, v0, v0 + length, z0, z1, k
            )
        _garden(b, rng, side, u, end, lot, setback, hw_, hd, uc, irregular)
        u = end
    _street_furniture(b, rng, side, urban=False, density=density)
    if side.parking:
        _parked_cars(b, rng, side, empty_p=0.6 / max(density, 0.2))


def _house(
    b: _Builder, rng: np.random.Generator, side: _Side, u: float, end: float, lot: float
) -> tuple[float, float, float, float]:
    """A house set back on the lot from ``u`` to ``end`` (and sometimes a garage beside it);
    returns its setback, width, depth and start along the street."""
    setback = rng.uniform(5.0, 12.0)
    hw_ = min(rng.uniform(9.0, 15.0), lot - 3.0)
    hd = min(rng.uniform(8.0, 13.0), side.depth / 2.0 - setback - 2.0)
    uc = u + (lot - hw_) * rng.uniform(0.2, 0.8)
    if hw_ > 4.0 and hd > 4.0:
        side.box(b, uc, uc + hw_, setback, setback + hd, 0.0, rng.uniform(5.0, 8.5), M.BUILDING)
        if rng.random() < 0.3:  # garage
            g0 = uc + hw_ + 0.5
            if g0 + 4.0 < end:
                side.box(
                    b,
                    g0,
                    min(g0 + 6.0, end - 0.5),
                    setback + 1.0,
                    setback + 7.0,
                    0.0,
                    3.0,
                    M.BUILDING,
                )
    return setback, hw_, hd, uc


def _lot_fences(
    b: _Builder,
    rng: np.random.Generator,
    side: _Side,
    u: float,
    end: float,
    drive: float,
    setback: float,
    hd: float,
) -> None:
    """A hedge or a fence along the street on both sides of the drive, and sometimes a fence
    between this lot and the next."""
    r = rng.random()
    if r < 0.7:
        hedge = r >= 0.4
        thick = rng.uniform(0.6, 1.0) if hedge else 0.06
        height = rng.uniform(0.9, 1.8) if hedge else rng.uniform(0.9, 1.4)
        klass = M.HEDGE if hedge else M.FENCE
        for a, c in ((u + 0.3, drive), (drive + 3.5, end - 0.3)):
            if c - a > 0.5:
                side.box(b, a, c, 0.1, 0.1 + thick, 0.0, height, klass)
    if rng.random() < 0.4:
        side.box(
            b,
            end - 0.06,
            end,
            0.2,
            setback + hd + rng.uniform(3.0, 10.0),
            0.0,
            rng.uniform(1.5, 1.9),
            M.FENCE,
        )


def _garden(
    b: _Builder,
    rng: np.random.Generator,
    side: _Side,
    u: float,
    end: float,
    lot: float,
    setback: float,
    hw_: float,
    hd: float,
    uc: float,
    irregular: bool,
) -> None:
    """Trees in the front garden, bushes before the house, and (irregular towns) a cluster of
    trees in the back garden."""
    for _ in range(rng.poisson(1.2)):
        _tree(
            b,
            rng,
            side.point(rng.uniform(u + 2.0, end - 2.0), rng.uniform(1.5, max(setback - 1.0, 1.6))),
            street=False,
            big=True,
        )
    for _ in range(rng.poisson(1.5)):
        s = rng.uniform(0.8, 2.0)
        bu = rng.uniform(uc, uc + max(hw_, 1.0))
        bv = setback - rng.uniform(0.6, 1.6)
        side.box(
            b,
            bu - s / 2,
            bu + s / 2,
            bv - s / 2,
            bv + s / 2,
            0.0,
            rng.uniform(0.6, 1.5),
            M.BUSH,
        )
    if irregular and rng.random() < 0.35 and lot > 8.0:
        # A cluster of trees in the back garden.
        v_back = setback + max(hd, 0.0) + rng.uniform(2.0, 6.0)
        if v_back < side.depth / 2.0 - 3.0:
            for _ in range(rng.integers(2, 6)):
                _tree(
                    b,
                    rng,
                    side.point(rng.uniform(u + 2.0, end - 2.0), v_back + rng.uniform(0.0, 5.0)),
                    street=False,
                    big=True,
                )


def _rect_frame(rect: tuple[float, float, float, float]) -> _Side:
    """A block rectangle as a side along its longer edge (u along, v across, both from 0)."""
    x0, y0, x1, y1 = rect
    if x1 - x0 >= y1 - y0:
        return _Side(
            np.array([x0, y0]),
            np.array([1.0, 0.0]),
            np.array([0.0, 1.0]),
            x1 - x0,
            y1 - y0,
            0.0,
            0.0,
            False,
        )
    return _Side(
        np.array([x1, y0]),
        np.array([0.0, 1.0]),
        np.array([-1.0, 0.0]),
        y1 - y0,
        x1 - x0,
        0.0,
        0.0,
        False,
    )


def _edge_line(
    b: _Builder,
    rng: np.random.Generator,
    f: _Side,
    klass: int,
    thick: float,
    z1: tuple[float, float],
    inset: float = 0.3,
) -> None:
    """Hedge, wall or fence pieces around a rectangle, with a few openings."""
    for u0, u1, v0, v1, along_u in (
        (0.0, f.length, 0.0, 0.0, True),
        (0.0, f.length, f.depth, f.depth, True),
        (0.0, 0.0, 0.0, f.depth, False),
        (f.length, f.length, 0.0, f.depth, False),
    ):
        n = (u1 - u0) if along_u else (v1 - v0)
        a = 0.0
        while a < n - 2.0:
            seg = float(rng.uniform(6.0, 18.0))
            c = min(a + seg, n - 1.0)
            h = float(rng.uniform(*z1))
            if along_u:
                v = inset if v0 == 0.0 else f.depth - inset - thick
                f.box(b, a, c, v, v + thick, 0.0, h, klass)
            else:
                uu = inset if u0 == 0.0 else f.length - inset - thick
                f.box(b, uu, uu + thick, a, c, 0.0, h, klass)
            a = c + float(rng.uniform(2.5, 5.0))


def _open_square(
    b: _Builder, rng: np.random.Generator, rect: tuple[float, float, float, float]
) -> None:
    """A paved square: lamps and bollards at its edge, trees, benches, and a fountain, statue or
    kiosk."""
    f = _rect_frame(rect)
    L, D = f.length, f.depth
    for v in (1.5, D - 1.5):
        u = rng.uniform(3.0, 10.0)
        while u < L - 3.0:
            f.box(b, u - 0.12, u + 0.12, v - 0.12, v + 0.12, 0.0, rng.uniform(4.0, 6.0), M.POLE)
            u += rng.uniform(12.0, 20.0)
    for v in (0.4, D - 0.4):
        u = 1.0
        while u < L - 1.0:
            if rng.random() < 0.7:
                f.box(
                    b, u - 0.12, u + 0.12, v - 0.12, v + 0.12, 0.0, rng.uniform(0.8, 1.1), M.BARRIER
                )
            u += rng.uniform(2.0, 4.0)
    if rng.random() < 0.5:
        # An avenue of trees along the two long edges.
        for v in (5.0, D - 5.0):
            u = rng.uniform(4.0, 8.0)
            while u < L - 4.0:
                _tree(b, rng, f.point(u, v), street=False, big=True)
                u += rng.uniform(8.0, 11.0)
    else:
        for _ in range(rng.integers(3, 11)):
            _tree(
                b,
                rng,
                f.point(rng.uniform(4.0, L - 4.0), rng.uniform(4.0, D - 4.0)),
                street=False,
                big=True,
            )
    for _ in range(rng.integers(4, 13)):
        u, v = rng.uniform(3.0, L - 3.0), rng.uniform(3.0, D - 3.0)
        f.box(
            b,
            u - 0.9,
            u + 0.9,
            v - 0.25,
            v + 0.25,
            0.0,
            0.5,
            M.BARRIER,
            dyaw=float(rng.choice([0.0, math.pi / 2])),
        )
    _square_centrepiece(b, rng, f)


def _square_centrepiece(b: _Builder, rng: np.random.Generator, f: _Side) -> None:
    """The middle of a square: a fountain, a statue or a kiosk."""
    L, D = f.length, f.depth
    c = f.point(L / 2, D / 2)
    r = rng.random()
    if r < 0.45:
        # A fountain: a ring of low basin walls.
        rad = rng.uniform(3.0, min(6.0, D / 4))
        n = max(int(2 * math.pi * rad / 1.5), 8)
        _ring(b, c, rad, n, 0.2, lambda: rng.uniform(0.5, 0.8), M.WALL)
    elif r < 0.75:
        b.add(
            float(c[0]),
            float(c[1]),
            rng.uniform(0, math.pi),
            1.0,
            1.0,
            0.0,
            rng.uniform(2.5, 5.0),
            M.WALL,
        )  # statue
    else:
        b.add(
            float(c[0]),
            float(c[1]),
            rng.uniform(0, math.pi),
            rng.uniform(1.5, 3.0),
            rng.uniform(1.5, 2.5),
            0.0,
            3.0,
            M.BUILDING,
        )


def _parking_lot(
    b: _Builder, rng: np.random.Generator, rect: tuple[float, float, float, float], density: float
) -> None:
    """Rows of parked cars, back to back, with aisles between, behind a hedge or low wall."""
    f = _rect_frame(rect)
    L, D = f.length, f.depth
    if rng.random() < 0.6:
        _edge_line(b, rng, f, M.HEDGE if rng.random() < 0.6 else M.WALL, 0.6, (0.8, 1.4))
    stall, depth, aisle = rng.uniform(2.4, 2.8), 5.0, rng.uniform(6.0, 7.5)
    v = 2.0
    row = 0
    while v + depth < D - 2.0:
        u = 2.5
        while u + stall < L - 2.5:
            if rng.random() < 0.7 * min(density, 1.3):
                k, length, width, z0, z1 = _vehicle_dims(rng, moving=False)
                if length < depth - 0.2:
                    uc = u + stall / 2 + rng.uniform(-0.15, 0.15)
                    vc = v + depth / 2 + rng.uniform(-0.2, 0.2)
                    f.box(
                        b,
                        uc - width / 2,
                        uc + width / 2,
                        vc - length / 2,
                        vc + length / 2,
                        z0,
                        z1,
                        k,
                        dyaw=float(rng.normal(0.0, 0.03)),
                    )
            u += stall
        if row % 2 == 0 and v + 2 * depth < D - 2.0:
            # Lamps on the line between two back-to-back rows.
            u = rng.uniform(5.0, 15.0)
            while u < L - 5.0:
                f.box(
                    b,
                    u - 0.12,
                    u + 0.12,
                    v + depth - 0.12,
                    v + depth + 0.12,
                    0.0,
                    rng.uniform(6.0, 8.0),
                    M.POLE,
                )
                u += rng.uniform(20.0, 30.0)
            v += depth
        else:
            v += depth + aisle
        row += 1


def _park(b: _Builder, rng: np.random.Generator, rect: tuple[float, float, float, float]) -> None:
    """Grass with clusters of trees, bushes, hedges and maybe a pavilion."""
    f = _rect_frame(rect)
    L, D = f.length, f.depth
    if rng.random() < 0.6:
        _edge_line(b, rng, f, M.HEDGE if rng.random() < 0.7 else M.FENCE, 0.8, (0.9, 1.8))
    for _ in range(rng.poisson(L * D / 1200.0) + 2):
        cu, cv = rng.uniform(5.0, L - 5.0), rng.uniform(5.0, D - 5.0)
        spread = rng.uniform(4.0, 12.0)
        for _ in range(rng.integers(3, 10)):
            u = float(np.clip(cu + rng.normal(0.0, spread / 2), 3.0, L - 3.0))
            v = float(np.clip(cv + rng.normal(0.0, spread / 2), 3.0, D - 3.0))
            _tree(b, rng, f.point(u, v), street=False, big=True)
    for _ in range(rng.poisson(L * D / 300.0)):
        s = rng.uniform(0.8, 2.5)
        u, v = rng.uniform(2.0, L - 2.0), rng.uniform(2.0, D - 2.0)
        f.box(b, u - s / 2, u + s / 2, v - s / 2, v + s / 2, 0.0, rng.uniform(0.5, 1.6), M.BUSH)
    if rng.random() < 0.25:
        u, v = rng.uniform(8.0, L - 8.0), rng.uniform(8.0, D - 8.0)
        f.box(b, u - 3.0, u + 3.0, v - 3.0, v + 3.0, 0.0, 3.5, M.BUILDING)


def _ring(
    b: _Builder,
    c: np.ndarray,
    rad: float,
    n: int,
    half_width: float,
    top: Callable[[], float],
    klass: int,
) -> None:
    """A ring of ``n`` short boxes around ``c`` at radius ``rad`` (a basin wall, a curb), each
    as tall as ``top()`` (drawn box by box where it is random)."""
    for k in range(n):
        a = 2 * math.pi * k / n
        b.add(
            float(c[0] + rad * math.cos(a)),
            float(c[1] + rad * math.sin(a)),
            a + math.pi / 2,
            math.pi * rad / n + 0.05,
            half_width,
            0.0,
            top(),
            klass,
        )


def _roundabout_island(
    b: _Builder, rng: np.random.Generator, c: np.ndarray, rad: float, clear: float
) -> None:
    """A round central island (curb ring, a hedge ring or bushes, a tree or a monument) and
    lamps around the circulating carriageway."""
    n = max(int(2 * math.pi * rad / 1.2), 10)
    _ring(b, c, rad, n, 0.15, lambda: 0.35, M.BARRIER)
    _island_planting(b, rng, c, rad)
    if rng.random() < 0.6:
        _tree(b, rng, c, street=False, big=True)
    else:
        b.add(
            float(c[0]),
            float(c[1]),
            rng.uniform(0, math.pi),
            0.6,
            0.6,
            0.0,
            rng.uniform(3.0, 6.0),
            M.WALL,
        )
    for k in range(rng.integers(4, 9)):
        a = rng.uniform(0, 2 * math.pi)
        p = c + (clear + 1.2) * np.array([math.cos(a), math.sin(a)])
        b.add(float(p[0]), float(p[1]), 0.0, 0.12, 0.12, 0.0, rng.uniform(6.0, 8.0), M.POLE)


def _island_planting(b: _Builder, rng: np.random.Generator, c: np.ndarray, rad: float) -> None:
    """A hedge ring inside the island's curb, or (on a small island, or by the draw) a few
    bushes scattered over it."""
    if rng.random() < 0.5 and rad > 3.0:
        r2 = rad - 0.8
        n2 = max(int(2 * math.pi * r2 / 1.5), 8)
        h = rng.uniform(0.8, 1.4)
        for k in range(n2):
            a = 2 * math.pi * k / n2
            b.add(
                float(c[0] + r2 * math.cos(a)),
                float(c[1] + r2 * math.sin(a)),
                a + math.pi / 2,
                math.pi * r2 / n2 + 0.05,
                0.35,
                0.0,
                h,
                M.HEDGE,
            )
    else:
        for _ in range(rng.integers(2, 7)):
            a, r = rng.uniform(0, 2 * math.pi), rng.uniform(0.0, rad - 1.0)
            s = rng.uniform(0.8, 1.8)
            b.add(
                float(c[0] + r * math.cos(a)),
                float(c[1] + r * math.sin(a)),
                a,
                s / 2,
                s / 2,
                0.0,
                rng.uniform(0.6, 1.4),
                M.BUSH,
            )


def _rows_array(rows: list) -> np.ndarray:
    return np.array(rows, dtype=np.float64).reshape(-1, 8)


def _split_rows(rows: np.ndarray, max_len: float = _PIECE_M) -> np.ndarray:
    """Boxes cut into pieces no longer than ``max_len`` on either side, so that a warp bends
    long facades, walls and hedges instead of tilting them as a whole."""
    nu = np.maximum(np.ceil(2 * rows[:, 3] / max_len), 1).astype(np.int64)
    nv = np.maximum(np.ceil(2 * rows[:, 4] / max_len), 1).astype(np.int64)
    if (nu * nv == 1).all():
        return rows
    k = np.repeat(np.arange(len(rows)), nu * nv)
    first = np.repeat(np.cumsum(nu * nv) - nu * nv, nu * nv)
    idx = np.arange(len(k)) - first
    iu, iv = idx % nu[k], idx // nu[k]
    r = rows[k].copy()
    hl, hw = rows[k, 3] / nu[k], rows[k, 4] / nv[k]
    du = -rows[k, 3] + (2 * iu + 1) * hl
    dv = -rows[k, 4] + (2 * iv + 1) * hw
    c, s = np.cos(rows[k, 2]), np.sin(rows[k, 2])
    r[:, 0] += c * du - s * dv
    r[:, 1] += s * du + c * dv
    r[:, 3], r[:, 4] = hl, hw
    return r


def _in_strip(rows: np.ndarray, p: np.ndarray, d: np.ndarray, half: float) -> np.ndarray:
    """Which boxes reach into the band of half width ``half`` around the line ``p + u d``?"""
    nx, ny = -d[1], d[0]
    c, s = np.cos(rows[:, 2]), np.sin(rows[:, 2])
    reach = rows[:, 3] * np.abs(nx * c + ny * s) + rows[:, 4] * np.abs(-nx * s + ny * c)
    return np.abs(nx * (rows[:, 0] - p[0]) + ny * (rows[:, 1] - p[1])) < half + reach


def _in_grid_streets(rows: np.ndarray, grid: StreetGrid) -> np.ndarray:
    """Which boxes reach into a grid street or its sidewalks (bounds test)?"""
    out = np.zeros(len(rows), bool)
    if not len(rows):
        return out
    c, s = np.abs(np.cos(rows[:, 2])), np.abs(np.sin(rows[:, 2]))
    ex, ey = rows[:, 3] * c + rows[:, 4] * s, rows[:, 3] * s + rows[:, 4] * c
    for centres, half, p, e in (
        (grid.xs, grid.x_hw + grid.x_sw, rows[:, 0], ex),
        (grid.ys, grid.y_hw + grid.y_sw, rows[:, 1], ey),
    ):
        k = np.clip(np.searchsorted(centres, p), 1, len(centres) - 1)
        for kk in (k - 1, k):
            out |= np.abs(p - centres[kk]) < half[kk] + e
    return out


def _warp_rows(rows: np.ndarray, warp: Warp) -> np.ndarray:
    """City-frame boxes bent by the warp: centres moved, yaw turned and sides stretched by its
    Jacobian."""
    out = rows.copy()
    x, y, yaw = rows[:, 0], rows[:, 1], rows[:, 2]
    out[:, 2], stretch_u = warp.direction(x, y, yaw)
    _, stretch_v = warp.direction(x, y, yaw + math.pi / 2)
    out[:, 0], out[:, 1] = warp.apply(x, y)
    out[:, 3] *= stretch_u
    out[:, 4] *= stretch_v
    return out


def _avenue_sides(
    grid: StreetGrid,
    p: np.ndarray,
    d: np.ndarray,
    hw: float,
    sw: float,
    u_lo: float,
    u_hi: float,
    parking: bool,
) -> list[_Side]:
    """Both sides of an avenue between the grid streets it crosses (u from ``u_lo`` to ``u_hi``)."""
    nrm = np.array([-d[1], d[0]])
    sides = []
    for sign in (1.0, -1.0):
        q0 = p + sign * (hw + sw) * nrm
        cuts = []
        for centres, half, k in (
            (grid.xs, grid.x_hw + grid.x_sw, 0),
            (grid.ys, grid.y_hw + grid.y_sw, 1),
        ):
            if abs(d[k]) < 1e-9:
                continue
            a = (centres - half - q0[k]) / d[k]
            b = (centres + half - q0[k]) / d[k]
            cuts += list(zip(np.minimum(a, b), np.maximum(a, b)))
        cuts.sort()
        u = u_lo
        for a, b in cuts + [(u_hi, u_hi)]:
            if b < u:
                continue
            end = min(a, u_hi)
            if end - u > 14.0:
                sides.append(
                    _Side(q0 + u * d, d.copy(), sign * nrm, end - u, 36.0, sw, hw, parking)
                )
            u = max(u, b)
            if u >= u_hi:
                break
    return sides


def _block_sides(grid: StreetGrid, i: int, j: int) -> list[_Side] | None:
    x0 = grid.xs[i] + grid.x_hw[i] + grid.x_sw[i]
    x1 = grid.xs[i + 1] - grid.x_hw[i + 1] - grid.x_sw[i + 1]
    y0 = grid.ys[j] + grid.y_hw[j] + grid.y_sw[j]
    y1 = grid.ys[j + 1] - grid.y_hw[j + 1] - grid.y_sw[j + 1]
    if x1 - x0 < 10 or y1 - y0 < 10:
        return None
    lx, ly = x1 - x0, y1 - y0
    return [
        _Side(
            np.array([x0, y0]),
            np.array([1.0, 0.0]),
            np.array([0.0, 1.0]),
            lx,
            ly,
            grid.y_sw[j],
            grid.y_hw[j],
            bool(grid.y_parking[j]),
        ),
        _Side(
            np.array([x1, y1]),
            np.array([-1.0, 0.0]),
            np.array([0.0, -1.0]),
            lx,
            ly,
            grid.y_sw[j + 1],
            grid.y_hw[j + 1],
            bool(grid.y_parking[j + 1]),
        ),
        _Side(
            np.array([x0, y1]),
            np.array([0.0, -1.0]),
            np.array([1.0, 0.0]),
            ly,
            lx,
            grid.x_sw[i],
            grid.x_hw[i],
            bool(grid.x_parking[i]),
        ),
        _Side(
            np.array([x1, y0]),
            np.array([0.0, 1.0]),
            np.array([-1.0, 0.0]),
            ly,
            lx,
            grid.x_sw[i + 1],
            grid.x_hw[i + 1],
            bool(grid.x_parking[i + 1]),
        ),
    ]


def _overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Do packed boxes ``a[k]`` and ``b[k]`` overlap in footprint (separating axis test)?"""
    d = b[:, :2] - a[:, :2]
    sep = np.zeros(len(a), dtype=bool)
    axes = (
        a[:, 2:4],
        np.stack([-a[:, 3], a[:, 2]], 1),
        b[:, 2:4],
        np.stack([-b[:, 3], b[:, 2]], 1),
    )
    for ax in axes:
        pd = np.abs((d * ax).sum(1))
        ra = a[:, 4] * np.abs((a[:, 2:4] * ax).sum(1)) + a[:, 5] * np.abs(
            a[:, 2] * ax[:, 1] - a[:, 3] * ax[:, 0]
        )
        rb = b[:, 4] * np.abs((b[:, 2:4] * ax).sum(1)) + b[:, 5] * np.abs(
            b[:, 2] * ax[:, 1] - b[:, 3] * ax[:, 0]
        )
        sep |= pd > ra + rb
    return ~sep


def _ego_boxes(traj: Trajectory, ts: np.ndarray, margin: float) -> np.ndarray:
    x, y, yaw = traj.pose_at(ts)
    off = EGO_LENGTH_M / 2 - EGO_REAR_OVERHANG_M
    return pack_boxes(
        x + off * np.cos(yaw),
        y + off * np.sin(yaw),
        yaw,
        np.full(len(ts), EGO_LENGTH_M / 2 + margin),
        np.full(len(ts), EGO_WIDTH_M / 2 + margin),
        np.zeros(len(ts)),
        np.full(len(ts), 1.6),
    )


def _aabbs(p: np.ndarray) -> np.ndarray:
    """Axis-aligned footprint bounds ``(x_lo, y_lo, x_hi, y_hi)`` of packed boxes."""
    ex = np.abs(p[:, 2]) * p[:, 4] + np.abs(p[:, 3]) * p[:, 5]
    ey = np.abs(p[:, 3]) * p[:, 4] + np.abs(p[:, 2]) * p[:, 5]
    return np.stack([p[:, 0] - ex, p[:, 1] - ey, p[:, 0] + ex, p[:, 1] + ey], -1)


def _touch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Do bounds ``a`` and ``b`` (broadcast, last axis x_lo, y_lo, x_hi, y_hi) intersect? Boxes
    whose bounds do not intersect cannot overlap, so only the others need the exact test."""
    return (
        (a[..., 0] <= b[..., 2])
        & (b[..., 0] <= a[..., 2])
        & (a[..., 1] <= b[..., 3])
        & (b[..., 1] <= a[..., 3])
    )


#: Samples of a track whose bounds are merged into one piece's bounds.
_SEGMENT = 16
#: Samples a piece of an accepted mover's track: the bounds it keeps for the whole build
#: (float32, rounded outward: 18 MiB for a 30-minute drive instead of 35). A piece's bounds hold
#: its samples', so any piece size and any outward rounding find the same touching samples;
#: larger pieces keep less but make more tracks be recomputed.
_KEPT_PIECE = _SEGMENT
#: Bytes of accepted movers' tracks (32 a sample) kept while the world is built, the most
#: recently used; the others are recomputed when a candidate comes near. Keeping every track
#: and its bounds grew with traffic x duration (1.7 GiB for a 30-minute drive).
_TRACK_CACHE_BYTES = 48 << 20
#: Samples a chunk of a cached track (51 s): a long track passes near others for a short
#: while, and only the chunks that are asked for stay.
_TRACK_CHUNK = 256


def _segment_bounds(box: np.ndarray, size: int = _SEGMENT) -> np.ndarray:
    """Bounds of each run of ``size`` consecutive sample bounds (the last may be shorter)."""
    n = len(box)
    pad = np.concatenate([box, np.repeat(box[-1:], (-n) % size, axis=0)]).reshape(-1, size, 4)
    return np.concatenate([pad[:, :, :2].min(1), pad[:, :, 2:].max(1)], -1)


def _outward_f32(bounds: np.ndarray) -> np.ndarray:
    """Bounds ``(x_lo, y_lo, x_hi, y_hi)`` as float32 rounded outward: they hold the float64
    bounds, so every pair of bounds that touches still touches."""
    out = bounds.astype(np.float32)
    lo, hi = out[:, :2], out[:, 2:]
    lo[:] = np.where(lo > bounds[:, :2], np.nextafter(lo, np.float32(-np.inf)), lo)
    hi[:] = np.where(hi < bounds[:, 2:], np.nextafter(hi, np.float32(np.inf)), hi)
    return out


def _segment_samples(segs: np.ndarray, n: int, size: int = _SEGMENT) -> np.ndarray:
    """Indices of the samples in pieces ``segs`` (of ``size`` samples) of a track of ``n``
    samples."""
    idx = (segs[:, None] * size + np.arange(size)).ravel()
    return idx[idx < n]


class _MoverSet:
    """Accepts candidate movers that collide with nothing over the scene (sampled every 0.2 s).

    Each test first compares axis-aligned bounds (whole tracks, pieces of 16 samples, then
    per sample time) and runs the exact separating-axis test only on the pairs left, so building
    a long drive's world
    grows with its traffic, not with traffic x duration x traffic."""

    def __init__(
        self, traj: Trajectory, duration: float, static: np.ndarray, warp: Warp | None = None
    ) -> None:
        self.traj = traj
        self.warp = warp
        self.ts = np.arange(-0.3, duration + 0.31, 0.2)
        self.ego = _ego_boxes(traj, self.ts, margin=0.6)
        self.ego_aabb = _aabbs(self.ego)
        self.static = static
        self.static_lo = static[:, 6] if len(static) else np.zeros(0)
        self.static_hi = static[:, 7] if len(static) else np.zeros(0)
        self.static_aabb = _aabbs(static) if len(static) else np.zeros((0, 4))
        self.accepted: list[dict] = []
        self.track_pieces: list[np.ndarray] = []
        self.track_bounds = np.zeros((0, 4))
        #: (accepted mover, chunk) -> its samples' centres, cos and sin of yaw, least recently
        #: used first
        self.track_cache: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self.cached_bytes = 0
        #: tracks recomputed after leaving the cache (for tests and benchmarks)
        self.recomputed = 0

    def _track(self, m: dict) -> np.ndarray:
        """Packed boxes of one candidate at every sample time."""
        ts = self.ts
        n = len(ts)
        if m["follow"]:
            x, y, yaw = self.traj.pose_at_s(self.traj.s_at(ts + m["lead"]) + m["gap"])
        else:
            tc = np.clip(ts, m["tb"], m["te"])
            yaw = np.full(n, m["heading"])
            x = m["p0"][0] + math.cos(m["heading"]) * m["speed"] * tc
            y = m["p0"][1] + math.sin(m["heading"]) * m["speed"] * tc
            if self.warp is not None:
                yaw, _ = self.warp.direction(x, y, yaw)
                x, y = self.warp.apply(x, y)
        return pack_boxes(
            x,
            y,
            yaw,
            np.full(n, m["hl"]),
            np.full(n, m["hw"]),
            np.full(n, m["z0"]),
            np.full(n, m["z1"]),
        )

    def offer(self, m: dict) -> bool:
        """Accept ``m`` if it overlaps neither the ego, nor accepted movers, nor static boxes."""
        tr = self._track(m)
        box = _aabbs(tr)
        segs = _segment_bounds(box)
        bounds = np.concatenate([box[:, :2].min(0), box[:, 2:].max(0)])
        near = _touch(box, self.ego_aabb)
        if near.any() and _overlap(tr[near], self.ego[near]).any():
            return False
        pieces = segs if _KEPT_PIECE == _SEGMENT else _segment_bounds(box, _KEPT_PIECE)
        for k in np.nonzero(_touch(self.track_bounds, bounds))[0]:
            close = np.nonzero(_touch(pieces, self.track_pieces[int(k)]))[0]
            if not len(close):
                continue
            idx = _segment_samples(close, len(box), _KEPT_PIECE)
            other = self._accepted_samples(int(k), idx)
            hit = _touch(box[idx], _aabbs(other))
            if hit.any() and _overlap(tr[idx[hit]], other[hit]).any():
                return False
        if len(self.static):
            cand = np.nonzero(
                _touch(self.static_aabb, bounds)
                & (self.static_lo < m["z1"])
                & (self.static_hi > m["z0"])
            )[0]
            if len(cand):
                # Pieces of the track first, then its samples in the pieces that touch a box.
                seg_idx, c_idx = np.nonzero(
                    _touch(segs[:, None, :], self.static_aabb[cand][None, :, :])
                )
                t_idx = (seg_idx[:, None] * _SEGMENT + np.arange(_SEGMENT)).ravel()
                c_idx = np.repeat(c_idx, _SEGMENT)
                ok = t_idx < len(box)
                t_idx, c_idx = t_idx[ok], cand[c_idx[ok]]
                ok = _touch(box[t_idx], self.static_aabb[c_idx])
                if ok.any() and _overlap(tr[t_idx[ok]], self.static[c_idx[ok]]).any():
                    return False
        self.accepted.append(m)
        self.track_pieces.append(_outward_f32(pieces))
        self.track_bounds = np.vstack([self.track_bounds, bounds])
        self._keep(len(self.accepted) - 1, tr, None)
        return True

    def _keep(self, k: int, tr: np.ndarray, needed: np.ndarray | None) -> None:
        """Cache accepted mover ``k``'s track by chunks of samples (centres, cos and sin of yaw;
        the rest is its constant size): the ``needed`` chunks (None: all) as the most recently
        used, the others as the least; then drop the least recently used over budget."""
        for c in range(-(-len(tr) // _TRACK_CHUNK)):
            part = tr[c * _TRACK_CHUNK : (c + 1) * _TRACK_CHUNK, :4].copy()
            old = self.track_cache.pop((k, c), None)
            self.cached_bytes += part.nbytes - (0 if old is None else old.nbytes)
            self.track_cache[(k, c)] = part
            if needed is not None and c not in needed:
                self.track_cache.move_to_end((k, c), last=False)
        while self.cached_bytes > _TRACK_CACHE_BYTES and len(self.track_cache) > 1:
            _, old = self.track_cache.popitem(last=False)
            self.cached_bytes -= old.nbytes

    def _accepted_samples(self, k: int, idx: np.ndarray) -> np.ndarray:
        """Packed boxes of accepted mover ``k`` at samples ``idx`` (ascending), from the cache
        or its track recomputed (the same arithmetic on the same inputs: the same bytes)."""
        m = self.accepted[k]
        chunks = np.unique(idx // _TRACK_CHUNK)
        parts = [self.track_cache.get((k, int(c))) for c in chunks]
        if any(p is None for p in parts):
            self.recomputed += 1
            tr = self._track(m)
            self._keep(k, tr, set(chunks.tolist()))
            return tr[idx]
        for c in chunks:
            self.track_cache.move_to_end((k, int(c)))
        first = np.concatenate([[0], np.cumsum([len(p) for p in parts])[:-1]])
        at = first[np.searchsorted(chunks, idx // _TRACK_CHUNK)] + idx % _TRACK_CHUNK
        out = np.empty((len(idx), 8))
        out[:, :4] = (parts[0] if len(parts) == 1 else np.concatenate(parts))[at]
        out[:, 4:] = (m["hl"], m["hw"], m["z0"], m["z1"])
        return out

    def movers(self) -> Movers:
        if not self.accepted:
            return Movers.empty() if self.warp is None else replace(Movers.empty(), warp=self.warp)
        a = self.accepted
        col = lambda k, dt=np.float64: np.array([m[k] for m in a], dtype=dt)  # noqa: E731
        return Movers(
            col("cls", np.int32),
            col("hl"),
            col("hw"),
            col("z0"),
            col("z1"),
            np.array([m["p0"] for m in a], dtype=np.float64),
            col("heading"),
            col("speed"),
            col("tb"),
            col("te"),
            col("follow", bool),
            col("gap"),
            col("lead"),
            self.warp,
        )


def _mover(
    klass: int,
    length: float,
    width: float,
    z0: float,
    z1: float,
    p0: np.ndarray,
    heading: float,
    speed: float,
    tb: float = -1e9,
    te: float = 1e9,
    follow: bool = False,
    gap: float = 0.0,
    lead: float = 0.0,
) -> dict:
    return dict(
        cls=klass,
        hl=length / 2,
        hw=width / 2,
        z0=z0,
        z1=z1,
        p0=np.asarray(p0, dtype=np.float64),
        heading=heading,
        speed=speed,
        tb=tb,
        te=te,
        follow=follow,
        gap=gap,
        lead=lead,
    )


def _plan(
    seed: int, config: SimConfig
) -> tuple[np.random.Generator, str, StreetGrid, Route, Warp | None, Trajectory]:
    rng = np.random.default_rng([int(seed), 0x5EED])
    env = config.world.environment
    if env == "mixed":
        env = "urban" if rng.random() < 0.6 else "suburban"
    irregular = config.world.layout == "irregular"
    lo, hi = config.ego.cruise_speed_mps
    cruise = float(rng.uniform(lo, hi)) + (0.0 if env == "urban" else 2.0)
    need = config.duration_s * cruise * 1.2 + 80.0
    grid = make_street_grid(rng, env, extent_m=need + 250.0, irregular=irregular)
    route = plan_route(rng, grid, need, config.ego)
    warp = Warp.draw(rng) if irregular else None
    traj = build_trajectory(rng, route, config.ego, cruise, config.duration_s, warp=warp)
    return rng, env, grid, route, warp, traj


def plan_drive(
    seed: int, config: SimConfig
) -> tuple[np.random.Generator, str, StreetGrid, Trajectory]:
    """The first stage of :func:`generate_world`: environment, streets and the ego trajectory
    (city frame, bent by the town's warp), with the generator in the state the rest of the world
    continues from."""
    rng, env, grid, _, _, traj = _plan(seed, config)
    return rng, env, grid, traj


def _choose_avenues(
    rng: np.random.Generator, grid: StreetGrid, upts: np.ndarray, env: str
) -> list[tuple[float, float, float, float, float]]:
    """Diagonal avenues, each through a grid junction near the route at 25-65 deg to the grid."""
    length_km = float(np.hypot(*np.diff(upts, axis=0).T).sum()) / 1000.0
    out = []
    for _ in range(rng.poisson(_AVENUES_PER_KM * max(length_km, 1.0))):
        p = upts[rng.integers(len(upts))]
        x = float(grid.xs[np.argmin(np.abs(grid.xs - p[0]))])
        y = float(grid.ys[np.argmin(np.abs(grid.ys - p[1]))])
        if any(abs(a[0] - x) < 1.0 and abs(a[1] - y) < 1.0 for a in out):
            continue
        angle = float(rng.uniform(math.radians(25.0), math.radians(65.0))) * (
            1.0 if rng.random() < 0.5 else -1.0
        )
        hw = float(rng.uniform(6.5, 9.5)) if env == "urban" else float(rng.uniform(5.5, 8.0))
        out.append((x, y, angle, hw, float(rng.uniform(3.5, 6.0))))
    return out


def _choose_roundabouts(
    rng: np.random.Generator, grid: StreetGrid, near, path: np.ndarray, avenues: list
) -> list[tuple[float, float, float]]:
    """Roundabouts at junctions near the route that the route never crosses (the ego needs no
    path around the island)."""
    out = []
    for i, x in enumerate(grid.xs):
        if not near(x, -1e9, x, 1e9):
            continue
        for j, y in enumerate(grid.ys):
            if not near(x, y, x, y) or rng.random() >= _ROUNDABOUT_P:
                continue
            rad = float(rng.uniform(2.5, max(min(grid.x_hw[i], grid.y_hw[j]) - 0.5, 2.6)))
            clear = rad + 7.5
            if np.min(np.hypot(path[:, 0] - x, path[:, 1] - y)) < clear + 4.0:
                continue
            if any(abs(a[0] - x) < 1.0 and abs(a[1] - y) < 1.0 for a in avenues):
                continue
            out.append((float(x), float(y), rad))
    return out


def _avenue_traffic(
    rng: np.random.Generator,
    movers: _MoverSet,
    avenue: tuple,
    u_lo: float,
    u_hi: float,
    urban: bool,
    density: float,
) -> None:
    """Two lanes each way along a diagonal avenue."""
    x, y, angle, hw, _ = avenue
    d = np.array([math.cos(angle), math.sin(angle)])
    left = np.array([-d[1], d[0]])
    spacing = 45.0 if urban else 90.0
    for sense in (1.0, -1.0):
        h = sense * d
        for off in (LANE_OFFSET_M, LANE_OFFSET_M + 3.3):
            if off + 1.0 > hw:
                continue
            speed = float(rng.uniform(7.0, 13.0))
            n = rng.poisson(density * (u_hi - u_lo) / spacing)
            for u in np.sort(rng.uniform(u_lo, u_hi, size=n)):
                k, length, width, z0, z1 = _vehicle_dims(rng, moving=True)
                p0 = np.array([x, y]) + u * d + off * sense * (-left)
                movers.offer(_mover(k, length, width, z0, z1, p0, math.atan2(h[1], h[0]), speed))


class _Near:
    """Whether a rectangle comes within ``r`` (m) of the driven path's samples ``pts``."""

    def __init__(self, pts: np.ndarray) -> None:
        self.pts = pts

    def __call__(
        self, x0: float, y0: float, x1: float, y1: float, r: float = _POPULATE_RADIUS_M
    ) -> bool:
        pts = self.pts
        dx = np.maximum(np.maximum(x0 - pts[:, 0], 0.0), pts[:, 0] - x1)
        dy = np.maximum(np.maximum(y0 - pts[:, 1], 0.0), pts[:, 1] - y1)
        return bool((dx * dx + dy * dy).min() <= r * r)


@dataclass
class _Town:
    """What :func:`generate_world` builds up, step by step, in the city frame."""

    rng: np.random.Generator
    env: str
    grid: StreetGrid
    warp: object
    density: float
    #: the driven path sampled every 2 m (unwarped city frame)
    pts: np.ndarray
    layout: TownLayout
    sides: list = field(default_factory=list)
    avenue_spans: list = field(default_factory=list)

    @property
    def urban(self) -> bool:
        return self.env == "urban"

    @property
    def irregular(self) -> bool:
        return self.warp is not None

    def line_side(self, b: _Builder, side: _Side) -> None:
        """Line a street side with the environment's buildings, fences and furniture."""
        fill = _urban_side if self.urban else _suburban_side
        fill(b, self.rng, side, self.density, self.irregular)


def _driven_path(traj: Trajectory, config: SimConfig, warp) -> np.ndarray:
    """The driven part of the path, sampled every 2 m, which decides what to populate (in the
    unwarped city frame, where the streets are straight)."""
    s_lo = float(traj.s_at(-0.5))
    s_hi = float(traj.s_at(config.duration_s + 0.5))
    ss = np.arange(s_lo, s_hi + 2.0, 2.0)
    px, py, _ = traj.pose_at_s(ss)
    if warp is not None:
        px, py = warp.inverse(px, py)
    return np.stack([px, py], 1)


def _block_kind(town: _Town) -> str:
    """What a block near the route holds: street sides, or (irregular towns) an open square,
    a parking lot or a park."""
    if not town.irregular:
        return "sides"
    use = _BLOCK_USE[town.env]
    r = town.rng.random()
    if r < use[0]:
        return "square"
    if r < use[0] + use[1]:
        return "lot"
    return "park" if r < sum(use) else "sides"


def _populate_blocks(town: _Town, b: _Builder, near: _Near) -> None:
    """Fill the blocks near the route and line their sides."""
    rng, grid, layout = town.rng, town.grid, town.layout
    for i in range(len(grid.xs) - 1):
        if not near(grid.xs[i], -1e9, grid.xs[i + 1], 1e9):
            continue
        for j in range(len(grid.ys) - 1):
            if not near(grid.xs[i], grid.ys[j], grid.xs[i + 1], grid.ys[j + 1]):
                continue
            blk = _block_sides(grid, i, j)
            if blk is None:
                continue
            kind = _block_kind(town)
            if kind != "sides":
                p0, p1 = blk[0].origin, blk[1].origin
                rect = (float(p0[0]), float(p0[1]), float(p1[0]), float(p1[1]))
                if kind == "square":
                    _open_square(b, rng, rect)
                    layout.squares.append(rect)
                elif kind == "lot":
                    _parking_lot(b, rng, rect, town.density)
                    layout.parking_lots.append(rect)
                else:
                    _park(b, rng, rect)
                    layout.parks.append(rect)
            for side in blk:
                if kind == "sides":
                    town.line_side(b, side)
                else:
                    _street_furniture(b, rng, side, urban=town.urban, density=town.density)
                    if side.parking:
                        empty_p = (0.22 if town.urban else 0.6) / max(town.density, 0.2)
                        _parked_cars(b, rng, side, empty_p=empty_p)
                town.sides.append(side)


def _avenue_rows(town: _Town, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
    """Diagonal avenues across the grid: clear their strips in ``rows`` and line their sides
    -> (rows, the avenues' own rows, the avenues)."""
    rng, grid, pts, layout = town.rng, town.grid, town.pts, town.layout
    avenues = _choose_avenues(rng, grid, pts, town.env)
    ab = _Builder()
    for x, y, angle, hw, sw in avenues:
        p, d = np.array([x, y]), np.array([math.cos(angle), math.sin(angle)])
        rows = rows[~_in_strip(rows, p, d, hw + sw)]
        dist = np.abs(-d[1] * (pts[:, 0] - x) + d[0] * (pts[:, 1] - y))
        u = (pts[:, 0] - x) * d[0] + (pts[:, 1] - y) * d[1]
        # Populated where it passes the route, at most _AVENUE_REACH_M from its junction (so a
        # long drive's world stays linear in its length).
        close = (dist < _POPULATE_RADIUS_M) & (np.abs(u) < _AVENUE_REACH_M)
        u_lo = float(u[close].min()) - 60.0 if close.any() else -60.0
        u_hi = float(u[close].max()) + 60.0 if close.any() else 60.0
        town.avenue_spans.append((u_lo, u_hi))
        for side in _avenue_sides(grid, p, d, hw, sw, u_lo, u_hi, parking=hw > 8.3):
            town.line_side(ab, side)
            town.sides.append(side)
    arows = _split_rows(_rows_array(ab.rows))
    arows = arows[~_in_grid_streets(arows, grid)]
    for x0, y0, x1, y1 in layout.squares + layout.parking_lots + layout.parks:
        # An avenue through an open block keeps it open.
        inside = (arows[:, 0] > x0) & (arows[:, 0] < x1) & (arows[:, 1] > y0) & (arows[:, 1] < y1)
        arows = arows[~inside]
    for x, y, angle, hw, _sw in avenues:
        d = np.array([math.cos(angle), math.sin(angle)])
        arows = arows[~_in_strip(arows, np.array([x, y]), d, hw)]
    layout.avenues.extend(avenues)
    return rows, arows, avenues


def _irregular_rows(town: _Town, rows: np.ndarray, route: Route, near: _Near) -> np.ndarray:
    """An irregular town's extras: avenues, then roundabouts (a round junction cleared, an
    island in its middle); all rows warped into the curved city frame."""
    rows, arows, avenues = _avenue_rows(town, _split_rows(rows))
    flat = _dense_path(route.points, route.radii)
    path = np.stack([flat[1][::4], flat[2][::4]], 1)
    rb = _Builder()
    rows = np.concatenate([rows, arows])
    for x, y, rad in _choose_roundabouts(town.rng, town.grid, near, path, avenues):
        c = np.array([x, y])
        reach = np.hypot(rows[:, 3], rows[:, 4])
        rows = rows[np.hypot(rows[:, 0] - x, rows[:, 1] - y) > rad + 7.5 + reach]
        _roundabout_island(rb, town.rng, c, rad, rad + 7.5)
        town.layout.roundabouts.append((x, y, rad))
    return _warp_rows(np.concatenate([rows, _rows_array(rb.rows)]), town.warp)


def _following_vehicles(town: _Town, movers: _MoverSet) -> None:
    """A vehicle ahead of the ego and one behind, driving its path (time-shifted)."""
    rng = town.rng
    for p, sign in ((0.55, 1.0), (0.45, -1.0)):
        if rng.random() < p * min(town.density, 1.0):
            k, length, width, z0, z1 = _vehicle_dims(rng, moving=True)
            gap = sign * (rng.uniform(8.0, 14.0) + (length - 4.5) / 2)
            lead = sign * rng.uniform(0.8, 2.0)
            movers.offer(
                _mover(
                    k, length, width, z0, z1, np.zeros(2), 0.0, 0.0, follow=True, gap=gap, lead=lead
                )
            )


def _lane_traffic(
    town: _Town, movers: _MoverSet, axis: int, c: float, d: int, span: tuple[float, float]
) -> None:
    """Vehicles at one speed in one lane (direction ``d``) of the street at ``c`` along
    ``axis``, and now and then a cyclist at the lane's right edge."""
    rng, urban, density = town.rng, town.urban, town.density
    a_lo, a_hi = span
    speed = float(rng.uniform(6.0, 12.5)) * (1.0 if urban else 1.15)
    n = rng.poisson(density * (a_hi - a_lo) / (45.0 if urban else 90.0))
    pos = np.sort(rng.uniform(a_lo, a_hi, size=n))
    if n > 1:
        keep = np.concatenate([[True], np.diff(pos) > 12.0])
        pos = pos[keep]
    lane = c - d * LANE_OFFSET_M if axis == 0 else c + d * LANE_OFFSET_M
    if axis == 0:
        heading = 0.0 if d > 0 else math.pi
    else:
        heading = math.pi / 2 if d > 0 else -math.pi / 2
    for p in pos:
        k, length, width, z0, z1 = _vehicle_dims(rng, moving=True)
        p0 = np.array([p, lane]) if axis == 0 else np.array([lane, p])
        movers.offer(_mover(k, length, width, z0, z1, p0, heading, speed))
    # Cyclists keep to the right edge of the lane.
    if rng.random() < (0.25 if urban else 0.15) * density:
        off = LANE_OFFSET_M + 1.1
        lane_c = c - d * off if axis == 0 else c + d * off
        p = rng.uniform(a_lo, a_hi)
        p0 = np.array([p, lane_c]) if axis == 0 else np.array([lane_c, p])
        v = float(rng.uniform(3.5, 6.0))
        movers.offer(_mover(M.CYCLIST, 1.8, 0.6, 0.0, 1.75, p0, heading, v))


def _street_traffic(town: _Town, movers: _MoverSet) -> None:
    """Traffic on the streets near the route: both directions, one speed a lane."""
    grid, pts = town.grid, town.pts
    xlo, xhi = pts[:, 0].min() - 120.0, pts[:, 0].max() + 120.0
    ylo, yhi = pts[:, 1].min() - 120.0, pts[:, 1].max() + 120.0
    for axis in (0, 1):
        centres = grid.ys if axis == 0 else grid.xs
        hws = grid.y_hw if axis == 0 else grid.x_hw
        span = (xlo, xhi) if axis == 0 else (ylo, yhi)
        for c, _hw in zip(centres, hws):
            if not ((ylo if axis == 0 else xlo) <= c <= (yhi if axis == 0 else xhi)):
                continue
            for d in (1, -1):
                _lane_traffic(town, movers, axis, c, d, span)
    for avenue, (u_lo, u_hi) in zip(town.layout.avenues, town.avenue_spans):
        _avenue_traffic(town.rng, movers, avenue, u_lo, u_hi, town.urban, town.density)


def _pedestrians(town: _Town, movers: _MoverSet, duration_s: float) -> None:
    """Pedestrians walking along sidewalks, and some crossing at corners."""
    rng, urban, density = town.rng, town.urban, town.density
    for side in town.sides:
        sw = side.sidewalk
        for _ in range(rng.poisson(density * side.length / (45.0 if urban else 150.0))):
            u = rng.uniform(0.0, side.length)
            v = -sw * rng.uniform(0.22, 0.42)
            fwd = rng.random() < 0.5
            heading = side.yaw if fwd else side.yaw + math.pi
            height = float(rng.uniform(1.5, 1.9))
            speed = float(rng.uniform(0.9, 1.6))
            p0 = side.point(u, v)
            movers.offer(_mover(M.PEDESTRIAN, 0.5, 0.6, 0.0, height, p0, heading, speed))
        if rng.random() < (0.3 if urban else 0.08) * density:
            speed = float(rng.uniform(1.1, 1.5))
            start = side.point(-1.0, -sw + 0.2)
            dist = 2 * side.half_width + 0.4
            tb = float(rng.uniform(-2.0, duration_s))
            heading = math.atan2(-side.n[1], -side.n[0])
            p0 = start - np.array([math.cos(heading), math.sin(heading)]) * speed * tb
            height = float(rng.uniform(1.5, 1.9))
            te = tb + dist / speed
            movers.offer(
                _mover(M.PEDESTRIAN, 0.5, 0.6, 0.0, height, p0, heading, speed, tb=tb, te=te)
            )


def _city_to_global(rng: np.random.Generator, config: SimConfig, traj: Trajectory) -> SE2:
    """A random rotation, the start a few hundred metres from the origin."""
    theta = float(rng.uniform(-math.pi, math.pi)) if config.world.random_orientation else 0.0
    start = np.array([float(traj.pose_at(0.0)[0]), float(traj.pose_at(0.0)[1])])
    target = rng.uniform(300.0, 1700.0, size=2)
    c, s = math.cos(theta), math.sin(theta)
    return SE2(
        float(target[0] - (c * start[0] - s * start[1])),
        float(target[1] - (s * start[0] + c * start[1])),
        theta,
    )


def _global_world(town: _Town, rows: np.ndarray, mv, tf: SE2) -> World:
    """The world in the global frame, with per-object material variation."""
    rng = town.rng
    static = pack_boxes(
        rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4], rows[:, 5], rows[:, 6]
    )
    static_cls = rows[:, 7].astype(np.int32)
    gxy = tf.apply(static[:, :2]) if len(static) else np.zeros((0, 2))
    yaw_g = rows[:, 2] + tf.yaw
    static_g = pack_boxes(
        gxy[:, 0], gxy[:, 1], yaw_g, static[:, 4], static[:, 5], static[:, 6], static[:, 7]
    )
    n_static = len(static_cls)
    refl = np.clip(
        M.LIDAR_REFLECTIVITY[static_cls] * rng.uniform(0.7, 1.3, size=n_static), 0.02, 1.0
    )
    rcs_off = rng.normal(0.0, 2.0, size=n_static)
    m_refl = np.clip(
        M.LIDAR_REFLECTIVITY[mv.classes] * rng.uniform(0.7, 1.3, size=len(mv)), 0.02, 1.0
    )
    m_rcs = rng.normal(0.0, 2.0, size=len(mv))
    return World(
        town.env,
        static_g,
        yaw_g,
        static_cls,
        refl,
        rcs_off,
        mv.transformed(tf),
        m_refl,
        m_rcs,
        town.grid,
        tf,
        town.layout if town.irregular else None,
    )


def generate_world(seed: int, config: SimConfig) -> tuple[World, Trajectory, Trajectory]:
    """Build the town around a random route -> (world, true trajectory (global), same in the
    city frame). The steps draw from one generator in this order, so a seed gives one world.
    A scene's world, town or highway, is :func:`evgrid_sim.scene.world_of`'s."""
    rng, env, grid, route, warp, traj = _plan(seed, config)
    pts = _driven_path(traj, config, warp)
    near = _Near(pts)
    town = _Town(rng, env, grid, warp, config.world.traffic_density, pts, TownLayout(warp))
    b = _Builder()
    _populate_blocks(town, b, near)
    rows = _rows_array(b.rows)
    if town.irregular:
        rows = _irregular_rows(town, rows, route, near)
    static = pack_boxes(
        rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4], rows[:, 5], rows[:, 6]
    )
    movers = _MoverSet(traj, config.duration_s, static, warp)
    _following_vehicles(town, movers)
    _street_traffic(town, movers)
    _pedestrians(town, movers, config.duration_s)
    mv = movers.movers()
    tf = _city_to_global(rng, config, traj)
    return _global_world(town, rows, mv, tf), traj.transformed(tf), traj
