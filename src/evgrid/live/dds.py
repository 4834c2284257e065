"""ROS 2 on DDS without ROS: topic and type names, QoS profiles, and readers and writers of raw
CDR payloads through the ``cyclonedds`` binding (the ``live`` extra).

ROS 2's rules (rmw_cyclonedds, rmw_fastrtps): topic ``/x/y`` is the DDS topic ``rt/x/y``; type
``pkg/msg/T`` is ``pkg::msg::dds_::T_``; the payload is plain little-endian CDR (XCDR1, the
4-byte encapsulation header ``00 01 00 00``), which is exactly what rosbags' CDR serializer
writes and what a ROS 2 bag records. So evgrid moves payloads as bytes: what it reads is decoded
by the same type store as a recording, what it writes is the bytes a recording would hold.

The DDS types themselves (for the type name and the type information matching asks for) are
built from rosbags' definitions of each message: final structs, fields in the ``.msg`` order.
"""

from __future__ import annotations

import functools
import logging
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from evgrid.ros import require

__all__ = [
    "dds_topic",
    "dds_type",
    "idl_type",
    "QosProfile",
    "SENSOR_QOS",
    "TF_QOS",
    "TF_STATIC_QOS",
    "MAP_QOS",
    "domain_id",
    "Graph",
    "RawReader",
    "RawWriter",
    "loopback_config",
]

log = logging.getLogger(__name__)


def dds_topic(topic: str) -> str:
    """The DDS topic of a ROS 2 topic (``/map`` -> ``rt/map``)."""
    return "rt/" + topic.lstrip("/")


def dds_type(msgtype: str) -> str:
    """The DDS type name of a ROS 2 message type (``nav_msgs/msg/OccupancyGrid`` ->
    ``nav_msgs::msg::dds_::OccupancyGrid_``)."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def domain_id() -> int:
    """``ROS_DOMAIN_ID`` (default 0), as ROS 2 reads it."""
    raw = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not raw:
        return 0
    if not raw.isdigit() or not 0 <= int(raw) <= 232:
        raise ValueError(f"ROS_DOMAIN_ID must be an integer 0-232, got {raw!r}")
    return int(raw)


def loopback_config() -> str:
    """A ``CYCLONEDDS_URI`` value keeping DDS on this machine: the loopback interface, no
    multicast, peers found at localhost (tests, demos)."""
    return (
        '<CycloneDDS><Domain><General><Interfaces><NetworkInterface name="lo"/></Interfaces>'
        "<AllowMulticast>false</AllowMulticast></General><Discovery>"
        "<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>40"
        '</MaxAutoParticipantIndex><Peers><Peer address="localhost"/></Peers></Discovery>'
        "</Domain></CycloneDDS>"
    )


# --- types ------------------------------------------------------------------------------------

_BASE = {
    "bool": "bool",
    "byte": "uint8",
    "char": "uint8",
    "int8": "int8",
    "uint8": "uint8",
    "int16": "int16",
    "uint16": "uint16",
    "int32": "int32",
    "uint32": "uint32",
    "int64": "int64",
    "uint64": "uint64",
    "float32": "float32",
    "float64": "float64",
}


@functools.cache
def idl_type(msgtype: str) -> type:
    """The DDS type of a ROS 2 message (from the type store's definition): a final IDL struct
    named as ROS 2 names it, its fields in the ``.msg`` order."""
    require("cyclonedds", "live")
    import types as pytypes
    from dataclasses import dataclass as make_dataclass

    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl import annotations as annotate
    from cyclonedds.idl import types as t
    from rosbags.typesys.store import Nodetype

    from evgrid.ros import typestore

    store = typestore(2)

    def base(spec: tuple) -> Any:
        name, bound = spec
        if name == "string":
            return t.bounded_str[bound] if bound else str
        if name == "wstring":
            raise ValueError(f"{msgtype}: wstring fields are not supported")
        return getattr(t, _BASE[name]) if name != "bool" else bool

    def field(node: tuple) -> Any:
        kind, spec = node
        if kind == Nodetype.BASE:
            return base(spec)
        if kind == Nodetype.NAME:
            return idl_type(spec)
        inner, n = spec
        if kind == Nodetype.ARRAY:
            return t.array[field(inner), n]
        return t.sequence[field(inner), n] if n else t.sequence[field(inner)]

    _, fields = store.fielddefs[msgtype]
    ann = {name: field(node) for name, node in fields}
    if not ann:  # an empty .msg is a struct with one uint8 in ROS 2's IDL
        ann = {"structure_needs_at_least_one_member": t.uint8}

    def body(ns: dict) -> None:
        ns["__annotations__"] = ann

    cls = pytypes.new_class(
        msgtype.split("/")[-1] + "_", (IdlStruct,), {"typename": dds_type(msgtype)}, body
    )
    return annotate.final(make_dataclass(cls))


# --- QoS --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class QosProfile:
    """The QoS of one ROS 2 topic: reliable or best effort, transient local or volatile, keep last
    ``depth``."""

    reliable: bool
    transient_local: bool
    depth: int

    def dds(self) -> Any:
        from cyclonedds.core import Policy, Qos
        from cyclonedds.util import duration

        return Qos(
            Policy.Reliability.Reliable(duration(seconds=1))
            if self.reliable
            else Policy.Reliability.BestEffort,
            Policy.Durability.TransientLocal
            if self.transient_local
            else Policy.Durability.Volatile,
            Policy.History.KeepLast(self.depth),
            Policy.DataRepresentation(use_cdrv0_representation=True),
        )

    def describe(self) -> str:
        return (
            f"{'reliable' if self.reliable else 'best effort'}, "
            f"{'transient local' if self.transient_local else 'volatile'}, depth {self.depth}"
        )


#: Sensor topics: best effort (rclcpp's SensorDataQoS); a best-effort reader also matches
#: reliable publishers.
SENSOR_QOS = QosProfile(reliable=False, transient_local=False, depth=5)
#: ``/tf``: tf2's broadcaster, reliable and volatile.
TF_QOS = QosProfile(reliable=True, transient_local=False, depth=100)
#: ``/tf_static``: tf2's static broadcaster, reliable and transient local (late joiners get it).
TF_STATIC_QOS = QosProfile(reliable=True, transient_local=True, depth=1)
#: ``/map`` and evgrid's map topics: map_server's, reliable, transient local, depth 1.
MAP_QOS = QosProfile(reliable=True, transient_local=True, depth=1)

#: DDS QoS policy ids (the ``last_policy_id`` of an incompatible-QoS status) by name.
_POLICY_NAMES = {
    2: "DURABILITY",
    3: "PRESENTATION",
    4: "DEADLINE",
    5: "LATENCY_BUDGET",
    6: "OWNERSHIP",
    8: "LIVELINESS",
    10: "PARTITION",
    11: "RELIABILITY",
    12: "DESTINATION_ORDER",
    13: "HISTORY",
    23: "DATA_REPRESENTATION",
}


# --- the graph ----------------------------------------------------------------------------------


class Graph:
    """A DDS participant on ``ROS_DOMAIN_ID`` (or ``domain``) with raw readers and writers of ROS 2
    topics; QoS mismatches are logged by topic and policy (``on_problem`` hears them too)."""

    def __init__(self, domain: int | None = None, on_problem: Callable[[str], None] | None = None):
        require("cyclonedds", "live")
        from cyclonedds.domain import DomainParticipant

        self.domain = domain_id() if domain is None else domain
        self.participant = DomainParticipant(self.domain)
        self.on_problem = on_problem
        self._topics: dict[str, Any] = {}
        self._lock = threading.Lock()

    def _topic(self, topic: str, msgtype: str) -> Any:
        from cyclonedds.topic import Topic

        with self._lock:
            found = self._topics.get(topic)
            if found is None:
                found = self._topics[topic] = Topic(
                    self.participant, dds_topic(topic), idl_type(msgtype)
                )
            return found

    def problem(self, text: str) -> None:
        log.warning("%s", text)
        if self.on_problem is not None:
            self.on_problem(text)

    def reader(self, topic: str, msgtype: str, qos: QosProfile) -> RawReader:
        return RawReader(self, topic, msgtype, qos)

    def writer(self, topic: str, msgtype: str, qos: QosProfile) -> RawWriter:
        return RawWriter(self, topic, msgtype, qos)

    def close(self) -> None:
        """Leave the graph (readers and writers go with the participant)."""
        from cyclonedds.core import DDSException

        try:
            # the binding deletes an entity (and what it holds) only when collected
            self.participant.__del__()
        except (DDSException, AttributeError):
            pass


def _policy(status: Any) -> str:
    pid = int(getattr(status, "last_policy_id", 0))
    return _POLICY_NAMES.get(pid, f"policy {pid}")


class RawReader:
    """A reader of a ROS 2 topic that hands out the raw CDR payloads (bytes with their 4-byte
    header); :meth:`take` never blocks."""

    def __init__(self, graph: Graph, topic: str, msgtype: str, qos: QosProfile):
        from cyclonedds.core import Listener
        from cyclonedds.sub import DataReader

        self.topic, self.msgtype, self.qos = topic, msgtype, qos

        def incompatible(reader: Any, status: Any) -> None:
            graph.problem(
                f"QoS mismatch on {topic}: a publisher's {_policy(status)} is incompatible with "
                f"what evgrid asks ({qos.describe()}); its messages are not received"
            )

        self._reader = DataReader(
            graph.participant,
            graph._topic(topic, msgtype),
            qos=qos.dds(),
            listener=Listener(on_requested_incompatible_qos=incompatible),
        )

    def take(self, n: int = 64) -> list[tuple[bytes, int]]:
        """Up to ``n`` payloads waiting, oldest first, each with its DDS source timestamp (ns)."""
        from cyclonedds._clayer import ddspy_take
        from cyclonedds.core import InstanceState, SampleState, ViewState

        ret = ddspy_take(self._reader._ref, SampleState.Any | ViewState.Any | InstanceState.Any, n)
        if isinstance(ret, int):
            from cyclonedds.core import DDSException

            raise DDSException(ret, f"taking from {self.topic}")
        return [(bytes(data), int(info.source_timestamp)) for data, info in ret if info.valid_data]

    def publishers(self) -> int:
        """How many publishers are matched."""
        return len(self._reader.get_matched_publications())


class RawWriter:
    """A writer of a ROS 2 topic that sends raw CDR payloads (as rosbags serialises them)."""

    def __init__(self, graph: Graph, topic: str, msgtype: str, qos: QosProfile):
        from cyclonedds.core import Listener
        from cyclonedds.pub import DataWriter

        self.topic, self.msgtype, self.qos = topic, msgtype, qos

        def incompatible(writer: Any, status: Any) -> None:
            graph.problem(
                f"QoS mismatch on {topic}: a subscriber asks for a {_policy(status)} that evgrid's "
                f"publisher ({qos.describe()}) does not offer; it receives nothing"
            )

        self._writer = DataWriter(
            graph.participant,
            graph._topic(topic, msgtype),
            qos=qos.dds(),
            listener=Listener(on_offered_incompatible_qos=incompatible),
        )

    def write(self, payload: bytes | bytearray | memoryview, stamp_ns: int | None = None) -> None:
        """Send one serialised message (CDR with its header), padded to 4 bytes as DDS wants."""
        from cyclonedds._clayer import ddspy_write, ddspy_write_ts

        data = bytes(payload)
        if len(data) % 4:
            data += b"\0" * (4 - len(data) % 4)
        ret = (
            ddspy_write(self._writer._ref, data)
            if stamp_ns is None
            else ddspy_write_ts(self._writer._ref, data, int(stamp_ns))
        )
        if ret < 0:
            from cyclonedds.core import DDSException

            raise DDSException(ret, f"writing to {self.topic}")

    def subscribers(self) -> int:
        """How many subscribers are matched."""
        return len(self._writer.get_matched_subscriptions())
