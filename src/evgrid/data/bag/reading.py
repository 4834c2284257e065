"""Reading recordings: the messages of some topics of a ROS 1 bag, a ROS 2 bag (sqlite3 or MCAP
storage) or a plain MCAP file, in bag order, up to where a damaged file breaks."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from evgrid.data.bag.errors import BagError

__all__ = ["bag_kind", "Recording"]


def bag_kind(path: str | Path) -> str:
    """``ros1`` (a ``.bag`` file), ``ros2-sqlite3`` / ``ros2-mcap`` (a rosbag2 folder) or
    ``mcap`` (a file)."""
    p = Path(path)
    if p.is_dir():
        meta = p / "metadata.yaml"
        if not meta.is_file():
            raise BagError(f"{p} is a folder without metadata.yaml: not a ROS 2 bag")
        text = meta.read_text()
        if "storage_identifier: mcap" in text:
            return "ros2-mcap"
        return "ros2-sqlite3"
    if not p.is_file():
        raise FileNotFoundError(f"no recording at {p}")
    if p.suffix == ".bag":
        return "ros1"
    if p.suffix == ".mcap":
        return "mcap"
    if p.suffix == ".db3":
        return "ros2-sqlite3"
    raise BagError(
        f"{p}: unknown recording type (expected a .bag or .mcap file or a ROS 2 bag folder)"
    )


class Recording:
    """Messages of some topics, in bag order, deserialised; notes where a damaged file stopped."""

    def __init__(self, path: str | Path):
        from evgrid.ros import require

        require("rosbags")
        self.path = Path(path)
        self.kind = bag_kind(self.path)
        self.topics: dict[str, str] = {}  # topic -> message type, as far as read
        self.stopped: str | None = None

    def _mcap_files(self) -> list[Path]:
        if self.kind == "mcap":
            return [self.path]
        files = sorted(self.path.glob("*.mcap"))
        if not files:
            raise BagError(f"{self.path}: ROS 2 bag with MCAP storage but no .mcap file in it")
        return files

    def messages(
        self, topics: set[str], count_only: set[str] = frozenset()
    ) -> Iterator[tuple[str, int, Any]]:
        """(topic, bag time ns, message) for ``topics``; ``count_only`` topics yield ``None``
        messages."""
        self.stopped = None
        if self.kind in ("mcap", "ros2-mcap"):
            for f in self._mcap_files():
                yield from self._mcap_messages(f, topics, count_only)
                if self.stopped:
                    return
        else:
            yield from self._rosbags_messages(topics, count_only)

    def _mcap_messages(
        self, path: Path, topics: set[str], count_only: set[str]
    ) -> Iterator[tuple[str, int, Any]]:
        from evgrid.ros import new_typestore, require

        require("mcap")
        from mcap.records import Channel, Message, Schema
        from mcap.stream_reader import StreamReader
        from rosbags.typesys import get_types_from_msg

        store = new_typestore(2)  # the file's own definitions are added to it
        schemas: dict[int, Schema] = {}
        channels: dict[int, tuple[str, str]] = {}
        last_t = None
        with open(path, "rb") as fh:
            reader = StreamReader(fh, validate_crcs=False)
            try:
                for rec in reader.records:
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        sch = schemas.get(rec.schema_id)
                        name = sch.name if sch else ""
                        if (
                            sch is not None
                            and name not in store.fielddefs
                            and sch.encoding == "ros2msg"
                        ):
                            store.register(get_types_from_msg(sch.data.decode(), name))
                        channels[rec.id] = (rec.topic, name)
                        self.topics[rec.topic] = name
                    elif isinstance(rec, Message):
                        topic, typ = channels.get(rec.channel_id, ("", ""))
                        last_t = rec.log_time
                        if topic in count_only:
                            yield topic, rec.log_time, None
                        elif topic in topics:
                            yield topic, rec.log_time, store.deserialize_cdr(rec.data, typ)
            except Exception as e:  # noqa: BLE001 - any damage ends the readable part
                self.stopped = (
                    f"{path} is damaged or truncated at byte {fh.tell()}"
                    f"{f' after bag time {last_t} ns' if last_t is not None else ''}: "
                    f"{type(e).__name__} {e}".rstrip()
                )

    def _rosbags_messages(
        self, topics: set[str], count_only: set[str]
    ) -> Iterator[tuple[str, int, Any]]:
        from rosbags.highlevel import AnyReader

        from evgrid.ros import typestore

        paths = [self.path.parent if self.path.suffix == ".db3" else self.path]
        try:
            reader = AnyReader(paths, default_typestore=typestore(2 if self.kind != "ros1" else 1))
            reader.open()
        except Exception as e:  # noqa: BLE001 - rosbags raises several types for damaged files
            if (
                self.kind == "ros1"
            ):  # a bag whose recording was cut has no index: read it record by record
                yield from self._ros1_scan(topics, count_only)
                return
            raise BagError(
                f"{self.path}: cannot read the recording: {type(e).__name__} {e}"
            ) from None
        last_t = None
        try:
            self.topics.update({c.topic: c.msgtype for c in reader.connections})
            conns = [c for c in reader.connections if c.topic in topics | set(count_only)]
            for conn, t, raw in reader.messages(connections=conns):
                last_t = t
                if conn.topic in count_only:
                    yield conn.topic, t, None
                else:
                    yield conn.topic, t, reader.deserialize(raw, conn.msgtype)
        except Exception as e:  # noqa: BLE001 - any damage ends the readable part
            self.stopped = (
                f"{self.path} is damaged or truncated after bag time {last_t} ns: "
                f"{type(e).__name__} {e}"
            )
        finally:
            reader.close()

    def _ros1_scan(self, topics: set[str], count_only: set[str]) -> Iterator[tuple[str, int, Any]]:
        """Messages of a ROS 1 bag (format 2.0) read record by record, without its index."""
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
        from rosbags.typesys.msg import normalize_msgtype

        store = get_typestore(Stores.EMPTY)
        conns: dict[int, tuple[str, str]] = {}
        last_t = None
        with open(self.path, "rb") as fh:
            if fh.readline() != b"#ROSBAG V2.0\n":
                raise BagError(f"{self.path} is not a ROS 1 bag (format 2.0)")
            try:
                for op, hdr, data in _ros1_records(fh):
                    for op2, hdr2, data2 in (
                        _ros1_chunk(hdr, data) if op == 0x05 else [(op, hdr, data)]
                    ):
                        if op2 == 0x07:  # connection: topic, type and message definition
                            ch = _ros1_header(data2)
                            typ = normalize_msgtype(ch["type"].decode())
                            if typ not in store.fielddefs:
                                store.register(
                                    get_types_from_msg(ch["message_definition"].decode(), typ)
                                )
                            topic = hdr2["topic"].decode()
                            conns[int.from_bytes(hdr2["conn"], "little")] = (topic, typ)
                            self.topics[topic] = typ
                        elif op2 == 0x02:  # message data
                            topic, typ = conns[int.from_bytes(hdr2["conn"], "little")]
                            sec, nsec = (
                                int.from_bytes(hdr2["time"][:4], "little"),
                                int.from_bytes(hdr2["time"][4:], "little"),
                            )
                            last_t = sec * 1_000_000_000 + nsec
                            if topic in count_only:
                                yield topic, last_t, None
                            elif topic in topics:
                                yield topic, last_t, store.deserialize_ros1(data2, typ)
            except Exception as e:  # noqa: BLE001 - any damage ends the readable part
                self.stopped = (
                    f"{self.path} is damaged or truncated at byte {fh.tell()}"
                    f"{f' after bag time {last_t} ns' if last_t is not None else ''}: "
                    f"{type(e).__name__} {e}".rstrip()
                )


def _ros1_header(buf: bytes) -> dict[str, bytes]:
    """Fields ``name=value`` of a ROS 1 record header (each prefixed by its uint32 length)."""
    out, i = {}, 0
    while i < len(buf):
        n = int.from_bytes(buf[i : i + 4], "little")
        name, _, value = buf[i + 4 : i + 4 + n].partition(b"=")
        out[name.decode()] = value
        i += 4 + n
    return out


def _ros1_records(fh: Any) -> Iterator[tuple[int, dict[str, bytes], bytes]]:
    """(op code, header fields, data) of each record of a ROS 1 bag stream; EOFError when one
    is cut short."""
    while True:
        raw = fh.read(4)
        if not raw:
            return
        parts = []
        for k in range(2):
            if len(raw) < 4:
                raise EOFError("record length cut short")
            n = int.from_bytes(raw, "little")
            body = fh.read(n)
            if len(body) < n:
                raise EOFError("record cut short")
            parts.append(body)
            raw = fh.read(4) if k == 0 else b""
        hdr = _ros1_header(parts[0])
        yield hdr["op"][0], hdr, parts[1]


def _ros1_chunk(
    hdr: dict[str, bytes], data: bytes
) -> Iterator[tuple[int, dict[str, bytes], bytes]]:
    import io

    comp = hdr.get("compression", b"none").decode()
    if comp == "bz2":
        import bz2

        data = bz2.decompress(data)
    elif comp == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(data)
    elif comp != "none":
        raise BagError(f"unknown ROS 1 chunk compression {comp!r}")
    return _ros1_records(io.BytesIO(data))
