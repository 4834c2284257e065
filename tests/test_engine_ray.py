"""The ray engine of evgrid.engine.fan_out: a local instance, a two-node cluster, and its errors.

Marked ``ray_cluster`` (deselect with ``-m 'not ray_cluster'``) and skipped when Ray is not
installed, except the test that simulates a missing Ray. Ray runs in subprocesses only: it reads
its configuration when imported and installs signal handlers, which would leak between tests.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from importlib.util import find_spec
from pathlib import Path

import pytest

from evgrid.engine import fan_out
from tests.ray_cluster import free_port, processes_naming

ROOT = Path(__file__).resolve().parents[1]
HAS_RAY = find_spec("ray") is not None
needs_ray = pytest.mark.skipif(not HAS_RAY, reason="ray is not installed (pip install -e '.[ray]')")

#: Three short simulated scenes, and one job that raises on its worker.
SCENE_SEEDS = (4, 9, 14)
SCENE_S = 2.0


# --- jobs (module level: they pickle by reference into Ray's workers) --------------------------


class _LastMaps:
    """An observer that digests the masses of every map after each update (the last one's
    digest is the run's: a run without a folder removes its temporary tile store when over)."""

    def __init__(self) -> None:
        self.digest = None

    def on_update(self, update) -> None:
        digest = hashlib.sha256()
        for map_name, m in sorted(update.maps.maps.items()):
            for key in sorted(m.tiles):
                digest.update(f"{map_name}{key}".encode())
                digest.update(m.tiles[key].tobytes())
        self.digest = digest.hexdigest()


def map_metrics(args: tuple) -> dict:
    """Map one simulated scene without a results folder; its IoUs, confusion and mass digest."""
    from evgrid.config import MapperConfig, OutputConfig
    from evgrid.runs import map_scene
    from evgrid.sources import SimSource

    seed, duration_s, fail = args
    if fail:
        raise RuntimeError(f"scene {seed} fails on purpose\nsecond line")
    source = SimSource((seed,), duration_s)
    (name,) = source.names()
    last = _LastMaps()
    res = map_scene(
        source.load(name),
        None,
        MapperConfig(),
        OutputConfig(figures=False),
        name=name,
        observers=(last,),
    )
    return {
        "vs_ray_ilm": res.metrics["vs_ray_ilm"],
        "vs_truth": res.metrics.get("vs_truth"),
        "confusion_vs_ray_ilm": res.metrics["confusion_vs_ray_ilm"],
        "masses_sha256": last.digest,
        "node": _ray_node(),
        "evgrid": __import__("evgrid").__file__,
    }


def _ray_node() -> str | None:
    """The Ray node a job ran on (None outside Ray)."""
    if "ray" not in sys.modules:
        return None
    import ray

    return ray.get_runtime_context().get_node_id() if ray.is_initialized() else None


def square_or_fail(args: tuple) -> dict:
    """``x * x``; raises for ``x == 3``; dies (os._exit) on its first try when given a marker."""
    x, marker = args
    if marker is not None and not os.path.exists(marker):
        Path(marker).write_text("tried")
        os._exit(3)
    if x == 3:
        raise ValueError("three is not allowed\nsecond line")
    import ray
    from ray._private.authentication.authentication_utils import is_token_auth_enabled

    return {"square": x * x, "ip": ray.util.get_node_ip_address(), "token": is_token_auth_enabled()}


# --- helpers ------------------------------------------------------------------------------------


def _run_python(code: str, env: dict, timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _base_env(**extra: str) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), str(ROOT)])
    env.update(extra)
    return env


# --- without Ray, and without a cluster ---------------------------------------------------------


def test_ray_not_installed_gives_one_line_naming_the_extra():
    code = """
        import sys
        sys.modules["ray"] = None  # as if the extra were not installed
        from evgrid.engine import fan_out
        try:
            list(fan_out(abs, [("a", -1)], engine="ray"))
        except OSError as e:
            print(type(e).__name__, str(e))
    """
    r = _run_python(code, _base_env(), timeout=60)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert len(lines) == 1, r.stdout
    assert lines[0].startswith("RayEngineError ")
    assert "'ray' extra" in lines[0] and "pip install -e '.[ray]'" in lines[0]


@pytest.mark.parametrize("via_env", [False, True])
def test_unreachable_address_gives_one_line_within_30s(monkeypatch, via_env):
    from evgrid.engine_ray import RayEngineError

    address = f"127.0.0.1:{free_port()}"  # nothing listens there
    if via_env:
        monkeypatch.setenv("RAY_ADDRESS", address)
    t = time.perf_counter()
    with pytest.raises(RayEngineError) as e:
        list(fan_out(abs, [("a", -1)], engine="ray", address=None if via_env else address))
    assert time.perf_counter() - t < 30
    msg = str(e.value)
    assert "\n" not in msg and address in msg and "no Ray cluster answers" in msg


def test_address_that_drops_packets_gives_up_within_30s():
    from evgrid.engine_ray import RayEngineError

    t = time.perf_counter()
    with pytest.raises(RayEngineError, match="no Ray cluster answers at 203.0.113.1:6379"):
        list(fan_out(abs, [("a", -1)], engine="ray", address="203.0.113.1:6379"))
    assert time.perf_counter() - t < 30


@needs_ray
@pytest.mark.ray_cluster
def test_address_where_nothing_speaks_ray_gives_up_within_30s():
    """The worst case: a port that accepts connections and never answers."""
    from evgrid.engine_ray import RayEngineError

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(8)
        address = f"127.0.0.1:{server.getsockname()[1]}"
        t = time.perf_counter()
        with pytest.raises(RayEngineError, match=f"no Ray cluster answers at {address}") as e:
            list(fan_out(abs, [("a", -1)], engine="ray", address=address))
        assert time.perf_counter() - t < 30
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    "address, message",
    [("ray://head:10001", "Ray Client"), ("head", "not host:port"), ("h:99999", "not host:port")],
)
def test_bad_addresses_are_named(address, message):
    from evgrid.engine_ray import RayEngineError

    with pytest.raises(RayEngineError, match=message):
        list(fan_out(abs, [("a", -1)], engine="ray", address=address))


def test_address_is_for_the_ray_engine_only():
    with pytest.raises(ValueError, match="ray engine only"):
        list(fan_out(abs, [("a", -1)], engine="local", address="127.0.0.1:6379"))


# --- a local Ray instance -----------------------------------------------------------------------


@needs_ray
@pytest.mark.ray_cluster
def test_local_instance_is_locked_down_reports_by_key_retries_and_shuts_down():
    tmp = tempfile.mkdtemp(prefix="evr", dir="/tmp")  # short: Ray's socket paths must fit
    try:
        code = f"""
            import glob, json, os
            from evgrid.engine import fan_out
            from tests.test_engine_ray import square_or_fail

            def consume_until_interrupted():
                for outcome in fan_out(square_or_fail, [("x1", (1, None)), ("x2", (2, None))],
                                       engine="ray", workers=1):
                    raise KeyboardInterrupt  # Ctrl-C while the jobs run

            jobs = [("x0", (0, None)), ("x3", (3, None)), ("x4", (4, {str(tmp)!r} + "/died")),
                    ("x5", (5, None))]
            out = {{o.key: [o.result, o.error] for o in fan_out(square_or_fail, jobs,
                                                                 engine="ray", workers=2)}}
            import ray
            after = {{"initialized": ray.is_initialized(),
                      "auth_env": [k for k in os.environ if k.startswith("RAY_AUTH")],
                      "temp": glob.glob(os.path.join({str(tmp)!r}, "evgrid-ray-*"))}}
            try:
                consume_until_interrupted()
            except KeyboardInterrupt:
                after["interrupted"] = {{"initialized": ray.is_initialized(),
                    "temp": glob.glob(os.path.join({str(tmp)!r}, "evgrid-ray-*"))}}
            print("RESULT", json.dumps({{"out": out, "after": after}}))
        """
        r = _run_python(code, _base_env(TMPDIR=tmp), timeout=240)
        lines = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]
        assert r.returncode == 0 and lines, r.stdout[-2000:] + r.stderr[-4000:]
        res = json.loads(lines[0][len("RESULT ") :])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    out = res["out"]
    assert set(out) == {"x0", "x3", "x4", "x5"}
    for key, x in (("x0", 0), ("x4", 4), ("x5", 5)):
        result, error = out[key]
        assert error is None
        assert result["square"] == x * x
        assert result["ip"] == "127.0.0.1"  # the node's address: Ray's servers bind loopback
        assert result["token"] is True
    assert out["x3"] == [None, "ValueError: three is not allowed second line"]
    # shut down, the environment as it was, the private temp dir (and its token) removed; the same
    # when the caller is interrupted while jobs run
    interrupted = res["after"].pop("interrupted", None)
    assert res["after"] == {"initialized": False, "auth_env": [], "temp": []}
    assert interrupted == {"initialized": False, "temp": []}


@needs_ray
@pytest.mark.ray_cluster
def test_local_instance_refuses_auth_disabled():
    code = """
        import os
        os.environ["RAY_AUTH_MODE"] = "disabled"
        from evgrid.engine import fan_out
        try:
            list(fan_out(abs, [("a", -1)], engine="ray"))
        except OSError as e:
            print(str(e))
    """
    r = _run_python(code, _base_env(), timeout=60)
    assert "only with token authentication" in r.stdout, r.stdout + r.stderr


# --- a two-node cluster on this machine ---------------------------------------------------------


@pytest.fixture(scope="module")
def two_node_cluster():
    """``ray start --head`` and a second ``ray start --address`` on this machine, token
    authentication on; stopped again however the tests end (tests.ray_cluster.local_cluster)."""
    if not HAS_RAY:
        pytest.skip("ray is not installed (pip install -e '.[ray]')")
    from tests.ray_cluster import local_cluster

    with local_cluster(nodes=2, cpus_per_node=1, python_path=(str(ROOT / "src"),)) as cluster:
        yield cluster
    assert not _ours(cluster["tmp"]), "a Ray process of the test cluster outlived it"


def _ours(marker: str) -> list[int]:
    return processes_naming(marker)


@needs_ray
@pytest.mark.ray_cluster
def test_two_node_cluster_maps_like_the_local_engine(two_node_cluster):
    jobs = [(f"sim-{s}", (s, SCENE_S, False)) for s in SCENE_SEEDS]
    jobs.append(("raises", (19, SCENE_S, True)))
    code = f"""
        import json, time
        import ray
        from tests.ray_cluster import wait_for_nodes
        ray.init(address={two_node_cluster["address"]!r}, log_to_driver=False)
        nodes = wait_for_nodes(ray, 2)
        ray.shutdown()
        from evgrid.engine import fan_out
        from tests.test_engine_ray import map_metrics
        jobs = [(k, tuple(a)) for k, a in json.loads({json.dumps(jobs)!r})]
        out = {{o.key: [o.result, o.error] for o in fan_out(map_metrics, jobs, engine="ray",
                                                             workers=2)}}
        print("RESULT", json.dumps({{"nodes": nodes, "out": out}}))
    """
    r = _run_python(code, two_node_cluster["env"], timeout=400)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]
    assert r.returncode == 0 and lines, r.stdout[-2000:] + r.stderr[-4000:]
    res = json.loads(lines[0][len("RESULT ") :])
    assert res["nodes"] == 2
    out = res["out"]
    assert out["raises"] == [None, "RuntimeError: scene 19 fails on purpose second line"]
    on_ray = {k: v[0] for k, v in out.items() if k != "raises"}
    assert all(out[k][1] is None for k in on_ray), {k: out[k][1] for k in on_ray}
    # two jobs in flight, one CPU per node: both nodes mapped scenes
    assert len({m.pop("node") for m in on_ray.values()}) == 2
    local = {
        o.key: o.result for o in fan_out(map_metrics, [j for j in jobs if not j[1][2]], "local")
    }
    for m in local.values():
        assert m.pop("node") is None
    # the nodes' workers mapped with this checkout's evgrid, not another installed one
    assert {m["evgrid"] for m in on_ray.values()} == {m["evgrid"] for m in local.values()}
    assert on_ray == json.loads(json.dumps(local))  # masses bit for bit, IoUs, confusion
