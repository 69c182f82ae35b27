"""One python-can bus with a canopen Network on it, and the bus's one reader thread.

canopen is used only for what it is good at (EDS import, SDO, NMT); the cycle sends and
receives raw frames on the same bus. ``BusReader`` is the only reader of the bus and feeds
canopen's listener and the driver's receive path alike. It replaces python-can's Notifier
(which canopen's ``Network.connect`` would start) for three reasons: it reads every waiting
frame after one wait (frame_io: a third of the system calls per frame), a listener that
raises cannot end it, and a failing interface is retried at a bounded pace instead of in a
busy loop.
"""
from __future__ import annotations

import logging
import math
import socket
import threading
import time
from collections.abc import Sequence
from typing import Any

import can
import canopen

from .frame_io import READ_LIMIT, FrameReader, FrameWriter, clock_offset, to_monotonic

log = logging.getLogger(__name__)

#: Receive buffer for SocketCAN sockets: a frame costs ~1 KiB of socket memory, so the
#: default (~200 KiB) holds a few hundred frames, a fraction of a second of a busy bus; a
#: stalled reader (GC, scheduler) would lose TPDOs and heartbeats.
RECEIVE_BUFFER_BYTES = 4 << 20


def enlarge_receive_buffer(sock: socket.socket, size: int = RECEIVE_BUFFER_BYTES) -> None:
    """Best effort: SO_RCVBUFFORCE (root / CAP_NET_ADMIN) or SO_RCVBUF, which the kernel caps
    at net.core.rmem_max (~200 KiB by default: raise it for a process without the
    capability)."""
    force = getattr(socket, "SO_RCVBUFFORCE", 33)  # Linux's value; Python may not name it
    for option in (force, socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, option, size)
            break
        except OSError:
            continue
    got = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)  # Linux reports twice the set
    if got < size:
        log.debug("CAN receive buffer %d bytes, not %d: raise net.core.rmem_max or run with "
                  "CAP_NET_ADMIN", got, size)


def enlarge_bus_buffer(bus: can.BusABC) -> can.BusABC:
    """The large receive buffer for a bus with a socket (SocketCAN); others are left alone.

    Every reader of ours can lag: the manager node's and the CLI's SDO readers, the
    simulator, recorders. A frame that arrives at a full socket is dropped by the kernel,
    and for SDO one lost segment is a transfer that is never answered."""
    sock = getattr(bus, "socket", None)
    if isinstance(sock, socket.socket):
        enlarge_receive_buffer(sock)
    return bus


def open_bus(interface: str, channel: str, bitrate: int | None = None,
             **kwargs: Any) -> can.BusABC:
    """A python-can bus that ignores ~/.canrc and CAN_* variables (the config says it all),
    with the large receive buffer on SocketCAN."""
    if bitrate is not None:
        kwargs["bitrate"] = bitrate
    try:
        bus = can.Bus(interface=interface, channel=channel, ignore_config=True, **kwargs)
    except (OSError, can.CanError) as e:
        raise OSError(f"cannot open CAN bus {interface}:{channel}: {e}") from e
    return enlarge_bus_buffer(bus)


class BusReader:
    """The one thread that reads a bus and hands every frame to its listeners, in order.

    Listener calls run on this thread and must be quick. A listener that raises has its
    ``on_error`` called (when it has one) and the others still get the frame; errors are
    counted in ``listener_errors``. A bus that fails (interface down) is reported to every
    listener's ``on_error`` and read again every ``retry`` seconds.
    """

    def __init__(self, bus: can.BusABC, listeners: Sequence[can.Listener] = (), *,
                 poll: float = 0.1, retry: float = 0.05, name: str = "can-reader") -> None:
        self.bus = bus
        self.listener_errors = 0
        self.bus_errors = 0
        self.exception: BaseException | None = None  # the last bus error, as Notifier has it
        # Every frame that arrived (monotonic) before this has been handed to the listeners.
        # A reader the scheduler starved (a frozen process, a loaded machine) lags behind its
        # socket; a deadline judged on the cycle's clock alone would call heartbeats lost
        # that arrived in time and wait unread (CanopenHardware judges against this).
        self.received_until = -math.inf
        self._listeners = tuple(listeners)
        self._poll, self._retry = poll, retry
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def add_listener(self, listener: can.Listener) -> None:
        self._listeners = (*self._listeners, listener)

    @property
    def alive(self) -> bool:
        """The reader thread runs (it ends only on ``stop``)."""
        return self._thread.is_alive()

    def stop(self, timeout: float = 2.0) -> None:
        self._stopping.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("CAN reader on %s did not stop within %.1f s",
                          self.bus.channel_info, timeout)

    def _run(self) -> None:
        reader = FrameReader(self.bus)
        while not self._stopping.is_set():
            before = time.monotonic()
            try:
                batch = reader.read(self._poll)
            except can.CanError as exc:
                if self._stopping.is_set():
                    return
                self.bus_errors += 1
                self.exception = exc
                self._report(exc, None)
                # a failed interface delivers nothing: deadlines may pass, as they should
                self.received_until = before
                self._stopping.wait(self._retry)
                continue
            for msg in batch:
                for listener in self._listeners:
                    try:
                        listener.on_message_received(msg)
                    except Exception as exc:  # noqa: BLE001 - one listener must not end reading
                        self.listener_errors += 1
                        self._report(exc, listener)
            if len(batch) < READ_LIMIT:  # read until empty: all that arrived before is handed over
                self.received_until = before
            else:  # a full batch (a backlog): frames come in order, so up to the last one's
                self.received_until = to_monotonic(clock_offset(), batch[-1].timestamp,
                                                   time.monotonic())

    def _report(self, exc: Exception, only: can.Listener | None) -> None:
        if self.listener_errors + self.bus_errors in (1, 10, 100, 1000, 10000):
            log.warning("CAN reader on %s: %r (%d listener errors, %d bus errors so far)",
                        self.bus.channel_info, exc, self.listener_errors, self.bus_errors)
        for listener in (only,) if only is not None else self._listeners:
            try:
                listener.on_error(exc)
            except Exception:  # noqa: BLE001 - counted above; nothing more to do
                pass


class CanopenBus:
    """A bus (opened here or lent by the caller), a canopen Network and the bus's reader."""

    def __init__(self, bus: can.BusABC, own_bus: bool = False) -> None:
        self.bus = bus
        self.own_bus = own_bus
        enlarge_bus_buffer(bus)  # a lent bus too
        self.network = canopen.Network(bus)  # not connect(): BusReader replaces its Notifier
        self.reader = BusReader(bus, self.network.listeners)
        self.writer = FrameWriter(bus)  # the cycle's frames: never blocks, one system call

    def add_listener(self, listener: can.Listener) -> None:
        self.reader.add_listener(listener)

    def close(self) -> None:
        """Stop the reader (joins its thread); shut the bus only if it was opened here."""
        self.reader.stop()
        if self.own_bus:
            self.bus.shutdown()
