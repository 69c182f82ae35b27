"""The live view's front (rocoma_can/live/front.py) before a real foxglove-sdk server on
loopback: the protocol under both names, the SDK's own refusals passed on, and its bounds
(viewers at once, a silent handshake, a viewer that stops reading)."""
from __future__ import annotations

import base64
import contextlib
import json
import os
import socket
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import ExitStack

import pytest
from fixtures.running import DEMO_WAIT, wait_for

from rocoma_can.live import front
from rocoma_can.live.front import LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOLS, Front, offered, renamed

foxglove = pytest.importorskip("foxglove")
sync_client = pytest.importorskip("websockets.sync.client")
_errors = pytest.importorskip("websockets.exceptions")
ConnectionClosed, InvalidMessage = _errors.ConnectionClosed, _errors.InvalidMessage
InvalidStatus = _errors.InvalidStatus


@pytest.fixture
def sdk() -> Iterator[tuple[object, object]]:
    """The SDK's server on a free loopback port, with one JSON channel (its context)."""
    context = foxglove.Context()
    channel = foxglove.Channel("/numbers", schema={"type": "object"}, context=context)
    server = foxglove.start_server(name="front-test", host="127.0.0.1", port=0,
                                   context=context, message_backlog_size=4)
    try:
        yield server, channel
    finally:
        server.stop()


@pytest.fixture
def counts() -> Counter[str]:
    return Counter()


def _counter(counts: Counter[str]):
    """The front's ``count(what)``: one more of ``what``."""
    return lambda what: counts.update([what])


@pytest.fixture
def served(sdk, counts) -> Iterator[Front]:
    server, _ = sdk
    f = Front("127.0.0.1", 0, server.port, _counter(counts))
    try:
        yield f
    finally:
        f.close()


def _handshake(port: int, protocols: str) -> bytes:
    """A raw upgrade request offering ``protocols``; the answer's head (empty when the
    connection was closed or reset unanswered)."""
    key = base64.b64encode(os.urandom(16)).decode()
    answer = b""
    with socket.create_connection(("127.0.0.1", port), timeout=DEMO_WAIT) as sock, \
            contextlib.suppress(ConnectionResetError, BrokenPipeError):
        sock.sendall((f"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\n"
                      f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                      f"Sec-WebSocket-Version: 13\r\n"
                      f"Sec-WebSocket-Protocol: {protocols}\r\n\r\n").encode())
        while b"\r\n\r\n" not in answer:
            chunk = sock.recv(4096)
            if not chunk:
                break
            answer += chunk
    return answer.partition(b"\r\n\r\n")[0]


def test_the_headers_are_read_and_renamed():
    head = (b"GET / HTTP/1.1\r\nHost: x\r\nsec-websocket-protocol: a, foxglove.websocket.v1"
            b"\r\nSec-WebSocket-Protocol:b\r\n\r\n")
    assert offered(head) == ["a", LEGACY_SUBPROTOCOL, "b"]
    new = renamed(head, SDK_SUBPROTOCOLS[0])
    assert offered(new) == [SDK_SUBPROTOCOLS[0]]
    assert new.startswith(b"GET / HTTP/1.1\r\n") and new.endswith(b"\r\n\r\n")
    assert b"Host: x" in new


def test_the_sdk_alone_refuses_the_old_name_the_front_takes_both(sdk, served):
    """Why the front: the SDK answers the specification's name with 400; through the
    front a viewer gets the name it asked for and the SDK's messages."""
    server, channel = sdk
    assert b" 400 " in _handshake(server.port, LEGACY_SUBPROTOCOL).split(b"\r\n")[0]
    for asked in (LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOLS[0]):
        with sync_client.connect(f"ws://127.0.0.1:{served.port}", subprotocols=[asked],
                                 open_timeout=DEMO_WAIT) as ws:
            assert ws.subprotocol == asked
            info = json.loads(ws.recv(timeout=DEMO_WAIT))
            assert info["op"] == "serverInfo" and info["name"] == "front-test"
            advertised = json.loads(ws.recv(timeout=DEMO_WAIT))
            assert advertised["op"] == "advertise"
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 1, "channelId": advertised["channels"][0]["id"]}]}))
            wait_for(lambda: channel.has_sinks(), "the subscription", DEMO_WAIT)
            channel.log({"n": 7})
            data = ws.recv(timeout=DEMO_WAIT)
            assert isinstance(data, bytes) and json.loads(data[13:]) == {"n": 7}
    # a viewer offering both gets the SDK's; one offering neither, the SDK's 400
    both = _handshake(served.port, f"{LEGACY_SUBPROTOCOL}, {SDK_SUBPROTOCOLS[0]}")
    assert offered(both) == [SDK_SUBPROTOCOLS[0]]
    with pytest.raises(InvalidStatus, match="400"):
        sync_client.connect(f"ws://127.0.0.1:{served.port}", subprotocols=["other.v1"],
                            open_timeout=DEMO_WAIT)


def test_viewers_past_the_limit_are_closed_and_counted(served, counts, monkeypatch):
    monkeypatch.setattr(front, "MAX_VIEWERS", 2)
    with ExitStack() as held:
        for _ in range(2):
            held.enter_context(sync_client.connect(
                f"ws://127.0.0.1:{served.port}", subprotocols=[LEGACY_SUBPROTOCOL],
                open_timeout=DEMO_WAIT))
        with pytest.raises((InvalidMessage, ConnectionClosed)):  # closed before any answer
            sync_client.connect(f"ws://127.0.0.1:{served.port}",
                                subprotocols=[LEGACY_SUBPROTOCOL], open_timeout=DEMO_WAIT)
        assert counts["viewers_refused"] == 1
    # their places free again once they have gone
    wait_for(lambda: _handshake(served.port, LEGACY_SUBPROTOCOL).startswith(b"HTTP/1.1 101"),
             "a place for a new viewer", DEMO_WAIT)


def test_a_silent_connection_is_closed_after_the_handshake_wait(served, monkeypatch):
    monkeypatch.setattr(front, "HANDSHAKE_WAIT", 0.3)
    with socket.create_connection(("127.0.0.1", served.port), timeout=DEMO_WAIT) as sock:
        sock.sendall(b"GET / HTTP/1.1\r\n")  # and never the rest
        assert sock.recv(100) == b""  # closed by the front, bounded by the test's timeout


def test_a_head_past_the_limit_is_closed(served):
    with socket.create_connection(("127.0.0.1", served.port), timeout=DEMO_WAIT) as sock:
        try:
            sock.sendall(b"GET / HTTP/1.1\r\nX: " + b"y" * (front.MAX_HEAD + 8192))
            assert sock.recv(100) == b""
        except (BrokenPipeError, ConnectionResetError):  # closed with the rest unread
            pass


def test_a_viewer_that_stops_reading_is_cut_off_and_counted(sdk, counts, monkeypatch):
    """The front holds BUFFER bytes for a viewer at most; one that takes nothing for
    STALL_LIMIT s while bytes wait is cut off, and its SDK side is reset."""
    monkeypatch.setattr(front, "STALL_LIMIT", 0.5)
    server, channel = sdk
    f = Front("127.0.0.1", 0, server.port, _counter(counts))
    try:
        raw = socket.socket()
        raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        raw.connect(("127.0.0.1", f.port))
        with sync_client.connect(f"ws://127.0.0.1:{f.port}", sock=raw, max_queue=1,
                                 subprotocols=[LEGACY_SUBPROTOCOL], open_timeout=DEMO_WAIT,
                                 close_timeout=0.1) as ws:  # (its close finds it cut off)
            info = json.loads(ws.recv(timeout=DEMO_WAIT))
            assert info["op"] == "serverInfo"
            advertised = json.loads(ws.recv(timeout=DEMO_WAIT))
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 1, "channelId": advertised["channels"][0]["id"]}]}))
            wait_for(lambda: channel.has_sinks(), "the subscription", DEMO_WAIT)
            payload = {"x": "z" * 8192}
            stop = threading.Event()

            def flood() -> None:
                while not stop.is_set():
                    channel.log(payload)
                    time.sleep(0.001)
            thread = threading.Thread(target=flood, daemon=True)
            thread.start()
            try:  # the test's client reads nothing meanwhile
                wait_for(lambda: counts["viewers_stalled"] == 1, "the stalled viewer cut",
                         DEMO_WAIT)
                wait_for(lambda: not channel.has_sinks(), "the SDK without the viewer",
                         DEMO_WAIT)
            finally:
                stop.set()
                thread.join(DEMO_WAIT)
    finally:
        f.close()


def test_close_ends_every_viewer(sdk, counts):
    server, _ = sdk
    f = Front("127.0.0.1", 0, server.port, _counter(counts))
    with sync_client.connect(f"ws://127.0.0.1:{f.port}", subprotocols=[LEGACY_SUBPROTOCOL],
                             open_timeout=DEMO_WAIT) as ws:
        f.close()
        assert not [t for t in threading.enumerate() if t.name.startswith("foxglove-")
                    and t.is_alive()]
        with pytest.raises(ConnectionClosed):
            while True:  # the messages already sent, then the end
                ws.recv(timeout=DEMO_WAIT)


def test_an_address_taken_is_one_line(sdk, counts):
    server, _ = sdk
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        with pytest.raises(front.FrontError, match=r"cannot serve on 127\.0\.0\.1:\d+: "):
            Front("127.0.0.1", taken.getsockname()[1], server.port, _counter(counts))
    finally:
        taken.close()


def test_a_viewer_that_will_not_close_after_the_sdk_did_is_let_go(served, monkeypatch):
    """The viewer asks to close, the SDK answers and closes its side; a viewer that then
    keeps its connection open holds no thread or place for more than HANDSHAKE_WAIT."""
    monkeypatch.setattr(front, "HANDSHAKE_WAIT", 0.5)
    key = base64.b64encode(os.urandom(16)).decode()
    with socket.create_connection(("127.0.0.1", served.port), timeout=DEMO_WAIT) as sock:
        sock.sendall((f"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: "
                      f"Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                      f"Sec-WebSocket-Protocol: {LEGACY_SUBPROTOCOL}\r\n\r\n").encode())
        received = b""
        while b"\r\n\r\n" not in received:
            received += sock.recv(4096)
        assert received.startswith(b"HTTP/1.1 101")
        sock.sendall(bytes([0x88, 0x80]) + os.urandom(4))  # a masked close, no payload
        try:
            while sock.recv(65536):  # messages, the SDK's close, then its end
                pass
        except ConnectionResetError:
            pass
        wait_for(lambda: not [t for t in threading.enumerate()
                              if t.name == "foxglove-viewer" and t.is_alive()],
                 "the viewer's thread ended while it keeps its end open", DEMO_WAIT)


def test_no_thread_for_a_viewer_is_a_refusal_not_the_end(served, counts, monkeypatch):
    """A thread that cannot be started (a process limit) refuses that viewer, counted;
    the front accepts the next one and closes as usual."""
    failing = [True]
    start = threading.Thread.start

    def start_or_fail(thread: threading.Thread) -> None:
        if thread.name == "foxglove-viewer" and failing.pop() if failing else False:
            raise RuntimeError("can't start new thread")
        start(thread)
    monkeypatch.setattr(threading.Thread, "start", start_or_fail)
    with pytest.raises((InvalidMessage, ConnectionClosed)):  # closed before any answer
        sync_client.connect(f"ws://127.0.0.1:{served.port}",
                            subprotocols=[LEGACY_SUBPROTOCOL], open_timeout=DEMO_WAIT)
    assert counts["viewers_refused"] == 1
    with sync_client.connect(f"ws://127.0.0.1:{served.port}", subprotocols=[LEGACY_SUBPROTOCOL],
                             open_timeout=DEMO_WAIT) as ws:
        assert ws.subprotocol == LEGACY_SUBPROTOCOL
