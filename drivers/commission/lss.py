"""LSS (CiA 305, layer setting services), the master's side: find nodes that have no node
id yet and give one a node id and a bit rate. The requests are canopen's LssMaster's; the
answers are judged here before they are read (``LssMaster``).

A node is addressed by its LSS address, the four values of its identity object (0x1018:
vendor-ID, product code, revision number, serial number), so a node without a node id
(0xFF: unconfigured) can still be told apart from the others. LSS uses two COB-IDs of its
own (0x7E5 master to slaves, 0x7E4 back) and works in any NMT state.

Fastscan finds one unconfigured node in about 130 request/answer turns, each of which
waits for an answer that only comes when the bits asked about match: a missing answer
costs the whole ``timeout``, so the timeout decides how long a fastscan takes (about 64
timeouts per node found, and one for a bus without unconfigured nodes).
"""
from __future__ import annotations

import queue
import struct
import time
from collections.abc import Callable

import canopen
from canopen import lss

from ...errors import LssFailed
from ..files.identity import Identity

#: master -> slaves, slaves -> master
LSS_REQUEST = lss.LssMaster.LSS_TX_COBID
LSS_RESPONSE = lss.LssMaster.LSS_RX_COBID
#: switch state global's modes
WAITING, CONFIGURATION = lss.LssMaster.WAITING_STATE, lss.LssMaster.CONFIGURATION_STATE
#: the node id of a node that has none (CiA 305)
UNCONFIGURED = 0xFF
#: CiA 305 bit timing table 0: table index -> bit/s (index 5 is reserved, 9 is automatic)
BIT_TIMING = {0: 1_000_000, 1: 800_000, 2: 500_000, 3: 250_000, 4: 125_000,
              6: 50_000, 7: 20_000, 8: 10_000}
#: how long a fastscan waits for an answer (a slave answers within milliseconds)
TIMEOUT = 0.05
#: most unconfigured nodes one listing looks for (a bound on its time)
MAX_NODES = 32


def bit_timing_index(bitrate: int) -> int:
    """The CiA 305 table index of ``bitrate`` (bit/s); ValueError for one not in it."""
    for index, rate in BIT_TIMING.items():
        if rate == bitrate:
            return index
    raise ValueError(f"bit rate {bitrate} is not in the CiA 305 table "
                     f"({', '.join(str(r) for r in BIT_TIMING.values())})")


class LssMaster:
    """The master's side of the LSS services used here, on a canopen Network (lent): each
    request is sent on 0x7E5 and its answer, where it has one, taken from 0x7E4 within
    ``timeout`` s, and judged before it is read. CiA 305 answers are 8 bytes with the
    command specifier of the request: any other frame there (empty, cut short, another
    service's, garbage) is LssFailed naming the step and the frame, never a struct.error of
    a parser that trusted it (canopen's LssMaster did, at every step). Requests are those
    of canopen's LssMaster, with its pauses (devices need them)."""

    def __init__(self, network: canopen.Network, timeout: float = TIMEOUT) -> None:
        self._network, self.timeout = network, timeout
        self._answers: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        network.subscribe(LSS_RESPONSE, self._on_answer)

    def close(self) -> None:
        self._network.unsubscribe(LSS_RESPONSE, self._on_answer)

    def __enter__(self) -> LssMaster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _on_answer(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._answers.put(bytes(data))

    def _send(self, command: int, body: bytes = b"") -> None:
        while not self._answers.empty():  # a late answer to an earlier request: not this one's
            self._answers.get_nowait()
        self._network.send_message(LSS_REQUEST, bytes((command,)) + body.ljust(7, b"\0"))

    def _ask(self, what: str, command: int, body: bytes = b"",
             answer: int | None = None) -> bytes | None:
        """Send; the answer (8 bytes, its command specifier ``answer``, default the
        request's) or None when none came in time. LssFailed for any other frame."""
        self._send(command, body)
        try:
            data = self._answers.get(timeout=self.timeout)
        except queue.Empty:
            return None
        expected = command if answer is None else answer
        if len(data) != 8 or data[0] != expected:
            raise LssFailed(f"LSS {what}: a malformed answer on 0x{LSS_RESPONSE:03X}: "
                            f"{_frame(data)}; CiA 305 answers with 8 bytes beginning "
                            f"0x{expected:02X}: is another device answering LSS?")
        return data

    # --- the services --------------------------------------------------------------------------
    def switch_state_global(self, mode: int) -> None:
        self._send(lss.CS_SWITCH_STATE_GLOBAL, bytes((mode,)))

    def switch_state_selective(self, vendor: int, product: int, revision: int,
                               serial: int) -> bool:
        """The node at this address into configuration state; whether it answered."""
        for command, part in ((lss.CS_SWITCH_STATE_SELECTIVE_VENDOR_ID, vendor),
                              (lss.CS_SWITCH_STATE_SELECTIVE_PRODUCT_CODE, product),
                              (lss.CS_SWITCH_STATE_SELECTIVE_REVISION_NUMBER, revision)):
            self._send(command, struct.pack("<I", part))
            time.sleep(SELECTIVE_PAUSE)
        return self._ask("switch state selective", lss.CS_SWITCH_STATE_SELECTIVE_SERIAL_NUMBER,
                         struct.pack("<I", serial),
                         lss.CS_SWITCH_STATE_SELECTIVE_RESPONSE) is not None

    def fast_scan(self) -> Identity | None:
        """The address of the unconfigured node with the lowest one, which is left in
        configuration state (CiA 305 fastscan, canopen's LssMaster.fast_scan's steps), or
        None when no node answered."""
        def matches(part: int, bit: int, sub: int, nxt: int) -> bool:
            found = self._ask("fastscan", lss.CS_FAST_SCAN,
                              struct.pack("<IBBB", part, bit, sub, nxt),
                              lss.CS_IDENTIFY_SLAVE) is not None
            time.sleep(FASTSCAN_PAUSE)
            return found
        address = [0, 0, 0, 0]
        if not matches(0, FASTSCAN_ANY, 0, 0):
            return None
        for sub in range(4):
            for bit in range(31, -1, -1):
                if not matches(address[sub], bit, sub, sub):
                    address[sub] |= 1 << bit
            if not matches(address[sub], 0, sub, (sub + 1) & 3):
                return None
        return Identity(*address)

    def inquire_node_id(self) -> int | None:
        """The node id of the node in configuration state (UNCONFIGURED: none)."""
        data = self._ask("inquire node id", lss.CS_INQUIRE_NODE_ID)
        return None if data is None else data[1]

    def configure(self, what: str, command: int, body: bytes, errors: dict[int, str]) -> None:
        """A configure service: LssFailed when no answer came or the node refused it."""
        data = self._ask(what, command, body)
        if data is None:
            raise LssFailed(f"LSS {what}: no answer within {self.timeout:g} s")
        if data[1] != lss.ERROR_NONE:
            why = errors.get(data[1], f"error {data[1]}" + (
                f", the device's own {data[2]}" if data[1] == lss.ERROR_VENDOR_SPECIFIC
                else ""))
            raise LssFailed(f"LSS {what}: refused by the node ({why})")


#: pause after each of the first three parts of switch state selective, and after each
#: fastscan request (canopen's LssMaster's: "some device needs these delays")
SELECTIVE_PAUSE = 0.2
FASTSCAN_PAUSE = 0.01
#: fastscan's "bit checked" that asks whether any unconfigured node is there
FASTSCAN_ANY = 0x80
#: what a refusal's error code means (CiA 305), per service
_NODE_ID_ERRORS = {lss.ERROR_INADMISSIBLE: "node id out of range"}
_BIT_TIMING_ERRORS = {lss.ERROR_INADMISSIBLE: "bit timing not supported"}
_STORE_ERRORS = {lss.ERROR_STORE_NOT_SUPPORTED: "storing not supported",
                 lss.ERROR_STORE_ACCESS_PROBLEM: "storage media access error"}


def _frame(data: bytes) -> str:
    """A frame as an error names it: its length and bytes."""
    return f"{len(data)} byte{'' if len(data) == 1 else 's'}" + (
        f" ({data.hex(' ').upper()})" if data else "")


def find_unconfigured(network: canopen.Network, timeout: float = TIMEOUT,
                      limit: int = MAX_NODES) -> list[Identity]:
    """The identity of every node without a node id, by fastscan; each one found stays
    in LSS configuration state (it takes no part in the next fastscan) until all are
    switched back to waiting, which changes nothing on a node that got no new id.
    LssFailed: a malformed answer (it names it)."""
    found: list[Identity] = []
    with LssMaster(network, timeout) as master:
        master.switch_state_global(WAITING)
        try:
            while len(found) < limit:
                address = master.fast_scan()
                if address is None:
                    break
                found.append(address)
        finally:
            master.switch_state_global(WAITING)
    return found


def assign(network: canopen.Network, node_id: int, address: Identity | None = None, *,
           bitrate: int | None = None, store: bool = False, timeout: float = TIMEOUT,
           occupant: Callable[[int], str | None] | None = None) -> Identity:
    """Give one node ``node_id`` (and the bit rate ``bitrate``), then switch every node
    back to waiting: a node that had no node id starts with the new one at once, a node
    that had one at its next NMT reset. ``address``: that node's LSS address (all four
    fields); None: the first unconfigured node fastscan finds. ``store``: kept across a
    power cycle (CiA 305 store configuration). ``occupant(node_id)``: how a node already
    at that node id shows itself, or None (drivers/commission/scan.py ``present``); asked before any
    LSS request, and a node id taken by another node is refused, nothing assigned (the
    addressed node itself may hold it already). Returns the node's address.

    Raises LssFailed when the node id is taken, no node answers, the node refuses a value
    or an answer is malformed (the message says which)."""
    if not 1 <= node_id <= 127:
        raise ValueError(f"node id must be 1..127, got {node_id}")
    index = bit_timing_index(bitrate) if bitrate is not None else None
    there = occupant(node_id) if occupant is not None else None
    if there is not None and address is None:
        raise LssFailed(_taken(node_id, there))
    with LssMaster(network, timeout) as master:
        master.switch_state_global(WAITING)
        try:
            target = _select(master, address)
            if there is not None and master.inquire_node_id() != node_id:
                raise LssFailed(_taken(node_id, there))
            steps: list[tuple[str, int, bytes, dict[int, str]]] = [
                (f"configure node id {node_id}", lss.CS_CONFIGURE_NODE_ID,
                 bytes((node_id,)), _NODE_ID_ERRORS)]
            if index is not None:
                steps.append((f"configure bit timing {bitrate}", lss.CS_CONFIGURE_BIT_TIMING,
                              bytes((0, index)), _BIT_TIMING_ERRORS))
            if store:
                steps.append(("store configuration", lss.CS_STORE_CONFIGURATION, b"",
                              _STORE_ERRORS))
            for what, command, body, errors in steps:
                try:
                    master.configure(what, command, body, errors)
                except LssFailed as exc:
                    raise LssFailed(f"{exc} (for {target.describe()})") from None
        finally:
            master.switch_state_global(WAITING)
    return target


def _taken(node_id: int, there: str) -> str:
    return (f"LSS: node id {node_id} is taken: node {node_id} is already on the bus "
            f"({there}); nothing was assigned (give another id, or move that node first)")


def _select(master: LssMaster, address: Identity | None) -> Identity:
    """Put exactly the one node into LSS configuration state."""
    if address is None:
        found = master.fast_scan()
        if found is None:
            raise LssFailed("LSS fastscan: no unconfigured node answered")
        return found
    parts = (address.vendor_id, address.product_code, address.revision, address.serial)
    if any(p is None for p in parts):
        raise ValueError(f"an LSS address needs all four identity fields, got "
                         f"{address.describe()}")
    vendor, product, revision, serial = (int(p or 0) for p in parts)
    if master.switch_state_selective(vendor, product, revision, serial):
        return address
    raise LssFailed(f"LSS switch state selective: no node answered at {address.describe()}")
