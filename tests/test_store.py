"""The tile store (docs/store.md): lossless paging, atomic tiles, damaged and foreign stores,
a full disk, maps saved and opened tile by tile."""

from __future__ import annotations

import errno
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid.fusion import MAP_NAMES, DynamicParams, MapSet
from evgrid.geometry import SE2, GridSpec
from evgrid.grid import load_map, open_store_map, save_map
from evgrid.store import StoreError, StoreParams, TileStore

GRID = GridSpec(n_cells=128, length_m=19.2)  # 0.15 m cells, 19.2 m local grids
TILE = 32  # 4.8 m tiles: many tiles leave and come back on a short drive


def _isms(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    out = {}
    for name in ("ray_ilm", "ray_irm", "deep_irm"):
        g = np.zeros((n, n, 3), np.float32)
        g[..., 2] = 1.0
        for _ in range(10):
            r, c = rng.integers(0, n - 30, 2)
            h, w = rng.integers(4, 30, 2)
            f, o = rng.uniform(0, 0.7), rng.uniform(0, 0.3)
            g[r : r + h, c : c + w] = (f, o, 1.0 - f - o)
        out[name] = g
    return out


def _drive() -> list[SE2]:
    """80 m out along x, a turn, and back past the start: every tile left is met again."""
    out = [SE2(1.2 * i, 0.3 * math.sin(i / 7), 0.02 * i) for i in range(67)]
    out += [SE2(80.0 - 1.3 * i, 2.5, math.pi + 0.01 * i) for i in range(70)]
    return out


def _maps(store: TileStore | None, radius: float) -> MapSet:
    dyn = DynamicParams(enabled=True, gate_nav=True, gate_maps=False)  # nav's hidden gated rows
    maps = MapSet(GRID, names=(*MAP_NAMES, "nav"), tile_cells=TILE, dynamic=dyn)
    if store is not None:
        maps.attach_store(store)
    rng = np.random.default_rng(35)
    isms = [_isms(rng, GRID.n_cells) for _ in range(5)]
    moving = np.array([[3.0, 1.0, 4.0, 0.0, 0.0]])
    for i, pose in enumerate(_drive()):
        maps.update(pose, isms[i % 5], moving + [pose.x, pose.y, 0, pose.x, pose.y])
        if i % 9 == 0:
            maps.maps["nav"]  # nav read now and then, as exporters do
        if store is not None:
            maps.page_out(pose.x, pose.y, radius)
    return maps


def _rows(maps: MapSet):
    return {f"{r.name}.{r.shown}.{r.plain}": r.map for r in maps._rows}


def _same(a, b) -> None:
    assert sorted(a.tiles) == sorted(b.tiles)
    for k in a.tiles:
        assert np.array_equal(a.tiles[k], b.tiles[k]), k
        assert np.array_equal(a.covered_tiles[k], b.covered_tiles[k]), k
        if a.dynamic:
            assert np.array_equal(a.dynamic_tiles[k], b.dynamic_tiles[k]), k
    assert a.covered_bounds() == b.covered_bounds()


@pytest.fixture(scope="module")
def resident():
    return _maps(None, 1e9)


def test_a_drive_away_and_back_with_a_30_m_radius_gives_the_same_maps(resident, tmp_path):
    store = TileStore(tmp_path / "store")
    paged = _maps(store, 30.0)
    paged.maps["nav"], resident.maps["nav"]  # noqa: B018 - both brought up to date
    rows, ref = _rows(paged), _rows(resident)
    assert rows.keys() == ref.keys() and len(rows) > 7  # hidden gated rows included
    for name, m in rows.items():
        _same(m, ref[name])
    fused = paged.maps["fused"]
    assert fused.pager.n_out > 0 and fused.pager.n_in > 0  # tiles left and came back
    # nav's gated copies live in the files of the maps they are copies of
    assert not (store.root / "fused.gated").exists() and not (store.root / "ray_ilm.gated").exists()
    assert any(p.name.endswith(".map+gated.tile") for p in (store.root / "fused").iterdir())
    assert len(fused._tiles) < len(fused.tiles)  # and some are on disk now
    # the store alone holds each map once its resident tiles are flushed, and opens as one
    fused.flush()
    _same(open_store_map(store.root / "fused"), resident.maps["fused"])


def test_saving_a_paged_map_writes_the_file_of_a_resident_one(resident, tmp_path):
    paged = _maps(TileStore(tmp_path / "store"), 10.0)
    a = save_map(paged.maps["deep_disc"], tmp_path / "a.npz")
    b = save_map(resident.maps["deep_disc"], tmp_path / "b.npz")
    eager, lazy = load_map(a), load_map(a, lazy=True)
    _same(eager, resident.maps["deep_disc"])
    _same(lazy, resident.maps["deep_disc"])
    assert not lazy._tiles  # the lazy map holds no tile in memory
    assert np.array_equal(eager.to_dense()[0], load_map(b).to_dense()[0])


def _small_store(tmp_path):
    maps = MapSet(GRID, names=("ray_ilm",), tile_cells=TILE)
    store = TileStore(tmp_path / "s")
    maps.attach_store(store)
    rng = np.random.default_rng(1)
    for i in range(30):
        maps.update(SE2(1.5 * i, 0.0, 0.0), _isms(rng, GRID.n_cells))
        maps.page_out(1.5 * i, 0.0, 5.0)
    return maps.maps["ray_ilm"], store


def test_the_store_of_a_killed_run_opens(tmp_path):
    m, store = _small_store(tmp_path)
    group = store.root / "ray_ilm"
    # a kill during a write leaves a temporary part; one between writing a tile's newer
    # generation and removing the older leaves both (the older one, stale, is never read)
    (group / ".0_0.g99.tile.abc.part").write_bytes(b"half a tile")
    key = next(k for k in m.pager.stored if m.pager.group._files[k][0] > 0)
    gen = m.pager.group._files[key][0]
    (group / f"{key[0]}_{key[1]}.g{gen - 1}.tile").write_bytes(b"stale")
    back = open_store_map(group)
    # every tile as last written: those on disk now, and older states of those back in memory
    assert set(back.tiles) == set(m.pager.group.keys()) >= set(m.pager.stored)
    for k in m.pager.stored:
        assert np.array_equal(back.tiles[k], m.tiles[k])
    assert not list(group.glob("*.part"))


def test_a_damaged_tile_or_a_foreign_store_is_refused_naming_the_file(tmp_path):
    m, store = _small_store(tmp_path)
    key = next(iter(m.pager.stored))
    path = store.root / "ray_ilm" / m.pager.group._files[key][1]
    data = bytearray(path.read_bytes())
    data[-5] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(StoreError, match=str(path.name)):
        open_store_map(store.root / "ray_ilm").tiles[key]
    path.write_bytes(b"junk")
    with pytest.raises(StoreError, match="truncated"):
        open_store_map(store.root / "ray_ilm").tiles[key]
    # a tile of the store's first version (before copies and the largest-mass residual)
    v1 = b"EVGTILE\x00" + (1).to_bytes(4, "little") + (2).to_bytes(4, "little") + b"{}"
    path.write_bytes(v1)
    with pytest.raises(StoreError, match=f"{path.name} is a tile of store version 1; this"):
        open_store_map(store.root / "ray_ilm").tiles[key]
    head = store.root / "store.json"
    head.write_text(json.dumps({"format": "evgrid-tile-store", "version": 1}))
    with pytest.raises(StoreError, match="store.json is a tile store of version 1; this evgrid"):
        open_store_map(store.root / "ray_ilm")
    head.write_text(json.dumps({"format": "evgrid-tile-store", "version": 99}))
    with pytest.raises(StoreError, match="store.json is a tile store of version 99"):
        open_store_map(store.root / "ray_ilm")
    (store.root / "ray_ilm" / "map.json").write_text("{")
    with pytest.raises(StoreError, match="map.json is damaged"):
        open_store_map(store.root / "ray_ilm")


def _masses(rng: np.random.Generator, ts: int) -> np.ndarray:
    return rng.dirichlet([0.5, 0.5, 2.0], size=(ts, ts)).astype(np.float32)


def test_a_copy_kept_in_its_maps_files_comes_back_whatever_the_order_of_paging(tmp_path):
    from evgrid.grid import EvidentialMap

    ts, rng = 16, np.random.default_rng(7)
    group = TileStore(tmp_path / "s").group("m")
    a, b = EvidentialMap(tile_cells=ts, dynamic=True), EvidentialMap(tile_cells=ts, dynamic=True)
    a.attach_store(group)
    b.attach_store(group, copy="gated")
    want: dict[tuple[str, tuple[int, int]], tuple] = {}

    def fill(m, name, key, like=None):
        t, c = m.tile(key)
        t[:] = _masses(rng, ts) if like is None else like[0]
        if like is not None:  # a copy: a few cells differ, as where the gate took occupied mass
            t[::5, ::3] = _masses(rng, ts)[::5, ::3]
        c[:] = rng.random((ts, ts)) < 0.7
        m.dynamic_tiles[key][:] = rng.random((ts, ts)) * (rng.random((ts, ts)) < 0.3)
        want[name, key] = (t.copy(), c.copy(), m.dynamic_tiles[key].copy())

    for key in [(0, 0), (0, 1), (1, 0)]:
        fill(a, "a", key)
    for key in [(0, 0), (0, 1)]:
        fill(b, "b", key, want["a", key])
    fill(b, "b", (2, 2))  # a key the map has not

    def check(a, b):
        for (name, key), (t, c, d) in want.items():
            m = a if name == "a" else b
            assert np.array_equal(m.tiles[key].view(np.uint32), t.view(np.uint32)), (name, key)
            assert np.array_equal(m.covered_tiles[key], c) and np.array_equal(
                m.dynamic_tiles[key], d
            )
        assert sorted(a.tiles) == sorted(k for n, k in want if n == "a")
        assert sorted(b.tiles) == sorted(k for n, k in want if n == "b")

    a.page_out(1e6, 1e6, 1.0)  # the copy's tiles of the same keys leave with the map's
    assert not a._tiles and set(b._tiles) == {(2, 2)}
    assert group._members[0, 0] == {"", "gated"} and group._members[1, 0] == {""}
    check(a, b)
    # the map's tile alone comes back and leaves again: the copy's is carried into the new file
    fill(a, "a", (0, 0))
    a.page_out(1e6, 1e6, 1.0)
    # the copy's tile alone comes back and leaves again: the map's is carried
    fill(b, "b", (0, 1), want["a", (0, 1)])
    b.page_out(1e6, 1e6, 1.0)
    assert group._files[2, 2][1].endswith(".gated.tile") and group._members[2, 2] == {"gated"}
    check(a, b)
    # the copy stored against the map compresses to less than the map itself
    both, alone = (group.folder / group._files[k][1] for k in [(0, 1), (1, 0)])
    assert both.stat().st_size < 1.6 * alone.stat().st_size
    # a store opened again holds both, each by its own name
    group2 = TileStore(tmp_path / "s").group("m")
    a2, b2 = EvidentialMap(tile_cells=ts, dynamic=True), EvidentialMap(tile_cells=ts, dynamic=True)
    b2.attach_store(group2, write_meta=False, copy="gated")  # either may attach first
    a2.attach_store(group2, write_meta=False)
    check(a2, b2)
    with pytest.raises(ValueError, match="already has a raster paging as 'gated'"):
        EvidentialMap(tile_cells=ts).attach_store(group2, copy="gated")


def test_a_full_disk_while_paging_names_the_store_and_keeps_the_map(tmp_path, monkeypatch):
    import evgrid.store

    m, store = _small_store(tmp_path)
    before = {k: np.array(m.tiles[k]) for k in m.tiles}

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(evgrid.store, "_write_atomic", full)
    with pytest.raises(StoreError, match=f"tile store {store.root} is out of disk space"):
        m.page_out(-1e4, 0.0, 1.0)
    monkeypatch.undo()
    for k, t in before.items():  # nothing was lost: the tile not written stayed in memory
        assert np.array_equal(m.tiles[k], t)
    assert set(open_store_map(store.root / "ray_ilm").tiles) == set(m.pager.group.keys())


@pytest.mark.parametrize("radius", [-1.0, math.nan, math.inf, 2e9])
def test_a_radius_that_means_nothing_is_refused(radius):
    with pytest.raises(ValueError, match="resident_m"):
        StoreParams(resident_m=radius)


def test_the_mapper_with_radius_0_maps_as_with_every_tile_resident():
    from evgrid.config import MapperConfig
    from evgrid.mapper import OccupancyMapper
    from evgrid.observers import SceneScores, TruthTracker
    from evgrid_sim import SimConfig, simulate_scene

    frames = list(simulate_scene(3, SimConfig(duration_s=2.0)))
    out = []
    for radius in (0.0, 1e9):
        config = MapperConfig(
            maps=("ray_ilm", "ray_irm"),
            dynamic=DynamicParams(enabled=True),
            store=StoreParams(resident_m=radius),
            tile_cells=64,
        )
        truth = TruthTracker(config.grid, config.tile_cells)
        mapper = OccupancyMapper(config)
        scores = SceneScores(mapper.maps.maps, truth)
        mapper.observers += [truth, scores]
        for f in frames:
            mapper.process(f)
        out.append((mapper, truth, scores.final()))
    (paged, ptruth, pfinal), (ref, rtruth, rfinal) = out
    assert paged.store is not None and ref.store is None
    assert paged.maps.maps["ray_ilm"].pager.n_out > 0
    for name in ref.maps.names:
        _same(paged.maps.maps[name], ref.maps.maps[name])
    _same(ptruth.map, rtruth.map)
    assert pfinal == rfinal
    paged.close()


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(width=32, allow_nan=True, allow_infinity=True), min_size=3, max_size=60))
def test_the_masses_encoding_gives_back_every_bit(values):
    from evgrid.store import _decode_masses, _encode_masses

    n = len(values) // 3
    a = np.array(values[: 3 * n], np.float32).reshape(n, 3)
    back = _decode_masses(_encode_masses(a), a.shape)
    assert np.array_equal(back.view(np.uint32), a.view(np.uint32))


def test_the_largest_mass_is_stored_as_a_small_residual_and_comes_back_bit_for_bit():
    from evgrid.store import _decode_masses, _encode_masses

    rng = np.random.default_rng(35)
    a = rng.dirichlet([0.5, 0.5, 2.0], size=(64, 64)).astype(np.float32)
    a.view(np.uint32)[::7, ::3] ^= rng.integers(0, 2**32, (10, 22, 3), dtype=np.uint32)  # junk
    a[0, 0] = (np.nan, 0.5, 0.5)
    a[0, 1] = (np.inf, -np.inf, 0.0)
    a[0, 2] = (-0.0, 1.0, 0.0)
    buf = _encode_masses(a)
    assert np.array_equal(_decode_masses(buf, a.shape).view(np.uint32), a.view(np.uint32))
    planes, largest = buf[: 12 * 64 * 64].view(np.uint32).reshape(3, -1), buf[12 * 64 * 64 :]
    assert largest[0] == largest[1] == 3  # a non-finite mass: the cell is stored as it is
    ok = np.zeros((64, 64), bool)
    ok[::7, ::3] = True
    ok = ~ok.reshape(-1)
    ok[:3] = False
    assert set(np.unique(largest[ok])) <= {0, 1, 2, 4, 5, 6}
    assert (planes[0, ok] <= 8).all()  # masses summing to 1: a few ulps off
    buf[12 * 64 * 64 + 5] = 7  # a damaged file (its CRC aside) is refused, never misread
    with pytest.raises(ValueError, match="largest mass"):
        _decode_masses(buf, a.shape)


def test_a_run_keeps_its_store_in_its_folder_while_mapping_and_removes_it_when_complete(tmp_path):
    from evgrid.config import MapperConfig, OutputConfig
    from evgrid.runs import STORE_FOLDER, map_scene
    from evgrid_sim import SimConfig, simulate_scene

    out = tmp_path / "scene"
    (out / STORE_FOLDER / "ray_ilm").mkdir(parents=True)  # what a killed run left
    (out / STORE_FOLDER / "ray_ilm" / "0_0.g0.tile").write_bytes(b"old")
    seen = []

    class Watch:
        def on_update(self, update):
            seen.append(sorted(p.name for p in (out / STORE_FOLDER).glob("*/*.tile")))

    config = MapperConfig(maps=("ray_ilm",), store=StoreParams(resident_m=0.0), tile_cells=64)
    frames = simulate_scene(3, SimConfig(duration_s=1.0))
    outputs = OutputConfig(figures=False, save_maps=True)
    map_scene(frames, out, config, outputs, observers=(Watch(),), overwrite=True)
    assert "0_0.g0.tile" not in sum(seen, [])  # the old run's store was not taken for this one
    assert any(seen)  # tiles went to the store in the scene's folder while mapping
    assert not (out / STORE_FOLDER).exists()
    assert [p.name for p in (out / "maps").iterdir()] == ["ray_ilm.npz"]


def test_a_tile_left_unchanged_since_its_last_write_is_not_written_again(tmp_path):
    m, store = _small_store(tmp_path)
    group = m.pager.group
    m.flush()  # as a checkpoint does
    key = next(iter(m._tiles))
    files, names = dict(group._files), sorted(p.name for p in group.folder.iterdir())
    # it leaves memory unchanged: the file the flush wrote holds it, and stays the only one
    assert m.pager.page_out([key]) == 0
    assert group._files == files and sorted(p.name for p in group.folder.iterdir()) == names
    assert key in m.pager.stored and key not in m._tiles
    t, _ = m.tile(key)  # back, and changed: a new generation
    t[0, 0] = (0.5, 0.25, 0.25)
    want = t.copy()
    assert m.pager.page_out([key]) > 0 and group._files[key][0] > files[key][0]
    assert np.array_equal(open_store_map(store.root / "ray_ilm").tiles[key], want)


def test_a_folder_that_is_not_a_store_is_refused_naming_the_file(tmp_path):
    m, store = _small_store(tmp_path)
    (store.root / "store.json").unlink()
    with pytest.raises(StoreError, match="store.json is missing"):
        open_store_map(store.root / "ray_ilm")
    assert not (store.root / "store.json").exists()  # opening writes nothing


def test_a_checkpoint_syncs_the_tiles_written_since_the_last_one_before_its_own_file(
    tmp_path, monkeypatch
):
    import evgrid.checkpoint as ckpt
    import evgrid.store as store_module

    m, store = _small_store(tmp_path)
    group = m.pager.group
    events: list[tuple[str, str]] = []
    real_fsync, real_write = os.fsync, ckpt.atomic_write_bytes

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        return real_fsync(fd)

    def write(path, data):
        events.append(("checkpoint", str(path)))
        return real_write(path, data)

    monkeypatch.setattr(store_module.os, "fsync", fsync)
    monkeypatch.setattr(ckpt, "atomic_write_bytes", write)
    path = ckpt.checkpoint_path(store.root)
    ckpt.save_checkpoint(path, {"m": m}, store, None, "h")
    at = events.index(("checkpoint", str(path)))
    synced = {Path(p).name for what, p in events[:at] if what == "fsync"}
    # every tile the checkpoint names (all on disk now) was synced before it, and the folder
    assert {n for _, n in group._files.values()} <= synced and group.folder.name in synced
    # the next checkpoint syncs only what was written since
    events.clear()
    key = next(iter(m.pager.layers["masses"]))
    m.tile(key)[0][0, 0] = (0.5, 0.25, 0.25)  # changed since the checkpoint: written again
    m.pager.page_out([key])
    ckpt.save_checkpoint(path, {"m": m}, store, None, "h")
    at = events.index(("checkpoint", str(path)))
    tiles = [p for what, p in events[:at] if what == "fsync" and p.endswith(".tile")]
    assert 1 <= len(tiles) <= len(m.pager.layers["masses"]) + 1


def test_page_out_all_leaves_no_tile_in_memory_and_the_maps_as_they_were():
    """The end of a drive: every tile of every map (hidden rows included) and of the truth map
    to the store, the maps reading as before, and further updates as with every tile resident."""
    from evgrid.config import MapperConfig
    from evgrid.mapper import OccupancyMapper
    from evgrid.observers import TruthTracker
    from evgrid_sim import SimConfig, simulate_scene

    frames = list(simulate_scene(3, SimConfig(duration_s=2.0)))
    half = len(frames) // 2
    out = []
    for radius in (50.0, 1e9):
        config = MapperConfig(
            maps=("ray_ilm", "ray_irm", "fused", "nav"),
            dynamic=DynamicParams(enabled=True, gate_nav=True),
            store=StoreParams(resident_m=radius),
            tile_cells=64,
        )
        truth = TruthTracker(config.grid, config.tile_cells)
        mapper = OccupancyMapper(config)
        mapper.observers.append(truth)
        for f in frames[:half]:
            mapper.process(f)
        out.append((mapper, truth, mapper.page_out_all()))
    (paged, ptruth, moved), (ref, rtruth, none) = out
    rows = [r.map for r in paged.maps._rows]
    # a gated copy is written in its map's tile files (store version 2): one write for both
    owners = {r.name for r in paged.maps._rows if r.shown or r.plain}
    files = [r.map for r in paged.maps._rows if r.shown or r.plain or r.name not in owners]
    assert len(rows) > len(files) > 3
    assert moved == sum(len(m.tiles) for m in files) + len(ptruth.map.tiles)
    assert none == 0 and ref.store is None  # every tile resident: nothing to page out
    assert not any(m._tiles for m in rows) and not ptruth.map._tiles
    for name in ref.maps.names:
        _same(paged.maps.maps[name], ref.maps.maps[name])
    _same(ptruth.map, rtruth.map)
    for f in frames[half:]:  # the tiles an update writes come back
        paged.process(f)
        ref.process(f)
    for name in ref.maps.names:
        _same(paged.maps.maps[name], ref.maps.maps[name])
    paged.close()


def test_maps_kept_past_the_end_of_their_run_say_their_temporary_store_is_gone():
    """A run without a folder pages into a temporary store that its end removes: a map an
    observer kept reads its resident tiles, and a paged one raises one line saying why."""
    from evgrid.config import MapperConfig
    from evgrid.mapper import OccupancyMapper
    from evgrid.store import StoreError
    from evgrid_sim import SimConfig, simulate_scene

    mapper = OccupancyMapper(MapperConfig(maps=("ray_ilm",), tile_cells=64))
    for f in simulate_scene(3, SimConfig(duration_s=1.0)):
        mapper.process(f)
    m = mapper.maps.maps["ray_ilm"]
    assert mapper.page_out_all() > 0
    first, *others = sorted(m.tiles)
    assert others
    before = m.tiles[first].copy()  # read back (made resident again) while the store is there
    mapper.close()
    assert not mapper.store.root.exists()
    assert np.array_equal(m.tiles[first], before)
    with pytest.raises(StoreError, match="temporary tile store .* removed when its run ended"):
        m.tiles[others[0]]


def test_a_run_pages_every_tile_out_before_its_exports_write_the_final_maps(tmp_path, monkeypatch):
    from evgrid.config import MapperConfig, OutputConfig
    from evgrid.export.nav2 import Nav2Exporter
    from evgrid.runs import map_scene
    from evgrid_sim import SimConfig, simulate_scene

    resident = []
    close = Nav2Exporter.close

    def counting(self):
        resident.append({n: len(m._tiles) for n, m in self._maps.items()})
        return close(self)

    monkeypatch.setattr(Nav2Exporter, "close", counting)
    config = MapperConfig(maps=("ray_ilm", "ray_irm", "fused"), tile_cells=64)
    outputs = OutputConfig(figures=False, exports=("nav2",))
    frames = simulate_scene(3, SimConfig(duration_s=1.0))
    map_scene(frames, tmp_path / "scene", config, outputs, overwrite=True)
    (counts,) = resident
    assert set(counts) >= {"ray_ilm", "fused", "nav"} and not any(counts.values())
