"""Exports recorded while mapping a scene (evgrid.runs.map_scene with OutputConfig.exports)."""

from __future__ import annotations

import pytest

from evgrid.config import ConfigError, MapperConfig, OutputConfig, RunConfig
from evgrid.data import SimConfig, simulate_scene
from evgrid.runs import map_scene


def test_a_run_writes_the_exports_it_is_asked_for(tmp_path):
    pytest.importorskip("mcap_ros2")
    scene = simulate_scene(4, SimConfig(duration_s=1.0))
    outputs = OutputConfig(figures=False, exports=("nav2", "mcap"))
    res = map_scene(scene, tmp_path / "run", MapperConfig(maps=("ray_ilm", "ray_irm")), outputs)
    # the navigation map under map_saver's names (ray_ilm: the run has neither nav nor fused)
    nav2 = tmp_path / "run" / "nav2"
    assert sorted(p.name for p in nav2.iterdir()) == ["map.pgm", "map.yaml"]
    assert "the navigation map: 'ray_ilm'" in (nav2 / "map.yaml").read_text()
    assert (tmp_path / "run" / f"{scene.name}.mcap").stat().st_size > 0
    assert set(res.files) >= {"export_nav2", "export_mcap", "metrics", "config"}


def test_exports_are_part_of_the_run_config():
    back = RunConfig.from_dict(
        RunConfig(outputs=OutputConfig(exports=("mcap",), export_window_m=50.0)).to_dict()
    )
    assert back.outputs.exports == ("mcap",) and back.outputs.export_window_m == 50.0
    with pytest.raises(ConfigError, match="unknown format"):
        RunConfig.from_dict({"outputs": {"exports": ["png"]}})
