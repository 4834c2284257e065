"""The five radars (Continental ARS 408-21 as mounted on the nuScenes vehicles).

A sweep casts horizontal beams over the near scan (+-60 deg; 70 m out to +-45 deg, less at the
edges) and the far scan (+-9 deg, 0.2-250 m; the two scans report their clusters apart), each
beam with a random azimuth inside its bin and finer than a resolution cell. Along a beam up to
four objects are considered in range order; the beam goes on past an object with a
class-dependent probability (under vehicles, through foliage and fences). Each object met
becomes a *scatterer* if the strip of surface the beam stands for holds a scattering centre
(centres are so many per metre of surface, ``RadarModel._centre_probability``), with power
``SNR = RCS(class, incidence) + fluctuation + antenna gain - 40 log10(range / r_ref)``, the
fluctuation being Swerling I/II (exponential power) times a log-normal aspect term.

Besides these *real* scatterers a sweep has:

* *ghosts*: a beam that meets a mirroring surface (building, wall, vehicle, barrier) is also
  reflected specularly; if the reflected beam meets an object, a scatterer appears along the
  original beam at the total path length, i.e. at the object's mirror image behind the
  surface, with the mirrored object's velocity (two-way bounce loss ``multipath_loss_db``);
* *clutter*: Poisson false alarms uniform over the range-azimuth cells, mostly without ground
  speed, and road-surface clutter (kerbs, drain covers) in the free space before each beam's
  first obstacle, static and mostly near.

Scatterers sharing a resolution cell (range bin x azimuth bin, even in sin(azimuth), x Doppler
bin) merge into one cluster at their power-weighted mean position, detected with a logistic
probability of the summed power; at most ``max_detections`` clusters are reported.
Measurements get range, azimuth (worse towards the edge) and Doppler noise by the datasheet's
accuracies; positions are 2-D (``z = 0`` in the sensor frame, as in nuScenes). ``vx, vy`` are
the radial velocity relative to the sensor resolved along the measured azimuth; ``vx_comp,
vy_comp`` the same with the sensor's own motion (from odometry) removed. The validity fields
follow the ARS 408 cluster list (see ``frame.RADAR_COLUMNS``): ghosts and false alarms are
flagged more often than real detections, but not always, as in the real sensor. Every default
and its source: docs/radar-calibration.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from evgrid.data.mounts import SensorMount
from evgrid_sim import materials as M
from evgrid_sim.config import RadarConfig
from evgrid_sim.raycast import radar_cast
from evgrid_sim.world import World

__all__ = ["RadarModel", "RADAR_REAL", "RADAR_CLUTTER", "RADAR_GHOST", "RADAR_LABEL_NAMES"]

#: Ground-truth label of each radar detection (kept by the simulator, not in the frame contract).
RADAR_REAL = 0
RADAR_CLUTTER = 1
RADAR_GHOST = 2
RADAR_LABEL_NAMES: tuple[str, ...] = ("real", "clutter", "ghost")

_K_HITS = 4


def _choice(
    rng: np.random.Generator, values: tuple[int, ...], probs: tuple[float, ...], n: int
) -> np.ndarray:
    return np.asarray(values, dtype=np.float64)[
        rng.choice(len(values), size=n, p=np.asarray(probs) / sum(probs))
    ]


class RadarModel:
    """Simulates sweeps of one radar with a fixed mounting and configuration."""

    def __init__(self, cfg: RadarConfig, mount: SensorMount) -> None:
        self.cfg = cfg
        self.mount = mount
        self.tan_beta = math.tan(math.radians(cfg.elevation_half_deg))
        # : Per point of the last sweep: true range (m), azimuth (rad) and scan (1 far) of its
        # strongest scatterer.
        self.last_truth = np.zeros((0, 3))

    def max_range(self, az: np.ndarray) -> np.ndarray:
        """Near-scan reach (m) at sensor azimuth ``az`` (rad)."""
        cfg = self.cfg
        a = np.abs(np.degrees(az))
        frac = np.clip((a - 45.0) / max(cfg.fov_deg - 45.0, 1e-6), 0.0, 1.0)
        return np.where(
            a <= 45.0,
            cfg.max_range_m,
            cfg.max_range_m + frac * (cfg.edge_range_m - cfg.max_range_m),
        )

    def _snr(
        self, rcs_db: np.ndarray, rng_m: np.ndarray, az: np.ndarray, far: np.ndarray
    ) -> np.ndarray:
        cfg = self.cfg
        gain = -10.0 * (np.degrees(az) / cfg.fov_deg) ** 2 + np.where(far, cfg.far_gain_db, 0.0)
        return rcs_db + gain - 40.0 * np.log10(np.maximum(rng_m, 0.5) / cfg.reference_range_m)

    def _centre_probability(
        self,
        kk: np.ndarray,
        rng_m: np.ndarray,
        far: np.ndarray,
        cos_inc: np.ndarray,
        size_m: np.ndarray | None = None,
    ) -> np.ndarray:
        """Chance that a simulated beam's hit on class ``kk`` at range ``rng_m`` (m), incidence
        cosine ``cos_inc``, on an object ``size_m`` (m) wide holds a scattering centre.

        Centres are a property of the surface (so many per metre), so the chance grows with the
        strip of surface the beam stands for, ``range * beam spacing / cos(incidence)``:
        ``1 - (1 - p) ** (strip / ref)`` with ``p = RADAR_SCATTER * scatter_probability`` and
        ``ref = scatter_strip_m``, or the object's width if narrower (a pole is one centre
        however many beams hit it). Without this a near object, which many beams hit, would hold
        many more centres than the same object far away."""
        cfg = self.cfg
        step = np.radians(np.where(far, cfg.far_spacing_deg, cfg.ray_spacing_deg))
        p = np.minimum(M.RADAR_SCATTER[kk] * cfg.scatter_probability, 1.0 - 1e-12)
        strip = np.maximum(rng_m, 0.0) * step / np.maximum(cos_inc, 0.05)
        ref = cfg.scatter_strip_m if size_m is None else np.clip(size_m, 1e-3, cfg.scatter_strip_m)
        return 1.0 - (1.0 - p) ** (strip / ref)

    def noise_sigmas(self, az: np.ndarray, far: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """1-sigma range (m) and azimuth (rad) noise of detections at sensor azimuth ``az`` (rad):
        the datasheet's accuracies, near scan interpolated over 0 deg, 45 deg and the edge."""
        cfg = self.cfg
        a = np.abs(np.degrees(az))
        near_az = np.interp(
            a,
            [0.0, 45.0, max(cfg.fov_deg, 45.0 + 1e-6)],
            [cfg.azimuth_noise_deg, cfg.azimuth_noise_mid_deg, cfg.azimuth_noise_edge_deg],
        )
        sig_az = np.radians(np.where(far, cfg.far_azimuth_noise_deg, near_az))
        sig_r = np.where(far, cfg.far_range_noise_m, cfg.range_noise_m)
        return sig_r, sig_az

    def _fluctuation(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """Per-look RCS fluctuation, dB: Swerling I/II (exponential power, many comparable
        scatterers) times a log-normal aspect term of ``rcs_fluctuation_db``."""
        f = rng.normal(0.0, self.cfg.rcs_fluctuation_db, n)
        if self.cfg.swerling:
            f += 10.0 * np.log10(np.maximum(rng.exponential(1.0, n), 1e-6))
        return f

    def sweep(
        self,
        world: World,
        dyn_boxes: np.ndarray,
        dyn_classes: np.ndarray,
        dyn_vel: np.ndarray,
        dyn_rcs_offset: np.ndarray,
        ego_xy_yaw: tuple[float, float, float],
        ego_speed_yawrate: tuple[float, float],
        odo_speed_yawrate: tuple[float, float],
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One sweep at ego pose ``(x, y, yaw)`` (m, rad), true and odometry (speed m/s, yaw
        rate rad/s) -> (points ``(n, 12)`` float32 in the sensor frame, ``RADAR_COLUMNS``;
        labels (n,) uint8).

        ``self.last_truth`` then holds, per point, the true range (m), azimuth (rad) and scan
        (1 far) of its strongest scatterer, for calibration. The random numbers are drawn in
        the order of the steps below, so a seed gives the same sweep."""
        beams = self._beams(ego_xy_yaw, ego_speed_yawrate, odo_speed_yawrate, rng)
        scene = world.cast_scene(dyn_boxes, dyn_classes)
        hits = self._cast(scene, beams, beams.gdx, beams.gdy, beams.reach, None)
        targets = _Targets(world, scene, dyn_vel, dyn_rcs_offset)
        sc = _Scatterers()
        self._real_scatterers(sc, beams, hits, targets, rng)
        self._ghosts(sc, beams, hits, targets, scene, rng)
        self._false_alarms(sc, beams, rng)
        self._road_clutter(sc, beams, hits, rng)
        self.last_truth = np.zeros((0, 3))
        if not sc:
            return np.zeros((0, 12), np.float32), np.zeros(0, np.uint8)
        return self._report(sc, beams, rng)

    def _beams(
        self,
        ego_xy_yaw: tuple[float, float, float],
        ego_speed_yawrate: tuple[float, float],
        odo_speed_yawrate: tuple[float, float],
        rng: np.random.Generator,
    ) -> _Beams:
        """The sensor's pose and velocity, and the sweep's beams: the near scan, then the far
        scan (which reports from ``far_min_range_m`` on), each beam at a random azimuth in its
        bin."""
        cfg = self.cfg
        mt = self.mount
        ex, ey, eyaw = ego_xy_yaw
        c, s = math.cos(eyaw), math.sin(eyaw)
        sx = ex + c * mt.x - s * mt.y
        sy = ey + s * mt.x + c * mt.y
        syaw = eyaw + mt.yaw
        # Sensor velocity (global): ego velocity plus the yaw rate's lever-arm term.
        v, w = ego_speed_yawrate
        rx, ry = c * mt.x - s * mt.y, s * mt.x + c * mt.y
        vs = np.array([v * c - w * ry, v * s + w * rx])
        # The same from odometry, in the ego frame, for the Doppler compensation.
        vo, wo = odo_speed_yawrate
        vs_odo_ego = np.array([vo - wo * mt.y, wo * mt.x])
        fov = math.radians(cfg.fov_deg)
        step = math.radians(cfg.ray_spacing_deg)
        n_near = int(math.floor(2 * fov / step))
        az_near = -fov + (np.arange(n_near) + rng.random(n_near)) * step
        ffov = math.radians(cfg.far_fov_deg)
        fstep = math.radians(cfg.far_spacing_deg)
        n_far = int(math.floor(2 * ffov / fstep)) if cfg.far_fov_deg > 0 else 0
        az_far = -ffov + (np.arange(n_far) + rng.random(n_far)) * fstep
        az = np.concatenate([az_near, az_far])
        far = np.concatenate([np.zeros(n_near, bool), np.ones(n_far, bool)])
        return _Beams(
            sx=sx,
            sy=sy,
            syaw=syaw,
            vs=vs,
            vs_odo_ego=vs_odo_ego,
            fov=fov,
            n_near=n_near,
            az=az,
            far=far,
            reach=np.where(far, cfg.far_range_m, self.max_range(az)),
            near_reach=self.max_range(az),
            gdx=np.cos(az + syaw),
            gdy=np.sin(az + syaw),
        )

    def _cast(
        self,
        scene: tuple,
        beams: _Beams,
        dx: np.ndarray,
        dy: np.ndarray,
        reach: np.ndarray,
        bounce: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> tuple[np.ndarray, ...]:
        """Cast beams along ``(dx, dy)`` -> per beam its nearest hits (t, id, cos, nx, ny):
        ``_K_HITS`` from the sensor, or one from ``bounce`` = (x, y, mirror box id)."""
        n, k = len(dx), (_K_HITS if bounce is None else 1)
        out = (np.empty((n, k)), np.empty((n, k), np.int64), *(np.empty((n, k)) for _ in range(3)))
        if bounce is None:
            ox, oy, exclude = np.full(n, beams.sx), np.full(n, beams.sy), np.full(n, -1, np.int64)
        else:
            ox, oy, exclude = bounce
        rays = (ox, oy, np.full(n, self.mount.z), dx, dy, reach)
        radar_cast(rays, exclude, self.tan_beta, scene, M.RADAR_OPAQUE, out)
        return out

    def _real_scatterers(
        self,
        sc: _Scatterers,
        beams: _Beams,
        hits: tuple[np.ndarray, ...],
        targets: _Targets,
        rng: np.random.Generator,
    ) -> None:
        """The returns of the objects along each beam, in range order: a beam goes on past an
        object with the class's transmission probability."""
        cfg = self.cfg
        out_t, out_id, out_cos = hits[0], hits[1], hits[2]
        az, far, gdx, gdy = beams.az, beams.far, beams.gdx, beams.gdy
        n_rays = len(az)
        alive = np.ones(n_rays, dtype=bool)
        for k in range(_K_HITS):
            ids = out_id[:, k]
            valid = alive & (ids >= 0)
            if not valid.any():
                break
            li = targets.lookup(ids)
            kk = targets.classes[li]
            t = out_t[:, k]
            px = beams.sx + gdx * np.where(valid, t, 0.0)
            py = beams.sy + gdy * np.where(valid, t, 0.0)
            rcs = (
                M.RADAR_RCS_DB[kk]
                + targets.rcs_offset[li]
                + M.RADAR_SPECULAR[kk] * 20.0 * np.log10(np.maximum(out_cos[:, k], 0.05))
                + targets.corner_gain(li, kk, px, py, cfg.corner_gain_db)
                + self._fluctuation(rng, n_rays)
            )
            in_band = np.where(far, t >= cfg.far_min_range_m, t <= beams.near_reach)
            size = 2.0 * np.maximum(targets.boxes[li, 4], targets.boxes[li, 5])
            p_centre = self._centre_probability(kk, t, far, out_cos[:, k], size)
            hit = valid & in_band & (rng.random(n_rays) < p_centre)
            if hit.any():
                vt = targets.velocity[li[hit]]
                moving = np.hypot(vt[:, 0], vt[:, 1]) > 0.2
                sc.add(t[hit], az[hit], rcs[hit], far[hit], vt, RADAR_REAL, moving)
            alive = valid & (rng.random(n_rays) < M.RADAR_TRANSMIT[kk])

    def _ghosts(
        self,
        sc: _Scatterers,
        beams: _Beams,
        hits: tuple[np.ndarray, ...],
        targets: _Targets,
        scene: tuple,
        rng: np.random.Generator,
    ) -> None:
        """Multipath ghosts: bounce each near beam's first hit on a mirroring surface once,
        specularly; an object the bounced beam meets appears at its mirror image."""
        cfg = self.cfg
        if not len(beams.az):
            return
        first_t, first_ids, out_nx, out_ny = hits[0][:, 0], hits[1][:, 0], hits[3], hits[4]
        fk = targets.classes[targets.lookup(first_ids)]
        mirror = (first_ids >= 0) & (M.RADAR_MIRROR[fk] > 0) & ~beams.far
        g = np.nonzero(mirror)[0]
        if not len(g):
            return
        nx, ny = out_nx[g, 0], out_ny[g, 0]
        dxg, dyg = beams.gdx[g], beams.gdy[g]
        dn = dxg * nx + dyg * ny
        rdx, rdy = dxg - 2 * dn * nx, dyg - 2 * dn * ny
        wx = beams.sx + dxg * first_t[g] + 0.02 * rdx
        wy = beams.sy + dyg * first_t[g] + 0.02 * rdy
        near_reach = beams.near_reach[g]
        rem = np.maximum(near_reach - first_t[g], 0.0)
        gt, gid, gcos = self._cast(scene, beams, rdx, rdy, rem, (wx, wy, first_ids[g]))[:3]
        li = targets.lookup(gid[:, 0])
        kk = targets.classes[li]
        total = first_t[g] + gt[:, 0]
        rcs = (
            M.RADAR_RCS_DB[kk]
            + targets.rcs_offset[li]
            + M.RADAR_SPECULAR[kk] * 20.0 * np.log10(np.maximum(gcos[:, 0], 0.05))
            + self._fluctuation(rng, len(g))
            - cfg.multipath_loss_db
        )
        p = M.RADAR_MIRROR[fk[g]] * cfg.multipath_probability
        p = p * M.RADAR_SCATTER[kk] * cfg.scatter_probability
        det = (gid[:, 0] >= 0) & (total <= near_reach) & (rng.random(len(g)) < p)
        if det.any():
            # The mirror image of the target moves with the mirrored velocity.
            vg = _mirrored(targets.velocity[li[det]], nx[det], ny[det])
            moving = np.hypot(vg[:, 0], vg[:, 1]) > 0.2
            az, far = beams.az[g][det], beams.far[g][det]
            sc.add(total[det], az, rcs[det], far, vg, RADAR_GHOST, moving)

    def _false_alarms(self, sc: _Scatterers, beams: _Beams, rng: np.random.Generator) -> None:
        """Noise over the threshold, uniform over the range-azimuth cells, mostly without
        ground speed (CFAR on a static scene), some with a random Doppler."""
        n_c = int(rng.poisson(self.cfg.clutter_rate))
        if not n_c:
            return
        caz = rng.uniform(-beams.fov, beams.fov, n_c)
        cr = 0.5 + rng.random(n_c) * (self.max_range(caz) - 0.5)
        moving = rng.random(n_c) < 0.2
        u = np.stack([np.cos(caz + beams.syaw), np.sin(caz + beams.syaw)], 1)
        vrad = np.where(moving, rng.normal(0.0, 3.0, n_c), 0.0)
        rcs = rng.normal(-8.0, 4.0, n_c)
        vel = u * vrad[:, None]
        sc.add(cr, caz, rcs, np.zeros(n_c, bool), vel, RADAR_CLUTTER, moving, forced=True)

    def _road_clutter(
        self,
        sc: _Scatterers,
        beams: _Beams,
        hits: tuple[np.ndarray, ...],
        rng: np.random.Generator,
    ) -> None:
        """Returns of the road surface, kerbs, drain covers and debris in the free space in
        front of each near beam's first obstacle; static, strongest near the sensor (grazing
        angle)."""
        n_g = int(rng.poisson(self.cfg.road_clutter_rate)) if beams.n_near else 0
        if not n_g:
            return
        first_t, first_valid = hits[0][:, 0], hits[1][:, 0] >= 0
        gi = rng.integers(0, beams.n_near, n_g)
        near_reach = beams.near_reach[gi]
        rmax = np.minimum(np.where(first_valid[gi], first_t[gi], near_reach), near_reach)
        gr = 1.0 + (rmax - 1.0) * rng.random(n_g) ** 2
        ok = rmax > 1.5
        if ok.any():
            m = int(ok.sum())
            rcs = rng.normal(-10.0, 3.0, m)
            sc.add(
                gr[ok],
                beams.az[gi][ok],
                rcs,
                np.zeros(m, bool),
                np.zeros((m, 2)),
                RADAR_CLUTTER,
                np.zeros(m, bool),
                forced=True,
                real_flags=True,
            )

    def _report(
        self, sc: _Scatterers, beams: _Beams, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """The cluster list the sensor reports: merged cells, at most ``max_detections`` (the
        strongest), with measurement noise, Doppler and the validity fields; sorted by range."""
        cfg = self.cfg
        mt = self.mount
        cl = self._merge(sc.arrays(), beams.syaw, beams.vs, rng)
        r, a, rcs, snr, vt, lab, is_mover, real_flags, truth = cl
        if len(r) > cfg.max_detections:
            keep = np.argsort(-snr, kind="stable")[: cfg.max_detections]
            r, a, rcs, vt, lab = r[keep], a[keep], rcs[keep], vt[keep], lab[keep]
            is_mover, real_flags, truth = is_mover[keep], real_flags[keep], truth[keep]
        n = len(r)
        # Radial velocities along the line of sight to the cluster.
        ug = np.stack([np.cos(a + beams.syaw), np.sin(a + beams.syaw)], 1)
        v_raw = ((vt - beams.vs[None, :]) * ug).sum(1) + rng.normal(0.0, cfg.doppler_noise_mps, n)
        # Measurement noise (datasheet accuracies, 1 sigma).
        sig_r, sig_az = self.noise_sigmas(a, truth[:, 2] > 0)
        am = a + rng.normal(0.0, 1.0, n) * sig_az
        rm = np.maximum(r + rng.normal(0.0, 1.0, n) * sig_r, 0.2)
        # Compensation with the odometry's sensor velocity, in the sensor frame.
        ca, sa = np.cos(am), np.sin(am)
        vo = beams.vs_odo_ego
        cy, sy = math.cos(mt.yaw), math.sin(mt.yaw)
        vs_sensor = np.array([cy * vo[0] + sy * vo[1], -sy * vo[0] + cy * vo[1]])
        v_comp = v_raw + vs_sensor[0] * ca + vs_sensor[1] * sa
        rcs_q = np.clip(np.round(rcs * 2.0) / 2.0, -64.0, 63.5)

        pts = np.zeros((n, 12), dtype=np.float32)
        pts[:, 0] = rm * ca
        pts[:, 1] = rm * sa
        pts[:, 3] = rcs_q
        pts[:, 4] = v_raw * ca
        pts[:, 5] = v_raw * sa
        pts[:, 6] = v_comp * ca
        pts[:, 7] = v_comp * sa
        # Road clutter is a real reflection to the sensor: flagged like real detections.
        flag_lab = np.where(real_flags, RADAR_REAL, lab).astype(np.uint8)
        pts[:, 8:12] = self._flags(rng, flag_lab, v_comp, is_mover, rcs_q, rm)
        order = np.argsort(rm, kind="stable")
        self.last_truth = truth[order]
        return pts[order], lab[order]

    def _cells(self, r: np.ndarray, a: np.ndarray, far: np.ndarray, vrad: np.ndarray) -> np.ndarray:
        """The resolution cell (range bin x azimuth bin x Doppler bin, per scan) of each
        scatterer at range ``r``, azimuth ``a`` and radial speed ``vrad``, numbered 0, 1, ..."""
        cfg = self.cfg
        res_r = np.where(far, cfg.far_range_resolution_m, cfg.range_resolution_m)
        # Beams of a digital beamformer are evenly spaced in sin(azimuth): cells widen off
        # boresight.
        res_u = np.radians(
            np.where(far, cfg.far_azimuth_resolution_deg, cfg.azimuth_resolution_deg)
        )
        rb = np.clip(np.floor(r / res_r), 0, 8191).astype(np.int64)
        ub = np.clip(np.floor(np.sin(a) / res_u), -2047, 2047).astype(np.int64) + 2048
        db = (
            np.clip(np.floor(vrad / cfg.doppler_resolution_mps), -32767, 32767).astype(np.int64)
            + 32768
        )
        key = ((far.astype(np.int64) * 8192 + rb) * 4096 + ub) * 65536 + db
        _, inv = np.unique(key, return_inverse=True)
        inv = inv.ravel()
        return inv

    def _merge(
        self, sc: dict[str, np.ndarray], syaw: float, vs: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, ...]:
        """Merge the scatterers of one resolution cell (range bin x azimuth bin x Doppler bin, per
        scan) into one cluster and detect it: position = power-weighted mean, RCS = summed power,
        label, velocity and truth of its strongest scatterer; detected with probability
        ``logistic(SNR / detection_softness_db)`` of the summed power (false alarms always)."""
        cfg = self.cfg
        r, a, rcs, far = sc["r"], sc["a"], sc["rcs"], sc["far"]
        snr = self._snr(rcs, r, a, far)
        p = 10.0 ** (snr / 10.0)
        # Radial velocity relative to the sensor: the Doppler the cell is binned by.
        vrad = (sc["vel"][:, 0] - vs[0]) * np.cos(a + syaw) + (sc["vel"][:, 1] - vs[1]) * np.sin(
            a + syaw
        )
        inv = self._cells(r, a, far, vrad)
        n_cells = int(inv.max()) + 1
        psum = np.bincount(inv, p, n_cells)
        rc = np.bincount(inv, p * r, n_cells) / psum
        ac = np.bincount(inv, p * a, n_cells) / psum
        order = np.lexsort((-p, inv))
        first = np.ones(len(order), dtype=bool)
        first[1:] = inv[order][1:] != inv[order][:-1]
        top = order[first]  # the strongest scatterer of each cell, cells in order
        forced = np.bincount(inv, sc["forced"].astype(np.float64), n_cells) > 0
        snr_c = 10.0 * np.log10(psum)
        det = forced | (
            rng.random(n_cells) < 1.0 / (1.0 + np.exp(-snr_c / cfg.detection_softness_db))
        )
        rcs_c = 10.0 * np.log10(np.bincount(inv, 10.0 ** (rcs / 10.0), n_cells))
        truth = np.stack([r[top], a[top], far[top].astype(np.float64)], 1)
        t = top[det]
        return (
            rc[det],
            ac[det],
            rcs_c[det],
            snr_c[det],
            sc["vel"][t],
            sc["lab"][t],
            sc["mover"][t],
            sc["real_flags"][t],
            truth[det],
        )

    @staticmethod
    def _flags(
        rng: np.random.Generator,
        lab: np.ndarray,
        v_comp: np.ndarray,
        mover: np.ndarray,
        rcs: np.ndarray,
        r: np.ndarray,
    ) -> np.ndarray:
        """dyn_prop, ambig_state, invalid_state, pdh0 of each detection (ARS 408 codes)."""
        n = len(lab)
        out = np.zeros((n, 4))
        moving_meas = np.abs(v_comp) >= 0.4
        stat = _choice(rng, (1, 3, 4), (0.75, 0.15, 0.10), n)
        stopped = _choice(rng, (7, 1), (0.5, 0.5), n)
        dyn = np.where(moving_meas, np.where(v_comp > 0, 0, 2), np.where(mover, 6, stat))
        # A moving object standing still right now (waiting pedestrian): "stopped" or stationary.
        dyn = np.where(
            ~moving_meas & mover & (lab == RADAR_REAL) & (np.abs(v_comp) < 0.1), stopped, dyn
        )
        out[:, 0] = dyn
        real = lab == RADAR_REAL
        ghost = lab == RADAR_GHOST
        clutter = lab == RADAR_CLUTTER
        out[:, 1] = np.where(
            clutter,
            _choice(rng, (3, 1, 2, 4), (0.7, 0.15, 0.05, 0.1), n),
            _choice(rng, (3, 4, 1), (0.93, 0.04, 0.03), n),
        )
        inv_real = np.where(
            rcs < -3.0,
            _choice(rng, (4, 0), (0.5, 0.5), n),
            _choice(rng, (0, 8, 11, 16, 17), (0.9, 0.03, 0.03, 0.02, 0.02), n),
        )
        inv_ghost = _choice(rng, (0, 6, 12), (0.65, 0.25, 0.10), n)
        inv_clutter = np.where(
            r < 3.0,
            _choice(rng, (0, 2, 1), (0.5, 0.3, 0.2), n),
            _choice(rng, (0, 1, 14, 12), (0.6, 0.2, 0.05, 0.15), n),
        )
        out[:, 2] = np.where(real, inv_real, np.where(ghost, inv_ghost, inv_clutter))
        out[:, 3] = np.where(
            real,
            _choice(rng, (1, 2, 3), (0.9, 0.07, 0.03), n),
            np.where(
                ghost,
                _choice(rng, (1, 2, 3, 4), (0.6, 0.2, 0.1, 0.1), n),
                _choice(rng, (1, 2, 3, 4, 5), (0.5, 0.2, 0.15, 0.1, 0.05), n),
            ),
        )
        return out


class _Scatterers:
    """Candidate returns of one sweep, gathered before the resolution cells merge them."""

    _FIELDS = ("r", "a", "rcs", "far", "vel", "lab", "mover", "forced", "real_flags")

    def __init__(self) -> None:
        self._parts: dict[str, list[np.ndarray]] = {f: [] for f in self._FIELDS}

    def __bool__(self) -> bool:
        """Whether any returns were added."""
        return bool(self._parts["r"])

    def add(
        self,
        r: np.ndarray,
        a: np.ndarray,
        rcs: np.ndarray,
        far: np.ndarray,
        vel: np.ndarray,
        label: int,
        mover: np.ndarray,
        forced: bool = False,
        real_flags: bool = False,
    ) -> None:
        n = len(r)
        for f, v in zip(
            self._FIELDS,
            (
                r,
                a,
                rcs,
                far,
                vel,
                np.full(n, label, np.uint8),
                mover,
                np.full(n, forced),
                np.full(n, real_flags or label == RADAR_REAL),
            ),
        ):
            self._parts[f].append(np.asarray(v))

    def arrays(self) -> dict[str, np.ndarray]:
        return {f: np.concatenate(v) for f, v in self._parts.items()}


@dataclass(frozen=True)
class _Beams:
    """One sweep's sensor state (global frame) and beams (sensor azimuths, rad)."""

    sx: float
    sy: float
    syaw: float
    #: true sensor velocity (global, m/s) and the odometry's (ego frame)
    vs: np.ndarray
    vs_odo_ego: np.ndarray
    fov: float
    n_near: int
    az: np.ndarray
    #: whether a beam belongs to the far scan
    far: np.ndarray
    #: each beam's reach (m), and the near scan's reach at its azimuth
    reach: np.ndarray
    near_reach: np.ndarray
    #: global direction of each beam
    gdx: np.ndarray
    gdy: np.ndarray


class _Targets:
    """What a beam can hit, static boxes then moving objects then "nothing" (one row each):
    class, RCS offset (dB), velocity (m/s) and packed box."""

    def __init__(
        self, world: World, scene: tuple, dyn_vel: np.ndarray, dyn_rcs_offset: np.ndarray
    ) -> None:
        dyn_boxes, dcls = scene[9], scene[10]
        n_static = world.n_static
        self.classes = np.concatenate([world.classes, dcls, [0]]).astype(np.int64)
        self.rcs_offset = np.concatenate([world.rcs_offset_db, dyn_rcs_offset, [0.0]])
        self.velocity = np.concatenate([np.zeros((n_static, 2)), dyn_vel, np.zeros((1, 2))])
        self.boxes = np.concatenate([world.boxes, dyn_boxes, np.zeros((1, 8))])

    def lookup(self, ids: np.ndarray) -> np.ndarray:
        """Rows of hit ids, "nothing" (-1) the last row."""
        return np.where(ids >= 0, ids, len(self.classes) - 1)

    def corner_gain(
        self, li: np.ndarray, kk: np.ndarray, px: np.ndarray, py: np.ndarray, gain_db: float
    ) -> np.ndarray:
        """Extra RCS (dB) of a hit at ``(px, py)`` near a vertical edge of a flat-faced object
        (building corners, vehicle corners): the strongest radar scatterers, by dihedral
        returns and edge diffraction."""
        b = self.boxes[li]
        qx, qy = px - b[:, 0], py - b[:, 1]
        lx = b[:, 2] * qx + b[:, 3] * qy
        ly = -b[:, 3] * qx + b[:, 2] * qy
        d = np.hypot(b[:, 4] - np.abs(lx), b[:, 5] - np.abs(ly))
        return np.where(M.RADAR_SPECULAR[kk] > 0, gain_db * np.exp(-((d / 0.6) ** 2)), 0.0)


def _mirrored(v: np.ndarray, nx: np.ndarray, ny: np.ndarray) -> np.ndarray:
    """Velocities ``v`` ``(k, 2)`` mirrored on surfaces of unit normals (nx, ny)."""
    vn = v[:, 0] * nx + v[:, 1] * ny
    return np.stack([v[:, 0] - 2 * vn * nx, v[:, 1] - 2 * vn * ny], 1)
