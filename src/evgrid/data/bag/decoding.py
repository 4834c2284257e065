"""Message decoding: lidar and radar sweeps from ``sensor_msgs/PointCloud2`` and
``radar_msgs/RadarScan`` messages, in evgrid's columns (``LIDAR_COLUMNS``, ``RADAR_COLUMNS``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from evgrid.data.bag.errors import BagError
from evgrid.data.bag.rig import RADIAL, LidarTopic, RadarTopic
from evgrid.data.frame import LIDAR_COLUMNS, NO_RETURN_RANGE_M, RADAR_COLUMNS

__all__ = [
    "RADAR_REQUIRED",
    "RADAR_DEFAULTS",
    "lidar_points",
    "radar_cloud_points",
    "radar_scan_points",
    "compensate",
]

#: Radar columns a cloud must provide (or that the rig must map): position and cross-section.
RADAR_REQUIRED = ("x", "y", "z", "rcs")
#: Values of the ARS 408 validity columns when a radar does not report them: stationary,
#: unambiguous, valid, false-alarm probability < 25 % (what the ISMs would accept anyway).
RADAR_DEFAULTS = {"dyn_prop": 1.0, "ambig_state": 3.0, "invalid_state": 0.0, "pdh0": 1.0}


#: A point is plausible when its range is within these bounds (m): no lidar or radar sees
#: beyond 10 km, and a byte-swapped float is mostly either astronomically large or tiny.
PLAUSIBLE_RANGE_M = (NO_RETURN_RANGE_M, 1e4)


def _plausible_share(xyz: np.ndarray) -> float:
    """The share of the returns whose range is plausible; points that are NaN or exactly
    (0, 0, 0) are no returns (organised clouds mark the beams without one so) and are not
    judged (1.0 when there is no return at all)."""
    with np.errstate(all="ignore"):  # garbage is what is being judged
        p = xyz.astype(np.float64)
        r = np.sqrt((p * p).sum(axis=1))
    ret = np.isfinite(p).all(axis=1) & (p != 0).any(axis=1)
    if not ret.any():
        return 1.0
    lo, hi = PLAUSIBLE_RANGE_M
    return float(((r >= lo) & (r <= hi) & ret).sum() / ret.sum())


def check_plausible(msg: Any, names: list[str], xyz: np.ndarray) -> None:
    """:class:`~evgrid.ros.CloudError` when fewer than half the points of a cloud lie at a
    plausible range: garbage, not a sweep (a cloud flagged big-endian whose data is
    little-endian reads so); the message says whether the other byte order would read well."""
    from dataclasses import replace

    from evgrid.ros import CloudError, cloud_to_columns

    share = _plausible_share(xyz)
    if share >= 0.5:
        return
    order = "big" if msg.is_bigendian else "little"
    other = "little" if msg.is_bigendian else "big"
    try:
        flipped = _plausible_share(
            cloud_to_columns(replace(msg, is_bigendian=not msg.is_bigendian), names)
        )
    except (CloudError, TypeError):
        flipped = 0.0
    hint = (
        f"; read as {other}-endian {100 * flipped:.0f} % would be: is_bigendian is probably wrong"
        if flipped >= 0.5
        else ""
    )
    raise CloudError(
        f"flagged {order}-endian, only {100 * share:.0f} % of its points decode to a plausible "
        f"range ({PLAUSIBLE_RANGE_M[0]:g}-{PLAUSIBLE_RANGE_M[1]:g} m){hint}"
    )


def lidar_points(msg: Any, lidar: LidarTopic, where: str) -> np.ndarray:
    """The lidar columns of a PointCloud2 (intensity and ring 0 when absent); BagError for a
    field the rig names that the cloud lacks, CloudError for a cloud that cannot be decoded or
    decodes to garbage."""
    from evgrid.ros import cloud_fields, cloud_to_columns

    have = set(cloud_fields(msg))
    names, fill = [], []
    for col in LIDAR_COLUMNS:
        name = lidar.field_name(col)
        if name in have:
            names.append(name)
        elif col in ("x", "y", "z") or col in lidar.fields:
            raise BagError(
                f"{where}: lidar field {name!r} (column {col}) not in the cloud; it has "
                f"{sorted(have)}"
            )
        else:
            fill.append(col)  # intensity / ring: optional
    pts = cloud_to_columns(msg, names)
    check_plausible(msg, names[:3], pts[:, :3])
    if not fill:
        return pts
    out = np.zeros((len(pts), len(LIDAR_COLUMNS)), dtype=np.float32)
    cols = [c for c in LIDAR_COLUMNS if c not in fill]
    out[:, [LIDAR_COLUMNS.index(c) for c in cols]] = pts
    return out


def radar_cloud_points(msg: Any, radar: RadarTopic, where: str) -> np.ndarray:
    """The radar columns of a PointCloud2 (see :func:`lidar_points` for the errors)."""
    from evgrid.ros import cloud_fields, cloud_to_columns

    have = set(cloud_fields(msg))
    out = np.zeros((int(msg.height) * int(msg.width), len(RADAR_COLUMNS)), dtype=np.float32)
    take = {c: radar.field_name(c) for c in RADAR_COLUMNS if radar.field_name(c) in have}
    for col in radar.fields:
        if col != RADIAL and col not in take:
            raise BagError(
                f"{where}: radar field {radar.fields[col]!r} (column {col}) not in the cloud; "
                f"it has {sorted(have)}"
            )
    missing = [radar.field_name(c) for c in RADAR_REQUIRED if c not in take]
    if missing:
        raise BagError(
            f"{where}: radar field(s) {missing} not in the cloud; it has {sorted(have)} (map "
            "them under fields:)"
        )
    if take:
        vals = cloud_to_columns(msg, list(take.values()))
        for i, col in enumerate(take):
            out[:, RADAR_COLUMNS.index(col)] = vals[:, i]
        check_plausible(msg, [take[c] for c in ("x", "y", "z")], out[:, :3])
    if "vx_comp" not in take or "vy_comp" not in take:
        if "vx" in take and "vy" in take:  # a vector (compensated below if the rig says raw)
            out[:, RADAR_COLUMNS.index("vx_comp")] = out[:, RADAR_COLUMNS.index("vx")]
            out[:, RADAR_COLUMNS.index("vy_comp")] = out[:, RADAR_COLUMNS.index("vy")]
        else:
            radial = radar.field_name(RADIAL)
            if radial not in have:
                raise BagError(
                    f"{where}: radar needs velocity fields (vx_comp and vy_comp, or vx and vy) or "
                    f"a radial velocity field {radial!r}; the cloud has {sorted(have)}"
                )
            _set_radial(out, cloud_to_columns(msg, [radial])[:, 0])
    for raw, comp in (("vx", "vx_comp"), ("vy", "vy_comp")):
        if raw not in take:
            out[:, RADAR_COLUMNS.index(raw)] = out[:, RADAR_COLUMNS.index(comp)]
    for col, v in RADAR_DEFAULTS.items():
        if col not in take:
            out[:, RADAR_COLUMNS.index(col)] = v
    return out


def _set_radial(out: np.ndarray, v_r: np.ndarray) -> None:
    """Velocity columns from a radial (Doppler) speed: the speed along the line of sight, as a
    vector."""
    x, y, z = (out[:, i].astype(np.float64) for i in range(3))
    r = np.sqrt(x * x + y * y + z * z)
    with np.errstate(invalid="ignore", divide="ignore"):
        ux = np.where(r > 0, x / r, 0.0)
        uy = np.where(r > 0, y / r, 0.0)
    out[:, RADAR_COLUMNS.index("vx_comp")] = v_r * ux
    out[:, RADAR_COLUMNS.index("vy_comp")] = v_r * uy


def compensate(out: np.ndarray, v_sensor: np.ndarray) -> None:
    """Ego-motion compensation of raw Doppler velocities: add the sensor's own speed along each
    line of sight.

    A static target seen from a sensor moving at ``v_sensor`` (sensor frame, m/s) has the raw
    radial speed ``-v_sensor . u`` (u: unit vector to the target); adding ``(v_sensor . u) u``
    to the raw vector ``(vx, vy)`` leaves the target's own motion, as ``vx_comp, vy_comp``.
    """
    p = out[:, :3].astype(np.float64)
    r = np.linalg.norm(p, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(r[:, None] > 0, p / r[:, None], 0.0)
    along = u @ v_sensor
    out[:, RADAR_COLUMNS.index("vx_comp")] = out[:, RADAR_COLUMNS.index("vx")] + along * u[:, 0]
    out[:, RADAR_COLUMNS.index("vy_comp")] = out[:, RADAR_COLUMNS.index("vy")] + along * u[:, 1]


def radar_scan_points(msg: Any) -> np.ndarray:
    """``radar_msgs/RadarScan`` returns -> radar columns (amplitude taken as RCS in dBsm)."""
    ret = msg.returns
    out = np.zeros((len(ret), len(RADAR_COLUMNS)), dtype=np.float32)
    if not len(ret):
        return out
    a = np.array(
        [(r.range, r.azimuth, r.elevation, r.doppler_velocity, r.amplitude) for r in ret],
        dtype=np.float64,
    )
    ce = np.cos(a[:, 2])
    out[:, 0] = a[:, 0] * ce * np.cos(a[:, 1])
    out[:, 1] = a[:, 0] * ce * np.sin(a[:, 1])
    out[:, 2] = a[:, 0] * np.sin(a[:, 2])
    out[:, 3] = a[:, 4]
    _set_radial(out, a[:, 3])
    out[:, 4] = out[:, 6]
    out[:, 5] = out[:, 7]
    for col, v in RADAR_DEFAULTS.items():
        out[:, RADAR_COLUMNS.index(col)] = v
    return out
