"""Cheap frame I/O for threads that see every frame on a bus: the simulated drives, recorders.

python-can's ``recv`` costs three system calls per frame (a clock read, ``select``,
``recvmsg``) and ``send`` three (clock, ``select``, ``send``). Natively that is a few
microseconds; inside a user-mode-linux guest, where even a clock read is a trapped system
call, a simulated segment of six drives at 25 Hz spent half the guest's only CPU on it and
fell a second behind the kernel. On SocketCAN this module reads every
waiting frame after one ``select`` with one non-blocking ``recvmsg`` each, and writes with
one ``send``; on the in-process bus (inproc.py) it takes a whole batch in one call; on any
other interface it uses python-can's API unchanged.

Frames keep the arrival time the kernel (SocketCAN) or python-can (virtual: send time)
stamped on them, in ``time.time()`` seconds. ``to_monotonic`` converts them, so a reader
that lags can still judge deadlines by when frames arrived rather than when it got to them.
"""
from __future__ import annotations

import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Collection, Sequence

import can
from can.interfaces.socketcan.constants import (
    CAN_EFF_FLAG,
    CAN_ERR_FLAG,
    CAN_RTR_FLAG,
    CANFD_BRS,
    CANFD_ESI,
    CANFD_MTU,
)
from can.interfaces.socketcan.socketcan import (
    RECEIVED_ANCILLARY_BUFFER_SIZE,
    RECEIVED_TIMESTAMP_STRUCT,
    build_can_frame,
    dissect_can_frame,
)

_CLASSIC_FRAME = struct.Struct("=IB3x8s")  # struct can_frame: id, dlc, pad, data


def _raw_socket(bus: can.BusABC) -> socket.socket | None:
    sock = getattr(bus, "socket", None)
    if isinstance(sock, socket.socket) and sock.family == getattr(socket, "AF_CAN", -1):
        return sock
    return None


def _message(frame: bytes, ancillary: list[tuple[int, int, bytes]]) -> can.Message:
    can_id, dlc, flags, data = dissect_can_frame(frame)
    timestamp = 0.0
    for level, _kind, payload in ancillary:
        if level == socket.SOL_SOCKET and len(payload) >= RECEIVED_TIMESTAMP_STRUCT.size:
            seconds, nanoseconds = RECEIVED_TIMESTAMP_STRUCT.unpack_from(payload)
            timestamp = seconds + nanoseconds * 1e-9
    extended = bool(can_id & CAN_EFF_FLAG)
    return can.Message(timestamp=timestamp,
                       arbitration_id=can_id & (0x1FFFFFFF if extended else 0x7FF),
                       is_extended_id=extended, is_remote_frame=bool(can_id & CAN_RTR_FLAG),
                       is_error_frame=bool(can_id & CAN_ERR_FLAG),
                       is_fd=len(frame) == CANFD_MTU, bitrate_switch=bool(flags & CANFD_BRS),
                       error_state_indicator=bool(flags & CANFD_ESI), dlc=dlc,
                       data=data[:dlc], check=False)


#: Frames one read takes at most: a full batch means more may be waiting.
READ_LIMIT = 256


class FrameReader:
    """Batches of received frames from one bus; the reader must be the bus's only reader."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self._sock = _raw_socket(bus)
        batch = getattr(bus, "recv_batch", None)
        self._batch: Callable[[float, int], list[can.Message]] | None = (
            batch if callable(batch) else None)

    def read(self, timeout: float, limit: int = READ_LIMIT) -> list[can.Message]:
        """The frames waiting now (at most ``limit``), after waiting up to ``timeout`` s for
        the first; [] when none came. An empty return after a batch shorter than ``limit``
        means the receive queue was empty at some instant during the call.

        Raises can.CanOperationError when the bus fails (interface down, socket closed).
        """
        sock = self._sock
        if sock is None:
            if self._batch is not None:  # the in-process bus hands over a batch at once
                return self._batch(timeout, limit)
            first = self.bus.recv(timeout)
            if first is None:
                return []
            batch = [first]
            while len(batch) < limit:
                msg = self.bus.recv(0.0)
                if msg is None:
                    break
                batch.append(msg)
            return batch
        try:
            if not select.select([sock], [], [], timeout)[0]:
                return []
            batch = []
            while len(batch) < limit:
                try:
                    frame, ancillary, _flags, _addr = sock.recvmsg(
                        CANFD_MTU, RECEIVED_ANCILLARY_BUFFER_SIZE, socket.MSG_DONTWAIT)
                except BlockingIOError:
                    break
                batch.append(_message(frame, ancillary))
            return batch
        except (OSError, ValueError) as exc:  # ValueError: select on a closed socket
            raise can.CanOperationError(f"receiving from {self.bus.channel_info}: {exc}",
                                        getattr(exc, "errno", None)) from exc


class BusSelector:
    """Waits until any of several buses has a frame, so that one thread can serve them all.

    Every thread that waits on a bus of its own costs a wake-up and a hand-over of the GIL
    per burst of frames; a simulator of four buses at 1 kHz paid that four times a cycle.
    SocketCAN buses are waited on with one ``select`` over their sockets; in-process buses
    (inproc.py) set one shared Event when a frame is queued. Other interfaces (python-can's
    ``virtual`` hands frames over a queue per bus) have nothing to wait on together:
    ValueError, and the caller keeps a thread per bus.

    A bus whose read failed (``failed``) is left out for ``retry`` seconds and then counts
    as ready once, so its read reports again: a failed interface is read at a bounded pace,
    never in a busy loop, and never holds up the others.
    """

    def __init__(self, buses: Sequence[can.BusABC], retry: float) -> None:
        self.buses = tuple(buses)
        if not self.supports(self.buses):
            kinds = ", ".join(sorted({type(bus).__name__ for bus in self.buses}))
            raise ValueError("one thread can wait on several buses only when all of them are "
                             f"SocketCAN or all in-process (inproc); got {kinds or 'none'}")
        self.retry = retry
        self._retry_at = [0.0] * len(self.buses)  # > 0: failed, read again from then on
        socks = [_raw_socket(bus) for bus in self.buses]
        self._socks: list[socket.socket] | None = None
        self._event: threading.Event | None = None
        if all(sock is not None for sock in socks):
            self._socks = [sock for sock in socks if sock is not None]
        else:
            self._event = threading.Event()
            for bus in self.buses:
                bus.add_wakeup(self._event)  # type: ignore[attr-defined]

    @staticmethod
    def supports(buses: Sequence[can.BusABC]) -> bool:
        """All SocketCAN, or all in-process: one thread can wait on them together."""
        return bool(buses) and (all(_raw_socket(bus) is not None for bus in buses) or all(
            callable(getattr(bus, "add_wakeup", None)) for bus in buses))

    def failed(self, index: int) -> None:
        """Reading bus ``index`` failed: leave it out for ``retry`` seconds."""
        self._retry_at[index] = time.monotonic() + self.retry

    def failing(self, index: int) -> bool:
        """Bus ``index`` failed and waits for its retry (its frames are not being read)."""
        return self._retry_at[index] > 0.0

    def wait(self, timeout: float) -> list[int]:
        """The buses to read now, after waiting up to ``timeout`` s for the first: those
        with frames waiting (or shut down: the read says so) and failed ones whose retry
        time has come; [] when none. Read each with a zero timeout; a bus not returned had
        nothing waiting when the wait ended."""
        if timeout <= 0.0 and self._event is not None and not any(self._retry_at):
            # a look without a wait (the simulator's pass in the loop's thread, every
            # cycle): the event stays set until a wait that blocks clears it before it
            # looks, so no frame is missed, and the senders skip setting it again
            return [i for i, bus in enumerate(self.buses)
                    if bus.pending]  # type: ignore[attr-defined]
        deadline = time.monotonic() + timeout
        while True:
            now = time.monotonic()
            due = [i for i, at in enumerate(self._retry_at) if 0.0 < at <= now]
            for i in due:
                self._retry_at[i] = 0.0  # its read succeeds, or reports and fails again
            skip = {i for i, at in enumerate(self._retry_at) if at > now}
            until = min([deadline, *(self._retry_at[i] for i in skip)])
            ready = self._poll(0.0 if due else max(0.0, until - now), skip)
            if ready or due:
                return sorted({*ready, *due})
            if time.monotonic() >= deadline:
                return []

    def _poll(self, timeout: float, skip: Collection[int]) -> list[int]:
        event = self._event
        if event is not None:
            end = time.monotonic() + timeout
            while True:
                event.clear()  # a frame queued from here on sets it again: none is missed
                ready = [i for i, bus in enumerate(self.buses)
                         if i not in skip and bus.pending]  # type: ignore[attr-defined]
                left = end - time.monotonic()
                if ready or left <= 0 or not event.wait(left):
                    return ready
        assert self._socks is not None
        socks = {sock: i for i, sock in enumerate(self._socks) if i not in skip}
        if not socks:
            time.sleep(timeout)
            return []
        try:
            readable = select.select(list(socks), [], [], timeout)[0]
        except (OSError, ValueError):  # a socket closed or failed: each read reports its own
            return sorted(socks.values())
        return [socks[sock] for sock in readable]

    def close(self) -> None:
        """No more wake-ups from the buses (in-process); idempotent."""
        if self._event is not None:
            for bus in self.buses:
                bus.remove_wakeup(self._event)  # type: ignore[attr-defined]


class FrameWriter:
    """Sends frames without ever blocking; a failure raises can.CanError (callers count it).

    On SocketCAN a full transmit queue fails at once (ENOBUFS, or EAGAIN when the socket's
    own buffer is full), as python-can's ``send(timeout=0)`` does, with one system call.
    """

    def __init__(self, bus: can.BusABC, fd: bool = False) -> None:
        self.bus = bus
        self.fd = fd
        self._sock = _raw_socket(bus)

    def send(self, cob_id: int, data: bytes) -> None:
        """An 11-bit data frame: classic, or CAN FD with bit rate switching when ``fd``."""
        if self.fd:
            self.send_message(can.Message(arbitration_id=cob_id, data=data,
                                          is_extended_id=False, is_fd=True,
                                          bitrate_switch=True))
            return
        if self._sock is None:
            self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False),
                          timeout=0)
            return
        self._send_raw(_CLASSIC_FRAME.pack(cob_id, len(data), data))

    def send_message(self, msg: can.Message) -> None:
        """Any frame python-can can describe (extended, remote, FD)."""
        if self._sock is None:
            self.bus.send(msg, timeout=0)
            return
        self._send_raw(build_can_frame(msg))

    def _send_raw(self, frame: bytes) -> None:
        try:
            self._sock.send(frame, socket.MSG_DONTWAIT)  # type: ignore[union-attr]
        except OSError as exc:  # ENOBUFS, EAGAIN, ENETDOWN, a closed socket
            raise can.CanOperationError(f"sending on {self.bus.channel_info}: {exc}",
                                        exc.errno) from exc


#: Oldest plausible arrival: older stamps come from another epoch (some interfaces count
#: from the adapter's power-on) or a wall-clock step, and are taken as "now".
MAX_FRAME_AGE = 10.0


def to_monotonic(offset: float, stamp: float, now: float) -> float:
    """A frame's ``time.time()`` stamp on the monotonic clock, never later than ``now``.

    ``offset`` is ``clock_offset()`` read once per batch. A frame without a plausible stamp
    (none, in the future, or more than MAX_FRAME_AGE old) is taken as arrived ``now``.
    """
    arrived = stamp + offset
    return arrived if now - MAX_FRAME_AGE < arrived <= now else now


def clock_offset() -> float:
    """``time.monotonic() - time.time()`` now: converts frame stamps to the monotonic clock."""
    return time.monotonic() - time.time()
