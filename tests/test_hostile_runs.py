"""Runs that behave under hostile conditions (issue 26, issue 24 point 2): configs of absurd size,
two runs into one folder, a run killed or interrupted midway, a scene that raises, folders and
files in the way. Small simulated scenes with the geometric maps only (no Ev-Net)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from evgrid.cli import app
from evgrid.config import ConfigError, MapperConfig, OutputConfig, RunConfig, load_config
from evgrid.outdir import LOCK_NAME, MARKER_NAME, RunLockedError, results_folder

runner = CliRunner()
SRC = str(Path(__file__).resolve().parents[1] / "src")
#: geometric maps only: fast, and no checkpoint to load
FAST = ["--maps", "ray_ilm,ray_irm", "--no-figures", "--duration", "1"]


def _default_sigint() -> None:
    # the child's Ctrl-C as a terminal's: a test process (a pytest-xdist worker, or a library an
    # earlier test loaded) may ignore or block SIGINT, and a child inherits both; Python then
    # installs no KeyboardInterrupt and the run ignores the signal
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _evgrid(*args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.Popen(
        [sys.executable, "-m", "evgrid.cli", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_default_sigint,
    )


def _scores(out: Path) -> dict:
    s = json.loads((out / "summary.json").read_text())
    return {k: s[k] for k in ("scenes", "maps", "vs_truth", "failed")}


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@pytest.mark.parametrize(
    "field,value,words",
    [
        ("threads", 1000, ["threads", "core"]),
        ("grid", {"n_cells": 100000, "length_m": 40.0}, ["n_cells", "GiB"]),
        ("tile_cells", 1000000, ["tile_cells", "TiB"]),
    ],
)
def test_sizes_beyond_the_machine_are_refused_naming_the_field(tmp_path, field, value, words):
    d = RunConfig().to_dict()
    d["mapper"][field] = value
    path = tmp_path / "config.json"
    path.write_text(json.dumps(d))
    with pytest.raises(ConfigError) as e:
        load_config(path)
    assert str(path) in str(e.value) and all(w in str(e.value) for w in words), e.value
    r = runner.invoke(app, ["map", "--config", str(path), "--out", str(tmp_path / "o")])
    assert r.exit_code == 1 and all(w in r.output for w in words) and "Traceback" not in r.output
    assert not (tmp_path / "o").exists()
    with pytest.raises(ValueError, match="threads"):
        MapperConfig(threads=10 * (os.cpu_count() or 1))


def test_a_second_run_into_a_held_folder_is_refused_naming_the_holder(tmp_path):
    out = tmp_path / "out"
    with results_folder(out):
        assert (out / LOCK_NAME).is_file()
        with pytest.raises(RunLockedError, match=f"pid {os.getpid()} on {socket.gethostname()}"):
            with results_folder(out, overwrite=True):
                pass
        r = runner.invoke(app, ["evaluate", *FAST, "--scenes", "1", "--out", str(out)])
        assert r.exit_code == 1 and "in use by another evgrid run" in r.output, r.output
    assert not (out / LOCK_NAME).exists()  # released with the run


def test_a_stale_lock_is_taken_over_with_a_warning(tmp_path, caplog):
    out = tmp_path / "out"
    out.mkdir()
    host = socket.gethostname()
    (out / LOCK_NAME).write_text(json.dumps({"pid": _dead_pid(), "host": host, "started": 0}))
    with results_folder(out, resume=True):
        pass
    assert "taking over the lock of a run that is gone" in caplog.text
    assert not (out / LOCK_NAME).exists()


def test_an_out_folder_with_other_content_is_refused_unless_overwrite(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    args = ["evaluate", *FAST, "--scenes", "1", "--workers", "1", "--out", str(out)]
    r = runner.invoke(app, args)
    assert r.exit_code == 1 and "already holds results" in r.output and "--overwrite" in r.output
    r = runner.invoke(app, [*args, "--overwrite"])
    assert r.exit_code == 0, r.output
    assert (out / "notes.txt").read_text() == "mine"  # results go into the folder
    assert (out / "sim-000004" / MARKER_NAME).is_file()
    # the scene folder names its own source and scene: --config maps that scene, not defaults
    scene = load_config(out / "sim-000004" / "config.json")
    assert scene.scenes == ("sim-000004",) and scene.source["seeds"] == [4]
    file = tmp_path / "a-file"
    file.write_text("x")
    r = runner.invoke(app, ["evaluate", *FAST, "--out", str(file)])
    assert r.exit_code == 1 and "is a file" in r.output


def test_simulate_into_a_file_and_a_split_with_no_scenes_say_what_is_there(tmp_path):
    file = tmp_path / "f"
    file.write_text("x")
    r = runner.invoke(app, ["simulate", "--out", str(file), "--duration", "0.2"])
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert r.exit_code == 1 and len(lines) == 1 and "is a file" in lines[0], r.output
    sims = tmp_path / "sims"
    r = runner.invoke(app, ["simulate", "--out", str(sims), "--seed", "0", "--duration", "0.2"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["map", "--sim-dir", str(sims), "--out", str(tmp_path / "o")])
    assert r.exit_code == 1 and "split 'val'" in r.output and "1 train" in r.output, r.output


def test_a_scene_that_raises_is_named_while_the_others_finish(tmp_path):
    sims = tmp_path / "sims"
    r = runner.invoke(
        app, ["simulate", "--out", str(sims), "--seed", "4", "--scenes", "6", "--duration", "0.5"]
    )
    assert r.exit_code == 0, r.output
    bad = sims / "sim-000009.npz"
    bad.write_bytes(bad.read_bytes()[:1000])  # truncated
    out = tmp_path / "out"
    args = ["evaluate", *FAST, "--sim-dir", str(sims), "--workers", "1", "--out", str(out)]
    r = runner.invoke(app, args)
    assert r.exit_code == 1 and "1 scene(s) failed" in r.output and "sim-000009" in r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scenes"] == ["sim-000004"] and list(summary["failed"]) == ["sim-000009"]
    assert str(bad) in summary["failed"]["sim-000009"]
    assert (out / "sim-000004" / MARKER_NAME).is_file()
    assert not (out / "sim-000009" / MARKER_NAME).exists()
    # the table is printed whole, not wrapped at 80 columns, when the output is no terminal
    rows = [ln for ln in r.output.splitlines() if ln.startswith("| `ray_irm` |")]
    assert all(ln.endswith("|") for ln in rows) and max(map(len, rows)) > 80, r.output


def test_resume_after_a_kill_gives_the_summary_of_an_uninterrupted_run(tmp_path):
    sims = tmp_path / "sims"
    r = runner.invoke(
        app, ["simulate", "--out", str(sims), "--seed", "4", "--scenes", "6", "--duration", "2"]
    )
    assert r.exit_code == 0, r.output
    common = ["evaluate", "--maps", "ray_ilm,ray_irm", "--sim-dir", str(sims), "--workers", "1"]
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    r = runner.invoke(app, [*common, "--out", str(whole)])
    assert r.exit_code == 0, r.output
    p = _evgrid(*common, "--out", str(killed))
    marker = killed / "sim-000004" / MARKER_NAME
    deadline = time.time() + 300
    while not marker.exists() and p.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    p.send_signal(signal.SIGKILL)  # no clean-up at all: the lock and a half scene stay
    p.wait()
    assert marker.exists() and not (killed / "summary.json").exists()
    assert (killed / LOCK_NAME).exists()
    r = runner.invoke(app, [*common, "--out", str(killed)])
    assert r.exit_code == 1 and "--resume" in r.output  # a plain re-run does not mix results
    r = runner.invoke(app, [*common, "--out", str(killed), "--resume"])
    assert r.exit_code == 0, r.output
    assert "kept: ['sim-000004']" in r.output
    assert _scores(killed) == _scores(whole)
    # a changed config is refused, naming the fields that differ (issue 39); nothing is redone
    r = runner.invoke(app, [*common, "--out", str(killed), "--resume", "--update-rate", "5"])
    assert r.exit_code == 1 and "changed config (mapper.update_rate_hz)" in r.output, r.output
    assert _scores(killed) == _scores(whole)


def test_ctrl_c_stops_cleanly_keeps_whole_files_and_resumes(tmp_path):
    out = tmp_path / "out"
    args = ["map", "--maps", "ray_ilm,ray_irm", "--no-figures", "--scenes", "2", "--duration"]
    p = _evgrid(*args, "3", "--export", "mcap", "--out", str(out))
    # the exporter's temporary file of the second scene (evgrid.export._files.AtomicFile)
    scene2 = out / "sim-000009"
    t0 = time.time()
    while (
        not (seen := list(scene2.glob(".sim-000009.mcap.*.part")))
        and p.poll() is None
        and time.time() < t0 + 300
    ):
        time.sleep(0.02)
    # at once: the scene takes seconds, but a fast machine once finished it within a wait of
    # half a second here, so the run ended without an interruption
    state = f"after {time.time() - t0:.1f} s: part {seen}, exit {p.poll()}"
    p.send_signal(signal.SIGINT)
    stdout, err = p.communicate(timeout=120)
    assert p.returncode == 130, f"{state}\nstderr: {err[-2000:]}\nstdout: {stdout[-2000:]}"
    assert "interrupted: 1 of 2 scene(s) complete" in err and "--resume" in err, err
    assert (out / "sim-000004" / "sim-000004.mcap").is_file()
    assert not list(out.rglob(".partial-*")) and not list(out.rglob("*.tmp"))
    assert not list(out.rglob("*.part"))  # the interrupted export aborted at once
    assert not (out / "sim-000009" / "sim-000009.mcap").exists()
    assert not (out / LOCK_NAME).exists()
    r = runner.invoke(app, [*args, "3", "--export", "mcap", "--out", str(out), "--resume"])
    assert r.exit_code == 0, r.output
    assert (out / "sim-000009" / "sim-000009.mcap").is_file()
    assert json.loads((out / "summary.json").read_text())["scenes"] == ["sim-000004", "sim-000009"]


def test_maps_without_the_reference_say_no_iou_can_be_computed(tmp_path):
    r = runner.invoke(
        app,
        [
            "evaluate",
            "--maps",
            "ray_irm",
            "--duration",
            "1",
            "--scenes",
            "1",
            "--out",
            str(tmp_path),
        ],
    )
    assert r.exit_code == 0, r.output
    assert "no IoU can be computed" in r.output and "ray_ilm" in r.output


def test_dropped_scenes_are_reported_with_why(tmp_path, monkeypatch):
    import evgrid.data.nuscenes as nus
    import evgrid.sources as sources
    from evgrid.runs import RunEvents, map_scenes

    monkeypatch.setattr(nus, "nuscenes_splits", lambda root, version: {"val": ["a", "b"]})
    monkeypatch.setattr(sources, "_nuscenes_scenes", lambda *a: {"a": None})
    src = sources.NuScenesSource(str(tmp_path), "v1.0-sim", "val")
    assert src.dropped() == {"b": "its vehicle travels less than 1 m (left out as in the paper)"}

    class Seen(RunEvents):
        frames: list = []

        def start(self, todo, kept, dropped):
            self.dropped = dict(dropped)

        def frame(self, scene, done, total):
            self.frames.append((scene, done, total))

    class Fails(sources.SimSource):
        def dropped(self):
            return {"sim-x": "why"}

    seen = Seen()
    out = tmp_path / "o"
    config = MapperConfig(maps=("ray_ilm",))
    summary = map_scenes(Fails((4,), 0.2), out, config, OutputConfig(figures=False), events=seen)
    assert seen.dropped == {"sim-x": "why"} and summary["dropped"] == {"sim-x": "why"}
    # progress per frame inside the scene, with the scene's length
    assert seen.frames == [("sim-000004", k, 4) for k in range(1, 5)]


def test_the_default_out_is_a_new_timestamped_folder_and_resume_continues_the_latest(
    tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    args = ["evaluate", *FAST, "--scenes", "1", "--workers", "1"]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    latest = tmp_path / "out" / "evaluate" / "latest"
    first = latest.resolve()
    assert latest.is_symlink() and (first / "summary.json").is_file()
    time.sleep(1.1)  # the next second: another folder
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output  # a second run does not trip over the first
    assert latest.resolve() != first and (latest.resolve() / "summary.json").is_file()
    r = runner.invoke(app, [*args, "--resume"])
    assert r.exit_code == 0 and "kept: ['sim-000004']" in r.output, r.output


def test_help_keeps_extra_names_and_hints_work_from_a_checkout():
    import evgrid
    from evgrid.console import error_line

    r = runner.invoke(app, ["simulate", "--help"])
    assert r.exit_code == 0 and "evgrid[ros]" in r.output, r.output
    hint = evgrid.install_hint("ros")
    assert hint.startswith("pip install -e '") and hint.endswith("[ros]'")  # a source checkout
    from evgrid.ros import require

    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(sys.modules, "mcap", None)
        with pytest.raises(ImportError) as info:
            require("mcap")
    assert hint in error_line(info.value)
