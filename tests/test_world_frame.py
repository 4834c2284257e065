"""Maps built in the recording's fixed frame (MapperConfig.frame = "world", the default) and
in the first pose's frame ("first_pose", the paper's figures); far from the frame's origin."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from evgrid.config import ConfigError, MapperConfig, OutputConfig, RunConfig
from evgrid.geometry import SE2, SE3
from evgrid.grid import load_map, save_map, warp_window, window_affine
from evgrid.mapper import OccupancyMapper
from evgrid.runs import map_scene
from evgrid.sources import BagSource, NuScenesSource, SimSource, fixed_frame_of
from evgrid_sim import SimConfig, simulate_scene

MAPS = ("ray_ilm", "ray_irm")
#: 1e7 m along x and -1e7 m along y: a whole number of 0.078125 m cells (1.28e8), so the maps
#: of the translated drive are those at the origin moved by whole cells.
FAR = (1e7, -1e7)


def _yawed(yaw: float, x: float, y: float) -> SE3:
    c, s = math.cos(yaw), math.sin(yaw)
    return SE3(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.array([x, y, 0.0]))


def _moved(pose: SE3, dx: float, dy: float) -> SE3:
    return SE3(pose.rotation, pose.translation + np.array([dx, dy, 0.0]))


def _translated(frames, dx: float, dy: float):
    """The same drive with every pose (frame, lidar and radar sweeps) moved by (dx, dy)."""
    for f in frames:
        radar = {
            ch: tuple(dataclasses.replace(s, ego_pose=_moved(s.ego_pose, dx, dy)) for s in sweeps)
            for ch, sweeps in f.radar.items()
        }
        lidar = dataclasses.replace(f.lidar, ego_pose=_moved(f.lidar.ego_pose, dx, dy))
        yield dataclasses.replace(f, ego_pose=_moved(f.ego_pose, dx, dy), lidar=lidar, radar=radar)


def _mapped(frames, **config) -> OccupancyMapper:
    mapper = OccupancyMapper(MapperConfig(maps=MAPS, **config))
    for f in frames:
        mapper.process(f)
    return mapper


@pytest.fixture(scope="module")
def scene():
    return list(simulate_scene(2, SimConfig(duration_s=1.0)))


def test_runs_map_in_the_fixed_frame_by_default_and_first_pose_stays_selectable():
    assert MapperConfig().frame == "world"
    assert MapperConfig(frame="first_pose").frame == "first_pose"
    with pytest.raises(ValueError, match="frame"):
        MapperConfig(frame="map")
    back = RunConfig.from_dict(RunConfig(MapperConfig(frame="first_pose")).to_dict())
    assert back.mapper.frame == "first_pose"


def test_pose_in_map_is_the_planar_ego_pose_in_world_and_relative_in_first_pose():
    first, later = _yawed(0.7, 1234.5, -987.25), _yawed(-0.2, 1240.0, -980.0)
    world = OccupancyMapper(MapperConfig(maps=("ray_ilm",)))
    assert world.pose_in_map(first) == first.to_se2()
    p = world.pose_in_map(later)
    assert (p.x, p.y, p.yaw) == (1240.0, -980.0, pytest.approx(-0.2))
    assert world.first_pose is first  # kept either way: where the drive began
    rel = OccupancyMapper(MapperConfig(maps=("ray_ilm",), frame="first_pose"))
    p0 = rel.pose_in_map(first)
    assert (p0.x, p0.y, p0.yaw) == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    p1 = rel.pose_in_map(later)
    expect = (first.inverse() @ later).to_se2()
    assert (p1.x, p1.y, p1.yaw) == pytest.approx((expect.x, expect.y, expect.yaw), abs=1e-9)


def test_world_and_first_pose_maps_agree_up_to_the_first_pose(scene):
    """The trajectory of the world-frame run is the first-pose trajectory placed at the first
    ego pose in the fixed frame."""
    world, first = _mapped(scene), _mapped(scene, frame="first_pose")
    p0 = scene[0].ego_pose.to_se2()
    for (xw, yw, aw), (xf, yf, af) in zip(world.trajectory, first.trajectory):
        placed = p0 @ SE2(xf, yf, af)
        assert (xw, yw) == pytest.approx((placed.x, placed.y), abs=1e-6)
        assert math.remainder(aw - placed.yaw, math.tau) == pytest.approx(0.0, abs=1e-9)


def test_a_drive_1e7_m_from_the_origin_gives_the_masses_of_the_drive_at_the_origin(scene):
    """Far from the origin the warp (window_affine, tile keys) keeps its precision: the maps
    of the translated drive equal those at the origin, moved by whole cells."""
    near = _mapped(scene)
    far = _mapped(list(_translated(scene, *FAR)))
    res = near.config.grid.resolution
    d_r, d_c = round(-FAR[0] / res), round(-FAR[1] / res)  # map rows run towards -x
    assert (d_r, d_c) == (-128_000_000, 128_000_000)
    for name in MAPS:
        a, b = near.maps[name], far.maps[name]
        r0, c0, h, w = a.covered_bounds()
        assert h > 0 and b.covered_bounds() == (r0 + d_r, c0 + d_c, h, w)
        ma, ca = a.read(r0, c0, h, w)
        mb, cb = b.read(r0 + d_r, c0 + d_c, h, w)
        assert np.array_equal(ca, cb)
        np.testing.assert_allclose(mb, ma, atol=2e-5, err_msg=name)
        assert np.abs(ma[..., :2]).max() > 0.1  # the maps hold evidence, not only vacuous mass


def test_the_warp_window_far_away_is_the_window_near_the_origin_moved():
    from evgrid.geometry import GridSpec

    grid = GridSpec()
    near, far = SE2(3.3, -1.7, 0.4), SE2(3.3 + FAR[0], -1.7 + FAR[1], 0.4)
    d_r, d_c = -128_000_000, 128_000_000
    r0, c0, h, w = warp_window(grid, near)
    assert warp_window(grid, far) == (r0 + d_r, c0 + d_c, h, w)
    a = window_affine(grid, near, r0, c0)
    b = window_affine(grid, far, r0 + d_r, c0 + d_c)
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-6)


def test_a_map_1e7_m_away_saves_and_loads(tmp_path, scene):
    far = _mapped(list(_translated(scene[:3], *FAR)))
    m = far.maps["ray_ilm"]
    back = load_map(save_map(m, tmp_path / "far.npz"))
    assert back.covered_bounds() == m.covered_bounds()
    r0, c0, h, w = m.covered_bounds()
    np.testing.assert_array_equal(back.read(r0, c0, h, w)[0], m.read(r0, c0, h, w)[0])


def test_sources_name_their_fixed_frame(tmp_path):
    assert SimSource((0,)).fixed_frame() == "world"
    assert NuScenesSource(str(tmp_path)).fixed_frame() == "global"
    rig = tmp_path / "rig.yaml"
    rig.write_text("world_frame: map_enu\nlidar:\n  topic: /points\n")
    assert BagSource((str(tmp_path / "x.mcap"),), str(rig)).fixed_frame() == "map_enu"
    assert fixed_frame_of(None, object()) == "world"  # a scene of no source: the simulator's


def _yaml_origin(path) -> tuple[float, float, float]:
    for line in path.read_text().splitlines():
        if line.startswith("origin:"):
            return tuple(float(v) for v in line.split("[")[1].split("]")[0].split(","))
    raise AssertionError(f"no origin in {path}")


def test_nav2_export_in_world_coordinates_and_the_first_pose_frame(tmp_path, scene):
    """With frame world the nav2 origin is in the recording's fixed frame (near the drive);
    with first_pose it is near 0 and the YAML says where the first pose lies."""
    outputs = OutputConfig(figures=False, convergence=False, exports=("nav2",))
    frames = list(_translated(scene[:4], 5000.0, -2500.0))
    x0, y0 = frames[0].ego_pose.translation[:2]
    map_scene(frames, tmp_path / "w", MapperConfig(maps=("ray_ilm",)), outputs, name="s")
    ox, oy, oyaw = _yaml_origin(tmp_path / "w" / "nav2" / "map.yaml")
    assert abs(ox - x0) < 30 and abs(oy - y0) < 30 and oyaw == 0.0
    assert (
        "map frame 'world'; the recording's fixed frame 'world'"
        in (tmp_path / "w" / "nav2" / "map.yaml").read_text()
    )
    cfg = MapperConfig(maps=("ray_ilm",), frame="first_pose")
    map_scene(frames, tmp_path / "f", cfg, outputs, name="s", fixed_frame="odom")
    ox, oy, _ = _yaml_origin(tmp_path / "f" / "nav2" / "map.yaml")
    assert abs(ox) < 30 and abs(oy) < 30
    text = (tmp_path / "f" / "nav2" / "map.yaml").read_text()
    assert "map frame 'map'; the recording's fixed frame 'odom'" in text


def _topics(path) -> dict[str, list]:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, ch, _, msg in reader.iter_decoded_messages():
            out.setdefault(ch.topic, []).append(msg)
    return out


def test_mcap_in_world_has_no_tf_and_first_pose_links_map_to_the_fixed_frame(tmp_path, scene):
    pytest.importorskip("mcap_ros2")
    outputs = OutputConfig(figures=False, convergence=False, exports=("mcap",))
    frames = list(_translated(scene[:4], *FAR))
    map_scene(frames, tmp_path / "w", MapperConfig(maps=("ray_ilm",)), outputs, name="s")
    topics = _topics(tmp_path / "w" / "s.mcap")
    assert "/tf" not in topics  # map frame == fixed frame: nothing to link
    grid = topics["/evgrid/ray_ilm/occupancy"][-1]
    assert grid.header.frame_id == "world"
    x0, y0 = frames[0].ego_pose.translation[:2]
    o = grid.info.origin.position
    assert abs(o.x - x0) < 60 and abs(o.y - y0) < 60  # world coordinates, 1e7 m out
    ego = topics["/evgrid/ego_pose"][0].pose.position
    assert (ego.x, ego.y) == pytest.approx((x0, y0), abs=1e-6)
    cfg = MapperConfig(maps=("ray_ilm",), frame="first_pose")
    map_scene(frames, tmp_path / "f", cfg, outputs, name="s", fixed_frame="odom")
    tf = _topics(tmp_path / "f" / "s.mcap")["/tf"]
    (t,) = tf[0].transforms
    assert (t.header.frame_id, t.child_frame_id) == ("map", "odom")  # never a 2nd base_link parent


def test_an_old_config_with_export_window_m_is_refused_naming_the_field():
    with pytest.raises(ConfigError, match=r"outputs\.export_window_m .*outputs\.mcap\.window_m"):
        RunConfig.from_dict({"outputs": {"export_window_m": 100.0}})
