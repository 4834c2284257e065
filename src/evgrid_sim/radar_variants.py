"""Radars other than the calibrated one: parameters drawn per scene, and fixed radars outside the
draw.

Ev-Net trained on one simulated radar learns that radar. Training on radars drawn per scene
(:class:`RadarRanges`) asks it to work on any radar in a family; :data:`OUT_OF_RANGE` holds
radars outside every training range, so its transfer to a radar it never saw can be measured
(``evgrid transfer``). A :class:`RadarVariant` changes a :class:`SimConfig` and nothing else:
the same seed gives the same town, drive and lidar whatever the radar.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from evgrid.data.frame import RADAR_CHANNELS
from evgrid.validation import check_number

if TYPE_CHECKING:
    from evgrid_sim.config import SimConfig

__all__ = ["RadarVariant", "RadarRanges", "TRAINING_RANGES", "OUT_OF_RANGE", "NOMINAL"]

_FRONT = "RADAR_FRONT"


@dataclass(frozen=True)
class RadarVariant:
    """One radar, as changes to the calibrated one.

    ``sensitivity_db`` shifts every target's signal-to-threshold (detection rate and reach);
    ``noise_scale`` scales range, azimuth and Doppler noise (near and far scan); ``clutter_scale``
    the false-alarm and road-clutter rates; ``ghost_db`` lowers the multipath bounce loss (more
    ghosts); ``channels`` are the nuScenes mount positions carrying a radar; ``rate_hz`` their
    sweep rate.
    """

    sensitivity_db: float = 0.0
    noise_scale: float = 1.0
    clutter_scale: float = 1.0
    ghost_db: float = 0.0
    channels: tuple[str, ...] = RADAR_CHANNELS
    rate_hz: float | None = None

    def __post_init__(self) -> None:
        check_number(self, "sensitivity_db", min=-40.0, max=40.0)
        check_number(self, "noise_scale", min=0.0)
        check_number(self, "clutter_scale", min=0.0)
        check_number(self, "ghost_db", min=-40.0, max=40.0)
        if self.rate_hz is not None:
            check_number(self, "rate_hz", min=0.0, min_open=True)
        from evgrid.data.mounts import RADAR_MOUNTS

        ch = tuple(self.channels)
        if not ch or len(set(ch)) != len(ch) or not set(ch) <= set(RADAR_MOUNTS):
            raise ValueError(
                "RadarVariant.channels must be distinct radar mounts among "
                f"{tuple(RADAR_MOUNTS)}, got {ch!r}"
            )

    def apply(self, config: SimConfig) -> SimConfig:
        """``config`` with this radar."""
        r = config.radar
        radar = replace(
            r,
            # SNR falls 40 log10(range / reference_range_m): +x dB is the reference range
            # x 10^(x/40).
            reference_range_m=r.reference_range_m * 10.0 ** (self.sensitivity_db / 40.0),
            range_noise_m=r.range_noise_m * self.noise_scale,
            far_range_noise_m=r.far_range_noise_m * self.noise_scale,
            azimuth_noise_deg=r.azimuth_noise_deg * self.noise_scale,
            azimuth_noise_mid_deg=r.azimuth_noise_mid_deg * self.noise_scale,
            azimuth_noise_edge_deg=r.azimuth_noise_edge_deg * self.noise_scale,
            far_azimuth_noise_deg=r.far_azimuth_noise_deg * self.noise_scale,
            doppler_noise_mps=r.doppler_noise_mps * self.noise_scale,
            clutter_rate=r.clutter_rate * self.clutter_scale,
            road_clutter_rate=r.road_clutter_rate * self.clutter_scale,
            multipath_loss_db=max(r.multipath_loss_db - self.ghost_db, 0.0),
            rate_hz=self.rate_hz if self.rate_hz is not None else r.rate_hz,
        )
        rig = replace(
            config.rig,
            radar_channels=tuple(self.channels),
            radar_mounts=(),
            radar_rates_hz=(self.rate_hz,) if self.rate_hz is not None else (),
        )
        return replace(config, radar=radar, rig=rig)

    def to_dict(self) -> dict[str, Any]:
        from evgrid.serial import to_dict

        return to_dict(self)


@dataclass(frozen=True)
class RadarRanges:
    """The family of radars training draws from, one per scene (uniform in each range).

    A radar always looks forward (``RADAR_FRONT``); the others are drawn from the four corner
    mounts, ``n_radars`` in all.
    """

    sensitivity_db: tuple[float, float] = (-4.0, 4.0)
    noise_scale: tuple[float, float] = (0.6, 1.8)
    clutter_scale: tuple[float, float] = (0.4, 2.5)
    ghost_db: tuple[float, float] = (-4.0, 4.0)
    n_radars: tuple[int, int] = (3, 5)
    rate_hz: tuple[float, float] = (9.0, 17.0)

    def __post_init__(self) -> None:
        for name in (
            "sensitivity_db",
            "noise_scale",
            "clutter_scale",
            "ghost_db",
            "rate_hz",
            "n_radars",
        ):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(
                    f"RadarRanges.{name} must be (low, high) with low <= high, got "
                    f"{getattr(self, name)!r}"
                )
        if not (1 <= self.n_radars[0] and self.n_radars[1] <= len(RADAR_CHANNELS)):
            raise ValueError(
                f"RadarRanges.n_radars must lie in [1, {len(RADAR_CHANNELS)}], got "
                f"{self.n_radars!r}"
            )
        if self.noise_scale[0] < 0 or self.clutter_scale[0] < 0 or self.rate_hz[0] <= 0:
            raise ValueError(
                "RadarRanges: noise_scale and clutter_scale must be >= 0 and rate_hz > 0"
            )

    def draw(self, seed: int) -> RadarVariant:
        """The radar of scene ``seed`` (its own generator: the scene's world does not change)."""
        rng = np.random.default_rng([int(seed), 0x12AD])
        u = lambda lo_hi: float(rng.uniform(*lo_hi))  # noqa: E731
        n = int(rng.integers(self.n_radars[0], self.n_radars[1] + 1))
        others = [c for c in RADAR_CHANNELS if c != _FRONT]
        chosen = {_FRONT, *rng.choice(others, size=n - 1, replace=False).tolist()}
        return RadarVariant(
            sensitivity_db=u(self.sensitivity_db),
            noise_scale=u(self.noise_scale),
            clutter_scale=u(self.clutter_scale),
            ghost_db=u(self.ghost_db),
            channels=tuple(c for c in RADAR_CHANNELS if c in chosen),
            rate_hz=u(self.rate_hz),
        )

    def outside(self, v: RadarVariant) -> list[str]:
        """The parameters of ``v`` that lie outside these ranges (empty: ``v`` could be drawn)."""
        out = [
            name
            for name in ("sensitivity_db", "noise_scale", "clutter_scale", "ghost_db")
            if not self._in(name, getattr(v, name))
        ]
        if (
            not (self.n_radars[0] <= len(v.channels) <= self.n_radars[1])
            or _FRONT not in v.channels
        ):
            out.append("channels")
        from evgrid_sim.config import RadarConfig

        if not self._in("rate_hz", RadarConfig().rate_hz if v.rate_hz is None else v.rate_hz):
            out.append("rate_hz")
        return out

    def _in(self, name: str, x: float) -> bool:
        lo, hi = getattr(self, name)
        return lo <= x <= hi

    def to_dict(self) -> dict[str, Any]:
        from evgrid.serial import to_dict

        return to_dict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RadarRanges:
        from evgrid.serial import from_dict

        return from_dict(cls, d)


#: What the shipped Ev-Net was trained on.
TRAINING_RANGES = RadarRanges()

#: Radars outside :data:`TRAINING_RANGES`, each in one respect, and one in all at once.
OUT_OF_RANGE: dict[str, RadarVariant] = {
    "weak (-9 dB)": RadarVariant(sensitivity_db=-9.0, rate_hz=13.0),
    "strong (+9 dB)": RadarVariant(sensitivity_db=9.0, rate_hz=13.0),
    "noisy (noise x3)": RadarVariant(noise_scale=3.0, rate_hz=13.0),
    "cluttered (clutter x6)": RadarVariant(clutter_scale=6.0, rate_hz=13.0),
    "ghostly (bounce loss -9 dB)": RadarVariant(ghost_db=9.0, rate_hz=13.0),
    "no front radar (4 corners)": RadarVariant(
        channels=tuple(c for c in RADAR_CHANNELS if c != _FRONT), rate_hz=13.0
    ),
    "two radars (front, back left)": RadarVariant(
        channels=(_FRONT, "RADAR_BACK_LEFT"), rate_hz=13.0
    ),
    "slow (5 Hz)": RadarVariant(rate_hz=5.0),
    "all at once": RadarVariant(
        sensitivity_db=-7.0,
        noise_scale=2.5,
        clutter_scale=4.0,
        ghost_db=7.0,
        channels=(_FRONT, "RADAR_BACK_LEFT"),
        rate_hz=6.0,
    ),
}


#: The calibrated radar itself: five radars at its own rate.
NOMINAL = RadarVariant()
