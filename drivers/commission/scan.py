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
   A number that comes in another length than its type's (a device type of 7 bytes, from
   a segmented upload that said 0xFFFFFFFF) is malformed, said so, never taken for an
   object the node lacks (``FoundNode.malformed``). Each request is let through to the
   client with its first answer only: a second answer to one request is a second device
   at that node id (two drives given one id), which the scan says
   (``FoundNode.several_devices``) instead of reading a mix of the two answers as one.
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

from ..files.identity import SUBINDEX, Identity
from ..link.bus import CanopenBus
from ..protocol import cia301 as c301
from ..protocol.cia301 import NmtState

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
#: upload initiate (request ccs 2, answer scs 2) and upload segment request (ccs 3); a
#: segment's answer is scs 0; the toggle bit of segments
_UPLOAD_INITIATE = 0x40
_UPLOAD_SEGMENT = 0x60
_TOGGLE = 0x10
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
    #: more than one device answered its requests (the values shown may mix them)
    several_devices: bool = False
    #: the objects that came malformed (e.g. "0x1000:0": not the length of its type)
    malformed: tuple[str, ...] = ()

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
    ``HEARTBEAT_WAIT`` and one ``timeout`` for a second device's late answers."""
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
        readers_of: list[_FirstAnswerSdo] = []  # (kept listening to the scan's end)
        try:
            with ThreadPoolExecutor(max_workers=readers, thread_name_prefix="scan") as pool:
                objects = dict(zip(present, pool.map(
                    lambda n: _read_objects(network, n, timeout, readers_of), present)))
            _await_heartbeats(heard, objects, start, clock)
            # A second device at a node id may answer later than the first, past the node's
            # last read (its thread or its CAN controller slower): its answers still count
            # until one SDO timeout after the reads.
            time.sleep(timeout)
        finally:
            for sdo in readers_of:
                network.unsubscribe(sdo.tx_cobid, sdo.on_response)
        with heard.changed:
            return [_found(n, objects[n], heard.heard.get(n)) for n in present]
    finally:
        canopen_bus.close()


def present(network: canopen.Network, node_id: int, *, listen: float = LISTEN,
            timeout: float = TIMEOUT) -> str | None:
    """How node ``node_id`` shows it is on the bus, as a scan would find it, or None: its
    heartbeat or boot-up within ``listen`` s, else an answer (an abort too) to an SDO
    upload of 0x1000 within ``timeout``. Sends that upload and nothing else. A STOPPED node
    answers no SDO (CiA 301): it is found only by a heartbeat heard in ``listen``."""
    heard = _Listener()
    cob_id = c301.HEARTBEAT + node_id
    network.subscribe(cob_id, heard.on_heartbeat)
    try:
        with heard.changed:
            heard.changed.wait_for(lambda: node_id in heard.heard, listen)
            seen = heard.heard.get(node_id)
        if seen is None:
            _probe(network, [node_id], heard, timeout, 1)
            with heard.changed:
                seen = heard.heard.get(node_id)
                answered = node_id in heard.answered
        else:
            answered = False
    finally:
        network.unsubscribe(cob_id, heard.on_heartbeat)
    if seen is not None:
        return f"its {seen.first} on 0x{cob_id:03X}, {seen.state}"
    if answered:
        return (f"it answered an SDO upload of 0x{c301.DEVICE_TYPE:04X} on "
                f"0x{c301.SDO_TX + node_id:03X}")
    return None


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
    malformed: dict[tuple[int, int], str] = field(default_factory=dict)  # -> what came
    doubled: int = 0      # requests answered more than once
    requests: int = 0     # requests sent
    #: per object, each different answer its requests had (two devices: what they differ in)
    answers: dict[tuple[int, int], list[bytes]] = field(default_factory=dict)


#: What a scan reads of every node, in order (0x1018:1 is mandatory, the rest optional).
_READS = ((c301.DEVICE_TYPE, 0), *((c301.IDENTITY, s) for s in SUBINDEX.values()),
          (DEVICE_NAME, 0), (SOFTWARE_VERSION, 0), (c301.PRODUCER_HEARTBEAT_TIME, 0))
#: The numbers among _READS: (index, subindex) -> (bytes of its type, its name); an
#: expedited answer without a size carries 4 bytes, which a shorter type accepts
_NUMBERS = {(c301.DEVICE_TYPE, 0): (4, "device type"),
            **{(c301.IDENTITY, s): (4, name.replace("_", " ")) for name, s in SUBINDEX.items()},
            (c301.PRODUCER_HEARTBEAT_TIME, 0): (2, "producer heartbeat time")}
_TYPE_NAMES = {4: "UNSIGNED32", 2: "UNSIGNED16"}


class _FirstAnswerSdo(SdoClient):
    """An SDO client that takes the first answer to each request it sends and counts the
    others: a second answer to one request is a second device at the node id (its answer,
    taken as the next request's, made the reads fail with "Toggle bit mismatch", or read
    one device's vendor with the other's serial). Answers are told apart by what they
    answer: an initiate answer by its index and subindex (each object is read once), a
    segment answer by its toggle bit."""

    def __init__(self, node_id: int, found: _Objects) -> None:
        super().__init__(  # type: ignore[no-untyped-call]  # canopen's own is untyped
            c301.SDO_RX + node_id, c301.SDO_TX + node_id, ObjectDictionary())
        self._found = found
        self._lock = threading.Lock()
        self._request = self._previous = b""
        self._answered = True
        self._objects: dict[bytes, tuple[int, int]] = {}  # initiate answer key -> object
        self._object: tuple[int, int] = (0, 0)

    def send_request(self, request: bytes | bytearray) -> None:
        with self._lock:
            self._previous, self._request = self._request, bytes(request)
            self._answered = False
            if request[0] & 0xE0 == _UPLOAD_INITIATE:
                self._object = struct.unpack_from("<HB", request, 1)
                self._objects[bytes(request[1:4])] = self._object
            self._found.requests += 1
        super().send_request(request)  # type: ignore[no-untyped-call]

    def on_response(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            earlier = self._answers_earlier(data)
            if self._answered or earlier:
                if earlier or self._answers(data, self._request):
                    self._found.doubled += 1
                    self._note(bytes(data))
                return  # the client sees one answer per request
            self._answered = True
            if self._answers(data, self._request):
                self._note(bytes(data))
        super().on_response(can_id, data, timestamp)  # type: ignore[no-untyped-call]

    @staticmethod
    def _answers(data: bytearray, request: bytes) -> bool:
        """Whether ``data`` answers ``request`` (an abort of it too)."""
        if len(data) < 4 or not request:
            return False
        if data[0] == _ABORT:
            return request[0] & 0xE0 != _UPLOAD_INITIATE or data[1:4] == request[1:4]
        if request[0] & 0xE0 == _UPLOAD_INITIATE:
            return data[0] & 0xE0 == _UPLOAD_INITIATE and data[1:4] == request[1:4]
        if request[0] & 0xE0 == _UPLOAD_SEGMENT:
            return data[0] & 0xE0 == 0 and data[0] & _TOGGLE == request[0] & _TOGGLE
        return False

    def _answers_earlier(self, data: bytearray) -> bool:
        """Whether ``data`` answers an earlier request and not the one outstanding: a
        second device's answer, later than the first one's (an initiate's by its object,
        the previous segment's by its toggle bit)."""
        if len(data) < 4 or self._answers(data, self._request):
            return False
        key = bytes(data[1:4])
        return (data[0] & 0xE0 in (_UPLOAD_INITIATE, _ABORT) and key in self._objects) \
            or (self._previous[:1] != b"" and self._previous[0] & 0xE0 == _UPLOAD_SEGMENT
                and self._answers(data, self._previous))

    def _note(self, data: bytes) -> None:
        """Keep each different answer to an expedited initiate (the value it carries)."""
        if data[0] & 0xE0 != _UPLOAD_INITIATE or not data[0] & 0x02:
            return
        seen = self._found.answers.setdefault(self._objects.get(data[1:4], self._object), [])
        value = data[4:8 - ((data[0] >> 2) & 0x3 if data[0] & 0x01 else 0)]
        if value not in seen:
            seen.append(value)


def _read_objects(network: canopen.Network, node_id: int, timeout: float,
                  listening: list[_FirstAnswerSdo]) -> _Objects:
    """Upload each of _READS; an abort is an object the node lacks, no answer ends it. The
    node's SDO client is left listening (appended to ``listening``, which the caller
    unsubscribes): answers after the reads are a second device's."""
    found = _Objects()
    sdo = _FirstAnswerSdo(node_id, found)
    sdo.network = network
    sdo.RESPONSE_TIMEOUT = timeout
    sdo.MAX_RETRIES = 1  # one attempt (canopen: 0 retries for ever)
    network.subscribe(sdo.tx_cobid, sdo.on_response)
    listening.append(sdo)
    cut: list[str] = []
    for index, subindex in _READS:
        try:
            data, complete, stated = _upload(sdo, index, subindex)
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
        why = _malformed(index, subindex, data, stated) if complete else None
        if why is not None:
            found.malformed[(index, subindex)] = why
            found.values[(index, subindex)] = None
            continue
        found.values[(index, subindex)] = data
        if not complete:
            cut.append(f"0x{index:04X}:{subindex} longer than {MAX_OBJECT_BYTES} bytes: "
                       "cut off")
    if cut:
        found.problem = "; ".join(cut + ([found.problem] if found.problem else []))
    return found


def _malformed(index: int, subindex: int, data: bytes, stated: int | None) -> str | None:
    """Why ``data`` (``stated``: the size its transfer announced) cannot be the number
    this object is, or None."""
    if (index, subindex) not in _NUMBERS:
        return None
    size, _ = _NUMBERS[(index, subindex)]
    if len(data) == size or (len(data) == 4 and stated is None):
        return None
    said = f"; the transfer said {stated} bytes" if stated is not None else ""
    return (f"{len(data)} bytes, where an {_TYPE_NAMES[size]} has {size}"
            + (said if stated != len(data) else ""))


def _upload(sdo: SdoClient, index: int, subindex: int) -> tuple[bytes, bool, int | None]:
    """An SDO upload of at most MAX_OBJECT_BYTES: the data, whether that was all of it,
    and the size the node announced (None: none). Past the bound the transfer is aborted
    (a node that sends segments for ever would hold the scan for ever: each segment is one
    request and one answer)."""
    stream = ReadableStream(sdo, index, subindex)
    data = bytearray()
    while len(data) <= MAX_OBJECT_BYTES:
        chunk = stream.read(7)
        if not chunk:  # the last segment has come (canopen's own end of an upload)
            return bytes(data), True, stream.size
        data += chunk
    if not stream._done:  # canopen keeps no other record of the last segment
        # the abort sent here, not by SdoClient.abort, which logs an ERROR line for it
        sdo.network.send_message(sdo.rx_cobid, struct.pack(
            "<BHBI", _ABORT, index, subindex, _ABORT_OUT_OF_MEMORY))
    return bytes(data[:MAX_OBJECT_BYTES]), False, stream.size


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
    device_type = (c301.DEVICE_TYPE, 0)
    if values.get(device_type) is None and objects.problem is None \
            and device_type not in objects.malformed:
        problem: str | None = "0x1000 (device type, mandatory) refused"
    else:
        problem = objects.problem
    malformed = [f"0x{i:04X}:{s} ({_NUMBERS[(i, s)][1]}): a malformed answer: {why}"
                 for (i, s), why in objects.malformed.items()]
    if malformed:
        problem = "; ".join(malformed + ([problem] if problem else []))
    if problem and heard is not None and heard.state == "STOPPED":
        problem += ": the node is STOPPED, where CiA 301 allows no SDO"
    several = objects.doubled > 0
    if several:
        problem = _several(node_id, objects) + (f"; {problem}" if problem else "")
    return FoundNode(
        node_id=node_id, identity=identity,
        device_type=_unsigned(values.get((c301.DEVICE_TYPE, 0))),
        device_name=visible_string(name) if name is not None else None,
        software_version=visible_string(version) if version is not None else None,
        heartbeat_ms=_unsigned(values.get((c301.PRODUCER_HEARTBEAT_TIME, 0))),
        nmt_state=heard.state if heard else "unknown",
        seen_by=heard.first if heard else "sdo", problem=problem, several_devices=several,
        malformed=tuple(f"0x{i:04X}:{s}" for i, s in objects.malformed))


def _several(node_id: int, objects: _Objects) -> str:
    """The problem of a node id more than one device answers at: how often, and the values
    they gave that differ (their identities tell them apart)."""
    differ = [f"{_NUMBERS[key][1]} " + ", ".join(
                  f"0x{n:08X}" for n in sorted(int.from_bytes(v, "little") for v in values))
              for key, values in objects.answers.items() if len(values) > 1 and key in _NUMBERS]
    return (f"two or more devices answer at node id {node_id} ({objects.doubled} of "
            f"{objects.requests} requests answered twice"
            + (f"; {'; '.join(differ)}" if differ else "") + "): give each its own node id "
            "(rocoma-can lss); what this row shows may mix their answers")


def device_type_text(device_type: int | None) -> str:
    """0x1000 as "CiA 402" (its low word: the device profile) with the raw value."""
    if device_type is None:
        return "-"
    profile = device_type & 0xFFFF
    return f"CiA {profile} (0x{device_type:08X})" if profile else f"0x{device_type:08X}"
