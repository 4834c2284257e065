"""One policy for every export writer: refuse unless overwrite, folders written into, atomic
renames, a full disk or Ctrl-C leaving no file under its final name; the MCAP's frame tree and
the writers' parameters (the nav2 values are in test_export.py)."""

from __future__ import annotations

import errno
import os
from types import SimpleNamespace as NS

import numpy as np
import pytest

from evgrid.export import ExportFileError, export_map, make_observer
from evgrid.export import _files as files_mod
from evgrid.export._files import AtomicFile
from evgrid.geometry import SE2, SE3, GridSpec
from evgrid.grid import EvidentialMap

SPEC = GridSpec(64, 5.0)


def _map(seed: int) -> EvidentialMap:
    m = EvidentialMap(SPEC, tile_cells=32)
    e = np.random.default_rng(seed).random((32, 32, 2)) * 5
    s = 2 + e.sum(-1)
    m.tile((0, 0))[0][:] = np.stack([e[..., 0] / s, e[..., 1] / s, 2 / s], -1)
    m.covered_tiles[(0, 0)][:] = True
    return m


MAPS = {"ray_ilm": _map(0), "fused": _map(1)}
FIRST = SE3.from_se2(SE2(1000.0, -500.0, 0.7))


def _update(i: int) -> NS:
    """A map update as the mapper makes it: ego pose in the fixed frame and in the map frame."""
    ego = SE3.from_se2(SE2(1000.0 + 0.5 * i, -500.0 + 0.2 * i, 0.7 + 0.01 * i))
    frame = NS(timestamp=10**6 + i * 10**5, is_keyframe=i % 5 == 0, ego_pose=ego)
    isms = {"ray_ilm": np.tile(np.float32([0.1, 0.2, 0.7]), (64, 64, 1))}
    pose = (FIRST.inverse() @ ego).to_se2()
    return NS(frame=frame, pose=pose, maps=NS(maps=MAPS, grid=SPEC), isms=isms)


def _run(obs, n: int = 12):
    for i in range(n):
        obs.on_update(_update(i))
    return obs.close()


def _formats():
    out = ["nav2"]
    for mod, fmt in (("mcap", "mcap"), ("rerun", "rerun")):
        try:
            __import__(mod)
            out.append(fmt)
        except ImportError:
            pass
    return out


@pytest.mark.parametrize("fmt", _formats())
def test_existing_files_are_refused_unless_overwrite_and_folders_written_into(tmp_path, fmt):
    first = export_map(MAPS["fused"], tmp_path, fmt)  # a folder: default names inside
    assert all(p.parent == tmp_path for p in first)
    assert [p.name for p in first] == {
        "nav2": ["map.pgm", "map.yaml"],
        "mcap": ["maps.mcap"],
        "rerun": ["maps.rrd"],
    }[fmt]
    before = {p: p.read_bytes() for p in first}
    with pytest.raises(FileExistsError, match=str(first[0])):
        export_map(MAPS["ray_ilm"], tmp_path, fmt)
    assert {p: p.read_bytes() for p in first} == before  # untouched
    again = export_map(MAPS["ray_ilm"], tmp_path, fmt, overwrite=True)
    assert again == first
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".part")]


def test_observers_refuse_existing_files_at_the_start(tmp_path):
    pytest.importorskip("mcap")
    (tmp_path / "run.mcap").write_bytes(b"old")
    with pytest.raises(FileExistsError, match="run.mcap exists"):
        make_observer("mcap", tmp_path / "run.mcap")
    (tmp_path / "nav2").mkdir()
    (tmp_path / "nav2" / "map.yaml").write_text("old")
    with pytest.raises(FileExistsError, match="map.yaml exists"):
        make_observer("nav2", tmp_path / "nav2")
    obs = make_observer("nav2", tmp_path / "nav2", overwrite=True)
    assert [p.name for p in _run(obs)] == ["map.pgm", "map.yaml"]


class _FullDisk:
    """A file object that raises ENOSPC once more than ``room`` bytes were written."""

    def __init__(self, f, room: int):
        self.f, self.room = f, room

    def write(self, data) -> int:
        self.room -= len(data)
        if self.room < 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        return self.f.write(data)

    def __getattr__(self, name):
        return getattr(self.f, name)


@pytest.mark.parametrize("fmt", _formats())
@pytest.mark.parametrize("room", [0, 600])
def test_a_full_disk_names_the_file_and_leaves_nothing(tmp_path, monkeypatch, fmt, room):
    real = os.fdopen
    monkeypatch.setattr(files_mod.os, "fdopen", lambda *a, **k: _FullDisk(real(*a, **k), room))
    path = tmp_path / {"nav2": "nav2", "mcap": "run.mcap", "rerun": "run.rrd"}[fmt]
    with pytest.raises(ExportFileError) as e:
        _run(make_observer(fmt, path))
    assert e.value.errno == errno.ENOSPC
    assert str(path) in str(e.value) and "No space left" in str(e.value)
    left = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert left == []  # no partial file, no temporary file


@pytest.mark.parametrize("fmt", ["mcap", "rerun"])
def test_ctrl_c_during_an_export_leaves_no_file_under_its_final_name(tmp_path, monkeypatch, fmt):
    pytest.importorskip({"mcap": "mcap", "rerun": "rerun"}[fmt])
    path = tmp_path / f"run.{'mcap' if fmt == 'mcap' else 'rrd'}"
    obs = make_observer(fmt, path)
    seen = []
    for i in range(6):
        obs.on_update(_update(i))
        seen += [p.name for p in tmp_path.iterdir()]
    assert path.name not in seen  # while running, only a temporary name exists
    assert any(n.startswith(f".{path.name}.") and n.endswith(".part") for n in seen)

    # Ctrl-C inside the exporter's own writing: the file is dropped, the interrupt goes on
    def interrupted(*a, **k):
        raise KeyboardInterrupt

    if fmt == "mcap":
        monkeypatch.setattr(obs, "_write_maps", interrupted)
    else:
        monkeypatch.setattr(obs._out, "drain", interrupted)
    with pytest.raises(KeyboardInterrupt):
        for i in range(6, 12):
            obs.on_update(_update(i))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("fmt", ["mcap", "rerun"])
def test_ctrl_c_elsewhere_then_abort_or_garbage_collection_leaves_nothing(tmp_path, fmt):
    pytest.importorskip({"mcap": "mcap", "rerun": "rerun"}[fmt])
    for k in range(2):
        path = tmp_path / f"run{k}.{'mcap' if fmt == 'mcap' else 'rrd'}"
        obs = make_observer(fmt, path)
        for i in range(3):
            obs.on_update(_update(i))
        if k == 0:
            obs.abort()  # what the runner does when a run stops
        else:
            del obs  # an exporter nobody closes removes its temporary file when collected
            import gc

            gc.collect()
        assert list(tmp_path.iterdir()) == []


def test_atomic_file_never_replaces_a_file_that_appeared_meanwhile(tmp_path):
    f = AtomicFile(tmp_path / "a.bin")
    f.write(b"new")
    (tmp_path / "a.bin").write_bytes(b"someone else's")
    with pytest.raises(FileExistsError, match="a.bin exists"):
        f.commit()
    assert (tmp_path / "a.bin").read_bytes() == b"someone else's"
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_one_atomic_writer_for_exports_and_evgrid_io(tmp_path):
    from evgrid import io

    assert AtomicFile is io.AtomicFile and ExportFileError is io.FileWriteError
    with io.AtomicFile(tmp_path / "t.txt", mode="w") as f:  # text mode, UTF-8
        f.write("käse\n")
    assert (tmp_path / "t.txt").read_bytes() == "käse\n".encode()
    with io.atomic_open(tmp_path / "t.txt", "w") as fh:  # replaces, as atomic_open always did
        fh.write("new")
    assert (tmp_path / "t.txt").read_text() == "new"
    with pytest.raises(KeyboardInterrupt), io.atomic_open(tmp_path / "t.txt", "w") as fh:
        fh.write("half")
        raise KeyboardInterrupt
    assert (tmp_path / "t.txt").read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["t.txt"]  # no temporary left
    (tmp_path / "ro").mkdir(mode=0o500)
    if not os.access(tmp_path / "ro", os.W_OK):  # root writes anywhere
        with pytest.raises(OSError, match="ro/x"), io.atomic_open(tmp_path / "ro" / "x"):
            pass


def test_mcap_frames_map_is_parent_of_the_fixed_frame(tmp_path):
    pytest.importorskip("mcap_ros2")
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from evgrid.export.mcap import McapParams

    path = _run(make_observer("mcap", tmp_path / "r.mcap", McapParams(fixed_frame="world")))
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        tfs = [
            d for _, ch, _, d in reader.iter_decoded_messages() if ch.topic == "/tf"
        ]  # fmt: skip
    assert len(tfs) == 12
    for i, msg in enumerate(tfs):
        (tr,) = msg.transforms
        assert (tr.header.frame_id, tr.child_frame_id) == ("map", "world")
        t = tr.transform
        fixed = SE2(t.translation.x, t.translation.y, 2 * np.arctan2(t.rotation.z, t.rotation.w))
        u = _update(i)
        # map -> world, then the recording's world -> base_link, is the ego pose in the map
        got = fixed @ u.frame.ego_pose.to_se2()
        assert (got.x, got.y, got.yaw) == pytest.approx((u.pose.x, u.pose.y, u.pose.yaw), abs=1e-6)
        # and it is the inverse of the first pose (maps in the first pose's frame)
        want = FIRST.to_se2().inverse()
        assert (fixed.x, fixed.y) == pytest.approx((want.x, want.y), abs=1e-6)


def test_export_params_are_checked():
    from evgrid.export.mcap import McapParams
    from evgrid.export.nav2 import Nav2Params
    from evgrid.export.rerun import RerunParams

    for bad, match in (
        (dict(window_m=-1.0), "window_m"),
        (dict(rate_hz=0.0), "rate_hz"),
        (dict(layers=("occupancy", "m_fre")), "m_fre"),
        (dict(compression="gzip"), "compression"),
        (dict(maps="fused"), "maps"),
        (dict(occupancy_values="grey"), "occupancy values|occupancy_values"),
    ):
        with pytest.raises(ValueError, match=match):
            McapParams(**bad)
    with pytest.raises(ValueError, match="maps"):
        Nav2Params(maps="fused")
    with pytest.raises(ValueError, match="step"):
        RerunParams(step=0)
    with pytest.raises(ValueError, match="not both"):
        make_observer("nav2", "x", Nav2Params(), maps=("fused",))


def test_a_map_asked_for_that_the_run_lacks_is_named_at_the_first_update(tmp_path):
    obs = make_observer("nav2", tmp_path / "nav2", maps=("deep_acc",))
    with pytest.raises(ValueError, match="deep_acc"):
        obs.on_update(_update(0))
    obs = make_observer("nav2", tmp_path / "nav2", navigation=("nav", "deep_acc"))
    with pytest.raises(ValueError, match="navigation maps"):
        obs.on_update(_update(0))


def test_rerun_quads_lie_on_their_cells():
    from evgrid.export.rerun import quad_corners

    r0, c0, h, w, res = -7, 12, 5, 3, 0.25
    q = quad_corners(r0, c0, h, w, res)
    # texel (i, j) centre at texture (u, v) = ((j + .5) / w, (i + .5) / h): bilinear on the quad
    for i, j in ((0, 0), (4, 2), (2, 1)):
        u, v = (j + 0.5) / w, (i + 0.5) / h
        p = (1 - u) * (1 - v) * q[0] + u * (1 - v) * q[1] + u * v * q[2] + (1 - u) * v * q[3]
        R, C = SPEC_AT(res).map_xy_to_cell(p[0], p[1])
        assert (int(R), int(C)) == (r0 + i, c0 + j)


def SPEC_AT(res: float) -> GridSpec:  # noqa: N802 (a grid of that resolution)
    return GridSpec(8, 8 * res)


@pytest.mark.parametrize(
    "params, windows",
    [
        (dict(), 3),  # keyframes: updates 0, 5, 10 of 12
        (dict(rate_hz=5.0), 6),  # updates every 0.1 s: every second one
        (dict(window_m=0.0), 0),
        (dict(compression="lz4", maps=("ray_ilm", "fused")), 6),  # 3 keyframes x 2 maps
        (dict(compression="none", final_maps=()), 3),
        (dict(map_frame="odom"), 3),  # maps in the fixed frame: no /tf (no odom -> odom)
    ],
)
def test_mcap_window_rate_maps_and_compression(tmp_path, params, windows):
    pytest.importorskip("mcap")
    from mcap.reader import make_reader

    from evgrid.export.mcap import McapParams

    p = McapParams(**params)
    path = _run(make_observer("mcap", tmp_path / "r.mcap", p))
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        chunks = {c.compression for c in summary.chunk_indexes}
        msgs = [(ch.topic, m.log_time) for _, ch, m in reader.iter_messages()]
    assert chunks == {"" if p.compression == "none" else p.compression}
    n_tf = sum(topic == "/tf" for topic, _ in msgs)
    assert n_tf == (0 if p.map_frame == p.fixed_frame else 12)
    last = max(t for topic, t in msgs if topic == "/evgrid/ego_pose")
    grids = [(topic, t) for topic, t in msgs if topic.endswith("/occupancy")]
    assert len([g for g in grids if g[1] <= last]) == windows
    final = sorted(topic for topic, t in grids if t > last)
    want = [] if p.final_maps == () else ["/evgrid/fused/occupancy", "/evgrid/ray_ilm/occupancy"]
    assert final == want
