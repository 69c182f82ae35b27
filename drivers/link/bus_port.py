"""One bus of the hardware layer: its handle, its receiver, its cycle frames, its health.

A robot with several CAN buses (one per limb is common: a classic 1 Mbit/s bus carries
~7,400-9,000 frames/s, so 12 drives at 1 kHz need several) has one ``BusPort`` per bus. The
hardware's cycle is still one: ``read`` drains every port, ``write`` sends every drive's
frames on its own port and then SYNC and the manager's heartbeat on each port, back to back,
so every bus sees its SYNC at the same instant of the cycle.

Per port: a receiver on the bus's reader thread that only filters and appends (so no lock
is shared with the cycle), pre-allocated SYNC and heartbeat frames (CAN FD on an FD bus),
and the transmit health that makes a bus that refuses frames cycle after cycle a bus fault.
"""
from __future__ import annotations

import collections
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Protocol

import can

from ..plan.config import BusConfig
from ..protocol import cia301
from .bus import SENT_HELD, CanopenBus, open_bus, start_reading
from .frame_io import FrameWriter

_FD = (can.CanProtocol.CAN_FD, can.CanProtocol.CAN_FD_NON_ISO)

#: Linux CAN error class of a bus-off error frame (linux/can/error.h CAN_ERR_BUSOFF)
CAN_ERR_BUSOFF = 0x40


class _Receiver(can.Listener):
    """Runs on the bus reader thread, or the loop's (drain_now): filter by COB-ID, append.
    Nothing else.

    Frames keep their arrival stamp (kernel or python-can, wall clock); the cycle converts
    it to the monotonic clock once per cycle, so a reader that lags does not make frames
    late. Only 11-bit data frames are CANopen (0x181 as a 29-bit id is another frame); the
    e-stop COB-ID is taken in any form an 11-bit frame has, data or remote (RTR).
    """

    #: takes no lock (deque appends): the control loop's own read may call it
    #: (BusReader.drain_now)
    lock_free = True

    def __init__(self, cob_ids: set[int], sink: collections.deque[can.Message],
                 errors: collections.deque[can.Message]) -> None:
        self._ids = frozenset(cob_ids)
        self._sink = sink
        self._errors = errors
        self.estop_cob_id = 0  # set by the hardware; read once per frame

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self._errors.append(msg)
        elif msg.is_extended_id:
            return
        elif msg.arbitration_id in self._ids and not msg.is_remote_frame:
            self._sink.append(msg)
        elif msg.arbitration_id == self.estop_cob_id and self.estop_cob_id:
            self._sink.append(msg)

    def on_error(self, exc: Exception) -> None:  # counted by the reader; nothing to do here
        pass


Bus = can.BusABC | BusConfig


def named_buses(bus: Bus | Mapping[str, Bus]) -> dict[str, Bus]:
    """One bus (named by its config, or "bus" when lent) or a name -> bus mapping."""
    if isinstance(bus, Mapping):
        if not bus:
            raise ValueError("buses: at least one bus is needed")
        return dict(bus)
    return {bus.label if isinstance(bus, BusConfig) else "bus": bus}


class SentFrames(Protocol):
    """Where a recording keeps the frames a bus sent (record/rings.py FrameRing): called on
    the cycle's thread only."""

    def put(self, msg: can.Message, stamp: float) -> None: ...


def _frame(cob_id: int, size: int, fd: bool) -> can.Message:
    """A pre-allocated 11-bit frame; on an FD bus with bit rate switching."""
    return can.Message(arbitration_id=cob_id, data=bytearray(size), is_extended_id=False,
                       is_fd=fd, bitrate_switch=fd)


def _no_hold() -> None:
    """A bus that wakes its readers at each frame anyway (SocketCAN: the kernel does)."""


class BusPort:
    """One bus: lent (a python-can bus) or opened here (a BusConfig) by ``open``."""

    def __init__(self, name: str, bus: can.BusABC | BusConfig, drives: list[int],
                 manager_node_id: int) -> None:
        self.name = name
        self.drives = drives  # indices of the hardware's drives on this bus
        self._arg = bus
        # a lent bus says whether it is FD (python-can's protocol); a config says so itself
        self.fd = bus.fd if isinstance(bus, BusConfig) else getattr(bus, "protocol", None) in _FD
        self.rx: collections.deque[can.Message] = collections.deque()
        self.rx_errors: collections.deque[can.Message] = collections.deque(maxlen=1024)
        self.canopen: CanopenBus | None = None
        self._writer: FrameWriter | None = None
        self._receiver: _Receiver | None = None
        self.sync = self.frame(cia301.SYNC, 0)
        self.heartbeat = self.frame(cia301.HEARTBEAT + manager_node_id, 1)
        self.heartbeat.data[0] = cia301.NmtState.OPERATIONAL
        # receive tables, COB-ID -> drive index (filled by the hardware)
        self.heartbeat_of: dict[int, int] = {}
        self.emcy_of: dict[int, tuple[int, ...]] = {}  # the axes of the node
        # transmit health
        self.tx_errors = 0
        self.last_tx_error: Exception | None = None
        self.refused = False       # a frame was refused since the last end_of_write
        self.refused_cycles = 0    # writes in a row with a refused frame
        self.clean_cycles = 0      # writes in a row without one (a recovery needs a run)
        self.error_frames = 0
        self.latched: str | None = None  # the bus fault's cause until recovery
        # a cycle's frames wake this bus's readers once, after the write (inproc.py's
        # hold_wakeups; a no-op on interfaces without it)
        self.hold_wakeups: Callable[[], None] = _no_hold
        self.release_wakeups: Callable[[], None] = _no_hold
        # a recording of this bus's frames (record_frames): what the cycle sent, and what
        # other threads sent, held for the cycle to hand over
        self._sent: SentFrames | None = None
        self._sent_elsewhere: collections.deque[tuple[can.Message, float]] = \
            collections.deque(maxlen=SENT_HELD)

    def frame(self, cob_id: int, size: int) -> can.Message:
        return _frame(cob_id, size, self.fd)

    @property
    def channel(self) -> str:
        arg = self._arg
        return arg.channel if isinstance(arg, BusConfig) else str(arg.channel_info)

    def open(self, cob_ids: set[int]) -> CanopenBus:
        """Open the bus (unless lent) and attach the receiver for ``cob_ids``; nothing is
        read until ``bus.start_reading`` (one reader thread for all the hardware's buses)."""
        arg = self._arg
        if isinstance(arg, BusConfig):
            extra: dict[str, object] = {"fd": True} if arg.fd else {}
            if arg.data_bitrate is not None:
                extra["data_bitrate"] = arg.data_bitrate
            cb = CanopenBus(open_bus(arg.interface, arg.channel, arg.bitrate, **extra),
                            own_bus=True, read=False)
        else:
            cb = CanopenBus(arg, read=False)
        self.canopen = cb
        self._writer = cb.writer
        self.hold_wakeups = getattr(cb.bus, "hold_wakeups", _no_hold)
        self.release_wakeups = getattr(cb.bus, "release_wakeups", _no_hold)
        self._receiver = _Receiver(cob_ids, self.rx, self.rx_errors)
        cb.add_listener(self._receiver)
        return cb

    def record_frames(self, received: can.Listener, sent: SentFrames) -> None:
        """Record every frame of the open bus: ``received`` is fed by the bus's own reader
        (the frames the hardware reads anyway: no second socket), ``sent`` gets each frame
        sent here (the cycle's, and on the cycle's thread, the canopen services' and the
        hang watchdog's, which other threads sent)."""
        assert self.canopen is not None, "record_frames() before open()"
        self.canopen.add_listener(received)
        self.canopen.network.sent = self._sent_elsewhere
        self._sent = sent

    def set_estop_cob_id(self, cob_id: int) -> None:
        if self._receiver is not None:
            self._receiver.estop_cob_id = cob_id

    def close(self) -> None:
        if self.canopen is not None:
            self.canopen.close()
            self.canopen = None
            self._writer = None
            self.hold_wakeups = self.release_wakeups = _no_hold

    def send(self, msg: can.Message) -> None:
        """Never raises, never blocks: a refused frame is counted (``end_of_write``). The
        cycle's thread only (``send_elsewhere`` for the others)."""
        if self._send(msg):
            sent = self._sent
            if sent is not None:
                sent.put(msg, time.time())

    def send_elsewhere(self, msg: can.Message) -> None:
        """``send`` from a thread other than the cycle's (the hang watchdog's torque-off):
        a recording gets the frame from the cycle (``end_of_write``), one producer."""
        if self._send(msg) and self._sent is not None:
            self._sent_elsewhere.append((can.Message(
                arbitration_id=msg.arbitration_id, data=bytes(msg.data), is_fd=msg.is_fd,
                bitrate_switch=msg.bitrate_switch, is_extended_id=msg.is_extended_id),
                time.time()))

    def _send(self, msg: can.Message) -> bool:
        try:
            self._writer.send_message(msg)  # type: ignore[union-attr]
        except Exception as exc:  # a full queue, a failed interface, or not started/closed
            self.tx_errors += 1
            self.last_tx_error = exc
            self.refused = True
            return False
        return True

    def end_of_write(self, limit: int) -> str | None:
        """After a cycle's frames: the cause while the bus has refused frames ``limit`` or
        more cycles in a row (a bus fault), else None. One refused frame is not a fault (a
        transmit queue can be full for a moment); the frames are tried again every cycle."""
        held = self._sent_elsewhere
        if held and self._sent is not None:  # SDO, NMT, the watchdog: into the recording
            put = self._sent.put
            for _ in range(len(held)):
                put(*held.popleft())
        if not self.refused:
            self.refused_cycles = 0
            if self.clean_cycles < limit:
                self.clean_cycles += 1
            return None
        self.refused = False
        self.clean_cycles = 0
        self.refused_cycles += 1
        if self.refused_cycles >= limit:
            return (f"bus {self.name!r} refused frames in {self.refused_cycles} cycles in a "
                    f"row (last: {self.last_tx_error})")
        return None

    def bus_off(self) -> str | None:
        """Drain error frames (cycle thread): the cause of the first bus-off, else None."""
        errors, cause = self.rx_errors, None
        while errors:
            msg = errors.popleft()
            self.error_frames += 1
            if msg.arbitration_id & CAN_ERR_BUSOFF and cause is None:
                cause = (f"CAN bus-off on bus {self.name!r} (error frame class "
                         f"0x{msg.arbitration_id:X})")
        return cause



def open_ports(ports: Sequence[BusPort], cob_ids: Sequence[set[int]], estop_cob_id: int,
               recorded: Sequence[tuple[can.Listener, SentFrames]] = ()
               ) -> tuple[list[tuple[Callable[[], None], Callable[[], None]]],
                          list[Callable[[], bool]]]:
    """Open every port (unless lent) with what its receiver keeps (``cob_ids``, in the
    ports' order) and the e-stop frame's COB-ID, its frames recorded where ``recorded``
    says, and start their readers. Returns the ports' wake-up holds, as pairs (a port closed
    while a write runs is still released by the bus it held), and the readers' drain_now
    (the cycle's read hands over what waits on the buses first). A bus that cannot be
    opened closes the ones opened before it and raises OSError."""
    try:
        for k, port in enumerate(ports):
            port.open(cob_ids[k])
            port.set_estop_cob_id(estop_cob_id)
            if recorded:
                port.record_frames(*recorded[k])
        # one reader thread for every bus where the interface allows (bus.readers_for)
        start_reading([port.canopen for port in ports if port.canopen is not None])
        holds = [(port.hold_wakeups, port.release_wakeups) for port in ports]
        readers = {id(port.canopen.reader): port.canopen.reader for port in ports
                   if port.canopen is not None and port.canopen.reader is not None}
        return holds, [reader.drain_now for reader in readers.values()]
    except BaseException:
        for port in ports:
            port.close()
        raise
