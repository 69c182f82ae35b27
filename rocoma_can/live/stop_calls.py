"""What the live view's front (front.py) reads of the bytes it passes between a viewer and
foxglove-sdk's server: enough of the WebSocket framing (RFC 6455, section 5.2) and of the
Foxglove protocol that a call of a stop service reaches the SDK in the one form the SDK takes.

Why: the SDK refuses a service call whose encoding is not the service's ("Unsupported
encoding": a viewer that calls /rocoma/estop with ``protobuf``, ``JSON`` or none), closes
the connection on a message past its size limit, and fails a frame it cannot read, all
before our handler runs: the stop would never happen, and a stop must act whatever it
carries (rocoma_can/stop_surfaces.py). So the front knows a stop call by its service alone
(the ids the SDK advertises for /rocoma/estop and /rocoma/failproof, read from the SDK's
``advertiseServices``) and hands the SDK, in its place, the same call as an empty JSON
request (same service, same call id): the SDK runs our handler, which stops and answers the
viewer. Nothing of the call but its service id and call id is read; the rest of the message,
however long and however framed, is dropped as it comes.

Everything else passes unchanged. The bytes are read as they come, held at most while a
binary message's first CALL_HEAD bytes arrive (HOLD bounds that), and the SDK's text
messages are read for the advertisement up to ADVERTISEMENT bytes. The front asks the SDK
for no WebSocket extension (``without_extensions``), so the frames are plain.
"""
from __future__ import annotations

import json
import re
import struct
from collections.abc import Iterator

#: the stop services, as the live view advertises them (server.py: /rocoma/<command>)
STOP_SERVICES = ("/rocoma/estop", "/rocoma/failproof")
#: the Foxglove protocol's binary opcode of a viewer's service call request
SERVICE_CALL_REQUEST = 0x02
#: what a call shows before it is judged: opcode, service id, call id (bytes)
CALL_HEAD = 9
#: bytes of a viewer's binary message held at most while its CALL_HEAD arrive (frames of a
#: byte each: headers of 6 bytes); past it the message passes as it is
HOLD = 4096
#: the longest text message of the SDK read for the stop services' ids
ADVERTISEMENT = 1 << 20

_FIN, _OPCODE, _MASKED = 0x80, 0x0F, 0x80
_CONTINUATION, _TEXT, _BINARY = 0x0, 0x1, 0x2
_EXTENSIONS_HEADER = re.compile(rb"^sec-websocket-extensions[ \t]*:.*$", re.I | re.M)


def without_extensions(head: bytes) -> bytes:
    """An upgrade request with no WebSocket extension asked for (permessage-deflate would
    make the frames unreadable here)."""
    return b"\r\n".join(line for line in head.split(b"\r\n")
                        if not _EXTENSIONS_HEADER.match(line))


def canonical_call(service_id: int, call_id: int) -> bytes:
    """The stop call the SDK takes: one final binary frame, masked (a client's frames are)
    with the all-zero key, of an empty JSON request."""
    payload = struct.pack("<BIII", SERVICE_CALL_REQUEST, service_id, call_id, 4) + b"json"
    return bytes((_FIN | _BINARY, _MASKED | len(payload))) + b"\0\0\0\0" + payload


class _Frames:
    """One direction's frames as its bytes come. ``take(data)`` yields ("head", bytes) for a
    frame's whole header, ("data", bytes) for each piece of its payload and ("end", b"")
    when the payload has all come; while an event is handled, ``fin``, ``opcode`` and
    ``key`` are its frame's and ``at`` is where a data piece begins in the payload."""

    def __init__(self) -> None:
        self._head = bytearray()
        self._left = 0
        self.fin = self.opcode = self.at = 0
        self.key = b""

    def take(self, data: bytes) -> Iterator[tuple[str, bytes]]:
        pos = 0
        while pos < len(data):
            if self._left:
                piece = data[pos:pos + self._left]
                pos += len(piece)
                yield "data", piece
                self.at += len(piece)
                self._left -= len(piece)
                if not self._left:
                    yield "end", b""
                continue
            self._head.append(data[pos])
            pos += 1
            if len(self._head) < self._header_size():
                continue
            head, self._head = bytes(self._head), bytearray()
            self._left = self._read(head)
            yield "head", head
            if not self._left:
                yield "end", b""

    def _header_size(self) -> int:
        head = self._head
        if len(head) < 2:
            return 2
        code = head[1] & 0x7F
        return 2 + (2 if code == 126 else 8 if code == 127 else 0) + (
            4 if head[1] & _MASKED else 0)

    def _read(self, head: bytes) -> int:
        self.fin, self.opcode, self.at = head[0] & _FIN, head[0] & _OPCODE, 0
        code = head[1] & 0x7F
        ext = 2 if code == 126 else 8 if code == 127 else 0
        length = code if not ext else struct.unpack_from(">H" if ext == 2 else ">Q", head, 2)[0]
        self.key = head[2 + ext:6 + ext] if head[1] & _MASKED else b""
        return int(length)

    @property
    def control(self) -> bool:
        """A ping, pong or close: it may come between the frames of a message."""
        return bool(self.opcode & 0x8)

    def unmask(self, piece: bytes) -> bytes:
        """A data piece (beginning at ``at``) as sent, before its masking."""
        key, at = self.key, self.at
        return piece if not key else bytes(b ^ key[(at + k) % 4] for k, b in enumerate(piece))


class StopCalls:
    """One viewer's connection as the front passes it (see module): ``from_sdk`` reads the
    SDK's bytes for the stop services' ids, ``from_viewer`` returns what of the viewer's
    bytes to hand the SDK."""

    def __init__(self) -> None:
        self.stop_ids: dict[int, str] = {}  # service id -> name, as the SDK advertised them
        self.calls = 0  # stop calls handed on in the canonical form
        self._sdk = _Frames()
        self._text: bytearray | None = None  # the SDK's text message being read
        self._viewer = _Frames()
        # the viewer's current data message: "probe" (a binary one, held until its head
        # is read), "pass", or "drop" (the rest of a stop call already handed on)
        self._mode = "pass"
        self._held = bytearray()  # the probed message's bytes as they came
        self._call = bytearray()  # its first CALL_HEAD payload bytes, unmasked

    # --- the SDK's side: only read ---------------------------------------------------------
    def from_sdk(self, data: bytes) -> None:
        frames = self._sdk
        for kind, piece in frames.take(data):
            if frames.control:
                continue
            if kind == "head":
                if frames.opcode == _TEXT:
                    self._text = bytearray()
                elif frames.opcode == _BINARY:
                    self._text = None  # nothing to read in it
            elif kind == "data" and self._text is not None:
                if len(self._text) + len(piece) > ADVERTISEMENT:
                    self._text = None  # no advertisement of ours is that long
                else:
                    self._text += piece
            elif frames.fin:
                self._text_done()

    def _text_done(self) -> None:
        text, self._text = self._text, None
        try:
            message = json.loads(bytes(text)) if text else None
        except ValueError:
            return
        if not isinstance(message, dict):
            return
        if message.get("op") == "advertiseServices":
            for service in message.get("services") or ():
                if isinstance(service, dict) and service.get("name") in STOP_SERVICES \
                        and isinstance(service.get("id"), int):
                    self.stop_ids[service["id"]] = service["name"]
        elif message.get("op") == "unadvertiseServices":
            for sid in message.get("serviceIds") or ():
                if isinstance(sid, int):
                    self.stop_ids.pop(sid, None)

    # --- the viewer's side: passed, a stop call made canonical -----------------------------
    def from_viewer(self, data: bytes) -> bytes:
        frames, out = self._viewer, bytearray()
        for kind, piece in frames.take(data):
            if frames.control:  # as it is, also between the frames of a message (in
                self._forward(piece, out, held=True)  # its place while one is held)
                continue
            if kind == "head":
                if frames.opcode in (_TEXT, _BINARY):  # a message begins
                    if self._mode == "probe":  # one left unfinished: as it was
                        out += self._held
                    self._mode = "probe" if frames.opcode == _BINARY else "pass"
                    self._held, self._call = bytearray(), bytearray()
                self._forward(piece, out)
            elif kind == "data":
                if self._mode == "probe" and len(self._call) < CALL_HEAD:
                    self._call += frames.unmask(piece[:CALL_HEAD - len(self._call)])
                self._forward(piece, out)
                if self._mode == "probe" and (len(self._call) >= CALL_HEAD
                                              or len(self._held) > HOLD):
                    self._judge(out)
            else:  # a frame's end; the message's with its last frame
                if self._mode == "probe" and (frames.fin or len(self._held) > HOLD):
                    self._judge(out)
                if frames.fin:
                    self._mode = "pass"
        return bytes(out)

    def _forward(self, piece: bytes, out: bytearray, held: bool = False) -> None:
        """A piece of the current message where its mode says; ``held``: one that is not
        the message's own (a control frame), never dropped."""
        if self._mode == "probe":
            self._held += piece
        elif self._mode == "pass" or held:
            out += piece

    def _judge(self, out: bytearray) -> None:
        """The held message's head is read (or all there will be of it): a stop call is
        handed on in the canonical form and the rest of it dropped; anything else goes on
        as it came."""
        call = bytes(self._call)
        if len(call) >= 5 and call[0] == SERVICE_CALL_REQUEST:
            service_id = struct.unpack_from("<I", call, 1)[0]
            if service_id in self.stop_ids:
                call_id = struct.unpack_from("<I", call.ljust(CALL_HEAD, b"\0"), 5)[0]
                out += canonical_call(service_id, call_id)
                self.calls += 1
                self._mode, self._held = "drop", bytearray()
                return
        out += self._held
        self._mode, self._held = "pass", bytearray()
