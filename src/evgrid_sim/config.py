"""Typed, frozen configuration of the driving simulator (every number in SI units)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

from evgrid.data.frame import RADAR_CHANNELS
from evgrid.geometry import GridSpec
from evgrid.validation import check_choice, check_int, check_number

__all__ = [
    "LidarConfig",
    "RadarConfig",
    "EgoConfig",
    "WorldConfig",
    "SweepFaults",
    "SimRadarRig",
    "SimConfig",
    "ENVIRONMENTS",
]

#: Procedural environments; ``"mixed"`` picks urban or suburban from the seed.
ENVIRONMENTS: tuple[str, ...] = ("urban", "suburban", "mixed")
#: Town layouts: ``"irregular"`` (curved streets, diagonal avenues, squares, parking lots, parks,
#: roundabouts) or ``"grid"`` (straight perpendicular streets lined with blocks); or no town:
#: a ``"highway"`` or an ``"open_road"`` (a held-out family Ev-Net never trains on).
LAYOUTS: tuple[str, ...] = ("irregular", "grid", "highway", "open_road")


def _positive(owner: str, name: str, value: float, allow_zero: bool = False) -> None:
    check_number(owner, name, value, min=0.0, min_open=not allow_zero)


def _fraction(owner: str, name: str, value: float) -> None:
    check_number(owner, name, value, min=0.0, max=1.0)


@dataclass(frozen=True)
class LidarConfig:
    """LIDAR_TOP (a Velodyne HDL-32E): beam layout, rate, range and noise."""

    rate_hz: float = 20.0
    #: 32 beams evenly spread over [elev_min_deg, elev_max_deg] (HDL-32E: -30.67 to +10.67 deg).
    n_beams: int = 32
    elev_min_deg: float = -30.67
    elev_max_deg: float = 10.67
    #: Firings per revolution (HDL-32E at 20 Hz: about 1080, 0.33 deg apart).
    n_azimuth: int = 1080
    max_range_m: float = 100.0
    #: Points closer than this are not reported (the sensor's blind zone), metres. Nothing but the
    #: ego vehicle's own body comes this close to a roof lidar.
    min_range_m: float = 0.8
    range_noise_m: float = 0.02
    #: Probability that any return is lost regardless of its strength.
    dropout: float = 0.02
    #: Return power (reflectivity * cos(incidence) / range^2, 1/m^2) at which a return is
    #: detected with probability 1 - 1/e; sets how far the grazing ground is seen.
    power_threshold: float = 1.2e-5
    #: Returns from the ego vehicle's own body (roof, sensor rack, mirrors), as a roof lidar has.
    self_returns: bool = True

    def __post_init__(self) -> None:
        o = "LidarConfig"
        _positive(o, "rate_hz", self.rate_hz)
        check_int(o, "n_beams", self.n_beams, min=1, max=128)
        check_int(o, "n_azimuth", self.n_azimuth, min=8, max=8192)
        if not (-89.0 < self.elev_min_deg <= self.elev_max_deg < 89.0):
            raise ValueError(
                f"{o} needs -89 < elev_min_deg <= elev_max_deg < 89, got {self.elev_min_deg!r}, "
                f"{self.elev_max_deg!r}"
            )
        _positive(o, "max_range_m", self.max_range_m)
        _positive(o, "min_range_m", self.min_range_m, allow_zero=True)
        if self.min_range_m >= self.max_range_m:
            raise ValueError(
                f"{o}.min_range_m ({self.min_range_m!r}) must be below max_range_m "
                f"({self.max_range_m!r})"
            )
        _positive(o, "range_noise_m", self.range_noise_m, allow_zero=True)
        _fraction(o, "dropout", self.dropout)
        _positive(o, "power_threshold", self.power_threshold)


#: The RadarConfig fields that must be positive, and those that may also be zero.
_RADAR_POSITIVE = (
    "rate_hz",
    "ray_spacing_deg",
    "fov_deg",
    "max_range_m",
    "edge_range_m",
    "far_range_m",
    "far_spacing_deg",
    "elevation_half_deg",
    "reference_range_m",
    "scatter_strip_m",
    "detection_softness_db",
    "range_resolution_m",
    "far_range_resolution_m",
    "azimuth_resolution_deg",
    "far_azimuth_resolution_deg",
    "doppler_resolution_mps",
)
_RADAR_NON_NEGATIVE = (
    "far_fov_deg",
    "far_gain_db",
    "corner_gain_db",
    "rcs_fluctuation_db",
    "range_noise_m",
    "far_range_noise_m",
    "far_min_range_m",
    "azimuth_noise_deg",
    "azimuth_noise_mid_deg",
    "azimuth_noise_edge_deg",
    "far_azimuth_noise_deg",
    "doppler_noise_mps",
    "clutter_rate",
    "road_clutter_rate",
    "multipath_loss_db",
)


@dataclass(frozen=True)
class RadarConfig:
    """The five Continental ARS 408-21 radars: rate, field of view, resolution, noise, clutter and
    ghosts. docs/radar-calibration.md gives the source (or the assumption) of every default."""

    rate_hz: float = 13.0
    #: Azimuth spacing of the simulated near-scan beams, degrees (finer than a resolution cell,
    #: so that cells merge several scatterers as the real sensor does).
    ray_spacing_deg: float = 1.0
    # : Near scan: +-fov_deg wide; range max_range_m out to +-45 deg, falling to edge_range_m at the
    # edge.
    fov_deg: float = 60.0
    max_range_m: float = 70.0
    edge_range_m: float = 25.0
    #: Far scan: +-far_fov_deg out to far_range_m (beams spaced far_spacing_deg).
    far_fov_deg: float = 9.0
    far_range_m: float = 250.0
    far_spacing_deg: float = 0.1
    #: Nearest range the far scan reports, m: the ARS 408's two scans are independent and each
    #: reports its own clusters, the far one over 0.2-250 m (inside the near reach too).
    far_min_range_m: float = 0.2
    #: Half-opening of the beam in elevation, degrees (what a beam at sensor height can hit).
    elevation_half_deg: float = 6.0
    #: Range at which a 0 dBsm target has 0 dB signal-to-threshold (near scan), metres: a
    #: 10 dBsm car then reaches 0 dB at the near scan's 70 m (40 * 10 ** (10 / 40) = 71 m).
    reference_range_m: float = 40.0
    #: Extra gain of the far scan, dB: the same target reaches 250 m instead of 70 m,
    #: 40 log10(250 / 70) = 22 dB.
    far_gain_db: float = 22.0
    #: Width of the logistic detection curve of a resolution cell's summed power, dB.
    detection_softness_db: float = 2.5
    # : Scales every class's chance that a beam-hit forms a scattering centre
    # (materials.RADAR_SCATTER).
    scatter_probability: float = 0.46
    #: Width of surface (m) over which materials.RADAR_SCATTER * scatter_probability is the chance
    # : of a scattering centre; a beam standing for a wider strip (farther, or spaced wider) more
    # likely holds one.
    scatter_strip_m: float = 0.44
    #: Swerling I/II fluctuation: each look's power is exponentially distributed about its mean.
    swerling: bool = True
    #: Log-normal aspect fluctuation on top, dB (1 sigma).
    rcs_fluctuation_db: float = 2.0
    #: Resolution cells (targets closer than a cell in range, azimuth and Doppler merge into one
    #: cluster): range bin near / far scan, m; azimuth bin at boresight (evenly spaced in
    #: sin(azimuth), so wider off boresight) near / far, deg; Doppler bin, m/s.
    range_resolution_m: float = 0.39
    far_range_resolution_m: float = 1.79
    azimuth_resolution_deg: float = 3.2
    far_azimuth_resolution_deg: float = 1.6
    doppler_resolution_mps: float = 0.12
    #: Range noise near / far scan, m (1 sigma).
    range_noise_m: float = 0.1
    far_range_noise_m: float = 0.4
    #: Near-scan azimuth noise at boresight, at +-45 deg and at the edge of the field of view;
    #: far-scan azimuth noise; degrees (1 sigma, linear in between).
    azimuth_noise_deg: float = 0.3
    azimuth_noise_mid_deg: float = 1.0
    azimuth_noise_edge_deg: float = 5.0
    far_azimuth_noise_deg: float = 0.1
    doppler_noise_mps: float = 0.03
    #: Mean number of false alarms (noise over the threshold) per sweep.
    clutter_rate: float = 3.0
    #: Mean number of road-surface clutter detections (kerbs, drain covers, debris) per sweep.
    road_clutter_rate: float = 6.0
    #: Extra return from a vertical edge of a flat-faced object (corner reflector), dB.
    corner_gain_db: float = 8.0
    #: Two-way loss of a bounce off a reflecting surface (multipath ghosts), dB.
    multipath_loss_db: float = 12.0
    #: Scales every class's chance that a bounce off it forms a ghost (materials.RADAR_MIRROR).
    multipath_probability: float = 1.0
    #: Clusters the sensor reports a cycle at most; the strongest are kept.
    max_detections: int = 125

    def __post_init__(self) -> None:
        o = "RadarConfig"
        for name in _RADAR_POSITIVE:
            _positive(o, name, getattr(self, name))
        for name in _RADAR_NON_NEGATIVE:
            _positive(o, name, getattr(self, name), allow_zero=True)
        _fraction(o, "scatter_probability", self.scatter_probability)
        _fraction(o, "multipath_probability", self.multipath_probability)
        if not isinstance(self.swerling, bool):
            raise ValueError(f"{o}.swerling must be True or False, got {self.swerling!r}")
        if self.fov_deg > 90.0 or self.far_fov_deg > self.fov_deg:
            raise ValueError(
                f"{o} needs far_fov_deg <= fov_deg <= 90, got {self.far_fov_deg!r}, "
                f"{self.fov_deg!r}"
            )
        if self.edge_range_m > self.max_range_m:
            raise ValueError(
                f"{o}.edge_range_m ({self.edge_range_m!r}) must not exceed max_range_m "
                f"({self.max_range_m!r})"
            )
        if self.far_min_range_m >= self.far_range_m:
            raise ValueError(
                f"{o}.far_min_range_m ({self.far_min_range_m!r}) must be below far_range_m "
                f"({self.far_range_m!r})"
            )
        check_int(o, "max_detections", self.max_detections, min=1)


@dataclass(frozen=True)
class EgoConfig:
    """Ego driving behaviour and odometry error."""

    #: Cruise speed is drawn per scene in this range, m/s (urban; suburban adds 2 m/s).
    cruise_speed_mps: tuple[float, float] = (7.0, 12.0)
    max_accel_mps2: float = 1.6
    max_decel_mps2: float = 2.8
    max_lateral_accel_mps2: float = 2.5
    #: Probability of stopping at an intersection ahead, and the stop's duration range (s).
    stop_probability: float = 0.35
    stop_duration_s: tuple[float, float] = (1.5, 6.0)
    #: Probability that the scene starts from standstill.
    start_at_rest_probability: float = 0.25
    #: Probability that each intersection is a turn (half left, half right).
    turn_probability: float = 0.45
    #: Odometry drift (0 = odometry is the true pose): constant yaw-rate bias drawn with this
    #: standard deviation (deg/s), and a speed scale error with this standard deviation.
    odometry_yaw_bias_std_deg_s: float = 0.0
    odometry_scale_std: float = 0.0

    def __post_init__(self) -> None:
        o = "EgoConfig"
        lo, hi = self.cruise_speed_mps
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi <= 30):
            raise ValueError(
                f"{o}.cruise_speed_mps must be (lo, hi) with 0 < lo <= hi <= 30, got "
                f"{self.cruise_speed_mps!r}"
            )
        for name in ("max_accel_mps2", "max_decel_mps2", "max_lateral_accel_mps2"):
            _positive(o, name, getattr(self, name))
        for name in ("stop_probability", "start_at_rest_probability", "turn_probability"):
            _fraction(o, name, getattr(self, name))
        a, b = self.stop_duration_s
        if not (math.isfinite(a) and math.isfinite(b) and 0 <= a <= b):
            raise ValueError(
                f"{o}.stop_duration_s must be (lo, hi) with 0 <= lo <= hi, got "
                f"{self.stop_duration_s!r}"
            )
        _positive(
            o, "odometry_yaw_bias_std_deg_s", self.odometry_yaw_bias_std_deg_s, allow_zero=True
        )
        _positive(o, "odometry_scale_std", self.odometry_scale_std, allow_zero=True)


@dataclass(frozen=True)
class WorldConfig:
    """Densities of the procedural world (multipliers of the per-environment defaults)."""

    #: "urban", "suburban", or "mixed" (drawn from the seed, 60 % urban).
    environment: str = "mixed"
    #: Scales the number of moving vehicles, pedestrians and parked cars.
    traffic_density: float = 1.0
    #: Random rotation of the whole city in the global frame (streets are not axis aligned).
    random_orientation: bool = True
    #: "irregular" towns (curved and diagonal streets, open squares, ...), the plain "grid", or
    #: a "highway" (a dual carriageway with barriers), or an "open_road" (a country road with
    #: sparse objects on its verges, never used in training); ``environment`` does not apply
    #: to either.
    layout: str = "irregular"
    #: The ego's cruise speed on a highway is drawn per scene in this range, m/s.
    highway_speed_mps: tuple[float, float] = (25.0, 35.0)

    def __post_init__(self) -> None:
        if self.environment not in ENVIRONMENTS:
            raise ValueError(
                f"WorldConfig.environment must be one of {ENVIRONMENTS}, got {self.environment!r}"
            )
        _positive("WorldConfig", "traffic_density", self.traffic_density, allow_zero=True)
        check_choice("WorldConfig", "layout", self.layout, choices=LAYOUTS)
        lo, hi = self.highway_speed_mps
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi <= 45):
            raise ValueError(
                "WorldConfig.highway_speed_mps must be (lo, hi) with 0 < lo <= hi <= 45, got "
                f"{self.highway_speed_mps!r}"
            )


@dataclass(frozen=True)
class SweepFaults:
    """What a real recording does to its sweeps, drawn per sweep from ``seed`` (fractions 0-1).

    Radar sweeps can be missing (``drop``), delivered twice (``duplicate``), or delivered after
    the next sweep of the same radar (``reorder``); lidar sweeps can be missing (``lidar_drop``;
    never a keyframe, so every scene keeps its samples).
    """

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    lidar_drop: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("drop", "duplicate", "reorder", "lidar_drop"):
            _fraction("SweepFaults", name, getattr(self, name))
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"SweepFaults.seed must be a non-negative integer, got {self.seed!r}")

    @property
    def any(self) -> bool:
        return any((self.drop, self.duplicate, self.reorder, self.lidar_drop))


@dataclass(frozen=True)
class SimRadarRig:
    """Which radars the simulated vehicle carries, where, and how fast they sweep.

    ``radar_channels``: any names. ``radar_mounts``: for each channel, the nuScenes mount it sits
    at (``evgrid.data.mounts.RADAR_MOUNTS``); empty: each channel's own name is its mount.
    ``radar_rates_hz``: one rate per channel or one for all; empty: ``RadarConfig.rate_hz``.
    """

    radar_channels: tuple[str, ...] = RADAR_CHANNELS
    radar_mounts: tuple[str, ...] = ()
    radar_rates_hz: tuple[float, ...] = ()
    faults: SweepFaults = field(default_factory=SweepFaults)

    def __post_init__(self) -> None:
        from evgrid.data.mounts import RADAR_MOUNTS

        o = "SimRadarRig"
        chans = self.radar_channels
        if not all(isinstance(c, str) and c for c in chans) or len(set(chans)) != len(chans):
            raise ValueError(f"{o}.radar_channels must be distinct non-empty names, got {chans!r}")
        if self.radar_mounts and len(self.radar_mounts) != len(chans):
            raise ValueError(
                f"{o}.radar_mounts must name one mount per channel ({len(chans)}), got "
                f"{self.radar_mounts!r}"
            )
        for m in self.mounts():
            if m not in RADAR_MOUNTS:
                raise ValueError(
                    f"{o}: no radar mount {m!r}; mounts are {tuple(RADAR_MOUNTS)} (set "
                    "radar_mounts)"
                )
        if len(self.radar_rates_hz) not in (0, 1, len(chans)):
            raise ValueError(
                f"{o}.radar_rates_hz must give one rate or one per channel, got "
                f"{self.radar_rates_hz!r}"
            )
        for r in self.radar_rates_hz:
            _positive(o, "radar_rates_hz", r)
        if not isinstance(self.faults, SweepFaults):
            raise ValueError(f"{o}.faults must be a SweepFaults, got {type(self.faults).__name__}")

    def mounts(self) -> tuple[str, ...]:
        """The nuScenes mount of each channel."""
        return self.radar_mounts or self.radar_channels

    def rates(self, default_hz: float) -> tuple[float, ...]:
        """The rate of each channel, Hz."""
        r = self.radar_rates_hz or (default_hz,)
        return r * len(self.radar_channels) if len(r) == 1 else r


#: The longest simulated scene (s).
MAX_DURATION_S = 3600.0


@dataclass(frozen=True)
class SimConfig:
    """Everything :func:`~evgrid_sim.simulate_scene` needs besides the seed."""

    #: Scene length in seconds (nuScenes scenes last about 20 s).
    duration_s: float = 20.0
    # : One keyframe (a nuScenes sample) every this many lidar sweeps; None: 2 Hz at the lidar's
    # rate.
    keyframe_every: int | None = None
    #: Unix time of the first lidar sweep, microseconds (the seed adds whole days).
    start_time_us: int = 1_533_000_000_000_000
    #: The local grid of the true occupancy raster (docs/conventions.md#local-grid).
    grid: GridSpec = field(default_factory=GridSpec)
    #: Heights above ground that make a cell occupied (the ray ILM's band, paper sec. V-A), metres.
    occupancy_z_min_m: float = 0.3
    occupancy_z_max_m: float = 3.0
    lidar: LidarConfig = field(default_factory=LidarConfig)
    radar: RadarConfig = field(default_factory=RadarConfig)
    ego: EgoConfig = field(default_factory=EgoConfig)
    world: WorldConfig = field(default_factory=WorldConfig)
    rig: SimRadarRig = field(default_factory=SimRadarRig)

    def __post_init__(self) -> None:
        o = "SimConfig"
        # up to an hour: long drives measure the tile store's flat memory (docs/store.md)
        if not (math.isfinite(self.duration_s) and 0.0 < self.duration_s <= MAX_DURATION_S):
            raise ValueError(
                f"{o}.duration_s must be in (0, {MAX_DURATION_S:g}] seconds, "
                f"got {self.duration_s!r}"
            )
        if self.keyframe_every is not None and (
            not isinstance(self.keyframe_every, int) or self.keyframe_every < 1
        ):
            raise ValueError(
                f"{o}.keyframe_every must be a positive integer, got {self.keyframe_every!r}"
            )
        if not isinstance(self.start_time_us, int) or self.start_time_us < 0:
            raise ValueError(
                f"{o}.start_time_us must be a non-negative integer, got {self.start_time_us!r}"
            )
        if not isinstance(self.grid, GridSpec):
            raise ValueError(f"{o}.grid must be a GridSpec, got {type(self.grid).__name__}")
        if not (0.0 <= self.occupancy_z_min_m < self.occupancy_z_max_m):
            raise ValueError(
                f"{o} needs 0 <= occupancy_z_min_m < occupancy_z_max_m, got "
                f"{self.occupancy_z_min_m!r}, {self.occupancy_z_max_m!r}"
            )
        for name, typ in (
            ("lidar", LidarConfig),
            ("radar", RadarConfig),
            ("ego", EgoConfig),
            ("world", WorldConfig),
            ("rig", SimRadarRig),
        ):
            if not isinstance(getattr(self, name), typ):
                raise ValueError(
                    f"{o}.{name} must be a {typ.__name__}, got {type(getattr(self, name)).__name__}"
                )

    @property
    def keyframe_step(self) -> int:
        """Lidar sweeps from one keyframe to the next (``keyframe_every``, or 2 Hz at the lidar's
        rate)."""
        if self.keyframe_every is not None:
            return self.keyframe_every
        return max(1, int(round(self.lidar.rate_hz / 2.0)))

    @property
    def n_frames(self) -> int:
        """Number of lidar sweeps (frames) in a scene."""
        return max(1, int(math.floor(self.duration_s * self.lidar.rate_hz + 1e-9)))

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (nested dicts; tuples become lists): evgrid.serial, the serialiser
        of every parameter dataclass."""
        from evgrid.serial import to_dict

        return to_dict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SimConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError`` naming them."""
        subs = {"lidar": LidarConfig, "radar": RadarConfig, "ego": EgoConfig, "world": WorldConfig}
        kwargs: dict[str, Any] = {}
        known = {f.name for f in fields(cls)}
        for key, value in d.items():
            if key not in known:
                raise ValueError(f"unknown SimConfig field {key!r}")
            if key == "grid":
                kwargs[key] = GridSpec.from_dict(value)
            elif key == "rig":
                v = dict(value)
                bad = set(v) - {f.name for f in fields(SimRadarRig)}
                if bad:
                    raise ValueError(f"unknown SimRadarRig field(s) {sorted(bad)!r}")
                faults = SweepFaults(**v.pop("faults", {}))
                kwargs[key] = SimRadarRig(faults=faults, **{k: tuple(x) for k, x in v.items()})
            elif key in subs:
                sub = subs[key]
                sub_known = {f.name for f in fields(sub)}
                bad = set(value) - sub_known
                if bad:
                    raise ValueError(f"unknown {sub.__name__} field(s) {sorted(bad)!r}")
                sub_kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in value.items()}
                kwargs[key] = sub(**sub_kwargs)
            else:
                kwargs[key] = value
        return cls(**kwargs)
