"""Deep IRM: Ev-Net on an accumulated radar detection image, used like the geometric ISMs.

The input image (docs/decisions.md#radar-image-channels) holds the detections of the last ``n_sweeps`` sweeps
of every radar, each moved into the *current* ego frame with its own ego pose and extrinsics,
on the local grid. Its channels, one value a cell (0 where a cell has no detection):

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
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numba
import numpy as np

from evgrid.data.frame import RadarSweep, radar_column
from evgrid.geometry import SE3, GridSpec

__all__ = [
    "CHANNELS",
    "DETECTION_COLUMNS",
    "RadarImageParams",
    "radar_detections",
    "detections_to_image",
    "radar_image",
    "DeepIrm",
    "default_checkpoint",
]

CHANNELS: tuple[str, ...] = ("log_count", "rcs", "doppler_x", "doppler_y", "recency", "range")

_X, _Y, _RCS, _VX, _VY = (radar_column(c) for c in ("x", "y", "rcs", "vx_comp", "vy_comp"))


@dataclass(frozen=True, slots=True)
class RadarImageParams:
    """How sweeps become an input image: sweeps kept per radar and the age horizon (s)."""

    n_sweeps: int = 10
    horizon_s: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.n_sweeps, int) or self.n_sweeps < 1:
            raise ValueError(f"n_sweeps must be a positive integer, got {self.n_sweeps!r}")
        if not (math.isfinite(self.horizon_s) and self.horizon_s > 0):
            raise ValueError(f"horizon_s must be a positive number of seconds, got {self.horizon_s!r}")


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


def radar_detections(
    sweeps: Sequence[RadarSweep],
    ego_pose: SE3,
    now_us: int | None = None,
    params: RadarImageParams = RadarImageParams(),
) -> np.ndarray:
    """Detections ``(k, 6)`` float32 in the ego frame at ``ego_pose``, columns ``DETECTION_COLUMNS`` (scaled).

    Each sweep is moved with its own ego pose and extrinsics; Doppler is rotated into the ego
    frame. ``now_us`` (µs) defaults to the newest sweep's time. NaN/inf detections are dropped.
    """
    if not sweeps:
        return np.zeros((0, len(DETECTION_COLUMNS)), np.float32)
    now = max(s.timestamp for s in sweeps) if now_us is None else int(now_us)
    to_ego = ego_pose.inverse()
    parts = []
    for s in sweeps:
        p = s.points
        ok = np.isfinite(p[:, [_X, _Y, 2, _RCS, _VX, _VY]]).all(axis=1)
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
    """The Ev-Net input ``(len(CHANNELS), n, n)`` float32 from a detection table of :func:`radar_detections`."""
    det = np.asarray(det)
    if det.ndim != 2 or det.shape[1] != len(DETECTION_COLUMNS):
        raise ValueError(f"detections must have shape (k, {len(DETECTION_COLUMNS)}), got {det.shape}")
    n = grid.n_cells
    img = np.zeros((len(CHANNELS), n, n), dtype=np.float32)
    count = np.zeros((n, n), dtype=np.float32)
    if len(det):
        _k_accumulate(np.ascontiguousarray(det, dtype=np.float64), n / 2.0, 1.0 / grid.resolution, img, count)
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
    """The Ev-Net input ``(len(CHANNELS), n, n)`` float32 from radar sweeps, in the ego frame at ``ego_pose``.

    The caller chooses which sweeps to pass (e.g. the last ``params.n_sweeps`` of each radar).
    """
    return detections_to_image(radar_detections(sweeps, ego_pose, now_us, params), grid)


def default_checkpoint() -> Path:
    """Path of the Ev-Net checkpoint shipped inside the package (trained on simulated scenes)."""
    return Path(__file__).resolve().parent / "checkpoints" / "evnet_sim.safetensors"


class DeepIrm:
    """The deep inverse radar model: radar sweeps in, a local mass grid ``(n, n, 3)`` out.

    Loads the shipped checkpoint unless another is named. ``threads`` sets torch's intra-op
    threads for inference (the paper runs on one core).
    """

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        grid: GridSpec = GridSpec(),
        params: RadarImageParams = RadarImageParams(),
        threads: int = 1,
    ):
        import torch

        from evgrid.ism.evnet import CheckpointError, load_checkpoint

        if not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads must be a positive integer, got {threads!r}")
        path = Path(checkpoint) if checkpoint is not None else default_checkpoint()
        loaded = load_checkpoint(path)
        trained_spec = loaded.extra.get("grid")
        if trained_spec is not None and GridSpec.from_dict(trained_spec) != grid:
            raise CheckpointError(f"{path}: trained on grid {trained_spec}, but the grid is {grid.to_dict()}")
        if loaded.model.config.in_channels != len(CHANNELS):
            raise CheckpointError(f"{path}: model takes {loaded.model.config.in_channels} channels, inputs have {len(CHANNELS)}")
        self.grid = grid
        self.params = params
        self.threads = threads
        self.checkpoint = path
        self.info = loaded.extra
        torch.set_num_threads(threads)
        self._torch = torch
        self.model = loaded.model.to(memory_format=torch.channels_last).eval()

    def predict_image(self, image: np.ndarray) -> np.ndarray:
        """Masses ``(n, n, 3)`` float32 from an input image ``(C, n, n)`` (see :func:`radar_image`)."""
        from evgrid.mass import from_evidence

        torch = self._torch
        if image.shape != (len(CHANNELS), self.grid.n_cells, self.grid.n_cells):
            raise ValueError(f"input image must be {(len(CHANNELS),) + self.grid.shape}, got {image.shape}")
        x = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32))[None]
        with torch.inference_mode():
            e = self.model(x.to(memory_format=torch.channels_last))[0]
        return from_evidence(e.permute(1, 2, 0).numpy())

    def __call__(self, sweeps: Sequence[RadarSweep], ego_pose: SE3, now_us: int | None = None) -> np.ndarray:
        """Local mass grid from radar sweeps, in the ego frame at ``ego_pose``."""
        return self.predict_image(radar_image(sweeps, ego_pose, self.grid, now_us, self.params))
