"""LIDAR_TOP: a 32-beam rotating lidar ray cast against the world and the ground.

Each sweep fires ``n_azimuth`` times around (one random start angle a sweep); the 32 beams
of a firing share its azimuth. A return is detected with a probability that grows with the
return power ``reflectivity * cos(incidence) / range^2`` (so grazing asphalt fades out at a
few tens of metres while walls are seen to the maximum range), times ``1 - dropout``; its
range gets Gaussian noise. The whole sweep is taken at the sweep's timestamp (no rolling
shutter), and the ego vehicle's own body is not modelled (no returns from it).
"""

from __future__ import annotations

import math

import numpy as np

from evgrid.data.sim import materials as M
from evgrid.data.sim.config import LidarConfig
from evgrid.data.sim.raycast import HIT_NONE, lidar_cast
from evgrid.data.mounts import LIDAR_MOUNT, SensorMount
from evgrid.data.sim.world import World

__all__ = ["LidarModel"]


class LidarModel:
    """Simulates sweeps of one lidar with a fixed mounting and configuration."""

    def __init__(self, cfg: LidarConfig, mount: SensorMount = LIDAR_MOUNT) -> None:
        self.cfg = cfg
        self.mount = mount
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
        sensor frame [x, y, z, intensity, ring], what each point hit: static box index,
        ``n_static + k`` for moving object k, -1 ground)."""
        cfg = self.cfg
        ex, ey, eyaw = ego_xy_yaw
        c, s = math.cos(eyaw), math.sin(eyaw)
        ox = ex + c * self.mount.x - s * self.mount.y
        oy = ey + s * self.mount.x + c * self.mount.y
        oz = self.mount.z
        syaw = eyaw + self.mount.yaw
        n_az = cfg.n_azimuth
        az_s = (rng.uniform(0.0, 2 * math.pi / n_az) + np.arange(n_az) * (2 * math.pi / n_az)).astype(np.float64)
        az_s = np.mod(az_s + math.pi, 2 * math.pi) - math.pi
        seed = np.uint64(rng.integers(0, 2**63 - 1))
        nb = cfg.n_beams
        out_t = np.empty((n_az, nb))
        out_id = np.empty((n_az, nb), dtype=np.int64)
        out_cos = np.empty((n_az, nb))
        idx = world.index
        lidar_cast(
            ox, oy, oz, az_s + syaw, self.slopes, self.max_h,
            world.boxes, world.classes, idx.start, idx.items, idx.x0, idx.y0, idx.cell, idx.nx, idx.ny,
            dyn_boxes, dyn_classes.astype(np.int32), M.LIDAR_DENSITY, M.LIDAR_PASS, seed,
            out_t, out_id, out_cos,
        )
        rng_u = rng.random((n_az, nb))
        noise = rng.standard_normal((n_az, nb))
        hit = out_id != HIT_NONE
        rng3 = out_t / self.cos_e[None, :]
        # One reflectivity table: static boxes, then moving objects, then the ground.
        refl_all = np.concatenate([world.reflectivity, dyn_reflectivity, [M.LIDAR_REFLECTIVITY[M.GROUND]]])
        refl = refl_all[np.where(out_id >= 0, out_id, len(refl_all) - 1)]
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
