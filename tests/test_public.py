"""The public surface: `import evgrid` is light and gives the names a user needs."""

from __future__ import annotations

import subprocess
import sys

import evgrid


def test_import_evgrid_is_light():
    code = (
        "import sys, evgrid; "
        "print(sorted(m for m in ('torch', 'numba', 'matplotlib') if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert out == "[]"


def test_every_public_name_resolves():
    for name in evgrid.__all__:
        assert getattr(evgrid, name) is not None, name
    assert "OccupancyMapper" in dir(evgrid)


def test_the_docstring_example_runs(tmp_path):
    mapper = evgrid.OccupancyMapper(evgrid.MapperConfig(maps=("ray_ilm", "fused")))
    for frame in evgrid.SimSource((4,), duration_s=1.0).load("sim-000004"):
        mapper.process(frame)
    evgrid.save_map(mapper.maps["fused"], tmp_path / "fused.npz")
    assert evgrid.load_map(tmp_path / "fused.npz").tiles.keys() == mapper.maps["fused"].tiles.keys()


def test_ism_never_imports_learn():
    """The ISMs (Ev-Net and its checkpoints included) stand without the training code."""
    code = (
        "import sys, evgrid.ism, evgrid.ism.deep, evgrid.ism.evnet; "
        "print(sorted(m for m in sys.modules if m.startswith('evgrid.learn')))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert out == "[]"
