"""Install hints: every optional import's error names its extra with a command that works from
where evgrid runs (a source checkout here), all from :func:`evgrid.install_hint`."""

from __future__ import annotations

import importlib.util
import re
import shutil
import sys
import tomllib
from pathlib import Path

import pytest

import evgrid

ROOT = Path(__file__).resolve().parents[1]


def _extras(root: Path) -> set[str]:
    with open(root / "pyproject.toml", "rb") as f:
        return set(tomllib.load(f)["project"]["optional-dependencies"])


def _assert_works_here(message: str, extra: str) -> None:
    """The message holds ``pip install -e '<path>[extra]'`` whose path, taken from the current
    folder, is this checkout, which declares the extra."""
    m = re.search(r"pip install -e '([^'\[]+)\[(\w+)\]'", message)
    assert m, message
    assert m.group(2) == extra, message
    assert (Path.cwd() / m.group(1)).resolve() == ROOT, message
    assert extra in _extras(ROOT), extra
    assert f"'evgrid[{extra}]'" not in message  # not the wheel's command as well


def _ros_require(module, extra):
    from evgrid.ros import require

    return lambda: require(module, extra)


def _rig(tmp_path):
    from evgrid.data.bag.rig import load_rig

    p = tmp_path / "rig.yaml"
    p.write_text("lidar: {topic: /points}\n")
    return lambda: load_rig(p)


def _onnxruntime(monkeypatch):
    import evgrid.ism.runtime as rt

    monkeypatch.setattr(rt, "ort_available", lambda: False)
    return lambda: rt.make_runtime(None, (6, 32, 32), "onnxruntime")


def _devkit():
    from evgrid.data.nuscenes import _devkit

    return _devkit


def _splits(tmp_path):
    from evgrid.data.nuscenes import nuscenes_splits

    return lambda: nuscenes_splits(tmp_path, "v1.0-mini")


def _ray():
    from evgrid.engine_ray import _import_ray

    return lambda: _import_ray(False)


def _live():
    from evgrid.live.dds import Graph

    return lambda: Graph(0)


# (what fails, the modules made unimportable, the extra it names)
CASES = {
    "rosbags": (lambda tp, mp: _ros_require("rosbags", "ros"), ["rosbags"], "ros"),
    "mcap": (lambda tp, mp: _ros_require("mcap", "ros"), ["mcap"], "ros"),
    "rerun": (lambda tp, mp: _ros_require("rerun", "rerun"), ["rerun"], "rerun"),
    "rig yaml": (lambda tp, mp: _rig(tp), ["yaml"], "ros"),
    "onnxruntime": (lambda tp, mp: _onnxruntime(mp), [], "fast"),
    "nuscenes devkit": (lambda tp, mp: _devkit(), ["nuscenes.nuscenes"], "nuscenes"),
    "nuscenes splits": (lambda tp, mp: _splits(tp), ["nuscenes.utils.splits"], "nuscenes"),
    "ray": (lambda tp, mp: _ray(), ["ray"], "ray"),
    "cyclonedds": (lambda tp, mp: _live(), ["cyclonedds"], "live"),
}


@pytest.mark.parametrize("where", ["checkout", "elsewhere"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_missing_extra_names_a_command_that_works_from_this_checkout(
    case, where, tmp_path, monkeypatch
):
    make, blocked, extra = CASES[case]
    call = make(tmp_path, monkeypatch)  # import evgrid's module before blocking its extra
    for name in blocked:
        monkeypatch.setitem(sys.modules, name, None)  # import raises ImportError
    monkeypatch.chdir(ROOT if where == "checkout" else tmp_path)
    with pytest.raises(Exception) as info:  # ImportError, NuScenesError, RayEngineError
        call()
    _assert_works_here(str(info.value), extra)
    if where == "checkout":
        assert f"pip install -e '.[{extra}]'" in str(info.value)


def test_from_a_parent_folder_the_hint_is_relative(monkeypatch):
    monkeypatch.chdir(ROOT.parent)
    hint = evgrid.install_hint("ros")
    assert hint == f"pip install -e '{ROOT.name}[ros]'"
    _assert_works_here(hint, "ros")


def _package_copy(base: Path, *parts: str):
    """evgrid's ``package`` module copied to ``base/parts/evgrid`` and loaded from there."""
    pkg = base.joinpath(*parts, "evgrid")
    pkg.mkdir(parents=True)
    shutil.copy(ROOT / "src" / "evgrid" / "package.py", pkg / "package.py")
    spec = importlib.util.spec_from_file_location("evgrid_copy", pkg / "package.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_an_installed_wheel_gets_the_wheel_command(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    wheel = _package_copy(tmp_path, "lib", "python3.11", "site-packages")
    assert wheel.source_checkout() is None
    assert wheel.install_hint("ros") == "pip install 'evgrid[ros]'"


def test_a_checkout_is_told_by_its_pyproject(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "proj").mkdir()
    mod = _package_copy(tmp_path / "proj", "src")
    assert mod.source_checkout() is None  # no pyproject.toml: not a checkout we can name
    (tmp_path / "proj" / "pyproject.toml").write_text('[project]\nname = "other"\n')
    assert mod.source_checkout() is None  # another project's src layout
    (tmp_path / "proj" / "pyproject.toml").write_text('[project]\nname = "evgrid"\n')
    assert mod.source_checkout() == (tmp_path / "proj").resolve()
    assert mod.install_hint("fast") == "pip install -e 'proj[fast]'"


def test_the_cli_prints_messages_as_they_are():
    from evgrid.console import error_line

    # no rewriting on the way out: the modules already say what works
    text = "x needs y (pip install 'evgrid[ros]')"
    assert error_line(ImportError(text)) == text


def test_no_module_writes_its_own_hint():
    src = ROOT / "src" / "evgrid"
    own = [
        f"{p.relative_to(ROOT)}:{i}"
        for p in sorted(src.rglob("*.py"))
        if p.name != "package.py" or p.parent != src
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if re.search(r"[\"'].*pip install", line) and "``" not in line
    ]
    assert not own, own
