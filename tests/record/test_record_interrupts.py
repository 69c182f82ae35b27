"""Stops that come while the recording's writer is being closed (record/recorder.py's close,
``rocoma-can run``'s end): an impatient second Ctrl-C or SIGTERM while the close waits for a
writer that does not answer (stopped: SIGSTOP, a debugger, swapped out) still ends the
writer, and the run exits with its documented code, leaving no process behind."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import pytest
from fixtures.budgets import within
from fixtures.configs import nobody_answers
from fixtures.console import untimed
from fixtures.processes import gone, stopped, writer_of
from fixtures.running import DEMO_WAIT, wait_for

from rocoma_can.cli.exit_codes import INTERRUPTED
from rocoma_can.drivers.protocol.joints import JointCommand, JointState
from rocoma_can.record.recorder import BusToRecord, Recorder


class _Manager:
    active_controller_name = "pd"
    estop_latched = False


@pytest.fixture
def ctrl_c_interrupts():
    """Ctrl-C raises KeyboardInterrupt in this process, as in a terminal: a suite started in
    the background by a shell without job control (a script's ``bash tools/test &``, a CI
    runner's step) inherits SIGINT ignored, Python then installs no handler, and the test's
    impatient Ctrl-C reached nobody: the close waited its 30 s and the test said "DID NOT
    RAISE". What ``rocoma-can`` itself does about an inherited SIG_IGN is the next test's."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_a_close_cut_short_by_ctrl_c_still_ends_a_writer_that_does_not_answer(
        tmp_path, ctrl_c_interrupts):
    """The close waits (CLOSE_WAIT) for a writer that is stopped; a Ctrl-C meanwhile goes on
    up (Runtime.close closes the other parts first), and the writer is ended on the way:
    it was left stopped for ever, its shared memory with it."""
    rec = Recorder(JointState.zeros(2), JointCommand.zeros(2), _Manager(), 100.0,
                   [BusToRecord("arm", "vcan0", False)], controllers=["pd"],
                   flight=str(tmp_path / "flight"))  # type: ignore[arg-type]
    writer = rec._process
    os.kill(writer.pid, signal.SIGSTOP)
    try:
        wait_for(lambda: stopped(writer.pid), "the writer stopped", DEMO_WAIT)
        impatient = threading.Timer(0.3, signal.pthread_kill,
                                    (threading.main_thread().ident, signal.SIGINT))
        impatient.start()
        with pytest.raises(KeyboardInterrupt):
            rec.close()
        impatient.join()
        wait_for(lambda: gone(writer.pid), "the writer ended", DEMO_WAIT)
        assert not [t for t in threading.enumerate() if t.name.startswith("recorder-")]
    finally:
        if writer.poll() is None:
            writer.kill()
            writer.wait(DEMO_WAIT)


@pytest.mark.parametrize(("second", "sigint_at_start"), [
    (signal.SIGTERM, signal.SIG_DFL), (signal.SIGINT, signal.SIG_DFL),
    (signal.SIGINT, signal.SIG_IGN)], ids=["SIGTERM", "SIGINT", "SIGINT-started-ignored"])
def test_a_second_stop_signal_while_run_closes_exits_130_and_leaves_no_writer(
        tmp_path, second, sigint_at_start):
    """`run --record` whose writer is stopped: the first SIGTERM stops the loop (torque-off,
    "stopped (signal SIGTERM)"), the close waits for the writer; a second stop signal then
    (an operator's `kill` again, an impatient Ctrl-C) ends the run as an interruption, exit
    130, no traceback, and the writer is not left behind (a SIGTERM killed the process
    outright, exit 143, and the stopped writer stayed for ever). So too when ``run`` was
    started with SIGINT ignored, as a script's background job is: the second Ctrl-C went
    unanswered and the close waited its 30 s (and this test, inheriting the suite's own
    start, failed only when the suite was started so)."""
    path = nobody_answers(tmp_path)
    out, err = tmp_path / "out.txt", tmp_path / "err.txt"
    with open(out, "w") as stdout, open(err, "w") as stderr:
        run = subprocess.Popen([sys.executable, "-m", "rocoma_can", "run", str(path),
                                "--record", str(tmp_path / "rec"), "--no-flight"],
                               stdout=stdout, stderr=stderr, cwd=tmp_path,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, sigint_at_start))
    writer = None
    try:
        wait_for(lambda: "recording every frame" in out.read_text(), "the run started",
                 within(10.0))
        writer = writer_of(run.pid)
        os.kill(writer, signal.SIGSTOP)
        wait_for(lambda: stopped(writer), "the writer stopped", DEMO_WAIT)
        run.send_signal(signal.SIGTERM)
        wait_for(lambda: "stopped (signal SIGTERM)" in out.read_text(), "the loop stopped",
                 DEMO_WAIT)
        time.sleep(0.2)  # into the close's wait for the writer
        run.send_signal(second)
        assert run.wait(DEMO_WAIT) == INTERRUPTED, err.read_text()
        assert untimed(err.read_text())[-1] == (
            f"rocoma-can: error: interrupted ({second.name}) while closing, after the "
            "torque-off"), err.read_text()
        wait_for(lambda: gone(writer), "the writer ended", DEMO_WAIT)
    finally:
        if run.poll() is None:
            run.kill()
            run.wait(DEMO_WAIT)
        if writer is not None and not gone(writer):
            os.kill(writer, signal.SIGKILL)



def test_a_ctrl_c_while_the_writer_starts_leaves_no_flight_record(tmp_path,
                                                                  ctrl_c_interrupts):
    """A Ctrl-C while the recorder waits for its writer to start (``run`` before bring-up:
    nothing ran): the writer is told to end, and ends without a record; its input's end
    read as the manager's death made a record "the manager's process ended without
    closing" of a run that never was."""
    main = threading.main_thread().ident
    stopped: list[int] = []

    def interrupt_once_started() -> None:
        """The writer held before it can say it is ready, the Ctrl-C, the writer let go."""
        def started() -> bool:
            try:
                return bool(writer_of(os.getpid()))
            except (AssertionError, OSError):  # not yet (or a child that just ended)
                return False
        wait_for(started, "the writer", DEMO_WAIT)
        writer = writer_of(os.getpid())
        os.kill(writer, signal.SIGSTOP)
        stopped.append(writer)
        signal.pthread_kill(main, signal.SIGINT)
        time.sleep(0.3)  # the recorder into its close of the start (which waits 5 s)
        os.kill(writer, signal.SIGCONT)
    helper = threading.Thread(target=interrupt_once_started)
    helper.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            Recorder(JointState.zeros(2), JointCommand.zeros(2), _Manager(), 100.0,
                     [BusToRecord("arm", "vcan0", False)], controllers=["pd"],
                     flight=str(tmp_path / "flight"))  # type: ignore[arg-type]
    finally:
        helper.join(DEMO_WAIT)
        for writer in stopped:
            if not gone(writer):
                os.kill(writer, signal.SIGCONT)
    assert stopped
    wait_for(lambda: gone(stopped[0]), "the writer ended", DEMO_WAIT)
    flight = tmp_path / "flight"
    assert not flight.exists() or not list(flight.glob("*.mcap")), list(flight.iterdir())


def test_a_writer_that_does_not_finish_is_said_once(tmp_path, monkeypatch, caplog):
    """A stopped writer the close gives up on: "did not finish within" is the one line for
    the flight recorder (its kill then also said "ended (exit code -9)": two errors for one
    loss), and the recording keeps that one reason."""
    from rocoma_can.record import recorder as recorder_module
    monkeypatch.setattr(recorder_module, "CLOSE_WAIT", 0.5)
    caplog.set_level("WARNING")
    rec = Recorder(JointState.zeros(2), JointCommand.zeros(2), _Manager(), 100.0,
                   [BusToRecord("arm", "vcan0", False)], controllers=["pd"],
                   flight=str(tmp_path / "flight"),
                   record=str(tmp_path / "rec"))  # type: ignore[arg-type]
    writer = rec._process
    os.kill(writer.pid, signal.SIGSTOP)
    try:
        rec.close()
    finally:
        if writer.poll() is None:
            writer.kill()
            writer.wait(DEMO_WAIT)
    assert rec.flight is not None and rec.recording is not None
    assert rec.flight.errors == ["the recording's writer process did not finish within "
                                 "0.5 s: no flight records from now on"]
    assert rec.recording.errors == ["the recording's writer process did not finish within "
                                    "0.5 s"]
    said = [r.getMessage() for r in caplog.records if r.name == recorder_module.__name__]
    assert len(said) == 2, said  # one for the recording, one for the flight recorder


def test_a_flight_directory_that_cannot_be_written_is_said_at_start(tmp_path, caplog):
    """The flight recorder's directory is tried at start: one line then, naming it and
    why, not at the first e-stop, whose record it then loses (the run said only where
    records would go)."""
    caplog.set_level("WARNING")
    (tmp_path / "file").write_text("not a directory")
    flight = tmp_path / "file" / "flight"
    rec = Recorder(JointState.zeros(2), JointCommand.zeros(2), _Manager(), 100.0,
                   [BusToRecord("arm", "vcan0", False)], controllers=["pd"],
                   flight=str(flight))  # type: ignore[arg-type]
    try:
        assert rec.flight is not None
        wait_for(lambda: rec.flight.errors, "the directory's problem said", DEMO_WAIT)
        [error] = rec.flight.errors
        assert error.startswith(f"{flight}: cannot write flight records: [Errno 20] Not a "
                                "directory"), error
        said = [r.getMessage() for r in caplog.records if "flight recorder" in r.getMessage()]
        assert said == [f"flight recorder: {error}"], said
    finally:
        rec.close()
    assert rec.flight.errors == [error]  # nothing more at the close: no e-stop


def test_a_recording_whose_directory_vanishes_is_said(tmp_path, caplog):
    """The --record directory deleted (or moved) mid-run: the writer wrote on into files
    nobody can open any more, without a word, and the run said the recording was whole.
    Now: the recording stops, said once with the path and why."""
    import shutil
    caplog.set_level("WARNING")
    record = tmp_path / "rec"
    rec = Recorder(JointState.zeros(2), JointCommand.zeros(2), _Manager(), 100.0,
                   [BusToRecord("arm", "vcan0", False)], controllers=["pd"],
                   record=str(record))  # type: ignore[arg-type]
    try:
        assert rec.recording is not None
        shutil.rmtree(record)
        wait_for(lambda: rec.recording.errors, "the vanished directory said", DEMO_WAIT)
    finally:
        rec.close()
    assert rec.recording.errors == [f"{record / 'trace.mcap'}: removed during the run (its "
                                    "directory deleted or moved?): the recording stops"]
    said = [r.getMessage() for r in caplog.records if "recording to" in r.getMessage()]
    assert len(said) == 1, said
