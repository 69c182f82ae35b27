"""The manager node's SDO server: canopen's, made strict where a lax server could let a
transfer take effect that must not (the node's objects switch controllers and e-stop)."""
from __future__ import annotations

import struct

import canopen
from canopen.objectdictionary import NUMBER_TYPES
from canopen.sdo.constants import (
    EXPEDITED,
    NO_MORE_DATA,
    REQUEST_SEGMENT_DOWNLOAD,
    REQUEST_SEGMENT_UPLOAD,
    RESPONSE_UPLOAD,
    SDO_STRUCT,
    SIZE_SPECIFIED,
)
from canopen.sdo.exceptions import SdoAbortedError
from canopen.sdo.server import SdoServer

from .objects import ABORT_COMMAND_SPECIFIER


class StrictSdoServer(SdoServer):
    """canopen's SDO server without the ways a transfer could take effect that must not, and
    without a traceback in the log for a request it cannot serve (a hostile or garbled bus
    must not flood the log; it gets an abort, or nothing when the frame is no SDO request).

    - A frame that is not 8 bytes is not an SDO request (CiA 301) and is ignored.
    - Segments continue only the transfer open in their own direction: a download segment
      never appends to an upload's data, and a segmented download that was aborted (by either
      side) or has completed is forgotten, so a stray last segment cannot complete it.
    - Every abort carries the multiplexer of the request it answers (0000:00 when no request
      named one), so the abort itself cannot fail.
    - Block download is refused with "command specifier not valid" (not supported; block
      upload falls back to a normal upload, which CiA 301 allows).
    - An expedited download without the size indicated carries the object's own size
      (CiA 301: the trailing bytes are unspecified), so a one-byte e-stop written that way is
      an e-stop, not a length error.
    """

    _open: int | None = None  # REQUEST_SEGMENT_UPLOAD / _DOWNLOAD while one is open

    def __init__(self, rx_cobid: int, tx_cobid: int, node: canopen.LocalNode) -> None:
        super().__init__(rx_cobid, tx_cobid, node)

    def on_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) != 8:
            return
        if data[0] & 0xE0 not in (REQUEST_SEGMENT_DOWNLOAD, REQUEST_SEGMENT_UPLOAD):
            _, self._index, self._subindex = SDO_STRUCT.unpack_from(data)
        super().on_request(can_id, data, timestamp)

    def init_upload(self, request: bytes) -> None:
        """canopen's, except that no data (an empty string) is a segmented upload of 0 bytes:
        an empty value is a value, not the "no data available" abort canopen sends."""
        self._open, self._buffer = None, None
        _, index, subindex = SDO_STRUCT.unpack_from(request)
        data = self._node.get_data(index, subindex, check_readable=True)
        response = bytearray(8)
        if 1 <= len(data) <= 4:
            command = RESPONSE_UPLOAD | SIZE_SPECIFIED | EXPEDITED | (4 - len(data)) << 2
            response[4:4 + len(data)] = data
        else:
            command = RESPONSE_UPLOAD | SIZE_SPECIFIED
            struct.pack_into("<L", response, 4, len(data))
            self._buffer, self._toggle = bytearray(data), 0
            self._open = REQUEST_SEGMENT_UPLOAD
        SDO_STRUCT.pack_into(response, 0, command, index, subindex)
        self.send_response(response)

    def segmented_upload(self, command: int) -> None:
        if self._open != REQUEST_SEGMENT_UPLOAD:
            raise SdoAbortedError(ABORT_COMMAND_SPECIFIER)
        super().segmented_upload(command)
        if not self._buffer:
            self._open = None

    def init_download(self, request: bytes) -> None:
        self._open, self._buffer = None, None
        command, index, subindex = SDO_STRUCT.unpack_from(request)
        if command & EXPEDITED and not command & SIZE_SPECIFIED:
            var = self._node.object_dictionary.get_variable(index, subindex)
            size = len(var) // 8 if var is not None and var.data_type in NUMBER_TYPES else 0
            if 1 <= size <= 4:
                request = bytes([command | SIZE_SPECIFIED | (4 - size) << 2]) + bytes(request[1:])
        super().init_download(request)
        if not command & EXPEDITED:
            self._open = REQUEST_SEGMENT_DOWNLOAD

    def segmented_download(self, command: int, request: bytes) -> None:
        if self._open != REQUEST_SEGMENT_DOWNLOAD:
            raise SdoAbortedError(ABORT_COMMAND_SPECIFIER)
        if command & NO_MORE_DATA:
            self._open = None  # completed or refused: either way it is over
        super().segmented_download(command, request)

    def block_download(self, data: bytes) -> None:
        self._open = None
        raise SdoAbortedError(ABORT_COMMAND_SPECIFIER)

    def request_aborted(self, data: bytes) -> None:
        self._open = None
        super().request_aborted(data)

    def abort(self, abort_code: int = 0x08000000) -> None:
        self._open = None
        self._index = self._index or 0
        self._subindex = self._subindex or 0
        super().abort(abort_code)
