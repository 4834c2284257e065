"""Exports (evgrid.export): map_server's PGM + YAML, MCAP for Foxglove, rerun recordings."""

from __future__ import annotations

import re
import sys

import numpy as np
import pytest

import evgrid
from evgrid.config import MapperConfig
from evgrid.export import FORMATS, export_map, make_observer
from evgrid.export.mcap import DYNAMIC_STEP, LAYERS, McapParams
from evgrid.export.nav2 import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    Nav2Thresholds,
    classify,
    occupancy_values,
    read_nav2,
    write_nav2,
)
from evgrid.geometry import SE2, GridSpec
from evgrid.grid import EvidentialMap
from evgrid.mapper import OccupancyMapper
from evgrid_sim import SimConfig, simulate_scene

O, F, U = OCCUPIED, FREE, UNKNOWN  # noqa: E741 (reads as the map it checks)


def _three_by_three() -> EvidentialMap:
    """Map cells R, C in 0..2 (rows towards -x, columns towards -y), 0.1 m cells."""
    m = EvidentialMap(GridSpec(8, 0.8), tile_cells=8)
    masses = np.array(
        [
            [
                [0.0, 0.9, 0.1],
                [0.9, 0.0, 0.1],
                [0.1, 0.3, 0.6],
            ],  # P(occ) .95 occ, .05 free, m_u .6 > .5 unknown
            [
                [0.3, 0.4, 0.3],
                [0.7, 0.1, 0.2],
                [0.8, 0.05, 0.15],
            ],  # .55 unknown, .2 unknown (>= .196), .125 free
            [[0.0, 0.6, 0.4], [0.25, 0.45, 0.3], [0.05, 0.7, 0.25]],  # .8 occ, .6 unknown, .825 occ
        ],
        dtype=np.float32,
    )
    tile = m.tile((0, 0))[0]
    tile[:3, :3] = masses
    m.covered_tiles[(0, 0)][:3, :3] = True
    return m


def test_nav2_hand_computed_three_by_three(tmp_path):
    pytest.importorskip("yaml")
    m = _three_by_three()
    pgm, yml = write_nav2(m, tmp_path / "map")
    assert (pgm.name, yml.name) == ("map.pgm", "map.yaml")
    # image rows top-down: row p is map column C = p (largest y first); image column q is map
    # row R = 2 - q (smallest x first)
    raw = pgm.read_bytes()
    assert raw.startswith(b"P5\n3 3\n255\n")
    image = np.frombuffer(raw[-9:], np.uint8).reshape(3, 3)
    np.testing.assert_array_equal(image, [[0, 205, 0], [205, 205, 254], [0, 254, 205]])
    data, res, origin = read_nav2(yml)  # map_server's trinary rule; OccupancyGrid rows bottom-up
    np.testing.assert_array_equal(data, [[O, F, U], [U, U, F], [O, U, O]])
    assert res == 0.1
    assert origin == pytest.approx((-0.3, -0.3, 0.0))  # outer corner of the lower-left pixel
    # the lower-left cell (i = 0, j = 0) is centred at x = y = -0.25 m: map cell R = C = 2
    assert m.grid.map_xy_to_cell(-0.25, -0.25) == (2, 2)
    text = yml.read_text()
    for key in (
        "image: map.pgm",
        "mode: trinary",
        "negate: 0",
        "occupied_thresh: 0.65",
        "free_thresh: 0.196",
    ):
        assert key in text


def test_classify_thresholds():
    m = np.array([[0.0, 0.6, 0.4], [0.5, 0.0, 0.5], [0.0, 0.3, 0.7]], np.float32)
    np.testing.assert_array_equal(classify(m), [O, U, U])  # .8 occ; P .25 unknown; m_u .7 unknown
    np.testing.assert_array_equal(
        classify(m, th=Nav2Thresholds(free_thresh=0.3, unknown_mass=0.8)), [O, F, U]
    )
    np.testing.assert_array_equal(classify(m, covered=np.array([False, True, True])), [U, U, U])
    with pytest.raises(ValueError, match="free_thresh"):
        Nav2Thresholds(occupied_thresh=0.2, free_thresh=0.3)
    with pytest.raises(ValueError, match="no observed cell"):
        write_nav2(EvidentialMap(GridSpec(8, 0.8), 8), "/nonexistent/x")


def test_occupancy_values_agree_with_the_nav2_classes_at_the_thresholds():
    rng = np.random.default_rng(0)
    e = rng.random((200_000, 2)) * rng.choice([0.5, 5, 50], (200_000, 1))
    s = 2 + e.sum(-1)
    m = np.stack([e[:, 0] / s, e[:, 1] / s, 2 / s], -1).astype(np.float32)
    # cells right at the thresholds, where rounding 100 P(occ) used to disagree (20 and 65)
    edge = np.array(
        [[0.0, 0.301, 0.699 - 0.35], [0.604, 0.0, 0.396], [0.0, 0.3, 0.4], [0.6, 0.0, 0.4]],
        np.float32,
    )
    edge[:, 2] = 1 - edge[:, 0] - edge[:, 1]
    m = np.concatenate([m, edge])
    for th in (Nav2Thresholds(), Nav2Thresholds(0.57, 0.2, 0.6), Nav2Thresholds(0.905, 0.05, 0.3)):
        cls = classify(m, th=th)
        for mode in ("trinary", "scale"):
            v = occupancy_values(m, th=th, mode=mode)
            p = v / 100.0  # a consumer's reading of the OccupancyGrid at the same thresholds
            back = np.where(p > th.occupied_thresh, OCCUPIED, np.where(p < th.free_thresh, FREE, 0))
            back = np.where(v == -1, UNKNOWN, back)
            np.testing.assert_array_equal(back, cls)
        scale = occupancy_values(m, th=th, mode="scale")
        want = np.clip(np.rint(100 * (m[:, 1] + 0.5 * m[:, 2])), 0, 100)
        known = cls != UNKNOWN
        assert known.sum() > 1000
        assert np.abs(scale[known] - want[known]).max() <= 1  # shade kept, moved at most 1
    assert set(np.unique(occupancy_values(m))) <= {FREE, OCCUPIED, UNKNOWN}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A short mapped scene with the MCAP and rerun observers attached."""
    pytest.importorskip("rosbags")
    pytest.importorskip("mcap")
    out = tmp_path_factory.mktemp("run")
    obs = [
        make_observer("mcap", out / "run.mcap"),  # the defaults
        make_observer(
            "mcap",
            out / "full.mcap",
            McapParams(layers=("occupancy", *LAYERS), occupancy_values="scale", maps=("ray_ilm",)),
        ),
        make_observer("nav2", out / "nav2", maps=("ray_ilm",)),
        make_observer("mcap", out / "dynamic.mcap", McapParams(layers=("dynamic",), window_m=0)),
    ]
    try:
        import rerun  # noqa: F401

        obs.append(make_observer("rerun", out / "run.rrd"))
    except ImportError:
        pass
    mapper = OccupancyMapper(
        MapperConfig(maps=("ray_ilm", "ray_irm", "fused")), observers=tuple(obs)
    )
    frames = list(simulate_scene(2, SimConfig(duration_s=1.0)))
    for f in frames:
        mapper.process(f)
    for o in obs:
        o.close()
    return mapper, frames, out


def _decoded(path, start_ns: int = 0):
    """Messages from ``start_ns`` on, decoded by mcap-ros2-support (pure Python: slow on big
    grids)."""
    pytest.importorskip("mcap_ros2")
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        return [
            (ch.topic, schema.name, msg.log_time, dec)
            for schema, ch, msg, dec in reader.iter_decoded_messages(starting_at=start_ns)
        ]


def _topic_counts(path) -> dict[str, int]:
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    return {
        summary.channels[k].topic: n for k, n in summary.statistics.channel_message_counts.items()
    }


def test_mcap_run_reads_back_with_the_reference_reader(run):
    mapper, frames, out = run
    counts = _topic_counts(out / "run.mcap")
    assert counts["/tf"] == counts["/evgrid/ego_pose"] == mapper.n_updates
    assert counts["/evgrid/path"] == 1
    msgs = _decoded(
        out / "run.mcap", frames[-2].timestamp * 1000
    )  # the last pose (updates: every other frame), final maps
    tfs = [d for t, _, _, d in msgs if t == "/tf"]
    tr = tfs[-1].transforms[0]
    # the map frame is a parent of the recording's fixed frame, not of base_link
    assert (tr.header.frame_id, tr.child_frame_id) == ("map", "odom")
    # map -> odom, then the recording's odom -> base_link, is the ego pose in the map
    t = tr.transform
    yaw = 2 * np.arctan2(t.rotation.z, t.rotation.w)
    fixed = SE2(t.translation.x, t.translation.y, yaw)
    stamp = tr.header.stamp
    by_ns = {f.timestamp * 1000: f for f in frames}
    last = by_ns[stamp.sec * 10**9 + stamp.nanosec]
    ego = fixed @ last.ego_pose.to_se2()
    x, y, yaw = mapper.trajectory[-1]
    assert (ego.x, ego.y) == pytest.approx((x, y), abs=1e-6)
    assert ego.yaw == pytest.approx(yaw, abs=1e-9)
    n_kf = sum(f.is_keyframe for f in frames)
    for name, m in mapper.maps.maps.items():
        # the navigation map (fused: no nav map here) at each keyframe, every map at close()
        assert counts[f"/evgrid/{name}/occupancy"] == (n_kf + 1 if name == "fused" else 1)
        assert f"/evgrid/{name}/grid_map" not in counts  # no GridMap by default
        (g,) = [d for t, s, _, d in msgs if t == f"/evgrid/{name}/occupancy"]
        r0, c0, h, w = m.covered_bounds()
        res = m.grid.resolution
        assert (g.info.width, g.info.height, g.info.resolution) == (h, w, res)
        assert (g.info.origin.position.x, g.info.origin.position.y) == pytest.approx(
            (-(r0 + h) * res, -(c0 + w) * res)
        )
        masses, cov = m.read(r0, c0, h, w)
        data = np.asarray(g.data, dtype=np.int8).reshape(w, h)  # rows along +y, columns along +x
        # cell (i, j) is map cell R = r0 + h - 1 - i, C = c0 + w - 1 - j; trinary values
        np.testing.assert_array_equal(data, classify(masses, cov)[::-1, ::-1].T)


def test_mcap_metadata_places_the_map_in_the_fixed_frame(run):
    from mcap.reader import make_reader

    _, frames, out = run
    with open(out / "run.mcap", "rb") as fh:
        (meta,) = [m for m in make_reader(fh).iter_metadata() if m.name == "evgrid"]
    d = meta.metadata
    assert (d["map_frame"], d["fixed_frame"]) == ("map", "odom")
    xyz = [float(v) for v in d["first_pose_xyz"].split()]
    np.testing.assert_allclose(xyz, frames[0].ego_pose.translation)
    q = [float(v) for v in d["first_pose_quaternion_wxyz"].split()]
    np.testing.assert_allclose(q, frames[0].ego_pose.quaternion())


def test_mcap_grid_map_layers_and_scaled_values(run):
    mapper, frames, out = run
    counts = _topic_counts(out / "full.mcap")
    n_kf = sum(f.is_keyframe for f in frames)
    assert counts["/evgrid/ray_ilm/grid_map"] == n_kf + 1
    msgs = _decoded(out / "full.mcap", frames[-2].timestamp * 1000)
    m = mapper.maps.maps["fused"]
    (g,) = [d for t, s, _, d in msgs if t == "/evgrid/fused/occupancy"]
    (gm,) = [d for t, s, _, d in msgs if t == "/evgrid/fused/grid_map"]
    r0, c0, h, w = m.covered_bounds()
    res = m.grid.resolution
    masses, cov = m.read(r0, c0, h, w)
    data = np.asarray(g.data, dtype=np.int8).reshape(w, h)
    want = occupancy_values(masses, cov, mode="scale")
    np.testing.assert_array_equal(data, want[::-1, ::-1].T)
    assert list(gm.layers) == ["m_free", "m_occupied", "m_unknown"]
    assert (gm.info.resolution, gm.info.length_x, gm.info.length_y) == (res, h * res, w * res)
    assert (gm.info.pose.position.x, gm.info.pose.position.y) == pytest.approx(
        (-(r0 + h / 2) * res, -(c0 + w / 2) * res)
    )
    for k, layer in enumerate(gm.data):
        assert [d.label for d in layer.layout.dim] == ["column_index", "row_index"]
        np.testing.assert_array_equal(
            np.asarray(layer.data, np.float32).reshape(w, h).T, masses[..., k]
        )


def test_mcap_dynamic_layer_round_trips(run):
    mapper, _, out = run
    counts = _topic_counts(out / "dynamic.mcap")
    assert not any(t.endswith("/occupancy") for t in counts)  # the GridMap alone
    msgs = {t: d for t, _, _, d in _decoded(out / "dynamic.mcap") if t.endswith("/grid_map")}
    assert set(msgs) == {f"/evgrid/{n}/grid_map" for n in mapper.maps.maps}
    scored = set(mapper.maps.dynamic_maps)
    assert scored == {"ray_ilm", "ray_irm", "fused"}  # every map of the run has a Dempster step
    called = 0
    for name, m in mapper.maps.maps.items():
        gm = msgs[f"/evgrid/{name}/grid_map"]
        assert list(gm.layers) == ["dynamic"]
        r0, c0, h, w = m.covered_bounds()
        got = np.asarray(gm.data[0].data, np.float32).reshape(w, h).T
        want = m.read_dynamic(r0, c0, h, w)
        np.testing.assert_allclose(got, want, atol=DYNAMIC_STEP / 2 + 1e-7)
        called += int((got > mapper.maps.dynamic.threshold).sum())
    assert called > 0  # the simulated scene's movers are scored

    # a map that keeps no score: NaN in every cell
    from evgrid.export.mcap import MapCells, grid_map_msg
    from evgrid.ros import typestore

    m = mapper.maps.maps["fused"]
    b = m.covered_bounds()
    gm = grid_map_msg(MapCells.read(m, b), 0, "map", typestore(2), ("m_free", "dynamic"))
    assert np.isnan(np.asarray(gm.data[1].data)).all()
    assert not np.isnan(np.asarray(gm.data[0].data)).any()
    with pytest.raises(ValueError, match="speed"):
        McapParams(layers=("occupancy", "speed"))


def test_rerun_dynamic_points_lie_on_the_cells_called_dynamic(run):
    rr = pytest.importorskip("rerun")
    mapper, _, out = run
    rec = rr.dataframe.load_recording(str(out / "run.rrd"))
    view = rec.view(index="update", contents="/final/fused/dynamic")
    (xyz,) = view.select_static().read_all().column("/final/fused/dynamic:Position3D").to_pylist()
    xyz = np.asarray(xyz, np.float64)
    m = mapper.maps.maps["fused"]
    r0, c0, h, w = m.covered_bounds()  # a small map: its picture has every cell (step 1)
    rows, cols = m.grid.map_xy_to_cell(xyz[:, 0], xyz[:, 1])
    got = set(zip(rows.tolist(), cols.tolist()))
    i, j = np.nonzero(m.read_dynamic(r0, c0, h, w) > mapper.maps.dynamic.threshold)
    assert got == set(zip((i + r0).tolist(), (j + c0).tolist())) and got


def test_rerun_recording_has_maps_isms_and_trajectory(run):
    rr = pytest.importorskip("rerun")
    _, _, out = run
    rec = rr.dataframe.load_recording(str(out / "run.rrd"))
    paths = {c.entity_path for c in rec.schema().component_columns()}
    for p in (
        "/trajectory",
        "/ego",
        "/ego/position",
        "/maps/fused",
        "/ego/isms/ray_ilm",
        "/ego/isms/ray_irm",
        "/final/fused",
        "/info",
        "/maps/fused/dynamic",  # the cells called dynamic, points in metres
        "/final/fused/dynamic",
    ):
        assert p in paths


def test_export_map_every_format(run, tmp_path):
    mapper, _, out = run
    m = mapper.maps.maps["fused"]
    files = {
        f: export_map(m, tmp_path / "fused", f)
        for f in FORMATS
        if f != "rerun" or "rerun" in sys.modules
    }
    assert [p.name for p in files["nav2"]] == ["fused.pgm", "fused.yaml"]
    # the run's nav2 observer wrote the navigation map (fused: no nav map in this run) as
    # map.pgm + map.yaml, and the map asked for beside it
    assert sorted(p.name for p in (out / "nav2").iterdir()) == [
        "map.pgm",
        "map.yaml",
        "ray_ilm.pgm",
        "ray_ilm.yaml",
    ]
    assert (out / "nav2" / "map.pgm").read_bytes() == files["nav2"][0].read_bytes()
    text = (out / "nav2" / "map.yaml").read_text()
    assert "image: map.pgm" in text and "the navigation map: 'fused'" in text
    assert "first ego pose in 'odom'" in text
    data, res, _ = read_nav2(files["nav2"][1])
    r0, c0, h, w = m.covered_bounds()
    assert data.shape == (w, h) and res == m.grid.resolution
    (grid,) = [d for t, _, _, d in _decoded(files["mcap"][0]) if t == "/evgrid/fused/occupancy"]
    # the OccupancyGrid and the nav2 map (as map_server loads it) agree on every cell
    occ = np.asarray(grid.data, np.int8).reshape(w, h)
    np.testing.assert_array_equal(occ, data)
    with pytest.raises(ValueError, match="nav2"):
        export_map(m, tmp_path / "x", "png")
    with pytest.raises(ValueError, match="rerun"):
        make_observer("gif", tmp_path / "x")


def test_missing_extras_say_how_to_install(monkeypatch):
    from evgrid.ros import require

    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(ImportError, match=re.escape(evgrid.install_hint("rerun"))):
        require("rerun", "rerun")
    monkeypatch.setitem(sys.modules, "rosbags", None)
    with pytest.raises(ImportError, match=re.escape(evgrid.install_hint("ros"))):
        require("rosbags")


def test_the_nav2_pgm_written_in_bands_is_the_whole_map_classified(tmp_path):
    """The PGM is written a tile column at a time; its pixels are those of the whole box
    classified at once and put in ROS order (map_to_occupancy), top row first."""
    from evgrid.export.nav2 import PIXEL, _read_pgm, classify_map, map_to_occupancy, write_nav2

    m = _patches()
    r0, c0, h, w = m.covered_bounds()
    cls, _ = map_to_occupancy(classify_map(m, r0, c0, h, w), r0, c0, m.grid.resolution)
    pgm, _ = write_nav2(m, tmp_path / "map")
    want = np.vectorize(PIXEL.__getitem__)(cls)[::-1]
    assert np.array_equal(_read_pgm(pgm), want.astype(np.uint8))


def _patches(seed: int = 35, tile_cells: int = 16) -> EvidentialMap:
    """Patches of random masses on both sides of the origin, across tile borders, 80 % covered."""
    from evgrid.grid import MapWindow

    rng = np.random.default_rng(seed)
    m = EvidentialMap(GridSpec(n_cells=64, length_m=6.4), tile_cells)
    for _ in range(12):
        r, c = rng.integers(-80, 80, 2)
        h, w = rng.integers(1, 50, 2)
        masses = rng.dirichlet([1, 1, 1], size=(h, w)).astype(np.float32)
        window = MapWindow(int(r), int(c), masses, rng.random((h, w)) < 0.8)
        m.apply(window, lambda view, x: view.__setitem__(slice(None), x))
    return m


@pytest.mark.parametrize("values", ["trinary", "scale"])
@pytest.mark.parametrize("frame_id", ["map", "odom_frame"])
def test_a_whole_maps_occupancy_grid_bytes_are_those_of_its_message(values, frame_id):
    """The final maps' OccupancyGrids are made straight into their CDR bytes: the same bytes as
    the message serialised (frame names of other lengths move the fields' alignment)."""
    from evgrid.export.mcap import TiledCells, occupancy_grid_cdr, occupancy_grid_msg
    from evgrid.ros import typestore

    store, th = typestore(2), Nav2Thresholds()
    for seed in (35, 36):
        m = _patches(seed)
        cells = TiledCells(m, *m.covered_bounds())
        msg = occupancy_grid_msg(cells, 1_700_000_000_123_456, frame_id, store, th, values)
        want = bytes(store.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid"))
        got = occupancy_grid_cdr(cells, 1_700_000_000_123_456, frame_id, store, th, values)
        assert bytes(got) == want


def test_the_mcap_of_whole_maps_is_the_file_the_messages_gave(tmp_path, monkeypatch):
    """Byte for byte the file written before the OccupancyGrids were made as bytes."""
    pytest.importorskip("mcap")
    import evgrid.export.mcap as mc

    maps = {"a": _patches(35), "b": _patches(36, tile_cells=32)}
    params = McapParams(occupancy_values="scale")
    new = mc.write_maps_mcap(maps, tmp_path / "new.mcap", params, stamp_us=123)

    def from_message(cells, t_us, frame_id, store, th, values, step=1):
        assert step == 1
        msg = mc.occupancy_grid_msg(cells, t_us, frame_id, store, th, values)
        return bytes(store.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid"))

    monkeypatch.setattr(mc, "occupancy_grid_cdr", from_message)
    old = mc.write_maps_mcap(maps, tmp_path / "old.mcap", params, stamp_us=123)
    assert new.read_bytes() == old.read_bytes()


def test_coarser_values_keep_every_obstacle_and_call_free_only_what_was_all_seen_free():
    """By hand: 2x2 blocks of OccupancyGrid values (trinary, and scale's shades)."""
    from evgrid.export.mcap import coarsen_values
    from evgrid.grid import coarse_step

    fine = np.array(
        [
            [0, 0, 0, -1, 100, -1, -1, -1],
            [0, 0, 0, 0, 0, 0, -1, -1],
            [10, 19, 70, 3, -1, 100, 0, 0],
            [5, 0, 0, 12, -1, -1, 0, 18],
        ],
        np.int8,
    )
    want = np.array([[0, -1, 100, -1], [19, 70, 100, 18]], np.int8)
    assert np.array_equal(coarsen_values(fine, 2, Nav2Thresholds()), want)
    assert np.array_equal(coarsen_values(fine, 1, Nav2Thresholds()), fine)
    # the smallest whole factor that fits; 0: no limit
    assert [coarse_step(h, w, 16384) for h, w in [(16384, 9), (16385, 9), (9, 22224)]] == [1, 2, 2]
    assert coarse_step(40000, 3, 16384) == 3 and coarse_step(10**6, 10**6, 0) == 1


@pytest.mark.parametrize("values", ["trinary", "scale"])
@pytest.mark.parametrize("step", [2, 3, 7])
def test_a_coarse_final_grid_lies_where_its_cells_do(values, step):
    """Every fine occupied cell's position falls in an occupied cell of the coarse message, and
    every coarse free cell holds free cells only; the bands (a tile's rows) give the same values
    as the box coarsened at once."""
    from evgrid.export.mcap import TiledCells, coarsen_values, occupancy_grid_cdr
    from evgrid.export.nav2 import _class_value_bounds
    from evgrid.grid import MapWindow
    from evgrid.ros import typestore

    store, th = typestore(2), Nav2Thresholds()
    rng = np.random.default_rng(37)
    m = EvidentialMap(GridSpec(n_cells=64, length_m=6.4), 16)
    for _ in range(6):  # free patches with obstacles, holes and shades
        r, c = rng.integers(-60, 60, 2)
        p = rng.dirichlet([30, 1, 1], size=(40, 40))
        p[rng.random((40, 40)) < 0.01] = (0.05, 0.9, 0.05)
        window = MapWindow(int(r), int(c), p.astype(np.float32), rng.random((40, 40)) < 0.99)
        m.apply(window, lambda view, x: view.__setitem__(slice(None), x))
    r0, c0, h, w = m.covered_bounds()
    res = m.grid.resolution
    buf = occupancy_grid_cdr(TiledCells(m, r0, c0, h, w), 5, "map", store, th, values, step)
    msg = store.deserialize_cdr(bytes(buf), "nav_msgs/msg/OccupancyGrid")
    H, W = -(-h // step), -(-w // step)
    assert (msg.info.width, msg.info.height) == (H, W)
    assert msg.info.resolution == pytest.approx(res * step)
    ox, oy = msg.info.origin.position.x, msg.info.origin.position.y
    assert (ox, oy) == pytest.approx((-(r0 + H * step) * res, -(c0 + W * step) * res))
    grid = np.asarray(msg.data, np.int8).reshape(W, H)  # ROS order: [j, i] along y, x
    fine = TiledCells(m, r0, c0, H * step, W * step).occupancy(th, values)
    assert np.array_equal(grid.swapaxes(0, 1)[::-1, ::-1], coarsen_values(fine, step, th))
    occ_min = _class_value_bounds(th)[1]
    rr, cc = np.nonzero(fine >= occ_min)
    x, y = -(r0 + rr + 0.5) * res, -(c0 + cc + 0.5) * res  # the cells' centres (map frame)
    i = np.floor((x - ox) / (res * step)).astype(int)
    j = np.floor((y - oy) / (res * step)).astype(int)
    assert len(rr) > 20 and np.all(grid[j, i] >= occ_min)
    jj, ii = np.nonzero((grid >= 0) & (grid < occ_min))  # coarse free cells
    assert len(jj) > 5
    for j0, i0 in zip(jj, ii):
        # the coarse cell spans x from ox + i0 * step * res: the box's fine rows from
        # (H - 1 - i0) * step (rows run towards -x), likewise columns along y
        r, c = (H - 1 - i0) * step, (W - 1 - j0) * step
        block = fine[r : r + step, c : c + step]
        assert block.shape == (step, step) and np.all((block >= 0) & (block < occ_min))


def test_the_mcap_final_map_above_final_max_side_is_written_coarser_and_says_so(tmp_path, caplog):
    pytest.importorskip("mcap")
    import logging

    from evgrid.export.mcap import write_maps_mcap
    from evgrid.grid import MapWindow

    m = EvidentialMap(GridSpec(n_cells=64, length_m=6.4), 64)
    occ = np.tile(np.array([0.0, 1.0, 0.0], np.float32), (8, 8, 1))
    for r, c in [(0, 0), (600, 0)]:  # a box of 608 by 8 cells
        m.apply(MapWindow(r, c, occ, np.ones((8, 8), bool)), lambda v, x: v.__setitem__(..., x))
    with caplog.at_level(logging.INFO, logger="evgrid.export.mcap"):
        path = write_maps_mcap({"a": m}, tmp_path / "a.mcap", McapParams(final_max_side=256))
    assert "written 3x coarser (203 x 3 cells of 0.3 m" in caplog.text
    ((topic, _, _, msg),) = [t for t in _decoded(path) if t[0].endswith("/occupancy")]
    assert (msg.info.width, msg.info.height) == (203, 3)
    assert msg.info.resolution == pytest.approx(0.3)
    full = write_maps_mcap({"a": m}, tmp_path / "b.mcap", McapParams(final_max_side=0))
    ((_, _, _, whole),) = [t for t in _decoded(full) if t[0].endswith("/occupancy")]
    assert (whole.info.width, whole.info.height) == (608, 8)


@pytest.mark.parametrize("side", [-1, 1, 255, 1.5, True, "16384"])
def test_a_final_max_side_that_means_nothing_is_refused(side):
    with pytest.raises(ValueError, match="final_max_side must be 0 .* got"):
        McapParams(final_max_side=side)


def test_a_whole_maps_occupancy_grid_takes_one_byte_a_cell_once():
    """The message of a whole map is one buffer, filled tile by tile: no copy of the box's
    values (ROS order, the message's array, its serialisation) on top of it (traced
    allocations, not the process's memory: the same on every run)."""
    import tracemalloc

    from evgrid.export.mcap import TiledCells, occupancy_grid_cdr
    from evgrid.grid import MapWindow
    from evgrid.ros import typestore

    m = EvidentialMap(GridSpec(n_cells=64, length_m=6.4), 64)
    ones = np.full((8, 8, 3), 1 / 3, np.float32)
    for r, c in [(0, 0), (1500, 0), (0, 1500), (1500, 1500)]:  # four tiles, a box of 2.3 MB
        m.apply(MapWindow(r, c, ones, np.ones((8, 8), bool)), lambda v, x: v.__setitem__(..., x))
    r0, c0, h, w = m.covered_bounds()
    store, cells = typestore(2), TiledCells(m, r0, c0, h, w)
    occupancy_grid_cdr(cells, 0, "map", store)  # the type store's first use allocates too
    tracemalloc.start()
    try:
        data = occupancy_grid_cdr(cells, 0, "map", store)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(data) > h * w == 1508 * 1508
    assert peak < 1.2 * h * w  # the buffer, and a tile's values at a time
    tracemalloc.start()
    try:
        coarse = occupancy_grid_cdr(cells, 0, "map", store, step=4)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(coarse) > 377 * 377
    assert peak < 0.25 * h * w  # 4x coarser: never the box's fine values at once


def test_the_rerun_whole_map_picture_made_in_bands_is_the_whole_map_sampled():
    from evgrid.export.rerun import _whole, quad_corners
    from evgrid.render import map_rgb, sample_map

    m = _patches()
    r0, c0, h, w = m.covered_bounds()
    for max_cells in (2048, 64, 37, 9):  # steps 1, 3, 5 and 18 (the tiles are 16 cells)
        step = -(-max(h, w) // max_cells)
        want = map_rgb(sample_map(m, r0, c0, h, w, step)[0])
        pic, corners = _whole(m, max_cells)
        assert np.array_equal(pic, want), step
        hh, ww = want.shape[:2]
        np.testing.assert_array_equal(
            corners, quad_corners(r0, c0, hh * step, ww * step, m.grid.resolution)
        )
