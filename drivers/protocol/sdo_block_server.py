"""SDO block upload, the server's side (CiA 301), for any canopen SdoServer: the manager
node's (rocoma_can/node/sdo_server.py) and the simulated drive's (drivers/sim/objects.py).

canopen's SdoServer answers every block command with a normal upload: a client that opened
a block upload of a value longer than its protocol switch threshold then gets a transfer
CiA 301 does not allow it to receive, and its start, acks and end are taken as new upload
requests. Stock clients (CANopenNode, canopen's BlockUploadStream) ask for 127 segments per
block, so any size 1..127 is served. Sequence numbers start at 1 in every block; the client's
ack names the last segment it got in order, and the next block resumes after it (a lost
segment is sent again, never skipped). The end carries the number of unused bytes of the
last segment and, when the client asked, the CRC over the whole value.

How the segments of a block leave is the server's choice (``_send_segments``): here all at
once, as a drive's controller sends them back to back; the manager node paces them, since
its frames share a transmit queue with the control loop's.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import can
from canopen.sdo.constants import (
    ABORT_INVALID_BLOCK_SIZE,
    ABORT_INVALID_COMMAND_SPECIFIER,
    ABORT_INVALID_SEQUENCE_NUMBER,
    BLOCK_SIZE_SPECIFIED,
    BLOCK_TRANSFER_RESPONSE,
    CRC_SUPPORTED,
    END_BLOCK_TRANSFER,
    INITIATE_BLOCK_TRANSFER,
    NO_MORE_BLOCKS,
    REQUEST_BLOCK_UPLOAD,
    RESPONSE_BLOCK_UPLOAD,
    SDO_STRUCT,
    START_BLOCK_UPLOAD,
)
from canopen.sdo.exceptions import SdoAbortedError
from canopen.sdo.server import SdoServer

#: The most segments a block may have (CiA 301: the sequence number is 7 bits, 0 unused).
MAX_BLKSIZE = 127
SEGMENT = 7  # bytes of data in one segment (the frame's first byte is the sequence number)


@dataclass
class BlockUpload:
    """The open block upload: what is left to send and where the client's last ack put us."""
    data: bytes
    blksize: int      # segments per block, as the client asked (1..MAX_BLKSIZE)
    crc: bool         # the client asked for a CRC and gets one
    acked: int = 0    # bytes the client has confirmed
    started: bool = False
    count: int = 0    # segments in the block in flight (0 before the first)
    sent: int = 0     # of those, sent so far
    ended: bool = False  # the end (size of the last segment, CRC) has been sent

    def next_segment(self) -> bytes | None:
        """The frame of the block's next unsent segment, None when all are sent. No data is
        one segment with nothing in it (the end says all 7 bytes are unused)."""
        if self.sent >= self.count:
            return None
        seqno = self.sent + 1
        start = self.acked + self.sent * SEGMENT
        chunk = self.data[start:start + SEGMENT]
        frame = bytearray(8)
        frame[0] = seqno | (NO_MORE_BLOCKS if start + SEGMENT >= len(self.data) else 0)
        frame[1:1 + len(chunk)] = chunk
        return bytes(frame)

    def new_block(self) -> None:
        left = len(self.data) - self.acked
        self.count = min(self.blksize, max(1, -(-left // SEGMENT)))
        self.sent = 0


def is_block_continuation(command: int) -> bool:
    """A block upload's start, ack or end: bytes 1-3 carry no multiplexer."""
    return command & 0xE0 == REQUEST_BLOCK_UPLOAD and command & 0x3 != INITIATE_BLOCK_TRANSFER


class BlockUploadServer(SdoServer):
    """canopen's SdoServer with block upload served. A request that opens another transfer
    (or an abort from either side) ends the open block upload."""

    _block: BlockUpload | None = None

    def __init__(self, rx_cobid: int, tx_cobid: int, node: Any) -> None:
        """``node``: a canopen LocalNode, or anything with its object_dictionary, get_data
        and set_data (the simulated drive's objects)."""
        super().__init__(rx_cobid, tx_cobid, node)

    def on_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) >= 1 and not is_block_continuation(data[0]):
            self._block = None
        super().on_request(can_id, data, timestamp)

    def block_upload(self, data: bytes) -> None:
        """All four client commands of a block upload: initiate, start, ack, end."""
        subcommand = data[0] & 0x3
        if subcommand == INITIATE_BLOCK_TRANSFER:
            self._initiate_block_upload(data)
            return
        block = self._block
        if block is None:
            raise SdoAbortedError(ABORT_INVALID_COMMAND_SPECIFIER)
        if subcommand == START_BLOCK_UPLOAD and not block.started:
            block.started = True
            block.new_block()
            self._send_segments(block)
        elif subcommand == BLOCK_TRANSFER_RESPONSE and block.started:
            self._block_acked(block, ackseq=data[1], blksize=data[2])
        elif subcommand == END_BLOCK_TRANSFER and block.ended:
            self._block = None  # the client confirmed the end: done, nothing to answer
        else:
            raise SdoAbortedError(ABORT_INVALID_COMMAND_SPECIFIER)

    def _initiate_block_upload(self, request: bytes) -> None:
        self._block = None
        command, index, subindex, blksize, pst = struct.unpack_from("<BHBBB", request)
        self._index, self._subindex = index, subindex  # what an abort names
        if not 1 <= blksize <= MAX_BLKSIZE:
            raise SdoAbortedError(ABORT_INVALID_BLOCK_SIZE)
        data = bytes(self._node.get_data(index, subindex, check_readable=True))
        if pst and len(data) <= pst:  # CiA 301: the server may switch to a normal upload
            self.init_upload(request)
            return
        crc = bool(command & CRC_SUPPORTED)
        self._block = BlockUpload(data, blksize, crc)
        response = bytearray(8)
        SDO_STRUCT.pack_into(response, 0, RESPONSE_BLOCK_UPLOAD | BLOCK_SIZE_SPECIFIED
                             | (CRC_SUPPORTED if crc else 0), index, subindex)
        struct.pack_into("<L", response, 4, len(data))
        self.send_response(response)

    def _send_segments(self, block: BlockUpload) -> None:
        """Send what is left of the block in flight. Here all of it, back to back, up to the
        first frame the interface refuses: the client's ack after its timeout names the
        last segment it got, and the next block resumes from there."""
        while (frame := block.next_segment()) is not None:
            if not self._sent(frame):
                return
            block.sent += 1

    def _sent(self, frame: bytes) -> bool:
        """Whether the interface took the frame."""
        try:
            self.send_response(frame)
        except can.CanError:
            return False
        return True

    def _block_acked(self, block: BlockUpload, ackseq: int, blksize: int) -> None:
        if ackseq > block.sent:
            raise SdoAbortedError(ABORT_INVALID_SEQUENCE_NUMBER)
        if not 1 <= blksize <= MAX_BLKSIZE:
            raise SdoAbortedError(ABORT_INVALID_BLOCK_SIZE)
        block.acked = min(len(block.data), block.acked + ackseq * SEGMENT)
        block.blksize = blksize
        if block.acked < len(block.data) or (not block.data and ackseq == 0):
            block.new_block()
            self._send_segments(block)
            return
        block.count = block.sent = 0
        block.ended = True
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

    def request_aborted(self, data: bytes) -> None:
        self._block = None
        super().request_aborted(data)

    def abort(self, abort_code: int = 0x08000000) -> None:
        """canopen's, naming 0000:00 when no request named an object yet (canopen's would
        fail to pack None)."""
        self._block = None
        self._index = self._index or 0
        self._subindex = self._subindex or 0
        super().abort(abort_code)
