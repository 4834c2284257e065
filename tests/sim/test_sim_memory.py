"""What the simulator keeps in memory (docs/store.md, "Memory, measured"): the world builder
keeps few movers' tracks and recomputes the others, a scene keeps the labels of its latest radar
sweeps only; neither changes a byte of the world or of a frame."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid_sim import SimConfig, simulate_scene
from evgrid_sim import scene as sim_scene
from evgrid_sim import world as sim_world
from evgrid_sim.config import SimRadarRig, SweepFaults, WorldConfig
from evgrid_sim.scene import world_of

from .test_data_sim import _frames_equal

DRIVE = SimConfig(duration_s=40.0)


def _movers_sets(monkeypatch) -> list:
    """Every _MoverSet the next world build makes, recorded."""
    made: list = []
    init = sim_world._MoverSet.__init__

    def record(self, *a, **kw):
        init(self, *a, **kw)
        made.append(self)

    monkeypatch.setattr(sim_world._MoverSet, "__init__", record)
    return made


def _world_bytes(seed: int, config: SimConfig) -> list[bytes]:
    w, traj, _ = world_of(seed, config)
    mv = w.movers
    arrays = [w.boxes, w.yaw, w.classes, w.reflectivity, w.rcs_offset_db, w.mover_reflectivity]
    arrays += [mv.classes, mv.half_length, mv.half_width, mv.p0, mv.heading, mv.speed]
    arrays += [mv.t_begin, mv.t_end, mv.follow, mv.follow_gap, traj.path_x, traj.profile_t]
    return [np.ascontiguousarray(a).tobytes() for a in arrays]


@pytest.mark.parametrize(("seed", "layout"), [(4, "irregular"), (2, "highway"), (5, "grid")])
@pytest.mark.parametrize(("budget", "chunk", "piece"), [(0, 256, 16), (96 << 10, 24, 64)])
def test_recomputed_tracks_build_the_same_world(monkeypatch, seed, layout, budget, chunk, piece):
    """Tracks dropped from the builder's cache (whole, or some of their chunks) and recomputed
    accept and refuse the same movers as tracks all kept, with any size of the pieces whose
    bounds every accepted track keeps."""
    cfg = SimConfig(duration_s=40.0, world=WorldConfig(layout=layout))
    monkeypatch.setattr(sim_world, "_TRACK_CACHE_BYTES", 1 << 40)
    made = _movers_sets(monkeypatch)
    kept = _world_bytes(seed, cfg)
    assert made[-1].recomputed == 0
    monkeypatch.setattr(sim_world, "_TRACK_CACHE_BYTES", budget)
    monkeypatch.setattr(sim_world, "_TRACK_CHUNK", chunk)
    monkeypatch.setattr(sim_world, "_KEPT_PIECE", piece)
    dropped = _world_bytes(seed, cfg)
    ms = made[-1]
    assert ms.recomputed > 0  # the test did exercise recomputation
    assert ms.cached_bytes <= max(budget, chunk * 32)
    assert dropped == kept


def test_builder_keeps_its_tracks_within_the_budget(monkeypatch):
    made = _movers_sets(monkeypatch)
    monkeypatch.setattr(sim_world, "_TRACK_CACHE_BYTES", 256 << 10)
    world_of(4, DRIVE)
    ms = made[-1]
    one = len(ms.ts) * 4 * 8  # centre, cos and sin of yaw, float64, a sample
    assert ms.cached_bytes == len(ms.track_cache) * one <= 256 << 10
    assert len(ms.accepted) > len(ms.track_cache)  # some dropped: a real test of the budget
    # What every accepted mover keeps: its pieces' bounds, one row per _KEPT_PIECE samples.
    pieces = -(-len(ms.ts) // sim_world._KEPT_PIECE)
    assert all(p.shape == (pieces, 4) and p.dtype == np.float32 for p in ms.track_pieces)


def test_dropped_radar_labels_come_back_the_same(monkeypatch):
    """A scene keeps the labels of its latest sweeps only; older ones are simulated again, with
    the same bytes, and a frame after that is the same as without the limit."""
    cfg = SimConfig(duration_s=1.0)
    full = simulate_scene(3, cfg)
    frames = list(full)
    monkeypatch.setattr(sim_scene, "_LABELS_KEPT", 3)
    small = simulate_scene(3, cfg)
    for i, f in enumerate(frames):
        _frames_equal(f, small.frame(i))
        assert len(small._labels) <= 3
    for ch in full.radar_channels:
        for ts in full.radar_timestamps[ch][:4]:
            want = full.radar_labels(ch, int(ts))
            assert small.radar_labels(ch, int(ts)).tobytes() == want.tobytes()
    assert len(small._labels) <= 3
    _frames_equal(frames[5], small.frame(5))


def test_radar_deliveries_by_frame_with_faults():
    """Each frame's radar sweeps, found by bisection in the delivery arrays: every delivery once,
    in delivery order, frames never going back (drops, repeats and delays included)."""
    rig = SimRadarRig(faults=SweepFaults(drop=0.2, duplicate=0.2, reorder=0.3, seed=5))
    scene = simulate_scene(8, SimConfig(duration_s=4.0, rig=rig))
    for ch in scene.radar_channels:
        frames, sweeps = scene._delivery[ch]
        assert frames.dtype == sweeps.dtype == np.int64
        assert np.all(np.diff(frames) >= 0)
        got = [scene.radar_sweep_indices(i)[ch] for i in range(len(scene))]
        assert all(g.dtype == np.int64 for g in got)
        assert np.array_equal(np.concatenate(got), sweeps)
        for i, g in enumerate(got):
            assert np.array_equal(g, sweeps[frames == i])
        # Sweeps in a frame arrive no earlier than their own time; repeats do occur.
        ts = scene.radar_timestamps[ch]
        for i, g in enumerate(got):
            assert np.all(ts[g] <= scene.lidar_timestamps[i])
    assert any(
        len(np.unique(scene._delivery[c][1])) < len(scene._delivery[c][1])
        for c in rig.radar_channels
    )


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e5, 1e5), min_size=4, max_size=4))
def test_kept_bounds_hold_the_exact_ones(v):
    """Piece bounds kept in float32 are rounded outward: they hold the float64 bounds."""
    b = np.array([[min(v[0], v[2]), min(v[1], v[3]), max(v[0], v[2]), max(v[1], v[3])]])
    kept = sim_world._outward_f32(b)
    assert kept.dtype == np.float32
    assert np.all(kept[:, :2] <= b[:, :2]) and np.all(kept[:, 2:] >= b[:, 2:])
    assert np.all(np.abs(kept.astype(np.float64) - b) <= 1e-2 + 1e-6 * np.abs(b))
