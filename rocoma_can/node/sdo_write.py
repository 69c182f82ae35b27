"""An expedited SDO download that takes only its own answer: how ManagerClient writes the
node's numbers (an e-stop, a clear, a switch by number).

The node has one SDO channel, and an operator's `status --watch` keeps it busy with block
uploads. canopen's download takes the first frame the node sends after the request as the
answer, so a segment of the view's upload, or an abort the node sends the view, made an
e-stop fail (the node had applied it) and its retry an e-stop twice. Here every frame that
does not name this object (the multiplexer in bytes 1-3) is another transfer's and is
skipped; no abort is sent on a timeout either, as one naming 0000:00 would end the other
client's transfer. The wait is bounded by the SDO timeout and by a number of frames.
"""
from __future__ import annotations

import queue
import struct
import time

from canopen.sdo.client import SdoClient
from canopen.sdo.constants import (
    EXPEDITED,
    REQUEST_DOWNLOAD,
    RESPONSE_ABORTED,
    RESPONSE_DOWNLOAD,
    SDO_STRUCT,
    SIZE_SPECIFIED,
)
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

#: frames of other transfers skipped before the wait counts as unanswered
MAX_STRAYS = 64


def download(sdo: SdoClient, index: int, subindex: int, data: bytes) -> None:
    """Write 1-4 bytes; SdoAbortedError when the node refuses, SdoCommunicationError when
    it does not answer within the SDO timeout."""
    if not 1 <= len(data) <= 4:
        raise ValueError(f"an expedited download carries 1-4 bytes, got {len(data)}")
    command = REQUEST_DOWNLOAD | EXPEDITED | SIZE_SPECIFIED | (4 - len(data)) << 2
    request = SDO_STRUCT.pack(command, index, subindex) + data.ljust(4, b"\0")
    while True:  # answers left from an earlier transfer are no answer to this one
        try:
            sdo.responses.get_nowait()
        except queue.Empty:
            break
    sdo.send_request(request)
    deadline = time.monotonic() + sdo.RESPONSE_TIMEOUT
    for _ in range(MAX_STRAYS):
        left = deadline - time.monotonic()
        if left <= 0:
            break
        try:
            response = sdo.responses.get(timeout=left)
        except queue.Empty:
            break
        if len(response) < 8:
            continue
        answer, answered, answered_sub = SDO_STRUCT.unpack_from(response)
        if (answered, answered_sub) != (index, subindex):
            continue  # another client's transfer on this channel
        if answer == RESPONSE_ABORTED:
            raise SdoAbortedError(struct.unpack_from("<L", response, 4)[0])
        if answer & 0xE0 == RESPONSE_DOWNLOAD:
            return
    raise SdoCommunicationError(f"no answer to the write of 0x{index:04X}:{subindex:02X}")
