"""Results folders: where a run writes, who holds it, and which scenes are complete.

One policy for every command that writes a results folder (docs/config.md#results-folders):

* ``--out`` defaults to a new timestamped folder ``out/<command>/<YYYYmmdd-HHMMSS>``, with a
  ``latest`` link beside it (as KISS-ICP does); ``--resume`` without ``--out`` continues it.
* A folder that holds anything is refused unless ``--overwrite`` (results go into it, the old
  run's completion markers and summary are removed first) or ``--resume`` (complete scenes of
  the same config are kept). A file is never a results folder.
* A run holds ``OUT/.evgrid.lock`` (pid, host, start), created atomically: a second run into the
  same folder is refused naming the holder; a lock whose process is gone (a killed run) is taken
  over with a warning. A lock of another host cannot be checked (a container gets a new host
  name at every start): it is refused saying it may be stale and how to clear it
  (:func:`break_lock`); ``--overwrite`` does not clear it. A lock file that is no lock (garbage)
  is taken over when older than a few seconds, else refused saying what it holds.
* Each scene folder gets ``.complete`` last, holding the hash of the config it was made with;
  ``--resume`` skips exactly the scenes whose marker matches.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from evgrid.io import load_json_bounded, make_folder, write_json

__all__ = [
    "ResultsExistError",
    "RunLockedError",
    "LOCK_NAME",
    "MARKER_NAME",
    "default_out",
    "results_folder",
    "locked",
    "break_lock",
    "BREAK_LOCK_HINT",
    "is_complete",
    "mark_complete",
]

log = logging.getLogger(__name__)

LOCK_NAME = ".evgrid.lock"
MARKER_NAME = ".complete"


class ResultsExistError(FileExistsError):
    """The results folder already holds another run's results (or is a file)."""


class RunLockedError(FileExistsError):
    """Another run, still alive, writes into the same results folder."""


def default_out(command: str, resume: bool = False, root: str | os.PathLike = "out") -> Path:
    """A new ``root/<command>/<timestamp>`` folder with ``latest`` pointing at it; with ``resume``
    the folder ``latest`` points at."""
    base = Path(root) / command
    latest = base / "latest"
    if resume:
        if not latest.exists():
            raise FileNotFoundError(f"{latest}: no earlier `evgrid {command}` run to resume")
        return latest.resolve()
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out, k = base / stamp, 1
    while out.exists():
        out, k = base / f"{stamp}-{k}", k + 1
    out.mkdir(parents=True)
    tmp = base / f".latest.{os.getpid()}"
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    tmp.symlink_to(out.name)
    os.replace(tmp, latest)  # the link is swapped atomically: never a missing `latest`
    return out


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


#: How a user clears a lock that may be stale (the command line's way to call break_lock).
BREAK_LOCK_HINT = "evgrid unlock {out}"

#: A lock file younger than this that holds no lock may be one being written right now.
_FRESH_S = 5.0


def _read_holder(lock: Path) -> tuple[dict[str, Any] | None, str]:
    """The lock's holder ``{"pid", "host", "started"}``, or None and why the file is no lock."""
    try:
        raw = lock.read_bytes()[:4096]
    except IsADirectoryError:
        return None, "it is a folder, not a lock file"
    except OSError as e:
        return None, f"it cannot be read ({e.strerror or e})"
    try:
        holder = json.loads(raw)
        return {
            "pid": int(holder["pid"]),
            "host": str(holder["host"]),
            "started": holder.get("started"),
        }, ""
    except (ValueError, KeyError, TypeError, AttributeError):
        text = raw[:60].decode("utf-8", errors="replace")
        return None, (
            f"it holds {text!r}{'...' if len(raw) > 60 else ''}, not an evgrid lock (a JSON "
            "object with pid and host)"
            if raw
            else "it is empty, not an evgrid lock (a JSON object with pid and host)"
        )


def _started(holder: dict[str, Any]) -> str:
    t = holder.get("started")
    if not isinstance(t, (int, float)):
        return ""
    return ", started " + time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t))


def _refuse_live_holder(out: Path, lock: Path, holder: dict[str, Any], host: str) -> None:
    """Raise RunLockedError unless ``holder`` is a run on this host that is gone: a holder on
    another host cannot be checked, a live pid here still writes."""
    if holder["host"] != host:
        hint = BREAK_LOCK_HINT.format(out=out)
        raise RunLockedError(
            f"{out} is locked by pid {holder['pid']} on host {holder['host']!r}"
            f"{_started(holder)} (lock {lock}); that is not this host "
            f"({host!r}), so evgrid cannot tell whether that run still lives. The "
            "lock may be stale (a container gets a new host name at every start): if "
            f"no run writes into {out}, clear it with `{hint}`; --overwrite does not "
            "clear it"
        ) from None
    if _pid_alive(holder["pid"]):
        raise RunLockedError(
            f"{out} is in use by another evgrid run (pid {holder['pid']} on "
            f"{holder['host']}{_started(holder)}, lock {lock}); wait for it or choose "
            "another --out"
        ) from None


def _take_lock(out: Path) -> Path:
    lock = out / LOCK_NAME
    me = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
    why = ""
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            holder, why = _read_holder(lock)
            if holder is None:
                try:
                    age = time.time() - lock.stat().st_mtime
                except FileNotFoundError:
                    continue  # its holder just released it
                if age < _FRESH_S and not lock.is_dir():
                    why += f", written {age:.1f} s ago (perhaps by a run starting right now)"
                    time.sleep(0.2)  # being written by its holder right now
                    continue
                log.warning("%s: taking over the lock file %s: %s", out, lock, why)
            else:
                _refuse_live_holder(out, lock, holder, me["host"])
                log.warning(
                    "%s: taking over the lock of a run that is gone (pid %s on %s)",
                    out,
                    holder["pid"],
                    holder["host"],
                )
            _remove_lock(lock)
            continue
        with os.fdopen(fd, "w") as f:
            json.dump(me, f)
        return lock
    hint = BREAK_LOCK_HINT.format(out=out)
    raise RunLockedError(
        f"{out}: could not take the lock {lock}: {why or 'another run took it first'}; if no "
        f"run writes into {out}, clear it with `{hint}`"
    )


def _remove_lock(lock: Path) -> None:
    if lock.is_dir() and not lock.is_symlink():
        with contextlib.suppress(OSError):
            lock.rmdir()  # an empty folder in the lock's place; a full one is refused below
        return
    with contextlib.suppress(FileNotFoundError):
        lock.unlink()


def break_lock(out: str | os.PathLike) -> dict[str, Any] | None:
    """Remove ``out``'s lock, stale or foreign (what ``evgrid unlock OUT`` does); returns the
    holder it named (None: the lock held no holder, or there was none). A lock held by a live
    process of this host is refused: that run still writes into ``out``."""
    out = Path(out)
    lock = out / LOCK_NAME
    if not (lock.exists() or lock.is_symlink()):
        log.info("%s: no lock to clear", out)
        return None
    holder, why = _read_holder(lock)
    if holder is not None and holder["host"] == socket.gethostname():
        if _pid_alive(holder["pid"]) and holder["pid"] != os.getpid():
            raise RunLockedError(
                f"{out} is in use by a live evgrid run (pid {holder['pid']} on this host"
                f"{_started(holder)}); stop it first, its lock is not stale"
            )
    _remove_lock(lock)
    if lock.exists():
        raise RunLockedError(f"{out}: could not clear the lock {lock}: {why}; remove it by hand")
    if holder is not None:
        log.warning(
            "%s: cleared the lock of pid %s on %s%s",
            out,
            holder["pid"],
            holder["host"],
            _started(holder),
        )
    else:
        log.warning("%s: cleared the lock file %s (%s)", out, lock, why)
    return holder


@contextlib.contextmanager
def locked(out: str | os.PathLike) -> Iterator[Path]:
    """Hold ``out``'s lock (creating the folder) while a run writes into it, as
    :func:`results_folder` does, without its policy on existing content (``evgrid train``
    continues into its folder)."""
    out = Path(out)
    make_folder(out)
    lock = _take_lock(out)
    try:
        yield out
    finally:
        lock.unlink(missing_ok=True)


def _holds_results(out: Path) -> bool:
    return any(p.name != LOCK_NAME for p in out.iterdir())


@contextlib.contextmanager
def results_folder(
    out: str | os.PathLike, overwrite: bool = False, resume: bool = False
) -> Iterator[Path]:
    """A results folder for one run, locked while the run lasts (see the module docstring);
    removed again if the run fails before writing anything into it."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ResultsExistError(f"{out} is a file, not a results folder")
    created = not out.exists()
    make_folder(out)
    try:
        lock = _take_lock(out)
    except BaseException:
        if created:
            _remove_empty_dirs(out)
        raise
    try:
        if _holds_results(out) and not (overwrite or resume):
            raise ResultsExistError(
                f"{out} already holds results; pass --overwrite to replace them, --resume to "
                "continue that run, or choose another --out"
            )
        if overwrite and not resume:
            _forget_results(out)
        yield out
    except BaseException:
        lock.unlink(missing_ok=True)
        if created:
            _remove_empty_dirs(out)
        raise
    lock.unlink(missing_ok=True)


def _forget_results(out: Path) -> None:
    """Before an overwrite: the old run's markers and summary go, so nothing of it counts as
    complete (its other files are replaced as the new run writes them)."""
    for marker in out.glob(f"*/{MARKER_NAME}"):
        marker.unlink(missing_ok=True)
    for name in ("summary.json", "table.md"):
        (out / name).unlink(missing_ok=True)


def _remove_empty_dirs(path: Path) -> None:
    for sub in sorted(
        (p for p in path.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True
    ):
        with contextlib.suppress(OSError):
            sub.rmdir()
    with contextlib.suppress(OSError):
        path.rmdir()


def mark_complete(scene_dir: str | os.PathLike, config_hash: str) -> Path:
    """Write a scene's completion marker, last of its files."""
    return write_json(Path(scene_dir) / MARKER_NAME, {"config_sha256": config_hash})


def is_complete(scene_dir: str | os.PathLike, config_hash: str) -> dict[str, Any] | None:
    """A scene's metrics when its marker holds ``config_hash`` (results of the same config)."""
    scene_dir = Path(scene_dir)
    try:
        marker = load_json_bounded(scene_dir / MARKER_NAME, "config")
        if marker.get("config_sha256") != config_hash:
            return None
        return load_json_bounded(scene_dir / "metrics.json", "config")
    except (OSError, ValueError, AttributeError):
        return None
