"""How a ROS 2 node appears on Zenoh (ros2/rmw_zenoh's docs/design.md): the key expressions
of topics and services, the liveliness tokens that put the node and its publishers,
subscriptions and service servers in the ROS 2 graph, their compact QoS text, and the
attachment every publication, request and reply carries. Pure functions and small values:
nothing here opens a session.

Key expression of a topic or a service::

    <domain_id>/<fully qualified name, no leading '/'>/<DDS type name>/<RIHS01 type hash>

Liveliness token (a node: up to the node name; an entity adds the rest)::

    @ros2_lv/<domain_id>/<session id>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/
    <node name>[/<name>/<DDS type name>/<type hash>/<qos>]

with every '/' inside a name written '%' (the root namespace and enclave are ``%``).
"""
from __future__ import annotations

import struct
import time
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION, SERVICE_SERVER, SERVICE_CLIENT = "NN", "MP", "MS", "SS", "SC"
#: attachment: sequence number (int64 LE), source timestamp (ns, int64 LE), GID length, GID
_ATTACHMENT = struct.Struct("<qqB")
GID_SIZE = 16


def mangle(name: str) -> str:
    """A name as one key chunk: '/' -> '%' (the root namespace '/' is '%')."""
    return name.replace("/", "%")


def qualified(namespace: str, name: str) -> str:
    """The fully qualified name of ``name`` (relative or absolute) in ``namespace``."""
    if name.startswith("/"):
        return name
    return f"{namespace.rstrip('/')}/{name}"


def topic_key(domain_id: int, name: str, dds_type: str, type_hash: str) -> str:
    """The key expression a topic's or a service's data goes on; ``name`` fully qualified."""
    return f"{domain_id}/{name.strip('/')}/{dds_type}/{type_hash}"


@dataclass(frozen=True)
class Qos:
    """The QoS a token announces (rmw's enums: reliability 1 reliable, 2 best effort;
    durability 1 transient local, 2 volatile; history 1 keep last, 2 keep all), lifespan in
    s (None: infinite)."""
    depth: int = 10
    reliability: int = 1
    durability: int = 2
    history: int = 1
    lifespan: float | None = None

    def text(self) -> str:
        """rmw_zenoh's compact form: every field equal to its default (reliable, volatile,
        keep last 42, infinite deadline, lifespan and lease, automatic liveliness) left
        empty: ``<rel>:<dur>:<hist>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,
        <lease s>,<ns>``."""
        def field(value: int, default: int) -> str:
            return "" if value == default else str(value)
        lifespan = ","
        if self.lifespan is not None:
            sec = int(self.lifespan)
            lifespan = f"{sec},{round((self.lifespan - sec) * 1e9)}"
        return (f"{field(self.reliability, 1)}:{field(self.durability, 2)}:"
                f"{field(self.history, 1)},{field(self.depth, 42)}:,:{lifespan}:,,")


#: rclcpp's default profile and the services' (reliable, volatile, keep last 10)
DEFAULT_QOS = Qos()
#: /rosout's (depth 1000, lifespan 10 s; volatile here: no publication cache is kept)
ROSOUT_QOS = Qos(depth=1000, lifespan=10.0)


@dataclass(frozen=True)
class NodeName:
    """Who the node is in the graph: ``session`` is the Zenoh session id (hex)."""
    domain_id: int
    session: str
    name: str
    namespace: str = "/"
    enclave: str = "/"
    node_id: int = 0

    def token(self) -> str:
        return "/".join((ADMIN_SPACE, str(self.domain_id), self.session, str(self.node_id),
                         str(self.node_id), NODE, mangle(self.enclave),
                         mangle(self.namespace), self.name))

    def entity_token(self, entity_id: int, kind: str, name: str, dds_type: str,
                     type_hash: str, qos: Qos = DEFAULT_QOS) -> str:
        """A publisher's, subscription's or service's token; ``name`` fully qualified."""
        return "/".join((ADMIN_SPACE, str(self.domain_id), self.session, str(self.node_id),
                         str(entity_id), kind, mangle(self.enclave), mangle(self.namespace),
                         self.name, mangle(name), dds_type, type_hash, qos.text()))


def attachment(sequence: int, gid: bytes, stamp_ns: int | None = None) -> bytes:
    """The attachment of a publication, a request or a reply."""
    if stamp_ns is None:
        stamp_ns = time.time_ns()
    return _ATTACHMENT.pack(sequence, stamp_ns, len(gid)) + gid


@dataclass(frozen=True)
class Attachment:
    sequence: int
    stamp_ns: int
    gid: bytes


def read_attachment(data: bytes | None) -> Attachment | None:
    """A request's attachment (None: absent or not one: too short, a GID cut off)."""
    if data is None or len(data) < _ATTACHMENT.size:
        return None
    sequence, stamp, size = _ATTACHMENT.unpack_from(data)
    gid = bytes(data[_ATTACHMENT.size:_ATTACHMENT.size + size])
    return Attachment(sequence, stamp, gid) if len(gid) == size else None
