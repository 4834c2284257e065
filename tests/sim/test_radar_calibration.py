"""The calibrated ARS 408 model (docs/radar-calibration.md): resolution cells, Swerling
fluctuation, datasheet noise, road clutter, and the detection count per nuScenes sample."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evgrid.data.frame import radar_column
from evgrid.data.mounts import SensorMount
from evgrid.preprocess import RadarFilter
from evgrid_sim import (
    RADAR_CLUTTER,
    RADAR_GHOST,
    RADAR_REAL,
    RadarConfig,
    SimConfig,
    WorldConfig,
    simulate_scene,
)
from evgrid_sim import materials as M
from evgrid_sim.radar import RadarModel
from evgrid_sim.world import World

#: A radar at the ego origin looking along +x (ego at the global origin), so sensor = global frame.
_MOUNT = SensorMount("RADAR_FRONT", 0.0, 0.0, 0.5, 0.0)
#: Everything random switched off: each beam-hit scatters, constant RCS, no noise, no clutter,
#: and so much sensitivity that every cell is detected; near scan only (the far scan, which
#: reports its own clusters of the same objects, is tested apart).
_EXACT = dict(
    far_fov_deg=0.0,
    scatter_probability=1.0,
    swerling=False,
    rcs_fluctuation_db=0.0,
    clutter_rate=0.0,
    road_clutter_rate=0.0,
    range_noise_m=0.0,
    far_range_noise_m=0.0,
    azimuth_noise_deg=0.0,
    azimuth_noise_mid_deg=0.0,
    azimuth_noise_edge_deg=0.0,
    far_azimuth_noise_deg=0.0,
    doppler_noise_mps=0.0,
    reference_range_m=1000.0,
)


def _world(static: list[tuple]) -> World:
    """Boxes (cx, cy, yaw, length, width, z0, z1, class) in the global frame."""
    return World.from_boxes(static)


def _pole(r: float, az_deg: float, size: float = 0.6) -> tuple:
    """A square pole of ``size`` m whose centre is ``r`` m away at ``az_deg``."""
    a = math.radians(az_deg)
    return (r * math.cos(a), r * math.sin(a), a, size, size, 0.0, 4.0, M.POLE)


def _sweeps(world: World, cfg: RadarConfig, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    radar = RadarModel(cfg, _MOUNT)
    empty = (np.zeros((0, 8)), np.zeros(0, np.int32), np.zeros((0, 2)), np.zeros(0))
    return [
        radar.sweep(
            world, *empty, (0.0, 0.0, 0.0), (0.0, 0.0), (0.0, 0.0), np.random.default_rng(k)
        )
        for k in range(n)
    ]


def test_two_targets_in_one_resolution_cell_give_one_detection():
    # Both poles in azimuth bin [0, 3.2 deg) and their faces (30.2 m) in range bin [30.03, 30.42) m.
    world = _world([_pole(30.5, 0.8), _pole(30.5, 2.4)])
    sweeps = _sweeps(world, RadarConfig(**_EXACT), 10)
    counts = [int((lab == RADAR_REAL).sum()) for _, lab in sweeps]
    assert max(counts) == 1 and sum(counts) >= 8
    for pts, _ in sweeps:
        if len(pts):
            # The cluster sits between the two poles (power-weighted mean of their hits).
            az = math.degrees(math.atan2(pts[0, 1], pts[0, 0]))
            assert -0.3 < az < 3.5
            assert 30.0 < math.hypot(pts[0, 0], pts[0, 1]) < 30.45
    # Without the merge (cells far finer than the beams) the same world gives two or more.
    fine = RadarConfig(**_EXACT, range_resolution_m=0.01, azimuth_resolution_deg=0.01)
    assert max(int((lab == RADAR_REAL).sum()) for _, lab in _sweeps(world, fine, 10)) >= 2


@pytest.mark.parametrize(
    "second", [(30.5, 20.0), (36.0, 2.6)], ids=["apart_in_azimuth", "apart_in_range"]
)
def test_two_targets_in_different_cells_give_two_detections(second):
    # 1.2 m poles: two or more beams each, so that each is seen in almost every sweep.
    world = _world([_pole(30.5, 0.8, 1.2), _pole(*second, 1.2)])
    sweeps = _sweeps(world, RadarConfig(**_EXACT), 10)
    # A cluster at each pole (a wide pole can straddle a cell boundary and give two).
    r2, az2 = second[0] - 0.6, second[1]
    both = [
        np.any(np.abs(np.hypot(p[:, 0], p[:, 1]) - 29.9) < 0.2)
        and np.any(
            (np.abs(np.hypot(p[:, 0], p[:, 1]) - r2) < 0.2)
            & (np.abs(np.degrees(np.arctan2(p[:, 1], p[:, 0])) - az2) < 1.5)
        )
        for p, _ in sweeps
    ]
    assert np.mean(both) >= 0.8


def test_swerling_fluctuation_is_exponential_power():
    # Swerling I/II: power ~ Exp(1); in dB its standard deviation is pi / sqrt(6) * 10 / ln 10 =
    # 5.57 dB.
    radar = RadarModel(RadarConfig(rcs_fluctuation_db=0.0), _MOUNT)
    f = radar._fluctuation(np.random.default_rng(0), 200_000)
    assert f.std() == pytest.approx(math.pi / math.sqrt(6) * 10 / math.log(10), rel=0.02)
    assert np.mean(10 ** (f / 10)) == pytest.approx(1.0, rel=0.02)
    off = RadarModel(RadarConfig(rcs_fluctuation_db=0.0, swerling=False), _MOUNT)
    assert np.all(off._fluctuation(np.random.default_rng(0), 10) == 0.0)


def test_noise_follows_the_datasheet_accuracies():
    radar = RadarModel(RadarConfig(), _MOUNT)
    az = np.radians([0.0, 45.0, 60.0, -45.0, 0.0])
    far = np.array([False, False, False, False, True])
    sig_r, sig_az = radar.noise_sigmas(az, far)
    np.testing.assert_allclose(np.degrees(sig_az), [0.3, 1.0, 5.0, 1.0, 0.1])
    np.testing.assert_allclose(sig_r, [0.1, 0.1, 0.1, 0.1, 0.4])


def test_road_clutter_lies_in_the_free_space_before_the_first_obstacle():
    # A wall 15 m ahead across the whole field of view; no real scatterers, only road clutter.
    world = _world([(15.5, 0.0, 0.0, 1.0, 80.0, 0.0, 5.0, M.WALL)])
    cfg = RadarConfig(**{**_EXACT, "scatter_probability": 0.0, "road_clutter_rate": 30.0})
    sweeps = _sweeps(world, cfg, 10)
    pts = np.concatenate([p for p, _ in sweeps])
    lab = np.concatenate([lab for _, lab in sweeps])
    assert len(pts) > 100 and np.all(lab == RADAR_CLUTTER)
    assert np.all(pts[:, 0] < 15.0 + 1e-3)  # in front of the wall's face
    assert np.mean(np.hypot(pts[:, 0], pts[:, 1]) < 7.5) > 0.5  # mostly near (grazing angle)
    # A real reflection to the sensor: flagged as real detections are, never with the states
    # only false alarms and ghosts get (1 invalid distance, 2 low-range, 6 mirror, 12 ..., 14 ...).
    inv = set(np.unique(pts[:, radar_column("invalid_state")]).astype(int).tolist())
    assert inv <= {0, 4, 8, 11, 16, 17} and 0 in inv
    assert np.mean(RadarFilter("nuscenes").keep(pts)) > 0.3


def test_detections_per_sample_fall_in_the_nuscenes_range():
    # nuScenes v1.0-mini, 404 samples, devkit default filters: 97 to 323 detections a sample
    # over the five radars (mean 196.8). A short urban scene's samples lie in that range.
    scene = simulate_scene(0, SimConfig(duration_s=3.0, world=WorldConfig(environment="urban")))
    keep = RadarFilter("nuscenes").keep
    counts = []
    for i in scene.keyframe_indices:
        t = int(scene.lidar_timestamps[i])
        n = 0
        for ch, ts in scene.radar_timestamps.items():
            j = int(np.searchsorted(ts, t, side="right")) - 1
            if j >= 0:
                n += int(keep(scene.radar_sweep(ch, j)[0].points).sum())
        counts.append(n)
    assert len(counts) == 6
    assert all(97 <= c <= 323 for c in counts), counts


@pytest.mark.parametrize(
    "kw,field",
    [
        ({"range_resolution_m": 0.0}, "range_resolution_m"),
        ({"far_azimuth_resolution_deg": -1.0}, "far_azimuth_resolution_deg"),
        ({"doppler_resolution_mps": float("nan")}, "doppler_resolution_mps"),
        ({"scatter_probability": 1.5}, "scatter_probability"),
        ({"multipath_probability": -0.5}, "multipath_probability"),
        ({"road_clutter_rate": -1.0}, "road_clutter_rate"),
        ({"azimuth_noise_mid_deg": -0.1}, "azimuth_noise_mid_deg"),
        ({"swerling": "yes"}, "swerling"),
        ({"far_min_range_m": 300.0}, "far_min_range_m"),
        ({"scatter_strip_m": 0.0}, "scatter_strip_m"),
    ],
)
def test_bad_radar_config_is_named(kw, field):
    with pytest.raises(ValueError, match=field):
        RadarConfig(**kw)


def test_multipath_probability_scales_the_ghosts():
    # A facade left of the road (face at y = 6) and a truck ahead: ghosts behind the facade.
    world = _world(
        [
            (20.0, 11.0, 0.0, 80.0, 10.0, 0.0, 20.0, M.BUILDING),
            (18.0, -1.0, 0.0, 7.0, 2.4, 0.3, 3.0, M.TRUCK),
        ]
    )
    cfg = dict(_EXACT, reference_range_m=25.0)

    def ghosts(p: float) -> int:
        return sum(
            int((lab == RADAR_GHOST).sum())
            for _, lab in _sweeps(world, RadarConfig(**cfg, multipath_probability=p), 20)
        )

    assert ghosts(1.0) >= 5
    assert ghosts(0.0) == 0


def test_far_scan_reports_inside_the_near_reach():
    # A pole 30 m ahead (inside the near scan's 70 m): the far scan reports its own cluster of it,
    # as the ARS 408's two independent scans do; with far_min_range_m = 70 (the old model) it does
    # not.
    world = _world([_pole(30.5, 0.0, 1.2)])
    cfg = {**_EXACT, "far_fov_deg": 9.0}
    scans = []
    for far_min in (0.2, 70.0):
        radar = RadarModel(RadarConfig(**cfg, far_min_range_m=far_min), _MOUNT)
        empty = (np.zeros((0, 8)), np.zeros(0, np.int32), np.zeros((0, 2)), np.zeros(0))
        seen = []
        for k in range(5):
            pts, lab = radar.sweep(
                world, *empty, (0.0, 0.0, 0.0), (0.0, 0.0), (0.0, 0.0), np.random.default_rng(k)
            )
            seen.append(radar.last_truth[lab == RADAR_REAL, 2])
        scans.append(np.concatenate(seen))
    assert np.sum(scans[0] > 0) >= 4 and np.sum(scans[0] == 0) >= 4  # both scans, most sweeps
    assert np.all(scans[1] == 0)


def test_scattering_centres_are_per_metre_of_surface():
    # The chance that a beam-hit holds a centre grows with the strip of surface the beam stands
    # for (range x beam spacing / cos(incidence)): RADAR_SCATTER * scatter_probability at
    # scatter_strip_m.
    cfg = RadarConfig()
    radar = RadarModel(cfg, _MOUNT)
    k = np.array([M.CAR, M.CAR, M.CAR])
    strip_range = cfg.scatter_strip_m / math.radians(cfg.ray_spacing_deg)
    normal = np.ones(3)
    p = radar._centre_probability(k, np.array([strip_range, 5.0, 60.0]), np.zeros(3, bool), normal)
    assert p[0] == pytest.approx(M.RADAR_SCATTER[M.CAR] * cfg.scatter_probability)
    assert p[1] < p[0] < p[2]
    # A finer-spaced beam stands for a narrower strip: same range, smaller chance.
    assert (
        radar._centre_probability(k[:1], np.array([60.0]), np.ones(1, bool), normal[:1])[0] < p[2]
    )
    # At oblique incidence the beam's strip on the surface is wider: 1 / cos(60 deg) = twice.
    oblique = radar._centre_probability(
        k[:1], np.array([strip_range / 2]), np.zeros(1, bool), np.array([0.5])
    )
    assert oblique[0] == pytest.approx(p[0])
    # An object narrower than scatter_strip_m (a pole) is one centre however many beams hit it:
    # a beam covering its whole width holds the centre with the table's chance.
    pole = np.array([M.POLE])
    width = 0.24
    whole = radar._centre_probability(
        pole,
        np.array([width / math.radians(cfg.ray_spacing_deg)]),
        np.zeros(1, bool),
        np.ones(1),
        np.array([width]),
    )
    assert whole[0] == pytest.approx(M.RADAR_SCATTER[M.POLE] * cfg.scatter_probability)


def test_front_radar_detections_are_mostly_far():
    # CRF-Net's statistics of all nuScenes RADAR_FRONT detections (devkit default filter, sensor
    # frame): distance mean 53.2 m, std 36.2 m. A short scene's front radar, over every sweep,
    # has its mean distance in a band around the calibrated 42 m (the previous model: 20 m).
    scene = simulate_scene(2, SimConfig(duration_s=3.0, world=WorldConfig(environment="urban")))
    keep = RadarFilter("nuscenes").keep
    pts = [
        scene.radar_sweep("RADAR_FRONT", j)[0].points
        for j in range(len(scene.radar_timestamps["RADAR_FRONT"]))
    ]
    pts = np.concatenate([p[keep(p)] for p in pts])
    d = np.hypot(pts[:, 0], pts[:, 1])
    assert len(d) > 400
    assert 30.0 < d.mean() < 60.0, d.mean()
    assert d.std() > 25.0, d.std()
