"""Pictures of masses: the paper's colours (red = free, green = occupied, blue = unknown), figures, GIFs.

matplotlib (Agg) is imported inside the functions that draw figures, so that importing
evgrid stays light.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from evgrid.evaluate import CLASSES
from evgrid.io import atomic_write

__all__ = ["masses_to_rgb", "plot_panels", "plot_convergence", "write_gif", "trajectory_cells"]

#: rgb -> {free, occupied, unknown}, as in the paper's figures.
CLASS_COLOURS = {"free": (1.0, 0.0, 0.0), "occupied": (0.0, 1.0, 0.0), "unknown": (0.0, 0.0, 1.0)}


def masses_to_rgb(m: np.ndarray) -> np.ndarray:
    """Masses ``(..., 3)`` to a uint8 RGB image with R = m_f, G = m_o, B = m_u."""
    a = np.asarray(m, dtype=np.float32)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(f"masses must have a last axis of length 3, got shape {a.shape}")
    return np.clip(np.rint(a * 255.0), 0, 255).astype(np.uint8)


def _pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _legend(ax) -> None:
    from matplotlib.patches import Patch

    handles = [Patch(color=CLASS_COLOURS[c], label=c) for c in CLASSES]
    ax.legend(handles=handles, loc="lower right", fontsize=7, framealpha=0.8)


def _save(fig, path: str | os.PathLike, title: str = "") -> Path:
    """Title and lay out a figure, write it atomically (format from the suffix) and close it."""
    import io

    plt = _pyplot()
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix.lstrip(".") or "png", dpi=fig.dpi, bbox_inches="tight")
    plt.close(fig)
    return atomic_write(path, lambda f: f.write(buf.getvalue()))


def plot_panels(
    panels: Mapping[str, np.ndarray],
    path: str | os.PathLike,
    title: str = "",
    extent_m: Sequence[float] | None = None,
    tracks: Mapping[str, np.ndarray] | None = None,
    cols: int | None = None,
    gamma: float = 1.0,
) -> Path:
    """Mass grids side by side (paper Figs. 2 and 4), with a legend; ``extent_m`` = (left, right, bottom, top).

    ``gamma < 1`` brightens small masses (a single ISM's m_f = 0.05 is invisible otherwise).
    """
    plt = _pyplot()

    n = len(panels)
    if n == 0:
        raise ValueError("no panels to draw")
    cols = cols or min(n, 3)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.6 * rows), dpi=110, squeeze=False)
    for ax, (name, m) in zip(axes.flat, panels.items()):
        shown = np.asarray(m, dtype=np.float32) ** gamma if gamma != 1.0 else m
        ax.imshow(masses_to_rgb(shown), extent=extent_m, interpolation="nearest")
        if tracks and name in tracks:
            t = tracks[name]
            ax.plot(t[:, 0], t[:, 1], "w-", lw=0.8)
        ax.set_title(name, fontsize=9)
        if extent_m is None:
            ax.set_xticks([])
            ax.set_yticks([])
        else:
            ax.tick_params(labelsize=6)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    _legend(axes.flat[0])
    return _save(fig, path, title)


def plot_convergence(
    curves: Mapping[str, Sequence[Mapping[str, float]]], path: str | os.PathLike, times_s: Sequence[float] | None = None, title: str = ""
) -> Path:
    """IoU over time of each map, one subplot per class (paper: faster convergence with the deep prior)."""
    plt = _pyplot()

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), dpi=110)
    for ax, cls in zip(axes, CLASSES):
        for name, series in curves.items():
            y = [s.get(cls, np.nan) for s in series]
            x = times_s if times_s is not None else np.arange(len(y))
            ax.plot(x, y, label=name, lw=1.2)
        ax.set_title(f"{cls} IoU vs ray_ilm", fontsize=9)
        ax.set_xlabel("time [s]" if times_s is not None else "keyframe", fontsize=8)
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=7)
    return _save(fig, path, title)


def write_gif(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: float = 4.0) -> Path:
    """Write uint8 RGB frames ``(H, W, 3)`` (all one size) as a looping GIF, atomically."""
    import io

    from PIL import Image

    if not frames:
        raise ValueError("no frames to write")
    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return atomic_write(path, lambda f: f.write(buf.getvalue()))


def trajectory_cells(xy: np.ndarray, resolution: float, r0: int, c0: int) -> np.ndarray:
    """Trajectory points in the first pose's frame (m) to (column, row) image coordinates of a map crop."""
    xy = np.asarray(xy, dtype=np.float64)
    rows = -xy[:, 0] / resolution - r0 - 0.5
    cols = -xy[:, 1] / resolution - c0 - 0.5
    return np.stack([cols, rows], axis=1)
