"""Several simulated segments (one per bus) served by ONE receive thread.

A bench of 12 drives on 4 buses at 1 kHz has four segments. Each with a receive thread of
its own, every cycle wakes four threads (more when the loop's RPDOs and SYNC arrive in
separate bursts), and each wake-up is a hand-over of the GIL that the control loop in the
same process waits behind. A group waits for frames on all its buses at once
(frame_io.BusSelector: one ``select`` on SocketCAN, one shared Event on in-process buses)
and hands each bus's frames to its own segment (``SimulatedSegment.pump``), so a cycle
wakes one thread. The drives cannot tell the difference: each segment keeps its lock, its
timers, its dynamics and its arrival-time rules (``received_until``: a bus the selector
found empty is vouched for with ``nothing_arrived``, so a lost heartbeat on a silent bus
is still seen).

Buses one thread cannot wait on together (python-can's ``virtual`` hands frames over a
queue per bus) get a receive thread per segment, as a lone segment has. A bus whose
interface fails is counted in its own segment's ``bus_errors`` and read again every
``RX_IDLE`` seconds (BusSelector.failed) while the others are served.
"""
from __future__ import annotations

import threading
from collections.abc import Iterable

from ..frame_io import BusSelector, FrameReader
from .segment import RX_IDLE, SimulatedSegment


class SegmentGroup:
    """``SegmentGroup(segments).start()``; the group starts and stops its segments."""

    def __init__(self, segments: Iterable[SimulatedSegment]) -> None:
        self.segments = tuple(segments)
        if not self.segments:
            raise ValueError("a segment group needs at least one segment")
        # one receive thread serves every segment (False: one thread each)
        self.shared_thread = BusSelector.supports([s.bus for s in self.segments])
        self._selector: BusSelector | None = None  # made by start: it hooks into the buses
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._receive_loop, name="sim-group-rx",
                                        daemon=True)
        self._started = False

    def start(self) -> SegmentGroup:
        if self._started:
            raise RuntimeError("segment group already started")
        self._started = True
        try:
            if self.shared_thread:
                self._selector = BusSelector([s.bus for s in self.segments], retry=RX_IDLE)
            for segment in self.segments:
                segment.start(receive=not self.shared_thread)
            if self._selector is not None:
                self._thread.start()
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        """Stop the receive thread (joined), then every segment; idempotent."""
        self._stopped.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        for segment in self.segments:
            segment.stop()
        if self._selector is not None:
            self._selector.close()

    def check(self) -> None:
        """Re-raise the first exception a segment's threads caught, if any."""
        for segment in self.segments:
            segment.check()

    def __enter__(self) -> SegmentGroup:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _receive_loop(self) -> None:
        selector = self._selector
        assert selector is not None  # started only with a selector
        segments = self.segments
        readers = [FrameReader(s.bus) for s in segments]
        clock = SimulatedSegment.clock
        try:
            while not self._stopped.is_set():
                since = clock()
                ready = selector.wait(RX_IDLE)
                for i, segment in enumerate(segments):
                    if i in ready:
                        if not segment.pump(readers[i], 0.0):
                            selector.failed(i)
                    elif not selector.failing(i):
                        segment.nothing_arrived(since)
        except Exception as exc:  # noqa: BLE001 - a bug here: every segment's check says so
            for segment in segments:
                segment.errors.append(exc)
            raise
