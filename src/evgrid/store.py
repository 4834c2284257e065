"""The tile store: a map's tiles far from the vehicle, on disk, compressed, read back on return.

A :class:`TileStore` is a folder; each map (or other tiled raster) paged into it has a group,
a sub-folder of its own, holding one file per tile (``TI_TJ.gN.tile``: tile row, tile column,
generation) with every layer of that tile (masses, coverage, dynamic score), each compressed
with blosc2 (zstd, byte shuffle; lossless) and checked by a CRC-32: the masses with the largest
of a cell's three as a residual of the other two, and a copy of the map (nav's gated input)
as the XOR of its layers against the map's, in the same file (docs/store.md#layout-on-disk).
A tile file is written under a temporary name and renamed into place, so a run killed at any
moment leaves only whole files; a tile written again gets a new generation, and the older
file goes once the newer one is in place. ``map.json`` in a group says what the tiles belong
to (grid, tiling, metadata, map frame), so a group opens as a map by itself
(:func:`evgrid.grid.load_map` on its folder).

:class:`Pager` is what a tiled raster (:class:`evgrid.grid.EvidentialMap`, the mover trail)
keeps beside its tiles in memory: which tiles are on disk, a small cache of tiles read
without being brought back, and the moves between the two (docs/store.md).
"""

from __future__ import annotations

import errno
import json
import logging
import math
import os
import re
import struct
import tempfile
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterator, MutableMapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba
import numpy as np

logger = logging.getLogger(__name__)

__all__ = [
    "STORE_VERSION",
    "StoreError",
    "TileStore",
    "TileGroup",
    "Pager",
    "TileLayer",
    "tile_distance_m",
    "StoreParams",
    "ALL_RESIDENT_M",
]

_STORE_FORMAT = "evgrid-tile-store"
#: The version of the store's layout and tile files; a store of another version is refused.
#: 2: the masses' largest mass as a residual, copies (nav's gated inputs) in their map's files.
STORE_VERSION = 2
_MAGIC = b"EVGTILE\x00"
_HEAD = struct.Struct("<8sII")  # magic, version, header length
#: ``TI_TJ.gN[.MEMBERS].tile``: MEMBERS, "+"-joined, are what the file holds ("map": the group's
#: own map, else copies of it such as "gated"); none named: the map alone.
_TILE_NAME = re.compile(r"^(-?\d+)_(-?\d+)\.g(\d+)(?:\.([a-z]+(?:\+[a-z]+)*))?\.tile$")
_MEMBER_NAME = re.compile(r"^[a-z]{1,20}$")
_GROUP_NAME = re.compile(r"^[A-Za-z0-9_.+-]{1,100}$")
#: Tiles read without being brought back into the map, kept per group (each a few MiB at most).
READ_CACHE_TILES = 8
#: A run's resumable state in its store's folder (:mod:`evgrid.checkpoint`); while it is there,
#: the tile files it names are kept (a group opened does not remove older generations).
CHECKPOINT_NAME = "checkpoint.pkl"


class StoreError(ValueError):
    """A tile store that cannot be used: another version, a damaged file, a full disk; the
    message names the file or the store."""


def _codec() -> Any:
    try:
        import blosc2
    except ImportError as e:  # pragma: no cover - a core dependency
        raise StoreError(
            "the tile store needs blosc2, a dependency of evgrid: reinstall evgrid to get it"
        ) from e
    return blosc2


class TileStore:
    """A folder of tile groups (one per map). ``root`` None: a temporary folder, removed by
    :meth:`close` (or when the store is collected).

    Opening a folder that holds a store of another version, or a ``store.json`` that is not
    one, raises :class:`StoreError` naming the file.
    """

    def __init__(self, root: str | os.PathLike | None = None):
        self._tmp: tempfile.TemporaryDirectory | None = None
        if root is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="evgrid-store-")
            root = self._tmp.name
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        head = self.root / "store.json"
        if head.exists():
            check_store_header(head)
        else:
            self._write(
                lambda: _write_atomic(
                    head,
                    json.dumps({"format": _STORE_FORMAT, "version": STORE_VERSION}).encode(),
                ),
                head,
            )
        self._groups: dict[str, TileGroup] = {}
        self.removed = False  # a temporary store after close: its tiles are gone

    def __repr__(self) -> str:
        return f"TileStore({str(self.root)!r}, {len(self._groups)} groups)"

    def group(self, name: str) -> TileGroup:
        """The group ``name`` (letters, digits, ``_.+-``), made if new."""
        g = self._groups.get(name)
        if g is None:
            if not _GROUP_NAME.match(name) or name in (".", ".."):
                raise ValueError(f"a tile group's name is letters, digits and _.+-, got {name!r}")
            g = self._groups[name] = TileGroup(self, self.root / name)
        return g

    @property
    def nbytes(self) -> int:
        """Bytes of the tile files on disk."""
        return sum(g.nbytes for g in self._groups.values())

    def close(self) -> None:
        """Remove the folder when it is a temporary one; a store in a run's folder stays."""
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None
            self.removed = True

    def _write(self, fn: Callable[[], Any], what: Path) -> Any:
        """Run a write; a full disk (or a quota) becomes one line naming the store."""
        try:
            return fn()
        except OSError as e:
            if e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
                raise StoreError(
                    f"the tile store {self.root} is out of disk space writing {what.name} "
                    f"({os.strerror(e.errno)}); the maps paged out so far stay loadable"
                ) from e
            raise


def _write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` under a temporary name beside ``path`` and rename it into place: a process
    killed at any moment leaves the old file or the new one, never a part. Not synced here: a
    tile is rewritten often; a checkpoint syncs the files written since the last one
    (:meth:`TileGroup.sync`) before its own file is written, so the tiles it names survive a
    power loss too."""
    fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", suffix=".part", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _fsync_dir(folder: Path) -> None:
    """fsync a folder (its entries: files renamed into it); a no-op where folders cannot be
    opened (Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _is_masses(a: np.ndarray) -> bool:
    return a.dtype == np.float32 and a.ndim >= 1 and a.shape[-1] == 3


# The masses of a cell sum to 1 up to float32 rounding, so the largest of the three is known from
# the other two to within a few units in its last place (its ulp is the largest of the three):
# per cell, plane 0 holds the zigzag of the difference of its bits from those of
# ``1 - (a + b)`` (small: mostly 0 to 3), planes 1 and 2 the other two, smaller first, and one
# byte says which mass is the largest (bits 0-1) and whether the other two were swapped (bit 2);
# 3: the three as they are (a cell with a non-finite mass). Every bit comes back: the decoder
# computes the same float32 prediction from the same two values. Planes of like values compress
# better than planes of m_f, m_o, m_u (3-4 % on the maps of a drive, docs/store.md).


@numba.njit(cache=True, nogil=True)
def _largest_as_residual(m, bits, planes, largest, scratch, scratch_bits):  # pragma: no cover
    one = np.float32(1.0)
    for i in range(m.shape[0]):
        f, o, u = m[i, 0], m[i, 1], m[i, 2]
        k = 0 if f >= o and f >= u else (1 if o >= u else 2)
        ia, ib = (k + 1) % 3, (k + 2) % 3
        scratch[0] = one - (m[i, ia] + m[i, ib])
        if not (np.isfinite(f) and np.isfinite(o) and np.isfinite(u) and np.isfinite(scratch[0])):
            for j in range(3):
                planes[j, i] = bits[i, j]
            largest[i] = 3
            continue
        swap = m[i, ia] > m[i, ib]
        if swap:
            ia, ib = ib, ia
        d = np.int64(bits[i, k]) - np.int64(scratch_bits[0])
        if d >= 2**31:
            d -= 2**32
        elif d < -(2**31):
            d += 2**32
        planes[0, i] = np.uint32(2 * d if d >= 0 else -2 * d - 1)
        planes[1, i] = bits[i, ia]
        planes[2, i] = bits[i, ib]
        largest[i] = k + 4 * swap


@numba.njit(cache=True, nogil=True)
def _residual_to_largest(
    planes, planes_f, largest, out, out_bits, scratch, scratch_bits
):  # pragma: no cover
    one = np.float32(1.0)
    for i in range(out.shape[0]):
        s = largest[i]
        if s > 6 or s & 3 == 3 and s != 3:
            return False
        if s == 3:
            for j in range(3):
                out_bits[i, j] = planes[j, i]
            continue
        k = s & 3
        ia, ib = (k + 1) % 3, (k + 2) % 3
        if s >= 4:
            ia, ib = ib, ia
        out_bits[i, ia] = planes[1, i]
        out_bits[i, ib] = planes[2, i]
        scratch[0] = one - (planes_f[1, i] + planes_f[2, i])
        z = np.int64(planes[0, i])
        d = z >> 1 if (z & 1) == 0 else -(z >> 1) - 1
        out_bits[i, k] = np.uint32((np.int64(scratch_bits[0]) + d) & 0xFFFFFFFF)
    return True


def _encode_masses(a: np.ndarray) -> np.ndarray:
    """Masses ``(..., 3)`` float32 as bytes: three uint32 planes (each cell's largest mass as its
    residual, then the other two masses' bits, the smaller first) and one byte a cell saying
    which mass is the largest; lossless (:func:`_decode_masses`)."""
    flat = np.ascontiguousarray(a).reshape(-1, 3)
    n = len(flat)
    out = np.empty(13 * n, np.uint8)
    scratch = np.empty(1, np.float32)
    planes = out[: 12 * n].view(np.uint32).reshape(3, n)
    _largest_as_residual(
        flat, flat.view(np.uint32), planes, out[12 * n :], scratch, scratch.view(np.uint32)
    )
    return out


def _decode_masses(buf: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """The masses of shape ``shape`` that :func:`_encode_masses` made ``buf`` of."""
    n = int(np.prod(shape[:-1], dtype=np.int64))
    if len(buf) != 13 * n:
        raise ValueError(f"masses of {len(buf)} bytes, not {13 * n}")
    planes = buf[: 12 * n].view(np.uint32).reshape(3, n)
    out = np.empty((n, 3), np.float32)
    scratch = np.empty(1, np.float32)
    sel, bits = buf[12 * n :], scratch.view(np.uint32)
    if not _residual_to_largest(
        planes, planes.view(np.float32), sel, out, out.view(np.uint32), scratch, bits
    ):
        raise ValueError("the masses name a largest mass that is none of the three")
    return out.reshape(shape)


def _encode(a: np.ndarray) -> tuple[str, np.ndarray, int]:
    """A layer as (encoding, bytes, blosc2's typesize)."""
    if _is_masses(a):
        return "masses", _encode_masses(a), 4
    return "raw", a.reshape(-1).view(np.uint8), a.dtype.itemsize


def check_store_header(head: Path) -> None:
    """Refuse a ``store.json`` that is not a store of this version (StoreError naming it)."""
    try:
        d = json.loads(head.read_bytes())
    except (OSError, ValueError) as e:
        raise StoreError(f"{head} is damaged or not an evgrid tile store ({e})") from e
    if not isinstance(d, dict) or d.get("format") != _STORE_FORMAT:
        raise StoreError(f"{head} is not an evgrid tile store")
    if d.get("version") != STORE_VERSION:
        raise StoreError(
            f"{head} is a tile store of version {d.get('version')!r}; this evgrid reads version "
            f"{STORE_VERSION} (map it again, or open it with the evgrid that wrote it)"
        )


def _members_of(tag: str | None) -> frozenset[str]:
    """The members a tile file's name says it holds ("" for the group's own map)."""
    if not tag:
        return frozenset({""})
    return frozenset("" if m == "map" else m for m in tag.split("+"))


def _tile_name(key: tuple[int, int], gen: int, members: frozenset[str]) -> str:
    tag = "" if members == {""} else "." + "+".join(m or "map" for m in sorted(members))
    return f"{key[0]}_{key[1]}.g{gen}{tag}.tile"


class TileGroup:
    """The tiles of one map in a store: ``write``/``read`` a tile's layers by tile key.

    A group's files may also hold copies of its map (members other than ``""``, such as nav's
    gated copy of the map: :attr:`Pager.member`), each layer of a copy stored as the XOR of its
    encoded bytes against the map's layer of the same tile in the same file (a copy differs from
    its map in few cells, so that compresses to little). Map and copies of a tile change together,
    in one file, so a file never needs another to be read.
    """

    def __init__(self, store: TileStore, folder: Path):
        self.store = store
        self.folder = folder
        folder.mkdir(exist_ok=True)
        # the newest generation of each key on disk: (generation, file name), and its members
        self._files: dict[tuple[int, int], tuple[int, str]] = {}
        self._members: dict[tuple[int, int], frozenset[str]] = {}
        self._gen = 0
        self.pagers: dict[str, Pager] = {}  # the rasters paging into this group, by member
        # files a checkpoint names (kept until the next one), and those replaced since
        self.pinned: set[str] = set()
        self.retired: list[str] = []
        # tile files written (renamed into place) since the last sync: a checkpoint syncs them
        self.unsynced: set[str] = set()
        stale = []
        for f in os.scandir(folder):
            m = _TILE_NAME.match(f.name)
            if m is None:
                if f.name.startswith(".") and f.name.endswith(".part"):
                    stale.append(f.path)  # a write cut by a kill
                continue
            key, gen = (int(m[1]), int(m[2])), int(m[3])
            self._gen = max(self._gen, gen + 1)
            old = self._files.get(key)
            if old is None or gen > old[0]:
                if old is not None:
                    stale.append(str(folder / old[1]))
                self._files[key] = (gen, f.name)
                self._members[key] = _members_of(m[4])
            else:
                stale.append(f.path)
        if (folder.parent / CHECKPOINT_NAME).exists():  # it may name older generations
            stale = [p for p in stale if p.endswith(".part")]
        for p in stale:  # older generations whose newer file made it, and cut writes
            try:
                os.unlink(p)
            except OSError:
                pass
        self.nbytes = sum((folder / n).stat().st_size for _, n in self._files.values())

    def __repr__(self) -> str:
        return f"TileGroup({str(self.folder)!r}, {len(self._files)} tiles)"

    @property
    def pager(self) -> Pager | None:
        """The group's own map's pager (None before one is attached)."""
        return self.pagers.get("")

    def keys(self, member: str = "") -> list[tuple[int, int]]:
        """The tile keys on disk (of ``member``: the map, or a copy of it)."""
        return [k for k, ms in self._members.items() if member in ms]

    def __contains__(self, key: tuple[int, int]) -> bool:
        return key in self._files

    def write(self, key: tuple[int, int], members: dict[str, dict[str, np.ndarray]]) -> int:
        """Write tile ``key``: the layers of each member (``""``: the map, else a copy of it)
        atomically in one file (replacing any older file of it); returns the bytes written (0:
        the file of the tile holds these layers already, and stays)."""
        blosc2 = _codec()
        blobs, entries = [], []
        encoded: dict[str, tuple[str, np.ndarray]] = {}  # the map's layers, encoded
        for member in sorted(members):  # the map first: copies are stored against it
            for name, a in members[member].items():
                a = np.ascontiguousarray(a)
                encoding, data, typesize = _encode(a)
                entry = {"name": f"{member}/{name}" if member else name, "dtype": a.dtype.str}
                base = encoded.get(name)
                if (
                    member
                    and base is not None
                    and base[0] == encoding
                    and len(base[1]) == len(data)
                ):
                    data = np.bitwise_xor(data, base[1])
                    entry["against"] = name
                elif not member:
                    encoded[name] = (encoding, data)
                blob = blosc2.compress2(
                    data,
                    typesize=typesize,
                    codec=blosc2.Codec.ZSTD,
                    clevel=1,
                    filters=[blosc2.Filter.SHUFFLE],
                    nthreads=1,
                )
                blobs.append(blob)
                entry.update(
                    shape=list(a.shape), nbytes=len(blob), crc32=zlib.crc32(blob), encoding=encoding
                )
                entries.append(entry)
        header = json.dumps({"key": list(key), "layers": entries}).encode()
        data = b"".join([_HEAD.pack(_MAGIC, STORE_VERSION, len(header)), header, *blobs])
        old = self._files.get(key)
        if old is not None and self._holds(old[1], data):
            # not changed since its last write (a tile that a checkpoint wrote and that left
            # memory later unwritten): no new generation beside the one the checkpoint keeps
            return 0
        gen = self._gen
        self._gen += 1
        held = frozenset(members)
        name = _tile_name(key, gen, held)
        path = self.folder / name
        self.store._write(lambda: _write_atomic(path, data), path)
        self._files[key] = (gen, name)
        self._members[key] = held
        self.unsynced.add(name)
        self.nbytes += len(data)
        if old is not None:
            if old[1] in self.pinned:  # the last checkpoint names it: it goes at the next one
                self.retired.append(old[1])
            else:
                self._unlink(old[1])
        return len(data)

    def _holds(self, name: str, data: bytes) -> bool:
        """Whether tile file ``name`` holds ``data`` (the encoding is deterministic: the same
        layers give the same bytes)."""
        path = self.folder / name
        try:
            return path.stat().st_size == len(data) and path.read_bytes() == data
        except OSError:
            return False

    def put(self, key: tuple[int, int], take: bool) -> int:
        """Write tile ``key`` of every member: those in memory as they are, those stored as their
        file holds them; with ``take`` the members' tiles in memory then leave it (as the maps
        they are copies of, a copy's tiles leave and stay together). Returns the bytes written;
        a tile whose write fails stays in memory."""
        members: dict[str, dict[str, np.ndarray]] = {}
        moving = []
        old = None
        for member, p in self.pagers.items():
            layers = p.resident_layers(key)
            if layers is not None:
                members[member] = layers
                moving.append(p)
            elif key in p.stored:
                if old is None:
                    old = self.read(key)
                members[member] = _member_layers(old, member)
        n = self.write(key, members) if members else 0
        if take:
            for p in moving:
                p.took(key, members[p.member])
        return n

    def flush(self) -> int:
        """Write every tile in memory of every member (they stay in memory); returns the bytes."""
        keys = dict.fromkeys(k for p in self.pagers.values() for k in p.resident_keys())
        return sum(self.put(k, take=False) for k in keys)

    def sync(self) -> int:
        """Make the tile files written since the last sync durable (fsync each, then the
        group's folder, whose entries the renames changed), so that a checkpoint written after
        this names only tiles a power loss keeps; returns how many files were synced."""
        names = [n for n in self.unsynced if (self.folder / n).exists()]
        for name in names:
            fd = os.open(self.folder / name, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        _fsync_dir(self.folder)
        self.unsynced = set()
        return len(names)

    def _unlink(self, name: str) -> None:
        self.unsynced.discard(name)
        p = self.folder / name
        self.nbytes -= p.stat().st_size
        p.unlink()

    def pin(self) -> None:
        """A checkpoint names the files as they are now: keep them until the next pin, and
        remove those replaced since the last one."""
        self.pinned = {n for _, n in self._files.values()}
        for name in self.retired:
            if name not in self.pinned:
                self._unlink(name)
        self.retired = []

    def restore(self) -> None:
        """Back to a checkpoint (this group as it was pickled): every tile file it does not name
        (written after it) goes."""
        self.pinned = {n for _, n in self._files.values()}
        self.retired = []
        self.unsynced = set()  # those it names were synced before it was written
        for f in os.scandir(self.folder):
            if f.name not in self.pinned and (_TILE_NAME.match(f.name) or f.name.endswith(".part")):
                os.unlink(f.path)
        self.nbytes = sum((self.folder / n).stat().st_size for n in self.pinned)

    def read(self, key: tuple[int, int], member: str | None = None) -> dict[str, np.ndarray]:
        """The layers of tile ``key`` (fresh, writable arrays): of ``member`` by their names, or
        (None) of every member, a copy's named ``MEMBER/NAME``; StoreError naming the file if it
        is damaged or of another version."""
        if self.store.removed:  # e.g. maps an observer kept past the end of their run
            raise StoreError(
                f"tile {key} of {self.folder.name!r} was paged out to a temporary tile store "
                f"({self.store.root}) removed when its run ended: read the maps during the run, "
                "or save them (--save-maps, evgrid.grid.save_map)"
            )
        path = self.folder / self._files[key][1]
        got = read_tile_file(path, key, member)
        return got if member is None else _member_layers(got, member)

    def write_meta(self, meta: dict[str, Any]) -> None:
        """``map.json``: what the group's tiles belong to."""
        path = self.folder / "map.json"
        doc = {"format": _STORE_FORMAT, "version": STORE_VERSION, "map": meta}
        self.store._write(lambda: _write_atomic(path, json.dumps(doc).encode()), path)

    def read_meta(self) -> dict[str, Any]:
        """What :meth:`write_meta` wrote; StoreError naming the file if missing or damaged."""
        return read_group_meta(self.folder)


def _member_layers(layers: dict[str, np.ndarray], member: str) -> dict[str, np.ndarray]:
    """The layers of one member among a tile file's (a copy's are named ``MEMBER/NAME``)."""
    if not member:
        return {n: a for n, a in layers.items() if "/" not in n}
    pre = member + "/"
    return {n[len(pre) :]: a for n, a in layers.items() if n.startswith(pre)}


def read_group_meta(folder: Path) -> dict[str, Any]:
    """A group's ``map.json``, checked (StoreError naming the file)."""
    path = Path(folder) / "map.json"
    try:
        d = json.loads(path.read_bytes())
    except FileNotFoundError as e:
        raise StoreError(f"{path} is missing: {folder} is not a map of an evgrid tile store") from e
    except (OSError, ValueError) as e:
        raise StoreError(f"{path} is damaged ({e})") from e
    if not isinstance(d, dict) or d.get("format") != _STORE_FORMAT:
        raise StoreError(f"{path} is not the header of an evgrid tile store's map")
    if d.get("version") != STORE_VERSION:
        raise StoreError(
            f"{path} belongs to a tile store of version {d.get('version')!r}; this evgrid reads "
            f"version {STORE_VERSION}"
        )
    return d


def read_tile_file(
    path: Path, key: tuple[int, int] | None = None, member: str | None = None
) -> dict[str, np.ndarray]:
    """The layers of one tile file (a copy's named ``MEMBER/NAME``; with ``member`` only those of
    that member, ``""`` the map's, named as in the file); StoreError naming it if it is damaged,
    of another version, or (with ``key``) holds another tile."""
    blosc2 = _codec()
    try:
        data = path.read_bytes()
    except OSError as e:
        raise StoreError(f"{path}: cannot read the tile ({e})") from e
    if len(data) < _HEAD.size:
        raise StoreError(f"{path} is truncated: not a whole tile of the store")
    magic, version, n = _HEAD.unpack_from(data)
    if magic != _MAGIC:
        raise StoreError(f"{path} is not a tile of an evgrid tile store")
    if version != STORE_VERSION:
        raise StoreError(
            f"{path} is a tile of store version {version}; this evgrid reads {STORE_VERSION}"
        )
    try:
        header = json.loads(data[_HEAD.size : _HEAD.size + n])
        got = tuple(header["key"])
        out: dict[str, np.ndarray] = {}
        encoded: dict[str, np.ndarray] = {}  # the map's layers as stored, for its copies'
        at = _HEAD.size + n
        pre = None if member is None else f"{member}/" if member else ""
        wanted = {e.get("against") for e in header["layers"] if pre and e["name"].startswith(pre)}
        for e in header["layers"]:
            blob = data[at : at + e["nbytes"]]
            at += e["nbytes"]
            mine = pre is None or (e["name"].startswith(pre) if pre else "/" not in e["name"])
            if not mine and e["name"] not in wanted:
                continue  # another member's, not needed to decode this one's
            if len(blob) != e["nbytes"] or zlib.crc32(blob) != e["crc32"]:
                raise ValueError(f"layer {e['name']!r} fails its CRC-32")
            dtype, shape = np.dtype(e["dtype"]), tuple(e["shape"])
            if dtype.hasobject:
                raise ValueError(f"layer {e['name']!r} has dtype {dtype}")
            raw = np.frombuffer(bytearray(blosc2.decompress2(blob)), np.uint8)
            against = e.get("against")
            if against is not None:
                raw ^= encoded[against]  # KeyError: a copy against a layer the file lacks
            elif "/" not in e["name"]:
                encoded[e["name"]] = raw
            if not mine:
                continue
            encoding = e.get("encoding")
            if encoding == "masses":
                out[e["name"]] = _decode_masses(raw, shape)
            elif encoding == "raw":
                out[e["name"]] = raw.view(dtype).reshape(shape)
            else:
                raise ValueError(f"layer {e['name']!r} has an unknown encoding {encoding!r}")
    except StoreError:
        raise
    except Exception as e:  # noqa: BLE001 - whatever a damaged file makes json, numpy or blosc2 raise
        why = " ".join(str(e).split())[:200]
        raise StoreError(f"{path} is damaged: {type(e).__name__}: {why}") from e
    if key is not None and got != tuple(key):
        raise StoreError(f"{path} holds tile {got}, not {tuple(key)}; the store is damaged")
    return out


def tile_distance_m(
    key: tuple[int, int], tile_cells: int, resolution: float, x: float, y: float
) -> float:
    """Distance (m) from map point ``(x, y)`` to the nearest point of tile ``key`` (map cell
    ``(R, C)`` holds ``-x / res`` in ``[R, R + 1)``, as ``GridSpec.map_xy_to_cell`` says)."""
    r, c = -x / resolution, -y / resolution
    lo_r, lo_c = key[0] * tile_cells, key[1] * tile_cells
    dr = max(lo_r - r, 0.0, r - (lo_r + tile_cells))
    dc = max(lo_c - c, 0.0, c - (lo_c + tile_cells))
    return math.hypot(dr, dc) * resolution


class Pager:
    """The tiles of a raster moving between memory and a :class:`TileGroup`.

    ``layers`` are the raster's resident tiles, one dict per layer (the same dicts the raster
    reads and writes). A tile paged out leaves every layer's dict for one file; reading a stored
    tile (:meth:`peek`) gives read-only arrays from a small cache and leaves it on disk; taking
    it back to write (:meth:`page_in`) puts it back into the dicts. ``summary`` (optional) is
    computed from a tile's layers as it leaves and kept in :attr:`stored`. ``member``: ``""``
    for the group's own map, else the name of a copy of it kept in the same files (its tiles
    leave memory with the map's of the same key).
    """

    def __init__(
        self,
        group: TileGroup,
        layers: dict[str, dict[tuple[int, int], np.ndarray]],
        summary: Callable[[dict[str, np.ndarray]], Any] | None = None,
        expect: dict[str, tuple[tuple[int, ...], np.dtype]] | None = None,
        member: str = "",
    ):
        if member and not _MEMBER_NAME.match(member) or member == "map":
            raise ValueError(f"a copy's name is 1-20 letters a-z but not 'map', got {member!r}")
        if member in group.pagers:
            raise ValueError(f"{group.folder} already has a raster paging as {member or 'map'!r}")
        if any("/" in name for name in layers):
            raise ValueError(f"a layer's name has no '/', got {sorted(layers)}")
        self.group = group
        self.member = member
        group.pagers[member] = self
        self.layers = layers
        self.expect = expect or {}
        self.summary = summary
        self.stored: dict[tuple[int, int], Any] = {k: None for k in group.keys(member)}
        self._cache: OrderedDict[tuple[int, int], dict[str, np.ndarray]] = OrderedDict()
        self.n_out = 0
        self.n_in = 0

    def __getstate__(self) -> dict:
        # a checkpoint (evgrid.checkpoint) leaves out the read cache: the tiles are on disk
        return {**self.__dict__, "_cache": OrderedDict()}

    def resident_keys(self) -> list[tuple[int, int]]:
        """The keys of the tiles in memory."""
        return list(next(iter(self.layers.values()), {}))

    def resident_layers(self, key: tuple[int, int]) -> dict[str, np.ndarray] | None:
        """Tile ``key``'s layers in memory, or None when it is not in memory."""
        got = {name: d[key] for name, d in self.layers.items() if key in d}
        return got or None

    def took(self, key: tuple[int, int], layers: dict[str, np.ndarray]) -> None:
        """Tile ``key`` (its ``layers``) is in the group now: it leaves memory."""
        for d in self.layers.values():
            d.pop(key, None)
        self.stored[key] = self.summary(layers) if self.summary else None
        self.n_out += 1

    def peek(self, key: tuple[int, int]) -> dict[str, np.ndarray]:
        """The layers of stored tile ``key``, read-only, left on disk."""
        got = self._cache.get(key)
        if got is not None:
            self._cache.move_to_end(key)
            return got
        got = self._read(key)
        for a in got.values():
            a.flags.writeable = False
        self._cache[key] = got
        if len(self._cache) > READ_CACHE_TILES:
            self._cache.popitem(last=False)
        return got

    def _read(self, key: tuple[int, int]) -> dict[str, np.ndarray]:
        got = self.group.read(key, self.member)
        for name, (shape, dtype) in self.expect.items():
            a = got.get(name)
            if a is None or a.shape != shape or a.dtype != dtype:
                what = "missing" if a is None else f"{a.dtype} {a.shape}"
                who = f" of copy {self.member!r}" if self.member else ""
                raise StoreError(
                    f"{self.group.folder / self.group._files[key][1]}: layer {name!r}{who} is "
                    f"{what}, not {np.dtype(dtype)} {shape}; the store is damaged or of another map"
                )
        return got

    def page_in(self, key: tuple[int, int]) -> None:
        """Bring stored tile ``key`` back into the layers' dicts (to be written)."""
        got = self._cache.pop(key, None)
        got = self._read(key) if got is None else {n: a.copy() for n, a in got.items()}
        for name, d in self.layers.items():
            if name in got:
                d[key] = got[name]
        del self.stored[key]
        self.n_in += 1

    def page_out(self, keys: list[tuple[int, int]]) -> int:
        """Write resident tiles ``keys`` to the group and drop them from memory (with the tiles
        of the same keys of the map's copies, or of the map a copy is of); returns the bytes
        written. A tile whose write fails stays in memory."""
        return sum(self.group.put(key, take=True) for key in keys)

    def flush(self) -> int:
        """Write every resident tile to the group, keeping it in memory (the group then holds the
        whole raster as it is now, and its copies or the map it is a copy of); returns the bytes
        written."""
        return self.group.flush()


class TileLayer(MutableMapping):
    """One layer of a paged raster by tile key: its resident tiles and, read-only, its stored ones.

    Reads behave as the dict of resident tiles did before paging, over every tile (resident or
    stored); a stored tile reads as a read-only array (writing goes through the raster's
    ``tile(key)``, which brings the tile back). Setting a key brings a stored tile back first.
    """

    __slots__ = ("_res", "_name", "_owner")

    def __init__(self, resident: dict, name: str, owner: Any):
        self._res = resident
        self._name = name
        self._owner = owner  # has .pager (None: nothing paged)

    def __getitem__(self, key):
        a = self._res.get(key)
        if a is not None:
            return a
        p = self._owner.pager
        if p is not None and key in p.stored:
            got = p.peek(key).get(self._name)
            if got is not None:
                return got
        raise KeyError(key)

    def get(self, key, default=None):
        a = self._res.get(key)
        if a is not None:
            return a
        try:
            return self[key]
        except KeyError:
            return default

    def __contains__(self, key) -> bool:
        if key in self._res:
            return True
        p = self._owner.pager
        return p is not None and key in p.stored and self._owner._layer_has(self._name)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        yield from list(self._res)
        p = self._owner.pager
        if p is not None and self._owner._layer_has(self._name):
            yield from list(p.stored)

    def __len__(self) -> int:
        p = self._owner.pager
        extra = len(p.stored) if p is not None and self._owner._layer_has(self._name) else 0
        return len(self._res) + extra

    def __bool__(self) -> bool:
        return len(self) > 0

    def __setitem__(self, key, value) -> None:
        p = self._owner.pager
        if p is not None and key in p.stored:
            p.page_in(key)
        self._res[key] = value

    def __delitem__(self, key) -> None:
        p = self._owner.pager
        if p is not None and key in p.stored:
            p.page_in(key)
        del self._res[key]

    @property
    def resident(self) -> dict:
        """The tiles in memory."""
        return self._res

    def __repr__(self) -> str:
        return f"TileLayer({self._name!r}, {len(self._res)} resident, {len(self)} in all)"


#: A radius this large keeps every tile in memory (no store is made).
ALL_RESIDENT_M = 1e9


@dataclass(frozen=True)
class StoreParams:
    """Where a run's map tiles live (docs/store.md); never changes the maps.

    Tiles of every map whose nearest point lies farther than ``resident_m`` metres from the
    vehicle leave memory for the run's tile store on disk and come back when the vehicle
    returns. ``1e9`` keeps every tile in memory. A radius below the reach of one update (half
    the local grid's diagonal, plus the navigation map's margin) is allowed but pages tiles
    out and in at every update.
    """

    resident_m: float = 50.0

    def __post_init__(self) -> None:
        from evgrid.validation import check_number

        v = self.resident_m
        if isinstance(v, (int, float)) and not isinstance(v, bool) and v > ALL_RESIDENT_M:
            raise ValueError(
                f"StoreParams.resident_m: {v!r} m is beyond any map; give at most "
                f"{ALL_RESIDENT_M:g} (which keeps every tile in memory)"
            )
        check_number(self, "resident_m", min=0.0)

    @property
    def paging(self) -> bool:
        """Whether tiles leave memory at all."""
        return self.resident_m < ALL_RESIDENT_M
