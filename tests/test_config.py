"""One config: the generic serialiser, resolution from a file plus overrides, files that reload."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from evgrid.cli import app
from evgrid.cli.options import config_from_args
from evgrid.config import (
    ConfigError,
    MapperConfig,
    OutputConfig,
    RunConfig,
    SweepConfig,
    document,
    from_dict,
    load_config,
    resolve_config,
    to_dict,
)
from evgrid.geometry import GridSpec
from evgrid.preprocess import BodyBox, RadarFilter
from evgrid_sim import SimConfig
from evgrid_sim.radar_variants import TRAINING_RANGES, RadarRanges

runner = CliRunner()


@pytest.mark.parametrize(
    "obj",
    [
        RunConfig(MapperConfig(maps=("ray_ilm",)), OutputConfig(exports=("nav2",))),
        SweepConfig(values=(0.2, 0.4)),
        MapperConfig(),
        GridSpec(256, 20.0),
        RadarFilter("nuscenes"),
        TRAINING_RANGES,
        SimConfig(duration_s=3.0),
        BodyBox(-1, -1, 0, 2, 1, 2),
    ],
    ids=lambda o: type(o).__name__,
)
def test_one_serialiser_round_trips_every_parameter_dataclass(obj):
    d = json.loads(json.dumps(to_dict(obj), allow_nan=False))
    assert from_dict(type(obj), d) == obj


def test_the_serialiser_agrees_with_the_hand_written_forms():
    for obj in (GridSpec(), RadarFilter("nuscenes"), TRAINING_RANGES, SimConfig()):
        assert to_dict(obj) == json.loads(json.dumps(obj.to_dict())), type(obj).__name__
    assert RadarRanges.from_dict(to_dict(TRAINING_RANGES)) == TRAINING_RANGES


def test_a_missing_section_or_unknown_key_is_an_error_naming_it(tmp_path):
    path = tmp_path / "config.json"
    d = RunConfig().to_dict()
    del d["mapper"]
    path.write_text(json.dumps(d))
    with pytest.raises(ConfigError, match=r"missing section\(s\) \['mapper'\]"):
        load_config(path)
    d = RunConfig().to_dict()
    d["outputs"]["gif_stepp"] = 3
    path.write_text(json.dumps(d))
    with pytest.raises(ConfigError, match="outputs.*gif_stepp"):
        load_config(path)
    with pytest.raises(ConfigError, match="not an evgrid config"):
        path.write_text('{"format": "octomap"}')
        load_config(path, None)


def test_relative_paths_resolve_against_the_configs_folder(tmp_path):
    d = RunConfig(source={"kind": "sim_files", "folder": "sims", "split": None}).to_dict()
    d["mapper"]["checkpoint"] = "ck/evnet.safetensors"
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.json").write_text(json.dumps(d))
    run = load_config(tmp_path / "run" / "config.json")
    assert run.source["folder"] == str(tmp_path / "run" / "sims")
    assert run.mapper.checkpoint == str(tmp_path / "run" / "ck" / "evnet.safetensors")


def test_overrides_are_parsed_by_the_fields_type():
    run = resolve_config(
        RunConfig,
        overrides=[
            ("mapper.fusion.m_u_min", "0.4"),
            ("mapper.maps", "ray_ilm,fused"),
            ("outputs.figures", "false"),
            ("mapper.checkpoint", "none"),
            ("mapper.self_returns.body", "-1,-1,0,4,1,2"),
            ("mapper.radar_filter", '{"mode": "nuscenes"}'),
        ],
    )
    assert run.mapper.fusion.m_u_min == 0.4 and run.mapper.maps == ("ray_ilm", "fused")
    assert run.outputs.figures is False and run.mapper.checkpoint is None
    assert run.mapper.self_returns.body == BodyBox(-1, -1, 0, 4, 1, 2)
    assert run.mapper.radar_filter == RadarFilter("nuscenes")
    with pytest.raises(ConfigError, match="m_u_min"):
        resolve_config(RunConfig, overrides=[("mapper.fusion.m_u_min", "lots")])
    # the command line's short options are overrides too; given beside a file, they win
    run = config_from_args(RunConfig, ["--m-u-min", "0.45", "--no-figures", "--scenes", "2"])
    assert run.mapper.fusion.m_u_min == 0.45 and not run.outputs.figures
    assert run.source["kind"] == "sim" and len(run.source["seeds"]) == 2


def test_config_show_prints_a_config_that_reloads(tmp_path):
    r = runner.invoke(app, ["config", "show", "--defaults"])
    assert r.exit_code == 0, r.output
    (tmp_path / "c.json").write_text(r.output)
    assert load_config(tmp_path / "c.json") == config_from_args(RunConfig, [])
    r = runner.invoke(
        app, ["config", "show", "--config", str(tmp_path / "c.json"), "--threads", "1"]
    )
    assert r.exit_code == 0 and json.loads(r.output)["mapper"]["threads"] == 1
    r = runner.invoke(app, ["config", "show", "--defaults", "--threads", "1"])
    assert r.exit_code != 0


def test_config_show_reads_every_kind_of_config_file(tmp_path):
    # simulate and bench write config files of their own kinds; a fresh process (nothing
    # imported yet that registers them) shows them as they are
    import subprocess
    import sys

    from evgrid.config import document
    from evgrid_lab.options import BenchOptions, SimulateConfig, SimulateOptions

    files = {
        "sim.json": document(SimulateConfig(SimulateOptions(seed=7))),
        "bench.json": document(BenchOptions(duration=0.5)),
    }
    for name, d in files.items():
        (tmp_path / name).write_text(json.dumps(d))
        code = (
            "import json, sys, evgrid.cli.groups; from evgrid.config import load_config, document; "
            "print(json.dumps(document(load_config(sys.argv[1], None))))"
        )
        out = subprocess.run(
            [sys.executable, "-c", code, str(tmp_path / name)], capture_output=True, text=True
        )
        assert out.returncode == 0, out.stderr
        assert json.loads(out.stdout) == d


def test_a_training_run_writes_a_config_that_trains_again(tmp_path):
    pytest.importorskip("torch")
    from evgrid.cli.options import train_config_from_args
    from evgrid.train_run import TrainRunConfig

    args = [
        "--scenes", "1", "--val-scenes", "1", "--duration", "0.6", "--epochs", "1",
        "--width", "4", "--depth", "2", "--workers", "0", "--frame-stride", "3",
    ]  # fmt: skip
    run = train_config_from_args(args)
    assert run.train.epochs == 1 and run.train.model.width == 4 and run.source["kind"] == "sim"
    first, again = tmp_path / "first", tmp_path / "again"
    r = runner.invoke(app, ["train", *args, "--out", str(first)])
    assert r.exit_code == 0, r.output
    back = load_config(first / "config.json", None)
    assert isinstance(back, TrainRunConfig) and back == run
    r = runner.invoke(app, ["train", "--config", str(first / "config.json"), "--out", str(again)])
    assert r.exit_code == 0, r.output
    assert json.loads((again / "config.json").read_text()) == document(run)
    assert (again / "best.safetensors").is_file()
