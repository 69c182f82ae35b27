"""The manager as a CANopen node (eds/rocoma_manager.eds): SDO services, e-stop frame, state frames.

Server side, ``ManagerNode`` (objects; docs/cli.md has the full table):

  0x2100 VISIBLE_STRING w  switch to the controller with this name
  0x2101 U8 w              switch to controller number n of 0x2123 (1-based)
  0x2102 U8 r              last switch result: 0 SWITCHED, 1 RUNNING, 2 NOT_FOUND, 3 ERROR,
                           0xFF PENDING (accepted, switcher still working), 0xFE none yet
  0x2103 VISIBLE_STRING r  why the last switch request was refused ("" = it was not)
  0x2110 / 0x2111 / 0x2112 / 0x2113 U8 w   e-stop / failproof stop / clear / recover drives
  0x2120 U8 r state (0 FAILPROOF, 1 EMERGENCY, 2 OK); 0x2121 active controller name;
  0x2122 U8 r active controller number (0 = none of 0x2123); 0x2123 controller list
  (comma separated); 0x2124 last e-stop cause; 0x2130 U32 rw e-stop COB-ID (0 = off);
  0x2131 U8 r e-stop latched; 0x2140 VISIBLE_STRING r drive status (JSON, see docs/cli.md);
  0x2150 VISIBLE_STRING w home the drive of this name (homing runs in the cycle: its
  progress is the drive's "homing" in 0x2140); 0x2151 VISIBLE_STRING r why the last homing
  request was refused

Why a switch is answered at once: canopen's SDO server answers on the bus reader's thread, and
the same thread carries the e-stop COB-ID listener. Waiting there for a switch (which runs
initialize/swap of the new controller, for any length of time) would delay e-stops and make
the client's SDO time out. So a write to 0x2100/0x2101 is checked synchronously (unknown
name -> abort 0x06090030 and 0x2102 = NOT_FOUND; e-stop latched, drives not ready or a switch
running -> abort 0x08000022, 0x2102 = ERROR and the reason in 0x2103), otherwise accepted
with 0x2102 = 0xFF (PENDING); the result lands in 0x2102 when the switch ends.
``rocoma-can switch`` polls 0x2102 for it.

Frames the node sends (from its own status thread, never from the control loop):
  TPDO1 0x180+id, 2 bytes [state, active controller number]: on every state or controller
  change and every ``status_period``.
  EMCY 0x080+id on every e-stop: code 0x9000 (external error), register 0x01, byte 3 =
  the new state; EMCY 0x0000 (error reset) when the e-stop latch is cleared.
Any frame on the e-stop COB-ID (0x2130), whatever its data, calls ``manager.emergency_stop``
from the bus reader's thread: the next control cycle handles it.

The node uses a bus of its own (a second socket on the same interface, or a second
virtual-bus instance) so its reader thread and SDO traffic never share a thread with the driver.
"""
from __future__ import annotations

import collections
import json
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Protocol

import can
import canopen
from canopen.objectdictionary import ODVariable
from canopen.sdo.constants import ABORT_GENERAL_ERROR
from canopen.sdo.exceptions import SdoAbortedError

from .. import eds as shipped_eds
from ..drivers.link.bus import BusReader, CanopenFrames
from ..drivers.protocol.cia301 import (
    EMCY,
    NMT,
    PRODUCER_HEARTBEAT_TIME,
    TPDO_BASE,
    TPDO_COMM,
    reserved_cob_id,
)
from ..drivers.protocol.wire import frame_bits
from ..errors import HomingFailed
from ..events import EventKind, ManagerEvent, ManagerState
from ..manager import ControllerManager, SwitchResult
from ..remote import cleared
from ..stop_surfaces import CAN_FRAME, SDO
from .objects import (
    ABORT_NO_RECOVERY,
    ABORT_NOT_FOUND,
    ABORT_REFUSED,
    ACTIVE_INDEX,
    ACTIVE_NAME,
    CLEAR,
    CONTROLLER_LIST,
    DRIVE_STATUS,
    ESTOP,
    ESTOP_CAUSE,
    ESTOP_COB_ID,
    ESTOP_LATCHED,
    FAILPROOF_STOP,
    HOME_DRIVE,
    HOMING_REFUSAL,
    NO_SWITCH_YET,
    PENDING,
    RECOVER,
    RESULT_NAMES,
    STATE,
    SWITCH_INDEX,
    SWITCH_NAME,
    SWITCH_REFUSAL,
    SWITCH_RESULT,
)
from .sdo_server import BURST, StrictSdoServer

log = logging.getLogger(__name__)

def _visible(text: str) -> str:
    """A VISIBLE_STRING is ASCII (CiA 301; canopen encodes it so and fails on anything else,
    which made the whole read abort): other characters are escaped, e.g. "j\\xe9"."""
    return text.encode("ascii", "backslashreplace").decode("ascii")


#: The bit rate block uploads are paced for when the node is not told its bus's: 125 kbit/s,
#: the slowest rate CANopen drives commonly run at.
ASSUMED_BITRATE = 125_000


def burst_gap(bitrate: int) -> float:
    """Seconds between two bursts of a block upload: a burst's time on the wire twice over
    (worst-case 8-byte frames), so its frames have left the transmit queue, and the control
    loop's frames that queued behind them too, before the next burst joins the queue."""
    return 2 * BURST * frame_bits(8) / bitrate


def _homing_end(job: Future[object], drive: str) -> str:
    """How a homing job ended, as ``home`` prints it ("homed", "failed: why"; the job's
    words begin with the drive's name, said already)."""
    exc = job.exception()
    return "homed" if exc is None else f"failed: {str(exc).removeprefix(f'{drive}: ')}"


def _never_produce_heartbeats(node: canopen.LocalNode) -> None:
    """Only the control loop sends this node's heartbeat (CanopenHardware.write).

    canopen's NmtSlave starts a periodic sender of its own on a write to 0x1017 or on its
    INITIALISING -> PRE-OPERATIONAL transition: a thread, or a kernel BCM task on SocketCAN,
    that keeps beating when the loop hangs, so the drives' heartbeat consumers would never
    time out and 0x6007 would never switch them off. 0x1017 is read-only in the shipped EDS
    (writes are aborted before any callback); for any EDS, the sender is taken out here.
    """
    node._write_callbacks.remove(node.nmt.on_write)  # canopen has no public way to undo it
    node.nmt.start_heartbeat = lambda heartbeat_time_ms: None  # type: ignore[method-assign]


def _integer(od: ODVariable, data: bytes) -> int:
    """An integer object's written value (the node's EDS types these objects as integers;
    anything else is a wrong EDS, refused like any write the node cannot take)."""
    value = od.decode_raw(data)
    if not isinstance(value, int):
        raise SdoAbortedError(ABORT_GENERAL_ERROR)
    return value


class StatusReport(Protocol):
    """The running system's status (runtime.system.RuntimeStatus), serialized here only."""
    def as_dict(self) -> dict[str, Any]: ...


class ManagerNode(can.Listener):
    """Serves a ControllerManager on a CAN bus (lent, not shut down here).

    Lend it a bus handle of its own: the node sets the handle's receive filters to what it
    serves (its SDO requests, NMT commands, and the e-stop COB-ID when the frames are its
    own to take), so the control loop's PDO traffic on that bus, a dozen frames or more a
    cycle, never wakes its reader (on SocketCAN the kernel drops them; on the in-process
    bus the sender does). ``close`` lifts the filters."""

    def __init__(self, manager: ControllerManager, node_id: int, bus: can.BusABC, *,
                 estop_cob_id: int = 0, status_period: float = 0.1,
                 recover: Callable[[], Future[bool]] | None = None,
                 eds_path: str | None = None,
                 heartbeat_ms: int | None = None,
                 drive_status: Callable[[], StatusReport] | None = None,
                 estop_in_cycle: Callable[[int], None] | None = None,
                 home: Callable[[str], object] | None = None,
                 bitrate: int | None = None) -> None:
        """``estop_in_cycle``: the hardware takes e-stop frames itself, on every bus, in
        the cycle (CanopenHardware.set_estop_cob_id): the node then only owns the COB-ID
        (0x2130) and hands it over on every change, and ignores the frames. ``bitrate``:
        the bus's, which paces block uploads (StrictSdoServer); None assumes
        ASSUMED_BITRATE, slow enough that a faster bus only waits longer than it needs."""
        self.manager = manager
        self.node_id = node_id
        self.bus = bus
        self.status_period = status_period
        self.recover = recover
        self.home = home  # CanopenHardware.home: raises HomingFailed when it refuses
        self.homing_refusal = ""
        self.last_result = NO_SWITCH_YET
        self.last_cause = ""
        self.drive_status = drive_status  # -> the 0x2140 report (JSON), None: no drives
        # monotonic receive times of the latest e-stop frames (a sender may repeat its frame
        # for as long as a button is held)
        self.estop_frames: collections.deque[float] = collections.deque(maxlen=1000)
        self.frames_sent = 0
        self._estop_cob_id = 0
        self._network = canopen.Network(bus)
        od = canopen.import_od(eds_path or str(shipped_eds.path(shipped_eds.MANAGER_NODE)),
                               node_id)
        self.heartbeat_ms = heartbeat_ms  # the loop's period, answered on 0x1017 reads
        self._node = canopen.LocalNode(node_id, od)
        self._node.sdo = StrictSdoServer(self._node.sdo.rx_cobid, self._node.sdo.tx_cobid,
                                          self._node,
                                          burst_gap=burst_gap(bitrate or ASSUMED_BITRATE))
        # a download to 0x2110 / 0x2111 stops at its first request, whatever it carries
        self._node.sdo.stops = {
            ESTOP: lambda: SDO.stop(self.manager, "estop", f" (0x{ESTOP:04X})"),
            FAILPROOF_STOP: lambda: SDO.stop(self.manager, "failproof",
                                             f" (0x{FAILPROOF_STOP:04X})")}
        _never_produce_heartbeats(self._node)
        self._node.add_read_callback(self._on_read)
        self._node.add_write_callback(self._on_write)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._status_loop, name="manager-node",
                                        daemon=True)
        self._unsubscribe: Callable[[], None] | None = None
        self._initial_cob = estop_cob_id
        self._estop_in_cycle = estop_in_cycle
        self._started = False
        self._reader: BusReader | None = None

    @property
    def _sdo(self) -> StrictSdoServer:
        sdo = self._node.sdo
        assert isinstance(sdo, StrictSdoServer)  # set in __init__
        return sdo

    # --- life cycle ---------------------------------------------------------------------------
    def start(self) -> ManagerNode:
        self._reader = BusReader(self.bus, (CanopenFrames(self._network), self),
                                 name="manager-node-rx")
        self._network.add_node(self._node)
        self.set_estop_cob_id(self._initial_cob)
        self._unsubscribe = self.manager.subscribe(self._on_event)
        self._started = True
        self._thread.start()
        return self

    def close(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        if self._reader is not None:
            self._reader.stop()
            self._reader = None
        self._sdo.close()
        if self._started:
            try:
                self.bus.set_filters(None)  # the lent handle as it came
            except can.CanError as exc:  # an interface that cannot: nothing is left running
                log.warning("manager node %d: receive filters not lifted: %s", self.node_id,
                            exc)

    def __enter__(self) -> ManagerNode:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def reader(self) -> BusReader | None:
        """The node's bus reader (None until started): its thread serves SDO and e-stops."""
        return self._reader

    # --- e-stop frame -------------------------------------------------------------------------
    @property
    def estop_cob_id(self) -> int:
        return self._estop_cob_id

    def set_estop_cob_id(self, cob_id: int) -> None:
        """0 switches the e-stop frame off; 1..0x7FF is an 11-bit identifier. With
        ``estop_in_cycle`` the hardware checks it against the drives' identifiers too."""
        if not 0 <= cob_id <= 0x7FF:
            raise SdoAbortedError(ABORT_NOT_FOUND)
        if self._estop_in_cycle is not None:
            try:
                self._estop_in_cycle(cob_id)
            except ValueError as exc:  # a drive's or a reserved identifier
                log.warning("manager node %d: e-stop COB-ID 0x%03X refused: %s",
                            self.node_id, cob_id, exc)
                raise SdoAbortedError(ABORT_NOT_FOUND) from None
        self._estop_cob_id = cob_id
        self._filter()

    def _filter(self) -> None:
        """Receive only what the node serves (see the class docstring); 11-bit frames, data
        or remote (a remote frame on the e-stop COB-ID is an e-stop too)."""
        ids = [self._node.sdo.rx_cobid, NMT]
        if self._estop_cob_id and self._estop_in_cycle is None:
            ids.append(self._estop_cob_id)
        self.bus.set_filters([{"can_id": i, "can_mask": 0x7FF, "extended": False}
                              for i in ids])

    def on_message_received(self, msg: can.Message) -> None:
        """On the bus reader's thread: any 11-bit frame on the e-stop COB-ID, data or remote
        (RTR), of any length, is an e-stop. (canopen's own listener drops remote frames, so
        this does not go through it.) A 29-bit frame is another identifier."""
        cob_id = self._estop_cob_id
        if cob_id and msg.arbitration_id == cob_id and self._estop_in_cycle is None \
                and not (msg.is_extended_id or msg.is_error_frame):
            CAN_FRAME.stop(self.manager, "estop", f" from 0x{cob_id:03X}")
            self.estop_frames.append(time.monotonic())

    def on_error(self, exc: Exception) -> None:  # the reader counts and retries bus errors
        pass

    # --- SDO ----------------------------------------------------------------------------------
    def _controller_index(self) -> int:
        names = self.manager.available_controllers()
        active = self.manager.active_controller_name
        return names.index(active) + 1 if active in names else 0

    def _on_read(self, index: int, subindex: int, od: ODVariable) -> int | str | None:
        m = self.manager
        if index == PRODUCER_HEARTBEAT_TIME and self.heartbeat_ms is not None:
            return self.heartbeat_ms
        if index == TPDO_COMM and subindex == 5:  # the status frame's period
            return min(0xFFFF, round(self.status_period * 1000))
        if index == STATE:
            return int(m.state)
        if index == ACTIVE_NAME:
            return _visible(m.active_controller_name)
        if index == ACTIVE_INDEX:
            return self._controller_index()
        if index == CONTROLLER_LIST:
            return _visible(",".join(m.available_controllers()))
        if index == ESTOP_CAUSE:
            return _visible(self.last_cause)
        if index == ESTOP_LATCHED:
            return int(m.estop_latched)
        if index == SWITCH_RESULT:
            return self.last_result
        if index == SWITCH_REFUSAL:
            return _visible(m.last_refusal)
        if index == DRIVE_STATUS:
            report = (self.drive_status().as_dict() if self.drive_status is not None
                      else {"startup_finished": True, "recovery": "", "drives": []})
            return json.dumps(report, separators=(",", ":"))
        if index == ESTOP_COB_ID:
            return self._estop_cob_id
        if index == HOMING_REFUSAL:
            return _visible(self.homing_refusal)
        return None

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        m = self.manager
        if index == SWITCH_NAME:
            try:  # strictly: canopen's decoding drops bytes it cannot read ("h\xffold" -> hold)
                name = bytes(data).decode("utf-8").strip("\x00 ")
            except UnicodeDecodeError:
                self.last_result = 2
                self._tell("switch", "NOT_FOUND (the name is not UTF-8)")
                raise SdoAbortedError(ABORT_NOT_FOUND) from None
            self._switch(name)
        elif index == SWITCH_INDEX:
            names = m.available_controllers()
            n = _integer(od, data)
            if not 1 <= n <= len(names):
                self.last_result = 2
                self._tell(f"switch to number {n}", f"NOT_FOUND (controllers: "
                                                    f"{', '.join(names) or 'none'})")
                raise SdoAbortedError(ABORT_NOT_FOUND)
            self._switch(names[n - 1])
        elif index in (ESTOP, FAILPROOF_STOP):
            pass  # stopped at the transfer's first request (StrictSdoServer.stops)
        elif index == CLEAR:
            latched = m.estop_latched
            m.clear_emergency_stop()
            self._tell("clear", cleared(latched))
            self._wake.set()
        elif index == RECOVER:
            if self.recover is None:
                self._tell("recover", "refused: this manager has no drives")
                raise SdoAbortedError(ABORT_NO_RECOVERY)
            self._tell("recover", "started")
            self.recover()
        elif index == ESTOP_COB_ID:
            self._change_estop_cob_id(_integer(od, data))
        elif index == HOME_DRIVE:
            self._home(bytes(data))

    def _tell(self, what: str, answer: str) -> None:
        """An SDO request and its answer, for the audit trail (ControllerManager.
        notify_request): the SDO channel does not say which client asked."""
        self.manager.notify_request(f"SDO (node {self.node_id}): {what}: {answer}")

    def _home(self, data: bytes) -> None:
        """Answered at once, like a switch: refused (abort, reason in 0x2151) or started."""
        if self.home is None:
            self.homing_refusal = "this manager has no drives"
            self._tell("home", f"refused: {self.homing_refusal}")
            raise SdoAbortedError(ABORT_NO_RECOVERY)
        try:
            name = data.decode("utf-8").strip("\x00 ")
        except UnicodeDecodeError:
            self.homing_refusal = "the drive name is not UTF-8"
            self._tell("home", f"refused: {self.homing_refusal}")
            raise SdoAbortedError(ABORT_NOT_FOUND) from None
        try:
            job = self.home(name)
        except HomingFailed as exc:
            self.homing_refusal = str(exc)
            self._tell(f"home {name!r}", f"refused: {exc}")
            raise SdoAbortedError(ABORT_REFUSED) from None
        self.homing_refusal = ""
        self._tell(f"home {name!r}", "started")
        if isinstance(job, Future):  # its end told too (queued: it may end in the cycle)
            job.add_done_callback(
                lambda done: self._tell(f"home {name!r}", _homing_end(done, name)))

    def _change_estop_cob_id(self, value: int) -> None:
        """An SDO write of 0x2130: bit 31 set (CiA 301 "not valid") or 0 switches the e-stop
        frame off, 1..0x7FF sets it; anything else is refused, never masked into another
        identifier. Allowed only while no controller commands (FAILPROOF) or the e-stop is
        latched: the e-stop path of a running machine is not changed under it."""
        cob_id = 0 if value >> 31 else value
        if not 0 <= cob_id <= 0x7FF or (cob_id and reserved_cob_id(cob_id)):
            raise SdoAbortedError(ABORT_NOT_FOUND)
        m = self.manager
        if m.state is not ManagerState.FAILPROOF and not m.estop_latched:
            raise SdoAbortedError(ABORT_REFUSED)
        old = self._estop_cob_id
        self.set_estop_cob_id(cob_id)  # may still refuse it (a drive's identifier)
        log.warning("manager node %d: e-stop COB-ID changed by SDO from 0x%03X to 0x%03X%s",
                    self.node_id, old, cob_id, " (off)" if not cob_id else "")

    def _switch(self, name: str) -> None:
        m = self.manager
        what = f"switch to {name!r}"
        if name not in m.available_controllers():
            m.last_refusal = f"no controller {name!r}"
            self.last_result = 2
            self._tell(what, f"NOT_FOUND (controllers: "
                             f"{', '.join(m.available_controllers()) or 'none'})")
            raise SdoAbortedError(ABORT_NOT_FOUND)
        blocked = m.switch_blocked()  # e-stop latched, drives not ready: m.last_refusal says
        if blocked is not None:
            m.last_refusal = blocked
            self.last_result = 3
            self._tell(what, f"refused: {blocked}")
            raise SdoAbortedError(ABORT_REFUSED)
        self.last_result = PENDING
        future = m.request_switch(name)
        future.add_done_callback(lambda done: self._switch_done(what, done))
        if future.done() and future.result() == 3:
            raise SdoAbortedError(ABORT_REFUSED)

    def _switch_done(self, what: str, future: Future[SwitchResult]) -> None:
        try:
            self.last_result = int(future.result())
        except Exception:
            self.last_result = 3
        result = RESULT_NAMES.get(self.last_result, str(self.last_result))
        refusal = self.manager.last_refusal if self.last_result == 3 else ""
        self._tell(what, f"{result}: {refusal}" if refusal else result)

    # --- frames out ---------------------------------------------------------------------------
    def _on_event(self, event: ManagerEvent) -> None:
        """Manager event thread: note the cause, wake the status thread (no I/O here)."""
        if event.kind is EventKind.EMERGENCY_STOP:
            self.last_cause = event.cause
            self._pending_emcy = int(event.state)
        self._wake.set()

    _pending_emcy: int | None = None

    def _status_loop(self) -> None:
        last = None
        latched = self.manager.estop_latched
        next_due = 0.0
        while not self._stop.is_set():
            self._wake.wait(max(0.0, min(self.status_period, next_due - time.monotonic())))
            self._wake.clear()
            if self._stop.is_set():
                return
            emcy, self._pending_emcy = self._pending_emcy, None
            if emcy is not None:
                self._send(EMCY + self.node_id, bytes([0x00, 0x90, 0x01, emcy, 0, 0, 0, 0]))
            now_latched = self.manager.estop_latched
            if latched and not now_latched:
                self._send(EMCY + self.node_id, bytes(8))
            latched = now_latched
            current = (int(self.manager.state), self._controller_index())
            now = time.monotonic()
            if current != last or now >= next_due:
                self._send(TPDO_BASE[0] + self.node_id, bytes(current))
                last = current
                next_due = now + self.status_period

    def _send(self, cob_id: int, data: bytes) -> None:
        try:
            self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False),
                          timeout=0.05)
            self.frames_sent += 1
        except can.CanError as exc:
            log.warning("manager node: frame 0x%03X not sent: %s", cob_id, exc)
