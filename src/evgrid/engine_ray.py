"""Ray as the engine of :func:`evgrid.engine.fan_out` (the ``ray`` extra; docs/cluster.md).

With an address (the ``address`` argument, else ``RAY_ADDRESS``, Ray's own convention) the
jobs run on that cluster, started beforehand with ``ray start``; this process joins it as a
driver. Without one, a private Ray instance is started for the call and shut down when it ends,
also on an exception or Ctrl-C. That local instance is locked down as far as Ray 2.60 allows:

* token authentication on (``RAY_AUTH_MODE=token``), with a fresh token for the run in a
  private temporary folder unless ``RAY_AUTH_TOKEN`` or ``RAY_AUTH_TOKEN_PATH`` names one;
* bound to the loopback address: Ray offers no bind option, and its gRPC servers listen on all
  interfaces unless the node's address is the loopback one, which on Linux it only takes with
  ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` (the switch that keeps Windows and macOS on one
  machine); that is set before Ray is imported;
* no dashboard (``include_dashboard=False``; ``dashboard=True`` starts it, bound to localhost).

Every job is a Ray task with ``num_cpus=1``; at most ``workers`` are in flight. A task whose
worker process dies is retried ``retries`` times (Ray's ``max_retries``); an exception raised by
the job is not (``retry_exceptions=False``) and is reported by the job's key in one line. Tasks
return their results to the driver, which writes every file.
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import os
import secrets
import shutil
import socket
import sys
import tempfile
from collections.abc import Callable, Iterator
from typing import Any

from evgrid.engine_local import _DIED, Outcome, _one_line

__all__ = ["RayEngineError", "fan_out_ray", "ray_session", "CONNECT_TIMEOUT_S"]

log = logging.getLogger(__name__)


def _needs_ray() -> str:
    from evgrid.package import install_hint

    return f"the ray engine needs the 'ray' extra: {install_hint('ray')}"


#: Seconds to wait for a cluster's address to accept a connection, and then for Ray's GCS to
#: answer there, before giving up: Ray's own attempts go on for minutes against an address
#: nobody listens on, or where something else answers. The GCS wait takes about three times
#: its timeout in all, so an unreachable address fails within 30 s.
CONNECT_TIMEOUT_S = 5.0

_LOOPBACK_SWITCH = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


class RayEngineError(OSError):
    """Ray cannot run the jobs: not installed, or the cluster cannot be reached or refused us."""


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _split_address(address: str) -> tuple[str, int]:
    """``host:port`` of a Ray cluster's GCS, as ``ray start --head`` prints it."""
    if "://" in address:
        raise RayEngineError(
            f"Ray address {address!r}: Ray Client addresses (ray://) are not supported; run "
            "evgrid on a node of the cluster with RAY_ADDRESS=<head>:<port> (docs/cluster.md)"
        )
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise RayEngineError(f"Ray address {address!r} is not host:port (e.g. 10.0.0.5:6379)")
    return host.strip("[]"), int(port)


def _check_reachable(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Fail in one line, within ``timeout_s``, when nothing listens at ``address``."""
    host, port = _split_address(address)
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as e:
        raise RayEngineError(
            f"no Ray cluster answers at {address} (RAY_ADDRESS or --address): {_one_line(e)}"
        ) from None


def _check_gcs(ray: Any, address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Fail in one line when what listens at ``address`` is no Ray GCS that lets us in."""
    try:
        from ray._raylet import InnerGcsClient  # Ray's GCS client with a deadline
    except ImportError:  # another Ray: leave it to ray.init
        return
    try:
        InnerGcsClient.standalone(address, None, int(timeout_s * 1000))
    except Exception as e:
        first = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), "")
        hint = ""
        if "auth" in f"{type(e).__name__} {first}".lower():
            hint = (
                "; the cluster wants its token: set RAY_AUTH_MODE=token and RAY_AUTH_TOKEN_PATH "
                "(or RAY_AUTH_TOKEN) here too (docs/cluster.md)"
            )
        raise RayEngineError(
            f"no Ray cluster answers at {address} (RAY_ADDRESS or --address): "
            f"{type(e).__name__}: {first[:200]}{hint}"
        ) from None


def _import_ray(loopback: bool) -> Any:
    """Import Ray, first asking it to take the loopback address as the node's when ``loopback``."""
    if loopback and "ray" not in sys.modules:
        # Read once, when Ray is imported (ray._private.ray_constants.ENABLE_RAY_CLUSTER).
        os.environ.setdefault(_LOOPBACK_SWITCH, "0")
    try:
        import ray
    except ImportError:
        raise RayEngineError(_needs_ray()) from None
    return ray


@contextlib.contextmanager
def _env(**values: str | None) -> Iterator[None]:
    """Set (or, with None, remove) environment variables for the block; restore them after."""
    old = {k: os.environ.get(k) for k in values}
    try:
        for k, v in values.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def ray_session(
    address: str | None = None, workers: int = 1, dashboard: bool = False
) -> Iterator[Any]:
    """Ray connected for the block: to ``address`` (else ``RAY_ADDRESS``), or a local instance.

    Yields the ``ray`` module. The local instance (``workers`` CPUs) is started with token
    authentication, on the loopback address and without the dashboard unless ``dashboard``, and
    shut down when the block ends, however it ends; connecting to a cluster leaves it running.
    """
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address == "local":
        address = None
    if address is not None and address != "auto":
        _check_reachable(address)
        # Ray's conventions unchanged: it takes a loopback address for this machine's own
        # (docs/cluster.md on why a cluster of several nodes cannot stay on loopback)
        ray = _import_ray(loopback=False)
        _check_gcs(ray, address)
        with _ray_errors(address):
            ray.init(address=address, log_to_driver=True, configure_logging=False)
        try:
            yield ray
        finally:
            ray.shutdown()
        return
    if address == "auto":
        ray = _import_ray(loopback=False)
        with _ray_errors("auto"):
            ray.init(address="auto", log_to_driver=True, configure_logging=False)
        try:
            yield ray
        finally:
            ray.shutdown()
        return
    yield from _local_session(workers, dashboard)


def _local_session(workers: int, dashboard: bool) -> Iterator[Any]:
    mode = os.environ.get("RAY_AUTH_MODE")
    if mode is not None and mode.lower() != "token":
        raise RayEngineError(
            f"RAY_AUTH_MODE={mode}: evgrid starts a local Ray instance only with token "
            "authentication; unset RAY_AUTH_MODE, or start a cluster yourself and set RAY_ADDRESS"
        )
    temp_dir = tempfile.mkdtemp(prefix="evgrid-ray-")  # mode 0700: the token file stays ours
    token_env: dict[str, str | None] = {"RAY_AUTH_MODE": "token"}
    if not os.environ.get("RAY_AUTH_TOKEN") and not os.environ.get("RAY_AUTH_TOKEN_PATH"):
        token_path = os.path.join(temp_dir, "auth_token")
        fd = os.open(token_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(32))  # 256 bits, as `ray get-auth-token --generate`
        token_env["RAY_AUTH_TOKEN_PATH"] = token_path
    try:
        with _env(**token_env):
            # Set before Ray reads its configuration (at import, or again below): the driver,
            # the GCS, the raylet and the workers all inherit the mode and the token's path.
            ray = _import_ray(loopback=True)
            _reload_auth(ray)
            try:
                with _ray_errors("a local instance"):
                    ray.init(
                        num_cpus=workers,
                        include_dashboard=dashboard,
                        _temp_dir=temp_dir,
                        log_to_driver=True,
                        configure_logging=False,
                    )
                _check_local(ray)
                yield ray
            finally:
                ray.shutdown()
        _reload_auth(ray)
    finally:
        shutil.rmtree(temp_dir, ignore_errors=True)


def _reload_auth(ray: Any) -> None:
    """Make this process see the authentication settings of the environment now.

    Ray reads ``RAY_AUTH_MODE`` into its configuration once and caches the token it loaded;
    Ray's own ``ray.init`` reloads both the same way when it turns token authentication on.
    """
    from ray._raylet import AuthenticationTokenLoader, Config

    Config.initialize("")
    AuthenticationTokenLoader.instance().reset_cache()


def _check_local(ray: Any) -> None:
    """Refuse a local instance without token authentication; say so if it is not on loopback."""
    from ray._private.authentication.authentication_utils import is_token_auth_enabled

    if not is_token_auth_enabled():
        raise RayEngineError("the local Ray instance came up without token authentication")
    node_ip = ray.util.get_node_ip_address()
    if not _is_loopback(node_ip):
        log.warning(
            "the local Ray instance listens on %s, not only on the loopback address: Ray was "
            "imported before evgrid could set %s=0 (docs/cluster.md)",
            node_ip,
            _LOOPBACK_SWITCH,
        )


@contextlib.contextmanager
def _ray_errors(where: str) -> Iterator[None]:
    """Ray's failures to start or connect as one :class:`RayEngineError` line."""
    try:
        yield
    except RayEngineError:
        raise
    except Exception as e:
        # Ray's messages carry tracebacks and advice over many lines: keep the first
        first = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), "")
        raise RayEngineError(f"Ray at {where}: {type(e).__name__}: {first[:300]}") from e


def fan_out_ray(
    fn: Callable[[Any], Any],
    jobs: list[tuple[str, Any]],
    workers: int = 1,
    retries: int = 1,
    address: str | None = None,
    dashboard: bool = False,
) -> Iterator[Outcome]:
    """Run ``fn(args)`` for each ``(key, args)`` of ``jobs`` as Ray tasks; yield :class:`Outcome` as
    they finish (see the module docstring for the cluster, the retries and the local instance)."""
    if not jobs:
        return
    workers = max(1, int(workers))
    with ray_session(address, workers, dashboard) as ray:
        from ray.exceptions import RayTaskError, WorkerCrashedError

        task = ray.remote(num_cpus=1, max_retries=retries, retry_exceptions=False)(fn)
        todo = list(reversed(jobs))
        running: dict[Any, str] = {}
        while todo or running:
            while todo and len(running) < workers:
                key, args = todo.pop()
                running[task.remote(args)] = key
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                key = running.pop(ref)
                try:
                    yield Outcome(key, ray.get(ref))
                except RayTaskError as e:  # raised by fn: not retried, reported by key
                    cause = getattr(e, "cause", None)
                    yield Outcome(key, error=_one_line(cause if cause is not None else e))
                except WorkerCrashedError:
                    yield Outcome(key, error=_DIED)
                except Exception as e:  # a node lost, an object lost: this job only
                    yield Outcome(key, error=_one_line(e))
