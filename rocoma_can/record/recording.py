"""``--record DIR`` in the writer process: every cycle, manager event and frame, as it happens.

``DIR/trace.mcap`` gets every cycle (/rocoma/cycle), manager event (/rocoma/event) and frame
(/can/<bus>, as a flight record has them), and the live view's channels made from them
(live_channels.py); ``DIR/<bus>.log`` every frame of the bus again, received (``R``) and
sent by this manager (``T``), in candump -L text (``canplayer`` and ``can.LogReader`` replay
it). The files are made at start, so a directory that cannot be written stops the run before
it begins; so does one that holds these files already, an earlier run's record, which is
never written over.

The first failure of any of its files (a full disk, mostly) or a ring the writer fell behind
(the loop's process overwrote records not yet written) stops every file, each closed: a
recording with a hole is no record of what happened. ``errors`` keeps every reason, the
first one first; the loop never hears of it.
"""
from __future__ import annotations

import functools
import os
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

from .can_log import RecordingError, candump_line
from .live_channels import LiveChannels
from .rings import Fields, RingReader, frame_chunks, in_time_order
from .trace import McapWriter, RowLayout


def slug(text: str) -> str:
    """A name fit for a file name."""
    return re.sub(r"[^A-Za-z0-9_]+", "-", text).strip("-")[:60] or "e-stop"


class BusLog:
    """One bus's candump file, fed from its received and sent rings in time order.

    A frame can reach its ring after later ones were written: a received one the bus's
    reader hands over late, one another thread sent (SDO, NMT, the hang watchdog) that the
    cycle moves in at its end (BusPort.end_of_write). So each write takes only the frames
    stamped before ``until`` (a while ago) and holds the rest for the next, in order with
    what comes meanwhile."""

    def __init__(self, path: Path, label: str, channel: str, rings: Sequence[RingReader],
                 pace: Callable[[], None]) -> None:
        self.path, self.label, self.frames = path, label, 0
        self._pace = pace  # between chunks of lines (pacing.py)
        self.channel = f"can{channel}" if channel.isdigit() else channel  # as python-can
        self._rings = rings
        self._next = [0] * len(rings)
        self._held = np.empty(0, rings[0].spec.dtype) if rings else None
        try:
            self._file: IO[str] = open(path, "w", encoding="ascii")  # noqa: SIM115 - close()
        except OSError as exc:
            raise RecordingError(f"{path}: cannot write: {exc}") from exc

    def write(self, until: float, also: Callable[[Sequence[Fields]], None]) -> None:
        """What the rings got since the last write and was stamped before ``until``
        (wall clock; ``math.inf``: all of it), into the log and, in the same order, to
        ``also`` (the trace: a RecordingError of its own names its file); RecordingError on
        a hole or a failed write."""
        parts = [] if self._held is None else [self._held]
        for k, ring in enumerate(self._rings):
            start, records = ring.read(self._next[k])
            if start > self._next[k]:
                raise RecordingError(f"{self.path}: {start - self._next[k]} frames lost (the "
                                     "writer fell a ring behind)")
            self._next[k] = start + len(records)
            parts.append(records)
        if not parts:
            return
        records = in_time_order(parts)
        cut = int(np.searchsorted(records["t"], until, side="left"))
        self._held = records[cut:]
        if not cut:
            return
        channel, pace = self.channel, self._pace
        try:
            for fields in frame_chunks(records[:cut]):
                self._file.write("".join([candump_line(t, channel, cob, flags, data)
                                          for t, cob, flags, data in fields]))
                self.frames += len(fields)
                also(fields)
                pace()
            self._file.flush()  # on disk now: a crash loses at most what is held
        except RecordingError:
            raise
        except (OSError, ValueError) as exc:
            raise RecordingError(f"{self.path}: writing failed after {self.frames} frames: "
                                 f"{exc}") from exc

    def close(self) -> None:
        self._file.close()


class Recording:
    """trace.mcap and one BusLog per bus (see module)."""

    def __init__(self, directory: Path, layout: RowLayout, rows: RingReader,
                 buses: Mapping[str, tuple[str, Sequence[RingReader]]],
                 live: Callable[[McapWriter], LiveChannels],
                 pace: Callable[[], None]) -> None:
        self.directory = directory
        self.path = directory / "trace.mcap"
        self.errors: list[str] = []
        self._layout, self._rows, self._next = layout, rows, 0
        self._events: list[Mapping[str, Any]] = []  # held for the next write (``write``)
        self._logs: list[BusLog] = []
        self._stream: IO[bytes] | None = None
        self._identity = (0, 0)  # the trace's device and inode
        self._writer: McapWriter | None = None
        try:
            directory.mkdir(parents=True, exist_ok=True)
            earlier = sorted(p.name for p in (self.path, *(
                directory / f"{slug(label)}.log" for label in buses)) if p.exists())
            if earlier:  # (the same command again from a shell's history)
                raise RecordingError(f"{directory}: holds an earlier recording "
                                     f"({', '.join(earlier)}): not written over; give "
                                     "--record a new directory, or move them")
            for label, (channel, rings) in buses.items():
                self._logs.append(BusLog(directory / f"{slug(label)}.log", label, channel,
                                         rings, pace))
            try:
                self._stream = open(self.path, "wb")  # noqa: SIM115 - closed in stop()
            except OSError as exc:
                raise RecordingError(f"{self.path}: cannot write: {exc}") from exc
            stat = os.fstat(self._stream.fileno())
            self._identity = (stat.st_dev, stat.st_ino)  # (where_it_is)
            self._writer = McapWriter(self._stream, layout.names, pace)
            self._live = live(self._writer)
        except RecordingError:
            self._close_files()  # no file left open
            raise
        except OSError as exc:  # the directory
            self._close_files()
            raise RecordingError(f"{directory}: cannot write: {exc}") from exc

    @property
    def running(self) -> bool:
        return self._writer is not None

    def write(self, controllers: Mapping[int, str], events: Iterable[Mapping[str, Any]],
              offset: float, until: float) -> str | None:
        """Everything new stamped before ``until`` (wall clock), the rest held for the next
        write: the frames (BusLog), and the rows and manager events, whose /rocoma/manager
        samples carry the e-stop latch and cause of their cycle from events that may still
        be on their way (live_channels.EstopHistory). The first failure's reason (every
        file then stopped), else None."""
        writer = self._writer
        if writer is None:
            return None
        since = until - offset  # (the monotonic clock of rows and events)
        start, rows = self._rows.read(self._next)
        rows = rows[:int(np.searchsorted(rows[:, 0], since, side="left"))]
        events = [*self._events, *events]
        self._events = [event for event in events if event["time"] >= since]
        events = [event for event in events if event["time"] < since]
        try:
            if start > self._next:
                raise RecordingError(f"{self.path}: {start - self._next} cycles lost (the "
                                     "writer fell a ring behind)")
            self._where_it_is()
            writer.cycles(self._layout, controllers, rows, offset)
            writer.events(events, offset)
            self._live.write(rows, start, events, controllers, offset)
            self._live.heard(offset)
            self._next = start + len(rows)
            for bus_log in self._logs:
                bus_log.write(until, functools.partial(self._frames, writer, bus_log.label))
        except (OSError, ValueError) as exc:  # RecordingError too
            reason = str(exc) if isinstance(exc, RecordingError) else \
                f"{self.path}: writing failed: {exc}"
            self.errors.append(reason)
            self.stop()
            return reason
        return None

    def _where_it_is(self) -> None:
        """RecordingError when the trace is no longer at its path (the directory deleted or
        moved mid-run): writing on would fill a file nobody can open, without a word."""
        try:
            stat = os.stat(self.path)
            here = (stat.st_dev, stat.st_ino) == self._identity
        except OSError:
            here = False
        if not here:
            raise RecordingError(f"{self.path}: removed during the run (its directory "
                                 "deleted or moved?): the recording stops")

    def _frames(self, writer: McapWriter, label: str, fields: Sequence[Fields]) -> None:
        """A bus's frames into the trace; a failure names the trace, not the bus's log."""
        try:
            writer.frames(label, fields)
        except (OSError, ValueError) as exc:
            raise RecordingError(f"{self.path}: writing failed: {exc}") from exc

    def stop(self) -> None:
        """Every file closed, whatever fails on the way (its reason kept)."""
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.finish()
            except (OSError, ValueError) as exc:  # a full disk: the summary cannot go out
                self.errors.append(f"{self.path}: closing failed: {exc}")
        self._close_files()

    def _close_files(self) -> None:
        for bus_log in self._logs:
            try:
                bus_log.close()
            except OSError as exc:
                self.errors.append(f"{bus_log.path}: closing failed: {exc}")
        if self._stream is not None:
            try:
                self._stream.close()  # closes the file even when its last flush fails
            except OSError as exc:
                self.errors.append(f"{self.path}: closing failed: {exc}")
