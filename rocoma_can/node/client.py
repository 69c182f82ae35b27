"""What the CLI verbs (and any Python program) use to talk to a running manager node over
SDO: one canopen SdoClient, one call at a time (canopen's SdoClient has no lock)."""
from __future__ import annotations

import json
import time
from typing import Any

import can
import canopen
from canopen.objectdictionary import DOMAIN, VISIBLE_STRING
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from .. import eds as shipped_eds
from ..drivers.link.bus import BusReader
from ..errors import NoAnswer, Refused, RocomaError
from . import sdo_block, sdo_write
from .objects import (
    ABORT_NO_OBJECT,
    ABORT_TEXT,
    ACTIVE_NAME,
    CONTROLLER_LIST,
    DRIVE_STATUS,
    ESTOP_CAUSE,
    ESTOP_COB_ID,
    ESTOP_LATCHED,
    HOME_DRIVE,
    HOMING_REFUSAL,
    PENDING,
    PROTOCOL_ABORTS,
    RESULT_NAMES,
    STATE,
    STATE_NAMES,
    SWITCH_INDEX,
    SWITCH_NAME,
    SWITCH_REFUSAL,
    SWITCH_RESULT,
)

__all__ = ["ManagerClient", "NoAnswer", "Refused"]

#: What an object of the manager node holds: integers and visible strings (its EDS).
SdoValue = int | float | str | bytes
#: Tries of a read that got no answer. A read is the same request again, and one lost frame
#: (a segment of the ~100-frame status upload, on a busy bus or a stalled host) must not
#: fail an operator's `status`; writes are tried once (a switch sent twice is two switches),
#: except the stops (cli/operator_verbs.STOP_ATTEMPTS). A node that is not there costs this many
#: timeouts.
READ_ATTEMPTS = 3


class ManagerClient:
    """Talks to a running manager node over SDO (one thread at a time: SdoClient has no lock)."""

    def __init__(self, bus: can.BusABC, node_id: int = 100, timeout: float = 0.5) -> None:
        self.bus = bus
        self.network = canopen.Network(bus)
        self.reader = BusReader(bus, self.network.listeners, name="manager-client-rx")
        od = canopen.import_od(str(shipped_eds.path(shipped_eds.MANAGER_NODE)), node_id)
        self.node = self.network.add_node(canopen.RemoteNode(node_id, od))
        self.node.sdo.RESPONSE_TIMEOUT = timeout
        self.node.sdo.MAX_RETRIES = 1  # one attempt (0 would retry for ever in canopen 2.4)
        self._blocks = True  # until the node answers a block upload with a normal one

    def close(self) -> None:
        self.reader.stop()

    def __enter__(self) -> ManagerClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def read(self, index: int) -> SdoValue:
        """The object's value; a transfer left unanswered or broken (a protocol abort) is
        started again (READ_ATTEMPTS: the broken one is aborted first, so the node starts
        afresh too). Text objects come in a block upload (sdo_block), when the node has it."""
        unanswered: Exception | None = None
        variable = self.node.sdo[index]
        for _ in range(READ_ATTEMPTS):
            try:
                if self._blocks and variable.od.data_type in (VISIBLE_STRING, DOMAIN):
                    data = sdo_block.upload(self.node.sdo, index)
                    if data is not None:
                        text: SdoValue = variable.od.decode_raw(data)
                        return text
                    self._blocks = False  # a node without block upload: segmented from now
                value: SdoValue = variable.raw
                return value
            except SdoAbortedError as exc:
                if exc.code not in PROTOCOL_ABORTS:
                    raise self._refused(exc.code, "read", index) from None
                unanswered = exc
            except SdoCommunicationError as exc:
                unanswered = exc
            except can.CanError as exc:
                raise NoAnswer(f"cannot ask manager node {self.node.id}: {exc}") from None
        raise NoAnswer(f"no answer from manager node {self.node.id}: {unanswered} "
                       f"({READ_ATTEMPTS} tries)")

    def read_int(self, index: int) -> int:
        """An integer object (the node's EDS says which): anything else is a wrong EDS."""
        value = self.read(index)
        if not isinstance(value, int):
            raise RocomaError(f"read 0x{index:04X}: expected an integer, got {value!r}: is "
                              f"node {self.node.id} a rocoma-can manager?")
        return value

    def read_text(self, index: int) -> str:
        """A VISIBLE_STRING object."""
        value = self.read(index)
        if not isinstance(value, str):
            raise RocomaError(f"read 0x{index:04X}: expected text, got {value!r}: is "
                              f"node {self.node.id} a rocoma-can manager?")
        return value

    def write(self, index: int, value: SdoValue) -> None:
        """A string goes as its UTF-8 bytes (the node takes UTF-8 names; canopen's own
        encoding of a VISIBLE_STRING is ASCII and raised on "é")."""
        try:
            if isinstance(value, str):
                self.node.sdo.download(index, 0, value.encode("utf-8", "surrogateescape"))
            else:  # numbers: taking only this write's answer (sdo_write says why)
                sdo_write.download(self.node.sdo, index, 0,
                                   bytes(self.node.sdo[index].od.encode_raw(value)))
        except SdoAbortedError as exc:
            raise self._refused(exc.code, "write", index) from None
        except SdoCommunicationError as exc:
            raise NoAnswer(f"no answer from manager node {self.node.id}: {exc}") from None
        except can.CanError as exc:
            raise NoAnswer(f"cannot ask manager node {self.node.id}: {exc}") from None

    def _refused(self, code: int, what: str, index: int) -> RocomaError:
        """An abort of a read or write of ``index``: the manager's refusal, or, where the
        node has no such object (abort 0x06020000), a node that is no rocoma-can manager
        (a wrong --node: a drive's id), which is no manager's answer (NoAnswer)."""
        if code == ABORT_NO_OBJECT:
            return NoAnswer(f"node {self.node.id} is no rocoma-can manager (or an older one): "
                            f"it has no object 0x{index:04X} (SDO abort 0x{code:08X}): "
                            "wrong --node? (rocoma-can scan lists the nodes)")
        return Refused(code, f"{what} 0x{index:04X}", _meaning(code))

    def home(self, drive: str, timeout: float = 60.0, poll: float = 0.1) -> str:
        """Home one drive and wait (bounded) until its 0x2140 entry says how it ended:
        "homed", "failed: ..." (or "timed out" after ``timeout`` s). A refusal raises
        Refused with the manager's reason (0x2151)."""
        try:
            self.write(HOME_DRIVE, drive)
        except Refused as exc:
            reason = self.read_text(HOMING_REFUSAL)
            raise Refused(exc.code, f"home {drive}", reason or _meaning(exc.code)) from None
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for d in self._drives():
                if d.get("name") == drive and d.get("homing", "").startswith(
                        ("homed", "failed")):
                    return str(d["homing"])
            time.sleep(poll)
        return "timed out"

    def _drives(self) -> list[dict[str, Any]]:
        try:
            report = json.loads(self.read_text(DRIVE_STATUS) or "{}")
        except ValueError:
            return []
        drives = report.get("drives", []) if isinstance(report, dict) else []
        return [d for d in drives if isinstance(d, dict)]

    def switch(self, name: str, timeout: float = 10.0) -> int:
        """Request a switch and poll 0x2102 until it is no longer PENDING (bounded)."""
        # a number from `list` (0x2101 is U8); anything else, "²" or "300" too, is a name
        if name.isascii() and name.isdigit() and 1 <= int(name) <= 255:
            self.write(SWITCH_INDEX, int(name))
        else:
            self.write(SWITCH_NAME, name)
        deadline = time.monotonic() + timeout
        while True:
            result = self.read_int(SWITCH_RESULT)
            if result != PENDING or time.monotonic() > deadline:
                return result
            time.sleep(0.02)

    def status(self) -> dict[str, Any]:
        """Everything the node serves about itself and its drives (0x2140 decoded)."""
        try:
            drives = json.loads(self.read_text(DRIVE_STATUS) or "{}")
        except ValueError:
            drives = {}
        return {
            "state": STATE_NAMES.get(self.read_int(STATE), "?"),
            "active": self.read_text(ACTIVE_NAME),
            "latched": bool(self.read_int(ESTOP_LATCHED)),
            "last_switch": RESULT_NAMES.get(self.read_int(SWITCH_RESULT), "?"),
            "switch_refused": self.read_text(SWITCH_REFUSAL),
            "estop_cause": self.read_text(ESTOP_CAUSE),
            "estop_cob_id": self.read_int(ESTOP_COB_ID),
            "startup_finished": drives.get("startup_finished"),
            "recovery": drives.get("recovery"),
            "bus_fault": drives.get("bus_fault"),
            "cycle": drives.get("cycle"),
            "buses": drives.get("buses", []),
            "drives": drives.get("drives", []),
            "zenoh": drives.get("zenoh"),
        }

    def controllers(self) -> list[str]:
        text = self.read_text(CONTROLLER_LIST)
        return [n for n in text.split(",") if n]


def _meaning(code: int) -> str:
    return ABORT_TEXT.get(code, "see CiA 301")
