"""Warping local grids into the map, the tiled map, and map files (evgrid.grid)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid import mass
from evgrid.fusion import update_ray_ilm
from evgrid.geometry import SE2, GridSpec
from evgrid.grid import (
    EvidentialMap,
    MapFileError,
    MapWindow,
    Warper,
    load_map,
    save_map,
    warp_to_map,
)
from tests.strategies import random_masses

SPEC = GridSpec(64, 5.0)  # small grids keep the tests fast; the code is size-agnostic
RES = SPEC.resolution
MARK = np.array([0.7, 0.1, 0.2], np.float32)


def test_warp_of_vacuous_grid_is_vacuous():
    w = warp_to_map(mass.vacuous(SPEC.shape), SE2(1.3, -0.4, 0.77), SPEC)
    np.testing.assert_array_equal(w.masses, mass.vacuous(w.masses.shape[:2]))


def test_identity_warp_is_exact():
    local = random_masses(np.random.default_rng(0), SPEC.shape)
    w = warp_to_map(local, SE2(), SPEC)
    r = -w.r0 - SPEC.n_cells // 2  # window row of local row 0
    c = -w.c0 - SPEC.n_cells // 2
    np.testing.assert_array_equal(w.masses[r : r + 64, c : c + 64], local)
    assert w.covered[r : r + 64, c : c + 64].all()
    # everything outside the local square is vacuous
    outside = np.ones(w.shape, bool)
    outside[r : r + 64, c : c + 64] = False
    np.testing.assert_array_equal(w.masses[outside], np.tile([0, 0, 1], (outside.sum(), 1)))


def test_whole_cell_translation_is_exact():
    local = random_masses(np.random.default_rng(1), SPEC.shape)
    w = warp_to_map(local, SE2(3 * RES, -5 * RES, 0.0), SPEC)
    # x forward by 3 cells = 3 rows up, y left by -5 cells = 5 columns right
    R, C = -32 - 3, -32 + 5
    np.testing.assert_array_equal(
        w.masses[R - w.r0 : R - w.r0 + 64, C - w.c0 : C - w.c0 + 64], local
    )


def test_90_degree_yaw_and_translation_move_a_cell_where_hand_computation_says():
    local = mass.vacuous(SPEC.shape)
    r, c = 10, 40
    local[r, c] = MARK
    # cell centre in the ego frame: x = (32 - 10 - 0.5) res = 21.5 res,
    # y = (32 - 40 - 0.5) res = -8.5 res; yaw +90 deg: (x, y) -> (-y, x) = (8.5 res, 21.5 res);
    # then + (4 res, -7 res) = (12.5 res, 14.5 res)
    # map cell: R = floor(-12.5) = -13, C = floor(-14.5) = -15
    w = warp_to_map(local, SE2(4 * RES, -7 * RES, math.pi / 2), SPEC)
    got = np.argwhere(w.masses[..., 2] < 1.0)
    assert got.tolist() == [[-13 - w.r0, -15 - w.c0]]
    np.testing.assert_array_equal(w.masses[-13 - w.r0, -15 - w.c0], MARK)
    rest = np.ones(w.shape, bool)
    rest[-13 - w.r0, -15 - w.c0] = False
    np.testing.assert_array_equal(w.masses[rest], np.tile(np.float32([0, 0, 1]), (rest.sum(), 1)))


@pytest.mark.parametrize("turns", [1, 2, 3, -1])
def test_quarter_turns_copy_every_cell_exactly(turns):
    local = random_masses(np.random.default_rng(turns + 10), SPEC.shape, p_edge=0.0)
    w = warp_to_map(local, SE2(2 * RES, 5 * RES, turns * math.pi / 2), SPEC)
    informative = np.argwhere(w.masses[..., 2] < 1.0)
    (r, c), n = informative.min(axis=0), SPEC.n_cells
    assert len(informative) == n * n  # nothing spills into neighbouring cells
    # the local grid, rotated (np.rot90 turns the +x rows towards the +y columns), bit for bit
    np.testing.assert_array_equal(w.masses[r : r + n, c : c + n], np.rot90(local, k=turns))


def test_half_cell_shift_mixes_bilinearly_with_vacuous_outside():
    local = mass.vacuous(SPEC.shape)
    local[0, 20] = MARK  # on the front edge
    w = warp_to_map(local, SE2(0.5 * RES, 0.0, 0.0), SPEC)
    # shifted half a cell forward: map cells R = -33 and -32 each get half of the mark
    for R in (-33, -32):
        np.testing.assert_allclose(
            w.masses[R - w.r0, -12 - w.c0], 0.5 * MARK + 0.5 * np.float32([0, 0, 1]), atol=1e-6
        )
    np.testing.assert_allclose(w.masses.sum(-1), 1.0, atol=1e-6)


def test_warp_rejects_wrong_shape():
    with pytest.raises(ValueError, match="shape"):
        warp_to_map(np.zeros((10, 10, 3), np.float32), SE2(), SPEC)


def _drive() -> list[SE2]:
    """An L-shaped drive: 12 m east, a left turn, 12 m north (in 0.37 m steps)."""
    poses = [SE2(0.37 * k, 0.0, 0.0) for k in range(33)]
    poses += [SE2(12.0, 0.37 * k, math.pi / 2 * min(1.0, k / 5)) for k in range(33)]
    return poses


def test_grown_map_matches_a_fixed_large_map():
    rng = np.random.default_rng(3)
    tiled = EvidentialMap(SPEC, tile_cells=32)
    size, off = 600, 300  # a dense array covering map cells [-300, 300)
    dense = mass.vacuous((size, size))
    warper = Warper(SPEC)
    for pose in _drive():
        ism = random_masses(rng, SPEC.shape, p_edge=0.05)
        ism[rng.random(SPEC.shape) < 0.5] = [0, 0, 1]
        w = warper.warp(ism, pose)
        tiled.apply(w, update_ray_ilm)
        h, wd = w.shape
        update_ray_ilm(dense[w.r0 + off : w.r0 + off + h, w.c0 + off : w.c0 + off + wd], w.masses)
    m, cov, r0, c0 = tiled.to_dense()
    np.testing.assert_array_equal(
        m, dense[r0 + off : r0 + off + m.shape[0], c0 + off : c0 + off + m.shape[1]]
    )
    # outside the tiles nothing was touched
    inside = np.zeros((size, size), bool)
    inside[r0 + off : r0 + off + m.shape[0], c0 + off : c0 + off + m.shape[1]] = True
    assert (dense[~inside][:, 2] == 1.0).all()
    mass.validate(m)
    assert cov.any() and not cov.all()


def test_map_memory_grows_with_area_not_bounding_box():
    tiled = EvidentialMap(SPEC, tile_cells=32)
    warper = Warper(SPEC)
    ism = random_masses(np.random.default_rng(4), SPEC.shape)
    for pose in _drive():
        tiled.apply(warper.warp(ism, pose), update_ray_ilm)
    r0, c0, h, w = tiled.bounds()
    n_box = (h // 32) * (w // 32)
    assert len(tiled.tiles) < 0.75 * n_box  # the L leaves the box's far corner empty
    # every tile holds covered cells
    assert all(c.any() for c in tiled.covered_tiles.values())


def test_read_returns_vacuous_where_never_covered():
    tiled = EvidentialMap(SPEC, tile_cells=32)
    m, cov = tiled.read(-1000, 500, 8, 9)
    np.testing.assert_array_equal(m, mass.vacuous((8, 9)))
    assert not cov.any()


def _some_map() -> EvidentialMap:
    tiled = EvidentialMap(SPEC, tile_cells=32, metadata={"scene": "scene-0001", "rule": "ray_ilm"})
    warper = Warper(SPEC)
    rng = np.random.default_rng(5)
    for pose in _drive()[::6]:
        tiled.apply(warper.warp(random_masses(rng, SPEC.shape), pose), update_ray_ilm)
    return tiled


def test_map_save_load_is_bit_identical(tmp_path):
    m = _some_map()
    path = save_map(m, tmp_path / "maps" / "ray_ilm.npz")
    back = load_map(path)
    assert back.grid == m.grid and back.tile_cells == m.tile_cells and back.metadata == m.metadata
    assert back.tiles.keys() == m.tiles.keys()
    for k in m.tiles:
        assert back.tiles[k].tobytes() == m.tiles[k].tobytes()
        np.testing.assert_array_equal(back.covered_tiles[k], m.covered_tiles[k])
    assert not list((tmp_path / "maps").glob(".*"))  # no temporary left behind


def test_a_map_file_keeps_the_dynamic_score_and_checks_it(tmp_path):
    from evgrid.fusion import DynamicParams, MapSet
    from evgrid.geometry import SE2
    from evgrid.grid import MapFileError

    grid = GridSpec(32, 4.0)
    rng = np.random.default_rng(2)
    ms = MapSet(grid, names=("ray_ilm",), dynamic=DynamicParams(decay=0.5), tile_cells=16)
    for k in range(3):
        ms.update(SE2(0.3 * k, 0.0, 0.2 * k), {"ray_ilm": random_masses(rng, grid.shape)})
    m = ms["ray_ilm"]
    assert m.dynamic and max(float(t.max()) for t in m.dynamic_tiles.values()) > 0
    back = load_map(save_map(m, tmp_path / "scored.npz"))
    assert back.dynamic and back.dynamic_tiles.keys() == m.dynamic_tiles.keys()
    for k in m.tiles:
        assert back.dynamic_tiles[k].tobytes() == m.dynamic_tiles[k].tobytes()
        assert back.tiles[k].tobytes() == m.tiles[k].tobytes()
    assert not load_map(save_map(_some_map(), tmp_path / "plain.npz")).dynamic
    # a corrupt score is refused, naming the field
    with np.load(tmp_path / "scored.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["dynamic"][0, 0, 0] = np.nan
    np.savez_compressed(tmp_path / "bad.npz", **arrays)
    with pytest.raises(MapFileError, match="bad.npz: field 'dynamic'"):
        load_map(tmp_path / "bad.npz")
    arrays["dynamic"] = arrays["dynamic"][:, :2]
    np.savez_compressed(tmp_path / "short.npz", **arrays)
    with pytest.raises(MapFileError, match="array 'dynamic'"):
        load_map(tmp_path / "short.npz")


def _same_frame(a, b) -> bool:
    return (a.kind, a.fixed_frame) == (b.kind, b.fixed_frame) and (
        a.first_pose is b.first_pose is None
        or np.array_equal(a.first_pose.matrix(), b.first_pose.matrix())
    )


def test_a_map_file_keeps_its_map_frame_exactly(tmp_path):
    from evgrid.geometry import SE3
    from evgrid.grid import MapFrame

    m = _some_map()
    assert load_map(save_map(m, tmp_path / "none.npz")).frame is None  # not known: none kept
    pose = SE3.from_quaternion([0.9, 0.1, -0.2, 0.3742], [664_123.25, 3_996_001.125, 1.5])
    for frame in (MapFrame("first_pose", "odom", pose), MapFrame("world", "global", pose)):
        back = load_map(save_map(m, tmp_path / f"{frame.kind}.npz", frame))
        assert _same_frame(back.frame, frame)  # the pose bit for bit
        assert all(back.tiles[k].tobytes() == m.tiles[k].tobytes() for k in m.tiles)
    m.frame = MapFrame("world", "map")  # a map's own frame is saved when none is given
    assert load_map(save_map(m, tmp_path / "own.npz")).frame == MapFrame("world", "map")
    with pytest.raises(ValueError, match="kind"):
        MapFrame("ego")


def _rewrite_header(path, edit) -> None:
    import json

    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    header = edit(json.loads(arrays["header"].tobytes().decode()))
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    np.savez_compressed(path, **arrays)


def test_version_1_map_files_still_load_without_a_frame(tmp_path):
    m = _some_map()
    path = save_map(m, tmp_path / "v1.npz")

    def as_v1(h):
        del h["frame"]
        return {**h, "version": 1}

    _rewrite_header(path, as_v1)
    back = load_map(path)
    assert back.frame is None and back.metadata == m.metadata
    assert all(back.tiles[k].tobytes() == m.tiles[k].tobytes() for k in m.tiles)
    _rewrite_header(path, lambda h: {**h, "version": 3})
    with pytest.raises(MapFileError, match="version 3; this evgrid reads 1, 2"):
        load_map(path)
    path = save_map(m, tmp_path / "bad.npz")
    _rewrite_header(path, lambda h: {**h, "frame": {"kind": "ego"}})
    with pytest.raises(MapFileError, match="bad.npz: header field 'frame' is invalid.*ego"):
        load_map(path)


def test_saved_maps_of_a_run_carry_its_map_frame(tmp_path):
    from evgrid.config import MapperConfig, OutputConfig
    from evgrid.runs import map_scene
    from evgrid_sim import SimConfig, simulate_scene

    scene = simulate_scene(4, SimConfig(duration_s=0.5))
    first = next(iter(scene)).ego_pose
    outputs = OutputConfig(figures=False, save_maps=True)
    for kind in ("world", "first_pose"):
        config = MapperConfig(maps=("ray_ilm",), frame=kind)
        map_scene(scene, tmp_path / kind, config, outputs, fixed_frame="odom")
        frame = load_map(tmp_path / kind / "maps" / "ray_ilm.npz").frame
        assert (frame.kind, frame.fixed_frame) == (kind, "odom")
        assert np.array_equal(frame.first_pose.matrix(), first.matrix())


def test_truncated_and_foreign_files_raise_clear_errors(tmp_path):
    path = save_map(_some_map(), tmp_path / "m.npz")
    data = path.read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(MapFileError, match="truncated or not an evgrid map"):
        load_map(tmp_path / "cut.npz")
    np.savez(tmp_path / "foreign.npz", a=np.zeros(3))
    with pytest.raises(MapFileError, match="not an evgrid map"):
        load_map(tmp_path / "foreign.npz")
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(MapFileError):
        load_map(tmp_path / "text.npz")
    with pytest.raises(FileNotFoundError):
        load_map(tmp_path / "missing.npz")


def test_failed_save_keeps_the_previous_file(tmp_path, monkeypatch):
    path = save_map(_some_map(), tmp_path / "m.npz")
    before = path.read_bytes()

    import evgrid.grid

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(evgrid.grid, "_write_member", boom)
    with pytest.raises(OSError, match="disk full"):
        save_map(_some_map(), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m.npz"]


def _numpy_warp_reference(
    local: np.ndarray, pose: SE2, grid: GridSpec, r0: int, c0: int, h: int, w: int
) -> np.ndarray:
    """Bilinear resampling written plainly: map cell centre -> ego frame -> local index."""
    R, C = np.meshgrid(np.arange(r0, r0 + h), np.arange(c0, c0 + w), indexing="ij")
    x, y = grid.map_cell_to_xy(R, C)
    lx, ly = SE2.inverse(pose).apply(np.stack([x, y], -1)).transpose(2, 0, 1)
    u, v = grid.xy_to_uv(lx, ly)
    n = grid.n_cells
    padded = mass.vacuous((n + 2, n + 2)).astype(np.float64)
    padded[1:-1, 1:-1] = local
    out = mass.vacuous((h, w)).astype(np.float64)
    ok = (u > -1) & (v > -1) & (u < n) & (v < n)
    iu, iv = np.floor(u[ok]).astype(int) + 1, np.floor(v[ok]).astype(int) + 1
    fu, fv = (u[ok] + 1 - iu)[:, None], (v[ok] + 1 - iv)[:, None]
    out[ok] = (
        (1 - fu) * (1 - fv) * padded[iu, iv]
        + (1 - fu) * fv * padded[iu, iv + 1]
        + fu * (1 - fv) * padded[iu + 1, iv]
        + fu * fv * padded[iu + 1, iv + 1]
    )
    return out


@pytest.mark.parametrize("deg", [0.0, 17.0, 37.0, 45.0, 123.0, -80.0])
def test_warp_matches_a_plain_numpy_reference_on_sparse_grids(deg):
    """Sparse blobs (the block-skipping path) and scattered cells, at several yaws."""
    grid = GridSpec(128, 10.0)
    rng = np.random.default_rng(int(deg) + 100)
    local = mass.vacuous(grid.shape)
    local[10:30, 70:75] = random_masses(rng, (20, 5))
    local[100, 3] = [0.2, 0.7, 0.1]
    local[0, 127] = [0.9, 0.0, 0.1]
    idx = rng.integers(0, 128, size=(40, 2))
    local[idx[:, 0], idx[:, 1]] = random_masses(rng, (40,))
    pose = SE2(1.37, -2.2, math.radians(deg))
    w = warp_to_map(local, pose, grid)
    ref = _numpy_warp_reference(local, pose, grid, w.r0, w.c0, *w.shape)
    np.testing.assert_allclose(w.masses, ref, atol=2e-6)


@pytest.mark.parametrize("deg", [0.0, 30.0, 45.0, 90.0, -135.0])
def test_warp_matches_a_plain_numpy_reference_on_dense_grids(deg):
    """Every cell informative (a deep IRM's grid): no block is skipped."""
    grid = GridSpec(128, 10.0)
    local = random_masses(np.random.default_rng(int(deg) + 700), grid.shape)
    pose = SE2(-0.61, 2.9, math.radians(deg))
    w = warp_to_map(local, pose, grid)
    ref = _numpy_warp_reference(local, pose, grid, w.r0, w.c0, *w.shape)
    np.testing.assert_allclose(w.masses, ref, atol=2e-6)


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-6.0, 6.0),
    y=st.floats(-6.0, 6.0),
    yaw=st.floats(-math.pi, math.pi),
)
def test_spans_are_exactly_the_covered_cells_and_the_rest_is_vacuous(x, y, yaw):
    pose = SE2(x, y, yaw)
    w = warp_to_map(random_masses(np.random.default_rng(0), SPEC.shape), pose, SPEC)
    h, wd = w.shape
    assert w.spans.shape == (h, 2) and w.spans.dtype == np.int64
    cols = np.arange(wd)
    from_spans = (cols >= w.spans[:, :1]) & (cols < w.spans[:, 1:])
    np.testing.assert_array_equal(from_spans, w.covered)
    np.testing.assert_array_equal(
        w.masses[~w.covered], np.tile(np.float32([0, 0, 1]), ((~w.covered).sum(), 1))
    )
    # coverage is the local square (-1, n) in continuous local indices, up to rounding at its edge
    R, C = np.meshgrid(np.arange(w.r0, w.r0 + h), np.arange(w.c0, w.c0 + wd), indexing="ij")
    lx, ly = SE2.inverse(pose).apply(np.stack(SPEC.map_cell_to_xy(R, C), -1)).transpose(2, 0, 1)
    u, v = SPEC.xy_to_uv(lx, ly)
    n = SPEC.n_cells
    inside = (u > -1) & (v > -1) & (u < n) & (v < n)
    edge = np.minimum.reduce([np.abs(u + 1), np.abs(v + 1), np.abs(u - n), np.abs(v - n)]) < 1e-9
    assert not (inside != w.covered)[~edge].any()
    assert w.covered.sum() > 0


def test_fusing_only_the_spans_equals_fusing_whole_pieces():
    rng = np.random.default_rng(8)
    with_spans, without = EvidentialMap(SPEC, tile_cells=32), EvidentialMap(SPEC, tile_cells=32)
    warper = Warper(SPEC)
    for pose in _drive()[::3]:
        w = warper.warp(random_masses(rng, SPEC.shape), pose)
        with_spans.apply(w, lambda c, m, spans: update_ray_ilm(c, m, spans=spans), pass_spans=True)
        without.apply(w, update_ray_ilm)
    assert with_spans.tiles.keys() == without.tiles.keys()
    for k in with_spans.tiles:
        np.testing.assert_array_equal(with_spans.tiles[k], without.tiles[k])
        np.testing.assert_array_equal(with_spans.covered_tiles[k], without.covered_tiles[k])


def test_a_window_built_by_hand_without_spans_fuses_its_covered_rows_whole():
    masses = mass.vacuous((4, 5))
    masses[1, 3] = [0.6, 0.2, 0.2]
    masses[2, 0] = [0.1, 0.8, 0.1]
    covered = np.zeros((4, 5), bool)
    covered[1, 3] = covered[2, 0] = True
    w = MapWindow(-2, 7, masses, covered)
    np.testing.assert_array_equal(w.row_spans(), [[0, 0], [0, 5], [0, 5], [0, 0]])
    m = EvidentialMap(SPEC, tile_cells=8)
    m.apply(w, lambda c, x, spans: update_ray_ilm(c, x, spans=spans), pass_spans=True)
    got, cov = m.read(-2, 7, 4, 5)
    np.testing.assert_array_equal(got, masses)
    np.testing.assert_array_equal(cov, covered)


@settings(max_examples=50, deadline=None)
@given(
    x=st.floats(-4.0, 4.0),
    y=st.floats(-4.0, 4.0),
    yaw=st.floats(-math.pi, math.pi),
    sparse=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_warp_matches_the_numpy_reference_at_any_pose(x, y, yaw, sparse, seed):
    """Blocks are skipped only where the local grid is vacuous, at any pose."""
    grid = GridSpec(48, 4.0)
    rng = np.random.default_rng(seed)
    local = random_masses(rng, grid.shape)
    if sparse:  # a few informative 8 x 8 blocks and scattered cells
        keep = np.kron(rng.random((6, 6)) < 0.2, np.ones((8, 8), bool)) | (
            rng.random(grid.shape) < 0.01
        )
        local[~keep] = [0, 0, 1]
    pose = SE2(x, y, yaw)
    w = warp_to_map(local, pose, grid)
    ref = _numpy_warp_reference(local, pose, grid, w.r0, w.c0, *w.shape)
    np.testing.assert_allclose(w.masses, ref, atol=2e-6)
