"""Hostile input, round 4, phase 2b (issue 39): a run that mapped nothing, a silent radar, empty
maps exported, a saved map's frame, an interrupted save, points at the sensor origin, a second tf
parent counted (docs/hostile-input.md). Each case says what a user saw before."""

from __future__ import annotations

import dataclasses
import json
import logging

import numpy as np
import pytest
from typer.testing import CliRunner

from evgrid.cli import app
from evgrid.data import LIDAR_COLUMNS
from evgrid.geometry import SE2, SE3

runner = CliRunner()


@pytest.fixture(scope="module")
def frames():
    from evgrid_sim import SimConfig, simulate_scene

    return list(simulate_scene(3, SimConfig(duration_s=0.4)))


def _recording(path, frames, cloud=None, silent_radar=None, second_parent=False):
    """A lidar recording of ``frames`` (/tf_static, /tf, /lidar); ``cloud(msg)`` tampers with
    every cloud, ``silent_radar`` a topic registered without a message, ``second_parent`` adds
    ``map -> base_link`` beside ``odom -> base_link``."""
    pytest.importorskip("rosbags")
    pytest.importorskip("mcap")
    from evgrid.ros import RecordingWriter, columns_to_cloud, tf_message, transform_msg, us_to_stamp

    w = RecordingWriter(path, "plain-mcap")
    s, t0 = w.store, frames[0].timestamp
    static = transform_msg("base_link", "LIDAR_TOP", t0, frames[0].lidar.sensor_to_ego, s)
    w.write("/tf_static", "tf2_msgs/msg/TFMessage", t0 * 1000, tf_message([static], s))
    if silent_radar:
        w._topic(silent_radar, "sensor_msgs/msg/PointCloud2")  # a channel, no message
    shift = SE3.from_se2(SE2(500.0, 0.0, 0.0))
    for f in frames:
        t = f.timestamp
        trs = [transform_msg("odom", "base_link", t, f.ego_pose, s)]
        if second_parent:
            trs.append(transform_msg("map", "base_link", t, shift @ f.ego_pose, s))
        w.write("/tf", "tf2_msgs/msg/TFMessage", t * 1000, tf_message(trs, s))
        sec, ns = us_to_stamp(t)
        msg = columns_to_cloud(f.lidar.points, LIDAR_COLUMNS, sec, ns, "LIDAR_TOP", s)
        w.write("/lidar", "sensor_msgs/msg/PointCloud2", t * 1000, cloud(msg) if cloud else msg)
    w.close()
    return path


def _rig(tmp_path, **extra):
    import yaml

    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump({"lidar": {"topic": "/lidar"}, **extra}))
    return rig


# --- 1. a run that mapped no frame fails, saying why ---------------------------------------------


def test_a_run_that_mapped_no_frame_fails_naming_the_skips(frames, tmp_path):
    # before: every cloud named and skipped, then `0 frames`, a table of n/a and exit 0
    def short(msg):
        return dataclasses.replace(msg, data=msg.data[: len(msg.data) // 2])

    bag = _recording(tmp_path / "bad.mcap", frames, cloud=short)
    out = tmp_path / "out"
    args = ["map", "--bag", str(bag), "--rig", str(_rig(tmp_path)), "--out", str(out)]
    r = runner.invoke(app, [*args, "--maps", "ray_ilm", "--figures", "off"])
    assert r.exit_code == 1, r.output
    said = [ln for ln in r.output.splitlines() if "no frame mapped" in ln]
    assert said and f"lidar_messages_malformed {len(frames)}" in said[-1], r.output
    assert "0 frame(s) made" in said[-1]
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["failed"]) == ["bad"] and not summary["scenes"]
    assert not list(out.glob("bad/*.mcap")) and not (out / "table.md").exists()


def test_no_frame_mapped_from_the_api_too(frames):
    from evgrid.runs import NoFrameMapped, map_scene

    with pytest.raises(NoFrameMapped, match=r"^empty: no frame mapped \(0 frame\(s\) made\)"):
        map_scene([], None, name="empty")


# --- 2. a radar topic with no message is named and counted ---------------------------------------


def test_a_silent_radar_topic_is_named_and_counted(frames, tmp_path, caplog):
    # before: the radar maps were made without it, silently (fused occupied IoU 5.2 % -> 1.0 %)
    from evgrid.data.bag import load_bag

    bag = _recording(tmp_path / "r.mcap", frames, silent_radar="/radar_front")
    rig = {"lidar": {"topic": "/lidar"}, "radars": [{"topic": "/radar_front", "channel": "RF"}]}
    with caplog.at_level(logging.WARNING, logger="evgrid.data.bag"):
        scene = load_bag(bag, rig)
        got = list(scene)
    assert len(got) == len(frames)
    said = [r.getMessage() for r in caplog.records if "/radar_front" in r.getMessage()]
    assert len(said) == 1 and "radar topic /radar_front has no message" in said[0]
    assert str(bag) in said[0]
    assert scene.counts["radar_topics_silent"] == 1


# --- 8. a second tf parent is counted per scene and the topic named ------------------------------


def test_a_second_tf_parent_is_counted_in_the_scene_and_names_the_topic(frames, tmp_path, caplog):
    # before: only TransformBuffer.second_parents knew, metrics.json said nothing
    from evgrid.data.bag import load_bag

    bag = _recording(tmp_path / "two.mcap", frames, second_parent=True)
    with caplog.at_level(logging.WARNING, logger="evgrid.data.bag"):
        scene = load_bag(bag, {"lidar": {"topic": "/lidar"}})
        list(scene)
    assert scene.counts["pose_samples_second_parent"] == len(frames)
    said = [r.getMessage() for r in caplog.records if "second parent (map)" in r.getMessage()]
    assert len(said) == 1 and f"{bag} /tf: {len(frames)} sample(s)" in said[0]
    clean = load_bag(_recording(tmp_path / "one.mcap", frames), {"lidar": {"topic": "/lidar"}})
    list(clean)
    assert clean.counts["pose_samples_second_parent"] == 0


# --- 3. an empty map is refused by every exporter alike -----------------------------------------


@pytest.mark.parametrize("fmt", ["nav2", "mcap", "rerun"])
def test_an_empty_map_is_refused_by_every_exporter(tmp_path, fmt):
    # before: a 0-message MCAP and a 7 kB RRD with exit 0 (nav2 refused it)
    pytest.importorskip({"nav2": "numpy", "mcap": "mcap", "rerun": "rerun"}[fmt])
    from evgrid.grid import EvidentialMap, GridSpec, save_map

    path = save_map(EvidentialMap(GridSpec(8, 0.8), 8), tmp_path / "fused.npz")
    r = runner.invoke(app, ["export", str(path), "--format", fmt])
    assert r.exit_code != 0
    line = r.output.strip().splitlines()[-1]
    assert line.startswith("evgrid: error: ") and "'fused' has no observed cell" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fused.npz"]  # nothing written


# --- 5. Ctrl-C while a map is saved is quiet -----------------------------------------------------


def _small_map():
    from evgrid.grid import EvidentialMap, GridSpec

    m = EvidentialMap(GridSpec(16, 0.5), tile_cells=16)
    for k in [(0, 0), (0, 1), (1, 1)]:
        m.tile(k)[0][...] = np.array([0.8, 0.0, 0.2], np.float32)
        m.covered_tiles[k][...] = True
    return m


@pytest.mark.parametrize(
    "where,nth",
    [("write", 1), ("write", 4), ("close", 1), ("close", 3), ("open", 2)],
    ids=["first write", "tiles", "closing the header", "closing the tiles", "opening keys"],
)
def test_ctrl_c_while_a_map_is_saved_leaves_no_file_and_prints_nothing(
    tmp_path, monkeypatch, capfd, where, nth
):
    # before: six lines of `Exception ignored in: ZipFile.__del__ ... seek of closed file` after
    # the clean Ctrl-C message (the zip was closed by its finaliser after its file was removed)
    import gc
    import sys
    import zipfile

    from evgrid.grid import save_map

    cls = zipfile.ZipFile if where == "open" else zipfile._ZipWriteFile
    orig, calls, unraisable = getattr(cls, where), [], []

    def interrupted(self, *a, **kw):
        calls.append(1)
        if len(calls) == nth:
            if where == "open":  # inside zf.open: marked as writing, no handle returned
                orig(self, *a, **kw)
            raise KeyboardInterrupt
        return orig(self, *a, **kw)

    monkeypatch.setattr(cls, where, interrupted)
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    with pytest.raises(KeyboardInterrupt):  # itself, not a ValueError raised while closing
        save_map(_small_map(), tmp_path / "fused.npz")
    gc.collect()
    assert not unraisable and capfd.readouterr().err == ""
    assert list(tmp_path.iterdir()) == []  # no map, no temporary file
    monkeypatch.undo()
    assert save_map(_small_map(), tmp_path / "fused.npz").exists()  # and saving still works


# --- 6. points at the sensor origin are no returns -----------------------------------------------


def test_points_at_the_sensor_origin_are_dropped_and_counted_not_a_free_disc(caplog):
    # before: a sweep of (0, 0, 0) points (the lidar 1.8 m up, so within the height band)
    # painted every ray's 15 m as free: a full free disc from no return at all
    from evgrid.geometry import GridSpec
    from evgrid.ism import ray_ilm_with_stats

    grid = GridSpec(64, 0.5)
    s2e = SE3.from_matrix(np.array([[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 1.8], [0, 0, 0, 1.0]]))
    at_origin = np.zeros((50, 3), np.float32)
    at_origin[:10] = 4e-4  # within 1 mm too
    with caplog.at_level(logging.WARNING, logger="evgrid.ism.lidar"):
        r = ray_ilm_with_stats(at_origin, s2e, grid=grid)
    assert r.n_at_origin == 50 and r.n_used == 0 and r.n_dropped == 0
    assert (r.masses[..., 2] == 1.0).all()  # vacuous: no measurement
    assert "all 50 finite point(s) lie within 0.001 m of the sensor" in caplog.text
    # one real return beside them: the origin points change nothing
    wall = np.array([[5.0, 0.0, 0.0]], np.float32)
    alone = ray_ilm_with_stats(wall, s2e, grid=grid)
    mixed = ray_ilm_with_stats(np.r_[at_origin, wall], s2e, grid=grid)
    np.testing.assert_array_equal(mixed.masses, alone.masses)
    assert mixed.n_at_origin == 50 and mixed.n_used == 1
    # 2 mm from the sensor is a return (in the lidar's own cell, which stops no ray)
    near = ray_ilm_with_stats(np.full((3, 3), 2e-3 / np.sqrt(3), np.float32), s2e, grid=grid)
    assert near.n_at_origin == 0 and near.n_used == 3


def test_the_mapper_counts_points_at_the_origin(frames):
    from evgrid.config import MapperConfig
    from evgrid.mapper import OccupancyMapper
    from evgrid.preprocess import SelfReturnParams

    f = frames[0]
    pts = f.lidar.points.copy()
    pts[:100, :3] = 0.0
    sweep = dataclasses.replace(f.lidar, points=pts)
    # the self-return filter (auto) would drop them first; off, they reach the ray ILM
    config = MapperConfig(maps=("ray_ilm",), self_returns=SelfReturnParams(mode="off"))
    mapper = OccupancyMapper(config)
    try:
        mapper.process(dataclasses.replace(f, lidar=sweep, is_keyframe=True))
        assert mapper.counts()["lidar_points_at_origin"] >= 100
    finally:
        mapper.close()


# --- 4. a saved map keeps its frame, stamp and metadata, and `evgrid export` uses them ----------


@pytest.fixture(scope="module")
def saved(frames, tmp_path_factory):
    """The maps a short run saved (its fixed frame `world`, the simulator's), in both frames."""
    from evgrid.config import MapperConfig, OutputConfig
    from evgrid.runs import map_scene

    out = tmp_path_factory.mktemp("saved")
    outputs = OutputConfig(save_maps=True, figures=False)
    paths = {}
    for kind in ("world", "first_pose"):
        cfg = MapperConfig(maps=("ray_ilm",), frame=kind)
        res = map_scene(frames, out / kind, cfg, outputs, name="s")
        paths[kind] = res.files["map_ray_ilm"]
    return paths


def _mcap_of(path):
    pytest.importorskip("mcap_ros2")
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        msgs = [(ch.topic, m.log_time, d) for _, ch, m, d in reader.iter_decoded_messages()]
    with open(path, "rb") as fh:
        meta = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}
    return msgs, meta


def test_a_saved_map_keeps_its_stamp(frames, saved):
    from evgrid.grid import load_map

    stamps = {f.timestamp for f in frames}
    for kind, path in saved.items():
        frame = load_map(path).frame
        assert frame.kind == kind and frame.fixed_frame == "world"
        assert frame.stamp_us in stamps and frame.stamp_us > frames[0].timestamp


@pytest.mark.parametrize("kind,map_frame", [("world", "world"), ("first_pose", "map")])
def test_export_of_a_saved_map_carries_its_frame_stamp_and_metadata(
    saved, tmp_path, kind, map_frame
):
    # before: frame `map`, stamp 0 and no metadata, while the run's own exports carried the
    # recording's frame
    from evgrid.grid import load_map

    frame = load_map(saved[kind]).frame
    out = tmp_path / "m.mcap"
    r = runner.invoke(app, ["export", saved[kind], "--format", "mcap", "--out", str(out)])
    assert r.exit_code == 0, r.output
    msgs, meta = _mcap_of(out)
    (grid,) = [(t, d) for topic, t, d in msgs if topic.endswith("/occupancy")]
    assert grid[1].header.frame_id == map_frame and grid[0] == frame.stamp_us * 1000
    evg = meta["evgrid"]
    assert evg["map_frame"] == map_frame and evg["fixed_frame"] == "world"
    assert evg["stamp_us"] == str(frame.stamp_us) and "first_pose_xyz" in evg
    assert json.loads(evg["map ray_ilm"])["rule"] == "ray_ilm"
    tfs = [d for topic, _, d in msgs if topic == "/tf"]
    assert len(tfs) == (kind == "first_pose")  # map -> world only when they differ
    # nav2: the YAML says the frames and the stamp in its comments
    r = runner.invoke(
        app, ["export", saved[kind], "--format", "nav2", "--out", str(tmp_path / "n")]
    )
    assert r.exit_code == 0, r.output
    yml = (tmp_path / "n.yaml").read_text()
    assert f"# map frame '{map_frame}'; the recording's fixed frame 'world'" in yml
    assert f"# stamp {frame.stamp_us} us (the last update)" in yml


# --- 7. fine-tuning: one recording says how; the parent's score beside the new one ------------


def test_one_recording_for_training_and_validation_says_how_to_fine_tune_on_it(tmp_path):
    # before: `scene(s) ['drive'] are both training and validation scenes ... remove that line
    # to name recordings by their file names`, which still names both `drive`
    from evgrid.sources import BagSource
    from evgrid.train_run import _check_disjoint

    bag = tmp_path / "drive.mcap"
    bag.write_bytes(b"")
    rig = _rig(tmp_path)
    same = {"train": BagSource((str(bag),), str(rig)), "val": BagSource((str(bag),), str(rig))}
    with pytest.raises(ValueError) as e:
        _check_disjoint(same)
    msg = str(e.value)
    assert msg.startswith(f"{bag}: both a training and a validation recording")
    assert "cut it in two by time" in msg and "--val-bag" in msg and "\n" not in msg


def test_fine_tuning_reports_the_parents_validation_score_beside_the_new_one(tmp_path):
    # before: the parent checkpoint's validation score was never shown
    from evgrid.console import train_report
    from evgrid.ism.evnet import EvNetConfig
    from evgrid.learn.train import TrainConfig, build_cache, fine_tune_config, train
    from evgrid_sim import SimConfig, simulate_scene

    cfg = TrainConfig(
        epochs=1, batch_size=2, workers=0, frame_stride=10,
        model=EvNetConfig(in_channels=6, width=4, depth=2),
    )  # fmt: skip
    scenes = [simulate_scene(s, SimConfig(duration_s=1.0)) for s in (0, 4)]
    names = build_cache(scenes, tmp_path / "cache", cfg, with_irm=True)
    parent = train(cfg, tmp_path / "cache", names[:1], names[1:], tmp_path / "parent")
    assert parent.parent_val is None  # a fresh network has no parent
    child_cfg = fine_tune_config(cfg, tmp_path / "parent" / "best.safetensors")
    child = train(child_cfg, tmp_path / "cache", names[:1], names[1:], tmp_path / "child")
    assert child.parent_recorded_val == pytest.approx(parent.best, nan_ok=True)
    # the parent on the same validation scenes, before any step: what the child's best beats
    assert child.parent_val == pytest.approx(parent.best, nan_ok=True)
    text = train_report(child, tmp_path / "child")
    assert "validation IoU on these scenes: fine-tuned free" in text
    assert "the parent before fine-tuning free" in text


def test_a_parent_of_the_map_path_that_is_a_file_is_named(tmp_path):
    # before: `FileExistsError: [Errno 17] File exists: '.../afile'` from save_map, and
    # `[Errno 20] Not a directory` from a run's --out
    from evgrid.geometry import GridSpec
    from evgrid.grid import EvidentialMap, save_map
    from evgrid.io import NotAFolderError
    from evgrid.outdir import results_folder

    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    with pytest.raises(NotAFolderError, match=r"afile is a file, not a folder$"):
        save_map(EvidentialMap(GridSpec()), afile / "fused.npz")
    with pytest.raises(NotAFolderError, match=r"run cannot be made: .*afile is a file$"):
        with results_folder(afile / "deeper" / "run"):
            pass
    assert afile.read_text() == "not a folder"
