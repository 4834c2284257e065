"""Pictures: colours, figures and GIFs are real files of the right size (evgrid.render)."""

from __future__ import annotations

import numpy as np
from PIL import Image

from evgrid import mass
from evgrid.render import masses_to_rgb, plot_convergence, plot_panels, trajectory_cells, write_gif


def test_masses_to_rgb_uses_the_papers_colours():
    rgb = masses_to_rgb(np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.25, 0.25]], np.float32))
    assert rgb.tolist() == [[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 64, 64]]


def test_figures_and_gif_are_written(tmp_path):
    m = mass.vacuous((40, 40))
    m[10:20, 5:30] = [0.8, 0.0, 0.2]
    p = plot_panels(
        {"a": m, "b": m, "c": m, "d": m},
        tmp_path / "fig.png",
        title="t",
        tracks={"a": np.array([[1, 1], [20, 20]])},
    )
    with Image.open(p) as im:
        assert im.size[0] > 300 and im.size[1] > 200
    c = plot_convergence(
        {"fused": [{"free": 0.2, "occupied": 0.1, "unknown": 0.5}] * 3}, tmp_path / "conv.png"
    )
    assert c.stat().st_size > 1000
    g = write_gif([masses_to_rgb(m), masses_to_rgb(mass.vacuous((40, 40)))], tmp_path / "a.gif")
    with Image.open(g) as im:
        assert im.n_frames == 2 and im.size == (40, 40)


def test_trajectory_cells_matches_map_convention():
    # map cell (R, C) = (-10, -20) has its centre at x = 9.5 res, y = 19.5 res
    res = 0.1
    xy = np.array([[9.5 * res, 19.5 * res]])
    col_row = trajectory_cells(xy, res, r0=-12, c0=-25)
    assert np.allclose(col_row, [[5.0, 2.0]])


def test_map_palette_reads_as_a_map():
    from evgrid.render import MAP_PALETTE, map_rgb

    rgb = map_rgb(
        np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.3, 0, 0.7], [0, 0.3, 0.7]], np.float32)
    )
    assert (rgb[..., 0] == rgb[..., 1]).all() and (rgb[..., 1] == rgb[..., 2]).all()  # greys
    free, occ, unk, weak_free, weak_occ = rgb[:, 0].tolist()
    assert (free, occ, unk) == (255, 0, round(255 * MAP_PALETTE["unknown"][0]))
    assert free > weak_free > unk > weak_occ > occ  # confidence by shade


def test_one_colour_per_map_in_every_plot(tmp_path):
    from evgrid.render import map_colour, plot_perception_field

    names = ["fused", "deep_disc", "nav", "radar-less prior", "ray_irm"]
    assert len({map_colour(n) for n in names}) == len(names)
    ci = {"mean": 0.5, "lo": 0.4, "hi": 0.6}
    conv = {
        "t_s": [1.0, 2.0],
        "maps": {n: {k: [ci, ci] for k in ("free", "occupied", "area_m2")} for n in names[::-1]},
    }
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {}
    real_close = plt.close

    def keep(fig=None):
        if fig is not None and hasattr(fig, "axes"):
            for ax in fig.axes:
                for line in ax.get_lines():
                    if not line.get_label().startswith("_"):
                        colours.setdefault(line.get_label(), set()).add(line.get_color())
        real_close(fig)

    plt.close = keep
    try:
        plot_convergence({n: [{"free": 0.2}] * 3 for n in names}, tmp_path / "c.png")
        plot_perception_field(conv, tmp_path / "p.png")
    finally:
        plt.close = real_close
    for n in names:
        assert colours[n] == {matplotlib.colors.to_hex(map_colour(n))} or colours[n] == {
            map_colour(n)
        }


def test_maps_figure_has_metres_scale_bar_and_path_legend(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = mass.vacuous((40, 40))
    m[10:20, 5:30] = [0.8, 0.0, 0.2]
    seen = {}
    real_close = plt.close

    def keep(fig=None):
        ax = fig.axes[0]
        seen["xlabel"], seen["ylabel"] = ax.get_xlabel(), ax.get_ylabel()
        seen["xlim"], seen["ylim"] = ax.get_xlim(), ax.get_ylim()
        seen["legend"] = [t.get_text() for t in fig.legends[0].get_texts()]
        seen["texts"] = [
            c.get_child().get_children()[0].get_text()
            for c in ax.artists
            if hasattr(c, "get_child")
        ]
        real_close(fig)

    plt.close = keep
    try:
        plot_panels(
            {"fused": m},
            tmp_path / "f.png",
            extent_m=(2.0, -2.0, -2.0, 2.0),
            tracks={"fused": np.array([[0.0, 0.0], [1.0, 0.5]])},
        )
    finally:
        plt.close = real_close
    assert "[m]" in seen["xlabel"] and "[m]" in seen["ylabel"]
    assert seen["xlim"] == (2.0, -2.0) and seen["ylim"] == (-2.0, 2.0)  # y grows to the left
    assert {"free", "occupied", "unknown", "path"} <= set(seen["legend"])
    assert seen["texts"] == ["0.5 m"]  # a round bar, about a fifth of 4 m


def test_gif_frames_are_labelled():
    from evgrid.render import label_panels

    pics = [np.full((60, 80, 3), 205, np.uint8)] * 2
    out = label_panels(pics, ["ray_ilm", "fused"], "t = 1.5 s", cols=2)
    assert out.shape == (60 + 18, 160, 3)
    assert (out[:18] != 205).any() and (out[18:32, :40] != 205).any()  # caption, name boxes
    assert (out[50:, 60:80] == 205).all()  # the picture itself is left as it was


def _dynamic_map(enabled: bool):
    """A 16 x 16 map (one tile) free everywhere, with a score of 0.5 in rows 4..7, columns
    2..5 and in the lone cell (12, 12) (when it keeps one)."""
    from evgrid.geometry import GridSpec
    from evgrid.grid import EvidentialMap

    m = EvidentialMap(GridSpec(16, 0.1), tile_cells=16, dynamic=enabled)
    t, cov = m.tile((0, 0))
    t[:] = [0.9, 0.0, 0.1]
    cov[:] = True
    if enabled:
        m.dynamic_tiles[(0, 0)][4:8, 2:6] = 0.5
        m.dynamic_tiles[(0, 0)][12, 12] = 0.5
        m.dynamic_tiles[(0, 0)][14, 2] = 0.05  # below the threshold: not called dynamic
    return m


def test_dynamic_cells_are_drawn_over_the_map_only_where_scored():
    from evgrid.render import DYNAMIC_COLOUR, map_picture, map_rgb, sample_map

    blue = np.rint(np.asarray(DYNAMIC_COLOUR) * 255).astype(np.uint8)
    m = _dynamic_map(True)
    pic = map_picture(m, 0, 0, 16, 16, 1, threshold=0.1)
    called = (pic == blue).all(-1)
    want = np.zeros((16, 16), bool)
    want[4:8, 2:6] = want[12, 12] = True
    np.testing.assert_array_equal(called, want)
    np.testing.assert_array_equal(pic[~want], map_rgb(sample_map(m, 0, 0, 16, 16)[0])[~want])
    # a coarse picture (4 x 4 cells a pixel) shows the blocks half called dynamic, not the one
    # with a lone cell (a mover shows; a single cell's conflict does not grow to a pixel)
    coarse = (map_picture(m, 0, 0, 16, 16, 4, threshold=0.1) == blue).all(-1)
    want = np.zeros((4, 4), bool)
    want[1, :2] = True
    np.testing.assert_array_equal(coarse, want)
    # no overlay: the score off, or no threshold asked for
    for pic in (
        map_picture(_dynamic_map(False), 0, 0, 16, 16, 1, 0.1),
        map_picture(m, 0, 0, 16, 16),
    ):
        assert not (pic == blue).all(-1).any()


def test_maps_figure_shows_the_dynamic_cells_with_a_legend_entry(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from evgrid.render import DYNAMIC_COLOUR, write_scene_figures

    blue = np.rint(np.asarray(DYNAMIC_COLOUR) * 255).astype(np.uint8)
    seen = []
    real_close = plt.close

    def keep(fig=None):
        seen.append(
            {
                "legend": [t.get_text() for t in fig.legends[0].get_texts()],
                "images": [ax.images[0].get_array() for ax in fig.axes if ax.images],
            }
        )
        real_close(fig)

    plt.close = keep
    try:
        for enabled in (True, False):
            maps = {"ray_ilm": _dynamic_map(enabled), "fused": _dynamic_map(enabled)}
            trajectory = [(0.0, 0.0, 0.0), (-0.5, -0.5, 0.0)]
            write_scene_figures(maps, tmp_path, "s", trajectory, dynamic_threshold=0.1)
    finally:
        plt.close = real_close
    on, off = seen
    assert "dynamic (score > 0.1)" in on["legend"]
    for img in on["images"]:
        assert (np.asarray(img) == blue).all(-1).sum() == 17
    assert not any("dynamic" in t for t in off["legend"])
    for img in off["images"]:
        assert not (np.asarray(img) == blue).all(-1).any()


def test_gif_frames_show_the_dynamic_cells_and_their_legend():
    from types import SimpleNamespace

    from evgrid.fusion import DynamicParams
    from evgrid.geometry import SE2
    from evgrid.observers import GifRecorder
    from evgrid.render import DYNAMIC_COLOUR

    blue = np.rint(np.asarray(DYNAMIC_COLOUR) * 255).astype(np.uint8)
    for enabled in (True, False):
        m = _dynamic_map(enabled)
        maps = SimpleNamespace(
            maps={"fused": m},
            dynamic=DynamicParams(enabled=enabled),
            dynamic_maps=("fused",) if enabled else (),
        )
        gif = GifRecorder(m.grid, window_m=4.8, step=1, cols=1)
        # around map cell (8, 8) (x = y = -0.85 m): the map's tile is the window's lower right,
        # clear of the name's box
        pose = SE2(-0.85, -0.85, 0.0)
        gif.on_update(
            SimpleNamespace(
                frame=SimpleNamespace(is_keyframe=True, timestamp=0), pose=pose, maps=maps
            )
        )
        (frame,) = gif.frames
        strip, pic = frame[:18], frame[18:]
        assert (pic == blue).all(-1).sum() == (17 if enabled else 0)
        assert (strip == blue).all(-1).any() == enabled  # the legend's swatch
