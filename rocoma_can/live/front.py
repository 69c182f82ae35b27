"""The live view's listening socket, in front of foxglove-sdk's server: the Foxglove
WebSocket protocol under both of its names.

The protocol's specification, and the viewers written to it before the SDK (Foxglove Studio,
Lichtblick, PlotJuggler's Foxglove bridge, ws-protocol's clients), ask for the subprotocol
``foxglove.websocket.v1``; foxglove-sdk's server takes only the name the SDK later gave the
same protocol, ``foxglove.sdk.v1`` (or ``foxglove.sdk.v1.1``), and answers any other
handshake with HTTP 400. The messages are the same under both names. So the view's port is
this front's: it reads each connection's HTTP upgrade request (bounded in size and time),
hands a request that offers only the old name to the SDK's server (on a loopback port of its
own) as asking for the new one, and gives the SDK's answer back naming the old one, the
name the viewer asked for; from then on the bytes pass unchanged both ways, but for a call of
a stop service, which reaches the SDK as an empty JSON call whatever its encoding, size or
framing (stop_calls.py: the SDK would refuse it before the stop).

Bounds: one thread per viewer moves its bytes (a live view's tens of kB/s), at most
MAX_VIEWERS at once (more are closed at once); each direction holds at most BUFFER bytes,
so a viewer that stops reading stops the front reading the SDK's socket for it, whose
outbox then fills and drops messages as for a viewer of the SDK's own (``viewer_drops``); a
viewer that took no byte for STALL_LIMIT s while some waited for it is cut off. A viewer
that goes without closing leaves the SDK's side reset, so the SDK's own record of it is
what the server counts (``viewers_gone``), as for a viewer connected to it directly.
"""
from __future__ import annotations

import re
import selectors
import socket
import struct
import threading
import time
from collections.abc import Callable

from .stop_calls import StopCalls, without_extensions

#: the subprotocol names of the one protocol: the SDK's, and the specification's
SDK_SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.sdk.v1.1")
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
#: viewers served at once; a connection past them is closed unread
MAX_VIEWERS = 16
#: the longest HTTP head (request or answer) read, bytes
MAX_HEAD = 16384
#: s a connection has for its upgrade request, and the SDK for its answer
HANDSHAKE_WAIT = 5.0
#: bytes held per direction: more waits in the kernel's buffers, then in the SDK's outbox
BUFFER = 65536
#: s a viewer may take nothing while bytes wait for it before it is cut off
STALL_LIMIT = 60.0
#: how often the threads look whether the front is closing, s
POLL = 0.2

_PROTOCOL_HEADER = re.compile(rb"^sec-websocket-protocol[ \t]*:(.*)$", re.I | re.M)
_RESET = struct.pack("ii", 1, 0)  # SO_LINGER on, 0 s: close() sends a reset


class FrontError(OSError):
    """The front cannot listen (the address taken or unknown): its one line."""


def offered(head: bytes) -> list[str]:
    """The subprotocols an upgrade request offers, in its order (every such header)."""
    return [name.strip() for value in _PROTOCOL_HEADER.findall(head)
            for name in value.decode("latin-1").split(",") if name.strip()]


def renamed(head: bytes, name: str) -> bytes:
    """``head`` with its subprotocol header(s) replaced by one naming ``name`` only."""
    lines = [line for line in head.split(b"\r\n") if not _PROTOCOL_HEADER.match(line)]
    return b"\r\n".join([*lines[:1], f"Sec-WebSocket-Protocol: {name}".encode(),
                         *lines[1:]])


def _read_head(sock: socket.socket, deadline: float) -> tuple[bytes, bytes]:
    """An HTTP head (through its blank line) and the bytes read after it; ValueError when
    it is longer than MAX_HEAD, ends first or takes past ``deadline``."""
    data = b""
    while b"\r\n\r\n" not in data:
        left = deadline - time.monotonic()
        if left <= 0 or len(data) > MAX_HEAD:
            raise ValueError("no HTTP head in time or in size")
        sock.settimeout(left)
        chunk = sock.recv(4096)
        if not chunk:
            raise ValueError("closed before its HTTP head ended")
        data += chunk
    head, _, rest = data.partition(b"\r\n\r\n")
    if len(head) > MAX_HEAD:
        raise ValueError("HTTP head too long")
    return head + b"\r\n\r\n", rest


class Front:
    """Listens on ``host``:``port`` (0: a free port) and hands every viewer to the SDK's
    server on 127.0.0.1:``upstream``, renaming the old subprotocol (see module);
    ``count(what)`` is told of ``viewers_refused`` (past MAX_VIEWERS) and
    ``viewers_stalled`` (cut off after STALL_LIMIT)."""

    def __init__(self, host: str, port: int, upstream: int,
                 count: Callable[[str], None]) -> None:
        self._upstream, self._count = upstream, count
        try:
            family, kind, proto, _, address = socket.getaddrinfo(
                host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
            listener = socket.socket(family, kind, proto)
            try:
                listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                listener.bind(address)
                listener.listen(MAX_VIEWERS)
            except OSError:
                listener.close()
                raise
        except OSError as exc:  # socket.gaierror too
            raise FrontError(f"cannot serve on {host}:{port}: {exc.strerror or exc}") \
                from None
        listener.settimeout(POLL)
        self._listener = listener
        self.host, self.port = listener.getsockname()[:2]
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._viewers: set[threading.Thread] = set()
        self._accepting = threading.Thread(target=self._accept, name="foxglove-front",
                                           daemon=True)
        self._accepting.start()

    def close(self) -> None:
        """Stop listening and cut every viewer; bounded: a viewer's thread ends within POLL,
        one still in its handshake within HANDSHAKE_WAIT."""
        self._stop.set()
        self._accepting.join(2 * POLL + 1.0)
        self._listener.close()
        with self._lock:
            viewers = list(self._viewers)
        for thread in viewers:
            thread.join(2 * POLL + HANDSHAKE_WAIT)

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:  # closed under it, or out of descriptors: try again
                if self._stop.wait(POLL):
                    return
                continue
            with self._lock:
                self._viewers = {t for t in self._viewers if t.is_alive()}
                served = len(self._viewers) < MAX_VIEWERS
                if served:
                    thread = threading.Thread(target=self._serve, args=(conn,),
                                              name="foxglove-viewer", daemon=True)
                    try:
                        thread.start()
                    except RuntimeError:  # no thread to be had (a process limit)
                        served = False
                    else:
                        self._viewers.add(thread)
            if not served:
                self._count("viewers_refused")
                conn.close()

    def _serve(self, viewer: socket.socket) -> None:
        sdk: socket.socket | None = None
        try:
            deadline = time.monotonic() + HANDSHAKE_WAIT
            request, early = _read_head(viewer, deadline)
            request = without_extensions(request)  # plain frames, for the stop calls
            calls = StopCalls()
            names = offered(request)
            legacy = LEGACY_SUBPROTOCOL in names and not any(
                n in SDK_SUBPROTOCOLS for n in names)
            if legacy:
                request = renamed(request, SDK_SUBPROTOCOLS[0])
            sdk = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            # a small window: a stalled viewer fills it soon, and the SDK's outbox drops
            sdk.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, BUFFER)
            sdk.settimeout(max(0.0, deadline - time.monotonic()) + HANDSHAKE_WAIT)
            sdk.connect(("127.0.0.1", self._upstream))
            sdk.sendall(request + calls.from_viewer(early))
            answer, rest = _read_head(sdk, time.monotonic() + HANDSHAKE_WAIT)
            calls.from_sdk(rest)
            if legacy and offered(answer):
                answer = renamed(answer, LEGACY_SUBPROTOCOL)
            viewer.settimeout(HANDSHAKE_WAIT)
            # as small towards the viewer: what it has not taken waits in the SDK's outbox
            viewer.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, BUFFER)
            _keep_alive(viewer)
            viewer.sendall(answer + rest)
            self._splice(viewer, sdk, calls)
        except (OSError, ValueError):
            _reset(sdk)  # the viewer or the SDK went during the handshake: nothing to keep
        finally:
            viewer.close()
            if sdk is not None:
                sdk.close()

    def _splice(self, viewer: socket.socket, sdk: socket.socket, calls: StopCalls) -> None:
        """Bytes both ways until both ends have closed; a viewer that fails, stalls or
        leaves without its half of a close leaves the SDK's side reset. The viewer's bytes
        go through ``calls`` (a stop call reaches the SDK in the form it takes), the SDK's
        are read by it (the stop services' ids)."""
        splice = _Splice(viewer, sdk, calls)
        with selectors.DefaultSelector() as selector:
            while not self._stop.is_set():
                if splice.finished():
                    return
                now = time.monotonic()
                if splice.stalled(now):
                    self._count("viewers_stalled")
                    break
                if splice.close_overdue(now):
                    break
                splice.watch(selector)
                try:
                    splice.step(selector)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:  # reset, or a shutdown of an end already gone
                    break
            _reset(sdk)  # failed, stalled or closing: the SDK sees the viewer gone


class _Splice:
    """One viewer's connection and the SDK's, spliced (``Front._splice``): what waits to
    be written to each end, which end still sends, and the viewer's last progress."""

    def __init__(self, viewer: socket.socket, sdk: socket.socket, calls: StopCalls) -> None:
        viewer.setblocking(False)
        sdk.setblocking(False)
        self.viewer, self.sdk, self.calls = viewer, sdk, calls
        self.other = {viewer: sdk, sdk: viewer}
        self.waiting = {viewer: bytearray(), sdk: bytearray()}  # bytes to write to each
        self.reading = {viewer: True, sdk: True}
        self.taken = time.monotonic()  # the viewer's last progress, or when bytes began waiting
        self.sdk_done: float | None = None  # when the SDK's side had ended, all delivered
        self.watched: dict[socket.socket, int] = {}

    def finished(self) -> bool:
        """Both ends closed and everything delivered."""
        return not (self.reading[self.viewer] or self.reading[self.sdk]
                    or self.waiting[self.viewer] or self.waiting[self.sdk])

    def stalled(self, now: float) -> bool:
        """The viewer has taken none of the bytes waiting for it for STALL_LIMIT."""
        return bool(self.waiting[self.viewer]) and now - self.taken > STALL_LIMIT

    def close_overdue(self, now: float) -> bool:
        """The SDK's side ended and was delivered HANDSHAKE_WAIT ago, and the viewer, whose
        turn it is to close, has not."""
        if self.reading[self.sdk] or self.waiting[self.viewer]:
            return False
        self.sdk_done = now if self.sdk_done is None else self.sdk_done
        return now - self.sdk_done > HANDSHAKE_WAIT

    def watch(self, selector: selectors.BaseSelector) -> None:
        """Each end watched for what it can do now: read while the other end's queue has
        room, write while its own holds bytes."""
        for sock in (self.viewer, self.sdk):
            events = (selectors.EVENT_READ if self.reading[sock]
                      and len(self.waiting[self.other[sock]]) < BUFFER else 0) | (
                selectors.EVENT_WRITE if self.waiting[sock] else 0)
            if events != self.watched.get(sock, 0):
                if not events:
                    selector.unregister(sock)
                elif sock in self.watched:
                    selector.modify(sock, events)
                else:
                    selector.register(sock, events)
                self.watched[sock] = events
                if not events:
                    del self.watched[sock]

    def step(self, selector: selectors.BaseSelector) -> None:
        """What the ends are ready for, done (OSError: an end failed)."""
        for key, mask in selector.select(POLL):
            sock = self.viewer if key.fileobj is self.viewer else self.sdk
            if mask & selectors.EVENT_WRITE:
                self._write(sock)
            if mask & selectors.EVENT_READ:
                self._read(sock)

    def _write(self, sock: socket.socket) -> None:
        waiting = self.waiting[sock]
        del waiting[:sock.send(waiting)]
        if sock is self.viewer:
            self.taken = time.monotonic()
        if not waiting and not self.reading[self.other[sock]]:
            sock.shutdown(socket.SHUT_WR)  # the other end's close

    def _read(self, sock: socket.socket) -> None:
        data = sock.recv(BUFFER)
        to = self.other[sock]
        if not data:
            self.reading[sock] = False
            if not self.waiting[to]:
                to.shutdown(socket.SHUT_WR)
            return
        if to is self.viewer and not self.waiting[to]:
            self.taken = time.monotonic()
        if sock is self.viewer:
            data = self.calls.from_viewer(data)
        else:
            self.calls.from_sdk(data)
        self.waiting[to] += data


def _keep_alive(sock: socket.socket) -> None:
    """TCP keep-alive probes: a viewer whose machine vanished (no reset will come) is found
    gone within about a minute, not held for ever."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    for option, value in (("TCP_KEEPIDLE", 30), ("TCP_KEEPINTVL", 10), ("TCP_KEEPCNT", 3)):
        if hasattr(socket, option):
            sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, option), value)


def _reset(sock: socket.socket | None) -> None:
    """Close with a reset (the SDK takes it as a viewer gone without closing)."""
    if sock is None:
        return
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, _RESET)
    except OSError:
        pass
    sock.close()
