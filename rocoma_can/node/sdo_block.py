"""SDO block upload, the client's side (CiA 301): how ManagerClient reads the node's text
objects (the server's side is sdo_server.StrictSdoServer, which says why blocks).

canopen 2.4's BlockUploadStream is not used: a node that answers with a normal upload (a
manager from before block upload) fails every read there, a lost end frame raises
AttributeError (it calls an abort() it does not have), and after asking for a block again
it counts the stale frames of the block it gave up on. Here a gap in the sequence (a lost
frame) ends the block: the ack names the last segment in order and the node sends the rest
again. Sequence numbers start at 1 in every block, so a late copy of an earlier block's
segment can sit where a new one belongs: only the CRC over the whole value tells, which is
why a node must offer it (and announce the size) or the object is read segmented. The data
and the number of blocks are bounded by the announced size, and every wait by the SDO
timeout. Every failure is an SdoCommunicationError after an abort: the caller may ask again.
"""
from __future__ import annotations

import struct
from typing import NoReturn

from canopen.sdo.base import CrcXmodem
from canopen.sdo.client import SdoClient
from canopen.sdo.constants import (
    BLOCK_SIZE_SPECIFIED,
    BLOCK_TRANSFER_RESPONSE,
    CRC_SUPPORTED,
    END_BLOCK_TRANSFER,
    INITIATE_BLOCK_TRANSFER,
    NO_MORE_BLOCKS,
    REQUEST_ABORTED,
    REQUEST_BLOCK_UPLOAD,
    RESPONSE_BLOCK_UPLOAD,
    RESPONSE_UPLOAD,
    SDO_STRUCT,
    START_BLOCK_UPLOAD,
)
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from .objects import (
    ABORT_BLOCK_SIZE,
    ABORT_COMMAND_SPECIFIER,
    ABORT_CRC,
    ABORT_NO_ANSWER,
    MAX_BLOCK_SIZE,
    SEGMENT,
)

#: Blocks in a row in which no segment arrived in order before the upload is given up.
STALLED_BLOCKS = 3

#: Frames read per block (or while waiting for an initiate or end answer) before the wait
#: counts as a timeout: late copies and strays are skipped, a stream of them is not.
FRAMES_PER_BLOCK = 4


def upload(sdo: SdoClient, index: int, subindex: int = 0,
           blksize: int = MAX_BLOCK_SIZE) -> bytes | None:
    """The object's bytes, or None when the node has no block upload for it (it answered
    with a normal upload, refused the block transfer, or offers no CRC or size): read the
    object the usual way."""
    request = struct.pack("<BHBBBxx", REQUEST_BLOCK_UPLOAD | INITIATE_BLOCK_TRANSFER
                          | CRC_SUPPORTED, index, subindex, blksize, 0)
    try:
        command, response = _initiated(sdo, request, index, subindex)
    except SdoAbortedError as exc:
        if exc.code in (ABORT_COMMAND_SPECIFIER, ABORT_BLOCK_SIZE):
            return None  # a node that does not do block transfers (this way)
        raise
    if command & 0xE0 == RESPONSE_UPLOAD or not command & CRC_SUPPORTED \
            or not command & BLOCK_SIZE_SPECIFIED:
        _abort(sdo, index, subindex, ABORT_COMMAND_SPECIFIER)  # whatever it opened
        return None
    size: int = struct.unpack_from("<L", response, 4)[0]
    most_blocks = 2 * -(-(size + 1) // (SEGMENT * blksize)) + STALLED_BLOCKS
    sdo.send_request(bytes([REQUEST_BLOCK_UPLOAD | START_BLOCK_UPLOAD]) + bytes(7))
    data = bytearray()
    stalled = blocks = 0
    while True:
        segments, last = _block(sdo, blksize)
        data += b"".join(segments)
        blocks += 1
        if len(data) > size + SEGMENT or blocks > most_blocks:
            _fail(sdo, index, subindex, ABORT_COMMAND_SPECIFIER,
                  f"0x{index:04X}: {len(data)} bytes in {blocks} blocks for {size} announced")
        sdo.send_request(bytes([REQUEST_BLOCK_UPLOAD | BLOCK_TRANSFER_RESPONSE, len(segments),
                                blksize]) + bytes(5))
        if last:
            break
        stalled = 0 if segments else stalled + 1
        if stalled >= STALLED_BLOCKS:
            _fail(sdo, index, subindex, ABORT_NO_ANSWER,
                  f"no segment of 0x{index:04X} in {STALLED_BLOCKS} blocks")
    end = _end(sdo, index, subindex)
    unused = (end[0] >> 2) & 0x7
    if unused:
        del data[-unused:]
    if len(data) != size:
        _fail(sdo, index, subindex, ABORT_COMMAND_SPECIFIER,
              f"0x{index:04X}: {len(data)} bytes received, {size} announced")
    crc = CrcXmodem()
    crc.process(data)
    if crc.final() != struct.unpack_from("<H", end, 1)[0]:
        _fail(sdo, index, subindex, ABORT_CRC, f"0x{index:04X}: CRC mismatch")
    sdo.send_request(bytes([REQUEST_BLOCK_UPLOAD | END_BLOCK_TRANSFER]) + bytes(7))
    return bytes(data)


def _initiated(sdo: SdoClient, request: bytes, index: int,
               subindex: int) -> tuple[int, bytes]:
    """The node's answer to the initiate: a block upload's or a normal upload's for this
    object. Frames before it that are neither (late ones of an earlier transfer) are
    skipped (a bounded number, one SDO timeout each)."""
    response: bytes = sdo.request_response(request)
    for _ in range(FRAMES_PER_BLOCK * MAX_BLOCK_SIZE):
        command, answered, answered_sub = SDO_STRUCT.unpack_from(response)
        initiate = command & 0xE1 == RESPONSE_BLOCK_UPLOAD | INITIATE_BLOCK_TRANSFER
        if (initiate or command & 0xE0 == RESPONSE_UPLOAD) \
                and (answered, answered_sub) == (index, subindex):
            return command, response
        try:
            response = sdo.read_response()
        except SdoCommunicationError:
            break
    _fail(sdo, index, subindex, ABORT_COMMAND_SPECIFIER,
          f"no answer to a block upload of 0x{index:04X}:{subindex:02X} (another client on "
          "this node's SDO channel?)")


def _block(sdo: SdoClient, blksize: int) -> tuple[list[bytes], bool]:
    """The data of one block's segments in sequence, up to the first gap, and whether the
    value's last segment was among them. The block ends with its last sequence number, the
    value's last segment, or a timeout (a frame lost, or the burst cut short). A frame
    that cannot be one of this block's segments (sequence number 0 or above blksize) and a
    repeat of the segment just taken are skipped."""
    segments: list[bytes] = []
    in_order = True
    for _ in range(FRAMES_PER_BLOCK * blksize):
        try:
            frame = sdo.read_response()  # an abort from the node raises SdoAbortedError
        except SdoCommunicationError:
            return segments, False
        seqno, last = frame[0] & 0x7F, bool(frame[0] & NO_MORE_BLOCKS)
        if not 1 <= seqno <= blksize or (segments and seqno == len(segments)):
            continue
        if in_order and seqno == len(segments) + 1:
            segments.append(frame[1:8])
            if last:
                return segments, True
        else:
            in_order = False
        if last or seqno == blksize:
            return segments, False
    return segments, False  # frames that are no use: as if the block had timed out


def _end(sdo: SdoClient, index: int, subindex: int) -> bytes:
    """The node's end frame; late segments before it are skipped (with blocks of at most
    MAX_BLOCK_SIZE a segment's first byte cannot look like an end: 110nnn01)."""
    for _ in range(FRAMES_PER_BLOCK * MAX_BLOCK_SIZE):
        try:
            frame: bytes = sdo.read_response()
        except SdoCommunicationError:
            break
        if frame[0] & 0xE1 == RESPONSE_BLOCK_UPLOAD | END_BLOCK_TRANSFER:  # 110 nnn x 1
            return frame
    _fail(sdo, index, subindex, ABORT_NO_ANSWER, "no end of the block upload")


def _abort(sdo: SdoClient, index: int, subindex: int, code: int) -> None:
    sdo.send_request(struct.pack("<BHBL", REQUEST_ABORTED, index, subindex, code))


def _fail(sdo: SdoClient, index: int, subindex: int, code: int, why: str) -> NoReturn:
    _abort(sdo, index, subindex, code)
    raise SdoCommunicationError(why)

