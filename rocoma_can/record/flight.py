"""The flight recorder, in the writer process: on every e-stop, the seconds before it.

After an e-stop the first question is what happened in the seconds before it. The rings the
loop's process fills (rings.py) hold the last ``seconds`` (10 by default) of the loop's
signals and of every frame on every bus, received and sent; this keeps the manager's events
(each e-stop with its cause, state and controller changes) and, on every e-stop and on a
shutdown after one, writes all three to ``flight-<time>-<cause>.mcap`` in its directory,
with the live view's channels (live_channels.py).

A storm of e-stops (a held e-stop button repeats its frame; each is a request while
FAILPROOF too) is a few records, not one file per frame: requests within half a window of
the last record wait for it to pass and go out together (the next file still overlaps the
last). Closing writes at once. A directory that cannot be written, or a full disk, leaves
no file and a reason in ``errors``. A record is written under a hidden name
(``.flight-....mcap.part``) and named when whole: a writer killed while writing (the close's
wait ran out, the OOM killer) leaves no record cut short.
"""
from __future__ import annotations

import collections
import math
import os
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..events import STOP_CAUSE, EventKind
from .live_channels import LiveChannels
from .recording import slug
from .rings import RingReader, frame_chunks, in_time_order
from .trace import McapWriter, RowLayout

#: frames kept per second, bus and direction at most (a saturated 1 Mbit/s bus carries
#: ~9,000; small CAN FD frames at 5 Mbit/s twice that, both ways together)
MAX_FRAMES_PER_SECOND = 10_000
#: manager events kept at most (a switch is two, an e-stop two or three)
MAX_EVENTS = 1000


class FlightRecords:
    """Requests, the storm rule and the dumps (see module). ``on_event`` takes each manager
    event as trace.event_message makes it; ``due`` says whether to ``dump`` now."""

    def __init__(self, directory: Path, seconds: float, layout: RowLayout, rows: RingReader,
                 buses: Mapping[str, Sequence[RingReader]],
                 live: Callable[[McapWriter], LiveChannels],
                 pace: Callable[[], None]) -> None:
        self.directory, self.seconds = directory, seconds
        self._pace = pace  # a record is 1-1.6 s of work: paced throughout (pacing.py)
        self.dumps: list[tuple[Path, str]] = []
        self.errors: list[str] = []
        self._layout, self._rows, self._buses, self._live = layout, rows, buses, live
        self._events: collections.deque[dict[str, Any]] = collections.deque(maxlen=MAX_EVENTS)
        self._requests: list[str] = []
        self._dropped = 0  # requests past MAX_EVENTS, merged by count only
        self._last_dump = -math.inf
        self.faulted = False

    def check(self) -> str | None:
        """Why no record could be written to the directory (made if missing), tried with a
        hidden file at start; None when one can. A record is tried at each e-stop anyway
        (the directory may be mounted, or given room, later)."""
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=self.directory, prefix=".flight-check-"):
                pass
        except OSError as exc:
            said = f"[Errno {exc.errno}] {exc.strerror}" if exc.strerror else str(exc)
            return (f"{self.directory}: cannot write flight records: {said} (each e-stop's "
                    "is tried, and said if it fails)")
        return None

    def on_event(self, event: dict[str, Any]) -> None:
        self._events.append(event)
        cause = str(event.get("cause", ""))
        if event.get("kind") == EventKind.EMERGENCY_STOP.value \
                and not cause.startswith(STOP_CAUSE):
            self.faulted = True
            self.request(cause or "e-stop")

    def request(self, cause: str) -> None:
        if len(self._requests) < MAX_EVENTS:  # a storm past that is counted, not kept
            self._requests.append(cause)
        else:
            self._dropped += 1

    def due(self, now: float, closing: bool) -> bool:
        return bool(self._requests) and (closing or now >= self._last_dump + self.seconds / 2)

    def dump(self, controllers: Mapping[int, str]) -> tuple[Path, str] | str:
        """One record of every request waiting: (its path, its cause), or why none could
        be written."""
        causes, self._requests = self._requests, []
        extra, self._dropped = len(causes) - 1 + self._dropped, 0
        cause = causes[0] + (f" (+{extra} more)" if extra else "")
        self._last_dump = time.monotonic()
        now_wall, now = time.time(), time.monotonic()
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now_wall))
        path = self.directory / (f"flight-{stamp}-{int(now_wall * 1000) % 1000:03d}-"
                                 f"{slug(cause)}.mcap")
        part = path.with_name(f".{path.name}.part")  # named a record once it is whole
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            with open(part, "wb") as stream:
                self._write(McapWriter(stream, self._layout.names, self._pace),
                            controllers, now, now_wall)
            os.replace(part, path)
        except (OSError, ValueError) as exc:  # unwritable directory, full disk: said, never
            # raised; a file begun and cut short is no record, and takes room the next needs
            try:
                part.unlink(missing_ok=True)
            except OSError:
                pass
            said = (f"[Errno {exc.errno}] {exc.strerror}"  # (its file name: the hidden one)
                    if isinstance(exc, OSError) and exc.strerror else str(exc))
            reason = f"flight record {path}: {said}"
            self.errors.append(reason)
            return reason
        self.dumps.append((path, cause))
        return path, cause

    def _write(self, writer: McapWriter, controllers: Mapping[int, str], now: float,
               now_wall: float) -> None:
        since, since_wall = now - self.seconds, now_wall - self.seconds
        start, rows = self._rows.read(0)
        kept = rows[:, 0] >= since
        start, rows = start + int(np.argmax(kept)) if kept.any() else start, rows[kept]
        events = [e for e in self._events if e["time"] >= since]
        live = self._live(writer)
        writer.cycles(self._layout, controllers, rows, now_wall - now)  # oldest first
        writer.events(events, now_wall - now)
        live.write(rows, start, events, controllers, now_wall - now)
        live.heard(now_wall - now, since)
        for label, rings in self._buses.items():
            parts = [ring.read(0)[1] for ring in rings]  # the window's frames, then sorted:
            # a ring holds 10,000 frames a second, more than the window on a calmer bus
            records = in_time_order([part[part["t"] >= since_wall] for part in parts])
            for chunk in frame_chunks(records):
                writer.frames(label, chunk)
        writer.finish()
