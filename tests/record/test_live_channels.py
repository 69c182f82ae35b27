"""The live view's channels in recordings (record/live_channels.py) as a reader finds them
after the fact: every /rocoma/manager sample carries the e-stop latch and cause in force at
its cycle, however the rows and the events that changed them reached the writer process
(rows through shared memory, events through a pipe, batched at different times); and the
samples of /rocoma/manager and /tf come at the documented rate on a loop's jittery rows."""
from __future__ import annotations

import io
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rocoma_can import ManagerState
from rocoma_can.cli.demo.config import demo_urdf
from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.events import EventKind, ManagerEvent
from rocoma_can.live.urdf import Robot, parse_urdf
from rocoma_can.record.live_channels import SAMPLE_RATE, EstopHistory, Facts, LiveChannels
from rocoma_can.record.rings import SharedFile, layout
from rocoma_can.record.trace import (
    McapWriter,
    RowLayout,
    SignalTrace,
    event_message,
    read_messages,
)
from rocoma_can.record.writer import Spec, Writer

#: a loop of ~100 Hz whose rows never fall on a sample's due time (rows 20, 100, 150 and
#: 200, where the latch changes, are sampled, with 50 µs to spare: no rounding decides it)
PERIOD = 0.01005
RATE = 1.0 / PERIOD
WORK = 0.001  # s: each cycle's work; an update's events are stamped within it
JOINTS = ["joint1", "joint2"]


class _Manager:
    active_controller_name = "pd"


def _event(kind: EventKind, at: float, latched: bool, cause: str = "",
           state: ManagerState = ManagerState.OK) -> dict[str, Any]:
    return event_message(ManagerEvent(kind, state, "pd", cause, time=at, latched=latched))


def _samples(path: Path) -> tuple[list[tuple[int, dict[str, Any]]], list[dict[str, Any]]]:
    """The /rocoma/manager samples in log-time order: (row number, message) of those a row
    made, and those an event made (told apart by the /rocoma/cycle message at a row's log
    time)."""
    messages = list(read_messages(str(path)))
    rows = {log_time: k for k, (_, log_time, _) in
            enumerate(m for m in messages if m[0] == "/rocoma/cycle")}
    samples = [(log_time, m) for topic, log_time, m in messages if topic == "/rocoma/manager"]
    return ([(rows[log_time], m) for log_time, m in samples if log_time in rows],
            [m for log_time, m in samples if log_time not in rows])


class _Loop:
    """A writer process's Writer in this process over rows this test's loop records: the
    rows' times and the writes' batches are the test's."""

    def __init__(self, tmp_path: Path, start: float, *, latched: bool,
                 flight: bool = False) -> None:
        state, command = JointState.zeros(len(JOINTS)), JointCommand.zeros(len(JOINTS))
        [rows] = layout([("rows", 1024, RowLayout(JOINTS).width, False)])
        self.shared = SharedFile(rows.size)
        self.trace = SignalTrace(state, command, _Manager(), rows.capacity,
                                 rows=self.shared.array(rows),
                                 publish=lambda n: self.shared.publish(rows, n), known=["pd"])
        self.record = tmp_path / "record"
        self.flight = tmp_path / "flight"
        self.writer = Writer(Spec(os.dup(self.shared.fd), self.shared.size, rows, {}, JOINTS,
                                  {"pd": 0}, record=str(self.record),
                                  flight=str(self.flight) if flight else None, rate=RATE,
                                  latched=latched), io.StringIO())
        self.start = start

    def time(self, k: int) -> float:
        return self.start + k * PERIOD

    def cycles(self, first: int, end: int, state: Callable[[int], ManagerState]) -> None:
        for k in range(first, end):
            self.trace.record(self.time(k), WORK, 0.0, state(k), 0.0)

    def close(self) -> None:
        self.writer.write(closing=True)
        self.writer.close()
        self.shared.close()


def _state(k: int) -> ManagerState:
    return (ManagerState.FAILPROOF if k < 50 else ManagerState.OK if k < 100
            else ManagerState.EMERGENCY if k < 150 else ManagerState.OK if k < 200
            else ManagerState.EMERGENCY)


def test_every_manager_sample_carries_the_latch_and_cause_of_its_cycle(tmp_path):
    """A manager that starts latched is cleared at row 20, e-stopped (joint3) at row 100,
    cleared at row 150 and e-stopped (joint6) at row 200. Its events reach the writer in
    the batch of rows around them, with the latch messages the loop's process sends as it
    sees the latch change (the first one as the e-stop's request set it, before the
    e-stop), and a switch's event, sent while that request waited, carries the latch set.
    Every sample, in the recording and in both flight records, says the latch and cause of
    its own cycle: none before the e-stop that set them, none after with the one before."""
    loop = _Loop(tmp_path, time.monotonic() - 3.5, latched=True, flight=True)
    writer, at = loop.writer, loop.time
    try:
        loop.cycles(0, 60, _state)
        writer.command({"event": _event(EventKind.STATE_CHANGED, at(19) + 0.005, False,
                                        "emergency stop cleared", ManagerState.FAILPROOF)})
        writer.command({"latched": False})
        writer.write()
        loop.cycles(60, 120, _state)
        writer.command({"latched": True})  # the request latched it after row 97
        writer.command({"event": _event(EventKind.ACTIVE_CONTROLLER_CHANGED, at(97) + 0.005,
                                        True)})
        writer.command({"event": _event(EventKind.EMERGENCY_STOP, at(100) + WORK / 2, True,
                                        "joint3: fault", ManagerState.EMERGENCY)})
        writer.command({"event": _event(EventKind.STATE_CHANGED, at(100) + WORK / 2, True,
                                        "", ManagerState.EMERGENCY)})
        writer.write()  # the first flight record: rows 0-119
        loop.cycles(120, 220, _state)
        writer.command({"event": _event(EventKind.STATE_CHANGED, at(149) + 0.005, False,
                                        "emergency stop cleared", ManagerState.EMERGENCY)})
        writer.command({"latched": False})
        writer.command({"latched": True})
        writer.command({"event": _event(EventKind.EMERGENCY_STOP, at(200) + WORK / 2, True,
                                        "joint6: fault", ManagerState.EMERGENCY)})
        writer.write()
        loop.cycles(220, 300, _state)
    finally:
        loop.close()
    flights = sorted(loop.flight.glob("flight-*.mcap"))
    assert len(flights) == 2  # joint3's at once, joint6's (within the storm rule) at the close
    for path, rows in [(loop.record / "trace.mcap", 300), (flights[0], 120),
                       (flights[1], 300)]:
        samples, of_events = _samples(path)
        assert abs(len(samples) - rows * PERIOD * SAMPLE_RATE) <= 1
        assert {20, 100, 150, 200} & set(range(rows)) <= {k for k, _ in samples}
        for k, sample in samples:
            latched = k < 20 or 100 <= k < 150 or k >= 200
            cause = "" if k < 100 else "joint3: fault" if k < 200 else "joint6: fault"
            assert (sample["state"], sample["latched"], sample["cause"]) == (
                _state(k).name, latched, cause), f"{path.name}, row {k}"
        # each event's own: the cycles up to it, its own included, and what it left
        assert [(m["cycles"], m["latched"], m["cause"]) for m in of_events] == [
            (20, False, ""), (98, False, ""), (101, True, "joint3: fault"),
            (101, True, "joint3: fault"), (150, False, "joint3: fault"),
            (201, True, "joint6: fault")][:len(of_events)]
        assert len(of_events) == (4 if rows == 120 else 6)


def test_a_row_waits_for_the_events_still_on_their_way_to_the_writer(tmp_path):
    """The rows of the last moments are written only once their cycles' events had time to
    come through the pipe: an e-stop heard after its row reached the ring still marks that
    row's sample and the ones after it."""
    loop = _Loop(tmp_path, time.monotonic() - 1.0, latched=False)
    writer = loop.writer
    just_now = time.monotonic() + 60.0  # newer than anything a write takes now
    try:
        loop.cycles(0, 10, _state)
        loop.start = just_now - 10 * PERIOD  # rows 10 on: the loop's newest
        loop.cycles(10, 20, lambda k: ManagerState.EMERGENCY)
        writer.write()  # before the e-stop of row 10 came through
        writer.command({"event": _event(EventKind.EMERGENCY_STOP, loop.time(10) + WORK / 2,
                                        True, "joint3: fault", ManagerState.EMERGENCY)})
    finally:
        loop.close()
    samples, of_events = _samples(loop.record / "trace.mcap")
    assert [(m["cycles"], m["cause"]) for m in of_events] == [(11, "joint3: fault")]
    assert 10 in [k for k, _ in samples] and len(samples) >= 8  # (a new start after a gap)
    assert [(s["latched"], s["cause"]) for k, s in samples if k >= 10] == \
        [(True, "joint3: fault")] * sum(k >= 10 for k, _ in samples)
    assert {(s["latched"], s["cause"]) for k, s in samples if k < 10} == {(False, "")}


def test_a_flight_records_window_starts_with_the_latch_and_cause_before_it(tmp_path):
    """A flight record's rows begin after the e-stop that latched the manager: its first
    sample says so (a file of its own, the events kept beside it: Facts)."""
    facts = Facts(latched=False)
    facts.on_event(_event(EventKind.EMERGENCY_STOP, 0.5, True, "joint3: fault",
                          ManagerState.EMERGENCY))
    facts.on_event(_event(EventKind.EMERGENCY_STOP, 0.6, True, "joint3: fault",
                          ManagerState.FAILPROOF))
    rows = np.zeros((100, RowLayout(JOINTS).width))
    rows[:, 0] = 1.0 + np.arange(100) * PERIOD
    samples = [m for topic, _, m in _live_file(tmp_path, [rows], PERIOD, None, facts)
               if topic == "/rocoma/manager"]
    assert len(samples) == 50
    assert {(m["latched"], m["cause"]) for m in samples} == {(True, "joint3: fault")}


def test_the_latch_rises_with_an_estop_only_and_every_change_is_in_time_order():
    """EstopHistory: a latch set on another event (a request waiting for its e-stop) is
    not taken as risen; an event heard after later ones takes its place in time, the
    causes after it following; a storm of the same e-stop keeps one change; changes older
    than ``span`` before the newest go, the one in force then kept."""
    history = EstopHistory(latched=False, span=10.0)
    history.add(1.0, True, None)  # a switch's event while an e-stop's request waited
    assert history.at(1.5) == (False, "")
    history.add(2.0, True, "a")
    history.add(4.0, False, None)  # a clear
    history.add(3.0, True, "b")    # heard after the clear, stamped before it
    assert [history.at(t) for t in (0.0, 1.0, 2.0, 3.5, 4.0, 5.0)] == [
        (False, ""), (False, ""), (True, "a"), (True, "b"), (False, "b"), (False, "b")]
    history.add(5.0, True, "c")
    for k in range(1000):
        history.add(5.0 + k * 0.001, True, "c")
    assert len(history._times) == 5  # -inf, 2, 3, 4, 5 (the 1.0 changed nothing)
    history.add(20.0, False, None)
    assert history.at(10.0) == (True, "c") and history.at(20.0) == (False, "c")
    assert len(history._times) == 2


@pytest.mark.parametrize("rate", [100.0, 1000.0, 20.0])
def test_samples_come_at_the_documented_rate_on_a_jittery_loop(rate, tmp_path):
    """10 s of a loop's rows, each up to 40 % of a period late (a loaded bench), handed over
    in the writer's 50 ms batches: /rocoma/manager and /tf come 50 times a second on
    average (each at the first row at or after its time), every cycle of a loop slower
    than that."""
    period, seconds = 1.0 / rate, 10.0
    count = int(seconds * rate)
    rows = np.zeros((count, RowLayout(JOINTS).width))
    rows[:, 0] = 100.0 + np.arange(count) * period + np.random.default_rng(1).uniform(
        0.0, 0.4 * period, count)
    robot = parse_urdf(demo_urdf(JOINTS).encode(), "demo")
    batch = max(1, int(0.05 * rate))
    messages = _live_file(tmp_path, [rows[first:first + batch]
                                     for first in range(0, count, batch)], period, robot,
                          Facts())
    times = {topic: np.array([t for other, t, _ in messages if other == topic])
             for topic in ("/rocoma/manager", "/tf")}
    assert list(times["/tf"]) == list(times["/rocoma/manager"])
    if rate <= SAMPLE_RATE:
        assert len(times["/tf"]) == count
        return
    assert abs(len(times["/tf"]) - seconds * SAMPLE_RATE) <= 1
    # sample n in [first + n / SAMPLE_RATE, first + (n + 1) / SAMPLE_RATE): none skipped
    since = (times["/tf"] - times["/tf"][0]) / 1e9 + 1e-7
    assert list(np.floor(since * SAMPLE_RATE)) == list(range(len(since)))


def _live_file(tmp_path: Path, batches: list[np.ndarray], period: float,
               robot: Robot | None, facts: Facts) -> list[tuple[str, int, dict[str, Any]]]:
    """The messages LiveChannels makes of rows handed over in ``batches`` (the first
    numbered 0), as a reader finds them in the file."""
    path = tmp_path / "live.mcap"
    with open(path, "wb") as stream:
        writer = McapWriter(stream, JOINTS)
        live = LiveChannels(writer, RowLayout(JOINTS), period, robot, facts)
        first = 0
        for rows in batches:
            live.write(rows, first, (), {0: "pd"}, 0.0)
            first += len(rows)
        writer.finish()
    return list(read_messages(str(path)))
