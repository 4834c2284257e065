"""Hostile scene and map files: one error naming the file and what is wrong, never a stray
exception.

Before issue 12 a 0-byte scene file raised EOFError (the CLI printed only "Aborted."), a corrupt
deflate stream raised zlib.error, a missing array KeyError and a broken 'meta' JSONDecodeError,
none naming the file; a map file with NaN cells loaded, one without 'tile_cells' gave KeyError.
"""

from __future__ import annotations

import json
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest

from evgrid.fusion import MapSet
from evgrid.geometry import SE2, GridSpec
from evgrid.grid import MapFileError, load_map, save_map
from evgrid_sim import SimConfig, simulate_scene
from evgrid_sim.store import SceneFileError, load_sim_scene, save_sim_scene
from tests.strategies import random_masses


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory) -> Path:
    scene = simulate_scene(2, SimConfig(duration_s=0.3))
    return save_sim_scene(scene, tmp_path_factory.mktemp("scene") / "s.npz")


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _garble_member(src: Path, dst: Path, member: str) -> None:
    """Copy ``src`` to ``dst`` with the first bytes of one zip member's data overwritten."""
    buf = bytearray(src.read_bytes())
    with zipfile.ZipFile(src) as zf:
        off = zf.getinfo(member).header_offset
    n_name, n_extra = struct.unpack("<HH", buf[off + 26 : off + 30])
    start = off + 30 + n_name + n_extra
    buf[start : start + 16] = b"\xff" * 16  # an invalid deflate block type
    dst.write_bytes(bytes(buf))


# --- scene files ----------------------------------------------------------------------------------


def test_an_empty_scene_file_names_the_file(tmp_path):
    (tmp_path / "empty.npz").write_bytes(b"")
    with pytest.raises(SceneFileError, match=r"empty\.npz: the scene file is empty"):
        load_sim_scene(tmp_path / "empty.npz")


def test_a_truncated_scene_file_names_the_file(scene_file, tmp_path):
    data = scene_file.read_bytes()
    for frac in (0.001, 0.5, 0.999):
        path = tmp_path / f"cut{frac}.npz"
        path.write_bytes(data[: int(len(data) * frac)])
        with pytest.raises(SceneFileError, match=rf"cut{frac}\.npz: .*truncated or corrupt"):
            load_sim_scene(path)


@pytest.mark.parametrize(
    "member", ["meta.npy", "timestamps.npy", "radar_RADAR_FRONT_points.npy", "lidar_points.npy"]
)
def test_a_corrupt_array_names_the_file_and_the_array(scene_file, tmp_path, member):
    path = tmp_path / "garbled.npz"
    _garble_member(scene_file, path, member)
    with pytest.raises(
        SceneFileError, match=rf"garbled\.npz: .*{member[:-4]}|garbled\.npz: .*corrupt"
    ):
        load_sim_scene(path)


@pytest.mark.parametrize(
    "change, says",
    [
        (lambda d: d.pop("lidar_offsets"), "'lidar_offsets' is missing"),
        (
            lambda d: d.pop("radar_RADAR_BACK_LEFT_labels"),
            "'radar_RADAR_BACK_LEFT_labels' is missing",
        ),
        (lambda d: d.__setitem__("meta", np.array("{not json")), "'meta' is not JSON"),
        (lambda d: d.__setitem__("meta", np.array("[1, 2]")), "'meta' must hold a JSON object"),
        (
            lambda d: d.__setitem__(
                "meta", np.array(json.dumps({**json.loads(str(d["meta"])), "seed": "x"}))
            ),
            "'seed'",
        ),
        (
            lambda d: d["lidar_offsets"].__setitem__(-1, d["lidar_offsets"][-1] + 7),
            "'lidar_offsets' does not index",
        ),
        (lambda d: d.__setitem__("ego_poses", d["ego_poses"][:-1]), "'ego_poses' has shape"),
        (
            lambda d: d.__setitem__(
                "radar_RADAR_FRONT_frame", d["radar_RADAR_FRONT_frame"] + 10_000
            ),
            "names frames outside",
        ),
        (lambda d: d.__setitem__("occupancy", d["occupancy"][:0]), "'occupancy' holds 0 keyframes"),
    ],
    ids=[
        "no-lidar-offsets",
        "no-radar-labels",
        "meta-not-json",
        "meta-list",
        "bad-seed",
        "offsets",
        "poses",
        "frames",
        "occupancy",
    ],
)
def test_an_inconsistent_scene_file_names_the_file_and_the_array(
    scene_file, tmp_path, change, says
):
    d = _arrays(scene_file)
    change(d)
    path = tmp_path / "bad.npz"
    np.savez(path, **d)
    with pytest.raises(SceneFileError, match=rf"bad\.npz: .*{says}"):
        scene = load_sim_scene(path)
        for _ in scene:  # used to fail here, if at all, with KeyError or IndexError
            pass


def test_a_single_npy_array_is_not_a_scene(tmp_path):
    path = tmp_path / "array.npz"
    with open(path, "wb") as f:
        np.save(f, np.zeros(3))
    with pytest.raises(SceneFileError, match=r"array\.npz: a single \.npy array"):
        load_sim_scene(path)


def test_scene_file_errors_are_value_errors():
    assert issubclass(SceneFileError, ValueError)


# --- map files ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def map_file(tmp_path_factory) -> Path:
    grid = GridSpec(32, 4.0)
    ms = MapSet(grid, names=("ray_ilm",), tile_cells=16)
    ms.update(SE2(0.1, 0.2, 0.3), {"ray_ilm": random_masses(np.random.default_rng(0), grid.shape)})
    return save_map(ms["ray_ilm"], tmp_path_factory.mktemp("map") / "m.npz")


def test_a_corrupt_deflate_stream_in_a_map_names_the_file(map_file, tmp_path):
    path = tmp_path / "garbled.npz"
    _garble_member(map_file, path, "tiles.npy")
    with pytest.raises(MapFileError, match=r"garbled\.npz"):
        load_map(path)


@pytest.mark.parametrize(
    "change, says",
    [
        (lambda h, a: h.pop("tile_cells"), "'tile_cells'"),
        (lambda h, a: h.__setitem__("tile_cells", "16"), "'tile_cells'"),
        (lambda h, a: h.pop("spec"), "'spec'"),
        (
            lambda h, a: a["tiles"].__setitem__((0, 3, 4, 1), np.nan),
            "1 cell\\(s\\) hold no valid mass",
        ),
        (
            lambda h, a: a["tiles"].__setitem__((0, 3, 4), [2.0, 0.0, -1.0]),
            "1 cell\\(s\\) hold no valid mass",
        ),
        (lambda h, a: a.__setitem__("covered", a["covered"].astype(np.uint8)), "coverage"),
        (
            lambda h, a: a.__setitem__("header", np.frombuffer(b"[1, 2]", np.uint8)),
            "not an evgrid map",
        ),
    ],
    ids=[
        "no-tile-cells",
        "text-tile-cells",
        "no-spec",
        "nan-tile",
        "negative-tile",
        "coverage-dtype",
        "header-list",
    ],
)
def test_a_broken_map_file_is_one_map_file_error(map_file, tmp_path, change, says):
    a = _arrays(map_file)
    header = json.loads(a["header"].tobytes().decode())
    change(header, a)
    if a["header"].tobytes()[:1] == b"{":
        a["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    path = tmp_path / "broken.npz"
    np.savez_compressed(path, **a)
    with pytest.raises(MapFileError, match=rf"broken\.npz.*{says}"):
        load_map(path)


@pytest.mark.parametrize(
    "text", ["", "{", "[]", '{"scenes": 3}', '{"scenes": [{"name": "x"}]}', '{"other": []}']
)
def test_a_bad_scene_index_is_one_error_naming_the_file(tmp_path, text):
    from evgrid.sources import SceneIndexError, SimFilesSource

    (tmp_path / "index.json").write_text(text)
    with pytest.raises(SceneIndexError, match="index.json"):
        SimFilesSource(str(tmp_path)).names()


def test_a_scene_missing_from_the_index_is_named(tmp_path):
    from evgrid.sources import SceneIndexError, SimFilesSource

    (tmp_path / "index.json").write_text(
        '{"scenes": [{"name": "sim-000001", "file": "sim-000001.npz"}]}'
    )
    with pytest.raises(SceneIndexError, match="no scene 'sim-000002'.*sim-000001"):
        SimFilesSource(str(tmp_path)).load("sim-000002")


@pytest.mark.parametrize("cut", [1, 3, 4, 16])
def test_a_cut_lidar_file_is_an_error_not_fewer_points(tmp_path, cut):
    from evgrid.data.nuscenes_format import read_lidar_bin, write_lidar_bin

    path = tmp_path / "sweep.pcd.bin"
    write_lidar_bin(path, np.ones((51, 5), np.float32))
    path.write_bytes(
        path.read_bytes()[:-cut]
    )  # 1,019 .. 1,004 bytes: 4 of them still a multiple of 4
    with pytest.raises(ValueError, match=r"sweep\.pcd\.bin.*not a multiple of 20"):
        read_lidar_bin(path)


def test_one_nan_radar_record_drops_that_record_only(tmp_path, caplog):
    from evgrid.data.frame import RADAR_COLUMNS
    from evgrid.data.nuscenes_format import (
        read_radar_pcd,
        read_radar_pcd_with_stats,
        write_radar_pcd,
    )

    pts = np.zeros((40, len(RADAR_COLUMNS)), np.float32)
    pts[:, 0] = np.arange(40) + 1.0
    pts[0, 0] = np.nan
    path = tmp_path / "radar.pcd"
    write_radar_pcd(path, pts)
    rec, n_bad = read_radar_pcd_with_stats(path)
    assert n_bad == 1 and len(rec) == 39 and rec["x"][0] == 2.0
    assert "1 of 40 radar records" in caplog.text
    write_radar_pcd(path, pts[:0])  # the devkit's empty cloud: one all-NaN record
    assert len(read_radar_pcd(path)) == 0


def test_a_radar_file_with_bytes_beyond_its_header_is_an_error(tmp_path):
    from evgrid.data.frame import RADAR_COLUMNS
    from evgrid.data.nuscenes_format import read_radar_pcd, write_radar_pcd

    path = tmp_path / "radar.pcd"
    write_radar_pcd(path, np.ones((3, len(RADAR_COLUMNS)), np.float32))
    path.write_bytes(path.read_bytes() + b"\0" * 7)
    with pytest.raises(ValueError, match=r"radar\.pcd.*declares 3 points"):
        read_radar_pcd(path)


# --- map files, round 3 (issue 26) ----------------------------------------------------------------


def test_every_single_byte_flip_in_a_map_file_is_a_map_file_error_or_a_valid_map(
    map_file, tmp_path
):
    # before: 45 of 674 flips raised a raw tokenize.TokenError naming no file
    data = map_file.read_bytes()
    path = tmp_path / "flipped.npz"
    outcomes = {"error": 0, "loaded": 0}
    for i in range(len(data)):
        buf = bytearray(data)
        buf[i] ^= 0xFF
        path.write_bytes(bytes(buf))
        try:
            m = load_map(path)
        except MapFileError as e:
            assert "flipped.npz" in str(e) and "\n" not in str(e)
            outcomes["error"] += 1
        else:  # a flip in a field nobody reads: the map is still whole and valid
            for t in m.tiles.values():
                assert np.isfinite(t).all() and (t >= 0).all()
            outcomes["loaded"] += 1
    assert outcomes["error"] > len(data) // 2


def test_a_npy_array_given_as_a_map_names_the_file(tmp_path):
    # before: TypeError: 'numpy.ndarray' object does not support the context manager protocol
    np.save(tmp_path / "a.npy", np.zeros((4, 4, 3), np.float32))
    with pytest.raises(MapFileError, match=r"a\.npy is a single numpy array"):
        load_map(tmp_path / "a.npy")


def _rewrite(map_file: Path, path: Path, header=None, **arrays) -> Path:
    a = _arrays(map_file)
    if header is not None:
        h = json.loads(a["header"].tobytes().decode())
        header(h)
        a["header"] = np.frombuffer(json.dumps(h).encode(), np.uint8)
    a.update(arrays)
    np.savez_compressed(path, **a)
    return path


def test_a_header_contradicting_its_tiles_names_file_and_field(map_file, tmp_path):
    # n_cells 100000: no update of such local grids covers only a few 16-cell tiles (before, the
    # nav2 export wrote a map of 0.4 mm cells)
    path = _rewrite(
        map_file, tmp_path / "wide.npz", lambda h: h["spec"].__setitem__("n_cells", 100000)
    )
    with pytest.raises(MapFileError, match=r"wide\.npz: field 'spec': n_cells 100000 contradicts"):
        load_map(path)


def test_several_tiles_under_one_key_name_file_and_field(map_file, tmp_path):
    a = _arrays(map_file)
    keys = a["keys"].copy()
    keys[1] = keys[0]
    path = _rewrite(map_file, tmp_path / "dup.npz", keys=keys)
    with pytest.raises(MapFileError, match=r"dup\.npz: field 'keys': tile key .* more than once"):
        load_map(path)


def test_a_tile_key_of_1e9_names_file_and_field(map_file, tmp_path):
    # before: numpy's "array is too big" when the map was exported
    a = _arrays(map_file)
    keys = a["keys"].copy()
    keys[0] = (10**9, 0)
    path = _rewrite(map_file, tmp_path / "far.npz", keys=keys)
    with pytest.raises(MapFileError, match=r"far\.npz: field 'keys': tile key 1000000000 lies"):
        load_map(path)


def test_an_array_declaring_more_than_the_file_holds_is_refused_before_reading(map_file, tmp_path):
    # tile_cells 4096 in the header: the arrays' shapes no longer fit it, checked from the
    # arrays' own headers before any data is read or allocated
    path = _rewrite(map_file, tmp_path / "big.npz", lambda h: h.__setitem__("tile_cells", 4096))
    with pytest.raises(MapFileError, match=r"big\.npz is inconsistent: array 'tiles'"):
        load_map(path)
    path = _rewrite(map_file, tmp_path / "huge.npz", lambda h: h.__setitem__("tile_cells", 10**6))
    with pytest.raises(MapFileError, match=r"huge\.npz: header field 'tile_cells'"):
        load_map(path)


def test_save_map_to_no_file_is_a_clear_error(map_file, tmp_path):
    m = load_map(map_file)
    with pytest.raises(ValueError, match="names no file"):
        save_map(m, "")
    with pytest.raises(IsADirectoryError, match="is a folder"):
        save_map(m, tmp_path)
    with pytest.raises(TypeError, match="EvidentialMap"):
        save_map(np.zeros(3), tmp_path / "x.npz")
