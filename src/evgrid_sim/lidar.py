"""LIDAR_TOP: a 32-beam rotating lidar ray cast against the world and the ground.

Each sweep fires ``n_azimuth`` times around (one random start angle a sweep); the 32 beams
of a firing share its azimuth. A return is detected with a probability that grows with the
return power ``reflectivity * cos(incidence) / range^2`` (so grazing asphalt fades out at a
few tens of metres while walls are seen to the maximum range), times ``1 - dropout``; its
range gets Gaussian noise. The whole sweep is taken at the sweep's timestamp (no rolling
shutter).

The ego vehicle's own body is in the way of the lower beams, as on a roof-mounted HDL-32E
(``LidarConfig.self_returns``, on by default): :data:`EGO_BODY_BOXES` (ego frame: the body, the
cabin, a sensor rack whose bars are 0.1 m below the sensor, mirrors) stop the beams that meet them
before anything else, and their hits are returned like any other (thousands of points a sweep
within 3 m of the sensor, many of them just below it; docs/simulator.md). The random numbers
drawn do not depend on them, so every return that does not meet the body is the same with or
without.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from evgrid.data.mounts import LIDAR_MOUNT, NUSCENES_CAR, SensorMount
from evgrid_sim import materials as M
from evgrid_sim.config import LidarConfig
from evgrid_sim.raycast import HIT_NONE, lidar_cast
from evgrid_sim.world import World

__all__ = ["LidarModel", "EGO_BODY_BOXES", "EGO_HIT"]

#: What a point hit when it is a return from the ego vehicle's own body.
EGO_HIT = -3
#: Reflectivity of the ego vehicle's paint and plastics (0-1).
_EGO_REFLECTIVITY = 0.45

#: The ego vehicle's body as axis-aligned boxes in the ego frame: (x0, y0, z0, x1, y1, z1),
#: metres, origin on the ground at the rear axle (the one description: ``NUSCENES_CAR``).
EGO_BODY_BOXES: np.ndarray = NUSCENES_CAR.body_boxes


@numba.njit(cache=True)
def _k_body_hits(origin, dirs, boxes, best, cos):  # pragma: no cover - compiled
    for i in range(dirs.shape[0]):
        for b in range(boxes.shape[0]):
            t_in, t_out, axis = -np.inf, np.inf, 0
            for a in range(3):
                d = dirs[i, a]
                lo_b, hi_b = boxes[b, a] - origin[a], boxes[b, a + 3] - origin[a]
                if d == 0.0:  # parallel to this slab: inside it or a miss
                    if lo_b > 0.0 or hi_b < 0.0:
                        t_in = np.inf
                    continue
                inv = 1.0 / d
                t0, t1 = lo_b * inv, hi_b * inv
                lo, hi = min(t0, t1), max(t0, t1)
                if lo > t_in:
                    t_in, axis = lo, a
                t_out = min(t_out, hi)
            if t_in <= t_out and 0.0 < t_in < best[i]:
                best[i] = t_in
                cos[i] = abs(dirs[i, axis])


def body_hits(
    origin: np.ndarray, dirs: np.ndarray, boxes: np.ndarray = EGO_BODY_BOXES
) -> tuple[np.ndarray, np.ndarray]:
    """First hit of rays on axis-aligned boxes (slab test): (distance along the unit ``dirs``,
    inf where none; |cosine| between the ray and the face it enters)."""
    flat = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1, 3)
    best = np.full(flat.shape[0], np.inf)
    cos = np.zeros(flat.shape[0])
    _k_body_hits(
        np.asarray(origin, dtype=np.float64),
        flat,
        np.ascontiguousarray(boxes, dtype=np.float64),
        best,
        cos,
    )
    return best.reshape(dirs.shape[:-1]), cos.reshape(dirs.shape[:-1])


class LidarModel:
    """Simulates sweeps of one lidar with a fixed mounting and configuration."""

    def __init__(
        self, cfg: LidarConfig, mount: SensorMount = LIDAR_MOUNT, body: np.ndarray | None = None
    ) -> None:
        self.cfg = cfg
        self.mount = mount
        #: the ego body's boxes (another vehicle's: ``Vehicle.body_boxes``)
        self.body = EGO_BODY_BOXES if body is None else np.asarray(body, dtype=np.float64)
        self.elev = np.radians(np.linspace(cfg.elev_min_deg, cfg.elev_max_deg, cfg.n_beams))
        self.slopes = np.tan(self.elev)
        self.cos_e = np.cos(self.elev)
        self.sin_e = np.sin(self.elev)
        # A beam is followed until its slant range reaches max_range_m.
        self.max_h = cfg.max_range_m * self.cos_e

    def sweep(
        self,
        world: World,
        dyn_boxes: np.ndarray,
        dyn_classes: np.ndarray,
        dyn_reflectivity: np.ndarray,
        ego_xy_yaw: tuple[float, float, float],
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One sweep at the ego pose ``(x, y, yaw)`` (m, rad) -> (points ``(n, 5)`` float32 in the
        sensor frame [x, y, z, intensity, ring], what each point hit: static box index, -3 (EGO_HIT)
        the ego body, ``n_static + k`` for moving object k, -1 ground)."""
        az_s, out_t, out_id, out_cos = self._cast(world, dyn_boxes, dyn_classes, ego_xy_yaw, rng)
        return self._returns(world, dyn_reflectivity, az_s, out_t, out_id, out_cos, rng)

    def _cast(
        self,
        world: World,
        dyn_boxes: np.ndarray,
        dyn_classes: np.ndarray,
        ego_xy_yaw: tuple[float, float, float],
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The sweep's beams cast (azimuths at a random phase): (azimuth per column in the
        sensor frame, and per column and beam the horizontal distance to the hit, what it hit
        and the cosine of incidence)."""
        cfg = self.cfg
        ex, ey, eyaw = ego_xy_yaw
        c, s = math.cos(eyaw), math.sin(eyaw)
        ox = ex + c * self.mount.x - s * self.mount.y
        oy = ey + s * self.mount.x + c * self.mount.y
        oz = self.mount.z
        syaw = eyaw + self.mount.yaw
        n_az = cfg.n_azimuth
        az_s = (
            rng.uniform(0.0, 2 * math.pi / n_az) + np.arange(n_az) * (2 * math.pi / n_az)
        ).astype(np.float64)
        az_s = np.mod(az_s + math.pi, 2 * math.pi) - math.pi
        seed = np.uint64(rng.integers(0, 2**63 - 1))
        nb = cfg.n_beams
        out_t = np.empty((n_az, nb))
        out_id = np.empty((n_az, nb), dtype=np.int64)
        out_cos = np.empty((n_az, nb))
        lidar_cast(
            (ox, oy, oz),
            az_s + syaw,
            self.slopes,
            self.max_h,
            world.cast_scene(dyn_boxes, dyn_classes),
            (M.LIDAR_DENSITY, M.LIDAR_PASS),
            seed,
            (out_t, out_id, out_cos),
        )
        if cfg.self_returns:
            self._add_body(az_s, out_t, out_id, out_cos)
        return az_s, out_t, out_id, out_cos

    def _returns(
        self,
        world: World,
        dyn_reflectivity: np.ndarray,
        az_s: np.ndarray,
        out_t: np.ndarray,
        out_id: np.ndarray,
        out_cos: np.ndarray,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The cast beams that return (range, detection probability from reflectivity and
        incidence, dropout), as :meth:`sweep`'s points and what each hit."""
        cfg = self.cfg
        n_az, nb = out_t.shape
        rng_u = rng.random((n_az, nb))
        noise = rng.standard_normal((n_az, nb))
        hit = out_id != HIT_NONE
        rng3 = out_t / self.cos_e[None, :]
        # One reflectivity table: static boxes, then moving objects, then the ground.
        refl_all = np.concatenate(
            [
                world.reflectivity,
                dyn_reflectivity,
                [M.LIDAR_REFLECTIVITY[M.GROUND]],
                [_EGO_REFLECTIVITY],
            ]
        )
        refl = refl_all[
            np.where(
                out_id >= 0,
                out_id,
                np.where(out_id == EGO_HIT, len(refl_all) - 1, len(refl_all) - 2),
            )
        ]
        cosv = np.maximum(out_cos, 0.02)
        power = refl * cosv / np.maximum(rng3, 0.1) ** 2
        p_det = (1.0 - cfg.dropout) * (1.0 - np.exp(-power / cfg.power_threshold))
        keep = hit & (rng3 >= cfg.min_range_m) & (rng_u < p_det)
        r = rng3[keep] + cfg.range_noise_m * noise[keep]
        cols, beams = np.nonzero(keep)
        ce = self.cos_e[beams]
        pts = np.empty((len(r), 5), dtype=np.float32)
        pts[:, 0] = r * ce * np.cos(az_s[cols])
        pts[:, 1] = r * ce * np.sin(az_s[cols])
        pts[:, 2] = r * self.sin_e[beams]
        # Intensity (0-255 integer counts): albedo and incidence, with a little speckle.
        inten = 255.0 * refl[keep] * (0.25 + 0.75 * cosv[keep]) + rng.normal(0.0, 1.5, size=len(r))
        pts[:, 3] = np.clip(np.rint(inten), 0, 255)
        pts[:, 4] = beams
        return pts, out_id[keep]

    def _add_body(
        self, az_s: np.ndarray, out_t: np.ndarray, out_id: np.ndarray, out_cos: np.ndarray
    ) -> None:
        """Let the ego body stop the beams that meet it before the world (in place)."""
        m = self.mount
        az = az_s[:, None] + m.yaw  # beam azimuths in the ego frame
        dirs = np.stack(
            np.broadcast_arrays(
                np.cos(az) * self.cos_e, np.sin(az) * self.cos_e, self.sin_e[None, :]
            ),
            axis=-1,
        )
        t3, cos = body_hits(np.array([m.x, m.y, m.z]), dirs, self.body)
        t = t3 * self.cos_e[None, :]  # horizontal distance, as out_t
        closer = np.isfinite(t) & ((out_id == HIT_NONE) | (t < out_t))
        out_t[closer] = t[closer]
        out_id[closer] = EGO_HIT
        out_cos[closer] = cos[closer]
