"""rocoma_can/record/recorder.py, writer.py: the recorder's writer process, its threads and its
shared memory over a recorder's life (record/recorder.py): a start that fails leaves nothing behind
and says why in one line; a writer that dies is said, and does not hold the run's close up; every
close ends them all."""
from __future__ import annotations

import gc
import logging
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

import can
import pytest
from fixtures.budgets import within
from fixtures.running import DEMO_WAIT, wait_for

from rocoma_can import ManagerState
from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.events import EventKind, ManagerEvent
from rocoma_can.record import recorder as recorder_module
from rocoma_can.record.can_log import RecordingError
from rocoma_can.record.pacing import unpaced
from rocoma_can.record.recorder import BusToRecord, Recorder
from rocoma_can.record.recording import BusLog
from rocoma_can.record.rings import FrameRing, RingReader, SharedFile, layout
from rocoma_can.record.trace import read_messages

RATE = 100.0


class _Manager:
    active_controller_name = "pd"
    estop_latched = False


def _recorder(tmp_path: Path, **kwargs: object) -> Recorder:
    state, command = JointState.zeros(2), JointCommand.zeros(2)
    kwargs.setdefault("flight", str(tmp_path / "flight"))
    return Recorder(state, command, _Manager(), RATE, [BusToRecord("arm", "vcan0", False)],
                    controllers=["pd"], **kwargs)  # type: ignore[arg-type]


def _fds() -> set[str]:
    """This process's open files, by what they are (a memfd, a pipe, ...); what earlier
    recorders left to the garbage collector (a closed recorder's memory is freed with the
    last array over it) collected first."""
    gc.collect()
    names = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            names.add(f"{fd} {os.readlink(f'/proc/self/fd/{fd}')}")
        except OSError:  # the listing's own
            pass
    return names


def _recorder_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("recorder-")]


def test_a_dead_writer_holds_the_close_up_no_longer_than_its_death_takes(tmp_path,
                                                                         monkeypatch):
    """The writer's death is seen when its output ends: the close after it has nothing to
    wait for (it waited CLOSE_WAIT for an answer that could never come, with the buses
    still open)."""
    monkeypatch.setattr(recorder_module, "CLOSE_WAIT", 100 * DEMO_WAIT)
    rec = _recorder(tmp_path)
    rec._process.kill()
    assert rec.flight is not None
    wait_for(lambda: rec.flight.errors, "the writer's death said", DEMO_WAIT)
    closing = threading.Thread(target=rec.close, daemon=True)
    closing.start()
    closing.join(within(1.0))
    assert not closing.is_alive(), "close waited for a dead writer"
    assert _recorder_threads() == []


def test_a_flight_recorders_dead_writer_is_said(tmp_path, caplog):
    """With the flight recorder alone (``run``'s default) the run must hear that no flight
    record will be written any more."""
    caplog.set_level(logging.WARNING)
    rec = _recorder(tmp_path)
    try:
        rec._process.kill()
        assert rec.flight is not None
        wait_for(lambda: rec.flight.errors, "the writer's death noted", DEMO_WAIT)
        wait_for(lambda: any("writer process ended" in r.getMessage() for r in caplog.records),
                 "the writer's death in the log", within(0.1))
    finally:
        rec.close()


def _failed_start(tmp_path: Path, **kwargs: object) -> str:
    """Why a recorder could not start; what it built is let go (garbage collected), so
    what stays open is what it left open."""
    try:
        _recorder(tmp_path, **kwargs)
    except RecordingError as exc:
        message = str(exc)
    else:
        raise AssertionError("the recorder started")
    gc.collect()
    return message


def test_a_writer_that_cannot_be_started_leaves_nothing_open(tmp_path, monkeypatch):
    before = _fds()
    monkeypatch.setattr(sys, "executable", str(tmp_path / "no-python"))
    message = _failed_start(tmp_path)
    assert "writer process" in message and "no-python" in message and "\n" not in message
    assert _fds() == before
    assert _recorder_threads() == []


def test_a_writer_that_never_answers_is_ended(tmp_path, monkeypatch):
    silent = tmp_path / "silent-python"
    silent.write_text("#!/bin/sh\nexec sleep 1000\n")
    silent.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(silent))
    monkeypatch.setattr(recorder_module, "START_WAIT", 0.5)
    before = _fds()
    assert "did not start within 0.5 s" in _failed_start(tmp_path)
    assert _fds() == before
    assert _recorder_threads() == []


def test_a_recording_that_cannot_start_leaves_nothing_open(tmp_path):
    (tmp_path / "file").write_text("")
    before = _fds()
    message = _failed_start(tmp_path, record=str(tmp_path / "file" / "rec"))
    assert "cannot write" in message and "\n" not in message
    assert _fds() == before
    assert _recorder_threads() == []


def test_a_writer_that_stops_reading_is_ended_by_the_close(tmp_path, monkeypatch):
    """A writer that reads no more (stopped, swapped out) while the events pile up: the
    recorder's sender blocks on the full pipe, and the close still ends the writer (it
    waited on that sender's write for ever)."""
    monkeypatch.setattr(recorder_module, "CLOSE_WAIT", 0.5)
    rec = _recorder(tmp_path)
    writer = rec._process
    os.kill(writer.pid, signal.SIGSTOP)
    try:
        for k in range(2000):  # ~300 kB of events: more than a pipe holds
            rec.on_event(ManagerEvent(EventKind.STATE_CHANGED, ManagerState.OK, "pd",
                                      cause=f"event {k}"))
        closing = threading.Thread(target=rec.close, daemon=True)
        closing.start()
        closing.join(within(1.0 + 5.0))  # CLOSE_WAIT, then the writer's end: 5 s
        assert not closing.is_alive(), "the close hangs on a writer that reads no more"
        assert writer.poll() is not None
    finally:
        if writer.poll() is None:
            writer.kill()
            writer.wait(DEMO_WAIT)


def test_a_recorder_without_mcap_is_refused_at_start(tmp_path, monkeypatch):
    """The MCAP writer is an optional extra: a writer process that cannot import it is
    refused at start with what to install (it started, and died at the first e-stop with a
    traceback, leaving an empty flight-*.mcap and no flight recorder for the rest of the
    run)."""
    shadow = tmp_path / "no-mcap" / "mcap"  # as an interpreter without the extra finds it
    shadow.mkdir(parents=True)
    (shadow / "__init__.py").write_text(
        "raise ModuleNotFoundError(\"No module named 'mcap'\", name='mcap')\n")
    monkeypatch.setenv("PYTHONPATH", str(shadow.parent))
    message = _failed_start(tmp_path)
    assert "rocoma-can[record]" in message and "\n" not in message, message
    assert not (tmp_path / "flight").exists() or not list((tmp_path / "flight").iterdir())


def test_a_writer_killed_while_writing_a_flight_record_leaves_no_cut_file(tmp_path):
    """A flight record is there whole or not at all: the writer killed in the middle of one
    (the close's CLOSE_WAIT ran out on a long window, the kernel's OOM killer) must not
    leave a flight-*.mcap cut short beside the good ones."""
    rec = _recorder(tmp_path)
    writer = rec._process
    try:
        received, sent = rec.frame_taps[0]
        msg = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)
        now, frames = time.time(), received.spec.capacity - 1
        for k in range(frames):  # the last seconds of a busy bus: a second's work to write
            received.put(msg, now - 5.0 + 5.0 * k / frames)
            sent.put(msg, now - 5.0 + 5.0 * k / frames)
        rec.on_event(ManagerEvent(EventKind.EMERGENCY_STOP, ManagerState.EMERGENCY, "pd",
                                  cause="test"))
        flight = tmp_path / "flight"
        wait_for(lambda: flight.exists() and any(flight.glob("flight-*.mcap")),
                 "a flight record begun", DEMO_WAIT)
        writer.kill()
        writer.wait(DEMO_WAIT)
        for record in flight.glob("flight-*.mcap"):
            assert sum(1 for topic, _, _ in read_messages(str(record))
                       if topic == "/can/arm") == 2 * frames
    finally:
        rec.close()


def test_a_frame_stamped_by_an_adapters_own_clock_is_in_the_flight_record(tmp_path):
    """Some interfaces stamp received frames from the adapter's power-on, not the wall
    clock (frame_io.MAX_FRAME_AGE): such a frame is recorded as arrived when it was handed
    over, as the hardware takes it, not dropped from the record as 55 years old."""
    rec = _recorder(tmp_path)
    try:
        received, _sent = rec.frame_taps[0]
        before = time.time()
        for k in range(3):  # what the bus's reader hands the recording, as it reads it
            received.on_message_received(can.Message(
                timestamp=120.0 + k, arbitration_id=0x181, data=bytes([k]),
                is_extended_id=False))
        rec.on_event(ManagerEvent(EventKind.EMERGENCY_STOP, ManagerState.EMERGENCY, "pd",
                                  cause="test"))
        assert rec.flight is not None
        wait_for(lambda: rec.flight.dumps, "the flight record", DEMO_WAIT)
    finally:
        rec.close()
    record = rec.flight.dumps[0]  # (the e-stop's; the close writes another)
    frames = [(log_time, m) for topic, log_time, m in read_messages(str(record))
              if topic == "/can/arm"]
    assert [m["data"] for _, m in frames] == ["00", "01", "02"]
    assert all(log_time >= before * 1e9 for log_time, _ in frames)


def test_a_trace_that_fails_on_frames_is_named_and_the_log_keeps_its_count(tmp_path):
    """Frames are most of a trace's bytes, so on a full disk the trace often fails as a
    chunk of frames goes in, after the bus's log took the same chunk's lines: the reason
    names the trace (not the log), and the log counts the lines it holds."""
    specs = layout([("bus received", 512, 0, False)])
    shared = SharedFile(specs[0].offset + specs[0].size)
    try:
        ring = FrameRing(shared, specs[0], sent=False)
        wall = time.time()
        for k in range(3):
            ring.put(can.Message(arbitration_id=0x181, data=bytes([k]), is_extended_id=False),
                     wall - 1.0 + k * 1e-3)
        bus_log = BusLog(tmp_path / "arm.log", "arm", "vcan0",
                         [RingReader(shared, specs[0])], unpaced)
        full = RecordingError(f"{tmp_path}/trace.mcap: writing failed: [Errno 28] No space "
                              "left on device")

        def trace(fields: object) -> None:
            raise full
        with pytest.raises(RecordingError) as raised:
            bus_log.write(math.inf, trace)
        bus_log.close()
    finally:
        shared.close()
    assert raised.value is full
    assert bus_log.frames == 3 == len(list(can.LogReader(str(tmp_path / "arm.log"))))
