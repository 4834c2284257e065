"""Long drives and odometry glitches: pose sanity, and per-frame work that does not grow with the
drive."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from evgrid.config import MapperConfig, OutputConfig, PoseLimits
from evgrid.geometry import SE3
from evgrid.mapper import OccupancyMapper, PoseError
from evgrid.observers import GifRecorder, SceneScores, TruthTracker
from evgrid.runs import map_scene
from evgrid_sim import SimConfig, simulate_scene

ILM_ONLY = MapperConfig(maps=("ray_ilm",))


@pytest.fixture(scope="module")
def scene():
    return list(simulate_scene(5, SimConfig(duration_s=2.0)))


def _moved(frame, dx: float, sweeps: bool = True):
    """``frame`` with its ego pose (and its sweeps' poses) shifted ``dx`` metres along x."""
    shift = SE3(np.eye(3), np.array([dx, 0.0, 0.0]))
    if not sweeps:
        return dataclasses.replace(frame, ego_pose=shift @ frame.ego_pose)
    lidar = dataclasses.replace(frame.lidar, ego_pose=shift @ frame.lidar.ego_pose)
    radar = {
        ch: tuple(dataclasses.replace(s, ego_pose=shift @ s.ego_pose) for s in sw)
        for ch, sw in frame.radar.items()
    }
    return dataclasses.replace(frame, ego_pose=shift @ frame.ego_pose, lidar=lidar, radar=radar)


def _map(frames, config=ILM_ONLY):
    mapper = OccupancyMapper(config)
    for f in frames:
        mapper.process(f)
    return mapper


def test_a_pose_jump_of_1_km_is_skipped_and_reported(scene, caplog):
    bad = len(scene) // 2
    frames = [(_moved(f, 1000.0) if f.index == bad else f) for f in scene]
    with caplog.at_level(logging.WARNING, logger="evgrid.mapper"):
        glitched = _map(frames)
    clean = _map(scene)
    assert glitched.poses.n_jumps == 1 and glitched.counts()["frames_pose_jump"] == 1
    assert glitched.poses.jumps[0]["timestamp"] == scene[bad].timestamp
    assert glitched.poses.jumps[0]["jump_m"] == pytest.approx(1000.0, abs=5.0)
    assert any(str(scene[bad].timestamp) in r.getMessage() for r in caplog.records)
    # the map never spans the glitch: same extent as without it, not a 1 km bounding box
    m, ref = glitched.maps.maps["ray_ilm"], clean.maps.maps["ray_ilm"]
    assert set(m.tiles) <= set(ref.tiles)
    assert m.covered_bounds()[2:] == ref.covered_bounds()[2:]


@pytest.mark.parametrize(
    "where", [1e9, 1e19, 1e30]
)  # non-finite poses never get this far: SE3 refuses them
def test_absurd_poses_are_errors_naming_the_record(scene, where):
    frames = [(_moved(f, where, sweeps=False) if f.index == 3 else f) for f in scene]
    with pytest.raises(PoseError, match=rf"frame 3 \(t = {scene[3].timestamp} us\)"):
        _map(frames)


def test_a_jump_that_never_comes_back_is_an_error(scene):
    frames = [(_moved(f, 500.0) if f.index >= 5 else f) for f in scene]
    with pytest.raises(
        PoseError, match=f"jumped at t = {scene[4].timestamp} us and has not come back within 0.5 s"
    ):
        _map(frames, dataclasses.replace(ILM_ONLY, poses=PoseLimits(max_glitch_s=0.5)))


def test_the_speed_bound_is_configurable(scene):
    # the simulated vehicle drives at city speed: a 1 m/s bound makes its motion a run of glitches
    slow = dataclasses.replace(
        ILM_ONLY, poses=PoseLimits(max_speed_mps=1.0, slack_m=0.0, max_glitch_s=100.0)
    )
    assert _map(scene, slow).poses.n_jumps > 0
    assert _map(scene).poses.n_jumps == 0


def test_stale_frames_and_radar_sweeps_with_bad_poses_are_dropped(scene):
    frames = list(scene)
    frames.insert(6, frames[5])  # the same timestamp again
    f = frames[8]
    ch = next(iter(f.radar))
    bad = tuple(
        dataclasses.replace(s, ego_pose=SE3(np.eye(3), np.array([2000.0, 0, 0])) @ s.ego_pose)
        for s in f.radar[ch]
    )
    frames[8] = dataclasses.replace(f, radar={**f.radar, ch: bad})
    counts = _map(frames).counts()
    assert counts["frames_stale"] == 1
    assert counts["radar_sweeps_bad_pose"] == len(bad) > 0


def test_keyframe_scores_recount_only_the_tiles_the_vehicle_touched(scene):
    """Scoring at a keyframe costs the tiles changed since the last one, never the whole map."""
    from evgrid.evaluate import tile_keys

    mapper = OccupancyMapper(MapperConfig(maps=("ray_ilm", "ray_irm"), tile_cells=32))
    truth = TruthTracker(mapper.config.grid, 32)
    scores = SceneScores(mapper.maps.maps, truth)
    recounted: set = set()
    count = scores.vs_ref._count
    scores.vs_ref._count = lambda k: (recounted.add(k), count(k))[1]
    touched: set = set()

    class Touched:
        def on_update(self, u):
            touched.update(tile_keys(u.maps.maps["ray_ilm"], *u.box))

    mapper.observers += [Touched(), truth, scores]
    checked = 0
    for f in scene:
        mapper.process(f)
        if f.is_keyframe and f.index:
            assert recounted and recounted <= touched
            checked += 1
            recounted.clear()
            touched.clear()
    assert checked >= 3
    # the vehicle drove off the first tiles: a dense recount would have touched them (the
    # update boxes are axis-aligned in the map frame, so on a diagonal heading they also
    # reach tiles that were never created; those are no recount)
    tiles = mapper.maps.maps["ray_ilm"].tiles
    assert len(tiles) > len(touched & tiles.keys())


def test_the_gif_keeps_a_bounded_number_of_frames(scene):
    gif = GifRecorder(MapperConfig().grid, window_m=20.0, step=16, max_frames=4)
    mapper = OccupancyMapper(ILM_ONLY, observers=(gif,))
    for f in scene:
        mapper.process(
            dataclasses.replace(f, is_keyframe=True)
        )  # every frame a keyframe: 40 GIF candidates
    assert 2 <= len(gif.frames) < 4
    assert gif.frames[0].shape == gif.frames[-1].shape


def test_metrics_report_per_frame_time_by_tenth_and_the_map_area(scene, tmp_path):
    res = map_scene(iter(scene), tmp_path / "out", ILM_ONLY, OutputConfig(figures=False), name="s")
    fm = res.metrics["frame_ms"]
    assert fm["first_tenth_mean"] > 0 and fm["last_tenth_mean"] > 0 and fm["p95"] >= fm["median"]
    assert 0 < res.metrics["map_area_km2"] < 0.1
