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

import collections
import logging
import math
import socket
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import can
import canopen
from can.interfaces import VALID_INTERFACES

from ...spelling import did_you_mean
from .frame_io import READ_LIMIT, BusSelector, FrameReader, FrameWriter, clock_offset, to_monotonic

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


def unknown_interface(interface: str) -> str | None:
    """Why ``interface`` cannot be opened, before anything opens: a name python-can does not
    know (its own backends and the ones installed packages add, as ``inproc``), with the
    nearest it knows; None when it knows it. A typo in a config or on the command line is
    a usage error in one line, not the NotImplementedError python-can raises on opening."""
    if interface in VALID_INTERFACES:
        return None
    return (f"{interface!r} is no interface python-can knows"
            f"{did_you_mean(interface, VALID_INTERFACES)} (known: "
            f"{', '.join(sorted(VALID_INTERFACES))})")


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
    except NotImplementedError:  # a typo in --interface or the config's bus.interface
        raise OSError(f"cannot open CAN bus {interface}:{channel}: "
                      f"{unknown_interface(interface)}") from None
    except Exception as e:  # noqa: BLE001 - a backend that breaks as it starts (below)
        # python-can's adapter backends fail in their own ways when the vendor's library
        # is missing or a setting is: kvaser without canlib NameError, neovi without
        # python-ics ImportError, socketcand without host/port TypeError.
        raise OSError(f"cannot open CAN bus {interface}:{channel}: {type(e).__name__}: {e} "
                      f"(python-can's {interface} backend: is the adapter's library "
                      "installed?)") from e
    return enlarge_bus_buffer(bus)


#: A reader whose drain_now was called within this long leaves the reading to its caller
#: (the control loop) and checks again after as long (BusReader.drain_now).
DRAIN_STANDBY = 0.02


class BusReader:
    """The one thread that reads a bus and hands every frame to its listeners, in order.

    Listener calls run on this thread and must be quick. A listener that raises has its
    ``on_error`` called (when it has one) and the others still get the frame; errors are
    counted in ``listener_errors``. A bus that fails (interface down) is reported to every
    listener's ``on_error`` and read again every ``retry`` seconds.

    ``more``: further buses, each with its listeners, read by the same thread (all SocketCAN
    or all in-process: frame_io.BusSelector; ValueError otherwise). Every thread that waits
    on a bus costs a wake-up and a GIL hand-over per burst of frames, which the control
    loop of the same process waits behind; one thread for four buses pays it once. A bus
    that fails is reported to its own listeners only, and the others are still served.
    """

    def __init__(self, bus: can.BusABC, listeners: Sequence[can.Listener] = (), *,
                 more: Sequence[tuple[can.BusABC, Sequence[can.Listener]]] = (),
                 poll: float = 0.1, retry: float = 0.05, name: str = "can-reader") -> None:
        self.bus = bus
        self.buses = (bus, *(b for b, _ in more))
        self.listener_errors = 0
        self.bus_errors = 0
        self.exception: BaseException | None = None  # the last bus error, as Notifier has it
        self._errors_of = [0] * len(self.buses)  # per bus: the log says when each starts
        self._until = [-math.inf] * len(self.buses)  # per bus: see received_until
        self._listeners = [tuple(listeners), *(tuple(ls) for _, ls in more)]
        # per bus, the listeners drain_now may call on its caller's thread (``lock_free``)
        self._lock_free = [tuple(ls) for ls in self._listeners]
        # the others, each with its ``wants(msg)`` if it has one (looked up once, here)
        self._locking: list[tuple[tuple[can.Listener, Callable[[can.Message], bool] | None],
                                  ...]] = [() for _ in self._listeners]
        for index in range(len(self.buses)):
            self._split(index)
        # frames drain_now read for the locking listeners: this thread hands them over
        self._deferred: collections.deque[tuple[int, can.Listener, can.Message]] = \
            collections.deque()
        self._deferred_ready = threading.Event()
        self._poll, self._retry = poll, retry
        # One bus is waited on as several are where the interface allows it (SocketCAN,
        # in-process), so the wait is apart from the read and drain_now can read too.
        self._selector = BusSelector(self.buses, retry) \
            if more or BusSelector.supports(self.buses) else None
        self._readers = [FrameReader(bus) for bus in self.buses]
        # held by whoever reads and hands over (this thread, or drain_now's caller): frames
        # reach the listeners in order, never two batches of one bus at once
        self._handing = threading.Lock()
        self._drained_at = -math.inf  # the latest drain_now
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def add_listener(self, listener: can.Listener, bus: can.BusABC | None = None) -> None:
        """Also feed ``listener`` (the frames of ``bus``, default the first bus)."""
        index = 0 if bus is None else self.buses.index(bus)
        self._listeners[index] = (*self._listeners[index], listener)
        self._split(index)

    def _split(self, index: int) -> None:
        listeners = self._listeners[index]
        self._lock_free[index] = tuple(ls for ls in listeners if getattr(ls, "lock_free", False))
        self._locking[index] = tuple((ls, getattr(ls, "wants", None)) for ls in listeners
                                     if not getattr(ls, "lock_free", False))

    def received_until(self, bus: can.BusABC | None = None) -> float:
        """Every frame of ``bus`` (default: the first) that arrived (monotonic) before this
        has been handed to the listeners (by drain_now: to the ``lock_free`` ones; the
        others' are queued). A reader the scheduler starved (a frozen process,
        a loaded machine) lags behind its socket; a deadline judged on the cycle's clock
        alone would call heartbeats lost that arrived in time and wait unread
        (CanopenHardware judges against this). A failed interface delivers nothing: its
        bus's time moves on with each failed read, so deadlines pass."""
        return self._until[0 if bus is None else self.buses.index(bus)]

    @property
    def alive(self) -> bool:
        """The reader thread runs (it ends only on ``stop``)."""
        return self._thread.is_alive()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop and join the thread; idempotent (a shared reader is stopped by each of its
        buses' owners: the first call waits, the others find it stopped)."""
        self._stopping.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("CAN reader of %s did not stop within %.1f s",
                          ", ".join(b.channel_info for b in self.buses), timeout)
        if self._selector is not None:
            self._selector.close()

    def drain_now(self) -> bool:
        """Hand what waits on every bus now to the listeners, on the caller's thread: the
        control loop's, at the start of its read (CanopenHardware.read), so a cycle sees
        every frame that arrived before it even when the scheduler starves this reader's
        thread (a reader thread starved for a few cycles on a loaded machine left those
        cycles without TPDOs, and TPDO supervision e-stopped). Never waits: False,
        nothing read, when the thread is reading itself (it has the frames) or the
        interface cannot be read apart from its wait (python-can's ``virtual``). A bus that
        fails here is left to the thread to report.

        Only listeners that take no lock (``lock_free = True``: the hardware's, a deque
        append) are called here: the caller is the control loop, which must never wait for
        a lock another thread holds. The frames the others want (canopen's SDO client, NMT
        and EMCY consumers, which notify Conditions; a listener's ``wants(msg)`` says, or
        every frame) are queued for this reader's thread, in order, and it is woken for
        them: during the cycle's steady traffic, none.

        While drains come (within DRAIN_STANDBY) and every bus reads, the thread stands by,
        handing over only those queued frames: it no longer wakes for every burst to take
        the GIL from the loop, and cannot be starved while holding the buses. A bus that
        fails or waits for its retry ends the stand-by: the thread reads, reports the
        failure (its listeners' ``on_error``, ``bus_errors``, deadlines pass) and retries,
        as without drains. When the loop stops calling, the thread reads again within
        DRAIN_STANDBY."""
        selector = self._selector
        if selector is None or self._stopping.is_set() \
                or not self._handing.acquire(blocking=False):
            return False
        deferred, lock_free, locking = self._deferred, self._lock_free, self._locking
        queued = trouble = False
        try:
            for i, reader in enumerate(self._readers):
                if selector.failing(i):
                    trouble = True
                    continue
                before = time.monotonic()
                try:
                    batch = reader.read(0.0)
                except can.CanError:
                    trouble = True  # the thread reads it again and reports
                    continue
                self._hand_over(batch, i, before, lock_free[i])
                for listener, wants in locking[i]:
                    for msg in batch:
                        if wants is None or wants(msg):
                            deferred.append((i, listener, msg))
                            queued = True
        finally:
            self._handing.release()
        if not trouble:
            self._drained_at = time.monotonic()
        if queued or trouble:
            self._deferred_ready.set()
        return True

    def _hand_over_deferred(self) -> None:
        """The frames drain_now queued, to the listeners it could not call, in order (this
        thread, ``_handing`` held: nothing it reads itself overtakes them)."""
        self._deferred_ready.clear()
        deferred = self._deferred
        while deferred:
            index, listener, msg = deferred.popleft()
            self._deliver(msg, (listener,), index)

    def _run(self) -> None:
        if self._selector is not None:
            self._run_several(self._selector)
            return
        reader = self._readers[0]
        while not self._stopping.is_set():
            before = time.monotonic()
            try:
                with self._handing:  # (drain_now never reads this interface)
                    batch = reader.read(self._poll)
                    self._hand_over(batch, 0, before)
            except can.CanError as exc:
                if self._stopping.is_set():
                    return
                self._bus_failed(exc, 0, before)
                self._stopping.wait(self._retry)

    def _run_several(self, selector: BusSelector) -> None:
        readers, until = self._readers, self._until
        while not self._stopping.is_set():
            since = time.monotonic()
            if since - self._drained_at < DRAIN_STANDBY:  # the loop reads: stand by
                self._deferred_ready.wait(DRAIN_STANDBY)
                with self._handing:
                    self._hand_over_deferred()
                continue
            ready = selector.wait(self._poll)
            with self._handing:
                self._hand_over_deferred()  # what drains queued: before anything newer
                if time.monotonic() - self._drained_at < DRAIN_STANDBY:
                    continue  # a drain came during the wait: the loop reads these
                for i, reader in enumerate(readers):
                    if i not in ready:
                        if not selector.failing(i):
                            until[i] = max(until[i], since)  # nothing waited at the wait's end
                        continue
                    before = time.monotonic()
                    try:
                        batch = reader.read(0.0)
                    except can.CanError as exc:
                        if self._stopping.is_set():
                            return
                        self._bus_failed(exc, i, before)
                        selector.failed(i)  # read again after ``retry``, the others meanwhile
                        continue
                    self._hand_over(batch, i, before)

    def _hand_over(self, batch: list[can.Message], index: int, before: float,
                   listeners: Sequence[can.Listener] | None = None) -> None:
        """``batch`` read from bus ``index`` by a read that began at ``before``, to
        ``listeners`` (default: all of the bus's)."""
        if listeners is None:
            listeners = self._listeners[index]
        for msg in batch:
            self._deliver(msg, listeners, index)
        if len(batch) < READ_LIMIT:  # read until empty: all that arrived before is handed over
            until = before
        else:  # a full batch (a backlog): frames come in order, so up to the last one's
            until = to_monotonic(clock_offset(), batch[-1].timestamp, time.monotonic())
        if until > self._until[index]:  # (a drain_now may have read past the thread's wait)
            self._until[index] = until

    def _deliver(self, msg: can.Message, listeners: Sequence[can.Listener],
                 index: int) -> None:
        for listener in listeners:
            try:
                listener.on_message_received(msg)
            except Exception as exc:  # noqa: BLE001 - one listener must not end reading
                self.listener_errors += 1
                self._report(exc, (listener,), index)

    def _bus_failed(self, exc: can.CanError, index: int, before: float) -> None:
        self.bus_errors += 1
        self.exception = exc
        self._until[index] = before  # a failed interface delivers nothing: deadlines pass
        self._report(exc, self._listeners[index], index)

    def _report(self, exc: Exception, listeners: Sequence[can.Listener], index: int) -> None:
        self._errors_of[index] += 1
        if self._errors_of[index] in (1, 10, 100, 1000, 10000):
            log.warning("CAN reader on %s: %r (%d errors on this bus so far)",
                        self.buses[index].channel_info, exc, self._errors_of[index])
        for listener in listeners:
            try:
                listener.on_error(exc)
            except Exception:  # noqa: BLE001 - counted above; nothing more to do
                pass


def readers_for(buses: Sequence[tuple[can.BusABC, Sequence[can.Listener]]], *,
                name: str = "can-reader") -> list[BusReader]:
    """Readers for several buses, each with its listeners: one thread for all of them
    (named ``name``) when one thread can wait on them together (all SocketCAN or all
    in-process), else one thread per bus (``name`` and the bus's channel). On a shared
    reader a slow listener delays every bus's frames, and ``bus_errors``/``exception``
    count all its buses: listeners must be quick (the hardware's only append to a deque)."""
    if len(buses) > 1 and BusSelector.supports([bus for bus, _ in buses]):
        (first, listeners), *more = buses
        return [BusReader(first, listeners, more=more, name=name)]
    readers: list[BusReader] = []
    try:
        for bus, listeners in buses:
            readers.append(BusReader(bus, listeners, name=f"{name} {bus.channel_info}"))
    except BaseException:
        for reader in readers:
            reader.stop()
        raise
    return readers


class CanopenFrames(can.Listener):
    """What a canopen Network's services (SDO clients and servers, NMT) are given: 11-bit
    data frames only, and an NMT command only as its two bytes (CiA 301). canopen's own
    listener passes 29-bit frames on as if they were 11-bit ones (an extended 0x664 would
    be served as an SDO request, an extended 0x581 taken as an SDO answer) and logs an error
    for every short NMT frame.

    Only COB-IDs a service subscribed to are passed on: the cycle's TPDOs, most of a bus's
    traffic, have no subscriber here (the hardware decodes them itself), and
    ``Network.notify`` would still feed each to canopen's node scanner, which nothing in
    rocoma-can uses (``Network.scanner`` stays empty)."""

    def __init__(self, network: canopen.Network) -> None:
        self.network = network
        self._subscribers = network.subscribers  # canopen fills this dict in place

    def wants(self, msg: can.Message) -> bool:
        """Whether a service takes ``msg`` (no lock: BusReader.drain_now asks on the
        control loop's thread, and queues for the reader thread only what is wanted)."""
        cob_id = msg.arbitration_id
        return cob_id in self._subscribers and not (
            msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame
            or (cob_id == 0 and msg.dlc != 2))

    def on_message_received(self, msg: can.Message) -> None:
        if self.wants(msg):
            self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)


#: frames the canopen services sent, held for the cycle to record (a recording only)
SENT_HELD = 4096


class RecordedNetwork(canopen.Network):
    """canopen's Network that, once ``sent`` is set (a recording of the bus's frames),
    keeps each frame it sent there with its stamp. Its senders are other threads (SDO
    workers, NMT): the cycle moves the frames into the recording (BusPort.end_of_write),
    so a recording ring keeps one producer."""

    sent: collections.deque[tuple[can.Message, float]] | None = None

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        super().send_message(can_id, data, remote)
        sent = self.sent
        if sent is not None:
            sent.append((can.Message(arbitration_id=can_id, data=data, is_remote_frame=remote,
                                     is_extended_id=can_id > 0x7FF), time.time()))


class CanopenBus:
    """A bus (opened here or lent by the caller), a canopen Network and the bus's reader.

    ``read=False``: no reader yet; ``start_reading`` gives several buses one reader thread
    (every listener is attached before the first frame is read)."""

    def __init__(self, bus: can.BusABC, own_bus: bool = False, *, read: bool = True) -> None:
        self.bus = bus
        self.own_bus = own_bus
        enlarge_bus_buffer(bus)  # a lent bus too
        self.network = RecordedNetwork(bus)  # not connect(): BusReader replaces its Notifier
        self.listeners: list[can.Listener] = [CanopenFrames(self.network)]
        self.reader: BusReader | None = BusReader(bus, self.listeners) if read else None
        self.writer = FrameWriter(bus)  # the cycle's frames: never blocks, one system call

    def add_listener(self, listener: can.Listener) -> None:
        self.listeners.append(listener)
        if self.reader is not None:
            self.reader.add_listener(listener, self.bus)

    def close(self) -> None:
        """Stop the reader (joins its thread, shared or not); shut the bus only if it was
        opened here."""
        if self.reader is not None:
            self.reader.stop()
        if self.own_bus:
            self.bus.shutdown()


def start_reading(buses: Sequence[CanopenBus], *, name: str = "can-reader") -> None:
    """Start reading buses opened with ``read=False`` (readers_for: one thread if it can)."""
    waiting = [cb for cb in buses if cb.reader is None]
    for reader in readers_for([(cb.bus, tuple(cb.listeners)) for cb in waiting], name=name):
        for cb in waiting:
            if cb.bus in reader.buses:
                cb.reader = reader
