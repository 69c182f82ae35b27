"""The live view's front and the stop calls it passes (rocoma_can/live/stop_calls.py), on the
bytes themselves: WebSocket frames as a viewer sends them (masked, fragmented, with pings
between, cut into any chunks by TCP) and as the SDK sends them. A running view is driven in
tests/safety/test_every_stop_surface.py; here the rule is checked against every framing
hypothesis finds."""
from __future__ import annotations

import json
import struct

from hypothesis import given, settings
from hypothesis import strategies as st

from rocoma_can.live.stop_calls import (
    HOLD,
    SERVICE_CALL_REQUEST,
    StopCalls,
    canonical_call,
    without_extensions,
)

ESTOP_ID, FAILPROOF_ID, SWITCH_ID = 7, 8, 3
TEXT, BINARY, CONTINUATION, PING = 0x1, 0x2, 0x0, 0x9


def frame(opcode: int, payload: bytes, fin: bool = True, key: bytes = b"\x11\x22\x33\x44"
          ) -> bytes:
    """One frame as RFC 6455 writes it (masked with ``key``, none for b"")."""
    n = len(payload)
    mask = 0x80 if key else 0
    size = (bytes((mask | n,)) if n < 126 else bytes((mask | 126,)) + struct.pack(">H", n)
            if n < 1 << 16 else bytes((mask | 127,)) + struct.pack(">Q", n))
    body = bytes(b ^ key[k % 4] for k, b in enumerate(payload)) if key else payload
    return bytes(((0x80 if fin else 0) | opcode,)) + size + key + body


def message(opcode: int, payload: bytes, cuts: list[int] | tuple[int, ...] = (),
            key: bytes = b"\x11\x22\x33\x44") -> bytes:
    """A message in frames cut at ``cuts`` (offsets into the payload), a ping after each."""
    points = sorted({c for c in cuts if 0 < c < len(payload)})
    pieces = [payload[a:b] for a, b in zip([0, *points], [*points, len(payload)])]
    out = b""
    for k, piece in enumerate(pieces):
        out += frame(opcode if k == 0 else CONTINUATION, piece, fin=k == len(pieces) - 1,
                     key=key)
        if k < len(pieces) - 1:
            out += frame(PING, b"p", key=key)
    return out


def call(service: int, call_id: int, encoding: bytes, payload: bytes) -> bytes:
    return struct.pack("<BIII", SERVICE_CALL_REQUEST, service, call_id,
                       len(encoding)) + encoding + payload


def messages_of(data: bytes) -> list[tuple[int, bytes]]:
    """(opcode, payload) of each data message in ``data`` (whole frames), pings left out."""
    out, pos, current = [], 0, None
    while pos < len(data):
        b0, b1 = data[pos], data[pos + 1]
        pos += 2
        n = b1 & 0x7F
        if n == 126:
            n, pos = struct.unpack_from(">H", data, pos)[0], pos + 2
        elif n == 127:
            n, pos = struct.unpack_from(">Q", data, pos)[0], pos + 8
        key = data[pos:pos + 4] if b1 & 0x80 else b""
        pos += len(key)
        body = data[pos:pos + n]
        pos += n
        if key:
            body = bytes(b ^ key[k % 4] for k, b in enumerate(body))
        if b0 & 0x08:
            continue
        current = (b0 & 0x0F, body) if b0 & 0x0F else (current[0], current[1] + body)
        if b0 & 0x80:
            out.append(current)
    return out


def passed(gate: StopCalls, data: bytes, chunks: list[int]) -> bytes:
    """``data`` fed in pieces cut at ``chunks``; what the gate hands on."""
    points = sorted({c for c in chunks if 0 < c < len(data)})
    return b"".join(gate.from_viewer(data[a:b])
                    for a, b in zip([0, *points], [*points, len(data)]))


def gate() -> StopCalls:
    g = StopCalls()
    g.from_sdk(frame(TEXT, json.dumps({"op": "advertiseServices", "services": [
        {"id": SWITCH_ID, "name": "/rocoma/switch"}, {"id": ESTOP_ID, "name": "/rocoma/estop"},
        {"id": FAILPROOF_ID, "name": "/rocoma/failproof"}]}).encode(), key=b""))
    return g


ENCODINGS = st.sampled_from([b"json", b"JSON", b"protobuf", b"", b"\xff\xfe", b"cbor"])
PAYLOADS = st.one_of(st.binary(max_size=300), st.sampled_from(
    [b"", b"{}", b'{"x": nul', b"\xff\xfe\xc3(", b"[1, 2]"]))


@st.composite
def traffic(draw, stops: bool):
    """(the viewer's bytes, the messages the SDK must get) for a run of messages."""
    data, want = b"", []
    for _ in range(draw(st.integers(1, 6))):
        kind = draw(st.sampled_from(["text", "binary", "call"] + ["stop"] * stops))
        if kind == "text":
            payload, opcode = json.dumps({"op": "subscribe", "n": draw(st.integers())}
                                         ).encode(), TEXT
        elif kind == "binary":
            payload, opcode = draw(st.binary(max_size=40)), BINARY
        else:
            service = draw(st.sampled_from([ESTOP_ID, FAILPROOF_ID])) if kind == "stop" \
                else draw(st.sampled_from([SWITCH_ID, 99]))
            call_id = draw(st.integers(0, 2**32 - 1))
            payload, opcode = call(service, call_id, draw(ENCODINGS), draw(PAYLOADS)), BINARY
        cuts = draw(st.lists(st.integers(0, len(payload)), max_size=4))
        key = draw(st.sampled_from([b"\x11\x22\x33\x44", b"\0\0\0\0", b"\xff\x01\x80\x7f"]))
        data += message(opcode, payload, cuts, key)
        want.append((opcode, canonical_call(*struct.unpack_from("<II", payload, 1))[6:]
                     if kind == "stop" else payload))
    return data, want


@settings(max_examples=300, derandomize=True, deadline=None)
@given(traffic(stops=False), st.lists(st.integers(0, 2000), max_size=8))
def test_a_viewer_that_calls_no_stop_passes_byte_for_byte(sent, chunks):
    data, _ = sent
    assert passed(gate(), data, chunks) == data


@settings(max_examples=300, derandomize=True, deadline=None)
@given(traffic(stops=True), st.lists(st.integers(0, 2000), max_size=8))
def test_every_stop_call_reaches_the_sdk_as_one_empty_json_call_in_its_place(sent, chunks):
    """Whatever its encoding, payload, framing and chunking: the same service and call id,
    in the same place among the viewer's messages; the others as they were."""
    data, want = sent
    assert messages_of(passed(gate(), data, chunks)) == want


def test_a_stop_call_of_megabytes_is_dropped_as_it_comes():
    g = gate()
    big = message(BINARY, call(ESTOP_ID, 5, b"protobuf", b"\xff" * (3 << 20)), cuts=[1 << 20])
    out = b"".join(g.from_viewer(big[k:k + 65536]) for k in range(0, len(big), 65536))
    assert out == canonical_call(ESTOP_ID, 5) + frame(PING, b"p") and g.calls == 1


def test_a_stop_call_cut_short_still_names_its_service():
    """Five bytes name the service: the stop goes on, with what came of its call id (the
    rest zeros)."""
    g = gate()
    assert g.from_viewer(frame(BINARY, bytes((SERVICE_CALL_REQUEST,)) + struct.pack(
        "<I", FAILPROOF_ID) + b"\x09")) == canonical_call(FAILPROOF_ID, 9)
    short = frame(BINARY, bytes((SERVICE_CALL_REQUEST, ESTOP_ID)))  # no whole service id
    assert g.from_viewer(short) == short


def test_a_message_of_endless_empty_frames_passes_as_it_was_after_hold():
    g = gate()
    empties = frame(BINARY, b"", fin=False) + frame(CONTINUATION, b"", fin=False) * (
        HOLD // 6 + 1)
    rest = frame(CONTINUATION, call(ESTOP_ID, 1, b"json", b""))
    assert g.from_viewer(empties + rest) == empties + rest


def test_the_ids_are_the_sdks_whatever_its_chunks_and_other_messages():
    g = StopCalls()
    sdk = (frame(BINARY, b"\x01" + b"x" * 300, key=b"")
           + frame(TEXT, b'{"op": "serverInfo", "name": "rocoma-can"}', key=b"")
           + message(TEXT, json.dumps({"op": "advertiseServices", "services": [
               {"id": 41, "name": "/rocoma/estop"}, {"id": 42, "name": "/rocoma/failproof"},
               {"id": 43, "name": "/rocoma/clear"}]}).encode(), cuts=[10, 50], key=b""))
    for k in range(0, len(sdk), 7):
        g.from_sdk(sdk[k:k + 7])
    assert g.stop_ids == {41: "/rocoma/estop", 42: "/rocoma/failproof"}
    g.from_sdk(frame(TEXT, b'{"op": "unadvertiseServices", "serviceIds": [41]}', key=b""))
    assert g.stop_ids == {42: "/rocoma/failproof"}
    g.from_sdk(frame(TEXT, b"[not json", key=b"") + frame(TEXT, b"[1]", key=b""))
    assert g.stop_ids == {42: "/rocoma/failproof"}


def test_no_call_is_a_stop_before_the_sdk_advertised_it():
    data = frame(BINARY, call(ESTOP_ID, 1, b"protobuf", b""))
    assert StopCalls().from_viewer(data) == data


def test_the_front_asks_the_sdk_for_no_extension():
    head = (b"GET / HTTP/1.1\r\nHost: x\r\nSec-WebSocket-Extensions: permessage-deflate; "
            b"client_max_window_bits\r\nsec-websocket-extensions: x\r\nUpgrade: websocket\r\n\r\n")
    assert without_extensions(head) == (b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\n"
                                        b"\r\n")
