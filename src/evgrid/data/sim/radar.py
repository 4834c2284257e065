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

import numpy as np

from evgrid.data.mounts import SensorMount
from evgrid.data.sim import materials as M
from evgrid.data.sim.config import RadarConfig
from evgrid.data.sim.raycast import radar_cast
from evgrid.data.sim.world import World

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
        #: Per point of the last sweep: true range (m), azimuth (rad) and scan (1 far) of its strongest scatterer.
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
        """One sweep at ego pose ``(x, y, yaw)`` (m, rad), true and odometry (speed m/s, yaw rate
        rad/s) -> (points ``(n, 12)`` float32 in the sensor frame, ``RADAR_COLUMNS``; labels (n,) uint8).

        ``self.last_truth`` then holds, per point, the true range (m), azimuth (rad) and scan
        (1 far) of its strongest scatterer, for calibration."""
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

        # Beams: near scan, then the far scan (which reports from far_min_range_m on).
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
        reach = np.where(far, cfg.far_range_m, self.max_range(az))
        n_rays = len(az)
        gdx, gdy = np.cos(az + syaw), np.sin(az + syaw)
        out = [np.empty((n_rays, _K_HITS)) for _ in range(3)] + [
            np.empty((n_rays, _K_HITS), np.int64)
        ]
        out_t, out_cos, out_nx, out_id = out
        out_ny = np.empty((n_rays, _K_HITS))
        idx = world.index
        dcls = dyn_classes.astype(np.int32)
        radar_cast(
            np.full(n_rays, sx),
            np.full(n_rays, sy),
            np.full(n_rays, mt.z),
            gdx,
            gdy,
            reach,
            np.full(n_rays, -1, np.int64),
            self.tan_beta,
            world.boxes,
            world.classes,
            idx.start,
            idx.items,
            idx.x0,
            idx.y0,
            idx.cell,
            idx.nx,
            idx.ny,
            dyn_boxes,
            dcls,
            M.RADAR_OPAQUE,
            out_t,
            out_id,
            out_cos,
            out_nx,
            out_ny,
        )
        n_static = world.n_static
        cls_all = np.concatenate([world.classes, dcls, [0]]).astype(np.int64)
        off_all = np.concatenate([world.rcs_offset_db, dyn_rcs_offset, [0.0]])
        vel_all = np.concatenate([np.zeros((n_static, 2)), dyn_vel, np.zeros((1, 2))])
        box_all = np.concatenate([world.boxes, dyn_boxes, np.zeros((1, 8))])

        def corner_gain(
            li: np.ndarray, kk: np.ndarray, px: np.ndarray, py: np.ndarray
        ) -> np.ndarray:
            # Vertical edges of flat-faced objects (building corners, vehicle corners) are the
            # strongest radar scatterers: dihedral returns and edge diffraction.
            b = box_all[li]
            qx, qy = px - b[:, 0], py - b[:, 1]
            lx = b[:, 2] * qx + b[:, 3] * qy
            ly = -b[:, 3] * qx + b[:, 2] * qy
            d = np.hypot(b[:, 4] - np.abs(lx), b[:, 5] - np.abs(ly))
            return np.where(
                M.RADAR_SPECULAR[kk] > 0, cfg.corner_gain_db * np.exp(-((d / 0.6) ** 2)), 0.0
            )

        def lookup(ids: np.ndarray) -> np.ndarray:
            return np.where(ids >= 0, ids, len(cls_all) - 1)

        near_reach = self.max_range(az)
        # Scatterers: every candidate return before the resolution cells merge them.
        sc = _Scatterers()
        alive = np.ones(n_rays, dtype=bool)
        first_ids, first_t = out_id[:, 0].copy(), out_t[:, 0].copy()
        first_valid = first_ids >= 0
        for k in range(_K_HITS):
            ids = out_id[:, k]
            valid = alive & (ids >= 0)
            if not valid.any():
                break
            li = lookup(ids)
            kk = cls_all[li]
            t = out_t[:, k]
            rcs = (
                M.RADAR_RCS_DB[kk]
                + off_all[li]
                + M.RADAR_SPECULAR[kk] * 20.0 * np.log10(np.maximum(out_cos[:, k], 0.05))
                + corner_gain(
                    li, kk, sx + gdx * np.where(valid, t, 0.0), sy + gdy * np.where(valid, t, 0.0)
                )
                + self._fluctuation(rng, n_rays)
            )
            in_band = np.where(far, t >= cfg.far_min_range_m, t <= near_reach)
            size = 2.0 * np.maximum(box_all[li, 4], box_all[li, 5])
            hit = (
                valid
                & in_band
                & (rng.random(n_rays) < self._centre_probability(kk, t, far, out_cos[:, k], size))
            )
            if hit.any():
                vt = vel_all[li[hit]]
                sc.add(
                    t[hit],
                    az[hit],
                    rcs[hit],
                    far[hit],
                    vt,
                    RADAR_REAL,
                    np.hypot(vt[:, 0], vt[:, 1]) > 0.2,
                )
            alive = valid & (rng.random(n_rays) < M.RADAR_TRANSMIT[kk])

        # Multipath ghosts: bounce the first hit on a mirroring surface once, specularly.
        if n_rays:
            fk = cls_all[lookup(first_ids)]
            mirror = first_valid & (M.RADAR_MIRROR[fk] > 0) & ~far
            g = np.nonzero(mirror)[0]
            if len(g):
                nx, ny = out_nx[g, 0], out_ny[g, 0]
                dxg, dyg = gdx[g], gdy[g]
                dn = dxg * nx + dyg * ny
                rdx, rdy = dxg - 2 * dn * nx, dyg - 2 * dn * ny
                wx = sx + dxg * first_t[g] + 0.02 * rdx
                wy = sy + dyg * first_t[g] + 0.02 * rdy
                rem = np.maximum(near_reach[g] - first_t[g], 0.0)
                gt = np.empty((len(g), 1))
                gid = np.empty((len(g), 1), np.int64)
                gcos = np.empty((len(g), 1))
                gnx = np.empty((len(g), 1))
                gny = np.empty((len(g), 1))
                radar_cast(
                    wx,
                    wy,
                    np.full(len(g), mt.z),
                    rdx,
                    rdy,
                    rem,
                    first_ids[g],
                    self.tan_beta,
                    world.boxes,
                    world.classes,
                    idx.start,
                    idx.items,
                    idx.x0,
                    idx.y0,
                    idx.cell,
                    idx.nx,
                    idx.ny,
                    dyn_boxes,
                    dcls,
                    M.RADAR_OPAQUE,
                    gt,
                    gid,
                    gcos,
                    gnx,
                    gny,
                )
                hitg = gid[:, 0] >= 0
                li = lookup(gid[:, 0])
                kk = cls_all[li]
                total = first_t[g] + gt[:, 0]
                rcs = (
                    M.RADAR_RCS_DB[kk]
                    + off_all[li]
                    + M.RADAR_SPECULAR[kk] * 20.0 * np.log10(np.maximum(gcos[:, 0], 0.05))
                    + self._fluctuation(rng, len(g))
                    - cfg.multipath_loss_db
                )
                p = (
                    M.RADAR_MIRROR[fk[g]]
                    * cfg.multipath_probability
                    * M.RADAR_SCATTER[kk]
                    * cfg.scatter_probability
                )
                det = hitg & (total <= near_reach[g]) & (rng.random(len(g)) < p)
                if det.any():
                    # The mirror image of the target moves with the mirrored velocity.
                    vt = vel_all[li[det]]
                    vn = vt[:, 0] * nx[det] + vt[:, 1] * ny[det]
                    vg = np.stack([vt[:, 0] - 2 * vn * nx[det], vt[:, 1] - 2 * vn * ny[det]], 1)
                    sc.add(
                        total[det],
                        az[g][det],
                        rcs[det],
                        far[g][det],
                        vg,
                        RADAR_GHOST,
                        np.hypot(vg[:, 0], vg[:, 1]) > 0.2,
                    )

        # False alarms: noise over the threshold, uniform over the range-azimuth cells, mostly
        # without ground speed (CFAR on a static scene), some with a random Doppler.
        n_c = int(rng.poisson(cfg.clutter_rate))
        if n_c:
            caz = rng.uniform(-fov, fov, n_c)
            cr = 0.5 + rng.random(n_c) * (self.max_range(caz) - 0.5)
            moving = rng.random(n_c) < 0.2
            u = np.stack([np.cos(caz + syaw), np.sin(caz + syaw)], 1)
            vrad = np.where(moving, rng.normal(0.0, 3.0, n_c), 0.0)
            sc.add(
                cr,
                caz,
                rng.normal(-8.0, 4.0, n_c),
                np.zeros(n_c, bool),
                u * vrad[:, None],
                RADAR_CLUTTER,
                moving,
                forced=True,
            )
        # Road clutter: returns of the road surface, kerbs, drain covers and debris in the free
        # space in front of the first obstacle; static, strongest near the sensor (grazing angle).
        n_g = int(rng.poisson(cfg.road_clutter_rate)) if n_near else 0
        if n_g:
            gi = rng.integers(0, n_near, n_g)
            rmax = np.minimum(
                np.where(first_valid[gi], first_t[gi], near_reach[gi]), near_reach[gi]
            )
            gr = 1.0 + (rmax - 1.0) * rng.random(n_g) ** 2
            ok = rmax > 1.5
            if ok.any():
                m = int(ok.sum())
                sc.add(
                    gr[ok],
                    az[gi][ok],
                    rng.normal(-10.0, 3.0, m),
                    np.zeros(m, bool),
                    np.zeros((m, 2)),
                    RADAR_CLUTTER,
                    np.zeros(m, bool),
                    forced=True,
                    real_flags=True,
                )

        self.last_truth = np.zeros((0, 3))
        if not sc:
            return np.zeros((0, 12), np.float32), np.zeros(0, np.uint8)
        cl = self._merge(sc.arrays(), syaw, vs, rng)
        r, a, rcs, snr, vt, lab, is_mover, real_flags, truth = cl
        # The sensor reports at most max_detections clusters: the strongest.
        if len(r) > cfg.max_detections:
            keep = np.argsort(-snr, kind="stable")[: cfg.max_detections]
            r, a, rcs, vt, lab, is_mover, real_flags, truth = (
                r[keep],
                a[keep],
                rcs[keep],
                vt[keep],
                lab[keep],
                is_mover[keep],
                real_flags[keep],
                truth[keep],
            )
        n = len(r)
        # Radial velocities along the line of sight to the cluster.
        ug = np.stack([np.cos(a + syaw), np.sin(a + syaw)], 1)
        v_raw = ((vt - vs[None, :]) * ug).sum(1) + rng.normal(0.0, cfg.doppler_noise_mps, n)
        # Measurement noise (datasheet accuracies, 1 sigma).
        sig_r, sig_az = self.noise_sigmas(a, truth[:, 2] > 0)
        am = a + rng.normal(0.0, 1.0, n) * sig_az
        rm = np.maximum(r + rng.normal(0.0, 1.0, n) * sig_r, 0.2)
        # Compensation with the odometry's sensor velocity, in the sensor frame.
        ca, sa = np.cos(am), np.sin(am)
        vs_sensor = np.array(
            [
                math.cos(mt.yaw) * vs_odo_ego[0] + math.sin(mt.yaw) * vs_odo_ego[1],
                -math.sin(mt.yaw) * vs_odo_ego[0] + math.cos(mt.yaw) * vs_odo_ego[1],
            ]
        )
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
        pts[:, 8:12] = self._flags(
            rng, np.where(real_flags, RADAR_REAL, lab).astype(np.uint8), v_comp, is_mover, rcs_q, rm
        )
        order = np.argsort(rm, kind="stable")
        self.last_truth = truth[order]
        return pts[order], lab[order]

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
        res_r = np.where(far, cfg.far_range_resolution_m, cfg.range_resolution_m)
        # Beams of a digital beamformer are evenly spaced in sin(azimuth): cells widen off boresight.
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
