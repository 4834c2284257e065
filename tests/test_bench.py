"""`evgrid bench` (evgrid_lab.bench): per-frame components, the deep IRM's parts, the rig and the
end-to-end run."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evgrid.geometry import GridSpec
from evgrid.ism.deep import CHANNELS, DeepIrm, radar_image
from evgrid.ism.evnet import EvNet, EvNetConfig, save_checkpoint
from evgrid_lab.bench import interleaved_ms, run_bench
from evgrid_sim.synthetic import street_radar_sweeps


def _tiny(tmp_path):
    torch.manual_seed(0)
    net = EvNet(EvNetConfig(in_channels=len(CHANNELS), width=4, depth=2))
    return save_checkpoint(net, tmp_path / "tiny.safetensors", extra={"grid": GridSpec().to_dict()})


def test_plain_path_gives_the_fast_path_masses(tmp_path):
    # the deep IRM's plain path (bench's "old:" parts) against what the mapper runs; the bench's
    # --old-path, which mapped whole scenes with it, is gone (issue 23)
    deep = DeepIrm(_tiny(tmp_path), runtime="torch")
    sweeps, ego = street_radar_sweeps(n_sweeps=2)
    old = deep.predict_image(radar_image(sweeps, ego, deep.grid, 1_000_000, deep.params))
    assert np.abs(old - deep.predict(sweeps, ego, 1_000_000)).max() <= 2e-6


def test_interleaved_ms_times_each_function():
    calls = []
    ms = interleaved_ms({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}, repeat=3)
    assert set(ms) == {"a", "b"} and all(v >= 0 for v in ms.values())
    assert calls == ["a", "b"] * 4  # one warm-up call each, then in turns


def test_run_bench_reports_components_rig_and_end_to_end(tmp_path):
    res = run_bench(
        0.5,
        str(_tiny(tmp_path)),
        repeats=1,
        rig_s=0.5,
        end_to_end_s=0.5,
        timing_repeat=1,
    )
    per = res["per_frame"]
    assert set(per) == {"six_maps", "fused_only"}
    for label in per:
        assert {"deep_irm", "warp", "fuse", "step_total"} <= set(per[label]["components_ms"])
    assert "ray_ilm" in per["six_maps"]["components_ms"]
    parts = res["deep_irm_parts_ms"]
    assert parts["exactness_vs_plain"]["torch"]["max_abs_mass_diff"] <= 2e-6
    assert "new: pooled_input" in parts["ms"] and "old: radar_image" in parts["ms"]
    assert (
        res["rig"]["lidar_hz"] == 10.0
        and res["rig"]["fused_only"]["updates"] == res["rig"]["frames"]
    )
    assert res["end_to_end"]["frames"] > 0 and res["end_to_end"]["frames_per_second"] > 0
    dyn = res["dynamic_score_ms"]
    assert dyn["scene_on"] > 0 and dyn["scene_off"] > 0
    assert dyn["scene_cost"] == pytest.approx(dyn["scene_on"] - dyn["scene_off"])
