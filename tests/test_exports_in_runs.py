"""Exports recorded while mapping a scene (evgrid.runs.map_scene with OutputConfig.exports)."""

from __future__ import annotations

import json

import pytest

from evgrid.cli.options import MAP_OPTIONS, config_from_args
from evgrid.config import ConfigError, MapperConfig, OutputConfig, RunConfig
from evgrid.export.mcap import McapParams
from evgrid.export.nav2 import Nav2Params
from evgrid.export.rerun import RerunParams
from evgrid.runs import map_scene
from evgrid_sim import SimConfig, simulate_scene


def test_a_run_writes_the_exports_it_is_asked_for(tmp_path):
    pytest.importorskip("mcap_ros2")
    scene = simulate_scene(4, SimConfig(duration_s=1.0))
    outputs = OutputConfig(figures=False, exports=("nav2", "mcap"))
    res = map_scene(scene, tmp_path / "run", MapperConfig(maps=("ray_ilm", "ray_irm")), outputs)
    # the navigation map under map_saver's names: a run exporting for robots from a rig with a
    # lidar and a radar maps nav too (not the fused map, whose radar free space passes through
    # walls), and config.json says so
    nav2 = tmp_path / "run" / "nav2"
    assert sorted(p.name for p in nav2.iterdir()) == ["map.pgm", "map.yaml"]
    assert "the navigation map: 'nav'" in (nav2 / "map.yaml").read_text()
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["mapper"]["maps"] == ["ray_ilm", "ray_irm", "nav"]
    assert (tmp_path / "run" / f"{scene.name}.mcap").stat().st_size > 0
    assert set(res.files) >= {"export_nav2", "export_mcap", "metrics", "config"}


def test_exports_are_part_of_the_run_config():
    outputs = OutputConfig(
        exports=("mcap", "nav2"),
        mcap=McapParams(window_m=50.0, rate_hz=1.0, maps=("fused",)),
        nav2=Nav2Params(maps=("ray_ilm",)),
        rerun=RerunParams(step=4),
    )
    back = RunConfig.from_dict(RunConfig(outputs=outputs).to_dict())
    assert back.outputs == outputs
    assert OutputConfig().mcap == McapParams()  # the exporter's defaults: 40 m at keyframes
    assert OutputConfig().mcap.window_m == 40.0 and OutputConfig().mcap.compression == "zstd"
    with pytest.raises(ConfigError, match="unknown format"):
        RunConfig.from_dict({"outputs": {"exports": ["png"]}})
    with pytest.raises(ConfigError, match="window_m"):
        RunConfig.from_dict({"outputs": {"mcap": {"window_m": -1}}})
    with pytest.raises(ConfigError, match="outputs.mcap"):
        RunConfig.from_dict({"outputs": {"mcap": {"windo_m": 60}}})


def test_mcap_options_on_the_command_line_and_through_set():
    assert "export-window" not in MAP_OPTIONS
    run = config_from_args(
        RunConfig,
        ["--mcap-window", "60", "--mcap-rate", "1.5", "--mcap-maps", "fused,ray_ilm"],
        sets=["outputs.nav2.maps=fused", "outputs.rerun.step=3"],
    )
    assert run.outputs.mcap.window_m == 60.0 and run.outputs.mcap.rate_hz == 1.5
    assert run.outputs.mcap.maps == ("fused", "ray_ilm")
    assert run.outputs.nav2.maps == ("fused",) and run.outputs.rerun.step == 3
    run = config_from_args(
        RunConfig, ["--map-frame", "first_pose"], sets=["outputs.mcap.window_m=0"]
    )
    assert run.mapper.frame == "first_pose" and run.outputs.mcap.window_m == 0.0
    with pytest.raises(ConfigError, match="mcap-rate|rate_hz"):
        config_from_args(RunConfig, ["--mcap-rate", "-2"])
    run = config_from_args(RunConfig, ["--mcap-layers", "occupancy,dynamic"])
    assert run.outputs.mcap.layers == ("occupancy", "dynamic")
    assert RunConfig().outputs.mcap.layers == ("occupancy",)  # the dynamic layer on request


def _leftovers(folder):
    """Files of an export not closed: temporary ones or any under a final name."""
    return sorted(
        p.name
        for p in folder.rglob("*")
        if p.name.endswith((".part", ".mcap", ".rrd", ".pgm", ".yaml"))
    )


def test_a_run_with_all_exports_at_defaults(tmp_path):
    """nav2 under map_saver's names, an MCAP within its bounds, a .rrd; nothing temporary."""
    pytest.importorskip("mcap_ros2")
    pytest.importorskip("rerun")
    from mcap.reader import make_reader

    scene = simulate_scene(4, SimConfig(duration_s=2.0))
    outputs = OutputConfig(figures=False, exports=("nav2", "mcap", "rerun"))
    cfg = MapperConfig(maps=("ray_ilm", "ray_irm", "nav"))
    res = map_scene(scene, tmp_path / "run", cfg, outputs)
    out = tmp_path / "run"
    assert sorted(p.name for p in (out / "nav2").iterdir()) == ["map.pgm", "map.yaml"]
    assert "the navigation map: 'nav'" in (out / "nav2" / "map.yaml").read_text()
    mcap, rrd = out / f"{scene.name}.mcap", out / f"{scene.name}.rrd"
    assert res.files["export_mcap"] == str(mcap) and res.files["export_rerun"] == str(rrd)
    # at defaults: the nav map's 40 m window at keyframes (2 s: 5 keyframes) and the final
    # maps whole, zstd: the goal is 20 MB for 4 s; 2 s stays far below half of it
    assert 0 < mcap.stat().st_size < 5e6
    assert rrd.stat().st_size > 0
    with open(mcap, "rb") as fh:
        summary = make_reader(fh).get_summary()
    topics = {c.topic: c.id for c in summary.channels.values()}
    counts = summary.statistics.channel_message_counts
    keyframes = sum(f.is_keyframe for f in scene)
    # windows at keyframes and the whole map once at the end
    assert counts[topics["/evgrid/nav/occupancy"]] == keyframes + 1
    assert counts[topics["/evgrid/ray_ilm/occupancy"]] == 1  # final maps only
    assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
    assert not [n for n in _leftovers(out) if n.endswith(".part")]


class _Stop:
    """An observer that raises ``error`` at the ``at``-th update."""

    def __init__(self, error: BaseException, at: int = 3):
        self.error, self.at, self.n = error, at, 0

    def on_update(self, update) -> None:
        self.n += 1
        if self.n == self.at:
            raise self.error


@pytest.mark.parametrize("error", [KeyboardInterrupt(), RuntimeError("a failing observer")])
def test_ctrl_c_or_an_exception_leaves_no_export_file(tmp_path, error):
    pytest.importorskip("mcap_ros2")
    pytest.importorskip("rerun")
    scene = simulate_scene(4, SimConfig(duration_s=1.0))
    outputs = OutputConfig(figures=False, exports=("nav2", "mcap", "rerun"))
    out = tmp_path / "run"
    (out / "nav2").mkdir(parents=True)
    (out / f".{scene.name}.mcap.killed.part").write_bytes(b"left by a killed run")
    with pytest.raises(type(error)):
        cfg = MapperConfig(maps=("ray_ilm",))
        map_scene(scene, out, cfg, outputs, observers=(_Stop(error),), overwrite=True)
    # aborted at once (not when garbage collected): no temporary file, no file under a final
    # name, and the temporary file of a killed run is gone too
    assert _leftovers(out) == []


def test_a_run_without_a_results_folder_maps_and_refuses_exports():
    scene = simulate_scene(4, SimConfig(duration_s=0.5))
    res = map_scene(scene, None, MapperConfig(maps=("ray_ilm",)), OutputConfig(figures=False))
    assert res.metrics["updates"] > 0 and res.files == {}
    with pytest.raises(ValueError, match="exports need a results folder"):
        map_scene(scene, None, MapperConfig(maps=("ray_ilm",)), OutputConfig(exports=("nav2",)))


def test_a_run_exporting_nothing_for_robots_maps_what_was_asked(tmp_path):
    scene = simulate_scene(4, SimConfig(duration_s=1.0))
    cfg = MapperConfig(maps=("ray_ilm", "ray_irm"))
    map_scene(scene, tmp_path / "run", cfg, OutputConfig(figures=False, exports=("rerun",)))
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["mapper"]["maps"] == ["ray_ilm", "ray_irm"]
