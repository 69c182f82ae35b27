"""The live view's channels in the recordings (live/messages.py), made in the writer process
from the rows and events it writes anyway: a recording or flight record opens in Foxglove
with the live view's layout (live/foxglove_layout.json).

``/joint_states`` every cycle (the plots); ``/rocoma/manager`` on every manager event and at
SAMPLE_RATE; ``/tf`` at SAMPLE_RATE (the 3D panel: forward kinematics costs per joint);
``/rocoma/log``, a line per manager event; ``/robot_description`` once, with the first
cycle; ``/rocoma/status``, the status reports the loop's process sent (every STATUS_PERIOD
while it records, recorder.py, and as often as a viewer of the live view asks), each once per
file, and the live view's service-call lines on ``/rocoma/log``. The status reports and
those lines are what the writer heard (``Facts``); the e-stop latch and cause of each
``/rocoma/manager`` sample are those in force at its cycle (``EstopHistory``): rows and
events reach the writer by different ways and at different times, and a file is read after
the fact, where a latch shown before the e-stop that set it would mislead.

A sample is due every 1/SAMPLE_RATE s on a fixed schedule, taken at the first row at or
after its time: anchored on the row instead, each sample would wait out a period plus that
row's lateness, and a loop's jitter would skip a cycle now and then (39 a second at 100 Hz).
"""
from __future__ import annotations

import bisect
import itertools
import math
import threading
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np

from ..events import EventKind
from ..live import messages
from ..live.urdf import Robot
from ..overrun import overran, waited
from .trace import McapWriter, RowLayout, state_name

T = TypeVar("T")

#: /rocoma/manager and /tf samples per second of a recording
SAMPLE_RATE = 50.0
_SAMPLE_PERIOD = 1.0 / SAMPLE_RATE
#: status reports (and service-call lines) a second, an upper bound: the recording's one
#: every STATUS_PERIOD, the live view's two; a HeardWindow keeps a flight record's window of them
HEARD_PER_SECOND = 4


class HeardWindow(Generic[T]):
    """The last ``keep`` things heard, each numbered as it came and stamped (the monotonic
    clock, one for every process). Any thread adds; a file takes what came after the last
    number it wrote, so none is written twice or passed over."""

    def __init__(self, keep: int) -> None:
        self._items: deque[tuple[int, float, T]] = deque(maxlen=keep)
        self._numbers = itertools.count()
        self._lock = threading.Lock()  # (the writer's threads: number and place together)

    def add(self, at: float, item: T) -> None:
        with self._lock:
            self._items.append((next(self._numbers), at, item))

    def after(self, number: int) -> list[tuple[int, float, T]]:
        with self._lock:
            return [entry for entry in self._items if entry[0] > number]


class EstopHistory:
    """The e-stop latch and the last e-stop's cause over time, as the manager's events set
    them (their ``time`` and ``latched``), in the events' time order: what was in force at
    a row's cycle, whether its event reached the writer before that row or after it, and
    before a flight record's window began. Only an e-stop raises the latch: the manager
    sets it at an e-stop's request, up to a cycle before the e-stop itself, and an event
    in between (a switch's, a recovery's) carries it set. Changes are kept ``span`` s back
    from the newest (the rows' ring: no older row is read); the writer's main thread only.
    """

    def __init__(self, latched: bool, span: float) -> None:
        self._span = span
        self._times: list[float] = [-math.inf]
        #: per change: what its event said (the latch, an e-stop's cause or None), then
        #: the latch and the cause in force from it on
        self._changes: list[tuple[bool, str | None, bool, str]] = [(latched, None, latched,
                                                                    "")]

    def add(self, at: float, latched: bool, cause: str | None) -> None:
        """An event stamped ``at`` that left the latch ``latched``; ``cause``: an
        e-stop's, None for any other event."""
        k = bisect.bisect_right(self._times, at)
        if k == len(self._times) and _in_force(latched, cause, self._changes[-1]) == \
                self._changes[-1][2:]:
            return  # nothing changed (an e-stop storm: the same cause again and again)
        self._times.insert(k, at)
        self._changes.insert(k, (latched, cause, latched, ""))
        for j in range(k, len(self._changes)):  # (past k: an event heard after later ones)
            said, own = self._changes[j][:2]
            self._changes[j] = (said, own, *_in_force(said, own, self._changes[j - 1]))
        old = bisect.bisect_right(self._times, self._times[-1] - self._span) - 1
        if old > 0:
            del self._times[:old], self._changes[:old]
            self._times[0] = -math.inf

    def at(self, time: float) -> tuple[bool, str]:
        """The latch and the last e-stop's cause in force at ``time`` (monotonic)."""
        _, _, latched, cause = self._changes[bisect.bisect_right(self._times, time) - 1]
        return latched, cause


def _in_force(latched: bool, cause: str | None, before: tuple[bool, str | None, bool, str]
              ) -> tuple[bool, str]:
    """The latch and the cause in force after an event (``latched``, an e-stop's ``cause``
    or None) that follows the change ``before``."""
    return latched and (before[2] or cause is not None), before[3] if cause is None else cause


@dataclass
class Facts:
    """What the manager's process tells the writer beside the rows: the e-stop latch and
    cause (from its events, ``on_event``), the status reports, and the live view's
    service-call lines (text, level). ``latched``: the manager's latch as recording began;
    ``span``: how far back, in s, a file may read rows (the rows' ring)."""
    window: float = 10.0  # s: the flight record's, whose reports and lines are kept
    latched: bool = False
    span: float = 10.0
    statuses: HeardWindow[dict[str, Any]] = field(init=False)
    logs: HeardWindow[tuple[str, int]] = field(init=False)
    estops: EstopHistory = field(init=False)

    def __post_init__(self) -> None:
        keep = max(64, int(HEARD_PER_SECOND * self.window) + 8)
        self.statuses, self.logs = HeardWindow(keep), HeardWindow(keep)
        self.estops = EstopHistory(self.latched, self.span)

    def on_event(self, event: Mapping[str, Any]) -> None:
        """A manager event as trace.event_message makes it (the writer's main thread)."""
        self.estops.add(float(event["time"]), bool(event["latched"]),
                        str(event["cause"]) if event["kind"] == EventKind.EMERGENCY_STOP.value
                        else None)


class LiveChannels:
    """The channels of one MCAP file (see module); ``period``: the loop's, for overruns."""

    def __init__(self, writer: McapWriter, layout: RowLayout, period: float,
                 robot: Robot | None, facts: Facts) -> None:
        self._writer, self._layout, self._period = writer, layout, period
        self._robot, self._facts = robot, facts
        channels = messages.MANAGER_CHANNELS + (messages.ROBOT if robot else ())
        self._id = {c.topic: writer.json_channel(c.topic, c.schema) for c in channels}
        self._status_seen = self._log_seen = -1  # the number of the last of each taken
        self._names = layout.names
        self._overruns = self._waiting = self._cycles = 0
        self._next_sample = -math.inf
        self._described = robot is None

    def write(self, rows: np.ndarray, first: int, events: Iterable[Mapping[str, Any]],
              controllers: Mapping[int, str], offset: float) -> None:
        """Rows ``first``, ``first + 1``, ... (cycle numbers) and the manager events among
        them (trace.event_message's), in time order: an event's sample counts the cycles
        and overruns up to its own, its cycle's included; ``offset`` as McapWriter's."""
        add, layout, ids = self._writer.add, self._layout, self._id
        position, velocity, torque = layout.slices[:3]
        pending = sorted(events, key=lambda event: float(event["time"]))
        taken = 0
        for k, row in enumerate(rows):
            values = row.tolist()
            t = values[0]
            while taken < len(pending) and pending[taken]["time"] < t:
                self._event(pending[taken], offset)
                taken += 1
            ns = int((t + offset) * 1e9)
            self._cycles = first + k + 1
            if overran(values[2], values[3], self._period):
                self._overruns += 1
                self._waiting += waited(values[2], values[3], values[6])
            if not self._described and self._robot is not None:
                add(ids[messages.ROBOT_DESCRIPTION.topic], ns,
                    messages.robot_description(self._robot.text))
                self._described = True
            add(ids[messages.JOINT_STATES.topic], ns, messages.joint_states(
                ns, self._names, values[position], values[velocity], values[torque]))
            if t >= self._next_sample:
                due = self._next_sample + _SAMPLE_PERIOD  # on schedule (see module), from
                self._next_sample = due if due > t else t + _SAMPLE_PERIOD  # a gap anew
                # as the cycle left them: an update's events are stamped before its end
                latched, cause = self._facts.estops.at(t + values[2])
                self._manager(ns, state_name(values[4]), controllers.get(int(values[5]), ""),
                              latched, cause)
                if self._robot is not None:
                    positions = dict(zip(self._names, values[position]))
                    add(ids[messages.TRANSFORMS.topic], ns, messages.frame_transforms(
                        ns, self._robot.transforms(positions)))
        for event in pending[taken:]:
            self._event(event, offset)

    def _event(self, event: Mapping[str, Any], offset: float) -> None:
        at = float(event["time"])
        ns = int((at + offset) * 1e9)
        self._writer.add(self._id[messages.LOG.topic], ns,
                         messages.log(ns, *messages.event_log(event)))
        self._manager(ns, event["state"], event["controller"], *self._facts.estops.at(at))

    def heard(self, offset: float, since: float = -math.inf) -> None:
        """What the writer heard beside rows and events (``Facts``: status reports, the
        live view's service-call lines) since the last written, and not before ``since``
        (the monotonic clock); ``offset`` as McapWriter's."""
        add = self._writer.add
        status = self._id[messages.STATUS.topic]
        for number, at, report in self._facts.statuses.after(self._status_seen):
            self._status_seen = number
            if at >= since:
                add(status, int((at + offset) * 1e9), report)
        log = self._id[messages.LOG.topic]
        for number, at, (text, level) in self._facts.logs.after(self._log_seen):
            self._log_seen = number
            if at >= since:
                ns = int((at + offset) * 1e9)
                add(log, ns, messages.log(ns, text, level))

    def _manager(self, ns: int, state: str, controller: str, latched: bool,
                 cause: str) -> None:
        self._writer.add(self._id[messages.MANAGER.topic], ns, messages.manager(
            state, controller, latched, cause, self._cycles,
            (self._overruns, self._waiting)))
