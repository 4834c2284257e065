"""Pictures of masses, figures and GIFs that read as maps.

Maps are drawn in a map_server-like palette (:func:`map_rgb`: free white, occupied black,
unknown grey, mixed masses as shades between), with the axes in metres (x forward up, y left),
a scale bar, and the legend outside the panels; every plot gives a map the same colour
(:func:`map_colour`). The cells called dynamic (:class:`evgrid.fusion.DynamicParams`) are drawn
in :data:`DYNAMIC_COLOUR` over the maps that keep a score (:func:`map_picture`). The paper's
colours (red free, green occupied, blue unknown) remain as :func:`masses_to_rgb` and
``palette="paper"``.

matplotlib (Agg) is imported inside the functions that draw figures, so that importing
evgrid stays light.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from evgrid.classes import CLASSES
from evgrid.grid import coarse_step
from evgrid.io import atomic_write
from evgrid.mass import vacuous

__all__ = [
    "map_rgb",
    "map_colour",
    "label_panels",
    "masses_to_rgb",
    "plot_panels",
    "plot_convergence",
    "plot_perception_field",
    "write_gif",
    "trajectory_cells",
    "sample_map",
    "called_dynamic",
    "map_picture",
    "overlay_dynamic",
    "dynamic_label",
    "mosaic",
    "write_scene_figures",
    "plot_m_u_min_sweep",
]

#: rgb -> {free, occupied, unknown}, as in the paper's figures.
CLASS_COLOURS = {"free": (1.0, 0.0, 0.0), "occupied": (0.0, 1.0, 0.0), "unknown": (0.0, 0.0, 1.0)}


def masses_to_rgb(m: np.ndarray) -> np.ndarray:
    """Masses ``(..., 3)`` to a uint8 RGB image with R = m_f, G = m_o, B = m_u."""
    a = np.asarray(m, dtype=np.float32)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(f"masses must have a last axis of length 3, got shape {a.shape}")
    return np.clip(np.rint(a * 255.0), 0, 255).astype(np.uint8)


#: The map palette's colours (map_server's PGM greys: free 254, occupied 0, unknown 205).
MAP_PALETTE = {"free": (1.0, 1.0, 1.0), "occupied": (0.0, 0.0, 0.0), "unknown": (0.8, 0.8, 0.8)}
#: The colour of the cells called dynamic, drawn over the map palette (no grey, nor the path's
#: red: it reads on free, occupied and unknown alike).
DYNAMIC_COLOUR = (0.1, 0.4, 1.0)


def map_rgb(m: np.ndarray) -> np.ndarray:
    """Masses ``(..., 3)`` to a uint8 RGB map picture: free white, occupied black, unknown grey.

    Each pixel mixes the three colours of :data:`MAP_PALETTE` by the masses (a mass is a convex
    weight), so confidence reads as shade: a cell with ``m_f = 0.3, m_u = 0.7`` is a lighter
    grey than unknown, one with ``m_o = 0.3, m_u = 0.7`` a darker one, as in a nav2 map.
    """
    a = np.asarray(m, dtype=np.float32)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(f"masses must have a last axis of length 3, got shape {a.shape}")
    grey = a[..., 0] * MAP_PALETTE["free"][0] + a[..., 2] * MAP_PALETTE["unknown"][0]
    v = np.clip(np.rint(grey * 255.0), 0, 255).astype(np.uint8)
    return np.repeat(v[..., None], 3, axis=-1)


def _pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: One line colour per map, the same in every plot (Tableau colours; the reference grey).
_LINE_COLOURS = {
    "ray_ilm": "#555555",
    "fused": "tab:blue",
    "deep_acc": "tab:orange",
    "deep_replace": "tab:green",
    "deep_disc": "tab:red",
    "ray_irm": "tab:purple",
    "nav": "tab:brown",
}
_SPARE_COLOURS = ("tab:pink", "tab:olive", "tab:cyan", "#1b9e77", "#7570b3", "#d95f02")
#: The path's colour in map figures (stands out on white, black and grey).
PATH_COLOUR = "#e6331a"


def map_colour(name: str) -> str:
    """The line colour of map ``name`` in every plot: fixed for the known maps, otherwise
    chosen by the name alone (a checksum), so it does not depend on which maps a plot has."""
    import zlib

    return _LINE_COLOURS.get(name) or _SPARE_COLOURS[zlib.crc32(name.encode()) % 6]


def _legend(fig, palette: str, path: bool, dynamic: str = "") -> None:
    """The classes' colours (the path, and ``dynamic``: the label of the cells called dynamic)
    as one row below the panels."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    colours = MAP_PALETTE if palette == "map" else CLASS_COLOURS
    handles = [Patch(facecolor=colours[c], edgecolor="0.3", label=c) for c in CLASSES]
    if palette == "map":
        handles.append(
            Patch(
                facecolor="0.55",
                edgecolor="0.3",
                label="shades: mixed masses (darker: more occupied)",
            )
        )
    if dynamic:
        handles.append(Patch(facecolor=DYNAMIC_COLOUR, edgecolor="0.3", label=dynamic))
    if path:
        handles.append(Line2D([], [], color=PATH_COLOUR, lw=1.2, label="path"))
    fig.legend(
        handles=handles, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=len(handles),
        fontsize=8, frameon=False,
    )  # fmt: skip


def _line_legend(fig, ax) -> None:
    """The maps' lines as one row below the panels, off the curves."""
    handles, labels = ax.get_legend_handles_labels()
    fig.legend(
        handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=len(handles),
        fontsize=8, frameon=False,
    )  # fmt: skip


def _scale_bar(ax, width_m: float) -> None:
    """A bar of a round length (1, 2 or 5 x 10^k m, about a fifth of the panel) at the lower
    left, black on a white box so that it reads on any map."""
    from matplotlib.offsetbox import AnchoredOffsetbox, AuxTransformBox, TextArea, VPacker
    from matplotlib.patches import Rectangle

    target = abs(width_m) / 5
    k = 10 ** np.floor(np.log10(target))
    length = max(v * k for v in (1, 2, 5) if v * k <= target)
    # in axes fractions, so an inverted axis (y grows to the left) draws it the same way
    frac = length / abs(width_m)
    bar = AuxTransformBox(ax.transAxes)
    bar.add_artist(Rectangle((0, 0), frac, 0.012, color="k"))
    label = TextArea(f"{length:g} m", textprops=dict(fontsize=7))
    box = AnchoredOffsetbox(
        loc="lower left", child=VPacker(children=[label, bar], align="center", pad=0, sep=2),
        pad=0.3, borderpad=0.4, frameon=True,
    )  # fmt: skip
    box.patch.set_alpha(0.8)
    ax.add_artist(box)


def _save(fig, path: str | os.PathLike, title: str = "") -> Path:
    """Title and lay out a figure, write it atomically (format from the suffix) and close it."""
    import io

    plt = _pyplot()
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(
        buf, format=Path(path).suffix.lstrip(".") or "png", dpi=fig.dpi, bbox_inches="tight"
    )
    plt.close(fig)
    return atomic_write(path, lambda f: f.write(buf.getvalue()))


def _gamma(m: np.ndarray, gamma: float) -> np.ndarray:
    """Masses raised to ``gamma`` and renormalised (still masses): small masses show."""
    a = np.asarray(m, dtype=np.float32)
    if gamma == 1.0:
        return a
    g = a**gamma
    return g / np.maximum(g.sum(-1, keepdims=True), 1e-12)


def plot_panels(
    panels: Mapping[str, np.ndarray],
    path: str | os.PathLike,
    title: str = "",
    extent_m: Sequence[float] | None = None,
    tracks: Mapping[str, np.ndarray] | None = None,
    cols: int | None = None,
    gamma: float = 1.0,
    palette: str = "map",
    dynamic: Mapping[str, np.ndarray] | None = None,
    dynamic_label: str = "dynamic",
) -> Path:
    """Mass grids side by side (paper Figs. 2 and 4), the legend below them.

    With ``extent_m`` = (left, right, bottom, top) in metres of the grid's outer edges as
    drawn (columns left to right, rows top to bottom: for evgrid's grids y at the left and
    right edges, x at the bottom and top, :mod:`evgrid.geometry`), the axes are in metres with
    a scale bar, and ``tracks`` are ``(n, 2)`` paths as (x, y) metres; without it, ``tracks``
    are image (column, row) coordinates. ``palette``: ``map`` (:func:`map_rgb`) or ``paper``
    (:func:`masses_to_rgb`). ``gamma < 1`` brightens small masses (a single ISM's m_f = 0.05
    is invisible otherwise). ``dynamic``: per panel, a boolean mask of its shape, the cells
    called dynamic, drawn in :data:`DYNAMIC_COLOUR` over the map, with ``dynamic_label`` in the
    legend (panels without a mask, and runs without the score, show none).
    """
    if palette not in ("map", "paper"):
        raise ValueError(f"palette must be 'map' or 'paper', got {palette!r}")
    plt = _pyplot()
    to_rgb = map_rgb if palette == "map" else masses_to_rgb

    n = len(panels)
    if n == 0:
        raise ValueError("no panels to draw")
    cols = cols or min(n, 3)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.8 * cols, 3.8 * rows), dpi=110, squeeze=False)
    dynamic = dynamic or {}
    for ax, (name, m) in zip(axes.flat, panels.items()):
        rgb = to_rgb(_gamma(m, gamma))
        if name in dynamic:
            rgb = overlay_dynamic(rgb, dynamic[name])
        ax.imshow(rgb, extent=extent_m, interpolation="nearest")
        if tracks and name in tracks:
            t = np.asarray(tracks[name], dtype=np.float64).reshape(-1, 2)
            if extent_m is not None:  # (x, y) metres: y runs along the image's columns
                ax.plot(t[:, 1], t[:, 0], "-", color=PATH_COLOUR, lw=1.0)
            else:
                ax.plot(t[:, 0], t[:, 1], "-", color=PATH_COLOUR, lw=1.0)
        ax.set_title(name, fontsize=9)
        if extent_m is None:
            ax.set_xticks([])
            ax.set_yticks([])
        else:
            ax.tick_params(labelsize=6)
            ax.set_xlabel("y [m] (left +)", fontsize=7)
            ax.set_ylabel("x [m] (forward +)", fontsize=7)
            _scale_bar(ax, extent_m[1] - extent_m[0])
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    _legend(fig, palette, bool(tracks), dynamic_label if dynamic else "")
    return _save(fig, path, title)


def plot_convergence(
    curves: Mapping[str, Sequence[Mapping[str, float]]],
    path: str | os.PathLike,
    times_s: Sequence[float] | None = None,
    title: str = "",
) -> Path:
    """IoU over time of each map, one subplot per class (paper: faster convergence with the
    deep prior)."""
    plt = _pyplot()

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), dpi=110)
    for ax, cls in zip(axes, CLASSES):
        for name, series in curves.items():
            y = [s.get(cls, np.nan) for s in series]
            x = times_s if times_s is not None else np.arange(len(y))
            ax.plot(x, y, label=name, lw=1.2, color=map_colour(name))
        ax.set_title(f"{cls} IoU vs ray_ilm", fontsize=9)
        ax.set_xlabel("time [s]" if times_s is not None else "keyframe", fontsize=8)
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
    _line_legend(fig, axes[0])
    return _save(fig, path, title)


def plot_perception_field(conv: Mapping, path: str | os.PathLike, title: str = "") -> Path:
    """Free and occupied IoU against the truth and the area classified correctly after 1, 2,
    5, 10 s of driving, mean over scenes with 95% bootstrap intervals
    (``summary["convergence_truth"]``)."""
    plt = _pyplot()

    t = np.asarray(conv["t_s"], dtype=float)
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), dpi=110)
    panels = (
        ("free", 1.0, "free IoU vs truth"),
        ("occupied", 1.0, "occupied IoU vs truth"),
        ("area_m2", 1e-3, "classified correctly [1000 m²]"),
    )
    for k, (name, q) in enumerate(conv["maps"].items()):
        dx = (
            k - (len(conv["maps"]) - 1) / 2
        ) * 0.08  # side by side, so the intervals stay readable
        for ax, (key, scale, label) in zip(axes, panels):
            cis = q[key]
            y = np.array([c["mean"] for c in cis], dtype=float) * scale
            lo = np.array([c["lo"] for c in cis], dtype=float) * scale
            hi = np.array([c["hi"] for c in cis], dtype=float) * scale
            ax.errorbar(
                t * np.exp(dx),
                y,
                yerr=[y - lo, hi - y],
                label=name,
                color=map_colour(name),
                lw=1.2,
                capsize=2,
                marker="o",
                ms=3,
            )
            ax.set_title(label, fontsize=9)
    for ax in axes:
        ax.set_xscale("log")
        ax.set_xticks(t, [f"{v:g}" for v in t])
        ax.set_xlabel("driving time [s]", fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
    _line_legend(fig, axes[0])
    return _save(
        fig, path, title or "perception field over time (mean over scenes, 95% bootstrap interval)"
    )


def write_gif(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: float = 4.0) -> Path:
    """Write uint8 RGB frames ``(H, W, 3)`` (all one size) as a looping GIF, atomically."""
    import io

    from PIL import Image

    if not frames:
        raise ValueError("no frames to write")
    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
    buf = io.BytesIO()
    images[0].save(
        buf, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0
    )
    return atomic_write(path, lambda f: f.write(buf.getvalue()))


def trajectory_cells(xy: np.ndarray, resolution: float, r0: int, c0: int) -> np.ndarray:
    """Trajectory points in the first pose's frame (m) to (column, row) image coordinates of a
    map crop."""
    xy = np.asarray(xy, dtype=np.float64)
    rows = -xy[:, 0] / resolution - r0 - 0.5
    cols = -xy[:, 1] / resolution - c0 - 0.5
    return np.stack([cols, rows], axis=1)


def _box_keys(m, r0: int, c0: int, h: int, w: int) -> list[tuple[int, int]]:
    """Tile keys to look up for box ``[r0, r0+h) x [c0, c0+w)``: those the box meets, or the
    stored ones when fewer (a box larger than the map)."""
    ts = m.tile_cells
    n_box = (
        ((r0 + h - 1) // ts - r0 // ts + 1) * ((c0 + w - 1) // ts - c0 // ts + 1) if h and w else 0
    )
    if n_box > len(m.tiles):
        return list(m.tiles)
    return [
        (ti, tj)
        for ti in range(r0 // ts, (r0 + h - 1) // ts + 1)
        for tj in range(c0 // ts, (c0 + w - 1) // ts + 1)
    ]


def _sampled_shape(name: str, step: int, h: int, w: int) -> tuple[int, int]:
    """The shape of every ``step``-th cell of an ``h`` x ``w`` box; ``name`` is the caller, for
    the error when the step or the box is not valid."""
    if step < 1 or h < 0 or w < 0:
        raise ValueError(
            f"{name} needs step >= 1 and a non-negative box, got step {step}, box {h} x {w}"
        )
    return -(-h // step), -(-w // step)


def sample_map(m, r0: int, c0: int, h: int, w: int, step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Every ``step``-th map cell of ``[r0, r0+h) x [c0, c0+w)``: masses and coverage, read
    tile by tile.

    Only tiles that exist are touched (at most those the box meets), so a picture of a window
    costs the same anywhere on a long drive, and a picture of a whole map grows with its area.
    """
    hh, ww = _sampled_shape("sample_map", step, h, w)
    out = vacuous((hh, ww))
    cov = np.zeros((hh, ww), dtype=np.bool_)
    ts = m.tile_cells
    for ti, tj in _box_keys(m, r0, c0, h, w):
        t = m.tiles.get((ti, tj))
        if t is None:
            continue
        # first sampled row/column inside this tile, as a map index
        ra = max(r0, ti * ts)
        ca = max(c0, tj * ts)
        ra += -(ra - r0) % step
        ca += -(ca - c0) % step
        rb, cb = min(r0 + h, (ti + 1) * ts), min(c0 + w, (tj + 1) * ts)
        if ra >= rb or ca >= cb:
            continue
        src = (slice(ra - ti * ts, rb - ti * ts, step), slice(ca - tj * ts, cb - tj * ts, step))
        piece = t[src]
        oi, oj = (ra - r0) // step, (ca - c0) // step
        out[oi : oi + piece.shape[0], oj : oj + piece.shape[1]] = piece
        cov[oi : oi + piece.shape[0], oj : oj + piece.shape[1]] = m.covered_tiles[(ti, tj)][src]
    return out, cov


#: The share of a picture's block of cells that must be called dynamic for the block to be drawn
#: dynamic: a mover larger than a pixel shows, a lone cell's conflict does not grow to a pixel.
DYNAMIC_SHARE = 0.25


def called_dynamic(m, r0: int, c0: int, h: int, w: int, step: int, threshold: float) -> np.ndarray:
    """Which blocks of ``step`` x ``step`` cells of ``[r0, r0+h) x [c0, c0+w)`` are drawn as
    dynamic: those where at least :data:`DYNAMIC_SHARE` of the cells have a dynamic score
    above ``threshold`` (with ``step`` 1, the cells called dynamic). Read tile by tile as
    :func:`sample_map`; bool ``(ceil(h / step), ceil(w / step))``, no cell called where no
    tile is stored. Raises ValueError if the map keeps no score."""
    if not m.dynamic:
        raise ValueError(
            f"map {m.metadata.get('rule', '?')!r} keeps no dynamic layer (dynamic off)"
        )
    hh, ww = _sampled_shape("called_dynamic", step, h, w)
    n_called = np.zeros((hh, ww), dtype=np.int64)
    ts = m.tile_cells
    for ti, tj in _box_keys(m, r0, c0, h, w):
        d = m.dynamic_tiles.get((ti, tj))
        if d is None:
            continue
        ra, rb = max(r0, ti * ts), min(r0 + h, (ti + 1) * ts)
        ca, cb = max(c0, tj * ts), min(c0 + w, (tj + 1) * ts)
        if ra >= rb or ca >= cb:
            continue
        piece = d[ra - ti * ts : rb - ti * ts, ca - tj * ts : cb - tj * ts] > threshold
        # the blocks this piece meets start at its first cell and at every multiple of step
        rs = np.unique(np.r_[0, np.arange(-(-(ra - r0) // step) * step, rb - r0, step) - ra + r0])
        cs = np.unique(np.r_[0, np.arange(-(-(ca - c0) // step) * step, cb - c0, step) - ca + c0])
        block = np.add.reduceat(np.add.reduceat(piece.astype(np.int64), rs, axis=0), cs, axis=1)
        oi, oj = (ra - r0) // step, (ca - c0) // step
        n_called[oi : oi + block.shape[0], oj : oj + block.shape[1]] += block
    # cells per block (the last row and column of blocks may be cut by the box)
    rows = np.minimum(step, h - np.arange(hh) * step)
    cols = np.minimum(step, w - np.arange(ww) * step)
    return n_called > 0 if step == 1 else n_called >= DYNAMIC_SHARE * np.outer(rows, cols)


def overlay_dynamic(rgb: np.ndarray, called: np.ndarray) -> np.ndarray:
    """A copy of RGB picture ``rgb`` with the cells of mask ``called`` in
    :data:`DYNAMIC_COLOUR`."""
    called = np.asarray(called, dtype=bool)
    if called.shape != rgb.shape[:2]:
        raise ValueError(f"dynamic mask of shape {called.shape} for a picture of {rgb.shape[:2]}")
    out = np.array(rgb, dtype=np.uint8, copy=True)
    out[called] = np.rint(np.asarray(DYNAMIC_COLOUR) * 255).astype(np.uint8)
    return out


def dynamic_label(threshold: float) -> str:
    """The legend's words for the cells called dynamic."""
    return f"dynamic (score > {threshold:g})"


def map_picture(
    m, r0: int, c0: int, h: int, w: int, step: int = 1, threshold: float | None = None
) -> np.ndarray:
    """Every ``step``-th cell of ``[r0, r0+h) x [c0, c0+w)`` as a map picture (:func:`map_rgb`),
    with the cells whose dynamic score exceeds ``threshold`` in :data:`DYNAMIC_COLOUR` when the
    map keeps a score (none drawn with ``threshold`` None)."""
    pic = map_rgb(sample_map(m, r0, c0, h, w, step)[0])
    if threshold is None or not getattr(m, "dynamic", False):
        return pic
    return overlay_dynamic(pic, called_dynamic(m, r0, c0, h, w, step, threshold))


def mosaic(pics: Sequence[np.ndarray], cols: int = 3) -> np.ndarray:
    """RGB pictures of one size tiled ``cols`` across (missing places black)."""
    if not pics:
        raise ValueError("no pictures to tile")
    h, w = pics[0].shape[:2]
    tiles = list(pics) + [np.zeros((h, w, 3), np.uint8)] * (-len(pics) % cols)
    return np.concatenate(
        [np.concatenate(tiles[i : i + cols], axis=1) for i in range(0, len(tiles), cols)], axis=0
    )


def label_panels(
    pics: Sequence[np.ndarray],
    labels: Sequence[str],
    caption: str = "",
    cols: int = 3,
    legend: Sequence[tuple[str, Sequence[float]]] = (),
) -> np.ndarray:
    """RGB pictures of one size tiled ``cols`` across (:func:`mosaic`), each with its label
    (a map's name) in its upper left corner, and ``caption`` (e.g. the time) in a strip above,
    followed by the ``legend``'s (label, RGB in [0, 1]) swatches."""
    from PIL import Image, ImageDraw, ImageFont

    if len(labels) != len(pics):
        raise ValueError(f"{len(pics)} pictures but {len(labels)} labels")
    try:
        font = ImageFont.load_default(size=11)
    except TypeError:  # Pillow without FreeType sizes
        font = ImageFont.load_default()
    out = []
    for pic, label in zip(pics, labels):
        im = Image.fromarray(np.asarray(pic, dtype=np.uint8))
        d = ImageDraw.Draw(im)
        x0, y0, x1, y1 = d.textbbox((3, 2), label, font=font)
        d.rectangle((0, 0, x1 + 3, y1 + 2), fill=(40, 40, 40))
        d.text((3, 2), label, fill=(255, 255, 255), font=font)
        out.append(np.asarray(im))
    grid = mosaic(out, cols)
    if not caption and not legend:
        return grid
    strip = Image.new("RGB", (grid.shape[1], 18), (40, 40, 40))
    d = ImageDraw.Draw(strip)
    d.text((4, 3), caption, fill=(255, 255, 255), font=font)
    x = d.textbbox((4, 3), caption, font=font)[2] + 16 if caption else 4
    for label, rgb in legend:
        d.rectangle((x, 4, x + 10, 14), fill=tuple(int(round(255 * v)) for v in rgb))
        d.text((x + 14, 3), label, fill=(255, 255, 255), font=font)
        x = d.textbbox((x + 14, 3), label, font=font)[2] + 16
    return np.concatenate([np.asarray(strip), grid], axis=0)


#: Longest side, in map cells read, of the whole-map figure (a figure has a few hundred
#: pixels a panel).
_FIGURE_CELLS = 1024


def write_scene_figures(
    maps: Mapping[str, object],
    out: Path,
    name: str,
    trajectory: Sequence[tuple[float, float, float]],
    last_isms: Mapping[str, np.ndarray] | None = None,
    keyframes: Sequence[Mapping] = (),
    gif_frames: Sequence[np.ndarray] = (),
    dynamic_threshold: float | None = None,
) -> dict[str, str]:
    """The maps side by side, the ISMs of the last update, convergence curves and the GIF;
    returns the files. With ``dynamic_threshold``, the cells of the maps that keep a dynamic
    score above it are drawn in :data:`DYNAMIC_COLOUR`."""
    files: dict[str, str] = {}
    ref = maps.get("ray_ilm") or next(iter(maps.values()))
    r0, c0, h, w = ref.covered_bounds()
    step = coarse_step(h, w, _FIGURE_CELLS)
    res = ref.grid.resolution
    panels = {n: sample_map(m, r0, c0, h, w, step)[0] for n, m in maps.items()}
    dynamic = {
        n: called_dynamic(m, r0, c0, h, w, step, dynamic_threshold)
        for n, m in maps.items()
        if dynamic_threshold is not None and getattr(m, "dynamic", False)
    }
    hh, ww = next(iter(panels.values())).shape[:2]
    # outer edges of the sampled cells (map cell R spans x in [-(R+1) res, -R res])
    extent = (-c0 * res, -(c0 + ww * step) * res, -(r0 + hh * step) * res, -r0 * res)
    track = np.array([(x, y) for x, y, _ in trajectory], dtype=np.float64).reshape(-1, 2)
    files["maps"] = str(
        plot_panels(
            panels,
            out / "maps.png",
            title=f"{name}: the maps (in the map frame, x up, y left)"
            + (f", one pixel per {step} x {step} cells" if step > 1 else ""),
            extent_m=extent,
            tracks={n: track for n in panels},
            dynamic=dynamic,
            dynamic_label=dynamic_label(dynamic_threshold) if dynamic else "",
        )
    )
    if last_isms:
        n = next(iter(last_isms.values())).shape[0]
        half = n / 2 * res
        files["isms"] = str(
            plot_panels(
                last_isms,
                out / "isms.png",
                gamma=0.4,
                extent_m=(half, -half, -half, half),
                title=f"{name}: ISMs of the last update (ego frame; masses^0.4, renormalised)",
            )
        )
    if keyframes and "iou" in keyframes[0]:
        curves = {n: [k["iou"].get(n, {}) for k in keyframes] for n in maps if n != "ray_ilm"}
        t0 = keyframes[0]["timestamp"]
        times = [(k["timestamp"] - t0) * 1e-6 for k in keyframes]
        files["convergence"] = str(
            plot_convergence(
                curves, out / "convergence.png", times, title=f"{name}: IoU against ray_ilm"
            )
        )
    if gif_frames:
        files["gif"] = str(write_gif(gif_frames, out / "maps.gif"))
    return files


def plot_m_u_min_sweep(
    rows: Sequence[Mapping],
    names: Sequence[str],
    path: str | os.PathLike,
    chosen: float | None = None,
) -> Path:
    """mIoU of the swept maps against m_u_min, per class and averaged, with the chosen value
    marked."""
    plt = _pyplot()

    xs = [r["m_u_min"] for r in rows]
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.4), dpi=110)
    for ax, cls in zip(axes, (*CLASSES, "mean")):
        for name in names:
            ys = [
                r["mean_of_classes"][name] if cls == "mean" else r["miou"][name][cls] for r in rows
            ]
            ax.plot(xs, ys, marker="o", label=name, color=map_colour(name))
        ax.set_title(
            f"{cls} mIoU vs ray_ilm" if cls != "mean" else "mean of the three classes", fontsize=9
        )
        ax.set_xlabel("m_u_min", fontsize=8)
        ax.grid(alpha=0.3)
        if chosen is not None:
            ax.axvline(chosen, color="k", ls="--", lw=0.8)
    _line_legend(fig, axes[0])
    return _save(fig, path)
