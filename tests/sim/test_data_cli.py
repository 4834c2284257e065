"""`evgrid simulate`, both output formats (small scenes)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from evgrid.cli import app
from evgrid_sim import SimConfig, WorldConfig, simulate_scene
from evgrid_sim.store import load_sim_scene

runner = CliRunner()


def test_simulate_npz(tmp_path):
    out = tmp_path / "sim"
    res = runner.invoke(
        app, ["simulate", "--out", str(out), "--scenes", "2", "--seed", "3", "--duration", "0.6"]
    )
    assert res.exit_code == 0, res.output
    index = json.loads((out / "index.json").read_text())
    assert [(s["name"], s["split"]) for s in index["scenes"]] == [
        ("sim-000003", "train"),
        ("sim-000004", "val"),
    ]
    back = load_sim_scene(out / "sim-000004.npz")
    direct = simulate_scene(4, SimConfig(duration_s=0.6, world=WorldConfig(environment="mixed")))
    assert len(back) == len(direct) == 12
    for i in (0, 11):
        np.testing.assert_array_equal(back.frame(i).lidar.points, direct.frame(i).lidar.points)
    np.testing.assert_array_equal(back.frame(10).occupancy, direct.frame(10).occupancy)
    # A second run does not clobber files unless told to.
    res = runner.invoke(
        app, ["simulate", "--out", str(out), "--scenes", "1", "--seed", "3", "--duration", "0.6"]
    )
    assert res.exit_code != 0 and "--overwrite" in res.output
    # Another seed into the same folder joins the index.
    res = runner.invoke(app, ["simulate", "--out", str(out), "--seed", "9", "--duration", "0.2"])
    assert res.exit_code == 0, res.output
    index = json.loads((out / "index.json").read_text())
    assert [(s["name"], s["split"]) for s in index["scenes"]] == [
        ("sim-000003", "train"),
        ("sim-000004", "val"),
        ("sim-000009", "val"),
    ]


def test_simulate_nuscenes(tmp_path):
    pytest.importorskip("nuscenes")
    from evgrid.data.nuscenes import load_nuscenes

    out = tmp_path / "nusc"
    args = [
        "simulate",
        "--out",
        str(out),
        "--scenes",
        "2",
        "--seed",
        "8",
        "--duration",
        "0.6",
        "--format",
        "nuscenes",
    ]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert json.loads((out / "v1.0-sim" / "splits.json").read_text()) == {
        "train": ["sim-000008"],
        "val": ["sim-000009"],
    }
    val = load_nuscenes(out, "v1.0-sim", split="val", min_travel_m=0.0)
    assert [s.name for s in val] == ["sim-000009"] and len(val[0]) == 12
    assert runner.invoke(app, args).exit_code != 0  # exists
    assert runner.invoke(app, args + ["--overwrite"]).exit_code == 0


@pytest.mark.parametrize(
    "extra,word",
    [
        (["--format", "las"], "--format"),
        (["--environment", "moon"], "--environment"),
        (["--duration", "-2"], "duration"),
    ],
)
def test_simulate_rejects_bad_options(tmp_path, extra, word):
    res = runner.invoke(app, ["simulate", "--out", str(tmp_path), *extra])
    assert res.exit_code != 0 and word in res.output


def test_simulate_writes_a_highway_and_names_a_bad_layout(tmp_path):
    res = CliRunner().invoke(
        app, ["simulate", "--out", str(tmp_path / "hw"), "--layout", "highway", "--duration", "1"]
    )
    assert res.exit_code == 0, res.output
    index = json.loads((tmp_path / "hw" / "index.json").read_text())
    assert [s["environment"] for s in index["scenes"]] == ["highway"]
    res = CliRunner().invoke(app, ["simulate", "--out", str(tmp_path / "x"), "--layout", "ring"])
    assert res.exit_code == 1 and "--layout must be one of" in res.output
