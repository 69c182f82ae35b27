"""The manager node's SDO server: canopen's, made strict where a lax server could let a
transfer take effect that must not (the node's objects switch controllers and e-stop)."""
from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable, Mapping

import can
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

from ..drivers.protocol.sdo_block_server import (
    BlockUpload,
    BlockUploadServer,
    is_block_continuation,
)
from .objects import ABORT_COMMAND_SPECIFIER, ABORT_TOO_LONG, MAX_DOWNLOAD, SEGMENT

#: Segments of a block upload the node hands the interface at once: 8 frames are ~1 ms of
#: a 1 Mbit/s bus, which the control loop's frames may queue behind.
BURST = 8
#: Bursts in a row the interface refused (its queue full) before the node stops sending
#: the block: the client's ack after its timeout names what it got, and the rest follows.
REFUSED_BURSTS = 8
#: How long the pacing thread sleeps with nothing to send before it looks again.
PACER_IDLE = 1.0
#: the command byte of a download's first request (CiA 301: ccs 1, and ccs 6 with cs 0 for a
#: block download), masked as ``on_request`` reads it
_DOWNLOAD_INITIATE = 0x20
_BLOCK_DOWNLOAD_INITIATE = 0xC0


class StrictSdoServer(BlockUploadServer):
    """canopen's SDO server without the ways a transfer could take effect that must not, and
    without a traceback in the log for a request it cannot serve (a hostile or garbled bus
    must not flood the log; it gets an abort, or nothing when the frame is no SDO request).

    - A frame that is not 8 bytes is not an SDO request (CiA 301) and is ignored.
    - Segments continue only the transfer open in their own direction: a download segment
      never appends to an upload's data, and a segmented download that was aborted (by either
      side) or has completed is forgotten, so a stray last segment cannot complete it.
    - Every abort carries the multiplexer of the request it answers (0000:00 when no request
      named one), so the abort itself cannot fail.
    - Block upload is served (drivers/protocol/sdo_block_server.py; CiA 301, with the CRC when the
      client asks, any block size 1..127): the 1-2 KB JSON of 0x2140 is ~250 segments, one
      round trip each in a segmented upload, a few in blocks. Each exchange between two
      processes on a busy host can stall for a second, so the status that matters most
      during a fault took 20 s (measured in a user-mode-linux guest) and failed when one
      stall passed the client's timeout. The node's frames share the interface's transmit
      queue (first in, first out) with the control loop's SYNC and RPDOs, so a block is
      never handed over whole: at most BURST segments at once, the next burst ``burst_gap``
      s later, from a thread of the server's own (the reader thread that answers requests
      never sleeps, and the loop never waits on either). python-can shows no transmit queue,
      so the gap is what the node can know: the caller derives it from the bit rate. A
      frame the interface refuses (its queue full) is tried again in the next burst; after
      REFUSED_BURSTS refused bursts in a row the node stops, and the client's ack after its
      timeout resumes from what it got. A client asking the protocol switch threshold gets
      a normal upload when the data is not longer (CiA 301).
    - An answer the interface refuses is dropped (counted in ``refused_sends``), not
      raised: the client's timeout covers it.
    - Block download is refused with "command specifier not valid" (not supported).
    - An expedited download without the size indicated carries the object's own size
      (CiA 301: the trailing bytes are unspecified), so a one-byte e-stop written that way is
      an e-stop, not a length error.
    - A download to a stop object (``stops``: the manager's 0x2110, 0x2111) is a stop at
      the request that opens it, whatever it carries (rocoma_can/stop_surfaces.py): any
      value, size and subindex, expedited, segmented (its segments need not follow, it may
      announce megabytes) or block (refused as a transfer after the stop), and a frame cut
      short as long as it names the object. What the transfer does afterwards is only
      what the client is answered.
    """

    _open: int | None = None  # REQUEST_SEGMENT_UPLOAD / _DOWNLOAD while one is open
    refused_sends = 0  # answers the interface refused (its transmit queue full)
    bursts = 0         # bursts of block segments sent
    longest_burst = 0  # segments in the longest of them

    def __init__(self, rx_cobid: int, tx_cobid: int, node: canopen.LocalNode, *,
                 burst_gap: float = 0.0) -> None:
        super().__init__(rx_cobid, tx_cobid, node)
        self.burst_gap = burst_gap
        # requests (the bus reader's thread) and bursts (the pacer's) change the transfer
        self._lock = threading.RLock()
        self._paced = threading.Condition(self._lock)
        self._due: float | None = None  # when the next burst of the open block is due
        self._refused_bursts = 0
        self._pacer: threading.Thread | None = None
        self._closed = False

    def close(self) -> None:
        """Stop the pacing thread (bounded): no segment is sent after this."""
        with self._paced:
            self._closed, self._block, self._due = True, None, None
            self._paced.notify()
            pacer = self._pacer
        if pacer is not None:
            pacer.join(2.0)

    #: object index -> what a download to it does at once (the node's stops)
    stops: Mapping[int, Callable[[], None]] = {}

    def on_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) >= 3 and (data[0] & 0xE0 == _DOWNLOAD_INITIATE or data[0] & 0xE1
                               == _BLOCK_DOWNLOAD_INITIATE):
            stop = self.stops.get(data[1] | data[2] << 8)
            if stop is not None:  # before anything the request carries is read
                stop()
        if len(data) != 8:
            return
        with self._lock:
            ccs = data[0] & 0xE0
            continues = ccs in (REQUEST_SEGMENT_DOWNLOAD, REQUEST_SEGMENT_UPLOAD) \
                or is_block_continuation(data[0])
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
        self._open = None
        super().block_upload(data)

    # --- pacing the block's segments ----------------------------------------------------------
    def _send_segments(self, block: BlockUpload) -> None:
        """The block's first burst at once (lock held, on the reader thread), the rest from
        the pacing thread."""
        self._due, self._refused_bursts = None, 0
        self._burst(block)

    def _burst(self, block: BlockUpload) -> None:
        """Up to BURST of the block's unsent segments; the next burst is due ``burst_gap``
        later while some are left (lock held)."""
        sent = 0
        while sent < BURST and (frame := block.next_segment()) is not None:
            if not self._sent(frame):
                self._refused_bursts += 1
                break
            block.sent += 1
            sent += 1
        else:
            self._refused_bursts = 0
        if sent:
            self.bursts += 1
            self.longest_burst = max(self.longest_burst, sent)
        if block.next_segment() is None or self._refused_bursts >= REFUSED_BURSTS \
                or self._closed:
            return
        self._due = time.monotonic() + self.burst_gap
        if self._pacer is None:
            self._pacer = threading.Thread(target=self._pace, name="manager-node-sdo-pacer",
                                           daemon=True)
            self._pacer.start()
        self._paced.notify()

    def _pace(self) -> None:
        with self._paced:
            while not self._closed:
                due = self._due
                left = PACER_IDLE if due is None else due - time.monotonic()
                if left > 0:
                    self._paced.wait(left)
                    continue
                self._due = None
                if self._block is not None:
                    self._burst(self._block)

    # --- frames out ---------------------------------------------------------------------------
    def send_response(self, response: bytes | bytearray) -> None:
        """canopen's, without the exception when the interface refuses the frame (its
        transmit queue full): the client's timeout and retry deal with a lost answer, and
        the bus reader thread this runs on must not log a traceback per refused frame."""
        self._sent(bytes(response))

    def _sent(self, frame: bytes) -> bool:
        try:
            super().send_response(frame)
        except can.CanError:
            self.refused_sends += 1
            return False
        return True

    def request_aborted(self, data: bytes) -> None:
        self._open = None
        super().request_aborted(data)

    def abort(self, abort_code: int = 0x08000000) -> None:
        self._open = None
        self._index = self._index or 0
        self._subindex = self._subindex or 0
        super().abort(abort_code)
