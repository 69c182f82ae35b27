"""Recording for ``rocoma-can run``: the flight recorder (on by default) and ``--record``.

After an e-stop the first question is what happened in the seconds before it. The flight
recorder keeps the last ``seconds`` (10 by default) of the loop's signals (trace.py, a ring
the cycle writes), of the manager's events (each e-stop with its cause, state and
controller changes) and of every CAN frame on every bus (passive bus handles of its own, like
``rocoma-can record``), and on every e-stop, and on a shutdown after one, dumps both to
``flight-<time>-<cause>.mcap`` in its directory (e-stops within half a window of the last
dump go into one more file together, so a held e-stop button writes a few files, not one
per frame). The dump runs on the recorder's own thread:
the loop only ever writes its ring row, and the manager's event thread only queues a request.

``--record DIR`` (``Recording``) writes everything instead, as it happens: ``DIR/<bus>.log``
per bus (candump, python-can's writer) and ``DIR/trace.mcap`` with every cycle and every
manager event.

A directory that cannot be written, or a full disk, ends that recording with the reason
logged (``errors``), never the loop.
"""
from __future__ import annotations

import collections
import logging
import math
import re
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import can

from ..drivers.bus import readers_for
from ..events import STOP_CAUSE, EventKind, ManagerEvent
from .can_log import FrameLog
from .trace import Frame, McapWriter, SignalTrace

log = logging.getLogger(__name__)

#: frames kept per second and bus at most (a saturated 1 Mbit/s bus carries ~9,000)
MAX_FRAMES_PER_SECOND = 10_000
#: manager events kept at most (a switch is two, an e-stop two or three)
MAX_EVENTS = 1000


class FrameTap(can.Listener):
    """Every frame of one bus into a bounded deque (on the bus reader's thread)."""

    def __init__(self, bus: str, seconds: float) -> None:
        self.bus = bus
        self.frames: collections.deque[tuple[float, int, bytes, int]] = collections.deque(
            maxlen=int(MAX_FRAMES_PER_SECOND * seconds))

    def on_message_received(self, msg: can.Message) -> None:
        flags = (msg.is_extended_id | msg.is_remote_frame << 1 | msg.is_error_frame << 2
                 | msg.is_fd << 3)
        self.frames.append((msg.timestamp, msg.arbitration_id, bytes(msg.data), flags))

    def on_error(self, exc: Exception) -> None:  # counted by the reader
        pass

    def since(self, wall: float) -> list[Frame]:
        return [Frame(t, self.bus, cob, data, flags)
                for t, cob, data, flags in list(self.frames) if t >= wall]


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]+", "-", text).strip("-")[:60] or "e-stop"


class FlightRecorder:
    """The last ``seconds`` of signals and frames, dumped on every e-stop (see module)."""

    def __init__(self, trace: SignalTrace, directory: str | Path, seconds: float,
                 buses: Sequence[str], announce: Callable[[str], None] | None = None) -> None:
        self.trace = trace
        self.directory = Path(directory)
        self.seconds = seconds
        self.dumps: list[Path] = []
        self.errors: list[str] = []
        self._announce = announce
        #: per bus, the listener its passive reader feeds (Taps wires them)
        self.taps = {name: FrameTap(name, seconds) for name in buses}
        self._requests: collections.deque[str] = collections.deque()
        self._dropped = 0  # requests past MAX_EVENTS queued, merged by count only
        self._events: collections.deque[ManagerEvent] = collections.deque(maxlen=MAX_EVENTS)
        self._wake = threading.Event()
        self._flush = threading.Event()  # closing: write what is queued now
        self._stop = threading.Event()
        self._last_dump = -math.inf
        self._faulted = False
        self._thread = threading.Thread(target=self._run, name="flight-recorder", daemon=True)
        self._thread.start()

    def on_event(self, event: ManagerEvent) -> None:
        """A manager subscriber (its event thread): every event is kept, an e-stop queues a
        dump."""
        self._events.append(event)
        if event.kind == EventKind.EMERGENCY_STOP and not event.cause.startswith(STOP_CAUSE):
            self._faulted = True
            self.request(event.cause or "e-stop")

    def request(self, cause: str) -> None:
        if len(self._requests) < MAX_EVENTS:  # a storm past that is counted, not kept
            self._requests.append(cause)
        else:
            self._dropped += 1
        self._wake.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            if not self._requests:
                continue
            # A storm of e-stops (a button held down repeats its frame; each is a request
            # while FAILPROOF too) is one record, not one file per frame: requests within
            # half a window of the last record wait for it to pass and go out together
            # (the next file still overlaps the last). Closing writes at once.
            self._flush.wait(self._last_dump + self.seconds / 2 - time.monotonic())
            causes = []
            while self._requests:
                causes.append(self._requests.popleft())
            extra, self._dropped = len(causes) - 1 + self._dropped, 0
            more = f" (+{extra} more)" if extra else ""
            self._dump(causes[0] + more)
            self._last_dump = time.monotonic()

    def _dump(self, cause: str) -> None:
        now_wall, now = time.time(), time.monotonic()
        offset = now_wall - now
        first = self.trace.since_time(now - self.seconds)
        _, rows = self.trace.rows(first)
        events = [e for e in list(self._events) if e.time >= now - self.seconds]
        frames = sorted((f for tap in self.taps.values()
                         for f in tap.since(now_wall - self.seconds)), key=lambda f: f.time)
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now_wall))
        path = self.directory / f"flight-{stamp}-{int(now_wall * 1000) % 1000:03d}-" \
                                f"{_slug(cause)}.mcap"
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            with open(path, "wb") as stream:
                writer = McapWriter(stream, self.trace.names)
                writer.cycles(self.trace, rows, offset)
                writer.events(events, offset)
                writer.frames(frames)
                writer.finish()
        except (OSError, ValueError) as exc:  # unwritable directory, full disk: said, never
            # raised; a file begun and cut short is no record, and takes room the next needs
            try:
                path.unlink(missing_ok=True)
            except OSError:
                pass
            self.errors.append(f"flight record {path}: {exc}")
            log.error("flight recorder: %s could not be written: %s", path, exc)
            return
        self.dumps.append(path)
        if self._announce is not None:  # said once: by the announcer, else in the log
            self._announce(f"flight record ({cause}): {path}")
        else:
            log.warning("flight record (%s): %s", cause, path)

    def close(self, timeout: float = 10.0) -> None:
        """A shutdown after an e-stop dumps once more (what led to the stop is then all in
        one file); then the readers and the thread end."""
        if self._faulted:
            self.request("shutdown after an e-stop")
        self._flush.set()
        deadline = time.monotonic() + timeout
        while self._requests and time.monotonic() < deadline:
            self._wake.set()
            time.sleep(0.05)
        self._stop.set()
        self._wake.set()
        self._thread.join(max(0.0, deadline - time.monotonic()))


class Recording:
    """``--record DIR``: every bus to ``DIR/<bus>.log``, every cycle and manager event to
    ``DIR/trace.mcap`` (written by a thread of its own every ``period`` s; ``on_event`` is
    the manager subscriber).

    The first failure of any of its writers (a full disk, mostly) stops them all, each
    closing its file, with one warning: a recording with a hole is no record of what
    happened, and writers that keep failing would only fill the log. The loop runs on.
    ``errors`` keeps every reason, the first one first."""

    def __init__(self, trace: SignalTrace, directory: str | Path, buses: Sequence[str],
                 period: float = 0.2) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.trace = trace
        self.errors: list[str] = []
        self.path = self.directory / "trace.mcap"
        #: per bus, the FrameLog its passive reader feeds (Taps wires them)
        self.logs: dict[str, FrameLog] = {}
        self._writer: McapWriter | None = None
        try:
            for name in buses:
                self.logs[name] = FrameLog(self.directory / f"{_slug(name)}.log").start()
            self._stream = open(self.path, "wb")  # noqa: SIM115 - closed in _stop_writers
            self._writer = McapWriter(self._stream, trace.names)
        except BaseException:  # a file that cannot be made: no writer thread left behind
            for frame_log in self.logs.values():
                frame_log.stop()
            raise
        self._offset = time.time() - time.monotonic()
        self._next = 0
        self._events: collections.deque[ManagerEvent] = collections.deque()
        self._period = period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="trace-writer", daemon=True)
        self._thread.start()

    def on_event(self, event: ManagerEvent) -> None:
        if self._writer is not None:  # a stopped recording keeps nothing
            self._events.append(event)

    def _run(self) -> None:
        while not self._stop.wait(self._period) and self._writer is not None:
            self._write()
        self._write()

    def _write(self) -> None:
        writer = self._writer
        if writer is None:
            return
        failed = next((f.error for f in self.logs.values() if f.error), None)
        if failed is not None:
            self._fail(failed)
            return
        start, rows = self.trace.rows(self._next)
        if start > self._next:
            self._fail(f"{self.path}: {start - self._next} cycles lost (the writer fell a "
                       "ring behind)")
            return
        events = [self._events.popleft() for _ in range(len(self._events))]
        try:
            writer.cycles(self.trace, rows, self._offset)
            writer.events(events, self._offset)
        except (OSError, ValueError) as exc:
            self._fail(f"{self.path}: writing failed: {exc}")
            return
        self._next = start + len(rows)

    def _fail(self, reason: str) -> None:
        """The recording's first failure (the writer thread's, or at close): said once,
        every writer stopped."""
        self._note(reason)
        self._stop_writers()

    def _note(self, reason: str) -> None:
        self.errors.append(reason)
        if len(self.errors) == 1:
            log.warning("recording to %s stopped, the loop runs on: %s", self.directory,
                        reason)
        else:
            log.debug("recording to %s: %s", self.directory, reason)

    def _stop_writers(self) -> None:
        """Every writer stopped and its file closed, whatever fails on the way."""
        writer, self._writer = self._writer, None
        self._events.clear()
        if writer is not None:
            try:
                writer.finish()
            except (OSError, ValueError) as exc:  # a full disk: the summary cannot go out
                self._note(f"{self.path}: closing failed: {exc}")
            try:
                self._stream.close()  # closes the file even when its last flush fails
            except (OSError, ValueError) as exc:
                self._note(f"{self.path}: closing failed: {exc}")
        for frame_log in self.logs.values():
            frame_log.stop()
            if frame_log.error and frame_log.error not in self.errors:
                self._note(frame_log.error)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(10.0)
        if self._thread.is_alive():  # stuck in a write: its files are its own to close
            self._note(f"{self.path}: the trace writer did not stop")
            for frame_log in self.logs.values():
                frame_log.stop()
            return
        self._stop_writers()


class Taps:
    """One passive bus handle and reader per bus, feeding every listener given for it (the
    flight recorder's tap, the --record log): a bus has one reader (one thread for all buses
    where the interface allows, bus.readers_for)."""

    def __init__(self, buses: Mapping[str, can.BusABC],
                 listeners: Mapping[str, Sequence[can.Listener]]) -> None:
        self._buses = dict(buses)
        self._readers = readers_for([(bus, tuple(listeners.get(name, ())))
                                     for name, bus in self._buses.items()], name="taps")

    def close(self) -> None:
        for reader in self._readers:
            reader.stop()
        for bus in self._buses.values():
            bus.shutdown()
