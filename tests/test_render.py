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
