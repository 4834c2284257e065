"""Evidence per distance seen: evgrid.ism.evidence, and the mapper passing it the distance
travelled (docs/equations.md#evidence-per-distance-seen)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid import mass
from evgrid.config import MapperConfig
from evgrid.data.frame import Frame, LidarSweep
from evgrid.geometry import SE3
from evgrid.ism.evidence import EvidenceParams, free_mass_per_distance
from evgrid.mapper import OccupancyMapper
from evgrid.serial import ConfigError

PER_METRE = EvidenceParams(reference_m=1.0)  # one metre a look: round figures by hand
DEFAULT = EvidenceParams()
PER_LOOK = EvidenceParams(mode="per_look")


@pytest.mark.parametrize(
    ("speed", "rate", "ilm", "irm"),
    [
        # 10 m/s at 10 Hz: 1 m an update, the reference: the paper's constants
        (10.0, 10.0, 0.05, 0.3),
        # 30 m/s at 10 Hz: 3 m, three reference looks: 1 - 0.95^3, 1 - 0.7^3
        (30.0, 10.0, 0.142625, 0.657),
        # 10 m/s at 20 Hz: 0.5 m, half a look: 1 - sqrt(0.95), 1 - sqrt(0.7)
        (10.0, 20.0, 0.0253206, 0.1633399),
        # 30 m/s at 5 Hz: 6 m: 1 - 0.95^6, 1 - 0.7^6
        (30.0, 5.0, 0.2649081, 0.882351),
    ],
)
def test_free_mass_per_update_by_hand(speed, rate, ilm, irm):
    dt = 1.0 / rate
    assert PER_METRE.free_mass(0.05, speed * dt, dt) == pytest.approx(ilm, abs=1e-6)
    assert PER_METRE.free_mass(0.3, speed * dt, dt) == pytest.approx(irm, abs=1e-6)
    # the paper's per-look constant, whatever the speed and rate
    assert PER_LOOK.free_mass(0.05, speed * dt, dt) == 0.05
    assert PER_LOOK.free_mass(0.3, speed * dt, dt) == 0.3


def test_the_default_reference_is_a_look_at_city_speed():
    # 0.65 m: one update at 10 Hz and 6.5 m/s (the simulated towns' mean speed) is one of the
    # paper's looks; 30 m/s at 10 Hz is 3 / 0.65 looks: 1 - 0.95^4.615, 1 - 0.7^4.615
    assert DEFAULT.reference_m == 0.65
    assert DEFAULT.free_mass(0.05, 0.65, 0.1) == pytest.approx(0.05, abs=1e-9)
    assert DEFAULT.free_mass(0.3, 0.65, 0.1) == pytest.approx(0.3, abs=1e-9)
    assert DEFAULT.free_mass(0.05, 3.0, 0.1) == pytest.approx(0.2108022, abs=1e-6)
    assert DEFAULT.free_mass(0.3, 3.0, 0.1) == pytest.approx(0.8072174, abs=1e-6)


def test_standstill_floor_and_gap_cap():
    # standing at 10 Hz: 1 m/s x 0.1 s = 0.1 m: 1 - 0.95^0.1
    assert PER_METRE.free_mass(0.05, 0.0, 0.1) == pytest.approx(0.00511616, abs=1e-7)
    assert PER_METRE.step_m(0.0, 0.1) == pytest.approx(0.1)
    # a 60 m gap counts 15 m (the cap): 1 - 0.95^15
    assert PER_METRE.step_m(60.0, 2.0) == 15.0
    assert PER_METRE.free_mass(0.05, 60.0, 2.0) == pytest.approx(0.5367088, abs=1e-6)
    assert free_mass_per_distance(0.05, 0.0) == 0.0
    assert free_mass_per_distance(1.0, 0.5) == 1.0
    with pytest.raises(ValueError, match="travelled_m must be >= 0"):
        PER_METRE.step_m(-1.0, 0.1)


def test_bad_evidence_params_are_named():
    with pytest.raises(ValueError, match="EvidenceParams.mode must be one of"):
        EvidenceParams(mode="per_second")
    with pytest.raises(ValueError, match="EvidenceParams.reference_m must be > 0"):
        EvidenceParams(reference_m=0.0)


def _updates_to_free(m_f: float) -> int:
    """Dempster updates of [m_f, 0, 1 - m_f] on a vacuous cell until free beats unknown."""
    cell = np.array([0.0, 0.0, 1.0])
    look = np.array([m_f, 0.0, 1.0 - m_f])
    for n in range(1, 100_000):
        cell = mass.dempster(cell, look)
        if cell[0] > cell[2]:
            return n
    raise AssertionError("never free")


@settings(max_examples=40, deadline=None)
@given(
    speed=st.floats(2.0, 40.0),
    rate=st.floats(2.0, 50.0),
)
def test_updates_to_free_scale_with_distance_not_count(speed, rate):
    """A cell turns free-dominant after the same distance seen, at any speed and rate: the
    number of updates is that distance over the step, not a constant count of looks."""
    step = speed / rate
    n = _updates_to_free(PER_METRE.free_mass(0.05, step, 1.0 / rate))
    # (1 - 0.05)^(L / 1 m) = 1/2: L = 13.51 m of road, whatever the split into updates
    distance = math.log(0.5) / math.log(0.95)
    assert (n - 1) * step < distance + 1e-6 and n * step >= distance - 1e-6
    # the paper's constant: always 14 looks, so the distance grows with the step
    assert _updates_to_free(PER_LOOK.free_mass(0.05, step, 1.0 / rate)) == 14


def _frames(speed: float, rate: float, n: int):
    """Frames at ``rate`` Hz driving +x at ``speed`` m/s, each with one lidar return 10 m
    ahead (ego frame, z = 1 m)."""
    pts = np.array([[10.0, 0.0, 1.0, 50.0, 0.0]], np.float32)
    for k in range(n):
        t = int(1_000_000 + k * 1e6 / rate)
        pose = SE3(np.eye(3), [100.0 + speed * k / rate, 50.0, 0.0])
        sweep = LidarSweep(pts, SE3.identity(), pose, t)
        yield Frame("s", k, t, pose, k % 5 == 0, sweep)


@pytest.mark.parametrize(("speed", "rate"), [(10.0, 10.0), (30.0, 10.0), (30.0, 5.0)])
def test_the_mapper_gives_each_update_its_distance(speed, rate):
    """Through the mapper: the ray ILM's free cells carry the mass of the distance travelled
    since the last update (the first update: one period standing)."""
    for evidence in (PER_METRE, PER_LOOK):
        config = MapperConfig(maps=("ray_ilm",), update_rate_hz=rate, evidence=evidence)
        mapper = OccupancyMapper(config)
        for k, frame in enumerate(_frames(speed, rate, 3)):
            assert mapper.process(frame)
            free = mapper.last_isms["ray_ilm"][..., 0].max()
            travelled = 0.0 if k == 0 else speed / rate
            want = evidence.free_mass(0.05, travelled, 1.0 / rate)
            assert free == pytest.approx(want, abs=1e-6)
            if evidence is PER_METRE and k > 0:
                assert mapper.last_step_m == pytest.approx(speed / rate)


def test_per_look_is_settable_by_name():
    from evgrid.config import RunConfig, resolve_config

    run = resolve_config(RunConfig, overrides=[("mapper.evidence.mode", "per_look")])
    assert run.mapper.evidence.mode == "per_look"
    assert MapperConfig().evidence.mode == "per_metre"
    with pytest.raises(ConfigError, match="per_second"):
        resolve_config(RunConfig, overrides=[("mapper.evidence.mode", "per_second")])
