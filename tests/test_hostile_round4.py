"""Hostile input, round 4 (issue 39): files read whole that never end or nest too deep, sizes that
would eat the machine's memory, locks of other hosts, sweeps of strings, a second tf parent, rig
topics that are not names (docs/hostile-input.md). Each case says what a user saw before."""

from __future__ import annotations

import json
import logging
import os
import socket

import numpy as np
import pytest

from evgrid.config import ConfigError, load_config
from evgrid.data.frame import LIDAR_COLUMNS, LidarSweep
from evgrid.geometry import SE2, SE3
from evgrid.io import READ_LIMITS, InputFileError, load_json_bounded, read_bounded
from evgrid.outdir import LOCK_NAME, RunLockedError, break_lock, results_folder

# --- files read whole ---


def test_a_device_as_config_is_refused_after_the_limit_not_read_forever():
    # before: /dev/zero read 3.35 GB in 10 s, then `evgrid: error: MemoryError`
    with pytest.raises(ConfigError, match=r"^/dev/zero: more than 16 MiB, the most a config"):
        load_config("/dev/zero")


def test_a_huge_file_as_config_is_refused_by_its_size_unread(tmp_path):
    big = tmp_path / "drive.mcap"
    with open(big, "wb") as f:
        f.truncate(5 * 2**30)  # sparse: 5 GiB reported, nothing on disk
    with pytest.raises(ConfigError, match=r"drive\.mcap: more than 16 MiB.*it holds 5 GiB"):
        load_config(big)


def test_a_deep_json_config_names_the_file_and_depth(tmp_path):
    # before: `maximum recursion depth exceeded while decoding a JSON array from a unicode string`
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 200_000 + "]" * 200_000)
    with pytest.raises(ConfigError, match=r"deep\.json: JSON nested 200000 levels deep"):
        load_config(deep)


def test_an_integer_of_5001_digits_names_the_file_and_position(tmp_path):
    # before: Python's `Exceeds the limit (4300 digits) for integer string conversion ...`
    p = tmp_path / "long.json"
    p.write_text('{"mapper": {\n  "threads": ' + "7" * 5001 + "}}")
    says = r"long\.json: an integer of 5001 digits at line 2 column 14"
    with pytest.raises(ConfigError, match=says):
        load_config(p)


def test_the_bounded_reader_reads_up_to_its_limit_and_no_further(tmp_path):
    p = tmp_path / "t.json"
    p.write_text(json.dumps({"a": [1, "[[[["]}))
    assert load_json_bounded(p, "config") == {"a": [1, "[[[["]}
    assert read_bounded(p, "config", limit=p.stat().st_size) == p.read_bytes()
    with pytest.raises(InputFileError, match=r"t\.json: more than"):
        read_bounded(p, "config", limit=p.stat().st_size - 1)
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)  # a pipe reports size 0, as a device does
    pid = os.fork()
    if pid == 0:  # the writer: more than the limit, then it ends
        with open(fifo, "wb") as f:
            f.write(b"x" * 100)
        os._exit(0)
    try:
        with pytest.raises(InputFileError, match="more than 64 B"):
            read_bounded(fifo, "config", limit=64)
    finally:
        os.waitpid(pid, 0)
    assert set(READ_LIMITS) == {"config", "rig", "nuScenes table"}


def test_a_rig_file_that_is_huge_deep_or_holds_a_long_integer_names_the_file(tmp_path):
    pytest.importorskip("yaml")
    from evgrid.data.bag import RigError, load_rig

    with pytest.raises(RigError, match=r"^/dev/zero: more than 16 MiB, the most a rig file"):
        load_rig("/dev/zero")  # before: `no rig file at /dev/zero`
    with pytest.raises(RigError, match="a folder, not a rig file"):
        load_rig(tmp_path)
    big = tmp_path / "big.yaml"
    with open(big, "wb") as f:
        f.truncate(READ_LIMITS["rig"] + 1)
    with pytest.raises(RigError, match=r"big\.yaml: more than 16 MiB, the most a rig file"):
        load_rig(big)
    deep = tmp_path / "deep.yaml"
    deep.write_text("[" * 20_000 + "]" * 20_000)
    with pytest.raises(RigError, match=r"deep\.yaml: nested deeper than the YAML reader goes"):
        load_rig(deep)
    long = tmp_path / "long.yaml"
    long.write_text("lidar: {topic: /lidar}\nsync_tolerance_s: " + "1" * 5001 + "\n")
    with pytest.raises(RigError, match=r"long\.yaml: a value YAML cannot read: Exceeds the limit"):
        load_rig(long)


def test_a_nuscenes_table_that_is_a_device_or_too_large_is_refused_before_the_devkit(tmp_path):
    from evgrid.data.nuscenes import NuScenesDataError, _check_table_sizes

    (tmp_path / "scene.json").write_text("[]")
    _check_table_sizes(tmp_path)
    (tmp_path / "sample_data.json").symlink_to("/dev/zero")
    with pytest.raises(NuScenesDataError, match=r"sample_data\.json: not a regular file"):
        _check_table_sizes(tmp_path)
    (tmp_path / "sample_data.json").unlink()
    with open(tmp_path / "ego_pose.json", "wb") as f:
        f.truncate(READ_LIMITS["nuScenes table"] + 1)
    says = r"ego_pose\.json: 4,294,967,297 bytes, more than the 4 GiB"
    with pytest.raises(NuScenesDataError, match=says):
        _check_table_sizes(tmp_path)


# --- locks ---


def _foreign_lock(out, host="a-container-gone"):
    out.mkdir(parents=True, exist_ok=True)
    (out / LOCK_NAME).write_text(json.dumps({"pid": 1, "host": host, "started": 1.7e9}))


def test_a_lock_of_another_host_says_it_may_be_stale_and_how_to_clear_it(tmp_path):
    # before: `OUT is in use by another evgrid run (pid 1 on HOST, lock ...); wait for it or
    # choose another --out`, also with --overwrite, and nothing said how to clear it
    out = tmp_path / "run"
    _foreign_lock(out)
    for overwrite in (False, True):  # --overwrite alone does not break another host's lock
        with pytest.raises(RunLockedError) as e:
            with results_folder(out, overwrite=overwrite):
                pass
        msg = str(e.value)
        assert "pid 1 on host 'a-container-gone'" in msg and "may be stale" in msg
        assert f"evgrid unlock {out}" in msg and "--overwrite does not clear it" in msg
    assert break_lock(out)["host"] == "a-container-gone"
    with results_folder(out, overwrite=True):
        assert json.loads((out / LOCK_NAME).read_text())["pid"] == os.getpid()
    assert break_lock(out) is None  # released, nothing to clear


def test_evgrid_unlock_clears_a_foreign_lock(tmp_path):
    from typer.testing import CliRunner

    from evgrid.cli import app

    out = tmp_path / "run"
    out.mkdir()
    lock = {"pid": 1, "host": "a-container-gone", "started": 0}
    (out / LOCK_NAME).write_text(json.dumps(lock))
    res = CliRunner().invoke(app, ["unlock", str(out)])
    assert res.exit_code == 0 and "was pid 1 on a-container-gone" in res.output
    assert not (out / LOCK_NAME).exists()


def test_break_lock_refuses_the_lock_of_a_live_run_on_this_host(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    holder = {"pid": os.getppid(), "host": socket.gethostname(), "started": 1.7e9}
    (out / LOCK_NAME).write_text(json.dumps(holder))
    with pytest.raises(RunLockedError, match="live evgrid run.*its lock is not stale"):
        break_lock(out)
    assert (out / LOCK_NAME).exists()


def test_a_garbage_lock_says_what_it_holds(tmp_path):
    # before: `OUT: could not take the lock OUT/.evgrid.lock`, no reason
    out = tmp_path / "run"
    out.mkdir()
    (out / LOCK_NAME).write_text("garbage")
    with pytest.raises(RunLockedError) as e:
        with results_folder(out):
            pass
    msg = str(e.value)
    assert "holds 'garbage', not an evgrid lock" in msg and "s ago" in msg
    assert f"evgrid unlock {out}" in msg
    assert break_lock(out) is None and not (out / LOCK_NAME).exists()


def test_an_old_garbage_lock_is_taken_over_with_the_reason(tmp_path, caplog):
    out = tmp_path / "run"
    out.mkdir()
    (out / LOCK_NAME).write_text("")
    os.utime(out / LOCK_NAME, (1e9, 1e9))
    with caplog.at_level(logging.WARNING, logger="evgrid.outdir"):
        with results_folder(out):
            pass
    assert "it is empty, not an evgrid lock" in caplog.text


# --- sweeps and images ---


@pytest.mark.parametrize(
    "points, says",
    [
        (np.full((3, 5), "1.5"), "strings"),
        (np.ones((3, 5), np.complex64) * (1 + 2j), "complex numbers"),
        (np.ones((3, 5), bool), "booleans"),
        (np.array([[1, 2, 3, 4, 5]] * 3, dtype=object), "Python objects"),
    ],
)
def test_a_lidar_sweep_of_strings_or_complex_numbers_is_refused(points, says):
    # before: converted silently ("1.5" -> 1.5, 1+2j -> 1 with a ComplexWarning)
    with pytest.raises(ValueError, match=rf"LidarSweep.points must hold real numbers.*{says}"):
        LidarSweep(points, SE3.identity(), SE3.identity(), 0)
    assert len(LIDAR_COLUMNS) == 5


def test_deep_irm_predict_image_names_a_list_and_a_nan_channel():
    from evgrid.ism.deep import CHANNELS, DeepIrm

    deep = DeepIrm()
    n = deep.grid.n_cells
    # before: AttributeError: 'list' object has no attribute 'shape'
    with pytest.raises(TypeError, match="image must be a numpy array.*got list"):
        deep.predict_image(np.zeros((len(CHANNELS), n, n)).tolist())
    image = np.zeros((len(CHANNELS), n, n), np.float32)
    image[1, 3, 4] = np.nan
    # before: `e: evidence must be finite`
    with pytest.raises(ValueError, match=r"not finite \(NaN or inf\) in channel\(s\) 1 \(rcs\)"):
        deep.predict_image(image)


# --- sizes: the memory budget ---


def _outputs(**kw):
    from evgrid.config import OutputConfig

    return OutputConfig(**kw)


@pytest.mark.parametrize(
    "window_m, says",
    [(1200.0, "5.05 GiB"), (3000.0, "31.6 GiB"), (1e9, "PiB")],
)
def test_an_mcap_window_beyond_the_budget_is_refused_naming_the_option(window_m, says):
    # before: a 2 s scene mapped, then 4.8 GB reached (1200 m), `Unable to allocate 16.5 GiB`
    # (3000 m) or `array is too big` (1e9 m), naming no option
    from evgrid.budget import BudgetError, check_budget
    from evgrid.cli.options import MAP_OPTIONS
    from evgrid.config import MapperConfig
    from evgrid.export.mcap import McapParams

    outputs = _outputs(exports=("mcap",), mcap=McapParams(window_m=window_m))
    with pytest.raises(BudgetError) as e:
        check_budget(MapperConfig(), outputs, budget=4 * 2**30, options=MAP_OPTIONS)
    msg = str(e.value)
    assert msg.startswith("outputs.mcap.window_m (--mcap-window): an MCAP window of")
    assert says in msg and "more than the memory budget of 4 GiB" in msg
    assert "EVGRID_MEMORY_BUDGET_GB" in msg
    check_budget(MapperConfig(), _outputs(exports=("mcap",)), budget=4 * 2**30)  # 40 m


def test_the_command_line_refuses_a_window_beyond_the_budget_before_any_scene(tmp_path):
    from typer.testing import CliRunner

    from evgrid.cli import app

    out = tmp_path / "run"
    args = ["map", "--scenes", "1", "--duration", "1", "--out", str(out), "--mcap-window", "1e9"]
    res = CliRunner().invoke(app, [*args, "--export", "mcap"])
    assert res.exit_code == 1
    assert "outputs.mcap.window_m (--mcap-window): an MCAP window of" in res.output
    assert not out.exists()  # refused before the results folder or any scene


def test_a_library_run_is_refused_too_naming_the_config_key(tmp_path):
    from evgrid.budget import BudgetError
    from evgrid.config import MapperConfig
    from evgrid.export.mcap import McapParams
    from evgrid.runs import map_scenes
    from evgrid.sources import SimSource

    outputs = _outputs(exports=("mcap",), mcap=McapParams(window_m=1e9))
    with pytest.raises(BudgetError, match=r"^outputs\.mcap\.window_m: an MCAP window"):
        map_scenes(SimSource((4,), 1.0), tmp_path / "run", MapperConfig(), outputs)
    assert not (tmp_path / "run").exists()


def test_a_gif_window_of_1e7_m_is_refused_before_mapping():
    # before: `Unable to allocate 2.73 PiB` after the scene was mapped
    from evgrid.budget import BudgetError, check_budget
    from evgrid.config import RunConfig

    cfg = RunConfig(outputs=_outputs(gif_window_m=1e7))
    with pytest.raises(
        BudgetError, match=r"^outputs\.gif_window_m: a GIF of up to 240 frames.*PiB"
    ):
        check_budget(cfg, budget=2**30)
    check_budget(RunConfig(outputs=_outputs(gif_window_m=1e7, figures=False)), budget=2**30)


def test_grids_tiles_and_their_sum_are_bounded_by_the_budget():
    from dataclasses import replace

    from evgrid.budget import BudgetError, check_budget, costs
    from evgrid.config import MapperConfig
    from evgrid.geometry import GridSpec

    base = MapperConfig()
    with pytest.raises(BudgetError, match=r"^mapper\.grid\.n_cells: 6 map\(s\).* 24 GiB"):
        check_budget(replace(base, grid=GridSpec(8192, 640.0)), budget=8 * 2**30)
    with pytest.raises(BudgetError, match=r"^mapper\.tile_cells: 4 tiles of 4096 x 4096"):
        check_budget(replace(base, tile_cells=4096), budget=2**30)
    each = sum(c.bytes for c in costs(base, _outputs()))
    check_budget(base, _outputs(), budget=int(each) + 1)
    with pytest.raises(BudgetError, match=r"^this run would take .* x 2 scenes at once"):
        check_budget(base, _outputs(), workers=2, budget=int(each) + 1)


def test_the_budget_comes_from_the_environment_or_a_quarter_of_the_memory():
    from evgrid.budget import BUDGET_ENV, machine_memory, memory_budget

    assert memory_budget({}) == int(machine_memory() * 0.25)
    assert memory_budget({BUDGET_ENV: "1.5"}) == 1_500_000_000
    for bad in ("-1", "nan", "lots"):
        with pytest.raises(ConfigError, match=f"{BUDGET_ENV}='{bad}': must be a positive"):
            memory_budget({BUDGET_ENV: bad})


def test_the_mcap_window_cost_bounds_what_its_write_allocates(tmp_path):
    # the estimate is an upper bound of the arrays the export allocates (tracemalloc sees numpy)
    import tracemalloc

    pytest.importorskip("mcap")
    from evgrid.budget import costs
    from evgrid.config import MapperConfig
    from evgrid.export.mcap import McapExporter, McapParams
    from evgrid.grid import EvidentialMap

    grid = MapperConfig().grid
    for layers in (("occupancy",), ("occupancy", "m_free", "m_occupied", "m_unknown", "dynamic")):
        params = McapParams(window_m=40.0, layers=layers)
        ex = McapExporter(tmp_path / f"{len(layers)}.mcap", params)
        n = grid.n_cells
        tracemalloc.start()
        ex.write_maps({"fused": EvidentialMap(grid, dynamic=True)}, 0, (0, 0, n, n))
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        ex.abort()
        (est,) = [
            c.bytes
            for c in costs(MapperConfig(), _outputs(exports=("mcap",), mcap=params))
            if c.key == "outputs.mcap.window_m"
        ]
        assert peak <= est <= 1.5 * peak, (layers, peak, est)


# --- rigs and /tf ---


def _rig_error(tmp_path, rig: dict) -> str:
    yaml = pytest.importorskip("yaml")
    from evgrid.data.bag import RigError, load_rig

    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(rig))
    with pytest.raises(RigError) as e:
        load_rig(path)
    return str(e.value)


def test_a_topic_that_is_no_string_is_said_so_not_missing(tmp_path):
    # before: `'lidar' must give at least a 'topic'` (as if it were missing)
    msg = _rig_error(tmp_path, {"lidar": {"topic": 5}})
    assert msg.endswith(
        "rig.yaml: lidar.topic must be a topic name (a string such as /lidar), got 5"
    )
    msg = _rig_error(tmp_path, {"lidar": {"topic": "/l"}, "radars": [{"topic": ["/r"]}]})
    assert "radars[0].topic must be a topic name" in msg and "['/r']" in msg


def test_the_lidar_topic_listed_as_a_radar_is_refused_naming_it(tmp_path):
    # before: accepted, and the radar entry ignored without a word
    msg = _rig_error(tmp_path, {"lidar": {"topic": "/points"}, "radars": [{"topic": "/points"}]})
    assert "radars[0]: topic '/points' is the lidar's topic too" in msg


def _tf(buf, parent, t_us, x):
    return buf.add(parent, "base_link", t_us, (x, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))


def test_a_second_tf_parent_is_kept_apart_logged_and_counted(caplog):
    # before: map -> base_link samples were stored as odom -> base_link (poses jumping between
    # the two) and `map` was in no edge: "frame(s) ['map'] not in /tf" with world_frame: map
    from evgrid.data.bag.transforms import TransformBuffer

    buf = TransformBuffer()
    with caplog.at_level(logging.WARNING, logger="evgrid.data.bag.transforms"):
        for k in range(5):
            assert _tf(buf, "odom", k * 100_000, float(k))
            assert _tf(buf, "/map", k * 100_000, 1000.0 + k)
    assert "map" in buf.frames() and buf.second_parents == {"base_link": {"map": 5}}
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "'base_link' has a second parent 'map' besides 'odom'" in said[0]
    assert buf.parent("base_link") == "odom"
    assert buf.lookup("odom", "base_link", 250_000).translation[0] == pytest.approx(2.5)
    assert buf.lookup("map", "base_link", 250_000).translation[0] == pytest.approx(1002.5)
    assert buf.span("map", "base_link") == (0, 400_000)
    # map -> odom -> base_link, the tree REP 105 asks for, still climbs through odom
    buf2 = TransformBuffer()
    for k in range(5):
        _tf(buf2, "odom", k * 100_000, float(k))
        buf2.add("map", "odom", k * 100_000, (10.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    assert buf2.lookup("map", "base_link", 100_000).translation[0] == pytest.approx(11.0)
    assert buf2.second_parents == {}


def test_a_recording_with_two_parents_for_base_link_maps_in_the_world_frame_asked(tmp_path):
    pytest.importorskip("rosbags")
    pytest.importorskip("mcap")
    pytest.importorskip("yaml")
    from evgrid.data.bag import load_bag
    from evgrid.ros import RecordingWriter, columns_to_cloud, tf_message, transform_msg, us_to_stamp
    from evgrid_sim import SimConfig, simulate_scene

    frames = list(simulate_scene(3, SimConfig(duration_s=0.4)))
    shift = SE3.from_se2(SE2(500.0, 0.0, 0.0))
    path = tmp_path / "two.mcap"
    w = RecordingWriter(path, "plain-mcap")
    s, t0 = w.store, frames[0].timestamp
    static = transform_msg("base_link", "LIDAR_TOP", t0, frames[0].lidar.sensor_to_ego, s)
    w.write("/tf_static", "tf2_msgs/msg/TFMessage", t0 * 1000, tf_message([static], s))
    for f in frames:
        t = f.timestamp
        both = [
            transform_msg("odom", "base_link", t, f.ego_pose, s),
            transform_msg("map", "base_link", t, shift @ f.ego_pose, s),
        ]
        w.write("/tf", "tf2_msgs/msg/TFMessage", t * 1000, tf_message(both, s))
        sec, ns = us_to_stamp(t)
        cloud = columns_to_cloud(f.lidar.points, LIDAR_COLUMNS, sec, ns, "LIDAR_TOP", s)
        w.write("/lidar", "sensor_msgs/msg/PointCloud2", t * 1000, cloud)
    w.close()
    for world, dx in (("map", 500.0), ("odom", 0.0)):
        got = list(load_bag(path, {"lidar": {"topic": "/lidar"}, "world_frame": world}))
        assert len(got) == len(frames)
        for g, f in zip(got, frames, strict=True):
            want = f.ego_pose.translation[0] + dx
            assert g.ego_pose.translation[0] == pytest.approx(want, abs=1e-6)
