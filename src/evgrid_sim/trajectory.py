"""Street grid, the ego route through it, and the ego trajectory (pose and velocity at any time).

The ego drives on the right-hand lane of a grid of streets, turning at some intersections on
circular arcs and stopping at some (stop lines), with a speed profile limited by the cruise
speed, the lateral acceleration in turns, and comfortable acceleration and braking.

Times are seconds since the first lidar sweep of the scene (``t = 0``); the trajectory also
answers for small negative times (radar sweeps just before the first lidar sweep).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from evgrid.geometry import SE2
from evgrid_sim.config import EgoConfig

__all__ = [
    "StreetGrid",
    "Route",
    "Trajectory",
    "Warp",
    "make_street_grid",
    "plan_route",
    "build_trajectory",
    "LANE_OFFSET_M",
]

#: Distance of the right lane's centre line from the street's centre line, metres.
LANE_OFFSET_M = 1.65
#: Length of path kept before the start point, so that poses exist for t < 0.
_PREROLL_M = 60.0


@dataclass(frozen=True, eq=False)
class StreetGrid:
    """A Manhattan street grid in the city frame: streets along y at ``xs``, along x at ``ys``.

    ``*_hw``: half width of the carriageway (curb to curb / 2), ``*_sw``: width of the band
    between curb and property line (sidewalk, tree strip), ``*_parking``: a parking lane on both
    sides. All metres.
    """

    environment: str
    xs: np.ndarray
    x_hw: np.ndarray
    x_sw: np.ndarray
    x_parking: np.ndarray
    ys: np.ndarray
    y_hw: np.ndarray
    y_sw: np.ndarray
    y_parking: np.ndarray


@dataclass(frozen=True)
class Warp:
    """A smooth shear of the city frame that bends straight streets into curves and makes junction
    angles differ from 90 deg: ``w(x, y) = (x + ax sin(kx y + px), y + ay sin(ky x + py))``.

    Its Jacobian ``[[1, ax kx cos(kx y + px)], [ay ky cos(ky x + py), 1]]`` has determinant
    ``>= 1 - slope_x slope_y > 0`` when both slopes ``|ax kx|, |ay ky|`` stay below 1, so the map
    never folds; with slopes <= 0.25 distances along a street change by at most 3 %.
    """

    ax: float
    kx: float
    px: float
    ay: float
    ky: float
    py: float

    #: Largest slope of either shear term (the tangent of the largest bend of a street).
    MAX_SLOPE = 0.25

    @staticmethod
    def draw(rng: np.random.Generator) -> Warp:
        """Amplitudes up to 20 m and wavelengths 250-600 m, with slopes <= MAX_SLOPE."""
        out = []
        for _ in range(2):
            wavelength = float(rng.uniform(250.0, 600.0))
            k = 2.0 * math.pi / wavelength
            amp = float(rng.uniform(0.3, 1.0)) * min(20.0, 0.9 * Warp.MAX_SLOPE / k)
            amp *= 1.0 if rng.random() < 0.5 else -1.0
            out += [amp, k, float(rng.uniform(0.0, 2.0 * math.pi))]
        return Warp(*out)

    def apply(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Warped coordinates of city-frame points (m)."""
        return x + self.ax * np.sin(self.kx * y + self.px), y + self.ay * np.sin(
            self.ky * x + self.py
        )

    def jacobian(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Off-diagonal terms (d wx / dy, d wy / dx) of the Jacobian; the diagonal is 1."""
        return self.ax * self.kx * np.cos(self.kx * y + self.px), self.ay * self.ky * np.cos(
            self.ky * x + self.py
        )

    def direction(
        self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Warped heading (rad, unwrapped next to ``yaw``), stretch of a unit vector at ``yaw``."""
        a, b = self.jacobian(x, y)
        c, s = np.cos(yaw), np.sin(yaw)
        ex, ey = c + a * s, b * c + s
        turn = np.arctan2(ey * c - ex * s, ex * c + ey * s)  # small: the warp rotates by < 15 deg
        return yaw + turn, np.hypot(ex, ey)

    def inverse(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """City-frame points that warp to ``(x, y)`` (fixed-point iteration, a contraction by the
        slopes)."""
        ux, uy = np.array(x, dtype=np.float64), np.array(y, dtype=np.float64)
        for _ in range(30):
            ux = x - self.ax * np.sin(self.kx * uy + self.px)
            uy = y - self.ay * np.sin(self.ky * ux + self.py)
        return ux, uy

    def path(self, path: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
        """A dense path ``(s, x, y, yaw, kappa)`` warped, with its arc length and curvature
        recomputed."""
        _, x, y, yaw, _ = path
        wx, wy = self.apply(x, y)
        wyaw, _ = self.direction(x, y, yaw)
        s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(wx), np.diff(wy)))])
        # Central differences (a zero-length piece of the path repeats a point, never two).
        kappa = np.gradient(wyaw) / np.maximum(np.gradient(s), 1e-6)
        return s, wx, wy, wyaw, kappa


@dataclass(frozen=True, eq=False)
class Route:
    """The ego's planned route in the city frame: corner points, fillet radii, stops."""

    points: list[np.ndarray]
    radii: list[float]
    #: Stop points (on the lane line, before an intersection's crosswalk) and dwell times (s).
    stop_points: list[np.ndarray]
    stop_dwell: list[float]
    start: np.ndarray


def make_street_grid(
    rng: np.random.Generator, environment: str, extent_m: float, irregular: bool = False
) -> StreetGrid:
    """Random street positions and widths covering ``[-extent_m, extent_m]^2`` (metres).

    ``irregular``: widths vary more from street to street (half widths 0.2 m narrower to 0.5 m
    wider, a fifth of the streets with a second lane each way, bands of 3-7 m to the property line).
    """
    if environment == "urban":
        block, hw_lane, park_p, park_w, shoulder, sw = (60.0, 110.0), 3.3, 0.7, 2.4, 0.5, (3.0, 5.0)
    elif environment == "suburban":
        block, hw_lane, park_p, park_w, shoulder, sw = (90.0, 160.0), 3.2, 0.3, 2.2, 0.6, (3.5, 5.0)
    else:
        raise ValueError(f"environment must be 'urban' or 'suburban', got {environment!r}")

    def axis() -> tuple[np.ndarray, ...]:
        # Streets on both sides of 0 so the start (near the origin) lies mid-grid.
        pos = [float(rng.uniform(-0.5, 0.5) * block[0])]
        while pos[-1] < extent_m:
            pos.append(pos[-1] + float(rng.uniform(*block)))
        while pos[0] > -extent_m:
            pos.insert(0, pos[0] - float(rng.uniform(*block)))
        c = np.asarray(pos)
        parking = rng.random(len(c)) < park_p
        hw = hw_lane + np.where(parking, park_w, shoulder)
        sidewalk = rng.uniform(*sw, size=len(c))
        if irregular:
            hw = (
                hw
                + rng.uniform(-0.2, 0.5, size=len(c))
                + np.where(rng.random(len(c)) < 0.2, 3.3, 0.0)
            )
            sidewalk = sidewalk + rng.uniform(0.0, 2.0, size=len(c))
        return c, hw, sidewalk, parking

    xs, x_hw, x_sw, x_parking = axis()
    ys, y_hw, y_sw, y_parking = axis()
    return StreetGrid(environment, xs, x_hw, x_sw, x_parking, ys, y_hw, y_sw, y_parking)


def _lane_coord(street_c: float, axis: int, d: int) -> float:
    # Right-hand traffic: heading +x the right side is -y; heading +y the right side is +x.
    return street_c - d * LANE_OFFSET_M if axis == 0 else street_c + d * LANE_OFFSET_M


def plan_route(
    rng: np.random.Generator, grid: StreetGrid, length_m: float, cfg: EgoConfig
) -> Route:
    """A random drive through the grid of at least ``length_m`` metres (city frame)."""
    axis = int(rng.integers(2))  # 0: along x on a street of ys; 1: along y on a street of xs
    d = 1 if rng.random() < 0.5 else -1
    along = grid.ys if axis == 0 else grid.xs
    k = int(np.argmin(np.abs(along)))
    cross = grid.xs if axis == 0 else grid.ys
    # Start mid-block around coordinate 0 along the driving axis.
    j = int(np.searchsorted(cross, 0.0))
    lo, hi = cross[max(j - 1, 0)], cross[min(j, len(cross) - 1)]
    pos = float(lo + (hi - lo) * rng.uniform(0.3, 0.7))
    lane = _lane_coord(float(along[k]), axis, d)
    start = np.array([pos, lane]) if axis == 0 else np.array([lane, pos])
    heading = np.array([d, 0.0]) if axis == 0 else np.array([0.0, d])
    # The start point is on the first leg, not a corner: the path begins _PREROLL_M before it.
    points = [start - heading * _PREROLL_M]
    radii: list[float] = []
    stop_points: list[np.ndarray] = []
    stop_dwell: list[float] = []
    total = 0.0
    last = start.copy()
    while total < length_m:
        cross = grid.xs if axis == 0 else grid.ys
        cross_hw = grid.x_hw if axis == 0 else grid.y_hw
        cross_sw = grid.x_sw if axis == 0 else grid.y_sw
        # Skip the street just turned from (its centre is a lane offset away from pos).
        idx = np.nonzero(cross > pos + 5.0)[0] if d > 0 else np.nonzero(cross < pos - 5.0)[0]
        if len(idx) == 0:
            raise RuntimeError(
                "street grid too small for the route; this is a bug in the simulator"
            )
        i = int(idx[0]) if d > 0 else int(idx[-1])
        c = float(cross[i])
        # The stop line: before the crosswalk that lines the cross street.
        stop_c = c - d * (cross_hw[i] + 0.5 * cross_sw[i] + 2.0)
        stop_pt = np.array([stop_c, lane]) if axis == 0 else np.array([lane, stop_c])
        dist_to_stop = abs(stop_c - pos) + total
        if dist_to_stop > 12.0 and rng.random() < cfg.stop_probability:
            stop_points.append(stop_pt)
            stop_dwell.append(float(rng.uniform(*cfg.stop_duration_s)))
        if rng.random() < cfg.turn_probability:
            left = rng.random() < 0.5
            # Heading h = (d, 0) or (0, d); left of h is (-h_y, h_x).
            h = np.array([d, 0.0]) if axis == 0 else np.array([0.0, d])
            new_h = np.array([-h[1], h[0]]) if left else np.array([h[1], -h[0]])
            new_axis = 1 - axis
            new_d = int(new_h[0] if new_axis == 0 else new_h[1])
            new_lane = _lane_coord(c, new_axis, new_d)
            corner = np.array([new_lane, lane]) if axis == 0 else np.array([lane, new_lane])
            total += float(np.abs(corner - last).sum())
            points.append(corner)
            # Left turns cross the oncoming lane on a wider arc.
            radii.append(float(rng.uniform(10.0, 13.0) if left else rng.uniform(5.5, 7.0)))
            last = corner
            pos = lane  # the old street's lane coordinate is the new axis position
            axis, d, lane = new_axis, new_d, new_lane
        else:
            total += abs(c - pos)
            pos = c
            last = np.array([pos, lane]) if axis == 0 else np.array([lane, pos])
    h = np.array([d, 0.0]) if axis == 0 else np.array([0.0, d])
    points.append(last + h * 60.0)
    return Route(points, radii, stop_points, stop_dwell, start)


def _dense_path(
    points: list[np.ndarray], radii: list[float], ds: float = 0.25
) -> tuple[np.ndarray, ...]:
    """Polyline through ``points`` with circular fillets -> (s, x, y, yaw, kappa) samples."""
    pts = [np.asarray(p, dtype=np.float64) for p in points]
    xs: list[np.ndarray] = []
    ys: list[np.ndarray] = []
    yaws: list[np.ndarray] = []
    kap: list[np.ndarray] = []
    cur = pts[0]
    for k in range(1, len(pts)):
        a, b = pts[k - 1], pts[k]
        h_in = (b - a) / np.linalg.norm(b - a)
        if k < len(pts) - 1:
            r = radii[k - 1]
            c = pts[k + 1]
            h_out = (c - b) / np.linalg.norm(c - b)
            t_in = b - h_in * r
            t_out = b + h_out * r
        else:
            t_in = b
        # Straight piece cur -> t_in.
        length = float(np.linalg.norm(t_in - cur))
        n = max(int(math.ceil(length / ds)), 1)
        u = np.arange(n) / n
        xs.append(cur[0] + (t_in[0] - cur[0]) * u)
        ys.append(cur[1] + (t_in[1] - cur[1]) * u)
        yaws.append(np.full(n, math.atan2(h_in[1], h_in[0])))
        kap.append(np.zeros(n))
        if k < len(pts) - 1:
            cross = h_in[0] * h_out[1] - h_in[1] * h_out[0]
            sign = 1.0 if cross > 0 else -1.0  # +1: left (counter-clockwise) turn
            normal = np.array([-h_in[1], h_in[0]]) * sign
            centre = t_in + normal * r
            a0 = math.atan2(t_in[1] - centre[1], t_in[0] - centre[0])
            sweep = sign * math.acos(max(-1.0, min(1.0, float(h_in @ h_out))))
            n = max(int(math.ceil(abs(sweep) * r / ds)), 1)
            ang = a0 + sweep * (np.arange(n) / n)
            xs.append(centre[0] + r * np.cos(ang))
            ys.append(centre[1] + r * np.sin(ang))
            yaws.append(math.atan2(h_in[1], h_in[0]) + sweep * (np.arange(n) / n))
            kap.append(np.full(n, sign / r))
            cur = t_out
        else:
            cur = t_in
    xs.append(np.array([cur[0]]))
    ys.append(np.array([cur[1]]))
    yaws.append(np.array([yaws[-1][-1]]))
    kap.append(np.zeros(1))
    x = np.concatenate(xs)
    y = np.concatenate(ys)
    yaw = np.unwrap(np.concatenate(yaws))
    kappa = np.concatenate(kap)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    return s, x, y, yaw, kappa


class Trajectory:
    """The ego's path (city or global frame) and its time profile ``s(t)``; poses are rear-axle
    poses."""

    def __init__(
        self,
        path: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
        profile_t: np.ndarray,
        profile_s: np.ndarray,
        profile_v: np.ndarray,
        s0: float,
        v0: float,
        frame: SE2 = SE2(),
    ) -> None:
        self.path_s, self.path_x, self.path_y, self.path_yaw, self.path_kappa = path
        self.profile_t = profile_t
        self.profile_s = profile_s
        self.profile_v = profile_v
        self.s0 = s0
        self.v0 = v0
        #: The transform that took the city frame to this trajectory's frame.
        self.frame = frame

    def transformed(self, tf: SE2) -> Trajectory:
        """The same trajectory with its path moved by ``tf`` (city -> global)."""
        xy = tf.apply(np.stack([self.path_x, self.path_y], axis=1))
        path = (self.path_s, xy[:, 0], xy[:, 1], self.path_yaw + tf.yaw, self.path_kappa)
        return Trajectory(
            path, self.profile_t, self.profile_s, self.profile_v, self.s0, self.v0, tf @ self.frame
        )

    def s_at(self, t: np.ndarray | float) -> np.ndarray:
        """Arc length (m) along the path at time(s) ``t`` (s); linear before t = 0."""
        t = np.asarray(t, dtype=np.float64)
        # Constant acceleration between profile points, so that s(t) integrates speed_at(t)
        # exactly (a linear interpolation of s would disagree with the speed by up to dv / 2).
        pt, ps, pv = self.profile_t, self.profile_s, self.profile_v
        k = np.clip(np.searchsorted(pt, t, side="right") - 1, 0, len(pt) - 2)
        dt = pt[k + 1] - pt[k]
        tau = np.clip(t - pt[k], 0.0, dt)
        acc = (pv[k + 1] - pv[k]) / np.maximum(dt, 1e-12)
        s = np.minimum(ps[k] + pv[k] * tau + 0.5 * acc * tau * tau, ps[k + 1])
        s = np.where(t >= pt[-1], ps[-1], s)
        return np.where(t < 0.0, self.s0 + self.v0 * t, s)

    def speed_at(self, t: np.ndarray | float) -> np.ndarray:
        """Ground speed (m/s) at time(s) ``t`` (s)."""
        t = np.asarray(t, dtype=np.float64)
        return np.where(t < 0.0, self.v0, np.interp(t, self.profile_t, self.profile_v))

    def pose_at_s(self, s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Path pose (x, y in m, yaw in rad) at arc length(s) ``s`` (m)."""
        s = np.asarray(s, dtype=np.float64)
        return (
            np.interp(s, self.path_s, self.path_x),
            np.interp(s, self.path_s, self.path_y),
            np.interp(s, self.path_s, self.path_yaw),
        )

    def pose_at(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True ego pose (x, y in m, yaw in rad) at time(s) ``t`` (s)."""
        return self.pose_at_s(self.s_at(t))

    def velocity_at(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True ego velocity (vx, vy m/s, frame of the path) and yaw rate (rad/s) at ``t`` (s)."""
        s = self.s_at(t)
        v = self.speed_at(t)
        yaw = np.interp(s, self.path_s, self.path_yaw)
        kappa = np.interp(s, self.path_s, self.path_kappa)
        return v * np.cos(yaw), v * np.sin(yaw), v * kappa

    def se2_at(self, t: float) -> SE2:
        """True ego pose at time ``t`` (s) as an :class:`SE2`."""
        x, y, yaw = self.pose_at(float(t))
        return SE2(float(x), float(y), float(math.remainder(float(yaw), 2 * math.pi)))


def build_trajectory(
    rng: np.random.Generator,
    route: Route,
    cfg: EgoConfig,
    cruise: float,
    duration_s: float,
    warp: Warp | None = None,
) -> Trajectory:
    """Speed profile along the route: cruise speed, curve limits, stops, acceleration limits.

    ``warp`` bends the route's path first, so that arc length, curvature (and the speed limits
    it sets) and poses all belong to the curved street."""
    path = _dense_path(route.points, route.radii)
    stop_points = route.stop_points
    s_start = _PREROLL_M
    if warp is not None:
        s_flat = path[0]
        path = warp.path(path)
        s_start = float(np.interp(_PREROLL_M, s_flat, path[0]))
        stop_points = [np.array(warp.apply(p[0], p[1])) for p in stop_points]
    s_path, x, y, _, kappa = path
    ds = 0.5
    s = np.arange(s_start, s_path[-1], ds)
    # Curvature limit with a little look-around so the speed is already low on entering the arc.
    k_abs = np.abs(np.interp(s, s_path, kappa))
    k_abs = np.maximum.reduce([k_abs, np.roll(k_abs, 2), np.roll(k_abs, -2)])
    # Cruise speed varies a little from leg to leg, smoothly.
    wobble = 1.0 + 0.08 * np.sin(2 * np.pi * s / rng.uniform(80, 160) + rng.uniform(0, 2 * np.pi))
    cap = np.minimum(cruise * wobble, np.sqrt(cfg.max_lateral_accel_mps2 / np.maximum(k_abs, 1e-9)))
    dwell = np.zeros_like(s)
    for p, w in zip(stop_points, route.stop_dwell):
        i = int(np.argmin(np.hypot(np.interp(s, s_path, x) - p[0], np.interp(s, s_path, y) - p[1])))
        cap[i] = 0.0
        dwell[i] = w
    at_rest = rng.random() < cfg.start_at_rest_probability
    v = cap.copy()
    v[0] = 0.0 if at_rest else cap[0]
    a_acc, a_dec = cfg.max_accel_mps2, cfg.max_decel_mps2
    for i in range(1, len(s)):
        v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2 * a_acc * ds))
    for i in range(len(s) - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * a_dec * ds))
    if at_rest:
        v[0] = 0.0
    # Time along the profile (trapezoid in v), with the dwell inserted after each stop.
    t_list = [0.0]
    s_list = [float(s[0])]
    v_list = [float(v[0])]
    if at_rest:
        # Waiting a moment at the start, like at a red light.
        w = float(rng.uniform(0.5, 3.0))
        t_list.append(w)
        s_list.append(float(s[0]))
        v_list.append(0.0)
    for i in range(1, len(s)):
        vm = 0.5 * (v[i - 1] + v[i])
        t_list.append(t_list[-1] + ds / max(vm, 1e-3))
        s_list.append(float(s[i]))
        v_list.append(float(v[i]))
        if dwell[i] > 0:
            t_list.append(t_list[-1] + float(dwell[i]))
            s_list.append(float(s[i]))
            v_list.append(0.0)
        if t_list[-1] > duration_s + 5.0:
            break
    if t_list[-1] < duration_s + 1.0:
        raise RuntimeError("route too short for the scene duration; this is a bug in the simulator")
    return Trajectory(
        path, np.asarray(t_list), np.asarray(s_list), np.asarray(v_list), float(s[0]), float(v[0])
    )
