"""The live view's channels in the recordings (live/messages.py), made in the writer process
from the rows and events it writes anyway: a recording or flight record opens in Foxglove
with the live view's layout (live/foxglove_layout.json).

``/joint_states`` every cycle (the plots); ``/rocoma/manager`` on every manager event and at
SAMPLE_RATE; ``/tf`` at SAMPLE_RATE (the 3D panel: forward kinematics cost ~5 µs a joint);
``/rocoma/log``, a line per manager event; ``/robot_description`` once, with the first
cycle; ``/rocoma/status``, the status reports the loop's process sent (every STATUS_PERIOD
while it records, recorder.py, and as often as a viewer of the live view asks), each once per
file, and the live view's service-call lines on ``/rocoma/log``. The e-stop latch, the
status reports and those lines are what the writer last heard (``Facts``).

A sample is due every 1/SAMPLE_RATE s on a fixed schedule, taken at the first row at or
after its time: anchored on the row instead, each sample would wait out a period plus that
row's lateness, and a loop's jitter would skip a cycle now and then (39 a second at 100 Hz).
"""
from __future__ import annotations

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
#: every STATUS_PERIOD, the live view's two; a Heard keeps a flight record's window of them
HEARD_PER_SECOND = 4


class Heard(Generic[T]):
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


@dataclass
class Facts:
    """What the manager's process tells the writer beside the rows: the e-stop latch, the
    status reports, and the live view's service-call lines (text, level)."""
    window: float = 10.0  # s: the flight record's, whose reports and lines are kept
    latched: bool = False
    statuses: Heard[dict[str, Any]] = field(init=False)
    logs: Heard[tuple[str, int]] = field(init=False)

    def __post_init__(self) -> None:
        keep = max(64, int(HEARD_PER_SECOND * self.window) + 8)
        self.statuses, self.logs = Heard(keep), Heard(keep)


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
        self._cause = ""
        self._overruns = self._waiting = self._cycles = 0
        self._next_sample = -math.inf
        self._described = robot is None

    def cycles(self, rows: np.ndarray, first: int, controllers: Mapping[int, str],
               offset: float) -> None:
        """Rows ``first``, ``first + 1``, ... (cycle numbers), ``offset`` as McapWriter's."""
        add, layout, ids = self._writer.add, self._layout, self._id
        position, velocity, torque = layout.slices[:3]
        for k, row in enumerate(rows):
            values = row.tolist()
            ns = int((values[0] + offset) * 1e9)
            if overran(values[2], values[3], self._period):
                self._overruns += 1
                self._waiting += waited(values[2], values[3], values[6])
            if not self._described and self._robot is not None:
                add(ids[messages.ROBOT_DESCRIPTION.topic], ns,
                    messages.robot_description(self._robot.text))
                self._described = True
            add(ids[messages.JOINT_STATES.topic], ns, messages.joint_states(
                ns, self._names, values[position], values[velocity], values[torque]))
            t = values[0]
            if t >= self._next_sample:
                due = self._next_sample + _SAMPLE_PERIOD  # on schedule (see module), from
                self._next_sample = due if due > t else t + _SAMPLE_PERIOD  # a gap anew
                state = state_name(values[4])
                self._cycles = first + k + 1
                self._manager(ns, state, controllers.get(int(values[5]), ""))
                if self._robot is not None:
                    positions = dict(zip(self._names, values[position]))
                    add(ids[messages.TRANSFORMS.topic], ns, messages.frame_transforms(
                        ns, self._robot.transforms(positions)))

    def events(self, events: Iterable[Mapping[str, Any]], offset: float) -> None:
        for event in events:
            ns = int((float(event["time"]) + offset) * 1e9)
            if event["kind"] == EventKind.EMERGENCY_STOP.value:
                self._cause = event["cause"]
            self._writer.add(self._id[messages.LOG.topic], ns,
                             messages.log(ns, *messages.event_log(event)))
            self._manager(ns, event["state"], event["controller"])

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

    def _manager(self, ns: int, state: str, controller: str) -> None:
        self._writer.add(self._id[messages.MANAGER.topic], ns, messages.manager(
            state, controller, self._facts.latched, self._cause, self._cycles,
            (self._overruns, self._waiting)))
