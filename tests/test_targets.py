"""Ev-Net's training targets (evgrid.learn.targets): lidar accumulated around each sample, and
the paper's single-frame targets."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from evgrid.classes import FREE, OCCUPIED, UNKNOWN
from evgrid.data.frame import LidarSweep
from evgrid.geometry import SE3, GridSpec
from evgrid.ism import ray_ilm
from evgrid.learn.targets import TargetConfig, TargetWindow, accumulated_classes, ilm_classes
from evgrid.learn.train import TrainConfig, scene_samples
from evgrid.preprocess import Preprocessor
from evgrid_sim import SimConfig, simulate_scene

# 0.25 m cells, 20 m either side: a point at x, y sits in row floor(80 - 4x), col
# floor(80 - 4y). The ray ILM casts rays all round to 15 m, stopping at the first return.
GRID = GridSpec(n_cells=160, length_m=40.0)


def cell(x: float, y: float) -> tuple[int, int]:
    return int(np.floor(80 - 4 * x)), int(np.floor(80 - 4 * y))


def sweep(x0: float, t_s: float, points_xy: list[tuple[float, float]]) -> LidarSweep:
    """A sweep taken with the ego (and lidar) at global (x0, 0), of points given in global
    metres at 1 m height."""
    pts = np.array([[x - x0, y, 1.0, 0.0, 0.0] for x, y in points_xy], dtype=np.float32)
    return LidarSweep(pts, SE3.identity(), SE3(np.eye(3), np.array([x0, 0.0, 0.0])), int(t_s * 1e6))


WALL_X = 5.125  # cell centres, so no ray ends on a cell boundary
LEFT = [(WALL_X, 0.125 + 0.25 * i) for i in range(8)]  # y 0.125 .. 1.875
RIGHT = [(WALL_X, -0.125 - 0.25 * i) for i in range(8)]  # y -0.125 .. -1.875


def test_a_wall_seen_from_two_places_is_whole_in_the_sample_grid():
    # the sample (ego at x = 0) sees the wall's left half, a frame from x = 2 m its right half
    a, b = sweep(0.0, 0.0, LEFT), sweep(2.0, 0.1, RIGHT)
    single = accumulated_classes([a], a, TargetConfig(), GRID)
    both = accumulated_classes([a, b], a, TargetConfig(), GRID)
    assert np.array_equal(single, ilm_classes(ray_ilm(a, grid=GRID)))
    for p in LEFT:
        assert single[cell(*p)] == OCCUPIED and both[cell(*p)] == OCCUPIED
    for p in RIGHT:
        # a's rays crossed these, b's stopped there: occupied in 1 of the 2 frames that saw
        # them, the vote's share of 0.5
        assert single[cell(*p)] == FREE and both[cell(*p)] == OCCUPIED
    assert both[cell(3.125, -1.0)] == FREE  # on both frames' rays, before the wall
    # 16 m from a, behind its half of the wall; 14 m from b, beside its half: b's rays alone
    assert single[cell(16.125, 0.625)] == UNKNOWN and both[cell(16.125, 0.625)] == FREE
    assert both[cell(-19.0, -19.0)] == UNKNOWN  # over 15 m from both
    assert both[cell(-14.125, 0.125)] == FREE  # 14 m behind a, 16 m behind b
    # b cast into a's grid is b's own ray ILM moved 8 rows (2 m) towards +x
    own_b = ilm_classes(ray_ilm(b, grid=GRID))
    cast_b = accumulated_classes([a, b], b, TargetConfig(), GRID)  # b's grid, for symmetry
    moved = np.full_like(own_b, UNKNOWN)
    moved[:-8] = own_b[8:]
    assert np.array_equal(ilm_classes(ray_ilm(b, reference_pose=a.ego_pose, grid=GRID)), moved)
    # and the union is symmetric: a's left half lands 8 rows further in b's grid
    for x, y in LEFT:
        r, c = cell(x - 2.0, y)
        assert cast_b[r, c] == OCCUPIED


def test_cells_no_frame_saw_stay_unknown():
    a, b = sweep(0.0, 0.0, LEFT), sweep(2.0, 0.1, RIGHT)
    for rule in ("vote", "dempster"):
        out = accumulated_classes([a, b], a, TargetConfig(rule=rule), GRID)
        seen = ray_ilm(a, grid=GRID)[..., 2] < 1
        seen |= ray_ilm(b, reference_pose=a.ego_pose, grid=GRID)[..., 2] < 1
        assert np.all((out == UNKNOWN) == ~seen)
        assert 0 < seen.sum() < GRID.n_cells**2  # the corners are over 15 m from both


def test_a_passing_car_leaves_no_trail_in_the_vote():
    # ego standing at x = 0; a car at x = 3 hides the wall on one ray in the first frame only
    car = (3.125, 0.125)
    frames = [sweep(0.0, 0.0, [car] + LEFT[1:])] + [sweep(0.0, 0.1 * i, LEFT) for i in (1, 2)]
    vote = accumulated_classes(frames, frames[0], TargetConfig(), GRID)
    # the car's cell: occupied in 1 of the 3 frames that saw it (< 0.5) -> free; the wall cell
    # behind it: seen by the 2 later frames, both occupied
    assert vote[cell(*car)] == FREE and vote[cell(*LEFT[0])] == OCCUPIED
    # a share of a third keeps it
    third = accumulated_classes(frames, frames[0], TargetConfig(occupied_share=1 / 3), GRID)
    assert third[cell(*car)] == OCCUPIED
    # Dempster (paper eq. (5)): [0, .5, .5] (+) [.05, 0, .95] (+) [.05, 0, .95]:
    # m_o = .5 * .95^2 / N > m_f = .5 * (1 - .95^2) / N -> occupied (the trail the vote avoids)
    dem = accumulated_classes(frames, frames[0], TargetConfig(rule="dempster"), GRID)
    assert dem[cell(*car)] == OCCUPIED and dem[cell(*LEFT[0])] == OCCUPIED


def test_the_window_takes_every_frame_step_th_frame_from_the_sample_and_forgets_old_ones():
    # frame i (0.05 s apart) alone sees wall point i; any occupied look counts here
    sweeps = [sweep(0.0, 0.05 * i, [LEFT[i]]) for i in range(6)]
    for step, kept in ((1, {1, 2, 3, 4, 5}), (2, {1, 3, 5})):
        cfg = TargetConfig(before_s=0.1, after_s=0.1, occupied_share=1e-6, frame_step=step)
        window = TargetWindow(cfg, GRID)
        for s in sweeps:
            window.push(s)
        assert window.complete_for(sweeps[2]) and not window.complete_for(sweeps[3])
        out = window.target(sweeps[3])  # its window: frames 1-5 (0.05 to 0.25 s)
        assert {i for i in range(6) if out[cell(*LEFT[i])] == OCCUPIED} == kept
        window.drop_before(sweeps[3].timestamp)
        assert [s for _, s in window.sweeps] == sweeps[1:]


@pytest.fixture(scope="module")
def frames():
    return list(simulate_scene(0, SimConfig(duration_s=1.5)))


CFG = TrainConfig(frame_stride=10)


def _samples(frames, target: TargetConfig):
    return list(scene_samples(frames, replace(CFG, target=target), with_irm=True))


def test_single_frame_targets_are_the_ray_ilm_of_the_frame(frames):
    # the paper's targets (sec. V-C), as evgrid made them before targets had a config
    got = _samples(frames, TargetConfig(kind="single_frame"))
    clean = Preprocessor.from_config(CFG, gate_poses=False)
    want = [ilm_classes(ray_ilm(clean.lidar(f.lidar), grid=CFG.grid)) for f in frames[::10]]
    assert len(got) == len(want) == 3
    for (_, t, _), w in zip(got, want, strict=True):
        assert t.dtype == np.uint8 and np.array_equal(t, w)


@pytest.mark.parametrize("rule", ["vote", "dempster"])
def test_a_window_of_zero_is_the_single_frame(frames, rule):
    single = _samples(frames, TargetConfig(kind="single_frame"))
    zero = _samples(frames, TargetConfig(before_s=0.0, after_s=0.0, rule=rule))
    wide = _samples(frames, TargetConfig(rule=rule))
    for (d0, t0, i0), (d1, t1, i1), (d2, t2, i2) in zip(single, zero, wide, strict=True):
        assert np.array_equal(t0, t1)
        # the inputs never depend on the targets
        assert np.array_equal(d0, d2) and np.array_equal(i0, i2)
    # a window sees more than one frame
    assert sum(np.count_nonzero(t != UNKNOWN) for _, t, _ in wide) > sum(
        np.count_nonzero(t != UNKNOWN) for _, t, _ in single
    )


def test_samples_stream_with_the_window_not_the_scene(frames):
    consumed = []

    def stream():
        for f in frames:
            consumed.append(f)
            yield f

    cfg = replace(CFG, target=TargetConfig(before_s=0.2, after_s=0.2))
    it = scene_samples(stream(), cfg)
    next(it)
    # the first sample (frame 0) comes once a frame past its window (0.2 s at 20 Hz) arrived
    assert len(consumed) == 6 < len(frames)


def test_the_cache_key_follows_the_target():
    keys = {
        TrainConfig(target=t).data_key()
        for t in (
            TargetConfig(),
            TargetConfig(kind="single_frame"),
            TargetConfig(after_s=2.0),
            TargetConfig(rule="dempster"),
        )
    }
    assert len(keys) == 4
    # single-frame targets ignore the window: one cache whatever it says
    assert (
        TrainConfig(target=TargetConfig(kind="single_frame")).data_key()
        == TrainConfig(target=TargetConfig(kind="single_frame", after_s=5.0)).data_key()
    )


@pytest.mark.parametrize(
    "field, value",
    [
        ("kind", "lidar"),
        ("rule", "max"),
        ("before_s", -1.0),
        ("after_s", -0.5),
        ("after_s", "x"),
        ("occupied_share", 0.0),
        ("frame_step", 0),
    ],
)
def test_bad_target_config_is_refused_naming_the_field(field, value):
    with pytest.raises(ValueError, match=rf"TargetConfig\.{field}") as e:
        TargetConfig(**{field: value})
    assert "\n" not in str(e.value)


def test_a_config_saved_before_targets_had_one_reads_as_single_frame():
    from evgrid.learn.train import saved_train_config

    saved = TrainConfig().to_dict()
    assert saved_train_config(saved, "ck").target == TargetConfig()
    del saved["target"]  # as checkpoints trained before it saved their config
    old = saved_train_config(saved, "ck")
    assert old.target.kind == "single_frame"
    assert old.data_key() == replace(TrainConfig(), target=old.target).data_key()
