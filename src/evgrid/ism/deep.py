"""Deep IRM: Ev-Net on an accumulated radar detection image, used like the geometric ISMs.

The input image (docs/decisions.md#radar-image-channels) holds the detections of the last
``n_sweeps`` sweeps of every radar, each moved into the *current* ego frame with its own ego pose
and extrinsics, on the local grid. Its channels, one value a cell (0 where a cell has no detection):

=============  ============================================================================
``log_count``  log(1 + number of detections in the cell)
``rcs``        mean radar cross-section, dBsm / 20
``doppler_x``  mean ego-motion compensated Doppler velocity along the ego x axis, m/s / 10
``doppler_y``  the same along y
``recency``    1 - age / ``horizon_s`` of the newest detection in the cell (1 = now)
``range``      distance of the cell centre from the ego origin / (grid half length); static
=============  ============================================================================

The ``range`` channel tells the network where a cell lies: its targets (the ray ILM, 15 m
reach) depend on the distance from the vehicle.

Detections with values no ARS 408 can report (RCS outside [-64, 63.5] dBsm, a compensated
velocity component beyond +-128 m/s, NaN/inf) are dropped, counted and logged once per sweep.

Two paths give the same masses (within 2e-6, tested): the plain one builds the full image
(:func:`radar_image`) and runs the whole Ev-Net (:meth:`DeepIrm.predict_image`); the fast one
(:meth:`DeepIrm.predict`, used by the mapper) builds Ev-Net's max-pooled input straight from the
detections, runs the network's trunk on the fastest runtime installed
(:mod:`evgrid.ism.runtime`), and upsamples the evidence into masses in one compiled pass.
"""

from __future__ import annotations

import collections
import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from evgrid.data.frame import RadarSweep, radar_column
from evgrid.geometry import SE3, GridSpec
from evgrid.package import shipped_checkpoint
from evgrid.validation import check_int, check_number

logger = logging.getLogger(__name__)

__all__ = [
    "CHANNELS",
    "DETECTION_COLUMNS",
    "RadarImageParams",
    "radar_detections",
    "detections_to_image",
    "radar_image",
    "DeepIrm",
    "checkpoint_file",
    "default_checkpoint",
    "evidence_to_masses",
    "RCS_RANGE_DBSM",
    "MAX_SPEED_MPS",
]

CHANNELS: tuple[str, ...] = ("log_count", "rcs", "doppler_x", "doppler_y", "recency", "range")

_X, _Y, _RCS, _VX, _VY = (radar_column(c) for c in ("x", "y", "rcs", "vx_comp", "vy_comp"))

#: RCS the ARS 408 can report (dBsm); values outside are corrupt and dropped.
RCS_RANGE_DBSM: tuple[float, float] = (-64.0, 63.5)
#: Largest velocity component the ARS 408 can report (m/s); faster detections are dropped.
MAX_SPEED_MPS: float = 128.0


class _SweepLog:
    """Remembers the last sweeps whose drops were reported, so each sweep is logged once, not once
    per update."""

    def __init__(self, size: int = 1024):
        self._seen: collections.OrderedDict[tuple[str, int], None] = collections.OrderedDict()
        self._size = size

    def first_time(self, sweep: RadarSweep) -> bool:
        key = (sweep.channel, sweep.timestamp)
        if key in self._seen:
            return False
        self._seen[key] = None
        if len(self._seen) > self._size:
            self._seen.popitem(last=False)
        return True


_PLAIN_LOG = _SweepLog()


def _log_drops(sweep: RadarSweep, n_nonfinite: int, n_range: int, n_points: int) -> None:
    if n_nonfinite or n_range:
        logger.warning(
            "deep_irm: %s sweep at t = %d us: dropped %d of %d detections (%d NaN/inf, %d outside "
            "the "
            "sensor's range: RCS in [%g, %g] dBsm, |v| <= %g m/s)",
            sweep.channel,
            sweep.timestamp,
            n_nonfinite + n_range,
            n_points,
            n_nonfinite,
            n_range,
            *RCS_RANGE_DBSM,
            MAX_SPEED_MPS,
        )


def _valid_detections(p: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Mask of the usable rows of a sweep's points, and the numbers dropped as non-finite and out of
    range."""
    finite = np.isfinite(p[:, [_X, _Y, 2, _RCS, _VX, _VY]]).all(axis=1)
    with np.errstate(invalid="ignore"):
        in_range = (
            (p[:, _RCS] >= RCS_RANGE_DBSM[0])
            & (p[:, _RCS] <= RCS_RANGE_DBSM[1])
            & (np.abs(p[:, _VX]) <= MAX_SPEED_MPS)
            & (np.abs(p[:, _VY]) <= MAX_SPEED_MPS)
        )
    ok = finite & in_range
    return ok, int((~finite).sum()), int((finite & ~in_range).sum())


@dataclass(frozen=True, slots=True)
class RadarImageParams:
    """How sweeps become an input image: sweeps kept per radar and the age horizon (s)."""

    n_sweeps: int = 10
    horizon_s: float = 1.0

    def __post_init__(self) -> None:
        check_int(self, "n_sweeps", min=1)
        check_number(self, "horizon_s", min=0.0, min_open=True)


#: Columns of a detection table (see :func:`radar_detections`).
DETECTION_COLUMNS: tuple[str, ...] = ("x", "y", "rcs", "doppler_x", "doppler_y", "recency")


@numba.njit(cache=True)
def _k_accumulate(det, half, inv_res, img, count):
    n = img.shape[1]
    for k in range(det.shape[0]):
        r = int(math.floor(half - det[k, 0] * inv_res))
        c = int(math.floor(half - det[k, 1] * inv_res))
        if r < 0 or r >= n or c < 0 or c >= n:
            continue
        count[r, c] += 1.0
        img[1, r, c] += det[k, 2]
        img[2, r, c] += det[k, 3]
        img[3, r, c] += det[k, 4]
        if det[k, 5] > img[4, r, c]:
            img[4, r, c] = det[k, 5]


@functools.lru_cache(maxsize=4)
def _range_channel(grid: GridSpec) -> np.ndarray:
    rows, cols = np.meshgrid(np.arange(grid.n_cells), np.arange(grid.n_cells), indexing="ij")
    x, y = grid.cell_to_xy(rows, cols)
    return (np.hypot(x, y) / grid.half_extent).astype(np.float32)


def _check_inputs(sweeps: Sequence[RadarSweep], ego_pose: SE3) -> None:
    """The deep IRM's arguments, named when wrong (not an AttributeError deep inside)."""
    if isinstance(sweeps, RadarSweep):
        raise TypeError(
            "radar sweeps must be a sequence of RadarSweep, got one RadarSweep: wrap it in a list"
        )
    if not isinstance(sweeps, Sequence) or isinstance(sweeps, (str, bytes)):
        raise TypeError(
            f"radar sweeps must be a sequence of RadarSweep, got {type(sweeps).__name__}"
        )
    bad = [type(s).__name__ for s in sweeps if not isinstance(s, RadarSweep)]
    if bad:
        raise TypeError(
            f"radar sweeps must be RadarSweep objects, got {bad[0]} (the first of {len(bad)}); "
            "build them with evgrid.data.frame.RadarSweep(points, sensor_to_ego, ego_pose, ...)"
        )
    if not isinstance(ego_pose, SE3):
        raise TypeError(
            f"ego_pose must be an SE3 (the ego pose of now), got {type(ego_pose).__name__}"
        )


def radar_detections(
    sweeps: Sequence[RadarSweep],
    ego_pose: SE3,
    now_us: int | None = None,
    params: RadarImageParams = RadarImageParams(),
) -> np.ndarray:
    """Detections ``(k, 6)`` float32 in the ego frame at ``ego_pose``, columns ``DETECTION_COLUMNS``
    (scaled).

    Each sweep is moved with its own ego pose and extrinsics; Doppler is rotated into the ego
    frame. ``now_us`` (µs) defaults to the newest sweep's time. NaN/inf detections and values
    outside the sensor's range are dropped (logged once per sweep).
    """
    _check_inputs(sweeps, ego_pose)
    if not sweeps:
        return np.zeros((0, len(DETECTION_COLUMNS)), np.float32)
    now = max(s.timestamp for s in sweeps) if now_us is None else int(now_us)
    to_ego = ego_pose.inverse()
    parts = []
    for s in sweeps:
        p = s.points
        ok, n_nonfinite, n_range = _valid_detections(p)
        if _PLAIN_LOG.first_time(s):
            _log_drops(s, n_nonfinite, n_range, len(p))
        if not ok.any():
            continue
        p = p[ok]
        t = to_ego @ s.ego_pose @ s.sensor_to_ego
        d = np.empty((len(p), len(DETECTION_COLUMNS)), np.float64)
        d[:, 0:2] = t.apply(p[:, 0:3])[:, :2]
        d[:, 2] = p[:, _RCS] / 20.0
        d[:, 3:5] = (p[:, [_VX, _VY]].astype(np.float64) @ t.rotation[:2, :2].T) / 10.0
        age = (now - s.timestamp) * 1e-6
        d[:, 5] = max(0.0, 1.0 - age / params.horizon_s)
        parts.append(d)
    if not parts:
        return np.zeros((0, len(DETECTION_COLUMNS)), np.float32)
    return np.concatenate(parts).astype(np.float32)


def detections_to_image(det: np.ndarray, grid: GridSpec = GridSpec()) -> np.ndarray:
    """The Ev-Net input ``(len(CHANNELS), n, n)`` float32 from a detection table of
    :func:`radar_detections`."""
    det = np.asarray(det)
    if det.ndim != 2 or det.shape[1] != len(DETECTION_COLUMNS):
        raise ValueError(
            f"detections must have shape (k, {len(DETECTION_COLUMNS)}), got {det.shape}"
        )
    n = grid.n_cells
    img = np.zeros((len(CHANNELS), n, n), dtype=np.float32)
    count = np.zeros((n, n), dtype=np.float32)
    if len(det):
        _k_accumulate(
            np.ascontiguousarray(det, dtype=np.float64), n / 2.0, 1.0 / grid.resolution, img, count
        )
        hit = count > 0
        for ch in (1, 2, 3):
            img[ch][hit] /= count[hit]
        img[0] = np.log1p(count)
    img[5] = _range_channel(grid)
    return img


def radar_image(
    sweeps: Sequence[RadarSweep],
    ego_pose: SE3,
    grid: GridSpec = GridSpec(),
    now_us: int | None = None,
    params: RadarImageParams = RadarImageParams(),
) -> np.ndarray:
    """The Ev-Net input ``(len(CHANNELS), n, n)`` float32 from radar sweeps, in the ego frame at
    ``ego_pose``.

    The caller chooses which sweeps to pass (e.g. the last ``params.n_sweeps`` of each radar).
    """
    return detections_to_image(radar_detections(sweeps, ego_pose, now_us, params), grid)


# --- the fast path: pooled input straight from the detections, upsample fused with eq. (9)-(14) ---


@numba.njit(cache=True)
def _k_sweep_rows(p, rot, trans, recency, rcs_lo, rcs_hi, v_max, out, start, drops):
    """Append a sweep's usable detections as rows of ``DETECTION_COLUMNS`` to ``out`` from
    ``start``.

    The same arithmetic as :func:`radar_detections` (float64, rounded to float32 once);
    ``drops`` += [non-finite, out of range]. Returns the next free row.
    """
    k = start
    for i in range(p.shape[0]):
        x, y, z = np.float64(p[i, _X]), np.float64(p[i, _Y]), np.float64(p[i, 2])
        rcs, vx, vy = np.float64(p[i, _RCS]), np.float64(p[i, _VX]), np.float64(p[i, _VY])
        if not (
            np.isfinite(x)
            and np.isfinite(y)
            and np.isfinite(z)
            and np.isfinite(rcs)
            and np.isfinite(vx)
            and np.isfinite(vy)
        ):
            drops[0] += 1
            continue
        if rcs < rcs_lo or rcs > rcs_hi or abs(vx) > v_max or abs(vy) > v_max:
            drops[1] += 1
            continue
        out[k, 0] = np.float32(rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0])
        out[k, 1] = np.float32(rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1])
        out[k, 2] = np.float32(rcs / 20.0)
        out[k, 3] = np.float32((vx * rot[0, 0] + vy * rot[0, 1]) / 10.0)
        out[k, 4] = np.float32((vx * rot[1, 0] + vy * rot[1, 1]) / 10.0)
        out[k, 5] = np.float32(recency)
        k += 1
    return k


@numba.njit(cache=True)
def _k_pooled_image(
    det, half, inv_res, pool, log1p_table, acc, count, fine_idx, pmax, occ, pooled_idx, out
):
    """Ev-Net's max-pooled input ``out`` ``(C, n/pool, n/pool)`` from detections, without the full
    image.

    Each touched fine cell gets the value :func:`detections_to_image` gives it (the same float32
    sums and divisions); a pooled cell is the max over its ``pool x pool`` fine cells, where an
    empty fine cell counts as 0 (``out`` holds zeros in channels 0-4 on entry). ``acc``,
    ``count`` (fine) and ``occ`` (pooled) are zero on entry and left zero.
    """
    n = count.shape[0]
    m = out.shape[1]
    nf = 0
    for k in range(det.shape[0]):
        r = int(math.floor(half - np.float64(det[k, 0]) * inv_res))
        c = int(math.floor(half - np.float64(det[k, 1]) * inv_res))
        if r < 0 or r >= n or c < 0 or c >= n:
            continue
        if count[r, c] == 0.0:
            fine_idx[nf] = r * n + c
            nf += 1
        count[r, c] += np.float32(1.0)
        acc[r, c, 0] = np.float32(acc[r, c, 0] + np.float64(det[k, 2]))
        acc[r, c, 1] = np.float32(acc[r, c, 1] + np.float64(det[k, 3]))
        acc[r, c, 2] = np.float32(acc[r, c, 2] + np.float64(det[k, 4]))
        if det[k, 5] > acc[r, c, 3]:
            acc[r, c, 3] = det[k, 5]
    npool = 0
    for q in range(nf):
        r = fine_idx[q] // n
        c = fine_idx[q] % n
        pr = r // pool
        pc = c // pool
        cnt = count[r, c]
        if pr < m and pc < m:  # MaxPool2d drops a remainder
            ci = int(cnt)
            v0 = log1p_table[ci] if ci < log1p_table.shape[0] else np.float32(math.log1p(cnt))
            v1 = np.float32(acc[r, c, 0] / cnt)
            v2 = np.float32(acc[r, c, 1] / cnt)
            v3 = np.float32(acc[r, c, 2] / cnt)
            v4 = acc[r, c, 3]
            if occ[pr, pc] == 0:
                pooled_idx[npool] = pr * m + pc
                npool += 1
                pmax[0, pr, pc] = v0
                pmax[1, pr, pc] = v1
                pmax[2, pr, pc] = v2
                pmax[3, pr, pc] = v3
                pmax[4, pr, pc] = v4
            else:
                pmax[0, pr, pc] = max(pmax[0, pr, pc], v0)
                pmax[1, pr, pc] = max(pmax[1, pr, pc], v1)
                pmax[2, pr, pc] = max(pmax[2, pr, pc], v2)
                pmax[3, pr, pc] = max(pmax[3, pr, pc], v3)
                pmax[4, pr, pc] = max(pmax[4, pr, pc], v4)
            occ[pr, pc] += 1
        count[r, c] = 0.0
        acc[r, c, 0] = 0.0
        acc[r, c, 1] = 0.0
        acc[r, c, 2] = 0.0
        acc[r, c, 3] = 0.0
    full = pool * pool
    for q in range(npool):
        pr = pooled_idx[q] // m
        pc = pooled_idx[q] % m
        for ch in range(5):
            v = pmax[ch, pr, pc]
            out[ch, pr, pc] = v if occ[pr, pc] == full else max(v, np.float32(0.0))
        occ[pr, pc] = 0


@numba.njit(cache=True)
def _k_upsample_masses(ef, eo, out):
    """Bilinear upsampling of evidence ``ef, eo`` ``(h, w)`` to ``out``'s ``(H, W)`` (torch's
    ``align_corners=False`` arithmetic, float32), turned into masses ``[e_f/S, e_o/S, 2/S]``, ``S =
    2 + e_f + e_o`` (paper eqs. (9), (10), (14); float64, as :func:`evgrid.mass.from_evidence`).

    Returns the number of cells whose evidence is negative or not finite.
    """
    h, w = ef.shape
    oh, ow = out.shape[0], out.shape[1]
    one = np.float32(1.0)
    half = np.float32(0.5)
    sh = np.float32(h) / np.float32(oh)
    sw = np.float32(w) / np.float32(ow)
    # torch mixes along columns first, then rows: w(i) = l0 (k x[r0, a] + l x[r0, b]) + l1 (...);
    # the column mixes of every source row are computed once and the row mix runs contiguous.
    cf = np.empty((h, ow), np.float32)
    co = np.empty((h, ow), np.float32)
    for j in range(ow):
        src = max(sw * (np.float32(j) + half) - half, np.float32(0.0))
        a = int(src)
        b = a + 1 if a < w - 1 else a
        fr = src - np.float32(a)
        k = one - fr
        for r in range(h):
            cf[r, j] = k * ef[r, a] + fr * ef[r, b]
            co[r, j] = k * eo[r, a] + fr * eo[r, b]
    bad = 0
    for i in range(oh):
        src = max(sh * (np.float32(i) + half) - half, np.float32(0.0))
        r0 = int(src)
        r1 = r0 + 1 if r0 < h - 1 else r0
        l1 = src - np.float32(r0)
        l0 = one - l1
        f0, f1, o0, o1 = cf[r0], cf[r1], co[r0], co[r1]
        for j in range(ow):
            f = l0 * f0[j] + l1 * f1[j]
            o = l0 * o0[j] + l1 * o1[j]
            bad += not (f >= 0.0 and o >= 0.0 and f < np.inf and o < np.inf)
            f64 = np.float64(f)
            o64 = np.float64(o)
            s = 2.0 + f64 + o64
            out[i, j, 0] = np.float32(f64 / s)
            out[i, j, 1] = np.float32(o64 / s)
            out[i, j, 2] = np.float32(2.0 / s)
    return bad


@functools.lru_cache(maxsize=4)
def _pooled_range(grid: GridSpec, pool: int) -> np.ndarray:
    m = grid.n_cells // pool
    r = _range_channel(grid)[: m * pool, : m * pool]
    return r.reshape(m, pool, m, pool).max(axis=(1, 3))


class _PooledInput:
    """Reused buffers of the fast path (fresh multi-megabyte arrays cost more in page faults than
    the work)."""

    def __init__(self, grid: GridSpec, pool: int):
        n = grid.n_cells
        m = n // pool
        self.grid, self.pool = grid, pool
        self.acc = np.zeros((n, n, 4), np.float32)
        self.count = np.zeros((n, n), np.float32)
        self.fine_idx = np.empty(0, np.int64)
        self.pmax = np.zeros((5, m, m), np.float32)
        self.occ = np.zeros((m, m), np.int32)
        self.pooled_idx = np.empty(m * m, np.int64)
        self.out = np.zeros((1, len(CHANNELS), m, m), np.float32)
        self.range = _pooled_range(grid, pool)
        self.det = np.empty((0, len(DETECTION_COLUMNS)), np.float32)
        self.log1p = np.log1p(np.arange(4096, dtype=np.float32))

    def detections(
        self, sweeps: Sequence[RadarSweep], ego_pose: SE3, now: int, horizon_s: float, report
    ) -> np.ndarray:
        total = sum(len(s.points) for s in sweeps)
        if self.det.shape[0] < total:
            self.det = np.empty(
                (max(total, 2 * self.det.shape[0]), len(DETECTION_COLUMNS)), np.float32
            )
        to_ego = ego_pose.inverse()
        drops = np.zeros(2, np.int64)
        k = 0
        for s in sweeps:
            if not len(s.points):
                continue
            t = to_ego @ s.ego_pose @ s.sensor_to_ego
            age = (now - s.timestamp) * 1e-6
            drops[:] = 0
            k = _k_sweep_rows(
                s.points,
                t.rotation,
                t.translation,
                max(0.0, 1.0 - age / horizon_s),
                RCS_RANGE_DBSM[0],
                RCS_RANGE_DBSM[1],
                MAX_SPEED_MPS,
                self.det,
                k,
                drops,
            )
            report(s, int(drops[0]), int(drops[1]))
        return self.det[:k]

    def image(self, det: np.ndarray) -> np.ndarray:
        out = self.out[0]
        out[:5] = 0.0
        out[5] = self.range
        if len(det):
            if self.fine_idx.shape[0] < len(det):
                self.fine_idx = np.empty(max(len(det), 2 * self.fine_idx.shape[0]), np.int64)
            g = self.grid
            _k_pooled_image(
                det,
                g.n_cells / 2.0,
                1.0 / g.resolution,
                self.pool,
                self.log1p,
                self.acc,
                self.count,
                self.fine_idx,
                self.pmax,
                self.occ,
                self.pooled_idx,
                out,
            )
        return self.out


def evidence_to_masses(evidence: np.ndarray, grid: GridSpec) -> np.ndarray:
    """Masses ``(n, n, 3)`` float32 from Ev-Net's trunk output ``(2, m, m)``: bilinear upsampling
    and eq. (9)-(14) in one pass."""
    e = np.asarray(evidence, dtype=np.float32)
    if e.ndim != 3 or e.shape[0] != 2:
        raise ValueError(f"evidence must have shape (2, h, w), got {e.shape}")
    out = np.empty(grid.shape + (3,), np.float32)
    if _k_upsample_masses(e[0], e[1], out):
        raise ValueError("e: evidence must be finite and non-negative")
    return out


def default_checkpoint() -> Path:
    """Path of the Ev-Net checkpoint shipped inside the package (trained on simulated scenes)."""
    return shipped_checkpoint("shipped")


def checkpoint_file(checkpoint: str | Path | None) -> Path:
    """The file a checkpoint setting names: None the default, a name of
    :data:`evgrid.package.SHIPPED_CHECKPOINTS` its shipped file, anything else a path."""
    if checkpoint is None:
        return default_checkpoint()
    return shipped_checkpoint(checkpoint) or Path(checkpoint)


class DeepIrm:
    """The deep inverse radar model: radar sweeps in, a local mass grid ``(n, n, 3)`` out.

    Loads the shipped checkpoint unless another is named. ``threads`` sets the intra-op
    threads for inference (the paper runs on one core). ``runtime`` runs the fast path's
    network (:data:`evgrid.ism.runtime.RUNTIMES`; ``auto``: ONNX Runtime when installed, else
    torch); the plain path (:meth:`predict_image`) always runs torch. ``n_dropped`` counts the
    detections dropped by :meth:`predict` (non-finite, outside the sensor's range), each sweep once.
    """

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        grid: GridSpec = GridSpec(),
        params: RadarImageParams = RadarImageParams(),
        threads: int = 1,
        runtime: str = "auto",
    ):
        import torch

        from evgrid.ism.evnet import CheckpointError, load_checkpoint
        from evgrid.ism.runtime import RUNTIMES

        if not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads must be a positive integer, got {threads!r}")
        if runtime not in RUNTIMES:
            raise ValueError(f"runtime must be one of {RUNTIMES}, got {runtime!r}")
        path = checkpoint_file(checkpoint)
        loaded = load_checkpoint(path)
        trained_spec = loaded.extra.get("grid")
        if trained_spec is not None and GridSpec.from_dict(trained_spec) != grid:
            raise CheckpointError(
                f"{path}: trained on grid {trained_spec}, but the grid is {grid.to_dict()}"
            )
        if loaded.model.config.in_channels != len(CHANNELS):
            raise CheckpointError(
                f"{path}: model takes {loaded.model.config.in_channels} channels, inputs have "
                f"{len(CHANNELS)}"
            )
        self.grid = grid
        self.params = params
        self.threads = threads
        self.runtime_name = runtime
        self.checkpoint = path
        self.info = loaded.extra
        torch.set_num_threads(threads)
        self._torch = torch
        self.model = loaded.model.to(memory_format=torch.channels_last).eval()
        self.pool = int(loaded.model.config.pool)
        self._runtime = None  # built on first use (the ONNX export takes a fraction of a second)
        self._pooled: _PooledInput | None = None
        self._seen = _SweepLog()
        self.n_dropped = 0

    @property
    def runtime(self):
        """The runtime of the fast path's network (see :mod:`evgrid.ism.runtime`), built on first
        use."""
        if self._runtime is None:
            from evgrid.ism.runtime import make_runtime

            m = self.grid.n_cells // self.pool
            self._runtime = make_runtime(
                self.model, (len(CHANNELS), m, m), self.runtime_name, self.threads
            )
        return self._runtime

    def predict_image(self, image: np.ndarray) -> np.ndarray:
        """Masses ``(n, n, 3)`` float32 from an input image ``(C, n, n)`` (see :func:`radar_image`):
        the plain path."""
        from evgrid.mass import from_evidence

        torch = self._torch
        if not isinstance(image, np.ndarray):
            raise TypeError(
                f"predict_image: image must be a numpy array (C, n, n) as radar_image makes, got "
                f"{type(image).__name__}"
            )
        if image.shape != (len(CHANNELS), self.grid.n_cells, self.grid.n_cells):
            raise ValueError(
                f"input image must be {(len(CHANNELS),) + self.grid.shape}, got {image.shape}"
            )
        if image.dtype.kind not in "fiu":
            raise TypeError(f"predict_image: image must hold real numbers, got dtype {image.dtype}")
        bad = ~np.isfinite(image).all(axis=(1, 2))
        if bad.any():
            # else Ev-Net turns it into NaN evidence: "e: evidence must be finite", naming nothing
            raise ValueError(
                "predict_image: the input image is not finite (NaN or inf) in channel(s) "
                + ", ".join(f"{i} ({CHANNELS[i]})" for i in np.flatnonzero(bad))
            )
        x = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32))[None]
        with torch.inference_mode():
            e = self.model(x.to(memory_format=torch.channels_last))[0]
        return from_evidence(e.permute(1, 2, 0).numpy())

    def pooled_input(
        self, sweeps: Sequence[RadarSweep], ego_pose: SE3, now_us: int | None = None
    ) -> np.ndarray:
        """Ev-Net's max-pooled input ``(1, C, n/pool, n/pool)``, built straight from the detections.

        Equals max-pooling :func:`radar_image`; the array is reused by the next call.
        """
        _check_inputs(sweeps, ego_pose)
        if self._pooled is None:
            self._pooled = _PooledInput(self.grid, self.pool)
        if not sweeps:
            return self._pooled.image(np.zeros((0, len(DETECTION_COLUMNS)), np.float32))
        now = max(s.timestamp for s in sweeps) if now_us is None else int(now_us)
        det = self._pooled.detections(sweeps, ego_pose, now, self.params.horizon_s, self._report)
        return self._pooled.image(det)

    def _report(self, sweep: RadarSweep, n_nonfinite: int, n_range: int) -> None:
        if self._seen.first_time(sweep):
            self.n_dropped += n_nonfinite + n_range
            _log_drops(sweep, n_nonfinite, n_range, len(sweep.points))

    def predict(
        self, sweeps: Sequence[RadarSweep], ego_pose: SE3, now_us: int | None = None
    ) -> np.ndarray:
        """Local mass grid ``(n, n, 3)`` float32 from radar sweeps, in the ego frame at
        ``ego_pose``: the fast path.

        The same masses as ``predict_image(radar_image(...))`` within float rounding (2e-6 on
        torch, about 1e-5 on ONNX Runtime, whose convolutions round differently).
        """
        evidence = self.runtime(self.pooled_input(sweeps, ego_pose, now_us))
        return evidence_to_masses(evidence, self.grid)

    def __call__(
        self, sweeps: Sequence[RadarSweep], ego_pose: SE3, now_us: int | None = None
    ) -> np.ndarray:
        """Local mass grid from radar sweeps, in the ego frame at ``ego_pose`` (:meth:`predict`)."""
        return self.predict(sweeps, ego_pose, now_us)
