"""The simulated drive's errors, and the faults a test can inject into it.

Errors are what a real drive reports: the error register (0x1001), the error history
(0x1003, newest first, at most 8) and EMCY frames (none in STOPPED, CiA 301). Injected
faults are the ways a real drive or its wiring misbehaves that a master must survive:
a dead TX line, a statusword bit error, no answer to SYNC, late TPDOs, sensor noise and a
babbling node; the drive's public methods switch them on and off.
"""
from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..protocol import cia301 as c301
from ..protocol.cia301 import ObjectKey
from .objects import ERROR_REGISTER
from .port import Segment

# Error register (0x1001) bit per EMCY error class (code >> 12), CiA 301; bit 0 = generic.
ERROR_REGISTER_BIT = {0x2: 1 << 1, 0x3: 1 << 2, 0x4: 1 << 3, 0x8: 1 << 4}


def register_bits(code: int) -> int:
    """The error register bits an error with EMCY ``code`` sets: generic, and its class's."""
    return 1 | ERROR_REGISTER_BIT.get(code >> 12, 0)


@dataclass
class InjectedFaults:
    silent: bool = False          # transmit nothing at all
    statusword_xor: int = 0       # XORed into every statusword reported
    answer_sync: bool = True      # False: SYNC ignored
    tpdo_delay: float = 0.0       # s, every TPDO this late
    position_noise: float = 0.0   # increments, standard deviation on 0x6064


class EmcyProducer:
    """Error register, error history and EMCY frames of one node (all its axes')."""

    def __init__(self, node_id: int, values: dict[ObjectKey, Any],
                 send: Callable[[int, bytes], None], stopped: Callable[[], bool]) -> None:
        self._cob_id = c301.EMCY + node_id
        self._values = values
        self._send = send
        self._stopped = stopped
        self.register = 0
        self._history: list[int] = []  # 0x1003, newest first

    def flag(self, code: int) -> None:
        """Set the generic bit and the bit of ``code``'s error class."""
        self.register |= register_bits(code)

    def record(self, code: int) -> None:
        """Push ``code`` onto the error history 0x1003."""
        self._history.insert(0, code)
        del self._history[8:]
        for sub in range(1, 9):
            key = (c301.PREDEFINED_ERROR_FIELD, sub)
            if key in self._values:
                self._values[key] = self._history[sub - 1] if sub <= len(self._history) else 0
        self._values[(c301.PREDEFINED_ERROR_FIELD, 0)] = len(self._history)

    def clear_history(self) -> None:
        """0x1003:0 written with 0, or power-on."""
        self._history.clear()

    def emit(self, code: int) -> None:
        """An EMCY frame with ``code`` and the current error register."""
        self._values[ERROR_REGISTER] = self.register
        if self._stopped():
            return  # CiA 301: no EMCY in STOPPED
        self._send(self._cob_id, struct.pack("<HB5s", code, self.register, bytes(5)))


class Babble:
    """A babbling node: bursts of one frame every millisecond from the segment's timer."""

    def __init__(self, segment: Segment) -> None:
        self._seg = segment
        self._left = 0

    def start(self, count: int, cob_id: int, data: bytes, burst: int) -> None:
        running = self._left > 0  # one flood at a time: a new call resets its count
        self._left = count
        if not running:
            self._seg.schedule(self._seg.clock(), self._burst, cob_id, bytes(data), burst)

    def _burst(self, cob_id: int, data: bytes, burst: int) -> None:
        n = min(burst, self._left)
        for _ in range(n):
            self._seg.send(cob_id, data)
        self._left -= n
        if self._left > 0:
            self._seg.schedule(self._seg.clock() + 0.001, self._burst, cob_id, data, burst)
