"""Radars drawn per scene for training, radars outside the draw, and the transfer measurement."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid.data.frame import RADAR_CHANNELS
from evgrid.sources import SimSource, source_from_dict, source_to_dict
from evgrid_sim.config import RadarConfig, SimConfig
from evgrid_sim.radar_variants import (
    NOMINAL,
    OUT_OF_RANGE,
    TRAINING_RANGES,
    RadarRanges,
    RadarVariant,
)


def test_a_variant_changes_the_radar_by_hand_computed_amounts():
    base = SimConfig(duration_s=2.0)
    r = base.radar
    v = RadarVariant(
        sensitivity_db=40 * math.log10(2.0),
        noise_scale=2.0,
        clutter_scale=3.0,
        ghost_db=5.0,
        channels=("RADAR_FRONT", "RADAR_BACK_RIGHT"),
        rate_hz=7.0,
    )
    c = v.apply(base)
    # +12.04 dB of signal is the 40 log10 range law's reference range doubled
    assert c.radar.reference_range_m == pytest.approx(2 * r.reference_range_m)
    assert c.radar.range_noise_m == pytest.approx(2 * r.range_noise_m)
    assert c.radar.azimuth_noise_deg == pytest.approx(2 * r.azimuth_noise_deg)
    assert c.radar.far_azimuth_noise_deg == pytest.approx(2 * r.far_azimuth_noise_deg)
    assert c.radar.road_clutter_rate == pytest.approx(3 * r.road_clutter_rate)
    assert c.radar.doppler_noise_mps == pytest.approx(2 * r.doppler_noise_mps)
    assert c.radar.clutter_rate == pytest.approx(3 * r.clutter_rate)
    assert c.radar.multipath_loss_db == pytest.approx(r.multipath_loss_db - 5.0)
    assert c.rig.radar_channels == ("RADAR_FRONT", "RADAR_BACK_RIGHT") and c.rig.rates(13.0) == (
        7.0,
        7.0,
    )
    # nothing else moves: the town, the drive, the lidar
    assert (c.lidar, c.world, c.ego, c.duration_s) == (
        base.lidar,
        base.world,
        base.ego,
        base.duration_s,
    )
    assert NOMINAL.apply(base).radar == r


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_every_drawn_radar_lies_in_the_training_ranges(seed):
    v = TRAINING_RANGES.draw(seed)
    assert TRAINING_RANGES.outside(v) == []
    assert v == TRAINING_RANGES.draw(seed)
    assert "RADAR_FRONT" in v.channels and set(v.channels) <= set(RADAR_CHANNELS)


def test_the_draw_varies_and_every_test_radar_lies_outside():
    draws = [TRAINING_RANGES.draw(s) for s in range(40)]
    assert (
        len({len(d.channels) for d in draws}) == 3
        and len({round(d.noise_scale, 3) for d in draws}) == 40
    )
    for name, v in OUT_OF_RANGE.items():
        assert TRAINING_RANGES.outside(v), name
    assert TRAINING_RANGES.outside(NOMINAL) == []


@pytest.mark.parametrize(
    "kwargs, word",
    [
        ({"noise_scale": -1.0}, "noise_scale"),
        ({"channels": ("RADAR_FRONT", "RADAR_FRONT")}, "channels"),
        ({"channels": ("RADAR_ROOF",)}, "RADAR_ROOF"),
        ({"rate_hz": 0.0}, "rate_hz"),
    ],
)
def test_bad_variants_are_named(kwargs, word):
    with pytest.raises(ValueError, match=word):
        RadarVariant(**kwargs)


def test_bad_ranges_are_named():
    with pytest.raises(ValueError, match="noise_scale"):
        RadarRanges(noise_scale=(2.0, 1.0))
    with pytest.raises(ValueError, match="n_radars"):
        RadarRanges(n_radars=(0, 6))
    assert RadarRanges.from_dict(TRAINING_RANGES.to_dict()) == TRAINING_RANGES


def test_sim_source_keeps_its_radar_through_a_run_config():
    for src in (
        SimSource((4,), 2.0, radar=OUT_OF_RANGE["all at once"]),
        SimSource((4, 9), 2.0, radar_ranges=TRAINING_RANGES),
    ):
        assert source_from_dict(source_to_dict(src)) == src
    with pytest.raises(ValueError, match="not both"):
        SimSource((4,), radar=NOMINAL, radar_ranges=TRAINING_RANGES)


def test_same_seed_same_town_whatever_the_radar():
    plain, two = (
        SimSource((4,), 1.0),
        SimSource((4,), 1.0, radar=OUT_OF_RANGE["two radars (front, back left)"]),
    )
    fa, fb = next(iter(plain.load(plain.names()[0]))), next(iter(two.load(two.names()[0])))
    assert (fa.lidar.points == fb.lidar.points).all() and fa.ego_pose == fb.ego_pose
    assert set(fb.radar) == {"RADAR_FRONT", "RADAR_BACK_LEFT"} and set(fa.radar) == set(
        RADAR_CHANNELS
    )
    assert RadarConfig().rate_hz == plain.config(4).radar.rate_hz


def test_transfer_scores_each_radar_on_the_same_scenes(tmp_path):
    from evgrid.ism.deep import default_checkpoint
    from evgrid_lab.transfer import (
        CALIBRATED,
        measure_transfer,
        transfer_markdown,
        transfer_sources,
    )

    sources = transfer_sources(1, 1000, 1.0)
    assert len({s.seeds for s in sources.values()}) == 1 and all(
        s % 5 == 4 for s in sources[CALIBRATED].seeds
    )
    picked = {k: sources[k] for k in (CALIBRATED, "all at once")}
    res = measure_transfer(default_checkpoint(), picked, tmp_path)
    assert (
        res[CALIBRATED]["outside_training"] == []
        and "channels" in res["all at once"]["outside_training"]
    )
    for r in res.values():
        assert r["samples"] >= 1 and all(
            0.0 <= r["deep_irm"][c] <= 1.0 for c in ("free", "unknown")
        )
    assert "| all at once |" in transfer_markdown(res)


def test_transfer_command_writes_its_table(tmp_path):
    from typer.testing import CliRunner

    from evgrid.cli import app

    r = CliRunner().invoke(
        app, ["transfer", "--scenes", "1", "--duration", "0.5", "--out", str(tmp_path)]
    )
    assert r.exit_code == 0, r.output
    import json

    res = json.loads((tmp_path / "transfer.json").read_text())["radars"]
    assert (
        set(OUT_OF_RANGE) < set(res)
        and (tmp_path / "transfer.md").read_text().count("\n") == len(res) + 2
    )


def test_transfer_makes_samples_as_the_checkpoint_was_trained(tmp_path):
    """A checkpoint trained on every frame of a coarser grid is scored on samples made so, not on
    defaults."""
    from evgrid.geometry import GridSpec
    from evgrid.ism.deep import default_checkpoint
    from evgrid.ism.evnet import load_checkpoint, save_checkpoint
    from evgrid.learn.train import TrainConfig
    from evgrid_lab.transfer import CALIBRATED, measure_transfer, transfer_sources

    ck = load_checkpoint(default_checkpoint())
    picked = {CALIBRATED: transfer_sources(1, 1000, 1.0)[CALIBRATED]}
    trained = TrainConfig(frame_stride=1, grid=GridSpec(128, 40.0))
    path = save_checkpoint(
        ck.model, tmp_path / "ck.safetensors", {**ck.extra, "config": trained.to_dict()}
    )
    res = measure_transfer(path, picked, tmp_path / "cache")[CALIBRATED]
    assert res["samples"] == 20  # 1 s at 20 Hz, every frame
    made = [p.name for p in (tmp_path / "cache").glob("*/*") if p.is_dir()]
    assert made == [TrainConfig(frame_stride=1, grid=GridSpec(128, 40.0)).data_key()]
