"""Raw CAN recording: every frame on a bus into a candump, ASC or BLF file.

A passive listener: it opens a bus handle of its own (on SocketCAN a second socket sees the
frames every other socket of the host sends, the manager's included) and never sends, so it
works beside any running manager, on the same machine or another one on the bus. The file
format follows the suffix, as python-can's ``can.Logger`` chooses it: ``.log`` candump -L
(the default; replays with ``canplayer`` and ``python -m can.player``), ``.asc`` Vector
ASCII, ``.blf`` Vector binary.

Frames are appended to a queue on the bus's reader thread and written by a thread of their
own, so a slow disk never delays reception; a failing write (full disk, unwritable file)
stops the recording with the reason in ``error`` and never reaches a control loop.
"""
from __future__ import annotations

import collections
import copy
import threading
from pathlib import Path

import can
from can.util import channel2int

from ..drivers.link.bus import BusReader
from ..drivers.protocol.wire import BRS, ERROR, ESI, EXTENDED, FD, REMOTE

#: a frame record's flags (rings.py): drivers/protocol/wire.py's, and this for a frame the hardware
#: sent (``T`` in a candump line, else ``R``)
SENT = 64

SUFFIXES = (".log", ".asc", ".blf")
#: Frames held for the writer at most (~30 s of four saturated buses): a writer that cannot
#: keep up loses the oldest and counts them, rather than growing without bound.
MAX_QUEUED = 1_000_000
#: ASC and BLF number channels from 1 (python-can: the digits a channel name ends in, + 1);
#: BLF stores the number in 16 bits
MAX_CHANNEL_NUMBER = 0xFFFE


#: candump's error-frame id (linux/can.h CAN_ERR_FLAG | CAN_ERR_BUSERROR), as python-can
#: writes every error frame
_ERROR_ID = 0x20000000 | 0x00000080


def candump_line(stamp: float, channel: str, cob_id: int, flags: int, data: str) -> str:
    """One frame as a ``candump -L`` line, as python-can's writer makes it (``can.LogReader``
    and ``canplayer`` read it); ``flags`` as rings.py keeps them (drivers/protocol/wire.py's, and
    ``SENT``: ``T``, else ``R``); ``data`` the payload in upper-case hex."""
    if flags & ERROR:
        return f"({stamp:f}) {channel} {_ERROR_ID:08X}#{data}\n"
    head = f"({stamp:f}) {channel} {cob_id:08X}#" if flags & EXTENDED else \
        f"({stamp:f}) {channel} {cob_id:03X}#"
    eol = " T\n" if flags & SENT else " R\n"
    if flags & REMOTE:
        return f"{head}R{eol}"
    fd = f"#{bool(flags & BRS) | bool(flags & ESI) << 1:X}" if flags & FD else ""
    return f"{head}{fd}{data}{eol}"


class RecordingError(OSError):
    """The file cannot be written (bad suffix, no such directory, not writable)."""


def check_path(path: str | Path) -> Path:
    """The file a recording will write: a known suffix, a writable directory, and not there
    yet (an earlier capture is never written over)."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise RecordingError(f"{path}: unknown recording format {path.suffix!r}; use "
                             f"{', '.join(SUFFIXES)}")
    if not path.parent.is_dir():
        raise RecordingError(f"{path}: directory {path.parent} does not exist")
    if path.exists() or path.is_symlink():
        raise RecordingError(f"{path}: exists: an earlier recording is not written over; "
                             "give another file, or move it")
    return path


class FrameLog(can.Listener):
    """Writes every frame it is handed (``on_message_received``) to ``path`` off the caller's
    thread. ``start`` opens the file; ``stop`` writes what is queued and closes it."""

    def __init__(self, path: str | Path, flush_period: float = 0.1) -> None:
        self.path = check_path(path)
        self.frames = 0          # written
        self.dropped = 0         # lost because the writer fell MAX_QUEUED behind
        self.error: str | None = None
        self._queue: collections.deque[can.Message] = collections.deque()
        self._numbered = self.path.suffix.lower() in (".asc", ".blf")
        self._unnumberable: dict[object, bool] = {}  # channel -> its digits do not fit
        self._flush_period = flush_period
        self._stop = threading.Event()
        self._writer: can.io.generic.MessageWriter | None = None
        self._thread = threading.Thread(target=self._run, name=f"can-log {self.path.name}",
                                        daemon=True)

    def start(self) -> FrameLog:
        try:
            self._writer = can.Logger(str(self.path))
        except (OSError, ValueError) as exc:
            raise RecordingError(f"{self.path}: cannot write: {exc}") from exc
        self._thread.start()
        return self

    def on_message_received(self, msg: can.Message) -> None:
        if self._stop.is_set() or self.error is not None:  # nothing will write it
            return
        if len(self._queue) >= MAX_QUEUED:
            self._queue.popleft()
            self.dropped += 1
        self._queue.append(msg)

    def on_error(self, exc: Exception) -> None:  # the bus's problem, reported by its reader
        pass

    def _run(self) -> None:
        while not self._stop.wait(self._flush_period):
            self._drain()
        self._drain()

    def _drain(self) -> None:
        writer = self._writer
        if writer is None or self.error is not None:
            self._queue.clear()
            return
        try:
            while self._queue:
                writer.on_message_received(self._for_file(self._queue.popleft()))
                self.frames += 1
            file = getattr(writer, "file", None)
            if file is not None:  # on disk now: a crash loses at most one flush period
                file.flush()
        except (OSError, ValueError) as exc:  # a full disk: stop writing; the owner says
            # why, once (rocoma-can record at its end, a run's Recording as it happens)
            self.error = f"{self.path}: writing failed after {self.frames} frames: {exc}"
            self._queue.clear()

    def _for_file(self, msg: can.Message) -> can.Message:
        """In ASC and BLF, a channel whose name ends in digits too large for a channel
        number (an in-process bus named by a random id) is written as the file's channel 1,
        on a copy: the frame itself may be shared with other receivers."""
        if not self._numbered:
            return msg
        bad = self._unnumberable.get(msg.channel)
        if bad is None:
            number = channel2int(msg.channel)
            bad = self._unnumberable[msg.channel] = (number is not None and not
                                                     0 <= number < MAX_CHANNEL_NUMBER)
        if not bad:
            return msg
        renamed = copy.copy(msg)
        renamed.channel = None
        return renamed

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout)
        if self._writer is not None:
            try:
                self._writer.stop()
            except (OSError, ValueError) as exc:
                self.error = self.error or f"{self.path}: closing failed: {exc}"
            self._writer = None


class BusRecording:
    """A passive bus handle of its own, its reader, and a FrameLog: ``rocoma-can record``
    and ``rocoma-can run --record`` (one per bus)."""

    def __init__(self, bus: can.BusABC, path: str | Path, *, own_bus: bool = True) -> None:
        self.bus = bus
        self.own_bus = own_bus
        self.log = FrameLog(path).start()
        self.reader = BusReader(bus, (self.log,), name=f"record {self.log.path.name}")

    def stop(self) -> None:
        self.reader.stop()
        self.log.stop()
        if self.own_bus:
            self.bus.shutdown()
