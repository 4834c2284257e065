"""Simulated scenes written in the nuScenes layout, read back through the official devkit and
through evgrid's loader; the loader's splits, travel filter and error messages."""

from __future__ import annotations

import json
import os
import re
import sys

import numpy as np
import pytest

import evgrid
from evgrid.data import LIDAR_CHANNEL, RADAR_CHANNELS, RADAR_COLUMNS, radar_column
from evgrid.data.nuscenes import NuScenesError, load_nuscenes, nuscenes_splits
from evgrid.data.nuscenes_format import (
    RADAR_PCD_FIELDS,
    read_radar_pcd,
    write_nuscenes,
    write_radar_pcd,
)
from evgrid_sim import EgoConfig, SimConfig, WorldConfig, simulate_scene

pytest.importorskip("nuscenes")
from nuscenes.nuscenes import NuScenes  # noqa: E402
from nuscenes.utils.data_classes import LidarPointCloud, RadarPointCloud  # noqa: E402

VERSION = "v1.0-sim"
ALL_STATES = dict(
    invalid_states=list(range(18)), dynprop_states=list(range(8)), ambig_states=list(range(5))
)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    root = tmp_path_factory.mktemp("nusc")
    moving = simulate_scene(3, SimConfig(duration_s=1.6, world=WorldConfig(environment="urban")))
    # A scene whose ego waits at a light the whole time (it never moves 1 m).
    parked = simulate_scene(
        4, SimConfig(duration_s=0.5, ego=EgoConfig(start_at_rest_probability=1.0))
    )
    frames = {moving.name: list(moving), parked.name: list(parked)}
    write_nuscenes(
        [moving, parked], root, VERSION, splits={"train": [moving.name], "val": [parked.name]}
    )
    return root, frames


def test_devkit_reads_every_frame_back(written):
    root, frames = written
    nusc = NuScenes(version=VERSION, dataroot=str(root), verbose=False)
    assert sorted(s["name"] for s in nusc.scene) == sorted(frames)
    for scene in nusc.scene:
        orig = frames[scene["name"]]
        assert scene["nbr_samples"] == sum(f.is_keyframe for f in orig)
        sample = nusc.get("sample", scene["first_sample_token"])
        assert set(sample["data"]) == {LIDAR_CHANNEL, *RADAR_CHANNELS}
        # Walk the lidar chain from the first sample: one sample_data per original frame.
        sd = nusc.get("sample_data", sample["data"][LIDAR_CHANNEL])
        for f in orig:
            assert sd["timestamp"] == f.timestamp and sd["is_key_frame"] == f.is_keyframe
            pc = LidarPointCloud.from_file(os.path.join(nusc.dataroot, sd["filename"]))
            np.testing.assert_array_equal(pc.points.T, f.lidar.points[:, :4])
            pose = nusc.get("ego_pose", sd["ego_pose_token"])
            np.testing.assert_allclose(pose["translation"], f.ego_pose.translation, atol=1e-9)
            np.testing.assert_allclose(pose["rotation"], f.ego_pose.quaternion(), atol=1e-12)
            cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
            np.testing.assert_allclose(cs["translation"], f.lidar.sensor_to_ego.translation)
            sd = nusc.get("sample_data", sd["next"]) if sd["next"] else None
        assert sd is None
        # Radar: every sweep of every channel, in order, unfiltered and with the default filters.
        for ch in RADAR_CHANNELS:
            sweeps = [s for f in orig for s in f.radar[ch]]
            sd = nusc.get("sample_data", sample["data"][ch])
            while sd["prev"]:
                sd = nusc.get("sample_data", sd["prev"])
            for s in sweeps:
                assert (
                    sd["timestamp"] == s.timestamp
                    and nusc.get(
                        "sensor",
                        nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])[
                            "sensor_token"
                        ],
                    )["channel"]
                    == ch
                )
                path = os.path.join(nusc.dataroot, sd["filename"])
                pc = RadarPointCloud.from_file(path, **ALL_STATES)
                names = [f[0] for f in RADAR_PCD_FIELDS]
                got = np.stack([pc.points[names.index(n)] for n in RADAR_COLUMNS], axis=1).astype(
                    np.float32
                )
                np.testing.assert_array_equal(got, s.points)
                # The devkit's default filters act on the fields we wrote, at the right places.
                default = RadarPointCloud.from_file(path)
                p = s.points
                keep = (
                    (p[:, radar_column("invalid_state")] == 0)
                    & (p[:, radar_column("dyn_prop")] <= 6)
                    & (p[:, radar_column("ambig_state")] == 3)
                )
                assert default.points.shape[1] == int(keep.sum())
                np.testing.assert_array_equal(default.points[0].astype(np.float32), p[keep, 0])
                pose = nusc.get("ego_pose", sd["ego_pose_token"])
                np.testing.assert_allclose(pose["translation"], s.ego_pose.translation, atol=1e-9)
                sd = nusc.get("sample_data", sd["next"]) if sd["next"] else None
            assert sd is None


def test_our_loader_yields_the_original_frames(written):
    root, frames = written
    scenes = load_nuscenes(root, VERSION, split="train")
    assert [s.name for s in scenes] == ["sim-000003"]
    orig = frames["sim-000003"]
    assert len(scenes[0]) == len(orig)
    for fo, fl in zip(orig, scenes[0]):
        assert (fl.index, fl.timestamp, fl.is_keyframe, fl.scene) == (
            fo.index,
            fo.timestamp,
            fo.is_keyframe,
            fo.scene,
        )
        assert fl.occupancy is None
        np.testing.assert_array_equal(fl.lidar.points, fo.lidar.points)
        np.testing.assert_allclose(fl.ego_pose.matrix(), fo.ego_pose.matrix(), atol=1e-9)
        np.testing.assert_allclose(
            fl.lidar.sensor_to_ego.matrix(), fo.lidar.sensor_to_ego.matrix(), atol=1e-12
        )
        for ch in RADAR_CHANNELS:
            assert [s.timestamp for s in fl.radar[ch]] == [s.timestamp for s in fo.radar[ch]]
            for sl, so in zip(fl.radar[ch], fo.radar[ch]):
                np.testing.assert_array_equal(sl.points, so.points)  # unfiltered, bit-exact float32
                np.testing.assert_allclose(sl.ego_pose.matrix(), so.ego_pose.matrix(), atol=1e-9)
                np.testing.assert_allclose(
                    sl.sensor_to_ego.matrix(), so.sensor_to_ego.matrix(), atol=1e-12
                )


def test_splits_and_the_one_metre_rule(written):
    root, _ = written
    assert load_nuscenes(root, VERSION, split="val") == []  # its only scene never moves 1 m
    kept = load_nuscenes(root, VERSION, split="val", min_travel_m=0.0)
    assert [s.name for s in kept] == ["sim-000004"] and kept[0].travel_m() < 1.0
    assert {s.name for s in load_nuscenes(root, VERSION, split=None)} == {"sim-000003"}
    splits = nuscenes_splits(root, VERSION)
    assert (
        splits["train"] == ["sim-000003"] and len(splits["mini_val"]) == 2
    )  # official lists are there too
    with pytest.raises(ValueError, match="unknown split 'bogus'"):
        load_nuscenes(root, VERSION, split="bogus")
    with pytest.raises(ValueError, match="mini_train"):
        load_nuscenes(root, VERSION, split="mini_train")  # official names, none of them here
    with pytest.raises(ValueError, match="not in"):
        load_nuscenes(root, VERSION, split=None, scene_names=["scene-0001"])


def test_missing_data_says_what_to_download(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nuscenes.org/download.*scene\.json"):
        load_nuscenes(tmp_path / "nowhere", "v1.0-trainval")
    (tmp_path / "v1.0-mini").mkdir()
    with pytest.raises(
        FileNotFoundError, match=r"v1\.0-trainval.*found \['v1\.0-mini'\].*download"
    ):
        load_nuscenes(tmp_path, "v1.0-trainval")


def test_missing_devkit_says_how_to_install(written, monkeypatch):
    root, _ = written
    monkeypatch.setitem(sys.modules, "nuscenes.nuscenes", None)
    with pytest.raises(NuScenesError, match=re.escape(evgrid.install_hint("nuscenes"))):
        load_nuscenes(root, VERSION, split=None)


def test_existing_database_is_not_overwritten_silently(written):
    root, _ = written
    with pytest.raises(FileExistsError, match="already holds"):
        write_nuscenes([], root, VERSION)


def test_radar_pcd_header_and_empty_sweep(tmp_path):
    path = tmp_path / "empty.pcd"
    write_radar_pcd(path, np.zeros((0, len(RADAR_COLUMNS)), np.float32))
    header = path.read_bytes().split(b"DATA binary\n")[0].decode().splitlines()
    assert header[0].startswith("#") and header[1] == "VERSION 0.7"
    assert header[2] == "FIELDS " + " ".join(f[0] for f in RADAR_PCD_FIELDS)
    assert header[3] == "SIZE 4 4 4 1 2 4 4 4 4 4 1 1 1 1 1 1 1 1"
    assert header[4] == "TYPE F F F I I F F F F F I I I I I I I I"
    assert RadarPointCloud.from_file(str(path), **ALL_STATES).points.shape == (18, 0)
    assert len(read_radar_pcd(path)) == 0
    pts = np.zeros((3, len(RADAR_COLUMNS)), np.float32)
    pts[:, 0] = [1.5, -2.25, 70.0]
    pts[:, radar_column("rcs")] = [-5.5, 0.0, 12.5]
    pts[:, radar_column("invalid_state")] = [0, 6, 17]
    write_radar_pcd(tmp_path / "three.pcd", pts)
    rec = read_radar_pcd(tmp_path / "three.pcd")
    np.testing.assert_array_equal(rec["x"], pts[:, 0])
    np.testing.assert_array_equal(rec["id"], [0, 1, 2])
    assert json.dumps(rec["invalid_state"].tolist()) == "[0, 6, 17]"


def test_same_seed_writes_the_same_files(tmp_path):
    cfg = SimConfig(duration_s=0.6)
    for d in ("a", "b"):
        write_nuscenes([simulate_scene(21, cfg)], tmp_path / d, VERSION)
    files = sorted(
        p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file()
    )
    assert len(files) > 20
    for f in files:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f


def test_the_doppler_cue_reads_the_same_from_the_nuscenes_layout(written):
    # the radar's compensated Doppler columns come back as written: the dynamic score's Doppler
    # cue (docs/equations.md#the-doppler-cue) is the same from either source
    from evgrid.config import MapperConfig
    from evgrid.doppler import moving_detections
    from evgrid.geometry import SE3
    from evgrid.mapper import OccupancyMapper

    root, frames = written
    scene = load_nuscenes(root, VERSION, split="train")[0]
    cfg = MapperConfig(maps=("ray_ilm",))
    loaded, original = OccupancyMapper(cfg), OccupancyMapper(cfg)
    n_moving = 0
    for fl, fo in zip(scene, frames["sim-000003"]):
        loaded.process(fl)
        original.process(fo)
        sweeps = [s for ch in fl.radar for s in fl.radar[ch]]
        n_moving += len(moving_detections(sweeps, SE3.identity(), cfg.dynamic.doppler_mps))
    assert n_moving > 0
    box = original.maps["ray_ilm"].bounds()
    np.testing.assert_allclose(
        loaded.maps["ray_ilm"].read_dynamic(*box),
        original.maps["ray_ilm"].read_dynamic(*box),
        atol=1e-5,
    )
