"""Joins the in-process channels (inproc.py) of two processes over one socket.

Why: ``rocoma-can demo`` simulates its drives. In the control loop's process, the
simulation of 12 drives took half of each 1 kHz cycle (the loop stepped it after its write,
in lockstep, because a simulator thread handing the GIL back and forth cost more). A robot's
drives compute in their own silicon; with the simulator in a process of its own over this
link, the loop's process pays only for the frames, as it would on a real bus.

A link has one endpoint on each channel it joins, in each process, and the channels are
matched by position in the list both sides give. A frame another endpoint of a channel
sends is packed (the Message is not copied) into the sending thread's buffer and written
to the socket at the end of its burst: a sender holding its buses' wake-ups
(``hold_wakeups``: the control loop's write on every bus, the simulator's answers) writes
one datagram for all of them at the first release, any other send at once. Each thread
writes what it packed, so one thread's frames arrive in the order it sent them, and
different threads' frames interleave as on a bus. The write never blocks: when the socket
is full (the other process stopped reading) the datagram is dropped and counted in
``tx_dropped``, as a SocketCAN socket drops what its full buffer cannot take; a sender
never waits for the other process.

On the other side each datagram's frames go to their channels' other endpoints, stamped
with their arrival (``time.time()``, as inproc.py stamps a send), every reader woken once
per datagram: by the link's receive thread (``start``), or by a thread of the caller's that
calls ``receive`` (the simulator's process: one thread reads the link and steps the drives,
with no hand-over between two). A frame that is not one (truncated, an unknown channel) is
counted in ``rx_bad`` and the rest of its datagram skipped.

The socket is one end of a ``SOCK_SEQPACKET`` pair (``socket.socketpair``): datagrams keep
their bounds, in order, and the other end closing (its process ended or died) ends the
receiving: ``closed`` is set and ``on_close`` called, so the side left can stop. A datagram
is frames, each ``FRAME`` (channel index, identifier, flags, DLC, data length) and its data.
"""
from __future__ import annotations

import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence

from can import Message

from ..protocol.wire import BRS, ERROR, ESI, EXTENDED, FD, REMOTE
from .inproc import InProcessBus, received

#: channel index, identifier, flags (wire.py), DLC, data length; the data follows
FRAME = struct.Struct("=BIBBB")
#: the largest datagram read: a burst of ~900 CAN FD frames of 64 bytes
MAX_DATAGRAM = 1 << 16
#: a datagram in the making is written once this long (the next frame could not fit)
FLUSH_AT = MAX_DATAGRAM - FRAME.size - 64
#: bytes the kernel may hold for the other process before a write is dropped, asked for;
#: Linux caps it at net.core.wmem_max (212,992 bytes on a stock kernel: a fraction of a
#: second of a 12-drive bench at 1 kHz)
SEND_BUFFER = 4 << 20
_SEND_FLAGS = socket.MSG_DONTWAIT | getattr(socket, "MSG_NOSIGNAL", 0)


class _LinkEnd(InProcessBus):
    """The link's endpoint on one channel: what the others send goes to the socket."""

    def __init__(self, link: InProcessLink, index: int, channel: str, fd: bool) -> None:
        self._link = link
        self._index = index
        super().__init__(channel=channel, fd=fd)

    def _deliver(self, msg: Message, wake: bool) -> bool:
        out = self._link.outgoing()
        data = msg.data
        out += FRAME.pack(self._index, msg.arbitration_id,
                          msg.is_extended_id | msg.is_remote_frame << 1
                          | msg.is_error_frame << 2 | msg.is_fd << 3
                          | msg.bitrate_switch << 4 | msg.error_state_indicator << 5,
                          msg.dlc, len(data))
        out += data
        if wake or len(out) > FLUSH_AT:
            self._link.write(out)
        return True

    def _wake(self) -> None:  # the release of a burst, on the thread that sent it
        out = self._link.outgoing()
        if out:
            self._link.write(out)


class InProcessLink:
    """``InProcessLink(sock, channels).start()``; see the module. ``fd``: the endpoints are
    CAN FD ones (what the channels' buses are)."""

    def __init__(self, sock: socket.socket, channels: Sequence[str], *, fd: bool = False,
                 on_close: Callable[[], None] | None = None,
                 name: str = "inproc-link") -> None:
        if not 0 < len(channels) <= 256:
            raise ValueError(f"a link joins 1 to 256 channels, got {len(channels)}")
        if len(set(map(str, channels))) != len(channels):
            raise ValueError(f"a link joins each channel once, got {list(channels)}")
        self._sock = sock
        self.channels = tuple(str(c) for c in channels)
        self.on_close = on_close
        self.tx_datagrams = self.tx_dropped = self.rx_frames = self.rx_bad = 0
        self.closed = threading.Event()
        # blocking, without a timeout: with one, CPython waits on a full socket even with
        # MSG_DONTWAIT (a sender would block), and ends a receive thread's read by raising
        sock.settimeout(None)
        self._poll = select.poll()
        self._poll.register(sock, select.POLLIN)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        except OSError:  # a platform that refuses: its default buffer
            pass
        self._local = threading.local()  # each sending thread's datagram in the making
        self._buf = bytearray(MAX_DATAGRAM)  # the receiving thread's
        self._ends: list[_LinkEnd] = []
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        try:
            for i, channel in enumerate(self.channels):
                self._ends.append(_LinkEnd(self, i, channel, fd))
        except BaseException:
            self.close()
            raise

    def start(self) -> InProcessLink:
        """Hand over what arrives on a receive thread of the link's own (else: ``receive``)."""
        self._thread.start()
        return self

    def outgoing(self) -> bytearray:
        """The calling thread's datagram in the making."""
        local = self._local
        try:
            out: bytearray = local.out
        except AttributeError:
            out = local.out = bytearray()
        return out

    def write(self, out: bytearray) -> None:
        """Send the datagram ``out`` and empty it."""
        try:
            self._sock.send(out, _SEND_FLAGS)
            self.tx_datagrams += 1
        except OSError:  # full (the other side is not reading), or closed: dropped
            self.tx_dropped += 1
        out.clear()

    def close(self) -> None:
        """Leave the channels and stop the receive thread (joined); idempotent. The socket
        is the caller's to close (the other side sees the close as the link's end)."""
        for end in self._ends:
            end.shutdown()
        try:
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the receive thread's recv
        except OSError:
            pass
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(2.0)

    def receive(self, timeout: float) -> int:
        """Wait up to ``timeout`` s for a datagram, then hand over it and every other one
        waiting; the number handed over (0 when the link has closed: see ``closed``)."""
        if self.closed.is_set():
            return 0
        try:  # (poll: select refuses descriptors past 1023)
            ready = self._poll.poll(max(0, round(timeout * 1000)))
        except OSError:  # closed meanwhile
            self._end()
            return 0
        count = 0
        while ready:
            try:
                n = self._sock.recv_into(self._buf, 0, socket.MSG_DONTWAIT)
            except BlockingIOError:
                break
            except OSError:
                n = 0
            if n == 0:  # the other end closed, or close() shut this one down
                self._end()
                break
            self._hand_over(n)
            count += 1
        return count

    def _run(self) -> None:
        try:
            while True:
                try:
                    n = self._sock.recv_into(self._buf)
                except OSError:
                    return
                if n == 0:
                    return
                self._hand_over(n)
        finally:
            self._end()

    def _end(self) -> None:
        if not self.closed.is_set():
            self.closed.set()
            if self.on_close is not None:
                self.on_close()

    def _hand_over(self, n: int) -> None:
        """The frames of the datagram in the first ``n`` bytes of the buffer, each to the
        other endpoints of its channel; every channel's readers are woken at the end."""
        buf, ends, size, unpack = self._buf, self._ends, FRAME.size, FRAME.unpack_from
        stamp = time.time()
        for end in ends:
            end.hold_wakeups()
        try:
            at = 0
            while at < n:
                if at + size > n:
                    self.rx_bad += 1
                    return
                index, cob_id, flags, dlc, length = unpack(buf, at)
                at += size
                if index >= len(ends) or at + length > n:
                    self.rx_bad += 1
                    return
                end = ends[index]
                end._broadcast(received(
                    stamp, cob_id, bool(flags & EXTENDED), bool(flags & REMOTE),
                    bool(flags & ERROR), end.channel_id, dlc, buf[at:at + length],
                    bool(flags & FD), bool(flags & BRS), bool(flags & ESI)))
                at += length
                self.rx_frames += 1
        finally:
            for end in ends:
                end.release_wakeups()
