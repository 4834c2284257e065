"""A scene's resumable state: what a run killed mid-scene continues from (docs/store.md).

A checkpoint is ``checkpoint.pkl`` in the scene's tile store. The tiles are on disk already: at
a checkpoint every resident tile is written to the store too (:meth:`evgrid.store.Pager.flush`),
and the file holds the rest, pickled: the mapper's own state (frame count, radar buffer, pose
gate, update schedule, the map sets' non-tile state, the dynamic score's), the observers'
(scores, truth, GIF, the nav2 export) and each tile by the name of its file. The store keeps the
files a checkpoint names until the next one (:meth:`evgrid.store.TileGroup.pin`), so the state
and its tiles always agree. The file is written atomically, with the format's version, evgrid's
version, the config's hash and a CRC-32; another version or a damaged file is refused naming it.
"""

from __future__ import annotations

import io
import pickle
import shutil
import struct
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from evgrid.io import atomic_write_bytes
from evgrid.package import __version__
from evgrid.store import CHECKPOINT_NAME, StoreError, TileStore, read_tile_file

__all__ = ["CHECKPOINT_VERSION", "save_checkpoint", "load_checkpoint", "checkpoint_path"]

#: The version of the checkpoint's layout; a file of another version is refused.
CHECKPOINT_VERSION = 1
_MAGIC = b"EVGCKPT\x00"
_HEAD = struct.Struct("<8sII")  # magic, version, header length


def checkpoint_path(store_root: Path) -> Path:
    """Where a store's checkpoint lies."""
    return Path(store_root) / CHECKPOINT_NAME


class _Pickler(pickle.Pickler):
    """Pickles a run's state, naming what is not state instead of copying it: the store, the
    deep IRM's model, and each resident tile by its file in the store."""

    def __init__(self, f: Any, store: TileStore | None, deep: Any, tiles: dict[int, tuple]):
        super().__init__(f, protocol=5)
        self.store, self.deep, self.tiles = store, deep, tiles

    def persistent_id(self, obj: Any) -> Any:
        if self.store is not None and obj is self.store:
            return ("store",)
        if self.deep is not None and obj is self.deep:
            return ("deep",)
        return self.tiles.get(id(obj))


class _Unpickler(pickle.Unpickler):
    def __init__(self, f: Any, store: TileStore | None, deep: Callable[[], Any]):
        super().__init__(f)
        self.store, self.deep = store, deep
        self._read: dict[tuple[str, str], dict] = {}

    def persistent_load(self, pid: tuple) -> Any:
        if pid[0] == "store":
            return self.store
        if pid[0] == "deep":
            return self.deep()
        _, group, name, key, layer = pid
        if (group, name) not in self._read:
            self._read[group, name] = read_tile_file(self.store.root / group / name, tuple(key))
        return self._read[group, name][layer]


def save_checkpoint(
    path: Path, state: dict[str, Any], store: TileStore | None, deep: Any, config_hash: str
) -> dict[str, float]:
    """Write ``state`` (a dict of the run's objects) as ``path``, atomically; the store's
    resident tiles are flushed first and named, not copied. Returns its cost: ``ms`` and
    ``bytes`` of the file and ``tile_bytes`` written to the store."""
    t = time.perf_counter()
    tiles: dict[int, tuple] = {}
    tile_bytes = 0
    groups = dict(store._groups) if store is not None else {}
    for gname, g in groups.items():
        tile_bytes += g.flush()
        for p in g.pagers.values():  # a copy's layers are MEMBER/NAME in its map's files
            for layer, d in p.layers.items():
                name = f"{p.member}/{layer}" if p.member else layer
                for key, a in d.items():
                    tiles[id(a)] = ("tile", gname, g._files[key][1], list(key), name)
    buf = io.BytesIO()
    _Pickler(buf, store, deep, tiles).dump({**state, "groups": groups})
    payload = buf.getvalue()
    head = pickle.dumps(
        {
            "evgrid": __version__,
            "config_sha256": config_hash,
            "crc32": zlib.crc32(payload),
            "nbytes": len(payload),
        }
    )
    data = b"".join([_HEAD.pack(_MAGIC, CHECKPOINT_VERSION, len(head)), head, payload])
    # synced before the rename (evgrid.io), after the tiles it names (only those written since
    # the last checkpoint, and their folders): a power loss leaves a checkpoint whose tiles exist
    if store is not None:
        for g in groups.values():
            store._write(g.sync, g.folder)
        store._write(lambda: atomic_write_bytes(path, data), path)
        for g in groups.values():  # the files this checkpoint names stay until the next one
            g.pin()
    else:
        atomic_write_bytes(path, data)
    return {"ms": (time.perf_counter() - t) * 1e3, "bytes": len(data), "tile_bytes": tile_bytes}


def read_header(path: Path) -> tuple[dict[str, Any], bytes]:
    """The checkpoint's header and payload; StoreError naming the file when it is of another
    version or damaged."""
    try:
        data = path.read_bytes()
    except OSError as e:
        raise StoreError(f"{path}: cannot read the checkpoint ({e.strerror})") from e
    if len(data) < _HEAD.size:
        raise StoreError(f"{path}: the checkpoint is cut short; start again with --overwrite")
    magic, version, n = _HEAD.unpack_from(data)
    if magic != _MAGIC:
        raise StoreError(f"{path}: not an evgrid checkpoint")
    if version != CHECKPOINT_VERSION:
        raise StoreError(
            f"{path}: a checkpoint of version {version}, this evgrid reads version "
            f"{CHECKPOINT_VERSION}; start the scene again with --overwrite"
        )
    try:
        head = pickle.loads(data[_HEAD.size : _HEAD.size + n])
        payload = data[_HEAD.size + n :]
        ok = len(payload) == head["nbytes"] and zlib.crc32(payload) == head["crc32"]
    except Exception as e:
        raise StoreError(f"{path}: the checkpoint's header is damaged ({e})") from e
    if not ok:
        raise StoreError(f"{path}: the checkpoint is damaged (its CRC-32 does not match)")
    if head["evgrid"] != __version__:
        raise StoreError(
            f"{path}: a checkpoint of evgrid {head['evgrid']}, this is {__version__}; start the "
            "scene again with --overwrite"
        )
    return head, payload


def load_checkpoint(
    path: Path, store: TileStore | None, deep: Callable[[], Any]
) -> tuple[dict[str, Any], str]:
    """The state :func:`save_checkpoint` wrote and the config hash it was written for; the
    store goes back to that moment (tile files written after it are removed). ``deep`` makes
    the deep IRM when the state had one."""
    head, payload = read_header(path)
    try:
        state = _Unpickler(io.BytesIO(payload), store, deep).load()
    except StoreError:
        raise
    except Exception as e:
        raise StoreError(f"{path}: the checkpoint cannot be read ({type(e).__name__}: {e})") from e
    groups = state.pop("groups")
    if store is not None:
        for sub in store.root.iterdir():  # groups made after the checkpoint
            if sub.is_dir() and sub.name not in groups:
                shutil.rmtree(sub)
        for name, g in groups.items():
            g.folder = store.root / name
            g.restore()
        store._groups = groups
    return state, head["config_sha256"]
