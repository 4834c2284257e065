"""Deep IRM: the radar input image and the Ev-Net wrapper (evgrid.ism.deep)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evgrid import mass
from evgrid.data.frame import RADAR_COLUMNS, RadarSweep
from evgrid.geometry import SE2, SE3, GridSpec
from evgrid.ism.deep import CHANNELS, DeepIrm, RadarImageParams, radar_image
from evgrid.ism.evnet import CheckpointError, EvNet, EvNetConfig, save_checkpoint

SPEC = GridSpec()


def sweep(
    points, t_us=0, ego=SE3.identity(), sensor=SE3.identity(), channel="RADAR_FRONT"
) -> RadarSweep:
    p = np.zeros((len(points), len(RADAR_COLUMNS)), np.float32)
    for k, d in enumerate(points):
        for name, v in d.items():
            p[k, RADAR_COLUMNS.index(name)] = v
    return RadarSweep(p, sensor, ego, t_us, channel)


def test_image_hand_computed():
    s1 = sweep([{"x": 10.0, "y": 0.01, "rcs": 10.0, "vx_comp": -2.0}], t_us=1_000_000)
    s0 = sweep([{"x": 10.0, "y": 0.01, "rcs": 0.0, "vx_comp": 0.0}], t_us=500_000)
    img = radar_image([s0, s1], SE3.identity(), SPEC)
    assert img.shape == (len(CHANNELS), 512, 512)
    r, c = 128, 255  # x = 10 m is 128 cells ahead of the centre line; y = +0.01 m is just left
    assert img[0, r, c] == pytest.approx(math.log(3.0))
    assert img[1, r, c] == pytest.approx(0.25)  # mean rcs 5 dBsm / 20
    assert img[2, r, c] == pytest.approx(-0.1)  # mean vx -1 m/s / 10
    assert img[4, r, c] == pytest.approx(1.0)  # newest detection is now
    assert np.count_nonzero(img[0]) == 1
    assert img[5, 255, 255] == pytest.approx(math.hypot(0.5, 0.5) * SPEC.resolution / 20.0)


def test_image_moves_old_sweeps_and_rotates_doppler():
    # the old sweep was taken 1 m behind the current pose, by a radar looking left
    left = SE3.from_se2(SE2(0.0, 0.0, math.pi / 2))
    old = sweep(
        [{"x": 5.0, "vx_comp": 3.0}], t_us=0, ego=SE3.from_se2(SE2(-1.0, 0.0, 0.0)), sensor=left
    )
    img = radar_image(
        [old], SE3.identity(), SPEC, now_us=500_000, params=RadarImageParams(horizon_s=1.0)
    )
    # global (-1, 5) -> current ego (-1, 5): row floor(256 + 12.8) = 268, col floor(256 - 64) = 192
    assert img[0, 268, 192] > 0
    assert img[3, 268, 192] == pytest.approx(0.3)  # vx along the radar axis = +y in the ego frame
    assert img[2, 268, 192] == pytest.approx(0.0, abs=1e-7)
    assert img[4, 268, 192] == pytest.approx(0.5)


def test_image_drops_nan_and_handles_empty_and_outside():
    s = sweep([{"x": float("nan")}, {"x": 100.0}, {"x": 1.0, "y": 1.0}])
    img = radar_image([s], SE3.identity(), SPEC)
    assert np.isfinite(img).all() and np.count_nonzero(img[0]) == 1
    empty = radar_image([], SE3.identity(), SPEC)
    assert np.count_nonzero(empty[:5]) == 0


def _checkpoint(tmp_path, grid=SPEC):
    torch.manual_seed(0)
    net = EvNet(EvNetConfig(in_channels=len(CHANNELS), width=4, pool=4, depth=2))
    return save_checkpoint(net, tmp_path / "evnet.safetensors", extra={"grid": grid.to_dict()})


def test_deep_irm_predicts_masses_on_the_simplex(tmp_path):
    deep = DeepIrm(_checkpoint(tmp_path), SPEC)
    m = deep([sweep([{"x": 8.0, "y": 2.0, "rcs": 5.0}])], SE3.identity())
    assert m.shape == (512, 512, 3) and m.dtype == np.float32
    mass.validate(m)
    with pytest.raises(ValueError, match="input image"):
        deep.predict_image(np.zeros((3, 512, 512), np.float32))


def test_deep_irm_refuses_a_checkpoint_for_another_grid(tmp_path):
    with pytest.raises(CheckpointError, match="trained on grid"):
        DeepIrm(_checkpoint(tmp_path, GridSpec(256, 40.0)), SPEC)
    with pytest.raises(ValueError, match="runtime must be one of"):
        DeepIrm(_checkpoint(tmp_path), SPEC, runtime="tensorrt")


def test_shipped_checkpoint_loads_and_predicts_masses():
    from evgrid.data.sweeps import RadarBuffer
    from evgrid.ism.deep import default_checkpoint
    from evgrid_sim import SimConfig, simulate_scene

    path = default_checkpoint()
    assert path.is_file() and path.stat().st_size < 5 * 2**20
    deep = DeepIrm()  # the shipped checkpoint is the default
    assert deep.info["grid"] == SPEC.to_dict() and deep.info["val_iou"]["free"] > 0.8
    # a held-out simulated scene (seed 44, not trained on): the radar the network was trained for
    buffer = RadarBuffer(deep.params.n_sweeps)
    for frame in simulate_scene(44, SimConfig(duration_s=1.0)):
        for sweep in frame.radar_sweeps():
            buffer.push(sweep)
    m = deep(buffer.sweeps(), frame.ego_pose, frame.timestamp)
    mass.validate(m)
    # it has learned something: free space around the vehicle, and not everywhere
    near = m[240:272, 240:272]
    assert (near[..., 0] > near[..., 2]).mean() > 0.5
    assert (m[..., 2] > m[..., 0]).mean() > 0.2


# --- the fast path (DeepIrm.predict) against the plain one (radar_image + predict_image) ---------


def random_scene(rng, n_radars=5, n_sweeps=3):
    """Sweeps of moving radars with random detections, some clustered so that whole 4 x 4 pooling
    blocks are occupied (where a block's max may be negative), some outside the grid or corrupt."""
    sweeps = []
    cols = {c: RADAR_COLUMNS.index(c) for c in ("x", "y", "z", "rcs", "vx_comp", "vy_comp")}
    for r in range(n_radars):
        sensor = SE3.from_se2(
            SE2(rng.uniform(-1, 3), rng.uniform(-1, 1), rng.uniform(-math.pi, math.pi)), 0.5
        )
        for k in range(n_sweeps):
            n = int(rng.integers(300, 500))
            p = np.zeros((n, len(RADAR_COLUMNS)), np.float32)
            p[:, cols["x"]] = rng.uniform(-5, 30, n)
            p[:, cols["y"]] = rng.uniform(-20, 20, n)
            p[:, cols["z"]] = rng.normal(0, 0.3, n)
            p[:, cols["rcs"]] = rng.uniform(-30, 40, n)
            p[:, cols["vx_comp"]] = rng.normal(0, 5, n)
            p[:, cols["vy_comp"]] = rng.normal(0, 5, n)
            # a dense cluster: a 5 cm lattice fills every cell of some pooled blocks, negative
            # values
            m = 256
            gx, gy = np.meshgrid(np.arange(16) * 0.05, np.arange(16) * 0.05)
            p[:m, cols["x"]] = 4.0 + gx.ravel()
            p[:m, cols["y"]] = 1.0 + gy.ravel()
            p[:m, cols["rcs"]] = rng.uniform(-40, -10, m)
            p[:m, cols["vx_comp"]] = rng.uniform(-9, -1, m)
            p[m, cols["rcs"]] = np.nan
            p[m + 1, cols["vx_comp"]] = 300.0
            ego = SE3.from_se2(SE2(-0.8 * (n_sweeps - k), 0.1 * k, 0.02 * k))
            sweeps.append(RadarSweep(p, sensor, ego, 100_000 * k + r, f"RADAR_{r}"))
    return sweeps, SE3.from_se2(SE2(0.0, 0.0, 0.01))


def test_pooled_input_is_the_max_pooled_image(tmp_path):
    deep = DeepIrm(_checkpoint(tmp_path), SPEC, runtime="torch")
    rng = np.random.default_rng(3)
    for _ in range(3):
        sweeps, ego = random_scene(rng)
        img = radar_image(sweeps, ego, SPEC, 250_000, deep.params)
        expected = torch.nn.functional.max_pool2d(torch.from_numpy(img)[None], 4).numpy()
        pooled = deep.pooled_input(sweeps, ego, 250_000)
        assert (expected[0, 1] < 0).any()  # some fully occupied blocks have a negative max
        np.testing.assert_array_equal(pooled, expected)
    empty = deep.pooled_input([], ego)
    assert not empty[0, :5].any() and empty[0, 5].max() > 1.0


@pytest.mark.parametrize("runtime, atol", [("torch", 2e-6), ("onnxruntime", 2e-5)])
def test_fast_path_gives_the_plain_path_masses(runtime, atol):
    from evgrid.ism.runtime import ort_available

    if runtime == "onnxruntime" and not ort_available():
        pytest.skip("onnxruntime is not installed (pip install 'evgrid[fast]')")
    deep = DeepIrm(runtime=runtime)  # the shipped Ev-Net
    assert deep.runtime.name == runtime
    rng = np.random.default_rng(7)
    for _ in range(3):
        sweeps, ego = random_scene(rng)
        plain = deep.predict_image(radar_image(sweeps, ego, SPEC, 300_000, deep.params))
        fast = deep.predict(sweeps, ego, 300_000)
        assert fast.shape == plain.shape and fast.dtype == np.float32
        assert np.abs(fast - plain).max() <= atol
        assert (fast.argmax(-1) != plain.argmax(-1)).sum() <= 2  # only exact ties could flip
        mass.validate(fast)


def test_evidence_to_masses_is_upsample_then_from_evidence():
    from evgrid.ism.deep import evidence_to_masses

    rng = np.random.default_rng(0)
    e = rng.gamma(0.5, 4.0, (2, 128, 128)).astype(np.float32)
    e[:, :3, :3] = 0.0  # vacuous cells
    up = torch.nn.functional.interpolate(
        torch.from_numpy(e)[None], size=(512, 512), mode="bilinear", align_corners=False
    )[0]
    expected = mass.from_evidence(up.permute(1, 2, 0).numpy())
    np.testing.assert_allclose(evidence_to_masses(e, SPEC), expected, rtol=0, atol=2e-7)
    for bad in (-1.0, np.nan, np.inf):
        e2 = e.copy()
        e2[1, 5, 5] = bad
        with pytest.raises(ValueError, match="finite and non-negative"):
            evidence_to_masses(e2, SPEC)


def test_values_outside_the_sensor_range_are_dropped_counted_and_logged_once_per_sweep(
    tmp_path, caplog
):
    deep = DeepIrm(_checkpoint(tmp_path), SPEC, runtime="torch")
    good = {"x": 6.0, "y": 1.0, "rcs": 5.0}
    bad = [
        {"x": 6.0, "y": -1.0, "rcs": 70.0},
        {"x": 6.0, "y": -2.0, "rcs": -65.0},
        {"x": 7.0, "y": 2.0, "vx_comp": 130.0},
        {"x": 7.0, "y": 3.0, "vy_comp": -129.0},
        {"x": 8.0, "y": 4.0, "rcs": float("inf")},
    ]
    s = sweep([good, *bad], t_us=123, channel="RADAR_FRONT_LEFT")
    with caplog.at_level("WARNING", logger="evgrid.ism.deep"):
        for _ in range(3):  # the sweep stays in the buffer for several updates
            pooled = deep.pooled_input([s], SE3.identity())
            img = radar_image([s], SE3.identity(), SPEC)
    assert np.count_nonzero(img[0]) == 1 and int(np.count_nonzero(pooled[0, 0])) == 1
    assert deep.n_dropped == 5
    msgs = [r.getMessage() for r in caplog.records]
    fast_msgs = [m for m in msgs if "RADAR_FRONT_LEFT" in m]
    assert len(fast_msgs) == 2  # once by the fast path, once by the plain one: not once per update
    assert "dropped 5 of 6 detections (1 NaN/inf, 4 outside" in fast_msgs[0]
