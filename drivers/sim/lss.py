"""The simulated nodes' LSS slaves (CiA 305, layer setting services).

Every simulated node has one, addressed by its identity (0x1018:1..4, the LSS address):
a node with a node id answers LSS as a real drive does, and a node without one
(``UNCONFIGURED``, 0xFF) answers nothing but LSS (no boot-up, heartbeat, SDO or PDO)
until it is given a node id. The services, requests on 0x7E5 and answers on 0x7E4:

- switch state global (waiting / configuration) and switch state selective (the four
  parts of the address in turn; answered by the node that matches);
- in configuration state: configure node id (1..127, or 0xFF), configure bit timing
  (CiA 305 table 0), store configuration, inquire the identity's four parts and the
  active node id (activate bit timing is taken and ignored: a simulated bus has no
  bit rate);
- identify remote slave (a range of revisions and serial numbers) and identify
  non-configured remote slave;
- fastscan: an unconfigured node in waiting state answers each 32-bit part of its address
  bit by bit, then goes to configuration state.

Node ids as CiA 305 keeps them: ``pending_id`` is what configure node id sets,
``stored_id`` what store configuration keeps (what a reset node or power-on starts
with), ``active_id`` the one the node uses. A node without a node id takes the pending
one when switched back to waiting; a node with one at its next NMT reset (reset node:
the stored id, reset communication: the pending one). Each change of the active id is
handed to ``move``, which puts the node on the bus at its new id (segment.py).
"""
from __future__ import annotations

import enum
import logging
import struct
from collections.abc import Callable, Sequence

from canopen import lss as cs

from ..commission.lss import BIT_TIMING, LSS_RESPONSE, UNCONFIGURED
from ..files.identity import Identity
from ..protocol.cia301 import NmtCommand

log = logging.getLogger(__name__)

_SELECTIVE = (cs.CS_SWITCH_STATE_SELECTIVE_VENDOR_ID, cs.CS_SWITCH_STATE_SELECTIVE_PRODUCT_CODE,
              cs.CS_SWITCH_STATE_SELECTIVE_REVISION_NUMBER,
              cs.CS_SWITCH_STATE_SELECTIVE_SERIAL_NUMBER)
_INQUIRE = (cs.CS_INQUIRE_VENDOR_ID, cs.CS_INQUIRE_PRODUCT_CODE,
            cs.CS_INQUIRE_REVISION_NUMBER, cs.CS_INQUIRE_SERIAL_NUMBER)
_IDENTIFY = tuple(range(cs.CS_IDENTIFY_REMOTE_SLAVE_VENDOR_ID,
                        cs.CS_IDENTIFY_REMOTE_SLAVE_SERIAL_NUMBER_HIGH + 1))
#: fastscan's "bit checked" that asks whether any unconfigured node is there
_FASTSCAN_ANY = 0x80


class IdentityError(ValueError):
    """The simulated nodes' identities cannot be LSS addresses (one incomplete, two alike):
    the arguments that gave them are wrong."""


class LssState(enum.IntEnum):
    WAITING = 0
    CONFIGURATION = 1


class LssSlave:
    """One node's LSS slave. ``joint`` and ``axes``: where the node's joints are in the
    segment's dynamics (they stay the node's whatever its node id)."""

    def __init__(self, identity: Identity, node_id: int, joint: int, axes: int,
                 send: Callable[[int, bytes], None],
                 move: Callable[[LssSlave, int], None]) -> None:
        address = (identity.vendor_id, identity.product_code, identity.revision,
                   identity.serial)
        if any(part is None for part in address):
            raise IdentityError(f"an LSS slave needs all four identity fields, got "
                             f"{identity.describe()}")
        self.identity = identity
        self.address: tuple[int, int, int, int] = address  # type: ignore[assignment]
        self.joint = joint
        self.axes = axes
        self.active_id = self.pending_id = self.stored_id = node_id
        self.pending_bit_timing: int | None = None
        self.stored_bit_timing: int | None = None
        self.state = LssState.WAITING
        self._send = send
        self._move = move
        self._selective = 0  # parts of the address matched so far (switch state selective)
        self._identify = 0   # steps of identify remote slave passed so far
        self._fastscan: int | None = None  # the address part fastscan compares; None: out

    @property
    def configured(self) -> bool:
        return self.active_id != UNCONFIGURED

    def _answer(self, command: int, *values: int, fmt: str = "") -> None:
        data = struct.pack("<B" + fmt, command, *values)
        self._send(LSS_RESPONSE, data.ljust(8, b"\x00"))

    def _activate(self, node_id: int) -> None:
        if node_id != self.active_id:
            old, self.active_id = self.active_id, node_id
            self._move(self, old)

    # ------------------------------------------------------------------ requests
    def on_request(self, data: bytes) -> None:
        if len(data) < 8:
            return
        command = data[0]
        value = struct.unpack_from("<I", data, 1)[0]
        if command == cs.CS_SWITCH_STATE_GLOBAL:
            self._switch(LssState.CONFIGURATION if data[1] else LssState.WAITING)
        elif command in _SELECTIVE:
            self._switch_selective(_SELECTIVE.index(command), value)
        elif command in _IDENTIFY:
            self._identify_remote(command - _IDENTIFY[0], value)
        elif command == cs.CS_IDENTIFY_NON_CONFIGURED_REMOTE_SLAVE:
            if not self.configured:
                self._answer(cs.CS_IDENTIFY_NON_CONFIGURED_SLAVE)
        elif command == cs.CS_FAST_SCAN:
            self._fast_scan(*struct.unpack_from("<IBBB", data, 1))
        elif self.state == LssState.CONFIGURATION:
            self._configure(command, data)

    def _switch(self, state: LssState) -> None:
        self._selective = 0
        self._fastscan = None
        was, self.state = self.state, state
        if (was == LssState.CONFIGURATION and state == LssState.WAITING
                and not self.configured and self.pending_id != UNCONFIGURED):
            self._activate(self.pending_id)  # CiA 305: it starts at once with the new id

    def _switch_selective(self, part: int, value: int) -> None:
        if self.state != LssState.WAITING:
            return
        if part != self._selective or value != self.address[part]:
            self._selective = 0
            return
        self._selective += 1
        if self._selective == len(self.address):
            self._selective = 0
            self.state = LssState.CONFIGURATION
            self._answer(cs.CS_SWITCH_STATE_SELECTIVE_RESPONSE)

    def _identify_remote(self, step: int, value: int) -> None:
        """Vendor and product must match; revision and serial lie in low..high."""
        if step != self._identify:
            self._identify = 0
            return
        vendor, product, revision, serial = self.address
        fits = (vendor == value, product == value, revision >= value, revision <= value,
                serial >= value, serial <= value)[step]
        self._identify = step + 1 if fits else 0
        if self._identify == len(_IDENTIFY):
            self._identify = 0
            self._answer(cs.CS_IDENTIFY_SLAVE)

    def _fast_scan(self, id_number: int, bit_checked: int, sub: int, nxt: int) -> None:
        if self.configured or self.state != LssState.WAITING:
            return
        if bit_checked == _FASTSCAN_ANY:
            self._fastscan = 0
            self._answer(cs.CS_IDENTIFY_SLAVE)
            return
        if self._fastscan != sub or bit_checked > 31 or sub > 3:
            return
        mask = (0xFFFF_FFFF << bit_checked) & 0xFFFF_FFFF
        if (self.address[sub] ^ id_number) & mask:
            return
        if bit_checked == 0:  # this part matches whole: on to LSSNext; after the last,
            self._fastscan = nxt  # back to the first: selected
            if nxt < sub:
                self._fastscan = None
                self.state = LssState.CONFIGURATION
        self._answer(cs.CS_IDENTIFY_SLAVE)

    def _configure(self, command: int, data: bytes) -> None:
        if command == cs.CS_CONFIGURE_NODE_ID:
            valid = 1 <= data[1] <= 127 or data[1] == UNCONFIGURED
            if valid:
                self.pending_id = data[1]
            self._answer(command, 0 if valid else cs.ERROR_INADMISSIBLE, fmt="B")
        elif command == cs.CS_CONFIGURE_BIT_TIMING:
            valid = data[1] == 0 and data[2] in BIT_TIMING
            if valid:
                self.pending_bit_timing = data[2]
            self._answer(command, 0 if valid else cs.ERROR_INADMISSIBLE, fmt="B")
        elif command == cs.CS_STORE_CONFIGURATION:
            self.stored_id = self.pending_id
            if self.pending_bit_timing is not None:
                self.stored_bit_timing = self.pending_bit_timing
            self._answer(command, cs.ERROR_STORE_NONE, fmt="B")
        elif command in _INQUIRE:
            self._answer(command, self.address[_INQUIRE.index(command)], fmt="I")
        elif command == cs.CS_INQUIRE_NODE_ID:
            self._answer(command, self.active_id, fmt="B")

    # ------------------------------------------------------------------ NMT
    def on_reset(self, command: int) -> bool:
        """An NMT reset of the node: True when it moved to another node id (``move`` has
        put it there, booted), False when the node handles the reset itself."""
        if command == NmtCommand.RESET_NODE:
            self.pending_id = self.stored_id
        elif command != NmtCommand.RESET_COMMUNICATION:
            return False
        if self.pending_id == self.active_id:
            return False
        self._activate(self.pending_id)
        return True


def check_addresses(slaves: Sequence[LssSlave]) -> None:
    """IdentityError for two nodes of one identity: LSS needs one of a kind."""
    owners: dict[tuple[int, int, int, int], str] = {}
    for slave in slaves:
        who = f"node {slave.active_id}" if slave.configured else "a node without a node id"
        if slave.address in owners:
            raise IdentityError(
                f"{owners[slave.address]} and {who} have the same identity "
                f"({slave.identity.describe()}), which LSS needs one of a kind: give each "
                "its own serial number")
        owners[slave.address] = who
