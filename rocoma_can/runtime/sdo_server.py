"""The manager node's SDO server: canopen's, made strict where a lax server could let a
transfer take effect that must not (the node's objects switch controllers and e-stop)."""
from __future__ import annotations

import struct
from dataclasses import dataclass

import can
import canopen
from canopen.objectdictionary import NUMBER_TYPES
from canopen.sdo.constants import (
    BLOCK_SIZE_SPECIFIED,
    BLOCK_TRANSFER_RESPONSE,
    CRC_SUPPORTED,
    END_BLOCK_TRANSFER,
    EXPEDITED,
    INITIATE_BLOCK_TRANSFER,
    NO_MORE_BLOCKS,
    NO_MORE_DATA,
    REQUEST_BLOCK_UPLOAD,
    REQUEST_SEGMENT_DOWNLOAD,
    REQUEST_SEGMENT_UPLOAD,
    RESPONSE_BLOCK_UPLOAD,
    RESPONSE_UPLOAD,
    SDO_STRUCT,
    SIZE_SPECIFIED,
    START_BLOCK_UPLOAD,
)
from canopen.sdo.exceptions import SdoAbortedError
from canopen.sdo.server import SdoServer

from .objects import (
    ABORT_BLOCK_SIZE,
    ABORT_COMMAND_SPECIFIER,
    ABORT_SEQUENCE_NUMBER,
    ABORT_TOO_LONG,
    MAX_BLOCK_SIZE,
    MAX_DOWNLOAD,
    SEGMENT,
)


@dataclass
class _BlockUpload:
    """The open block upload: what is left to send and where the client's last ack put us."""
    data: bytes
    blksize: int      # segments per block, as the client asked (1..MAX_BLOCK_SIZE)
    crc: bool         # the client asked for a CRC and gets one
    acked: int = 0    # bytes the client has confirmed
    started: bool = False
    sent: int = 0     # segments sent in the block in flight (0 before the first)
    ended: bool = False  # the end (size of the last segment, CRC) has been sent


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
    - Block upload is served (CiA 301 block transfer, with the CRC when the client asks):
      the 1-2 KB JSON of 0x2140 is ~250 segments, one round trip each in a segmented upload,
      ~35 in blocks of MAX_BLOCK_SIZE. Each exchange between two processes on a
      busy host can stall for a second, so the status that matters most during a fault
      took 20 s (measured in a user-mode-linux guest) and failed when one stall passed the
      client's timeout. A block is sent as one burst, and the node's frames share the
      interface's transmit queue (first in, first out) with the control loop's SYNC and
      RPDOs, so a block is at most MAX_BLOCK_SIZE segments (~1 ms of a 1 Mbit/s bus); a
      client asking more gets 0x05040002 (invalid block size). A frame the interface
      refuses (its queue full) ends the burst early, and the client's ack of what it got
      resumes from there: the reader thread never waits on a full queue. A client asking
      the protocol switch threshold gets a normal upload when the data is not longer.
    - An answer the interface refuses is dropped (counted in ``refused_sends``), not
      raised: the client's timeout covers it.
    - Block download is refused with "command specifier not valid" (not supported).
    - An expedited download without the size indicated carries the object's own size
      (CiA 301: the trailing bytes are unspecified), so a one-byte e-stop written that way is
      an e-stop, not a length error.
    """

    _open: int | None = None  # REQUEST_SEGMENT_UPLOAD / _DOWNLOAD while one is open
    _block: _BlockUpload | None = None  # the block upload while one is open
    refused_sends = 0  # answers the interface refused (its transmit queue full)

    def __init__(self, rx_cobid: int, tx_cobid: int, node: canopen.LocalNode) -> None:
        super().__init__(rx_cobid, tx_cobid, node)

    def on_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) != 8:
            return
        ccs = data[0] & 0xE0
        continues = ccs in (REQUEST_SEGMENT_DOWNLOAD, REQUEST_SEGMENT_UPLOAD) or (
            ccs == REQUEST_BLOCK_UPLOAD and data[0] & 0x3 != INITIATE_BLOCK_TRANSFER)
        if not continues:  # the others name the object in bytes 1-3
            _, self._index, self._subindex = SDO_STRUCT.unpack_from(data)
        elif self._open is None and self._block is None:
            # a segment or block ack of no open transfer (another client's request ended
            # it): its abort names no object, not the one written last, which would read
            # as a refusal to the client that wrote it
            self._index, self._subindex = 0, 0
        super().on_request(can_id, data, timestamp)

    def init_upload(self, request: bytes) -> None:
        """canopen's, except that no data (an empty string) is a segmented upload of 0 bytes:
        an empty value is a value, not the "no data available" abort canopen sends."""
        self._open, self._buffer, self._block = None, None, None
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
        self._open, self._buffer, self._block = None, None, None
        command, index, subindex = SDO_STRUCT.unpack_from(request)
        if command & EXPEDITED and not command & SIZE_SPECIFIED:
            var = self._node.object_dictionary.get_variable(index, subindex)
            size = len(var) // 8 if var is not None and var.data_type in NUMBER_TYPES else 0
            if 1 <= size <= 4:
                request = bytes([command | SIZE_SPECIFIED | (4 - size) << 2]) + bytes(request[1:])
        if not command & EXPEDITED and command & SIZE_SPECIFIED \
                and struct.unpack_from("<L", request, 4)[0] > MAX_DOWNLOAD:
            raise SdoAbortedError(ABORT_TOO_LONG)  # announced too long: not even started
        super().init_download(request)
        if not command & EXPEDITED:
            self._open = REQUEST_SEGMENT_DOWNLOAD

    def segmented_download(self, command: int, request: bytes) -> None:
        if self._open != REQUEST_SEGMENT_DOWNLOAD:
            raise SdoAbortedError(ABORT_COMMAND_SPECIFIER)
        if len(self._buffer or b"") + SEGMENT - (command >> 1 & 0x7) > MAX_DOWNLOAD:
            self._open, self._buffer = None, None  # over: a later segment starts nothing
            raise SdoAbortedError(ABORT_TOO_LONG)
        if command & NO_MORE_DATA:
            self._open = None  # completed or refused: either way it is over
        super().segmented_download(command, request)

    def block_download(self, data: bytes) -> None:
        self._open, self._block = None, None
        raise SdoAbortedError(ABORT_COMMAND_SPECIFIER)

    def block_upload(self, data: bytes) -> None:
        """All four client commands of a block upload: initiate, start, ack, end."""
        subcommand = data[0] & 0x3
        if subcommand == INITIATE_BLOCK_TRANSFER:
            self._initiate_block_upload(data)
            return
        block = self._block
        if block is None:
            raise SdoAbortedError(ABORT_COMMAND_SPECIFIER)
        if subcommand == START_BLOCK_UPLOAD and not block.started:
            block.started = True
            self._send_block(block)
        elif subcommand == BLOCK_TRANSFER_RESPONSE and block.started:
            self._block_acked(block, ackseq=data[1], blksize=data[2])
        elif subcommand == END_BLOCK_TRANSFER and block.ended:
            self._block = None  # the client confirmed the end: done, nothing to answer
        else:
            raise SdoAbortedError(ABORT_COMMAND_SPECIFIER)

    def _initiate_block_upload(self, request: bytes) -> None:
        self._open, self._buffer, self._block = None, None, None
        command, index, subindex, blksize, pst = struct.unpack_from("<BHBBB", request)
        if not 1 <= blksize <= MAX_BLOCK_SIZE:
            raise SdoAbortedError(ABORT_BLOCK_SIZE)
        data = bytes(self._node.get_data(index, subindex, check_readable=True))
        if pst and len(data) <= pst:  # CiA 301: the server may switch to a normal upload
            self.init_upload(request)
            return
        crc = bool(command & CRC_SUPPORTED)
        self._block = _BlockUpload(data, blksize, crc)
        response = bytearray(8)
        SDO_STRUCT.pack_into(response, 0, RESPONSE_BLOCK_UPLOAD | BLOCK_SIZE_SPECIFIED
                             | (CRC_SUPPORTED if crc else 0), index, subindex)
        struct.pack_into("<L", response, 4, len(data))
        self.send_response(response)

    def _send_block(self, block: _BlockUpload) -> None:
        """Up to blksize segments from the last acked byte; the last one of the data says so.
        No data is one segment with nothing in it (the end says all 7 bytes are unused)."""
        left = len(block.data) - block.acked
        count = min(block.blksize, max(1, -(-left // SEGMENT)))
        block.sent = 0
        for seqno in range(1, count + 1):
            start = block.acked + (seqno - 1) * SEGMENT
            chunk = block.data[start:start + SEGMENT]
            last = start + SEGMENT >= len(block.data)
            frame = bytearray(8)
            frame[0] = seqno | (NO_MORE_BLOCKS if last else 0)
            frame[1:1 + len(chunk)] = chunk
            if not self._sent(frame):
                return  # queue full: the client's ack says how far it got
            block.sent = seqno

    def _block_acked(self, block: _BlockUpload, ackseq: int, blksize: int) -> None:
        if ackseq > block.sent:
            raise SdoAbortedError(ABORT_SEQUENCE_NUMBER)
        if not 1 <= blksize <= MAX_BLOCK_SIZE:
            raise SdoAbortedError(ABORT_BLOCK_SIZE)
        block.acked = min(len(block.data), block.acked + ackseq * SEGMENT)
        block.blksize = blksize
        if block.acked < len(block.data) or (not block.data and ackseq == 0):
            self._send_block(block)
            return
        block.sent, block.ended = 0, True
        unused = -len(block.data) % SEGMENT if block.data else SEGMENT
        crc = 0
        if block.crc:
            checksum = self.crc_cls()
            checksum.process(block.data)
            crc = checksum.final()
        response = bytearray(8)
        struct.pack_into("<BH", response, 0,
                         RESPONSE_BLOCK_UPLOAD | unused << 2 | END_BLOCK_TRANSFER, crc)
        self.send_response(response)

    def send_response(self, response: bytes | bytearray) -> None:
        """canopen's, without the exception when the interface refuses the frame (its
        transmit queue full): the client's timeout and retry deal with a lost answer, and
        the bus reader thread this runs on must not log a traceback per refused frame."""
        self._sent(response)

    def _sent(self, response: bytes | bytearray) -> bool:
        try:
            super().send_response(response)
        except can.CanError:
            self.refused_sends += 1
            return False
        return True

    def request_aborted(self, data: bytes) -> None:
        self._open, self._block = None, None
        super().request_aborted(data)

    def abort(self, abort_code: int = 0x08000000) -> None:
        self._open, self._block = None, None
        self._index = self._index or 0
        self._subindex = self._subindex or 0
        super().abort(abort_code)
