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
