"""A Ray cluster of several nodes on this machine, for the tests and benchmarks of the ``ray``
engine (:mod:`evgrid.engine_ray`; docs/cluster.md): not part of the library."""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from typing import Any

from evgrid.engine_ray import RayEngineError, _needs_ray


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def processes_naming(marker: str) -> list[int]:
    """Processes whose command line names ``marker`` (a cluster's own temporary folder)."""
    found = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            with contextlib.suppress(OSError):
                if marker.encode() in open(f"/proc/{pid}/cmdline", "rb").read():
                    found.append(int(pid))
    return found


def stop_node(proc: Any, grace_s: float = 20.0) -> None:
    """Stop one ``ray start --block`` started here: SIGTERM (it stops its node), then its group."""
    import subprocess

    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(grace_s)
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)  # what it left in its own session
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(5)


def _driver_env(tmp: str, python_path: tuple[str, ...]) -> dict[str, str]:
    """This environment without its ``RAY_`` variables, with token authentication (a fresh
    token in ``tmp``) and ``python_path``, then ``PYTHONPATH``, made absolute."""
    token = os.path.join(tmp, "token")
    fd = os.open(token, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(secrets.token_hex(32))
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN_PATH=token)
    paths = [*python_path, *os.environ.get("PYTHONPATH", "").split(os.pathsep)]
    env["PYTHONPATH"] = os.pathsep.join(os.path.abspath(p) for p in paths if p)
    return env


@contextlib.contextmanager
def local_cluster(
    nodes: int = 2,
    cpus_per_node: int = 1,
    timeout_s: float = 120.0,
    python_path: tuple[str, ...] = (),
) -> Iterator[dict[str, Any]]:
    """A Ray cluster of ``nodes`` nodes on this machine, for tests and benchmarks.

    ``ray start --head`` then ``ray start --address`` per further node, each ``--block`` in a
    session of its own, with token authentication (a fresh token in a private temporary folder)
    and without the dashboard. Yields ``{"address", "env", "tmp"}``: ``env`` is this
    environment with what a driver needs (``RAY_ADDRESS``, ``RAY_AUTH_MODE``,
    ``RAY_AUTH_TOKEN_PATH``). The nodes' workers import from ``python_path``, then this
    environment's ``PYTHONPATH`` made absolute, as every node of a real cluster must import the
    driver's version of evgrid (docs/cluster.md). Every process is stopped again however the
    block ends, by its process id. Ray 2.60 runs several nodes only on the machine's address,
    not on loopback (docs/cluster.md), so the cluster listens there while it runs.
    """
    import time

    ray_bin = os.path.join(os.path.dirname(sys.executable), "ray")
    if not os.path.exists(ray_bin):
        raise RayEngineError(_needs_ray())
    tmp = tempfile.mkdtemp(prefix="evc", dir="/tmp")  # short: Ray's socket paths must fit
    env = _driver_env(tmp, python_path)
    port = free_port()
    address = f"127.0.0.1:{port}"
    procs: list[Any] = []

    def start(log: str, *args: str) -> Any:
        with open(os.path.join(tmp, log), "w") as f:
            proc = subprocess.Popen(
                [ray_bin, "start", "--block", "--disable-usage-stats", *args],
                env=env,
                stdout=f,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        procs.append(proc)
        return proc

    def log_tail(log: str) -> str:
        with open(os.path.join(tmp, log)) as f:
            return " ".join(f.read().split()[-60:])

    try:
        head = start(
            "head.log",
            "--head",
            "--node-ip-address=127.0.0.1",
            f"--port={port}",
            f"--temp-dir={tmp}/head",
            f"--num-cpus={cpus_per_node}",
            "--include-dashboard=false",
        )
        deadline = time.monotonic() + timeout_s
        while True:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 1):
                break
            if head.poll() is not None or time.monotonic() > deadline:
                raise RayEngineError(f"the head node did not start: {log_tail('head.log')}")
            time.sleep(0.5)
        for i in range(1, nodes):
            start(
                f"node{i}.log",
                f"--address={address}",
                f"--temp-dir={tmp}/node{i}",
                f"--num-cpus={cpus_per_node}",
            )
        yield {"address": address, "env": dict(env, RAY_ADDRESS=address), "tmp": tmp}
    finally:
        for proc in reversed(procs):
            stop_node(proc)
        for pid in processes_naming(tmp):  # a daemon that left its session: ours by its folder
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, 9)
        shutil.rmtree(tmp, ignore_errors=True)


def wait_for_nodes(ray: Any, nodes: int, timeout_s: float = 90.0) -> int:
    """Wait until ``nodes`` nodes of the connected cluster are alive; the number alive."""

    deadline = time.monotonic() + timeout_s
    while True:
        alive = sum(bool(n["Alive"]) for n in ray.nodes())
        if alive >= nodes or time.monotonic() > deadline:
            return alive
        time.sleep(0.5)
