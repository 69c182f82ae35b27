"""Which nodes are on a bus, and what each one is: the first look at a robot's bus.

A scan only listens and reads: it sends SDO upload requests and nothing else (no NMT
command, no SDO download, no SYNC), so it may run on a bus where a manager drives the
robot, and a drive it finds is left in the NMT and CiA 402 state it was in.

It goes in three steps, bounded as a whole:

1. Listen (``listen`` seconds) for boot-ups and heartbeats (0x700 + node id). The default
   is 1.5 periods of the heartbeat rocoma-can gives drives and the shipped drive file
   has (100 ms): every node producing at that period is heard at least once, whatever
   its phase, and a node that heartbeats slower is found by the probe below. Listening
   goes on until the scan ends, so a slower heartbeat still gives a node's NMT state.
2. Probe every node id not heard with an expedited SDO upload of 0x1000 (device type,
   mandatory on every CANopen device): any answer, an abort too, means a node is there.
   At most ``in_flight`` probes are outstanding at once, each ``timeout`` seconds long:
   one request per slot and timeout keeps the scan's own frames to a trickle on a busy
   bus (SDO requests win arbitration over the drives' heartbeats, never over PDOs).
3. Read each node's objects over SDO, several nodes at once, one canopen SdoClient per
   node id (a client has no lock and takes every answer on its COB-ID: two clients of one
   node would steal each other's answers): 0x1000, 0x1018:1..4, 0x1008, 0x100A (segmented
   uploads), 0x1017. An object the node does not have is None; a node that stops
   answering, or answers frames too short to be SDO, is left after that read, and an
   object longer than MAX_OBJECT_BYTES is cut off there (``FoundNode.problem`` says so).
   A node whose 0x1017 names a heartbeat period not heard yet is waited for up to 1.5
   of its periods (at most ``HEARTBEAT_WAIT``), for its NMT state.
"""
from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Literal

import can
import canopen
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo.client import ReadableStream, SdoClient
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from . import cia301 as c301
from .bus import CanopenBus
from .cia301 import NmtState
from .identity import SUBINDEX, Identity

#: Device name and software version (CiA 301 VISIBLE_STRING objects, optional).
DEVICE_NAME = 0x1008
SOFTWARE_VERSION = 0x100A
#: Listen for heartbeats this long first: 1.5 x the usual 100 ms period (module docstring).
LISTEN = 0.15
#: An SDO answer later than this is taken as none (a drive answers within milliseconds).
TIMEOUT = 0.15
#: SDO probes outstanding at once.
IN_FLIGHT = 16
#: Nodes read at once (one thread and one SDO client each).
READERS = 8
#: The longest a scan waits for the heartbeat of a node whose 0x1017 says it sends one.
HEARTBEAT_WAIT = 1.5
#: The most a scan reads of one object (device name and software version are a few dozen
#: bytes); a longer one is cut off here, its transfer aborted.
MAX_OBJECT_BYTES = 256
#: SDO abort (CiA 301: cs 4) and its code "out of memory", the client's "no more"
_ABORT = 0x80
_ABORT_OUT_OF_MEMORY = 0x0504_0005
#: An expedited upload request of 0x1000:0 (CiA 301: ccs 2).
_PROBE = bytes((0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0))
_NODE_IDS = range(1, 128)

SeenBy = Literal["heartbeat", "boot-up", "sdo"]


@dataclass(frozen=True)
class FoundNode:
    """One node a scan found. None: the node has no such object (or did not answer)."""
    node_id: int
    identity: Identity
    device_type: int | None
    device_name: str | None
    software_version: str | None
    heartbeat_ms: int | None
    #: from its heartbeat: OPERATIONAL, PRE-OPERATIONAL, STOPPED; "unknown" without one
    nmt_state: str
    #: how it was first found: its heartbeat, its boot-up or the SDO probe
    seen_by: SeenBy
    #: why objects are missing, e.g. a node that stopped answering; None when all answered
    problem: str | None = None

    def as_json(self) -> dict[str, object]:
        """Plain values for ``json.dumps`` (the identity as a nested object)."""
        return asdict(self)


def nmt_state_name(byte: int) -> str:
    """A heartbeat's state byte as a name (a boot-up leaves the node PRE-OPERATIONAL)."""
    state = byte & 0x7F  # bit 7 is the node guarding toggle
    if state == NmtState.BOOT_UP:
        return "PRE-OPERATIONAL"
    try:
        return NmtState(state).name.replace("_", "-")
    except ValueError:
        return f"0x{state:02X}"


def visible_string(data: bytes) -> str:
    """A VISIBLE_STRING as printable text: trailing NULs and blanks dropped (devices pad
    their names), anything not printable ASCII escaped, so a device cannot write control
    sequences to the terminal of whoever scans it."""
    text = data.rstrip(b"\x00 ").decode("ascii", "backslashreplace")
    return "".join(c if " " <= c <= "~" else f"\\x{ord(c):02x}" for c in text)


@dataclass
class _Heard:
    """What the listener has seen of one node (written on the bus reader's thread)."""
    first: SeenBy
    state: str


@dataclass
class _Listener:
    heard: dict[int, _Heard] = field(default_factory=dict)
    answered: set[int] = field(default_factory=set)
    changed: threading.Condition = field(default_factory=threading.Condition)

    def on_heartbeat(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        if not data:
            return
        node = cob_id - c301.HEARTBEAT
        with self.changed:
            known = self.heard.get(node)
            first: SeenBy = "boot-up" if data[0] == NmtState.BOOT_UP else "heartbeat"
            self.heard[node] = _Heard(known.first if known else first, nmt_state_name(data[0]))
            self.changed.notify_all()

    def on_probe_answer(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        with self.changed:
            self.answered.add(cob_id - c301.SDO_TX)
            self.changed.notify_all()


def scan(bus: can.BusABC, *, listen: float = LISTEN, timeout: float = TIMEOUT,
         node_ids: Iterable[int] = _NODE_IDS, in_flight: int = IN_FLIGHT,
         readers: int = READERS, clock: Callable[[], float] = time.monotonic
         ) -> list[FoundNode]:
    """Every node among ``node_ids`` on ``bus``, by node id (the module docstring says how).

    The bus is lent: a reader thread of the scan's own reads it meanwhile, and the bus is
    left open. Takes at most about ``listen + ceil(ids / in_flight) x timeout`` for the
    probe, then a few ``timeout`` per ``readers`` nodes that stop answering, plus
    ``HEARTBEAT_WAIT``."""
    ids = sorted(set(node_ids))
    if not all(1 <= n <= 127 for n in ids):
        raise ValueError(f"node ids must be 1..127, got {ids}")
    if not (math.isfinite(listen) and listen >= 0 and math.isfinite(timeout) and timeout > 0
            and in_flight >= 1 and readers >= 1):
        raise ValueError(f"scan: listen >= 0, timeout > 0, in_flight and readers >= 1; got "
                         f"{listen}, {timeout}, {in_flight}, {readers}")
    canopen_bus = CanopenBus(bus)
    network = canopen_bus.network
    heard = _Listener()
    start = clock()
    try:
        for n in ids:
            network.subscribe(c301.HEARTBEAT + n, heard.on_heartbeat)
        time.sleep(listen)  # listen first
        _probe(network, [n for n in ids if n not in heard.heard], heard, timeout, in_flight)
        with heard.changed:
            present = sorted(set(heard.heard) | heard.answered)
        with ThreadPoolExecutor(max_workers=readers, thread_name_prefix="scan") as pool:
            objects = dict(zip(present, pool.map(
                lambda n: _read_objects(network, n, timeout), present)))
        _await_heartbeats(heard, objects, start, clock)
        with heard.changed:
            return [_found(n, objects[n], heard.heard.get(n)) for n in present]
    finally:
        canopen_bus.close()


def _probe(network: canopen.Network, ids: list[int], heard: _Listener, timeout: float,
           in_flight: int) -> None:
    """Send the 0x1000 probes, ``in_flight`` outstanding at once, each ``timeout`` long."""
    for n in ids:
        network.subscribe(c301.SDO_TX + n, heard.on_probe_answer)
    try:
        waiting: dict[int, float] = {}  # node id -> deadline
        queue = list(reversed(ids))
        with heard.changed:
            while queue or waiting:
                now = time.monotonic()
                for n in [n for n, due in waiting.items()
                          if n in heard.answered or due <= now]:
                    del waiting[n]
                while queue and len(waiting) < in_flight:
                    n = queue.pop()
                    waiting[n] = now + timeout
                    network.send_message(c301.SDO_RX + n, _PROBE)
                if waiting:
                    heard.changed.wait(max(0.0, min(waiting.values()) - now))
    finally:
        for n in ids:
            network.unsubscribe(c301.SDO_TX + n, heard.on_probe_answer)


@dataclass
class _Objects:
    values: dict[tuple[int, int], bytes | None] = field(default_factory=dict)
    problem: str | None = None


#: What a scan reads of every node, in order (0x1018:1 is mandatory, the rest optional).
_READS = ((c301.DEVICE_TYPE, 0), *((c301.IDENTITY, s) for s in SUBINDEX.values()),
          (DEVICE_NAME, 0), (SOFTWARE_VERSION, 0), (c301.PRODUCER_HEARTBEAT_TIME, 0))


def _read_objects(network: canopen.Network, node_id: int, timeout: float) -> _Objects:
    """Upload each of _READS; an abort is an object the node lacks, no answer ends it."""
    sdo = SdoClient(c301.SDO_RX + node_id, c301.SDO_TX + node_id, ObjectDictionary())
    sdo.network = network
    sdo.RESPONSE_TIMEOUT = timeout
    sdo.MAX_RETRIES = 1  # one attempt (canopen: 0 retries for ever)
    network.subscribe(sdo.tx_cobid, sdo.on_response)
    found = _Objects()
    cut: list[str] = []
    try:
        for index, subindex in _READS:
            try:
                data, complete = _upload(sdo, index, subindex)
            except SdoAbortedError:
                found.values[(index, subindex)] = None
                continue
            except SdoCommunicationError as exc:
                found.problem = f"no SDO answer reading 0x{index:04X}:{subindex} ({exc})"
                break
            except struct.error:  # canopen unpacks a frame shorter than 8 bytes: garbage
                found.problem = (f"a malformed SDO answer reading 0x{index:04X}:{subindex} "
                                 "(shorter than an SDO frame)")
                break
            found.values[(index, subindex)] = data
            if not complete:
                cut.append(f"0x{index:04X}:{subindex} longer than {MAX_OBJECT_BYTES} bytes: "
                           "cut off")
    finally:
        network.unsubscribe(sdo.tx_cobid, sdo.on_response)
    if cut:
        found.problem = "; ".join(cut + ([found.problem] if found.problem else []))
    return found


def _upload(sdo: SdoClient, index: int, subindex: int) -> tuple[bytes, bool]:
    """An SDO upload of at most MAX_OBJECT_BYTES: the data, and whether that was all of it.
    Past the bound the transfer is aborted (a node that sends segments for ever would hold
    the scan for ever: each segment is one request and one answer)."""
    stream = ReadableStream(sdo, index, subindex)
    data = bytearray()
    while len(data) <= MAX_OBJECT_BYTES:
        chunk = stream.read(7)
        if not chunk:  # the last segment has come (canopen's own end of an upload)
            return bytes(data), True
        data += chunk
    if not stream._done:  # canopen keeps no other record of the last segment
        # the abort sent here, not by SdoClient.abort, which logs an ERROR line for it
        sdo.network.send_message(sdo.rx_cobid, struct.pack(
            "<BHBI", _ABORT, index, subindex, _ABORT_OUT_OF_MEMORY))
    return bytes(data[:MAX_OBJECT_BYTES]), False


def _unsigned(data: bytes | None) -> int | None:
    if data is None or not 1 <= len(data) <= 4:
        return None
    return int.from_bytes(data, "little")


def _await_heartbeats(heard: _Listener, objects: dict[int, _Objects], start: float,
                      clock: Callable[[], float]) -> None:
    """Wait for the heartbeat of each node whose 0x1017 says it has one (bounded)."""
    periods = {n: p for n, found in objects.items()
               if (p := _unsigned(found.values.get((c301.PRODUCER_HEARTBEAT_TIME, 0))))}
    if not periods:
        return
    until = start + min(1.5 * max(periods.values()) / 1000.0, HEARTBEAT_WAIT)
    with heard.changed:
        heard.changed.wait_for(lambda: all(n in heard.heard for n in periods),
                               timeout=max(0.0, until - clock()))


def _found(node_id: int, objects: _Objects, heard: _Heard | None) -> FoundNode:
    values = objects.values
    identity = Identity(**{name: _unsigned(values.get((c301.IDENTITY, sub)))
                           for name, sub in SUBINDEX.items()})
    name, version = values.get((DEVICE_NAME, 0)), values.get((SOFTWARE_VERSION, 0))
    if values.get((c301.DEVICE_TYPE, 0)) is None and objects.problem is None:
        problem: str | None = "0x1000 (device type, mandatory) refused"
    else:
        problem = objects.problem
    if problem and heard is not None and heard.state == "STOPPED":
        problem += ": the node is STOPPED, where CiA 301 allows no SDO"
    return FoundNode(
        node_id=node_id, identity=identity,
        device_type=_unsigned(values.get((c301.DEVICE_TYPE, 0))),
        device_name=visible_string(name) if name is not None else None,
        software_version=visible_string(version) if version is not None else None,
        heartbeat_ms=_unsigned(values.get((c301.PRODUCER_HEARTBEAT_TIME, 0))),
        nmt_state=heard.state if heard else "unknown",
        seen_by=heard.first if heard else "sdo", problem=problem)


def device_type_text(device_type: int | None) -> str:
    """0x1000 as "CiA 402" (its low word: the device profile) with the raw value."""
    if device_type is None:
        return "-"
    profile = device_type & 0xFFFF
    return f"CiA {profile} (0x{device_type:08X})" if profile else f"0x{device_type:08X}"
