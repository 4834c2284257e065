"""The command line: map, evaluate, bench (small runs with a tiny checkpoint)."""

from __future__ import annotations

import json

import pytest
import torch
from typer.testing import CliRunner

from evgrid.cli import app
from evgrid.fusion import MAP_NAMES
from evgrid.geometry import GridSpec
from evgrid.ism.deep import CHANNELS
from evgrid.ism.evnet import EvNet, EvNetConfig, save_checkpoint

runner = CliRunner()


def evgrid(*words: object, **options: object):
    """``evgrid WORDS --OPTION VALUE ...``: each keyword is an option, in the order given
    (underscores become dashes; ``True`` is a bare flag)."""
    args = [str(w) for w in words]
    for name, value in options.items():
        args.append("--" + name.replace("_", "-"))
        if value is not True:
            args.append(str(value))
    return runner.invoke(app, args)


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    net = EvNet(EvNetConfig(in_channels=len(CHANNELS), width=4, depth=2))
    return save_checkpoint(
        net,
        tmp_path_factory.mktemp("ck") / "tiny.safetensors",
        extra={"grid": GridSpec().to_dict()},
    )


def test_map_writes_per_scene_results_and_table(tmp_path, tiny_checkpoint):
    r = evgrid(
        "map", scenes=1, duration=2, checkpoint=tiny_checkpoint, out=tmp_path, save_maps=True
    )
    assert r.exit_code == 0, r.output
    assert "frames/s" in r.output and "| `fused` |" in r.output
    scene_dir = tmp_path / "sim-000004"  # the first validation seed
    for name in ("metrics.json", "maps.png", "isms.png", "maps.gif", "maps/fused.npz"):
        assert (scene_dir / name).is_file(), name
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert set(summary["maps"]) == set(MAP_NAMES)  # the six maps of Table I
    assert summary["scenes"] == ["sim-000004"] and summary["frames_per_second"] > 0
    assert (tmp_path / "convergence_truth.png").is_file()
    assert summary["convergence_truth"]["t_s"] == [1.0, 2.0, 5.0, 10.0]
    assert summary["convergence_truth"]["maps"]["fused"]["area_m2"][0]["mean"] > 0


def test_evaluate_over_two_scenes_in_two_processes(tmp_path, tiny_checkpoint):
    r = evgrid(
        "evaluate",
        scenes=2,
        duration=1.5,
        workers=2,
        checkpoint=tiny_checkpoint,
        out=tmp_path,
        m_u_min=0.4,
        lidar_min_range=1.5,
    )
    assert r.exit_code == 0, r.output
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["scenes"] == ["sim-000004", "sim-000009"]
    assert "vs_truth" in summary and not (tmp_path / "sim-000004" / "maps.png").exists()
    config = json.loads((tmp_path / "sim-000009" / "config.json").read_text())["mapper"]
    assert config["fusion"]["m_u_min"] == 0.4 and config["lidar"]["min_range_m"] == 1.5
    assert config["radar"]["n_sweeps"] == 10  # the ISM parameters used are written down
    table = (tmp_path / "table.md").read_text()
    assert (
        "against the true occupancy" in table and "convergence against the true occupancy" in table
    )
    assert summary["maps_interval"]["fused"]["free"]["n"] == 2
    assert (
        summary["maps_interval"]["fused"]["free"]["lo"]
        <= summary["maps"]["fused"]["free"]
        <= summary["maps_interval"]["fused"]["free"]["hi"]
    )


def test_bad_options_are_rejected(tmp_path):
    r = runner.invoke(app, ["map", "--maps", "ray_ilm,octomap", "--out", str(tmp_path)])
    assert r.exit_code != 0 and "unknown map" in r.output
    r = runner.invoke(app, ["map", "--nuscenes", str(tmp_path), "--sim-dir", str(tmp_path)])
    assert r.exit_code != 0


def test_bench_prints_json(tmp_path, tiny_checkpoint):
    out = tmp_path / "bench.json"
    r = evgrid("bench", duration=1, checkpoint=tiny_checkpoint, out=out)
    assert r.exit_code == 0, r.output
    res = json.loads(out.read_text())
    fused = res["per_frame"]["fused_only"]["components_ms"]
    assert {"ray_irm", "deep_irm", "warp", "fuse", "step_total"} <= set(fused)
    assert "ray_ilm" not in fused  # the fused map needs no lidar
    assert res["kernels_ms"]["dempster_512"] > 0
    # the options beside the result reload: the same bench again, an option given wins
    from evgrid_lab.options import BenchOptions, bench_options

    cfg = tmp_path / "bench.config.json"
    same = BenchOptions(duration=1.0, checkpoint=str(tiny_checkpoint))
    assert json.loads(cfg.read_text())["format"] == "evgrid-bench"
    assert bench_options({}, cfg) == same
    assert bench_options({"repeats": 1}, cfg).repeats == 1
    cfg.write_text(cfg.read_text().replace('"repeats"', '"repeat"'))
    r = evgrid("bench", config=cfg)
    assert r.exit_code != 0 and "bench.config.json" in r.output and "repeat" in r.output, r.output


def test_simulate_writes_a_config_that_reloads(tmp_path):
    from evgrid_lab.options import SimulateOptions, simulate_options

    data = tmp_path / "data"
    r = evgrid("simulate", out=data, scenes=1, seed=3, duration=0.5, lidar_rate=10)
    assert r.exit_code == 0, r.output
    opts = SimulateOptions(scenes=1, seed=3, duration=0.5, lidar_rate=10.0)
    assert simulate_options({}, data / "config.json") == opts
    # simulate again from it: another seed, the rest as before
    r = evgrid("simulate", out=tmp_path / "again", config=data / "config.json", seed=8)
    assert r.exit_code == 0, r.output
    again = simulate_options({}, tmp_path / "again" / "config.json")
    assert again == SimulateOptions(scenes=1, seed=8, duration=0.5, lidar_rate=10.0)
    index = json.loads((tmp_path / "again" / "index.json").read_text())["scenes"]
    assert [e["seed"] for e in index] == [8] and index[0]["frames"] == 5
    bad = tmp_path / "bad.json"
    bad.write_text((data / "config.json").read_text().replace('"seed"', '"sed"'))
    r = evgrid("simulate", out=tmp_path / "x", config=bad)
    assert r.exit_code != 0 and "bad.json" in r.output and "sed" in r.output, r.output


def test_sweep_m_u_min(tmp_path, tiny_checkpoint):
    r = evgrid(
        "sweep-m-u-min",
        scenes=1,
        duration=1.5,
        values="0.2,0.6",
        workers=1,
        checkpoint=tiny_checkpoint,
        out=tmp_path,
    )
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "m_u_min_sweep.json").read_text())
    assert [row["m_u_min"] for row in res["rows"]] == [0.2, 0.6]
    assert set(res["rows"][0]["miou"]) == {"deep_replace", "deep_disc", "fused"}
    assert res["chosen"] in (0.2, 0.6) and "highest m_u_min" in res["rule"]
    assert (tmp_path / "m_u_min_sweep.png").stat().st_size > 1000
    # its config.json reloads: the same sweep again with --config
    from evgrid.config import SweepConfig, load_config

    sweep = load_config(tmp_path / "config.json", None)
    assert isinstance(sweep, SweepConfig) and sweep.values == (0.2, 0.6)
    assert sweep.scenes == ("sim-000004",) and sweep.mapper.checkpoint == str(tiny_checkpoint)
    again = tmp_path / "again"
    r = evgrid("sweep-m-u-min", config=tmp_path / "config.json", out=again, workers=1)
    assert r.exit_code == 0, r.output
    assert json.loads((again / "m_u_min_sweep.json").read_text())["rows"] == res["rows"]


def test_map_on_a_dataset_in_the_nuscenes_layout(tmp_path, tiny_checkpoint):
    """`evgrid map --nuscenes`: the devkit reads a simulated dataset written in the nuScenes
    layout."""
    data = tmp_path / "nuscenes"
    r = evgrid("simulate", out=data, scenes=1, seed=4, duration=1.5, format="nuscenes")
    assert r.exit_code == 0, r.output
    out = tmp_path / "out"
    r = evgrid(
        "map",
        nuscenes=data,
        version="v1.0-sim",
        split="val",
        checkpoint=tiny_checkpoint,
        out=out,
    )
    assert r.exit_code == 0, r.output
    m = json.loads((out / "sim-000004" / "metrics.json").read_text())
    assert m["frames"] == 30 and "vs_truth" not in m  # nuScenes has no true occupancy
    assert set(m["vs_ray_ilm"]) == {"deep_acc", "deep_replace", "deep_disc", "ray_irm", "fused"}


def test_demo_writes_the_metrics_contract(tmp_path):
    """DIR/metrics.json = {"maps": {<six names>: {"free", "occupied", "unknown"}}, ...} with the
    shipped Ev-Net."""
    r = evgrid("demo", scenes=1, duration=2, workers=1, out=tmp_path)
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert set(m["maps"]) == set(MAP_NAMES)  # the six maps of Table I
    for ious in m["maps"].values():
        assert set(ious) == {"free", "occupied", "unknown"}
        assert all(v is None or 0.0 <= v <= 1.0 for v in ious.values())
    assert (tmp_path / "table.md").is_file()
    for name in ("maps.png", "isms.png", "convergence.png", "maps.gif"):
        assert (tmp_path / "sim-000004" / name).is_file()


def test_a_run_reproduces_from_its_own_config(tmp_path, tiny_checkpoint):
    first, again = tmp_path / "first", tmp_path / "again"
    r = evgrid(
        "evaluate",
        scenes=1,
        duration=1.5,
        workers=1,
        seed=3,
        checkpoint=tiny_checkpoint,
        m_u_min=0.35,
        update_rate=5,
        out=first,
    )
    assert r.exit_code == 0, r.output
    r = evgrid("evaluate", config=first / "config.json", workers=1, out=again)
    assert r.exit_code == 0, r.output
    a, b = (json.loads((d / "summary.json").read_text()) for d in (first, again))
    assert a["scenes"] == b["scenes"] == ["sim-000004"]
    assert a["maps"] == b["maps"] and a["vs_truth"] == b["vs_truth"]
    ca, cb = (json.loads((d / "config.json").read_text()) for d in (first, again))
    assert ca["mapper"] == cb["mapper"] and ca["mapper"]["update_rate_hz"] == 5.0
    assert (
        ca["source"]
        == cb["source"]
        == {"kind": "sim", "seeds": [4], "duration_s": 1.5, "radar": None, "radar_ranges": None}
    )
    # an option given beside --config wins over the file
    r = evgrid(
        "evaluate", config=first / "config.json", m_u_min=0.5, workers=1, out=tmp_path / "changed"
    )
    assert r.exit_code == 0, r.output
    assert (
        json.loads((tmp_path / "changed" / "config.json").read_text())["mapper"]["fusion"][
            "m_u_min"
        ]
        == 0.5
    )


def test_results_are_never_silently_overwritten(tmp_path, tiny_checkpoint):
    args = dict(scenes=1, duration=1, workers=1, checkpoint=tiny_checkpoint, out=tmp_path)
    r = evgrid("evaluate", **args)
    assert r.exit_code == 0, r.output
    before = (tmp_path / "summary.json").read_text()
    r = evgrid("evaluate", **args)
    assert r.exit_code == 1 and "already holds results" in r.output and "--overwrite" in r.output
    assert (tmp_path / "summary.json").read_text() == before
    assert evgrid("evaluate", **args, overwrite=True).exit_code == 0


def test_failures_print_one_line_and_leave_no_empty_folder(tmp_path):
    out = tmp_path / "never"
    r = runner.invoke(app, ["map", "--sim-dir", str(tmp_path / "missing"), "--out", str(out)])
    assert r.exit_code == 1
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("evgrid: error:") and "index.json" in lines[0], (
        r.output
    )
    assert not out.exists()
    bad = tmp_path / "bad.json"
    bad.write_text('{"mapper": {"fusion": {"m_u_min": 2.0}}}')
    r = runner.invoke(app, ["map", "--config", str(bad), "--out", str(out)])
    assert (
        r.exit_code == 1
        and "m_u_min" in r.output
        and str(bad) in r.output
        and "Traceback" not in r.output
    )
    bad.write_text('{"mapper": {"lidar": {"m_fre": 0.1}}}')
    r = runner.invoke(app, ["map", "--config", str(bad), "--out", str(out)])
    assert (
        r.exit_code == 1
        and "config.mapper.lidar" in r.output.replace(str(bad), "config")
        and "m_fre" in r.output
    )
    r = runner.invoke(app, ["--debug", "map", "--config", str(bad), "--out", str(out)])
    assert (
        r.exit_code == 1 and r.exception is not None
    )  # --debug lets the exception (and its traceback) through
    assert not out.exists()


def test_too_short_a_scene_still_gives_a_table(tmp_path, tiny_checkpoint):
    r = evgrid(
        "evaluate", scenes=1, duration=0.1, workers=1, checkpoint=tiny_checkpoint, out=tmp_path
    )
    assert r.exit_code == 0, r.output
    assert "| `fused` |" in (tmp_path / "table.md").read_text()


def test_a_simulated_recording_maps_through_bag_and_rig_and_exports(tmp_path, tiny_checkpoint):
    pytest.importorskip("rosbags")
    r = evgrid(
        "simulate",
        format="ros2",
        out=tmp_path / "bags",
        seed=4,
        duration=1,
        lidar_rate=10,
        radar_rate=4,
    )
    assert r.exit_code == 0, r.output
    bag, rig = tmp_path / "bags" / "sim-000004", tmp_path / "bags" / "sim-000004.rig.yaml"
    assert bag.is_dir() and rig.is_file()
    r = evgrid(
        "map",
        bag=bag,
        rig=rig,
        maps="ray_ilm,ray_irm,fused",
        checkpoint=tiny_checkpoint,
        export="nav2,mcap",
        save_maps=True,
        out=tmp_path / "out",
    )
    assert r.exit_code == 0, r.output
    scene = tmp_path / "out" / "sim-000004"
    # the navigation map (fused: this run has no nav map) under map_saver's names
    assert (scene / "nav2" / "map.pgm").is_file() and (scene / "sim-000004.mcap").is_file()
    metrics = json.loads((scene / "metrics.json").read_text())
    assert metrics["counts"]["updates"] > 0 and "vs_ray_ilm" in metrics
    run = json.loads((tmp_path / "out" / "config.json").read_text())
    assert run["source"]["kind"] == "bag" and run["outputs"]["exports"] == ["nav2", "mcap"]
    # a saved map exports on its own too
    r = evgrid("export", scene / "maps" / "fused.npz", format="nav2", out=tmp_path / "f")
    assert r.exit_code == 0, r.output
    assert (tmp_path / "f.yaml").is_file() and "mode: trinary" in (tmp_path / "f.yaml").read_text()


def test_bag_options_fail_in_one_line(tmp_path):
    r = runner.invoke(app, ["map", "--bag", str(tmp_path / "x.mcap"), "--out", str(tmp_path / "o")])
    assert r.exit_code != 0 and "--rig" in r.output
    r = evgrid("map", bag=tmp_path / "x.mcap", sim_dir=tmp_path, out=tmp_path / "o")
    assert r.exit_code != 0 and "one data source" in r.output
    r = runner.invoke(app, ["export", str(tmp_path / "missing.npz"), "--format", "nav2"])
    assert r.exit_code == 1 and "missing.npz" in r.output and "Traceback" not in r.output


def test_upgrade_checkpoint_rewrites_an_old_format(tmp_path, tiny_checkpoint):
    from evgrid.ism.evnet import load_checkpoint

    dst = tmp_path / "new.safetensors"
    r = runner.invoke(app, ["upgrade-checkpoint", str(tiny_checkpoint), str(dst)])
    assert r.exit_code == 0, r.output
    old, new = load_checkpoint(tiny_checkpoint), load_checkpoint(dst)
    assert new.version == 2
    for (k, a), (_, b) in zip(old.model.state_dict().items(), new.model.state_dict().items()):
        assert torch.equal(a, b), k


def test_export_refuses_an_existing_file_unless_overwrite(tmp_path):
    import numpy as np

    from evgrid.grid import EvidentialMap, save_map

    m = EvidentialMap(GridSpec(16, 1.6), tile_cells=16)
    m.tile((0, 0))[0][...] = np.array([0.8, 0.0, 0.2], np.float32)  # free
    m.covered_tiles[(0, 0)][...] = True
    path = save_map(m, tmp_path / "fused.npz")
    args = ["export", str(path), "--format", "nav2", "--out", str(tmp_path / "nav")]
    assert runner.invoke(app, args).exit_code == 0
    r = runner.invoke(app, args)
    assert r.exit_code != 0 and "nav.pgm exists" in r.output and "--overwrite" in r.output
    r = runner.invoke(app, [*args, "--overwrite"])
    assert r.exit_code == 0, r.output
    assert "wrote" in r.output and (tmp_path / "nav.yaml").is_file()


def test_map_with_the_gate_writes_the_moving_objects_table(tmp_path):
    r = runner.invoke(
        app,
        [
            "map",
            *("--scenes", "1", "--duration", "2", "--out", str(tmp_path)),
            *("--maps", "ray_ilm,ray_irm", "--figures", "off"),
            *("--dynamic", "on", "--dynamic-gate", "on"),
        ],
    )
    assert r.exit_code == 0, r.output
    config = json.loads((tmp_path / "config.json").read_text())["mapper"]["dynamic"]
    assert config["enabled"] and config["gate_maps"]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert set(summary["left_behind_m2"]) == {"ray_ilm", "ray_irm"}
    table = (tmp_path / "table.md").read_text()
    assert "**moving objects**" in table and "| `ray_ilm` |" in table
